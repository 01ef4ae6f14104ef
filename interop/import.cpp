// Reading foreign sources into ImportedRig, and writing an ImportedRig as a take.
#include <algorithm>
#include <cctype>
#include <cmath>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <set>

#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/image.h"
#include "core/take.h"
#include "interop/internal/import_frames.h"
#include "interop/interop.h"

namespace holocap {

namespace interop_internal {

std::string LowerExtension(const fs::path& file) {
  std::string ext = file.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(),
                 [](unsigned char c) { return std::tolower(c); });
  return ext;
}

bool IsImageFile(const fs::path& file) {
  static const std::set<std::string> known = {".png", ".jpg",  ".jpeg", ".bmp",
                                              ".tif", ".tiff", ".ppm",  ".pgm"};
  return known.count(LowerExtension(file)) > 0;
}

std::vector<fs::path> ImageFilesIn(const fs::path& folder) {
  std::vector<fs::path> files;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(folder, ec)) {
    if (entry.is_regular_file() && IsImageFile(entry.path())) files.push_back(entry.path());
  }
  std::sort(files.begin(), files.end());
  return files;
}

std::optional<int64_t> TrailingNumber(const fs::path& file) {
  std::string stem = file.stem().string();
  size_t start = stem.size();
  while (start > 0 && std::isdigit(static_cast<unsigned char>(stem[start - 1]))) --start;
  if (start == stem.size() || stem.size() - start > 18) return std::nullopt;
  return std::stoll(stem.substr(start));
}

namespace {

// Whether JPEG bytes end their last scan with the end-of-image marker. Entropy-coded data
// never holds 0xFF 0xD9 (a 0xFF there is followed by 0x00 or a restart marker), and libjpeg
// completes a cut scan with grey, warning only: this is how a truncated photograph is told.
bool JpegIsComplete(const std::string& bytes) {
  size_t last_scan = std::string::npos;
  for (size_t at = 0; at + 1 < bytes.size(); ++at) {
    if (static_cast<unsigned char>(bytes[at]) == 0xFF &&
        static_cast<unsigned char>(bytes[at + 1]) == 0xDA)
      last_scan = at;
  }
  if (last_scan == std::string::npos) return false;
  for (size_t at = last_scan + 2; at + 1 < bytes.size(); ++at) {
    if (static_cast<unsigned char>(bytes[at]) == 0xFF &&
        static_cast<unsigned char>(bytes[at + 1]) == 0xD9)
      return true;
  }
  return false;
}

}  // namespace

cv::Mat ReadSourceImage(const fs::path& file) {
  if (!fs::is_regular_file(file)) Fail("image '", file.string(), "' does not exist");
  const std::string bytes = ReadFileToString(file);
  const std::string ext = LowerExtension(file);
  if (ext == ".png") return DecodePng(bytes, file.string());
  if ((ext == ".jpg" || ext == ".jpeg") && !JpegIsComplete(bytes))
    Fail("image '", file.string(), "' is truncated (its JPEG data has no end after its last scan)");
  cv::Mat image = DecodeImageBytes(bytes);
  if (image.empty()) Fail("image '", file.string(), "' cannot be decoded");
  return image;
}

std::string SanitizedName(const std::string& text) {
  std::string name;
  for (unsigned char c : text)
    name += (std::isalnum(c) || c == '_' || c == '-' || c == '.') ? c : '_';
  if (name.empty()) name = "cam";
  return name;
}

PixelFormat PixelFormatOf(const cv::Mat& image, const std::string& origin) {
  switch (image.type()) {
    case CV_8UC1:
      return {"mono8"};
    case CV_8UC3:
      return {"bgr8"};
    case CV_8UC4:
      return {"bgra8"};
    case CV_16UC1:
      return {"mono16"};
    case CV_16UC3:
      return {"bgr16"};
    case CV_16UC4:
      return {"bgr16", true};
  }
  Fail("image '", origin, "' has ", image.channels(), " channel(s) of depth ", image.depth(),
       "; takes hold 8/16-bit mono or colour");
}

void AlphaCounts::AddNotes(std::vector<std::string>* notes) const {
  if (kept > 0) {
    notes->push_back(Cat("alpha kept in ", kept,
                         " image(s) (bgra8: the silhouettes the reconstruction uses "
                         "first)"));
  }
  if (dropped > 0) {
    notes->push_back(Cat("alpha channel of ", dropped,
                         " 16-bit image(s) dropped (takes hold alpha at 8 bits; colour kept "
                         "exactly)"));
  }
}

