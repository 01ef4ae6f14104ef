// holocap train TAKE --method nvol: learn an avatar from a calibrated take; and the demo's
// neural stage (a tiny model on the demo take, then a short orbit).
#include <cstdio>
#include <filesystem>
#include <iostream>

#include "app/commands.h"
#include "core/error.h"
#include "core/report.h"
#include "neural/neural.h"
#include "neural/rerender.h"
#include "playback/playback.h"

namespace holocap {
namespace {

struct TrainArgs {
  std::string take;
  std::string method = "nvol";
  std::string out;
  std::string bounds = "auto";
  NeuralVolumeOptions options;
  RerenderOptions rerender;  // --method rerender
  std::string silhouettes = "background";
  std::string recon_method = "auto";
  std::string recon_bounds;
  bool recon_no_completion = false;
};

void PrintPlan(const nlohmann::json& plan) {
  std::printf("plan:\n");
  for (const auto& [key, value] : plan.items()) std::printf("  %-18s %s\n", key.c_str(), value.dump().c_str());
}

// Neural rerendering shares the data and budget options with Neural Volumes.
void TrainRerenderCommand(const TrainArgs& args, const std::filesystem::path& out) {
  RerenderOptions o = args.rerender;
  const NeuralVolumeOptions& shared = args.options;
  o.minutes = shared.minutes;
  o.iterations = shared.iterations;
  o.image_width = shared.image_width;
  o.heldout_cameras = shared.heldout_cameras;
  o.heldout = shared.heldout;
  o.last_frame = shared.last_frame;
  o.eval_every_s = shared.eval_every_s;
  o.seed = shared.seed;
  o.threads = shared.threads;
  o.ground_truth_cameras = shared.ground_truth_cameras;
  if (args.silhouettes != "background" && args.silhouettes != "threshold") {
    Fail("--silhouettes must be background or threshold (got '", args.silhouettes, "')");
  }
  o.reconstruction.silhouette.mode =
      args.silhouettes == "threshold" ? SilhouetteMode::kThreshold : SilhouetteMode::kBackgroundSubtraction;
  o.reconstruction.method = ReconstructionMethodFromString(args.recon_method);
  if (!args.recon_bounds.empty()) o.reconstruction.bounds = ParseBounds(args.recon_bounds, "--recon-bounds");
  if (args.recon_no_completion) o.reconstruction.tsdf_hull_completion = false;
  o.Check();
  Report report("train");
  RerenderSummary summary = TrainRerender(args.take, out, o, &report);
  PrintPlan(summary.plan);
  std::printf("iterations   %lld in %.1f s\n", static_cast<long long>(summary.iterations), summary.seconds);
  std::printf("loss         %.6f -> %.6f\n", summary.first_loss, summary.last_loss);
  std::printf("held-out     PSNR %.2f dB (raw render %.2f dB), SSIM %.4f (raw %.4f)\n", summary.heldout_psnr_db,
              summary.raw_render_psnr_db, summary.heldout_ssim, summary.raw_render_ssim);
  std::printf("flicker      %.3f x truth's (raw render %.3f x)\n", summary.flicker_ratio, summary.raw_flicker_ratio);
  std::printf("%s: %s\nmodel: %s\nreport: %s\n", ToString(summary.termination), summary.message.c_str(), out.c_str(),
              (out / "report.json").c_str());
  if (!IsUsable(summary.termination) && summary.termination != Termination::kNoConvergence) {
    Fail("training ended with ", ToString(summary.termination), ": ", summary.message);
  }
}

void AddTrainCommand(CLI::App& app) {
  auto* command = app.add_subcommand("train", "Learn an avatar (Neural Volumes) from a calibrated take");
  auto args = std::make_shared<TrainArgs>();
  NeuralVolumeOptions& o = args->options;
  command->add_option("TAKE", args->take, "The take directory")->required();
  command->add_option("--method", args->method, "Model kind: nvol (Neural Volumes) or rerender (neural rerendering)")->capture_default_str();
  command->add_option("--out", args->out, "Model directory (default: TAKE/models/<method>)");
  command->add_option("--grid", o.grid, "RGBA voxels per axis (16..128, power of two)")->capture_default_str();
  command->add_option("--minutes", o.minutes, "Training time budget")->capture_default_str();
  command->add_option("--iterations", o.iterations, "Stop after this many iterations (0: time only)")->capture_default_str();
  command->add_option("--width", o.image_width, "Training image width (0: native)")->capture_default_str();
  command->add_option("--rays", o.rays_per_batch, "Rays per iteration")->capture_default_str();
  command->add_option("--heldout", o.heldout_cameras, "Cameras held out for evaluation")->capture_default_str();
  command->add_option("--heldout-names", o.heldout, "Hold out these cameras (names)");
  command->add_option("--scene", o.scene, "auto, static or dynamic")->capture_default_str();
  command->add_option("--frames", o.last_frame, "Train on the first N frame sets (-1: all)")->capture_default_str();
  command->add_option("--bounds", args->bounds, "Volume bounds: auto, hull, gt or stage")->capture_default_str();
  command->add_option("--lr", o.learning_rate, "Adam learning rate of the networks")->capture_default_str();
  command->add_option("--eval-every", o.eval_every_s, "Held-out evaluation interval, seconds")->capture_default_str();
  command->add_option("--kl-weight", o.kl_weight, "nvol: KL weight of the latent (dynamic scenes)")->capture_default_str();
  command->add_option("--tv-weight", o.tv_weight, "nvol: total-variation weight of the grid")->capture_default_str();
  command->add_option("--alpha-prior-weight", o.alpha_prior_weight, "nvol: beta prior on ray alpha")->capture_default_str();
  command->add_option("--silhouette-weight", o.silhouette_weight,
                      "nvol: ray alpha against the training silhouettes (0: off)")->capture_default_str();
  command->add_option("--warp-prior-weight", o.warp_prior_weight,
                      "nvol: mean squared warp displacement (dynamic scenes)")->capture_default_str();
  command->add_option("--seed", o.seed, "Random seed")->capture_default_str();
  command->add_option("--threads", o.threads, "Threads (0: all cores)")->capture_default_str();
  command->add_flag("--ground-truth-cameras", o.ground_truth_cameras, "Use gt/cameras even when calib/ exists");
  command->add_flag("--resume", o.resume, "Continue from the model directory's checkpoint");
  RerenderOptions& r = args->rerender;
  command->add_option("--witness", r.witness_cameras, "rerender: witness cameras left out of the reconstruction")->capture_default_str();
  command->add_option("--witness-names", r.witness, "rerender: these witness cameras (names, comma- or space-separated)")
      ->delimiter(',');
  command->add_option("--witness-folds", r.witness_folds,
                      "rerender: witness sets, each seen through a reconstruction built without it (1: one set)")
      ->capture_default_str();
  command->add_option("--fold-witnesses", r.fold_witness,
                      "rerender: the witnesses of a further fold, comma-separated (once per fold, in order; the "
                      "last fold's validate; overrides --witness-folds)")
      ->delimiter(',');
  command->add_option("--fold-recon", r.fold_recon_dirs, "rerender: use these reconstructions of the further folds (in order)");
  command->add_option("--validation-witnesses", r.validation_witnesses,
                      "rerender: witnesses kept from training to choose the weights where they peak (0: last weights, "
                      "-1: a fifth of the witnesses, at least one when there are three or more)")
      ->capture_default_str();
  command->add_option("--unet-width", r.net.width, "rerender: U-Net channels of the first level")->capture_default_str();
  command->add_option("--unet-depth", r.net.depth, "rerender: U-Net levels")->capture_default_str();
  command->add_option("--supersample", r.supersample,
                      "rerender: raster samples per pixel along each axis (1..4; playback does the same)")->capture_default_str();
  command->add_option("--witness-scales", r.witness_scales,
                      "rerender: the witnesses also train at these fractions of the training width, e.g. 1,0.6 "
                      "(views with shorter lenses or from farther away see the subject smaller)")
      ->delimiter(',')
      ->capture_default_str();
  command->add_option("--crop", r.crop_px, "rerender: training crop size near the subject (0: whole images)")->capture_default_str();
  command->add_option("--recon", r.recon_dir, "rerender: use this reconstruction (built without the witnesses)");
  command->add_option("--recon-voxel", r.reconstruction.voxel_m, "rerender: reconstruction voxel in metres")->capture_default_str();
  command->add_option("--silhouettes", args->silhouettes, "rerender: reconstruction silhouettes, background or threshold")->capture_default_str();
  command->add_option("--recon-method", args->recon_method,
                      "rerender: reconstruction method of every fold, auto, hull, tsdf or mvs")->capture_default_str();
  command->add_option("--recon-bounds", args->recon_bounds,
                      "rerender: reconstruction volume xmin,ymin,zmin,xmax,ymax,zmax in metres (default -1.5,-1.5,0,1.5,1.5,2.5)");
  command->add_flag("--recon-no-completion", args->recon_no_completion,
                    "rerender: TSDF folds mesh only what the depth sensors saw, as a live fusion system does "
                    "(no completion from the visual hull)");
  command->add_option("--subject-weight", r.subject_weight, "rerender: loss weight of pixels near the subject")->capture_default_str();
  command->add_option("--alpha-weight", r.alpha_weight, "rerender: weight of alpha against the witnesses' silhouettes (0: off)")->capture_default_str();
  command->add_option("--temporal-weight", r.temporal_weight, "rerender: temporal-consistency loss weight")->capture_default_str();
  command->add_option("--gan-weight", r.gan_weight, "rerender: PatchGAN loss weight (0: none)")->capture_default_str();
  command->callback([args] {
    if (args->method != "nvol" && args->method != "rerender") {
      Fail("unknown training method '", args->method, "' (known: nvol, rerender)");
    }
    args->options.bounds = VolumeBoundsSourceFromString(args->bounds);
    args->options.Check();
    const std::filesystem::path out = args->out.empty()
        ? std::filesystem::path(args->take) / "models" / args->method : std::filesystem::path(args->out);
    if (args->method == "rerender") return TrainRerenderCommand(*args, out);
    Report report("train");
    NeuralVolumeSummary summary = TrainNeuralVolume(args->take, out, args->options, &report);
    PrintPlan(summary.plan);
    std::printf("iterations   %lld in %.1f s (%.2f it/s)\n", static_cast<long long>(summary.iterations),
                summary.seconds, summary.iterations / std::max(summary.seconds, 1e-9));
    std::printf("loss         %.6f -> %.6f\n", summary.first_loss, summary.last_loss);
    std::printf("held-out     PSNR %.2f dB (subject %.2f dB), SSIM %.4f\n", summary.heldout_psnr_db,
                summary.heldout_psnr_fg_db, summary.heldout_ssim);
    std::printf("%s: %s\nmodel: %s\nreport: %s\n", ToString(summary.termination), summary.message.c_str(),
                out.c_str(), (out / "report.json").c_str());
    if (!IsUsable(summary.termination)) Fail("training ended with ", ToString(summary.termination), ": ", summary.message);
  });
}

// The demo: a tiny dynamic model for a few tens of seconds, then a short orbit video.
Summary TrainDemoAvatar(DemoContext& context) {
  NeuralVolumeOptions options;
  options.grid = 32;
  options.image_width = 96;
  options.minutes = 0.4;
  options.decoder_channels = 64;
  options.latent_dim = 64;
  options.warp_grid = 16;
  options.rays_per_batch = 2048;
  options.eval_every_s = 8;
  const std::filesystem::path model_dir = context.out / "nvol";
  Report report("train");
  NeuralVolumeSummary summary = TrainNeuralVolume(context.take, model_dir, options, &report);
  std::printf("[demo] nvol: %s\n", summary.message.c_str());
  nlohmann::json metrics = {{"iterations", summary.iterations},
                            {"seconds", summary.seconds},
                            {"first_loss", summary.first_loss},
                            {"last_loss", summary.last_loss},
                            {"heldout_psnr_db", summary.heldout_psnr_db},
                            {"heldout_psnr_fg_db", summary.heldout_psnr_fg_db}};
  if (!IsUsable(summary.termination)) {
    context.report->metrics()["nvol"] = metrics;
    return {summary.termination, summary.message};
  }
  auto model = OpenModel(model_dir);
  OrbitOptions orbit;
  orbit.views = 24;
  orbit.width = 256;
  orbit.height = 256;
  PlaybackOptions playback;
  playback.out = context.out / "nvol" / "orbit.mp4";
  PlaybackSummary rendered = RenderPath(*model, OrbitPath(*model, orbit), playback);
  metrics["orbit"] = playback.out.string();
  metrics["render_fps_256"] = rendered.render_fps;
  metrics["samples_per_ray"] = rendered.samples_per_ray;
  context.report->metrics()["nvol"] = metrics;
  std::printf("[demo] nvol orbit: %s -> %s\n\n", rendered.message.c_str(), playback.out.c_str());
  return {summary.termination, summary.message + "; " + rendered.message};
}

}  // namespace

HOLOCAP_COMMAND(60, AddTrainCommand);
HOLOCAP_DEMO_STAGE(40, "nvol", TrainDemoAvatar);

}  // namespace holocap
