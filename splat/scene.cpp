// A take as a splat scene: Neural Volumes' training data (the same views, held-out cameras,
// silhouettes and backgrounds), lenses undistorted to pinholes, and the seed from the frame's
// reconstruction.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <opencv2/imgproc.hpp>

#include "core/error.h"
#include "core/fs.h"
#include "core/mesh.h"
#include "neural/data.h"
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

// The pinhole of the lens's intrinsics core and the view resampled into it (colour and
// background bilinear, the silhouette nearest).
void Undistort(SplatView* view) {
  const CameraModel& lens = view->camera;
  const auto& k = lens.intrinsics();
  CameraModel pinhole("LENSMODEL_PINHOLE", {k[0], k[1], k[2], k[3]}, lens.width(), lens.height(),
                      lens.cam_from_world());
  const int w = lens.width(), h = lens.height();
  Eigen::Matrix3Xd rays(3, static_cast<int64_t>(w) * h);
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x)
      rays.col(static_cast<int64_t>(y) * w + x) << (x - k[2]) / k[0], (y - k[3]) / k[1], 1.0;
  }
  const Eigen::Matrix2Xd pixels = lens.ProjectMany(rays);
  cv::Mat map_x(h, w, CV_32FC1), map_y(h, w, CV_32FC1);
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      map_x.at<float>(y, x) = static_cast<float>(pixels(0, static_cast<int64_t>(y) * w + x));
      map_y.at<float>(y, x) = static_cast<float>(pixels(1, static_cast<int64_t>(y) * w + x));
    }
  }
  cv::Mat image, mask, background;
  cv::remap(view->image, image, map_x, map_y, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
  cv::remap(view->mask, mask, map_x, map_y, cv::INTER_NEAREST, cv::BORDER_CONSTANT);
  cv::remap(view->background, background, map_x, map_y, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
  view->camera = pinhole;
  view->image = image;
  view->mask = mask;
  view->background = background;
}

// The first planned frame set's surface: recon_dir's, else reconstructed now by the plan's
// method from the training cameras (the held-out ones never). Empty when the reconstruction
// found none; `source` says what happened.
Mesh SeedSurface(const fs::path& take_dir, const fs::path& model_dir, const SplatOptions& options,
                 const neural::TrainingData& data, std::string* source) {
  const int64_t set = data.sets.front();
  fs::path recon_dir = options.recon_dir;
  if (recon_dir.empty()) {
    recon_dir = model_dir / "seed_recon";
    TakeSelection selection = options.take;
    selection.last_frame = selection.first_frame + 1;
    selection.heldout.clear();
    for (const auto& view : data.views)
      if (view.heldout) selection.heldout.push_back(view.name);
    ReconstructionOptions recon;
    // A seed needs points a few pixels apart, not the finest surface: 1/256 of the volume.
    recon.voxel_m = (data.box_max - data.box_min).maxCoeff() / 256.0;
    recon.sweep_voxels_m.clear();
    recon.write_glb = false;
    recon.threads = options.threads;
    const ReconstructionSummary summary = ReconstructTake(take_dir, selection, recon_dir, recon);
    *source = Cat("reconstructed now (", summary.plan.value("method", std::string("?")), ", voxel ",
                  recon.voxel_m * 1000, " mm): ", summary.message);
    if (!summary.IsUsable()) return Mesh{};
  } else {
    *source = Cat("reconstruction ", recon_dir.string());
  }
  const fs::path file = recon_dir / (SetName(set) + ".ply");
  if (!fs::exists(file)) {
    *source += Cat("; no surface for frame set ", set, " (", file.string(), ")");
    return Mesh{};
  }
  Mesh mesh = ReadPly(file);
  *source += Cat("; ", file.filename().string(), ": ", mesh.vertices.size(), " vertices");
  return mesh;
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
                          const SplatOptions& options) {
  options.Check();
  NeuralVolumeOptions data_options;
  data_options.image_width = options.image_width;
  data_options.heldout_cameras = options.heldout_cameras;
  data_options.heldout = options.heldout;
  data_options.take = options.take;
  data_options.threads = options.threads;
  data_options.scene = "static";
  const neural::TrainingData data = neural::LoadTrainingData(take_dir, data_options);
  SplatScene scene;
  scene.plan = data.plan;
  scene.plan.erase("encoder_views");
  scene.plan.erase("occupancy");
  scene.box = Eigen::AlignedBox3d(data.box_min, data.box_max);
  std::vector<std::string> undistorted;
  for (size_t v = 0; v < data.views.size(); ++v) {
    SplatView view;
    view.name = data.views[v].name;
    view.camera = data.views[v].camera;
    view.image = data.images.front()[v];
    view.mask = data.masks.front()[v];
    view.background = data.views[v].background;
    view.heldout = data.views[v].heldout;
    if (view.camera.lensmodel() != "LENSMODEL_PINHOLE") {
      Undistort(&view);
      undistorted.push_back(view.name);
    }
    scene.views.push_back(std::move(view));
  }
  scene.plan["lenses"] =
      undistorted.empty() ? nlohmann::json("pinhole: trained on the images as they are")
                          : nlohmann::json(Cat(undistorted.size(),
                                               " distorting lens(es): images, silhouettes and "
                                               "backgrounds resampled to the pinhole of each "
                                               "lens's intrinsics core (held-out scored there)"));
  if (scene.plan["left_out"].contains("depth sensors"))
    scene.plan["left_out"]["depth sensors"] =
        "splats learn from colour alone (the seed's "
        "reconstruction may fuse their depth)";
  scene.plan["frame_set"] = data.sets.front();
  if (data.sets.size() > 1) {
    scene.plan["left_out"]["frames after the first"] =
        Cat(data.sets.size() - 1,
            " frame set(s): splats train one frame; frame-to-frame training is not built");
  }
  std::string source;
  const Mesh mesh = SeedSurface(take_dir, model_dir, options, data, &source);
  scene.seed = SeedFrom(mesh, scene.views, options.max_seed_points, options.seed);
  scene.seed.source = source + (scene.seed.source.empty() ? "" : "; " + scene.seed.source);
  return scene;
}

}  // namespace holocap
