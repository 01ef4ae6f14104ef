// What every avatar kind shares, without LibTorch: the model interface that playback, the web
// export and the benchmarks render through, the views and baked frames it returns, and the
// registry of kinds.
//
// A trained avatar is a directory holding model.json, whose "method" names its kind, and the
// kind's own files. A kind registers itself by name in AvatarKindRegistry (as a capture driver
// registers in DriverRegistry); OpenModel() then opens any directory of a registered kind. The
// CLI registers every kind compiled into it (RegisterAvatarKinds(), app/avatar_kinds.cpp):
//   nvol           Neural Volumes (neural/neural.h), needs LibTorch
//   rerender       neural rerendering of a reconstruction (neural/rerender.h), needs LibTorch
//   live-rerender  rerendering of `holocap live` meshes (neural/live_rerender.h), needs LibTorch
//   splat          3D Gaussian splats (splat/splat.h)
// docs/add-an-avatar-kind.md shows a new kind: one folder and one registration line.
#pragma once

#include <Eigen/Core>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/box.h"
#include "core/camera.h"
#include "core/error.h"

namespace holocap {

struct ViewRenderOptions {
  double step_voxels = 1.0;         // ray-marching step in voxels
  bool skip_empty = true;           // skip empty space through the occupancy grid
  double min_transmittance = 1e-3;  // a ray stops once this little light is left
  double depth_min_alpha = 0.5;     // depth is reported where alpha reaches this (else NaN)
  int threads = 0;                  // 0: all cores
  bool bake = true;                 // march one world-space RGBA grid (the template resampled
                                    // through the warp once per frame) instead of warp + template
  double bake_scale = 1.0;          // baked voxels per template voxel along each axis (>= 1)
};

struct RenderedView {
  cv::Mat color;  // CV_32FC3, BGR in [0, 1], premultiplied by alpha (over black)
  cv::Mat alpha;  // CV_32FC1 in [0, 1]
  cv::Mat depth;  // CV_32FC1 z-depth in metres along the optical axis, NaN where alpha is
                  // below ViewRenderOptions::depth_min_alpha
  double samples_per_ray = 0;  // mean over the rays that enter the volume
  int64_t rays_in_volume = 0;
  double seconds = 0;  // marching (and decoding, when the frame was not cached)
};

// One frame of a volumetric avatar exactly as Render marches it: a world-space RGBA grid
// (channels last, x fastest; colour in [0, 1], density in 1/m; voxel centres at normalised box
// coordinates (i + 0.5) / grid) and the occupancy whose empty cells add nothing.
struct BakedFrame {
  Box box{Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones()};
  int grid = 0;
  std::vector<float> rgba;        // grid³ x 4
  bool clamped = false;           // outside its voxel centres the grid continues its border
                                  // (a resampled grid), else it is zero there
  int occupancy_cells = 0;        // cells per axis; 0: no cell is skipped
  std::vector<uint8_t> occupied;  // occupancy_cells³, x fastest
  double step_m = 0;              // Render's sample spacing at the options' step_voxels
};

class AvatarModel {
 public:
  virtual ~AvatarModel() = default;
  virtual std::string method() const = 0;
  virtual int64_t frame_count() const = 0;  // frames it can play (1 for a static scene)
  // The world box the avatar lives in.
  virtual Box box() const = 0;
  // The cameras it was trained from (for orbits at their distance and for comparisons).
  virtual std::vector<CameraModel> cameras() const = 0;
  // Renders frame `frame` (clamped to the model's range) through any camera.
  virtual RenderedView Render(const CameraModel& camera, int64_t frame,
                              const ViewRenderOptions& options) = 0;
  // The frame as the grid Render marches (the web export streams it); false for a kind that is
  // not a volume.
  virtual bool Bake(int64_t /*frame*/, const ViewRenderOptions& /*options*/, BakedFrame* /*out*/) {
    return false;
  }
};

// Opens a model directory of one kind; `model_json` is its parsed model.json. Throws Error for
// files the kind cannot read.
using ModelOpener = std::function<std::unique_ptr<AvatarModel>(const std::filesystem::path& dir,
                                                               const nlohmann::json& model_json)>;

struct AvatarKind {
  std::string method;       // model.json's "method"
  std::string description;  // one line, for listings and errors
  ModelOpener open;
};

// The kinds a program can open, by method.
class AvatarKindRegistry {
 public:
  // The process-wide registry; the CLI fills it with every kind compiled in.
  static AvatarKindRegistry& Global();

  void Register(AvatarKind kind);  // replaces a kind of the same method
  bool has(const std::string& method) const;
  std::vector<std::string> methods() const;  // in alphabetical order
  // Opens a model directory by its model.json's "method". Throws Error for a missing or
  // corrupt model.json or a method no registered kind has (naming the known ones).
  std::unique_ptr<AvatarModel> Open(const std::filesystem::path& dir) const;

 private:
  mutable std::mutex mutex_;
  std::map<std::string, AvatarKind> kinds_;
};

// AvatarKindRegistry::Global().Open(dir).
std::unique_ptr<AvatarModel> OpenModel(const std::filesystem::path& dir);

// "; on white, as NeRF-synthetic scores, X dB" for a take scored on white (alpha), else "".
inline std::string OnWhiteClause(double heldout_psnr_white_db) {
  return std::isfinite(heldout_psnr_white_db)
             ? Cat("; on white, as NeRF-synthetic scores, ", heldout_psnr_white_db, " dB")
             : std::string();
}

// The metrics every trained model's report.json starts with, by the same names (Neural Volumes,
// splats): held-out scores, the background alone's, the budget spent and the loss's course.
template <typename TrainingSummary>
nlohmann::json TrainingMetrics(const TrainingSummary& summary) {
  return {{"heldout_psnr_db", summary.heldout_psnr_db},
          {"heldout_psnr_fg_db", summary.heldout_psnr_fg_db},
          {"heldout_ssim", summary.heldout_ssim},
          {"background_psnr_fg_db", summary.background_psnr_fg_db},
          {"iterations", summary.iterations},
          {"seconds", summary.seconds},
          {"first_loss", summary.first_loss},
          {"last_loss", summary.last_loss},
          {"divergences", summary.divergences}};
}

}  // namespace holocap
