// Neural rerendering (after LookinGood, Martin-Brualla et al. 2018): the reconstruction of a
// take is rasterised into a camera (colour, depth, normal and coverage buffers) and a U-Net
// turns those buffers into the photo the camera would have taken (RGB and alpha). The network
// learns on "witness" cameras that the reconstruction never saw, so it learns to repair what
// the reconstruction gets wrong (holes, blurry texture, over-smooth silhouettes) in views it
// was not built from; further cameras are held out from both for measurement.
//
// This header pulls in no LibTorch header (the CLI and playback include it).
#pragma once

#include <cstdint>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "avatar/mesh_raster.h"
#include "core/camera.h"
#include "core/mesh.h"
#include "core/report.h"
#include "neural/neural.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

// ---------------------------------------------------------------------------------------------
// The network

struct UNetConfig {
  int width = 24;  // channels of the first level (doubled per level, capped at 8x)
  int depth = 4;   // levels (each halves the resolution; inputs are padded to 2^depth)
  nlohmann::json ToJson() const;
  static UNetConfig FromJson(const nlohmann::json& json);
  void Check() const;
};

// A U-Net from G-buffers to RGB and alpha. Its output starts as the raw render (the last layer
// is zero at initialisation: colour is the render's, alpha its coverage), so training only
// has to learn corrections; the alpha correction is bounded so that a large early step cannot
// saturate it beyond recovery. Holds LibTorch state behind a pointer.
class RerenderNetwork {
 public:
  RerenderNetwork(const UNetConfig& config, uint64_t seed);
  ~RerenderNetwork();
  RerenderNetwork(RerenderNetwork&&) noexcept;
  RerenderNetwork& operator=(RerenderNetwork&&) noexcept;
  static RerenderNetwork Load(const std::filesystem::path& weights, const UNetConfig& config);
  void Save(const std::filesystem::path& weights) const;  // atomic

  const UNetConfig& config() const;
  int64_t parameter_count() const;
  // Inference on one view: colour premultiplied by alpha (BGR in [0, 1]), alpha, depth copied
  // from the buffers. Empty, holed or NaN buffers give finite output (NaN depth is no depth).
  RenderedView Apply(const GBuffer& buffers, int threads = 0) const;

  struct State;
  State& state() const { return *state_; }

 private:
  explicit RerenderNetwork(std::unique_ptr<State> state);
  std::unique_ptr<State> state_;
};

// ---------------------------------------------------------------------------------------------
// Training

struct RerenderOptions {
  UNetConfig net;

  // Cameras. The colour cameras are split three ways: the reconstruction's, the witnesses
  // (the network trains on them) and the held-out ones (measurement only).
  int witness_cameras = 2;           // spread around the rig
  int heldout_cameras = 1;           // spread around the rig
  std::vector<std::string> witness;  // by name (overrides witness_cameras)
  std::vector<std::string> heldout;  // by name (overrides heldout_cameras)
  TakeSelection take;                // frame sets, clean plate and cameras (core/take_plan.h);
                                     // the folds' reconstructions use the same

  // The reconstruction, built from the other cameras into MODEL/recon (or taken from
  // `recon_dir` when given: it must then not have used the witnesses).
  std::filesystem::path recon_dir;
  // More witnesses: each further fold is another set of witness cameras with a reconstruction
  // of its own, built without them (and without the held-out cameras) into MODEL/recon-<k>.
  // The network trains on the witnesses of every fold, each through the reconstruction that
  // never saw it, so it sees more viewpoints of what a reconstruction gets wrong. Held-out
  // measurement and playback use the first fold's reconstruction.
  int witness_folds = 3;  // folds in all (fewer when the cameras run out); further
                          // witnesses are picked spread around among the cameras
                          // not yet a witness; 1: the first set only
  std::vector<std::vector<std::string>> fold_witness;  // by name, the folds after the first
                                                       // (overrides witness_folds)
  std::vector<std::filesystem::path> fold_recon_dirs;  // their reconstructions, when given
  // Early stopping: this many witnesses (the last fold's) are not trained on but scored at
  // every evaluation, and the model keeps the weights where their PSNR peaked (the network
  // starts as the raw render, so it never ends worse than that on them); 0: the last weights;
  // -1: a fifth of the witnesses, at least one once there are three in all (one view's PSNR
  // swings from evaluation to evaluation and chooses early, noisy weights), else none.
  int validation_witnesses = -1;
  ReconstructionOptions reconstruction;

