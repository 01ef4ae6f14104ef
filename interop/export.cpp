// Writing a take's cameras (and colour frames) as a COLMAP text model or a transforms.json.
#include <cstdio>

#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/image.h"
#include "core/take.h"
#include "interop/interop.h"

namespace holocap {
namespace {

std::string SetFileName(int64_t set_index) {
  char buffer[32];
  std::snprintf(buffer, sizeof(buffer), "%06lld.png", static_cast<long long>(set_index));
  return buffer;
}

}  // namespace

void ExportOptions::Check() const {
  HOLOCAP_CHECK_OPTION(format == InteropFormat::kColmap || format == InteropFormat::kNerf, format,
                       "export writes colmap or nerf");
}

ExportSummary ExportTake(const fs::path& take_dir, const fs::path& out_dir,
                         const ExportOptions& options, Report* report) {
  options.Check();
  Take take = Take::Open(take_dir);
  // Claimed first: a refused output costs nothing (the folder is made empty if it is new).
  const OutputDirectory claimed =
      OutputDirectory::Claim(out_dir, {"export", options.overwrite, {take_dir}});
  if (report != nullptr) report->SetFailureDestination(out_dir / "report.json");
  if (report != nullptr) {
    report->options() = {{"format", ToString(options.format)},
                         {"take", take_dir.string()},
                         {"ground_truth", options.ground_truth},
                         {"copy_images", options.copy_images}};
  }
  ExportSummary summary;
  // Cameras first: a model the format cannot hold stops the export before any file is written.
  std::vector<std::pair<const StreamInfo*, CameraModel>> cameras;
  std::vector<std::string> unrepresentable;
  for (const auto& stream : take.streams()) {
    if (stream.role != SensorRole::kColor) {
      summary.skipped.push_back(
          Cat(stream.name, " (", ToString(stream.role), ": the format holds colour cameras)"));
      continue;
    }
    CameraModel camera = take.Camera(stream.name, options.ground_truth);
    try {
      if (options.format == InteropFormat::kColmap) {
        ColmapFromCamera(camera, 1);
      } else {
        NerfFromCamera(camera);
      }
    } catch (const Error& e) {
      unrepresentable.push_back(Cat(stream.name, " (", e.what(), ")"));
      continue;
    }
    cameras.emplace_back(&stream, std::move(camera));
  }
  if (!unrepresentable.empty()) {
    if (!options.skip_unrepresentable) {
      std::string names;
      for (const auto& item : unrepresentable) {
        if (!names.empty()) names += "; ";
        names += item;
      }
      Fail(unrepresentable.size(), " camera(s) cannot be exported exactly to ",
           ToString(options.format), ": ", names, " (--skip-unrepresentable exports the others)");
    }
    summary.skipped.insert(summary.skipped.end(), unrepresentable.begin(), unrepresentable.end());
  }
  if (cameras.empty())
    Fail("take '", take_dir.string(), "' has no colour camera to export to ",
         ToString(options.format));

  // Every frame of every camera becomes one image named <sensor>/<set>.png.
  struct ExportedImage {
    size_t camera;
    int64_t set;
    std::string name;
  };
  std::vector<ExportedImage> images;
  for (size_t i = 0; i < take.size(); ++i) {
    for (size_t c = 0; c < cameras.size(); ++c) {
      const std::string& sensor = cameras[c].first->name;
      if (take.entry(i).Find(sensor) == nullptr) continue;
      images.push_back({c, take.entry(i).index, sensor + "/" + SetFileName(take.entry(i).index)});
      if (options.copy_images) {
        CreateDirectories(out_dir / "images" / sensor);
        WritePng(out_dir / "images" / images.back().name, take.ReadFrame(i, sensor));
      }
    }
  }

  if (options.format == InteropFormat::kColmap) {
    std::map<int64_t, ColmapCamera> colmap_cameras;
    for (size_t c = 0; c < cameras.size(); ++c) {
      colmap_cameras.emplace(c + 1,
                             ColmapFromCamera(cameras[c].second, static_cast<int64_t>(c + 1)));
    }
    std::vector<ColmapImage> colmap_images;
    for (const auto& image : images) {
      const Pose& cam_from_world = cameras[image.camera].second.cam_from_world();
      ColmapImage out;
      out.id = static_cast<int64_t>(colmap_images.size() + 1);
      out.cam_from_world_rotation = Eigen::Quaterniond(cam_from_world.linear()).normalized();
      out.cam_from_world_translation = cam_from_world.translation();
      out.camera_id = static_cast<int64_t>(image.camera + 1);
      out.name = image.name;
      colmap_images.push_back(out);
    }
    fs::path model = out_dir / "sparse" / "0";
    CreateDirectories(model);
    WriteFileAtomic(model / "cameras.txt", FormatColmapCameras(colmap_cameras));
    WriteFileAtomic(model / "images.txt", FormatColmapImages(colmap_images));
    WriteFileAtomic(model / "points3D.txt", FormatColmapPoints({}));
  } else {
    nlohmann::json json;
    json["camera_model"] = "OPENCV";
    json["frames"] = nlohmann::json::array();
    for (const auto& image : images) {
      const CameraModel& camera = cameras[image.camera].second;
      NerfIntrinsics intrinsics = NerfFromCamera(camera);
      nlohmann::json frame;
      frame["file_path"] = "images/" + image.name;
      Eigen::Matrix4d matrix = NerfWorldFromCamGl(camera.cam_from_world());
      for (int r = 0; r < 4; ++r) {
        frame["transform_matrix"].push_back(
            {matrix(r, 0), matrix(r, 1), matrix(r, 2), matrix(r, 3)});
      }
      frame["fl_x"] = *intrinsics.fl_x;
      frame["fl_y"] = *intrinsics.fl_y;
      frame["cx"] = *intrinsics.cx;
      frame["cy"] = *intrinsics.cy;
      frame["w"] = *intrinsics.w;
      frame["h"] = *intrinsics.h;
      for (const auto& [key, value] : intrinsics.distortion) frame[key] = value;
      json["frames"].push_back(frame);
    }
    // nlohmann writes doubles with 17 significant digits, so they read back bit for bit.
    WriteFileAtomic(out_dir / "transforms.json", json.dump(2) + "\n");
  }
  summary.cameras = static_cast<int>(cameras.size());
  summary.images = static_cast<int64_t>(images.size());
  std::string message = Cat("exported ", summary.cameras, " camera(s) and ", summary.images,
                            " image(s) as ", ToString(options.format));
  if (!summary.skipped.empty()) message += Cat("; ", summary.skipped.size(), " stream(s) skipped");
  summary.End(Termination::kSuccess, std::move(message));
  if (report != nullptr) {
    report->plan() = {
        {"cameras", summary.cameras}, {"images", summary.images}, {"skipped", summary.skipped}};
    report->SetSummary(summary);
  }
  return summary;
}

}  // namespace holocap
