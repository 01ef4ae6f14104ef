// Neural Volumes (Lombardi et al. 2019): an avatar learned from a calibrated multi-view take
// and played back from any viewpoint. This header is the whole public interface of
// holocap_neural and pulls in no LibTorch header, so the CLI and playback compile fast.
//
// The model, after the paper and its public code:
//   encoder  a few fixed views of a frame -> a 256-d latent (a VAE: mean and log-sigma, KL)
//   decoder  transposed 3D convolutions from the latent -> an RGBA voxel grid (D³, D = 16..128)
//   warp     a mixture of 16 affine warps blended on a 32³ grid, mapping each sample to the
//            template grid
//   per-camera colour calibration (gain, bias) and per-camera background images
// and the renderer is the differentiable ray marcher of neural/raymarch.h (rays through the
// mrcal models, distortion included, clipped to the volume's box, about one voxel per step
// with jitter, empty space skipped through an occupancy grid).
//
// What a scene does not need is left out: a static take (one frame set, or the --static plan)
// builds no encoder and no warp field; its RGBA grid itself is optimised. The plan is printed
// and stored in report.json.
//
// A trained model is a directory holding model.json (its "method" names the kind) and the
// kind's own files. OpenModel() reads any kind registered with RegisterModelKind(); "nvol" is
// built in.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <limits>
#include <memory>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/camera.h"
#include "core/report.h"
#include "core/take_plan.h"

namespace holocap {

// The source of the box that bounds the volume, in order of preference for kAuto.
enum class VolumeBoundsSource {
  kAuto,         // hull, then ground-truth meshes, then the stage
  kHull,         // the visual hull of the training views (reconstruction/), per frame
  kGroundTruth,  // the take's gt/meshes (simulated takes)
  kStage,        // the take plan's bounds (--bounds, else from the rig; see core/take_plan.h)
};
const char* ToString(VolumeBoundsSource source);
VolumeBoundsSource VolumeBoundsSourceFromString(const std::string& text);  // throws Error

struct NeuralVolumeOptions {
  // Model.
  int grid = 64;               // RGBA voxels per axis: a power of two in [16, 128]
  int latent_dim = 256;        // latent code of a frame (dynamic scenes)
  int warp_count = 16;         // affine warps in the mixture (dynamic scenes)
  int warp_grid = 32;          // warp field voxels per axis, power of two in [8, 64]
  int encoder_views = 3;       // training cameras the encoder sees (spread around the rig)
  int encoder_width = 64;      // encoder input width in pixels (height keeps the aspect)
  int decoder_channels = 128;  // channels after the first decoder layer (halved per layer)
  std::string scene = "auto";  // "auto" (static iff one frame set), "static", "dynamic"

  // Data.
  int image_width = 160;             // training/evaluation width (cameras rescaled); 0: native
  int heldout_cameras = 2;           // cameras never trained on, spread around the rig
  std::vector<std::string> heldout;  // or these by name (overrides heldout_cameras)
  TakeSelection take;                // frame sets, clean plate and cameras (core/take_plan.h)
  VolumeBoundsSource bounds = VolumeBoundsSource::kAuto;
  double bounds_margin_m = 0.08;  // the box grows by this on every side
  int occupancy_cells = 32;       // cells per axis of the skipping grid (0: no skipping)

  // Optimisation.
  double minutes = 5;                    // wall-clock budget of training
  int64_t iterations = 0;                // > 0: stop after this many iterations (whichever first)
  int rays_per_batch = 4096;             // random pixels per iteration, across cameras and frames
  int frames_per_batch = 1;              // frames decoded per iteration (dynamic scenes)
  double learning_rate = 2e-3;           // Adam
  double static_learning_rate = 3e-2;    // Adam on the grid itself (static scenes)
  double template_learning_rate = 3e-2;  // Adam on the template's directly optimised residual
                                         // grid (dynamic scenes)
  double kl_weight = 1.5e-8;  // KL of the latent (dynamic scenes): the paper's 1e-3 against
                              // 0..255 pixel errors. Much more and the posterior collapses to
                              // the prior: each sampled latent is mostly noise, the decoder
                              // learns to ignore it and renders every frame as the take's
                              // average, a fog filling each frame's hull.
  double alpha_prior_weight = 1e-4;  // beta prior pushing ray alpha towards 0 or 1 (colours in
                                     // [0, 1]: the paper weighs it against 0..255 pixel errors)
  double tv_weight = 1e-2;           // total variation of the grid
  double silhouette_weight = 0.05;   // ray alpha of training pixels against their silhouettes
                                     // (where the take gives them): the six views' hull holds a
                                     // faint subject as well as an opaque one, and only the
                                     // opaque one is right from cameras between them
  double warp_prior_weight = 0.1;    // mean squared displacement of the warp field (template
                                     // units, dynamic scenes): unchecked, the affine warps move
                                     // every sample out of the template within tens of steps
                                     // and the volume renders empty with no gradient left
  bool learn_background = true;      // refine the training cameras' backgrounds where no frame
                                     // shows the subject
  double step_voxels = 1.0;          // ray-marching step in voxels
  bool jitter = true;                // random offset of the first sample of each training ray
  double min_transmittance = 1e-3;   // training rays stop once this little light is left
  uint64_t seed = 1;