cv::Mat ConformedFrame(cv::Mat image, const StreamInfo& stream, const std::string& origin,
                       const std::string& expected, AlphaCounts* alpha) {
  if (image.cols != stream.width || image.rows != stream.height) {
    Fail("image '", origin, "' is ", image.cols, "x", image.rows, " but camera '", stream.name,
         "' ", expected, " ", stream.width, "x", stream.height);
  }
  const PixelFormat format = PixelFormatOf(image, origin);
  if (format.name != stream.pixel_format) {
    Fail("image '", origin, "' is ", format.name, " but the earlier images of '", stream.name,
         "' are ", stream.pixel_format);
  }
  if (format.drops_alpha) {
    cv::cvtColor(image, image, cv::COLOR_BGRA2BGR);
    ++alpha->dropped;
  } else if (image.channels() == 4) {
    ++alpha->kept;
  }
  return image;
}

void AddImportedStream(const std::string& sensor, const std::string& format, int width, int height,
                       const std::string& pixel_format, const std::string& clock,
                       RigDescription* rig, std::vector<StreamInfo>* streams) {
  SensorSpec spec;
  spec.name = sensor;
  spec.uri = Cat("import:", format, "#", sensor);
  rig->sensors.push_back(spec);
  StreamInfo stream;
  stream.name = sensor;
  stream.uri = spec.uri;
  stream.width = width;
  stream.height = height;
  stream.pixel_format = pixel_format;
  stream.codec = ImageCodec::kPng;
  stream.clock = clock;
  streams->push_back(stream);
}

TakeWriterOptions ImportWriterOptions(int png_compression, bool overwrite,
                                      std::vector<fs::path> inputs) {
  TakeWriterOptions options;
  options.png_compression = png_compression;
  options.overwrite = overwrite;
  options.command = "import";
  options.inputs = std::move(inputs);
  return options;
}

}  // namespace interop_internal

namespace {

using interop_internal::IsImageFile;
using interop_internal::PixelFormatOf;
using interop_internal::ReadSourceImage;
using interop_internal::SanitizedName;
using interop_internal::TrailingNumber;

// One camera as a source describes it, before sensor names are chosen.
struct SourceView {
  std::string source_name;
  CameraModel camera;
  std::map<int64_t, fs::path> frames;
};

// The images of one camera's folder, keyed by the number in their names (by name order when
// the names carry no distinct numbers).
std::map<int64_t, fs::path> NumberedImages(const fs::path& folder) {
  const std::vector<fs::path> files = interop_internal::ImageFilesIn(folder);
  std::map<int64_t, fs::path> frames;
  bool numbered = true;
  for (const auto& file : files) {
    auto number = TrailingNumber(file);
    if (!number || !frames.emplace(*number, file).second) {
      numbered = false;
      break;
    }
  }
  if (!numbered) {
    frames.clear();
    for (size_t i = 0; i < files.size(); ++i) frames.emplace(static_cast<int64_t>(i), files[i]);
  }
  return frames;
}

cv::Size ImageSize(const fs::path& file) { return ReadSourceImage(file).size(); }

// Sensor names: each camera's image folder when every camera has its own, else each camera's
// first image stem (or its source name), made unique.
std::vector<std::string> ChooseSensorNames(const std::vector<SourceView>& views) {
  std::vector<std::string> names;
  std::set<std::string> folders;
  bool by_folder = true;
  for (const auto& view : views) {
    std::set<fs::path> parents;
    for (const auto& [number, file] : view.frames) parents.insert(file.parent_path());
    if (parents.size() != 1 || !folders.insert(parents.begin()->filename().string()).second)
      by_folder = false;
  }
  std::set<std::string> taken;
  for (const auto& view : views) {
    std::string base;
    if (by_folder && !view.frames.empty()) {
      base = view.frames.begin()->second.parent_path().filename().string();
    } else if (!view.frames.empty() && view.frames.size() == 1) {
      base = view.frames.begin()->second.stem().string();
    } else {
      base = fs::path(view.source_name).stem().string();
    }
    base = SanitizedName(base);
    std::string name = base;
    for (int suffix = 2; !taken.insert(name).second; ++suffix)
      name = base + "_" + std::to_string(suffix);
    names.push_back(name);
  }
  return names;
}

fs::path SingleFileIn(const fs::path& dir, const std::string& prefix, const std::string& suffix,
                      const std::string& what) {
  std::vector<fs::path> found;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(dir, ec)) {
    std::string name = entry.path().filename().string();
    if (entry.is_regular_file() && name.size() >= prefix.size() + suffix.size() &&
        name.compare(0, prefix.size(), prefix) == 0 &&
        name.compare(name.size() - suffix.size(), suffix.size(), suffix) == 0) {
      found.push_back(entry.path());
    }
  }
  if (found.size() != 1) {
    Fail("'", dir.string(), "' holds ", found.size(), " ", what, " files (", prefix, "*", suffix,
         "); name the one to import");
  }
  return found[0];
}

