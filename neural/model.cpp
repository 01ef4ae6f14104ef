// Neural Volumes' options: the part without LibTorch.
#include <cmath>

#include "core/error.h"
#include "neural/neural.h"

namespace holocap {

namespace {

bool IsPowerOfTwo(int value) { return value > 0 && (value & (value - 1)) == 0; }

}  // namespace

void NeuralVolumeOptions::Check() const {
  if (!IsPowerOfTwo(grid) || grid < 16 || grid > 128)
    Fail("grid must be a power of two in [16, 128], got ", grid);
  if (latent_dim < 1) Fail("latent_dim must be positive, got ", latent_dim);
  if (warp_count < 1) Fail("warp_count must be positive, got ", warp_count);
  if (!IsPowerOfTwo(warp_grid) || warp_grid < 8 || warp_grid > 64)
    Fail("warp_grid must be a power of two in [8, 64], got ", warp_grid);
  if (encoder_views < 1) Fail("encoder_views must be at least 1, got ", encoder_views);
  if (encoder_width < 16) Fail("encoder_width must be at least 16 pixels, got ", encoder_width);
  if (decoder_channels < 16) Fail("decoder_channels must be at least 16, got ", decoder_channels);
  if (scene != "auto" && scene != "static" && scene != "dynamic")
    Fail("scene must be auto, static or dynamic, got '", scene, "'");
  if (image_width < 0) Fail("image_width must be >= 0 (0: native), got ", image_width);
  if (heldout_cameras < 0) Fail("heldout_cameras must be >= 0, got ", heldout_cameras);
  take.Check();
  if (!(bounds_margin_m >= 0)) Fail("bounds_margin_m must be >= 0, got ", bounds_margin_m);
  if (occupancy_cells < 0) Fail("occupancy_cells must be >= 0, got ", occupancy_cells);
  if (!(minutes > 0) && iterations <= 0)
    Fail("give a positive minutes budget or a number of iterations");
  if (iterations < 0) Fail("iterations must be >= 0, got ", iterations);
  if (rays_per_batch < 16) Fail("rays_per_batch must be at least 16, got ", rays_per_batch);
  if (frames_per_batch < 1) Fail("frames_per_batch must be at least 1, got ", frames_per_batch);
  if (!(learning_rate > 0) || !(static_learning_rate > 0) || !(template_learning_rate > 0))
    Fail("learning rates must be positive");
  if (!(kl_weight >= 0) || !(alpha_prior_weight >= 0) || !(tv_weight >= 0) ||
      !(silhouette_weight >= 0) || !(warp_prior_weight >= 0)) {
    Fail("loss weights must be >= 0");
  }
  if (!(step_voxels > 0)) Fail("step_voxels must be positive, got ", step_voxels);
  if (!(min_transmittance >= 0 && min_transmittance < 1))
    Fail("min_transmittance must be in [0, 1), got ", min_transmittance);
  if (!(eval_every_s > 0)) Fail("eval_every_s must be positive, got ", eval_every_s);
  if (eval_every_iterations < 0)
    Fail("eval_every_iterations must be >= 0, got ", eval_every_iterations);
  if (eval_frames < 1) Fail("eval_frames must be at least 1, got ", eval_frames);
  if (!(checkpoint_every_s > 0))
    Fail("checkpoint_every_s must be positive, got ", checkpoint_every_s);
  if (!(divergence_factor > 1)) Fail("divergence_factor must exceed 1, got ", divergence_factor);
  if (max_divergences < 0) Fail("max_divergences must be >= 0, got ", max_divergences);
  if (threads < 0) Fail("threads must be >= 0, got ", threads);
}

TrainingDataOptions NeuralVolumeOptions::data_options() const {
  TrainingDataOptions data;
  data.image_width = image_width;
  data.heldout_cameras = heldout_cameras;
  data.heldout = heldout;
  data.take = take;
  data.scene = scene;
  data.encoder_views = encoder_views;
  data.bounds = bounds;
  data.bounds_margin_m = bounds_margin_m;
  data.occupancy_cells = occupancy_cells;
  data.threads = threads;
  return data;
}

nlohmann::json NeuralVolumeOptions::ToJson() const {
  return {{"grid", grid},
          {"latent_dim", latent_dim},
          {"warp_count", warp_count},
          {"warp_grid", warp_grid},
          {"encoder_views", encoder_views},
          {"encoder_width", encoder_width},
          {"decoder_channels", decoder_channels},
          {"scene", scene},
          {"image_width", image_width},
          {"heldout_cameras", heldout_cameras},
          {"heldout", heldout},
          {"take", take.ToJson()},
          {"bounds", ToString(bounds)},
          {"bounds_margin_m", bounds_margin_m},
          {"occupancy_cells", occupancy_cells},
          {"minutes", minutes},
          {"iterations", iterations},
          {"rays_per_batch", rays_per_batch},
          {"frames_per_batch", frames_per_batch},
          {"learning_rate", learning_rate},
          {"static_learning_rate", static_learning_rate},
          {"template_learning_rate", template_learning_rate},
          {"kl_weight", kl_weight},
          {"alpha_prior_weight", alpha_prior_weight},
          {"tv_weight", tv_weight},
          {"silhouette_weight", silhouette_weight},
          {"warp_prior_weight", warp_prior_weight},
          {"learn_background", learn_background},
          {"step_voxels", step_voxels},
          {"jitter", jitter},
          {"min_transmittance", min_transmittance},
          {"seed", seed},
          {"eval_every_s", eval_every_s},
          {"eval_every_iterations", eval_every_iterations},
          {"eval_frames", eval_frames},
          {"checkpoint_every_s", checkpoint_every_s},
          {"resume", resume},
          {"divergence_factor", divergence_factor},
          {"max_divergences", max_divergences},
          {"threads", threads}};
}

}  // namespace holocap