  // Bookkeeping.
  double eval_every_s = 20;           // held-out PSNR/SSIM every this many seconds
  int64_t eval_every_iterations = 0;  // > 0: every this many iterations instead (runs that
                                      // must not depend on the host's speed)
  int eval_frames = 3;                // held-out frames evaluated (spread over the take)
  double checkpoint_every_s = 60;     // checkpoint interval
  bool resume = false;                // continue from the model directory's checkpoint
  double divergence_factor = 20;      // a loss above this x its running mean is a divergence
  int max_divergences = 5;            // then training stops with kFailure
  int threads = 0;                    // 0: all cores

  void Check() const;  // throws Error naming the bad field and why
  nlohmann::json ToJson() const;
};

// NO_CONVERGENCE when the budget is spent (training has no stopping criterion of its own),
// FAILURE on repeated divergence or a non-finite result.
struct NeuralVolumeSummary : Summary {
  nlohmann::json plan;  // what was built and why (also in report.json)
  int64_t iterations = 0;
  double seconds = 0;             // training wall time (data loading excluded)
  double first_loss = 0;          // mean photometric loss over the first iterations
  double last_loss = 0;           // and over the last ones
  double heldout_psnr_db = 0;     // held-out cameras, whole image (background included)
  double heldout_psnr_fg_db = 0;  // held-out cameras, inside the subject's silhouette only
  // Held-out cameras composited on white (prediction by its alpha, truth by the frames' own
  // alpha): NeRF-synthetic's published convention; NaN unless the silhouettes are alpha.
  double heldout_psnr_white_db = std::numeric_limits<double>::quiet_NaN();
  double background_psnr_fg_db = 0;  // the same pixels rendered as background alone (the
                                     // score of an empty volume: what training must beat)
  double heldout_ssim = 0;
  int divergences = 0;  // restored checkpoints
  bool built_encoder = false;
  bool built_warp = false;
  double samples_per_ray = 0;  // mean over the last training batch
};

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

// Trains a Neural Volume on a take into `model_dir` (model.json, weights, per-frame latents,
// backgrounds, checkpoint.pt, report.json). Cameras come from calib/, else from gt/cameras
// (said in the plan). `report` receives options, plan, metrics (metrics.heldout_psnr_db) and
// the series heldout_psnr_db, heldout_ssim and loss. Throws Error for bad options or a take
// that cannot be trained on (missing cameras, too few views); numerical trouble is reported in
// the summary.
NeuralVolumeSummary TrainNeuralVolume(const std::filesystem::path& take_dir,
                                      const std::filesystem::path& model_dir,
                                      const NeuralVolumeOptions& options, Report* report = nullptr);

// ---------------------------------------------------------------------------------------------
// Trained models, of any kind.

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
  Eigen::Vector3d box_min = Eigen::Vector3d::Zero();
  Eigen::Vector3d box_max = Eigen::Vector3d::Ones();
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
  virtual Eigen::Vector3d box_min() const = 0;
  virtual Eigen::Vector3d box_max() const = 0;
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

using ModelOpener = std::function<std::unique_ptr<AvatarModel>(const std::filesystem::path& dir,
                                                               const nlohmann::json& model_json)>;
// Adds a model kind; model.json's "method" selects it.
void RegisterModelKind(const std::string& method, ModelOpener opener);
std::vector<std::string> ModelKinds();
// Opens a model directory. Throws Error for a missing/corrupt model.json or an unknown method
// (naming the known ones).
std::unique_ptr<AvatarModel> OpenModel(const std::filesystem::path& dir);

// Image quality, on 8-bit or float images of one size and type (float: range [0, 1]).
double PsnrDb(const cv::Mat& image, const cv::Mat& reference, const cv::Mat& mask = {});
double Ssim(const cv::Mat& image, const cv::Mat& reference);

}  // namespace holocap