fs::path ResolveFile(const fs::path& source, const std::string& prefix, const std::string& suffix,
                     const std::string& what) {
  if (fs::is_directory(source)) return SingleFileIn(source, prefix, suffix, what);
  if (!fs::is_regular_file(source)) Fail("'", source.string(), "' does not exist");
  return source;
}

// The first of a format's known file names that a folder holds (the file itself when a file is
// given). `chosen` says which name was taken from a folder.
fs::path ResolveKnownName(const fs::path& source, const std::vector<std::string>& names,
                          const std::string& what, std::string* chosen) {
  if (!fs::is_directory(source)) {
    if (!fs::is_regular_file(source)) Fail("'", source.string(), "' does not exist");
    return source;
  }
  for (const auto& name : names) {
    if (fs::is_regular_file(source / name)) {
      *chosen = name;
      return source / name;
    }
  }
  std::string listed;
  for (const auto& name : names) listed += (listed.empty() ? "" : ", ") + name;
  Fail("'", source.string(), "' holds no ", what, " (looked for ", listed,
       "); name the file to import");
}

fs::path ImageRoot(const ImportOptions& options, const fs::path& fallback) {
  return options.images.empty() ? fallback : options.images;
}

std::vector<double> RowMajor(const Eigen::Matrix3d& matrix) {
  return {matrix(0, 0), matrix(0, 1), matrix(0, 2), matrix(1, 0), matrix(1, 1),
          matrix(1, 2), matrix(2, 0), matrix(2, 1), matrix(2, 2)};
}

std::string RotationWhere(const KrtCamera& camera) {
  return Cat(camera.rotation_origin.empty() ? std::string("?") : camera.rotation_origin,
             ": camera '", camera.name, "'");
}

// K[R|t] cameras (Middlebury, Neural Volumes, Panoptic) into mrcal models. The rotations'
// shared non-orthonormal part, if any, becomes the world map (see interop.h).
std::vector<CameraModel> KrtCamerasToModels(const std::vector<KrtCamera>& cameras,
                                            double metres_per_unit, const ImportOptions& options,
                                            ImportedRig* rig) {
  std::vector<Eigen::Matrix3d> rotations;
  for (const auto& camera : cameras) {
    CheckRotation(camera.R, RotationWhere(camera));
    rotations.push_back(camera.R);
  }
  RigidWorld world = SplitRigidWorld(rotations);
  rig->metrics["rotation_non_orthonormality"] = world.non_orthonormality;
  rig->metrics["rotation_residual"] = world.residual;
  if (world.residual > options.max_rotation_residual) {
    Fail("the cameras' rotations are non-orthonormal in different ways (max |S_i - S| = ",
         world.residual, " > ", options.max_rotation_residual,
         "), so their K[R|t] cannot all be represented exactly; "
         "allow the nearest rotations with --max-rotation-residual ",
         world.residual);
  }
  if (world.world_from_source != Eigen::Matrix3d::Identity()) {
    rig->notes.push_back(Cat("the rotations share a non-orthonormal part S (max |R^T R - I| = ",
                             world.non_orthonormality,
                             "); the take's world is S times the source's"));
  }
  rig->world_from_source = metres_per_unit * world.world_from_source;
  const Eigen::Matrix3d source_from_world = world.world_from_source.inverse();
  for (size_t i = 0; i < cameras.size(); ++i) {
    CheckedRotation rotation =
        CheckRotation(cameras[i].R * source_from_world, RotationWhere(cameras[i]));
    world.rotations[i] = rotation.rotation;
    if (rotation.reorthonormalised()) {
      rig->notes.push_back(Cat("camera ", cameras[i].name,
                               ": rotation re-orthonormalised (residual ", rotation.residual, ")"));
    }
  }
  std::vector<CameraModel> models;
  for (size_t i = 0; i < cameras.size(); ++i) {
    Pose cam_from_world = Pose::Identity();
    cam_from_world.linear() = world.rotations[i];
    cam_from_world.translation() = metres_per_unit * cameras[i].t;
    models.push_back(CameraFromKrt(cameras[i], cam_from_world));
  }
  return models;
}

