// Neural Volumes' options: the part without LibTorch.
#include <cmath>

#include "core/check_option.h"
#include "core/error.h"
#include "neural/neural.h"

namespace holocap {

namespace {

bool IsPowerOfTwo(int value) { return value > 0 && (value & (value - 1)) == 0; }

}  // namespace

void NeuralVolumeOptions::Check() const {
  HOLOCAP_CHECK_OPTION_IN(grid, 16, 128);
  HOLOCAP_CHECK_OPTION(IsPowerOfTwo(grid), grid);
  HOLOCAP_CHECK_OPTION_GE(latent_dim, 1);
  HOLOCAP_CHECK_OPTION_GE(warp_count, 1);
  HOLOCAP_CHECK_OPTION_IN(warp_grid, 8, 64);
  HOLOCAP_CHECK_OPTION(IsPowerOfTwo(warp_grid), warp_grid);
  HOLOCAP_CHECK_OPTION_GE(encoder_views, 1);
  HOLOCAP_CHECK_OPTION_GE(encoder_width, 16, "pixels");
  HOLOCAP_CHECK_OPTION_GE(decoder_channels, 16);
  HOLOCAP_CHECK_OPTION(IsOneOf(scene, {"auto", "static", "dynamic"}), scene);
  HOLOCAP_CHECK_OPTION_GE(image_width, 0, "0: native");
  HOLOCAP_CHECK_OPTION_GE(heldout_cameras, 0);
  take.Check();
  HOLOCAP_CHECK_OPTION_GE(bounds_margin_m, 0);
  HOLOCAP_CHECK_OPTION_GE(occupancy_cells, 0);
  HOLOCAP_CHECK_OPTION(std::isfinite(minutes), minutes, "a budget must end");
  HOLOCAP_CHECK_OPTION(minutes > 0 || iterations > 0 || cpu_minutes > 0, minutes,
                       "give a positive minutes budget or a number of iterations");
  HOLOCAP_CHECK_OPTION_GE(cpu_minutes, 0, "0: the wall clock (minutes)");
  HOLOCAP_CHECK_OPTION(std::isfinite(cpu_minutes), cpu_minutes, "a budget must end");
  HOLOCAP_CHECK_OPTION_GE(iterations, 0);
  HOLOCAP_CHECK_OPTION_GE(rays_per_batch, 16);
  HOLOCAP_CHECK_OPTION_GE(frames_per_batch, 1);
  HOLOCAP_CHECK_OPTION_GT(learning_rate, 0);
  HOLOCAP_CHECK_OPTION_GT(static_learning_rate, 0);
  HOLOCAP_CHECK_OPTION_GT(template_learning_rate, 0);
  HOLOCAP_CHECK_OPTION_GE(kl_weight, 0);
  HOLOCAP_CHECK_OPTION_GE(alpha_prior_weight, 0);
  HOLOCAP_CHECK_OPTION_GE(tv_weight, 0);
  HOLOCAP_CHECK_OPTION_GE(silhouette_weight, 0);
  HOLOCAP_CHECK_OPTION_GE(warp_prior_weight, 0);
  HOLOCAP_CHECK_OPTION_GT(step_voxels, 0);
  HOLOCAP_CHECK_OPTION_GE(min_transmittance, 0);
  HOLOCAP_CHECK_OPTION_LT(min_transmittance, 1);
  HOLOCAP_CHECK_OPTION_GT(eval_every_s, 0);
  HOLOCAP_CHECK_OPTION_GE(eval_every_iterations, 0);
  HOLOCAP_CHECK_OPTION_GE(eval_frames, 1);
  HOLOCAP_CHECK_OPTION_GT(checkpoint_every_s, 0);
  HOLOCAP_CHECK_OPTION_GT(divergence_factor, 1);
  HOLOCAP_CHECK_OPTION_GE(max_divergences, 0);
  HOLOCAP_CHECK_OPTION_GE(threads, 0);
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
          {"cpu_minutes", cpu_minutes},
          {"checkpoint_every_s", checkpoint_every_s},
          {"resume", resume},
          {"divergence_factor", divergence_factor},
          {"max_divergences", max_divergences},
          {"threads", threads}};
}

}  // namespace holocap
