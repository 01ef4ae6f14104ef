// Neural Volumes (Lombardi et al. 2019): an avatar learned from a calibrated multi-view take
// and played back from any viewpoint. The public interface of Neural Volumes in holocap_neural
// (rerendering: neural/rerender.h, live rerendering: neural/live_rerender.h); it pulls in no
// LibTorch header, so what includes it compiles fast.
//
// The model, after the paper and its public code:
//   encoder  a few fixed views of a frame -> a 256-d latent (a VAE: mean and log-sigma, KL)
//   decoder  transposed 3D convolutions from the latent -> an RGBA voxel grid (D³, D = 16..128)
//   warp     a mixture of 16 affine warps blended on a 32³ grid, mapping each sample to the
//            template grid
//   per-camera colour calibration (gain, bias) and per-camera background images
// and the renderer is the differentiable ray marcher of avatar/raymarch.h (rays through the
// mrcal models, distortion included, clipped to the volume's box, about one voxel per step
// with jitter, empty space skipped through an occupancy grid).
//
// What a scene does not need is left out: a static take (one frame set, or the --static plan)
// builds no encoder and no warp field; its RGBA grid itself is optimised. The plan is printed
// and stored in report.json.
//
// A trained model is a directory holding model.json (its "method" is "nvol") and its weights;
// RegisterNeuralVolumeAvatarKind() lets OpenModel (avatar/avatar.h) open it.
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

#include "avatar/avatar.h"
#include "avatar/training_data.h"
#include "core/camera.h"
#include "core/report.h"
#include "core/take_plan.h"

namespace holocap {

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
  double minutes = 5;  // wall-clock budget of training
  // > 0: a budget of the process's CPU seconds (user + system, every thread) instead of the
  // wall clock, counted from the start of TrainNeuralVolume: loading the take spends it too;
  // scoring the held-out views does not.
  double cpu_minutes = 0;
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
  TrainingDataOptions data_options() const;  // what the training-data loader reads
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
  // Process CPU seconds (user + system, every thread): loading the take, training (everything
  // after it but the held-out scoring) and the held-out scoring.
  double cpu_s_loading = 0, cpu_s_training = 0, cpu_s_scoring = 0;
  bool built_encoder = false;
  bool built_warp = false;
  double samples_per_ray = 0;  // mean over the last training batch
};

// Trains a Neural Volume on a take into `model_dir` (model.json, weights, per-frame latents,
// backgrounds, checkpoint.pt, report.json). Cameras come from calib/, else from gt/cameras
// (said in the plan). `report` receives options, plan, metrics (metrics.heldout_psnr_db) and
// the series heldout_psnr_db, heldout_ssim and loss. Throws Error for bad options or a take
// that cannot be trained on (missing cameras, too few views); numerical trouble is reported in
// the summary.
NeuralVolumeSummary TrainNeuralVolume(const std::filesystem::path& take_dir,
                                      const std::filesystem::path& model_dir,
                                      const NeuralVolumeOptions& options, Report* report = nullptr);

// Lets OpenModel (avatar/avatar.h) open "nvol" model directories.
void RegisterNeuralVolumeAvatarKind(AvatarKindRegistry& registry);

}  // namespace holocap
