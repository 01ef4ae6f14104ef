// The training data of an avatar, read from a take without LibTorch: the views at the
// training resolution, their frames, silhouettes and backgrounds, the box the avatar lives in
// and per-frame occupancy. Every kind (Neural Volumes, rerendering, splats) loads through it,
// so that all of them train and are scored on the same views and the same held-out cameras.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "avatar/raymarch.h"
#include "core/box.h"
#include "core/camera.h"
#include "core/take_plan.h"

namespace holocap {

// The source of the box that bounds the volume, in order of preference for kAuto.
enum class VolumeBoundsSource {
  kAuto,         // hull, then the stage
  kHull,         // the visual hull of the training views (reconstruction/), per frame
  kGroundTruth,  // the take's gt/meshes (simulated takes): only when asked for, never by kAuto
  kStage,        // the take plan's bounds (--bounds, else from the rig; see core/take_plan.h)
};
const char* ToString(VolumeBoundsSource source);
VolumeBoundsSource VolumeBoundsSourceFromString(const std::string& text);  // throws Error

// What LoadTrainingData reads and how it plans (each trainer fills it from its own options).
struct TrainingDataOptions {
  int image_width = 160;             // training/evaluation width (cameras rescaled); 0: native
  int heldout_cameras = 2;           // cameras never trained on, spread around the rig
  std::vector<std::string> heldout;  // or these by name (overrides heldout_cameras)
  TakeSelection take;                // frame sets, clean plate and cameras (core/take_plan.h)
  std::string scene = "auto";        // "auto" (static iff one frame set), "static", "dynamic"
  int encoder_views = 3;             // views chosen for an encoder (dynamic scenes)
  VolumeBoundsSource bounds = VolumeBoundsSource::kAuto;
  double bounds_margin_m = 0.08;  // the box grows by this on every side
  int occupancy_cells = 32;       // cells per axis of the skipping grid (0: no skipping)
  int threads = 0;                // 0: all cores

  void Check() const;  // throws Error naming the bad field and why
};

struct TrainingView {
  std::string name;
  CameraModel camera;  // at the training resolution
  bool heldout = false;
  cv::Mat background;  // CV_8UC3 BGR at the training resolution
};

struct TrainingData {
  std::vector<TrainingView> views;
  std::vector<int64_t> sets;                 // the take's frame-set numbers used
  std::vector<std::vector<cv::Mat>> images;  // [frame][view], CV_8UC3 BGR
  // [frame][view] CV_8UC1 silhouettes (255 = subject). Those of training views carve the hull;
  // those of held-out views only select the pixels of the subject-only PSNR.
  std::vector<std::vector<cv::Mat>> masks;
  bool alpha_masks = false;  // the masks are the frames' own alpha (exact; scored on white too)
  Box box{Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones()};
  std::vector<OccupancyGrid> occupancy;  // per frame (empty grids: no skipping)
  bool dynamic = false;
  std::vector<int> encoder_views;  // indices into views (dynamic scenes)
  nlohmann::json plan = nlohmann::json::object();

  std::vector<int> TrainingViews() const;
  std::vector<int> HeldoutViews() const;
  Eigen::Vector3f box_min_f() const { return box.min.cast<float>(); }
  Eigen::Vector3f box_max_f() const { return box.max.cast<float>(); }
};

// Reads and plans (cameras, held-out views, frames, backgrounds, bounds, occupancy). Throws
// Error for a take that cannot be trained on.
TrainingData LoadTrainingData(const std::filesystem::path& take_dir,
                              const TrainingDataOptions& options);

// Pixels (x, y) of a camera whose rays cross the box.
std::vector<int32_t> PixelsSeeingBox(const CameraModel& camera, const Eigen::Vector3f& box_min,
                                     const Eigen::Vector3f& box_max);

}  // namespace holocap
