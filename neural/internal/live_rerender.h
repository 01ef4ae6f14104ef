// The training pairs of a live-rerender model (neural/live_rerender.h), shared by the pair
// builder and the trainer. Internal to holocap_neural.
#pragma once

#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <vector>

#include "neural/live_rerender.h"

namespace holocap::neural {

// The composition of live_set seen from target_set's colour camera.
struct LivePair {
  int64_t live_set = 0, target_set = 0;
  double turn_deg = 0;  // the subject's turn between the two frames
  GBuffer buffers;      // at the training resolution, positions left out
  cv::Mat target;       // CV_32FC3 BGR in [0, 1]: the target frame, black outside its silhouette
  cv::Mat silhouette;   // CV_8U 255: the target frame's own composition covers the pixel
};

// NOLINTNEXTLINE(bugprone-exception-escape): its implicit members only move vectors and JSON
struct LivePairs {
  std::vector<LivePair> train, validation;
  int64_t composed = 0, refused = 0;
  nlohmann::json plan;  // sensors, frames, pairs, resolution, what is left out
};

// Composes options.live_frames frames of the scan take with the scan and pairs them (throws
// Error as TrainLiveRerender does).
LivePairs MakeLivePairs(const std::filesystem::path& scan_take,
                        const std::filesystem::path& scan_dir, const LiveRerenderOptions& options);

// Mean squared error (per channel) of `image` against the pair's target inside its silhouette,
// and the pixels counted (PSNR over many pairs pools these).
struct MaskedError {
  double squared = 0;
  int64_t count = 0;
};
MaskedError ErrorInSilhouette(const cv::Mat& image, const LivePair& pair);

}  // namespace holocap::neural
