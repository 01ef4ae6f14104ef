// A take as a splat scene: Neural Volumes' training data (the same views, held-out cameras,
// silhouettes and backgrounds), lenses undistorted to pinholes, and the seed from the frame's
// reconstruction.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <opencv2/imgproc.hpp>
#include <optional>

#include "avatar/camera_score.h"
#include "avatar/training_data.h"
#include "core/error.h"
#include "core/frame_tasks.h"
#include "core/fs.h"
#include "core/mesh.h"
#include "reconstruction/reconstruction.h"
#include "splat/splat.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;

std::string SetName(int64_t set) {
  char name[32];
  std::snprintf(name, sizeof(name), "%06lld", static_cast<long long>(set));
  return name;
}

// `selection` narrowed to its first frame set (a static scene; the seed of one frame), whether
// it names a range A:B or a list of frame sets.
TakeSelection FirstSetOnly(TakeSelection selection) {
  if (!selection.frame_list.empty()) {
    selection.frame_list.resize(1);
  } else {
    selection.last_frame = selection.first_frame + 1;
  }
  return selection;
}

// The first planned frame set's surface: recon_dir's, else reconstructed now by the plan's
// method from the training cameras (the held-out ones never). Empty when the reconstruction
// found none; `source` says what happened.
// `frames` of them from the first (a dynamic take's later frames seed where their surface is new).
std::vector<Mesh> SeedSurfaces(const fs::path& take_dir, const fs::path& model_dir,
                               const SplatOptions& options, const TrainingData& data, size_t frames,
                               const std::function<bool(size_t)>& needed, std::string* source) {
  std::vector<Mesh> meshes(frames);
  fs::path recon_dir = options.recon_dir;
  if (recon_dir.empty()) {
    recon_dir = model_dir / "seed_recon";
    TakeSelection selection = frames == 1 ? FirstSetOnly(options.take) : options.take;
    selection.heldout.clear();
    for (const auto& view : data.views)
      if (view.heldout) selection.heldout.push_back(view.name);
    ReconstructionOptions recon;
    // A seed needs points a few pixels apart, not the finest surface: 1/256 of the volume.
    recon.voxel_m = data.box.size().maxCoeff() / 256.0;
    recon.sweep_voxels_m.clear();
    recon.write_glb = false;
    recon.threads = options.threads;
    recon.method = ReconstructionMethodFromString(options.seed_method);
    const ReconstructionSummary summary = ReconstructTake(take_dir, selection, recon_dir, recon);
    *source = Cat("reconstructed now (", summary.plan.value("method", std::string("?")), ", voxel ",
                  recon.voxel_m * 1000, " mm): ", summary.message);
    if (!summary.IsUsable()) return meshes;
  } else {
    *source = Cat("reconstruction ", recon_dir.string());
  }
  for (size_t f = 0; f < frames; ++f) {
    if (!needed(f)) continue;
    const fs::path file = recon_dir / (SetName(data.sets[f]) + ".ply");
    if (!fs::exists(file)) {
      if (f == 0)
        *source += Cat("; no surface for frame set ", data.sets[f], " (", file.string(), ")");
      continue;
    }
    meshes[f] = ReadPly(file);
    if (f == 0)
      *source += Cat("; ", file.filename().string(), ": ", meshes[f].vertices.size(), " vertices");
  }
  return meshes;
}

// Points spread over the surface, each coloured by the mean of the training views that see it
// (in front of the surface's own depth there, inside the silhouette).
SplatSeed SeedFrom(const Mesh& mesh, const std::vector<SplatView>& views, int64_t count,
                   uint64_t seed) {
  SplatSeed out;
  if (mesh.faces.empty()) return out;
  const std::vector<Eigen::Vector3d> points = mesh.SampleSurface(count, seed);
  out.spacing_m = std::sqrt(mesh.SurfaceArea() / std::max<size_t>(1, points.size()));
  std::vector<Eigen::Vector3d> sum(points.size(), Eigen::Vector3d::Zero());
  std::vector<int> seen(points.size(), 0);
  for (const SplatView& view : views) {
    if (view.heldout) continue;
    const cv::Mat depth = RenderDepth(mesh, view.camera);
    for (size_t i = 0; i < points.size(); ++i) {
      const Eigen::Vector3d in_cam = view.camera.cam_from_world() * points[i];
      Eigen::Vector2d pixel;
      if (in_cam.z() <= 0 || !view.camera.Project(in_cam, &pixel) || !view.camera.InImage(pixel))
        continue;
      const int x = static_cast<int>(std::lround(pixel.x())),
                y = static_cast<int>(std::lround(pixel.y()));
      if (x < 0 || y < 0 || x >= view.image.cols || y >= view.image.rows) continue;
      const float surface = depth.at<float>(y, x);
      if (!std::isfinite(surface) || in_cam.z() > surface + 4 * out.spacing_m) continue;
      if (view.mask.at<uint8_t>(y, x) == 0) continue;
      const cv::Vec3b bgr = view.image.at<cv::Vec3b>(y, x);
      sum[i] += Eigen::Vector3d(bgr[0], bgr[1], bgr[2]) / 255.0;
      ++seen[i];
    }
  }
  int64_t unseen = 0;
  for (size_t i = 0; i < points.size(); ++i) {
    out.points.push_back(points[i].cast<float>());
    if (seen[i] == 0) ++unseen;
    out.colors.push_back(seen[i] > 0 ? Eigen::Vector3f((sum[i] / seen[i]).cast<float>())
                                     : Eigen::Vector3f::Constant(0.5f));
  }
  out.source = Cat(points.size(), " surface samples, ", unseen, " seen by no training camera");
  return out;
}

}  // namespace