void ReadMiddlebury(const fs::path& source, const ImportOptions& options, ImportedRig* rig,
                    std::vector<SourceView>* views) {
  fs::path file = ResolveFile(source, "", "_par.txt", "Middlebury camera-parameter");
  std::vector<KrtCamera> cameras = ParseMiddleburyPar(ReadFileToString(file), file.string());
  fs::path root = ImageRoot(options, file.parent_path());
  for (auto& camera : cameras) {
    cv::Size size = ImageSize(root / camera.name);
    camera.width = size.width;
    camera.height = size.height;
  }
  std::vector<CameraModel> models = KrtCamerasToModels(
      cameras, options.metres_per_unit > 0 ? options.metres_per_unit : 1, options, rig);
  for (size_t i = 0; i < cameras.size(); ++i) {
    views->push_back({cameras[i].name, models[i], {{0, root / cameras[i].name}}});
  }
}

// Cameras of a calibration that lists more cameras than were recorded keep only those with an
// image folder.
void KeepRecorded(std::vector<KrtCamera>* cameras,
                  const std::vector<std::vector<fs::path>>& folder_candidates,
                  std::vector<std::map<int64_t, fs::path>>* frames, ImportedRig* rig,
                  const std::string& where) {
  std::vector<KrtCamera> kept;
  std::vector<std::string> skipped;
  for (size_t i = 0; i < cameras->size(); ++i) {
    std::map<int64_t, fs::path> found;
    for (const auto& folder : folder_candidates[i]) {
      if (fs::is_directory(folder)) {
        found = NumberedImages(folder);
        if (!found.empty()) break;
      }
    }
    if (found.empty()) {
      skipped.push_back((*cameras)[i].name);
      continue;
    }
    kept.push_back((*cameras)[i]);
    frames->push_back(std::move(found));
  }
  if (kept.empty())
    Fail("none of the ", cameras->size(), " cameras has an image folder under ", where);
  if (!skipped.empty()) {
    rig->notes.push_back(
        Cat(skipped.size(), " camera(s) without images skipped (first: ", skipped.front(), ")"));
  }
  rig->metrics["cameras_skipped_without_images"] = skipped.size();
  *cameras = std::move(kept);
}

void ReadKrtCameras(std::vector<KrtCamera> cameras, std::vector<std::map<int64_t, fs::path>> frames,
                    double metres_per_unit, const ImportOptions& options, ImportedRig* rig,
                    std::vector<SourceView>* views) {
  for (size_t i = 0; i < cameras.size(); ++i) {
    cv::Size size = ImageSize(frames[i].begin()->second);
    if (cameras[i].width > 0 &&
        (cameras[i].width != size.width || cameras[i].height != size.height)) {
      Fail("camera '", cameras[i].name, "' is calibrated for ", cameras[i].width, "x",
           cameras[i].height, " but its images are ", size.width, "x", size.height);
    }
    cameras[i].width = size.width;
    cameras[i].height = size.height;
  }
  std::vector<CameraModel> models = KrtCamerasToModels(cameras, metres_per_unit, options, rig);
  for (size_t i = 0; i < cameras.size(); ++i)
    views->push_back({cameras[i].name, models[i], std::move(frames[i])});
}

void ReadNeuralVolumes(const fs::path& source, const ImportOptions& options, ImportedRig* rig,
                       std::vector<SourceView>* views) {
  fs::path file = fs::is_directory(source) ? source / "KRT" : source;
  if (!fs::is_regular_file(file))
    Fail("'", file.string(), "' does not exist (a Neural Volumes KRT file)");
  std::vector<KrtCamera> cameras = ParseNeuralVolumesKrt(ReadFileToString(file), file.string());
  fs::path root = ImageRoot(options, file.parent_path());
  std::vector<std::vector<fs::path>> candidates;
  candidates.reserve(cameras.size());
  for (const auto& camera : cameras)
    candidates.push_back({root / ("cam" + camera.name), root / camera.name});
  std::vector<std::map<int64_t, fs::path>> frames;
  KeepRecorded(&cameras, candidates, &frames, rig, root.string());
  ReadKrtCameras(std::move(cameras), std::move(frames),
                 options.metres_per_unit > 0 ? options.metres_per_unit : 1, options, rig, views);
}

