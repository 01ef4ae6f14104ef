// The training data of a Neural Volume, read from a take without LibTorch: the views at the
// training resolution, their frames, backgrounds, the volume's box and per-frame occupancy.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/camera.h"
#include "neural/neural.h"
#include "neural/raymarch.h"

namespace holocap::neural {

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
  Eigen::Vector3d box_min = Eigen::Vector3d::Zero();
  Eigen::Vector3d box_max = Eigen::Vector3d::Ones();
  std::vector<OccupancyGrid> occupancy;  // per frame (empty grids: no skipping)
  bool dynamic = false;
  std::vector<int> encoder_views;  // indices into views (dynamic scenes)
  nlohmann::json plan = nlohmann::json::object();

  std::vector<int> TrainingViews() const;
  std::vector<int> HeldoutViews() const;
  Eigen::Vector3f box_min_f() const { return box_min.cast<float>(); }
  Eigen::Vector3f box_max_f() const { return box_max.cast<float>(); }
};

// Reads and plans (cameras, held-out views, frames, backgrounds, bounds, occupancy). Throws
// Error for a take that cannot be trained on.
TrainingData LoadTrainingData(const std::filesystem::path& take_dir,
                              const NeuralVolumeOptions& options);

// Pixels (x, y) of a camera whose rays cross the box.
std::vector<int32_t> PixelsSeeingBox(const CameraModel& camera, const Eigen::Vector3f& box_min,
                                     const Eigen::Vector3f& box_max);

}  // namespace holocap::neural