SplatScene LoadSplatScene(const fs::path& take_dir, const fs::path& model_dir,
                          const SplatOptions& options, const SplatFramesNeeded& needed_frames) {
  options.Check();
  const double cpu_start = CpuSeconds();
  TrainingDataOptions data_options;
  data_options.image_width = options.image_width;
  data_options.heldout_cameras = options.heldout_cameras;
  data_options.heldout = options.heldout;
  data_options.take = options.take;
  data_options.threads = options.threads;
  data_options.scene = "static";
  if (options.scene == "static") data_options.take = FirstSetOnly(options.take);
  const TrainingData data = LoadTrainingData(take_dir, data_options);
  const bool dynamic = options.scene == "dynamic" || data.sets.size() > 1;
  SplatScene scene;
  scene.plan = data.plan;
  scene.plan.erase("encoder_views");
  scene.plan.erase("occupancy");
  scene.box = data.box;
  scene.alpha_masks = data.alpha_masks;
  std::vector<std::string> undistorted;
  scene.later_frames.resize(dynamic ? data.sets.size() - 1 : 0);
  const int64_t frames = 1 + static_cast<int64_t>(scene.later_frames.size());
  auto needed = [&](size_t frame) {
    return frame == 0 || !needed_frames || needed_frames(static_cast<int64_t>(frame), frames);
  };
  for (size_t f = 0; f < scene.later_frames.size(); ++f)
    scene.later_frames[f].set = data.sets[f + 1];
  for (size_t v = 0; v < data.views.size(); ++v) {
    SplatView view;
    view.name = data.views[v].name;
    view.camera = data.views[v].camera;
    view.image = data.images.front()[v];
    view.mask = data.masks.front()[v];
    view.background = data.views[v].background;
    view.heldout = data.views[v].heldout;
    std::optional<Undistortion> undistortion;
    if (view.camera.lensmodel() != "LENSMODEL_PINHOLE") {
      undistortion.emplace(view.camera);
      view.camera = undistortion->pinhole;
      view.image = undistortion->Color(view.image);
      view.mask = undistortion->Mask(view.mask);
      view.background = undistortion->Color(view.background);
      undistorted.push_back(view.name);
    }
    for (size_t f = 0; f < scene.later_frames.size(); ++f) {
      if (!needed(f + 1)) continue;
      const cv::Mat& image = data.images[f + 1][v];
      const cv::Mat& mask = data.masks[f + 1][v];
      scene.later_frames[f].images.push_back(undistortion ? undistortion->Color(image) : image);
      scene.later_frames[f].masks.push_back(undistortion ? undistortion->Mask(mask) : mask);
    }
    scene.views.push_back(std::move(view));
  }
  scene.plan["lenses"] =
      undistorted.empty() ? nlohmann::json("pinhole: trained on the images as they are")
                          : nlohmann::json(Cat(undistorted.size(),
                                               " distorting lens(es): images, silhouettes and "
                                               "backgrounds resampled to the pinhole of each "
                                               "lens's intrinsics core (held-out scored there)"));
  if (options.take.color_only) {
    scene.plan["seed_sensors"] = "colour cameras only (--no-depth)";
  } else if (scene.plan["left_out"].contains("depth sensors")) {
    scene.plan["left_out"]["depth sensors"] =
        "splats learn from colour alone (the seed's "
        "reconstruction may fuse their depth)";
  }
  scene.plan["frame_set"] = data.sets.front();
  scene.plan["scene"] = dynamic ? "dynamic" : "static";
  if (dynamic) {
    scene.plan["frames"] = data.sets.size();
    scene.plan["temporal"] =
        "frame 0 trained fully; each later frame from the one before, stored as a delta";
  } else {
    scene.plan["left_out"]["temporal"] =
        data.sets.size() > 1 || options.scene == "static"
            ? "a static scene (--scene static): one frame trained, no frame-to-frame deltas"
            : "one frame set: one frame trained, no frame-to-frame deltas";
  }
  std::string source;
  const std::vector<Mesh> meshes =
      SeedSurfaces(take_dir, model_dir, options, data, frames, needed, &source);
  scene.seed = SeedFrom(meshes.front(), scene.views, options.max_seed_points, options.seed);
  scene.seed.source = source + (scene.seed.source.empty() ? "" : "; " + scene.seed.source);
  for (size_t f = 0; f < scene.later_frames.size(); ++f) {
    if (!needed(f + 1)) continue;
    std::vector<SplatView> views = scene.views;
    for (size_t v = 0; v < views.size(); ++v) {
      views[v].image = scene.later_frames[f].images[v];
      views[v].mask = scene.later_frames[f].masks[v];
    }
    scene.later_frames[f].seed =
        SeedFrom(meshes[f + 1], views, options.max_seed_points, options.seed + f + 1);
  }
  scene.load_cpu_s = CpuSeconds() - cpu_start;
  return scene;
}

}  // namespace holocap