void ReadPanoptic(const fs::path& source, const ImportOptions& options, ImportedRig* rig,
                  std::vector<SourceView>* views) {
  // A Panoptic sequence folder holds calibration_<sequence>.json; some copies name it
  // camera_parameters.json.
  fs::path file = source;
  if (fs::is_directory(source) && fs::is_regular_file(source / "camera_parameters.json")) {
    bool sequence_file = false;
    for (const auto& entry : fs::directory_iterator(source)) {
      const std::string name = entry.path().filename().string();
      if (name.rfind("calibration_", 0) == 0 && entry.path().extension() == ".json")
        sequence_file = true;
    }
    if (sequence_file) {
      Fail("'", source.string(), "' holds both camera_parameters.json and a calibration_*.json; ",
           "name the one to import");
    }
    file = source / "camera_parameters.json";
  } else {
    file = ResolveFile(source, "calibration_", ".json", "Panoptic calibration");
  }
  std::vector<KrtCamera> cameras = ParsePanopticCalibration(ReadFileToString(file), file.string());
  fs::path root = ImageRoot(options, file.parent_path());
  std::vector<std::vector<fs::path>> candidates;
  candidates.reserve(cameras.size());
  for (const auto& camera : cameras) {
    candidates.push_back({root / "hdImgs" / camera.name, root / "vgaImgs" / camera.name,
                          root / "kinectImgs" / camera.name, root / camera.name});
  }
  std::vector<std::map<int64_t, fs::path>> frames;
  KeepRecorded(&cameras, candidates, &frames, rig, root.string());
  // Panoptic's calibration is in centimetres.
  ReadKrtCameras(std::move(cameras), std::move(frames),
                 options.metres_per_unit > 0 ? options.metres_per_unit : 0.01, options, rig, views);
}

void ReadMrcalFolders(const fs::path& source, const ImportOptions& options, ImportedRig* rig,
                      std::vector<SourceView>* views) {
  if (!fs::is_directory(source))
    Fail("'", source.string(), "' is not a directory of .cameramodel files");
  std::vector<fs::path> models;
  for (const auto& entry : fs::directory_iterator(source)) {
    if (entry.is_regular_file() && entry.path().extension() == ".cameramodel")
      models.push_back(entry.path());
  }
  std::sort(models.begin(), models.end());
  if (models.empty()) Fail("'", source.string(), "' holds no .cameramodel files");
  fs::path root = ImageRoot(options, source);
  const double scale = options.metres_per_unit > 0 ? options.metres_per_unit : 1;
  std::vector<std::string> skipped;
  for (const auto& file : models) {
    std::string name = file.stem().string();
    std::map<int64_t, fs::path> frames =
        fs::is_directory(root / name) ? NumberedImages(root / name) : std::map<int64_t, fs::path>{};
    if (frames.empty()) {
      skipped.push_back(name);
      continue;
    }
    CameraModel camera = CameraModel::Read(file);
    Pose pose = camera.cam_from_world();
    pose.translation() *= scale;
    camera.set_cam_from_world(pose);
    views->push_back({name, camera, std::move(frames)});
  }
  if (views->empty())
    Fail("no .cameramodel in '", source.string(), "' has an image folder of its name under ",
         root.string());
  if (!skipped.empty())
    rig->notes.push_back(Cat(skipped.size(), " model(s) without an image folder skipped (first: ",
                             skipped.front(), ")"));
  rig->world_from_source = scale * Eigen::Matrix3d::Identity();
}

// Views with identical camera models are one camera filmed several times. When every camera
// has one image they all form frame set 0; otherwise a camera's images are numbered as
// NumberedImages does, so numbered files of different cameras line up.
void GroupViews(const std::vector<std::pair<std::string, SourceView>>& items,
                std::vector<SourceView>* views) {
  std::map<std::string, size_t> group_of;
  std::vector<std::vector<fs::path>> files;
  const size_t first = views->size();
  for (const auto& [key, view] : items) {
    auto [it, inserted] = group_of.emplace(key, views->size());
    if (inserted) {
      views->push_back(view);
      files.emplace_back();
    }
    files[it->second - first].push_back(view.frames.begin()->second);
  }
  bool single = true;
  for (const auto& group : files) single = single && group.size() == 1;
  for (size_t g = 0; g < files.size(); ++g) {
    std::map<int64_t, fs::path>& frames = (*views)[first + g].frames;
    frames.clear();
    bool numbered = !single;
    for (const auto& file : files[g]) {
      auto number = TrailingNumber(file);
      if (numbered && (!number || !frames.emplace(*number, file).second)) numbered = false;
    }
    if (!numbered) {
      frames.clear();
      for (size_t i = 0; i < files[g].size(); ++i)
        frames.emplace(static_cast<int64_t>(i), files[g][i]);
    }
  }
}

std::string ModelKey(const CameraModel& camera) { return camera.ToString(); }