  // Data.
  int image_width = 160;  // training/evaluation width (cameras rescaled); 0: native
  int supersample = 2;    // raster samples per pixel along each axis, averaged
                          // (the raw render too; the model keeps it and playback
                          // rasterises alike): 1 samples pixel centres only,
                          // whose aliased edges the network would learn to smooth
  std::vector<double> witness_scales = {
      1.0};  // the witnesses are also trained on at these
             // fractions of the training width (rasterised anew,
             // their images area-averaged): a view asked for with
             // a shorter lens or from farther away sees the subject
             // smaller than any witness did; must include 1;
             // training crops are at most the smallest such image

  // Optimisation.
  double minutes = 3;           // wall-clock budget
  int64_t iterations = 0;       // > 0: stop after this many (whichever first)
  int batch_pairs = 2;          // pairs of consecutive frames (same camera, same crop)
  int crop_px = 64;             // square training crops centred on a pixel near the
                                // subject (rounded up to a multiple of 2^depth, at
                                // most the image): the network learns where the
                                // reconstruction is, not on empty background; 0:
                                // whole images
  double learning_rate = 3e-4;  // Adam, decayed to a tenth over the budget (cosine)
  double l1_weight = 1;
  double ssim_weight = 0.5;    // 1 - SSIM averaged over three scales
  double subject_weight = 4;   // loss weight of pixels near the rendered subject (the
                               // rest, mostly background, weighs 1)
  double alpha_weight = 1;     // L1 of alpha against the witness's own silhouette
                               // (the reconstruction's silhouette options on the
                               // witness image; background subtraction needs a clean
                               // plate): the subject is drawn opaque where the
                               // witness saw it, and only there; 0: off
  double temporal_weight = 8;  // L1 of (output change - truth change) between frames (8-32 beat
                               // 0.5-2 on held-out cameras of a holed reconstruction)
  double gan_weight = 0;       // > 0: adds a PatchGAN discriminator (LSGAN)
  uint64_t seed = 1;

  // Bookkeeping.
  double eval_every_s = 15;  // held-out PSNR/SSIM every this many seconds
  int threads = 0;           // 0: all cores

  void Check() const;  // throws Error naming the bad field and why
  nlohmann::json ToJson() const;
};

// FAILURE when the loss became non-finite; DEGENERATE when the kept network shows the held-out
// cameras no more of the subject than the background alone; CONVERGENCE when the validation
// witnesses peaked before the budget ran out (those weights are kept); else NO_CONVERGENCE.
struct RerenderSummary : Summary {
  nlohmann::json plan;
  int64_t iterations = 0;
  double seconds = 0;                    // training wall time
  double first_loss = 0, last_loss = 0;  // means over the first and last iterations
  // Held-out cameras over every trained frame, whole images over the clean plate.
  double heldout_psnr_db = 0, raw_render_psnr_db = 0;
  double heldout_ssim = 0, raw_render_ssim = 0;
  // Early stopping: the validation witnesses' best PSNR, its iteration, and their raw render's.
  double validation_psnr_db = 0, validation_raw_psnr_db = 0;
  int64_t kept_iteration = -1;  // the weights kept (-1: the last ones)
  // The same, on the pixels near the subject only.
  double heldout_psnr_subject_db = 0, raw_render_psnr_subject_db = 0;
  // The background alone (clean plate, or black) on the same frames: what an output that
  // dropped the subject would score.
  double background_psnr_db = 0, background_psnr_subject_db = 0, background_ssim = 0;
  // Flicker on the first held-out camera: mean |frame-to-frame difference| divided by the
  // truth's (1 = as steady as reality), and the mean |output change - truth change|.
  double flicker_ratio = 0, raw_flicker_ratio = 0;
  double flicker_excess = 0, raw_flicker_excess = 0;
};

// Trains a rerendering model on a take into `model_dir` (model.json, unet.pt, cameras/,
// recon/, report.json, and heldout.png: truth, raw render and rerendered view side by side
// for the first held-out camera's middle frame). `report` receives options, plan, metrics
// (heldout_psnr_db, raw_render_psnr_db, background_psnr_db, heldout_ssim, raw_render_ssim, flicker)
// and the series heldout_psnr_db, heldout_ssim and loss. Throws Error for bad options or a take
// that cannot be used (no cameras, too few colour cameras for the split, no frames); numerical
// trouble (a diverging loss, a reconstruction that failed) is reported in the summary.
RerenderSummary TrainRerender(const std::filesystem::path& take_dir,
                              const std::filesystem::path& model_dir,
                              const RerenderOptions& options, Report* report = nullptr);

// Lets OpenModel (avatar/avatar.h) open "rerender" model directories.
void RegisterRerenderAvatarKind(AvatarKindRegistry& registry);

}  // namespace holocap