fs::path FindColmapModel(const fs::path& source) {
  for (const fs::path& dir : {source, source / "sparse" / "0", source / "sparse"}) {
    if (fs::is_regular_file(dir / "cameras.txt")) return dir;
  }
  if (fs::is_regular_file(source / "sparse" / "0" / "cameras.bin") ||
      fs::is_regular_file(source / "cameras.bin")) {
    Fail("'", source.string(),
         "' holds a binary COLMAP model; convert it with "
         "'colmap model_converter --output_type TXT' first");
  }
  Fail("no COLMAP text model (cameras.txt) in '", source.string(), "', its sparse/0 or sparse");
}

void ReadColmap(const fs::path& source, const ImportOptions& options, ImportedRig* rig,
                std::vector<SourceView>* views) {
  fs::path model_dir = FindColmapModel(source);
  for (const char* name : {"images.txt", "points3D.txt"}) {
    if (!fs::is_regular_file(model_dir / name))
      Fail("'", (model_dir / name).string(), "' is missing");
  }
  ColmapModel model;
  model.cameras = ParseColmapCameras(ReadFileToString(model_dir / "cameras.txt"),
                                     (model_dir / "cameras.txt").string());
  model.images = ParseColmapImages(ReadFileToString(model_dir / "images.txt"),
                                   (model_dir / "images.txt").string());
  model.points = ParseColmapPoints(ReadFileToString(model_dir / "points3D.txt"),
                                   (model_dir / "points3D.txt").string());
  if (model.images.empty()) Fail("'", (model_dir / "images.txt").string(), "' lists no images");
  fs::path root;
  if (!options.images.empty()) {
    root = options.images;
  } else {
    for (const fs::path& candidate : {source / "images", model_dir / ".." / ".." / "images",
                                      model_dir / "images", model_dir / ".."}) {
      if (fs::is_regular_file(candidate / model.images.front().name)) {
        root = candidate.lexically_normal();
        break;
      }
    }
    if (root.empty()) {
      Fail("cannot find image '", model.images.front().name, "' under ",
           (source / "images").string(),
           " or beside the model; name the image folder with --images");
    }
  }
  const double scale = options.metres_per_unit > 0 ? options.metres_per_unit : 1;
  std::map<int64_t, CameraModel> by_image;
  std::vector<std::pair<std::string, SourceView>> items;
  std::vector<ColmapImage> sorted = model.images;
  std::sort(sorted.begin(), sorted.end(),
            [](const ColmapImage& a, const ColmapImage& b) { return a.name < b.name; });
  for (const auto& image : sorted) {
    auto camera = model.cameras.find(image.camera_id);
    if (camera == model.cameras.end())
      Fail("image ", image.id, " (", image.name, ") names camera ", image.camera_id,
           ", which cameras.txt lacks");
    Pose cam_from_world = Pose::Identity();
    cam_from_world.linear() = image.cam_from_world_rotation.toRotationMatrix();
    cam_from_world.translation() = scale * image.cam_from_world_translation;
    CameraModel converted = CameraFromColmap(camera->second, cam_from_world);
    by_image.emplace(image.id, converted);
    items.push_back(
        {ModelKey(converted), SourceView{image.name, converted, {{0, root / image.name}}}});
  }
  GroupViews(items, views);
  rig->world_from_source = scale * Eigen::Matrix3d::Identity();

  // The points' reprojection error through the imported cameras, next to the file's own.
  std::map<int64_t, const ColmapImage*> image_by_id;
  for (const auto& image : model.images) image_by_id[image.id] = &image;
  double sum_error = 0, sum_file_error = 0, max_difference = 0;
  int64_t observations = 0, unprojectable = 0;
  for (const auto& point : model.points) {
    double point_sum = 0;
    int64_t point_count = 0;
    for (const auto& [image_id, index] : point.track) {
      auto image = image_by_id.find(image_id);
      if (image == image_by_id.end() || index < 0 ||
          index >= static_cast<int64_t>(image->second->points2d.size())) {
        Fail("point ", point.id, " names observation (", image_id, ", ", index,
             "), which images.txt lacks");
      }
      Eigen::Vector2d pixel;
      if (!by_image.at(image_id).ProjectWorld(scale * point.xyz, &pixel)) {
        ++unprojectable;
        continue;
      }
      Eigen::Vector2d observed = image->second->points2d[index] - Eigen::Vector2d::Constant(0.5);
      point_sum += (pixel - observed).norm();
      ++point_count;
    }
    observations += point_count;
    if (point_count == 0) continue;
    double mean = point_sum / point_count;
    sum_error += mean;
    sum_file_error += point.error;
    max_difference = std::max(max_difference, std::abs(mean - point.error));
  }
  nlohmann::json& points = rig->metrics["colmap_points"];
  points["count"] = model.points.size();
  points["observations"] = observations;
  points["observations_behind_camera"] = unprojectable;
  if (!model.points.empty()) {
    points["mean_reprojection_error_px"] = sum_error / model.points.size();
    points["file_mean_reprojection_error_px"] = sum_file_error / model.points.size();
    points["max_per_point_difference_px"] = max_difference;
  }
}

void ReadNerf(const fs::path& source, const ImportOptions& options, ImportedRig* rig,
              std::vector<SourceView>* views) {
  // A folder's transforms.json, else its training split (NeRF-synthetic's layout): the test
  // split is the dataset's held-out set and is imported only when named.
  std::string chosen;
  fs::path file = ResolveKnownName(source, {"transforms.json", "transforms_train.json"},
                                   "NeRF transforms file", &chosen);
  if (chosen == "transforms_train.json") {
    std::string others;
    for (const char* split : {"transforms_val.json", "transforms_test.json"}) {
      if (fs::is_regular_file(source / split)) others += Cat(others.empty() ? "" : ", ", split);
    }
    rig->notes.push_back(Cat("read the training split (transforms_train.json)",
                             others.empty() ? std::string()
                                            : Cat(" without ", others,
                                                  " (the dataset's own held-out views: import "
                                                  "them by naming the file)")));
  }
  std::vector<NerfFrame> frames = ParseNerfTransforms(ReadFileToString(file), file.string());
  fs::path root = ImageRoot(options, file.parent_path());
  const double scale = options.metres_per_unit > 0 ? options.metres_per_unit : 1;
  std::vector<std::pair<std::string, SourceView>> items;
  for (size_t i = 0; i < frames.size(); ++i) {
    fs::path image = (root / frames[i].file_path).lexically_normal();
    // Blender's synthetic sets name frames without their ".png".
    if (!fs::is_regular_file(image) && !image.has_extension()) {
      for (const char* ext : {".png", ".jpg", ".jpeg"}) {
        if (fs::is_regular_file(image.string() + ext)) {
          image = image.string() + ext;
          break;
        }
      }
    }
    cv::Size size = ImageSize(image);
    Eigen::Matrix4d world_from_cam = frames[i].world_from_cam_gl;
    world_from_cam.topRightCorner<3, 1>() *= scale;
    CameraModel camera = CameraFromNerf(frames[i].intrinsics, world_from_cam, size.width,
                                        size.height, Cat(file.string(), ": frames[", i, "]"));
    items.push_back({ModelKey(camera), SourceView{frames[i].file_path, camera, {{0, image}}}});
  }
  GroupViews(items, views);
  rig->world_from_source = scale * Eigen::Matrix3d::Identity();
}

}  // namespace

void ImportOptions::Check() const {
  HOLOCAP_CHECK_OPTION_GE(metres_per_unit, 0, "0: the format's unit");
  HOLOCAP_CHECK_OPTION(std::isfinite(metres_per_unit), metres_per_unit);
  HOLOCAP_CHECK_OPTION_GE(max_rotation_residual, 0);
  HOLOCAP_CHECK_OPTION_GT(fps, 0);
  HOLOCAP_CHECK_OPTION_LE(fps, 10000);
  HOLOCAP_CHECK_OPTION_IN(png_compression, 0, 9);
}

ImportedRig ReadForeignRig(const fs::path& source, const ImportOptions& options) {
  options.Check();
  if (!fs::exists(source)) Fail("'", source.string(), "' does not exist");
  ImportedRig rig;
  rig.format = options.format;
  rig.source = fs::absolute(source).lexically_normal();
  std::vector<SourceView> views;
  switch (options.format) {
    case InteropFormat::kMiddlebury:
      ReadMiddlebury(source, options, &rig, &views);
      break;
    case InteropFormat::kKrt:
      ReadNeuralVolumes(source, options, &rig, &views);
      break;
    case InteropFormat::kColmap:
      ReadColmap(source, options, &rig, &views);
      break;
    case InteropFormat::kNerf:
      ReadNerf(source, options, &rig, &views);
      break;
    case InteropFormat::kPanoptic:
      ReadPanoptic(source, options, &rig, &views);
      break;
    case InteropFormat::kMrcal:
      ReadMrcalFolders(source, options, &rig, &views);
      break;
  }
  std::vector<std::string> names = ChooseSensorNames(views);
  for (size_t i = 0; i < views.size(); ++i) {
    rig.views.push_back({names[i], views[i].source_name, views[i].camera, views[i].frames});
  }
  return rig;
}

ImportSummary ImportTake(const fs::path& source, const fs::path& take_dir,
                         const ImportOptions& options, Report* report) {
  ImportedRig rig = ReadForeignRig(source, options);
  if (report != nullptr) {
    report->options() = {{"format", ToString(options.format)},
                         {"source", rig.source.string()},
                         {"images", options.images.string()},
                         {"metres_per_unit", options.metres_per_unit},
                         {"max_rotation_residual", options.max_rotation_residual},
                         {"fps", options.fps},
                         {"png_compression", options.png_compression},
                         {"overwrite", options.overwrite}};
  }
  // Frame sets: the union of the cameras' frame numbers, in order.
  std::set<int64_t> numbers;
  for (const auto& view : rig.views) {
    for (const auto& [number, file] : view.frames) numbers.insert(number);
  }
  // Each stream's pixel format is its first image's.
  RigDescription description;
  description.name = SanitizedName(rig.source.stem().string());
  description.fps = options.fps;
  std::vector<StreamInfo> streams;
  interop_internal::AlphaCounts alpha;
  for (const auto& view : rig.views) {
    const fs::path& first = view.frames.begin()->second;
    interop_internal::AddImportedStream(view.sensor, ToString(rig.format), view.camera.width(),
                                        view.camera.height(),
                                        PixelFormatOf(ReadSourceImage(first), first.string()).name,
                                        "none (imported: set index / fps)", &description, &streams);
  }
  description.Check();
  nlohmann::json metadata;
  nlohmann::json& interop = metadata["interop"];
  interop["format"] = ToString(rig.format);
  interop["source"] = rig.source.string();
  interop["world_from_source"] = RowMajor(rig.world_from_source);
  for (const auto& view : rig.views) interop["source_names"][view.sensor] = view.source_name;
  interop["notes"] = rig.notes;
  std::vector<fs::path> inputs = {source, rig.source};
  if (!options.images.empty()) inputs.push_back(options.images);
  for (const auto& view : rig.views) {
    for (const auto& [number, file] : view.frames) inputs.push_back(file);
  }
  TakeWriter writer(
      take_dir, description, streams, metadata,
      interop_internal::ImportWriterOptions(options.png_compression, options.overwrite, inputs));
  // A failed import leaves its report in a new take; a replaced take is put back untouched.
  if (report != nullptr && !writer.replacing())
    report->SetFailureDestination(take_dir / "report.json");
  CreateDirectories(take_dir / "calib");
  for (const auto& view : rig.views)
    view.camera.Write(take_dir / "calib" / (view.sensor + ".cameramodel"));
  const int64_t period_ns = static_cast<int64_t>(std::llround(1e9 / options.fps));
  int64_t set_index = 0, frames = 0;
  for (int64_t number : numbers) {
    FrameSet set;
    set.index = set_index;
    for (size_t v = 0; v < rig.views.size(); ++v) {
      auto it = rig.views[v].frames.find(number);
      if (it == rig.views[v].frames.end()) continue;
      cv::Mat image =
          interop_internal::ConformedFrame(ReadSourceImage(it->second), streams[v],
                                           it->second.string(), "is calibrated for", &alpha);
      set.frames.push_back(
          {rig.views[v].sensor, image, set_index * period_ns, static_cast<uint64_t>(number)});
    }
    writer.Append(set);
    frames += static_cast<int64_t>(set.frames.size());
    ++set_index;
  }
  writer.Close();
  ImportSummary summary;
  summary.sensors = static_cast<int>(rig.views.size());
  summary.frame_sets = set_index;
  summary.frames = frames;
  summary.metrics = rig.metrics;
  summary.metrics["alpha_channels_dropped"] = alpha.dropped;
  summary.metrics["alpha_channels_kept"] = alpha.kept;
  std::string message = Cat("imported ", summary.sensors, " camera(s), ", frames, " frame(s) in ",
                            set_index, " frame set(s) from ", ToString(rig.format));
  alpha.AddNotes(&rig.notes);
  for (const auto& note : rig.notes) message += "; " + note;
  summary.End(Termination::kSuccess, std::move(message));
  if (report != nullptr) {
    report->plan() = {
        {"sensors", summary.sensors}, {"frame_sets", summary.frame_sets}, {"frames", frames}};
    report->metrics() = summary.metrics;
    report->SetSummary(summary);
  }
  return summary;
}

}  // namespace holocap
