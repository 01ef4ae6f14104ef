// holocap train nvol|rerender|splat TAKE: learn an avatar from a calibrated take, one
// subcommand per method, each with only its own flags (the shared ones are defined once); and
// the demo's avatar stages (tiny models on the demo take, then a short orbit). Compiled into both
// programs: splats train in holocap itself; nvol and rerender need LibTorch (holocap-neural,
// HOLOCAP_WITH_NEURAL), and so does the demo.
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <iostream>

#include "app/commands.h"
#include "app/options.h"
#include "core/error.h"
#include "core/report.h"
#include "neural/live_rerender.h"
#include "neural/neural.h"
#include "neural/rerender.h"
#include "playback/playback.h"
#include "splat/splat.h"

namespace holocap {
namespace {

// Where a run's report went: OUT/report.json, or beside it (report.failed.json) when the run
// is not usable and a usable one was there (core/report.h).
std::string ReportWhere(const std::filesystem::path& out, const Report& report) {
  return ReportDestination(out / "report.json", report.json()).string();
}

// `train` takes words no method knows, to name an unknown method (AddTrainCommand), and the
// methods added after it inherit that; so each method refuses here, by name and before it runs,
// the words it was given that are not its own (whether it kept them or handed them up).
void RefuseForeignFlags(const CLI::App* method) {
  std::vector<std::string> extras = method->remaining();
  if (extras.empty()) extras = method->get_parent()->remaining();
  if (extras.empty()) return;
  Fail("train ", method->get_name(), " has no option '", extras.front(), "' (holocap train ",
       method->get_name(), " --help lists its options)");
}

// What every training method takes, filled by AddSharedTrainFlags.
struct SharedTrainArgs {
  std::string take;
  std::string out;
  bool overwrite = false;
  TakeSelectionFlags selection;
  double minutes = 0;
  int64_t iterations = 0;
  int image_width = 0;
  int heldout_cameras = 0;
  std::vector<std::string> heldout;
  double learning_rate = 0;
  double eval_every_s = 0;
  uint64_t seed = 1;
  int threads = 0;

  // The model directory: --out, else TAKE/models/<method>.
  std::filesystem::path Out(const char* method) const {
    return out.empty() ? std::filesystem::path(take) / "models" / method
                       : std::filesystem::path(out);
  }
  // The model directory, claimed for `train <method>` (core/output.h): the take is locked
  // while the returned object lives.
  OutputDirectory Claim(const char* method) const {
    return OutputDirectory::Claim(Out(method),
                                  {std::string("train ") + method, overwrite, {}, false, take});
  }
};

// The shared fields carry the same names in every method's options.
template <typename Options>
void TakeSharedDefaults(const Options& o, SharedTrainArgs* shared) {
  shared->minutes = o.minutes;
  shared->iterations = o.iterations;
  shared->image_width = o.image_width;
  shared->heldout_cameras = o.heldout_cameras;
  shared->learning_rate = o.learning_rate;
  shared->eval_every_s = o.eval_every_s;
  shared->seed = o.seed;
  shared->threads = o.threads;
}

template <typename Options>
void ApplyShared(const SharedTrainArgs& shared, Options* o) {
  o->take = shared.selection.Parse();
  o->minutes = shared.minutes;
  o->iterations = shared.iterations;
  o->image_width = shared.image_width;
  o->heldout_cameras = shared.heldout_cameras;
  o->heldout = shared.heldout;
  o->learning_rate = shared.learning_rate;
  o->eval_every_s = shared.eval_every_s;
  o->seed = shared.seed;
  o->threads = shared.threads;
}

// The shared flags; their defaults are the method's own (TakeSharedDefaults first).
void AddSharedTrainFlags(CLI::App* command, SharedTrainArgs* args) {
  command->add_option("TAKE", args->take, "The take directory")->required();
  command->add_option("--out", args->out, "Model directory (default: TAKE/models/<method>)");
  AddOverwriteFlag(command, &args->overwrite);
  AddTakeSelectionFlags(command, &args->selection);
  command->add_option("--minutes", args->minutes, "Training time budget")->capture_default_str();
  command
      ->add_option("--iterations", args->iterations,
                   "Stop after this many iterations (0: time only)")
      ->capture_default_str();
  command->add_option("--width", args->image_width, "Training image width (0: native)")
      ->capture_default_str();
  command
      ->add_option("--heldout", args->heldout_cameras,
                   "Cameras held out for evaluation, spread around the rig")
      ->capture_default_str();
  command
      ->add_option("--heldout-names", args->heldout,
                   "Hold out these cameras (names, comma-separated)")
      ->delimiter(',');
  command->add_option("--lr", args->learning_rate, "Adam learning rate")->capture_default_str();
  command->add_option("--eval-every", args->eval_every_s, "Held-out evaluation interval, seconds")
      ->capture_default_str();
  command->add_option("--seed", args->seed, "Random seed")->capture_default_str();
  command->add_option("--threads", args->threads, "Threads (0: all cores)")->capture_default_str();
  NameFieldFlags(command, {{"image_width", "--width"},
                           {"heldout_cameras", "--heldout"},
                           {"heldout", "--heldout-names"},
                           {"learning_rate", "--lr"},
                           {"eval_every_s", "--eval-every"}});
}

// --cpu-minutes, which nvol and splat take alike.
void AddCpuMinutesFlag(CLI::App* command, double* cpu_minutes, const char* what_counts,
                       const char* more = "") {
  command
      ->add_option(
          "--cpu-minutes", *cpu_minutes,
          Cat("A budget of this process's CPU minutes (user + system, every thread) "
              "instead of the wall clock (--minutes): ",
              what_counts, " spend it; scoring the held-out views does not", more, " (0: off)"))
      ->capture_default_str();
}

void PrintPlan(const nlohmann::json& plan) {
  std::printf("plan:\n");
  for (const auto& [key, value] : plan.items())
    std::printf("  %-18s %s\n", key.c_str(), value.dump().c_str());
}

#if HOLOCAP_WITH_NEURAL

// ---------------------------------------------------------------------------------------------
// holocap train nvol

struct NvolArgs {
  SharedTrainArgs shared;
  NeuralVolumeOptions options;
  std::string bounds = "auto";
};

void FillNvolCommand(CLI::App* command) {
  auto args = std::make_shared<NvolArgs>();
  NeuralVolumeOptions& o = args->options;
  SharedTrainArgs& shared = args->shared;
  TakeSharedDefaults(o, &shared);
  AddSharedTrainFlags(command, &shared);
  command->add_option("--grid", o.grid, "RGBA voxels per axis (16..128, power of two)")
      ->capture_default_str();
  command->add_option("--rays", o.rays_per_batch, "Rays per iteration")->capture_default_str();
  command->add_option("--scene", o.scene, "auto, static or dynamic")->capture_default_str();
  command
      ->add_option("--bounds", args->bounds,
                   "Volume bounds: auto (the hull, else the stage), hull, stage, or gt (a "
                   "simulated take's true meshes, when asked for)")
      ->capture_default_str();
  command->add_option("--kl-weight", o.kl_weight, "KL weight of the latent (dynamic scenes)")
      ->capture_default_str();
  command->add_option("--tv-weight", o.tv_weight, "Total-variation weight of the grid")
      ->capture_default_str();
  command->add_option("--alpha-prior-weight", o.alpha_prior_weight, "Beta prior on ray alpha")
      ->capture_default_str();
  command
      ->add_option("--silhouette-weight", o.silhouette_weight,
                   "Ray alpha against the training silhouettes (0: off)")
      ->capture_default_str();
  command
      ->add_option("--warp-prior-weight", o.warp_prior_weight,
                   "Mean squared warp displacement (dynamic scenes)")
      ->capture_default_str();
  command->add_flag("--resume", o.resume, "Continue from the model directory's checkpoint");
  AddCpuMinutesFlag(command, &o.cpu_minutes, "loading the take and every training step");
  command
      ->add_option("--eval-frames", o.eval_frames,
                   "Frames the held-out cameras are scored on, spread over the take")
      ->capture_default_str();
  NameFieldFlags(command, {{"rays_per_batch", "--rays"}});
  command->callback([command, args] {
    RefuseForeignFlags(command);
    NeuralVolumeOptions o = args->options;
    const SharedTrainArgs& shared = args->shared;
    ApplyShared(shared, &o);
    o.bounds = VolumeBoundsSourceFromString(args->bounds);
    o.Check();
    const OutputDirectory claimed = shared.Claim("nvol");
    const std::filesystem::path& out = claimed.path();
    Report report("train nvol");
    report.SetFailureDestination(out / "report.json");
    NeuralVolumeSummary summary = TrainNeuralVolume(shared.take, out, o, &report);
    PrintPlan(summary.plan);
    std::printf("iterations   %lld in %.1f s (%.2f it/s)\n",
                static_cast<long long>(summary.iterations), summary.seconds,
                summary.iterations / std::max(summary.seconds, 1e-9));
    std::printf("loss         %.6f -> %.6f\n", summary.first_loss, summary.last_loss);
    std::printf("held-out     PSNR %.2f dB (subject %.2f dB), SSIM %.4f\n", summary.heldout_psnr_db,
                summary.heldout_psnr_fg_db, summary.heldout_ssim);
    std::printf("model: %s\nreport: %s\n", out.c_str(), ReportWhere(out, report).c_str());
    EndCommand(summary, "training");
  });
}

// ---------------------------------------------------------------------------------------------
// holocap train rerender

struct RerenderArgs {
  SharedTrainArgs shared;
  RerenderOptions options;
  std::string silhouettes = "background";
  std::string recon_method = "auto";
  std::string recon_bounds;
  bool recon_no_completion = false;
  // With a scan: the network for `holocap live`'s compositions, trained on the scan take.
  std::string scan;
  LiveRerenderOptions live;
};

void AddRerenderWitnessFlags(CLI::App* command, RerenderOptions& r) {
  command
      ->add_option("--witness", r.witness_cameras, "Witness cameras left out of the reconstruction")
      ->capture_default_str();
  command
      ->add_option("--witness-names", r.witness, "These witness cameras (names, comma-separated)")
      ->delimiter(',');
  command
      ->add_option("--witness-folds", r.witness_folds,
                   "Witness sets, each seen through a reconstruction built without it (1: one set)")
      ->capture_default_str();
  command
      ->add_option("--fold-witnesses", r.fold_witness,
                   "The witnesses of a further fold, comma-separated (once per fold, in order; the "
                   "last fold's "
                   "validate; overrides --witness-folds)")
      ->delimiter(',');
  command
      ->add_option("--fold-recon", r.fold_recon_dirs,
                   "Use these reconstructions of the further folds (in order, comma-separated)")
      ->delimiter(',');
  command
      ->add_option("--validation-witnesses", r.validation_witnesses,
                   "Witnesses kept from training to choose the weights where they peak (0: last "
                   "weights, -1: a "
                   "fifth of the witnesses, at least one when there are three or more)")
      ->capture_default_str();
  command
      ->add_option("--witness-scales", r.witness_scales,
                   "The witnesses also train at these fractions of the training width, e.g. 1,0.6 "
                   "(views with "
                   "shorter lenses or from farther away see the subject smaller)")
      ->delimiter(',')
      ->capture_default_str();
}

void AddRerenderReconstructionFlags(CLI::App* command, RerenderArgs* args) {
  RerenderOptions& r = args->options;
  command->add_option("--recon", r.recon_dir,
                      "Use this reconstruction (built without the witnesses)");
  command->add_option("--recon-voxel", r.reconstruction.voxel_m, "Reconstruction voxel in metres")
      ->capture_default_str();
  command
      ->add_option("--silhouettes", args->silhouettes,
                   "Reconstruction silhouettes, background or threshold")
      ->capture_default_str();
  command
      ->add_option("--recon-method", args->recon_method,
                   "Reconstruction method of every fold, auto, hull, tsdf or mvs")
      ->capture_default_str();
  command->add_option("--recon-bounds", args->recon_bounds,
                      "Reconstruction volume xmin,ymin,zmin,xmax,ymax,zmax in metres (default "
                      "-1.5,-1.5,0,1.5,1.5,2.5)");
  command->add_flag("--recon-no-completion", args->recon_no_completion,
                    "TSDF folds mesh only what the depth sensors saw, as a live fusion system does "
                    "(no completion "
                    "from the visual hull)");
}

void AddRerenderNetworkFlags(CLI::App* command, RerenderOptions& r) {
  command->add_option("--unet-width", r.net.width, "U-Net channels of the first level")
      ->capture_default_str();
  command->add_option("--unet-depth", r.net.depth, "U-Net levels")->capture_default_str();
  command
      ->add_option("--supersample", r.supersample,
                   "Raster samples per pixel along each axis (1..4; playback does the same)")
      ->capture_default_str();
  command->add_option("--crop", r.crop_px, "Training crop size near the subject (0: whole images)")
      ->capture_default_str();
  command
      ->add_option("--subject-weight", r.subject_weight, "Loss weight of pixels near the subject")
      ->capture_default_str();
  command
      ->add_option("--alpha-weight", r.alpha_weight,
                   "Weight of alpha against the witnesses' silhouettes (0: off)")
      ->capture_default_str();
  command->add_option("--temporal-weight", r.temporal_weight, "Temporal-consistency loss weight")
      ->capture_default_str();
  command->add_option("--gan-weight", r.gan_weight, "PatchGAN loss weight (0: none)")
      ->capture_default_str();
}

RerenderOptions RerenderOptionsFrom(const RerenderArgs& args) {
  RerenderOptions o = args.options;
  ApplyShared(args.shared, &o);
  if (args.silhouettes != "background" && args.silhouettes != "threshold") {
    Fail("--silhouettes must be background or threshold (got '", args.silhouettes, "')");
  }
  o.reconstruction.silhouette.mode = args.silhouettes == "threshold"
                                         ? SilhouetteMode::kThreshold
                                         : SilhouetteMode::kBackgroundSubtraction;
  o.reconstruction.method = ReconstructionMethodFromString(args.recon_method);
  if (!args.recon_bounds.empty())
    o.reconstruction.bounds = ParseBounds(args.recon_bounds, "--recon-bounds");
  if (args.recon_no_completion) o.reconstruction.tsdf_hull_completion = false;
  o.Check();
  return o;
}

void AddLiveRerenderFlags(CLI::App* command, RerenderArgs* args) {
  LiveRerenderOptions& l = args->live;
  command->add_option(
      "--scan", args->scan,
      "TAKE is a scan take and this its scan (`holocap scan`): train the network that rerenders "
      "`holocap live`'s compositions, on pairs of the scan take's frames (the witness and "
      "reconstruction flags do not apply)");
  command
      ->add_option("--live-frames", l.live_frames,
                   "With --scan: frames composed as the live frame, spread over the take")
      ->capture_default_str();
  command
      ->add_option("--targets-per-frame", l.targets_per_frame,
                   "With --scan: views of each composition, frames turned 60-180 degrees away")
      ->capture_default_str();
  command
      ->add_option("--jitter", l.jitter_m,
                   "With --scan: each composition moved by a random shift of this RMS per axis "
                   "(metres) before it is rendered, as a live alignment errs")
      ->capture_default_str();
  command
      ->add_option("--jitter-deg", l.jitter_deg,
                   "With --scan: ... and turned by this RMS (degrees)")
      ->capture_default_str();
  command
      ->add_option("--validate-every", l.eval_every,
                   "With --scan: validation PSNR every this many iterations (the best is kept)")
      ->capture_default_str();
}

void TrainLiveRerenderCommand(const RerenderArgs& args) {
  LiveRerenderOptions o = args.live;
  const RerenderOptions& r = args.options;
  const SharedTrainArgs& shared = args.shared;
  o.net = r.net;
  o.supersample = r.supersample;
  o.crop_px = r.crop_px;
  o.subject_weight = r.subject_weight;
  o.alpha_weight = r.alpha_weight;
  o.minutes = shared.minutes;
  o.iterations = shared.iterations;
  o.image_width = shared.image_width;
  o.learning_rate = shared.learning_rate;
  o.seed = shared.seed;
  o.threads = shared.threads;
  o.ground_truth_cameras = shared.selection.ground_truth_cameras;
  o.Check();
  // A bad scan is refused before any output is claimed.
  ReadScanAlbedo(args.scan, ReadScan(args.scan));
  const OutputDirectory claimed =
      OutputDirectory::Claim(shared.Out("rerender"),
                             {"train rerender", shared.overwrite, {args.scan}, false, shared.take});
  const std::filesystem::path& out = claimed.path();
  Report report("train rerender");
  report.SetFailureDestination(out / "report.json");
  const LiveRerenderSummary summary = TrainLiveRerender(shared.take, args.scan, out, o, &report);
  PrintPlan(summary.plan);
  std::printf("iterations   %lld in %.1f s (kept %lld)\n",
              static_cast<long long>(summary.iterations), summary.seconds,
              static_cast<long long>(summary.kept_iteration));
  std::printf("loss         %.6f -> %.6f\n", summary.first_loss, summary.last_loss);
  std::printf("validation   PSNR %.2f dB (raw composition %.2f dB) inside the silhouettes\n",
              summary.validation_psnr_db, summary.raw_psnr_db);
  std::printf("model: %s\nreport: %s\n", out.c_str(), ReportWhere(out, report).c_str());
  EndCommand(summary, "training");
}

void FillRerenderCommand(CLI::App* command) {
  auto args = std::make_shared<RerenderArgs>();
  RerenderOptions& r = args->options;
  SharedTrainArgs& shared = args->shared;
  TakeSharedDefaults(r, &shared);
  AddSharedTrainFlags(command, &shared);
  AddRerenderWitnessFlags(command, r);
  AddRerenderReconstructionFlags(command, args.get());
  AddRerenderNetworkFlags(command, r);
  command->add_option("--batch-pairs", r.batch_pairs, "Pairs of consecutive frames per iteration")
      ->capture_default_str();
  AddLiveRerenderFlags(command, args.get());
  // The U-Net's width and depth are not the training images' (--width); the reconstruction's
  // voxel is --recon-voxel; --scan's validation interval counts iterations (--eval-every: s).
  NameFieldFlags(command, {{"witness_cameras", "--witness"},
                           {"witness", "--witness-names"},
                           {"fold_witness", "--fold-witnesses"},
                           {"fold_recon_dirs", "--fold-recon"},
                           {"recon_dir", "--recon"},
                           {"voxel_m", "--recon-voxel"},
                           {"UNetConfig::width", "--unet-width"},
                           {"UNetConfig::depth", "--unet-depth"},
                           {"LiveRerenderOptions::eval_every", "--validate-every"}});
  command->callback([command, args] {
    RefuseForeignFlags(command);
    if (!args->scan.empty()) return TrainLiveRerenderCommand(*args);
    const RerenderOptions o = RerenderOptionsFrom(*args);
    const OutputDirectory claimed = args->shared.Claim("rerender");
    const std::filesystem::path& out = claimed.path();
    Report report("train rerender");
    report.SetFailureDestination(out / "report.json");
    RerenderSummary summary = TrainRerender(args->shared.take, out, o, &report);
    PrintPlan(summary.plan);
    std::printf("iterations   %lld in %.1f s\n", static_cast<long long>(summary.iterations),
                summary.seconds);
    std::printf("loss         %.6f -> %.6f\n", summary.first_loss, summary.last_loss);
    std::printf("held-out     PSNR %.2f dB (raw render %.2f dB), SSIM %.4f (raw %.4f)\n",
                summary.heldout_psnr_db, summary.raw_render_psnr_db, summary.heldout_ssim,
                summary.raw_render_ssim);
    std::printf("flicker      %.3f x truth's (raw render %.3f x)\n", summary.flicker_ratio,
                summary.raw_flicker_ratio);
    std::printf("model: %s\nreport: %s\n", out.c_str(), ReportWhere(out, report).c_str());
    EndCommand(summary, "training");
  });
}

#endif  // HOLOCAP_WITH_NEURAL

// ---------------------------------------------------------------------------------------------
// holocap train splat

struct SplatArgs {
  SharedTrainArgs shared;
  SplatOptions options;
  std::string shard;
  bool profile = false;
};

// A per-frame run's outcome (its frames are in its report).
void PrintFrameRun(const SplatSummary& summary, const std::filesystem::path& out,
                   const Shard& shard) {
  if (!shard.whole()) {
    std::printf("task report: %s\n", TaskReportPath(out, shard).c_str());
    EndCommand(summary, "the shard");
    return;
  }
  std::printf("model: %s\nreport: %s\n", out.c_str(), (out / "report.json").c_str());
  EndCommand(summary, "training");
}

// A dynamic take's flags: the scene's kind, each later frame's budget, motion, delta and
// additions, and the per-frame runs' segments and shards.
void AddSplatFrameFlags(CLI::App* command, SplatArgs* args) {
  SplatOptions& o = args->options;
  command
      ->add_option("--scene", o.scene,
                   "auto (dynamic iff several frame sets), static (the first frame only) or "
                   "dynamic (frame to frame, each later frame a delta of the one before)")
      ->capture_default_str();
  command->add_option("--frame-minutes", o.frame_minutes, "Budget of each frame after the first")
      ->capture_default_str();
  command
      ->add_option("--frame-iterations", o.frame_iterations,
                   "Iterations of each frame after the first (0: time only)")
      ->capture_default_str();
  command
      ->add_option("--frame-motion-spacings", o.frame_motion_spacings,
                   "A later frame's motion: a field of nodes this many seed spacings apart, "
                   "each Gaussian moved by its eight nodes' blend, so neighbours move together "
                   "(0: each Gaussian learns its own motion)")
      ->capture_default_str();
  command
      ->add_option("--max-frame-mb", o.max_frame_megabytes,
                   "A later frame's delta is coarsened until it fits this many MB")
      ->capture_default_str();
  command
      ->add_option("--max-added-per-frame", o.max_added_per_frame,
                   "Gaussians a later frame may add (densified or on new surface)")
      ->capture_default_str();
  command
      ->add_option("--segment-frames", o.segment_frames,
                   "A per-frame run: frame 0 trained once (the run's plan), the later frames "
                   "in segments of this many, each segment's first frame from frame 0 (a "
                   "delta of it) and the rest chained; budgets in iterations only; complete "
                   "frames are skipped on a re-run (0: one chain in one process)")
      ->capture_default_str();
  command
      ->add_option("--segment-start-iterations", o.segment_start_iterations,
                   "Iterations of a segment's first frame (0: 4 x --frame-iterations)")
      ->capture_default_str();
  command->add_option(
      "--shard", args->shard,
      "Do task K of N of a per-frame run (K from 0): the K-th of N contiguous blocks "
      "of its segments; the first task trains frame 0 into OUT/plan, the others "
      "wait for it and read it; the model and report.json are merged when every "
      "frame is done (holocap report OUT --merge)");
}

void AddSplatCommand(CLI::App* train) {
  auto* command = train->add_subcommand(
      "splat", "3D Gaussian splats seeded from the reconstruction, tiled CPU rasteriser");
  auto args = std::make_shared<SplatArgs>();
  SplatOptions& o = args->options;
  SharedTrainArgs& shared = args->shared;
  TakeSharedDefaults(o, &shared);
  shared.learning_rate = o.learning_rate;
  AddSharedTrainFlags(command, &shared);
  command->get_option("--lr")->description("Multiplies every parameter group's Adam rate");
  command->add_option("--sh-degree", o.sh_degree, "Spherical-harmonic degree (0..3)")
      ->capture_default_str();
  command->add_option("--max-gaussians", o.max_gaussians, "Cap on the Gaussian count")
      ->capture_default_str();
  command
      ->add_option("--seed-points", o.max_seed_points, "Surface samples the Gaussians start from")
      ->capture_default_str();
  command->add_option("--recon", o.recon_dir, "Seed from this reconstruction (recon/<set>.ply)");
  command
      ->add_option("--seed-method", o.seed_method,
                   "The seed's reconstruction: auto (TSDF fusion of the depth sensors, else "
                   "multi-view stereo; with --no-depth, colour cameras only), hull (the colour "
                   "cameras' visual hull), tsdf or mvs")
      ->capture_default_str();
  AddCpuMinutesFlag(command, &o.cpu_minutes,
                    "loading the take, the seed's reconstruction and every training step",
                    "; --minutes and --frame-minutes then share it between frame 0 and each "
                    "later frame");
  command->add_option("--initial-opacity", o.initial_opacity, "Opacity of every seeded Gaussian")
      ->capture_default_str();
  command
      ->add_option("--densify-until", o.densify_until, "Last iteration that densifies and prunes")
      ->capture_default_str();
  command->add_option("--ssim-weight", o.ssim_weight, "Lambda of (1 - lambda) L1 + lambda D-SSIM")
      ->capture_default_str();
  AddSplatFrameFlags(command, args.get());
  command
      ->add_option("--pixel-budget", o.pixel_budget,
                   "Pixels an iteration draws at the start: views larger than this train halved "
                   "until they fit, reaching full resolution halfway through the budget (0: "
                   "full resolution throughout)")
      ->capture_default_str();
  command->add_flag("--no-random-background{false}", o.random_background,
                    "An alpha take: train over the view's background as takes without alpha are, "
                    "not over a random colour each iteration (which learns only what the alpha "
                    "holds)");
  command->add_flag("--profile", args->profile,
                    "Print the wall time of one iteration by stage (projection, sort, binning, "
                    "forward, loss and SSIM, backward, reduction, Adam, densification); "
                    "report.json holds it as metrics.profile either way");
  command->add_flag("--redo", o.tasks.redo,
                    "A per-frame run: train frames whose deltas are complete from an earlier run "
                    "too");
  NameFieldFlags(command, {{"max_seed_points", "--seed-points"},
                           {"recon_dir", "--recon"},
                           {"max_frame_megabytes", "--max-frame-mb"}});
  command->callback([command, args] {
    RefuseForeignFlags(command);
    SplatOptions o = args->options;
    const SharedTrainArgs& shared = args->shared;
    ApplyShared(shared, &o);
    if (!args->shard.empty()) o.tasks.shard = Shard::Parse(args->shard);
    if (o.segment_frames > 0) {
      // A wall-clock budget would make each frame's bytes depend on the machine that trained it.
      for (const char* flag : {"--minutes", "--frame-minutes"}) {
        if (command->count(flag) > 0)
          Fail(flag,
               " is a wall-clock budget; a per-frame run (--segment-frames) trains each "
               "frame for --iterations / --frame-iterations, the same bytes on any machine");
      }
    }
    o.Check();
    const OutputDirectory claimed = OutputDirectory::Claim(
        shared.Out("splat"),
        {"train splat", shared.overwrite, {}, !o.tasks.shard.whole(), shared.take});
    const std::filesystem::path& out = claimed.path();
    Report report("train splat");
    report.SetFailureDestination(o.segment_frames > 0 ? TaskReportPath(out, o.tasks.shard)
                                                      : out / "report.json");
    SplatSummary summary = TrainSplats(shared.take, out, o, &report);
    if (o.segment_frames > 0) {
      PrintFrameRun(summary, out, o.tasks.shard);
      return;
    }
    PrintPlan(summary.plan);
    std::printf("iterations   %lld in %.1f s (%.2f it/s)\n",
                static_cast<long long>(summary.iterations), summary.seconds,
                summary.iterations / std::max(summary.seconds, 1e-9));
    std::printf("loss         %.6f -> %.6f\n", summary.first_loss, summary.last_loss);
    std::printf(
        "held-out     PSNR %.2f dB (subject %.2f dB, background alone %.2f dB), SSIM %.4f\n",
        summary.heldout_psnr_db, summary.heldout_psnr_fg_db, summary.background_psnr_fg_db,
        summary.heldout_ssim);
    std::printf("gaussians    %lld from %lld seeds (%s), %.2f MB, render %.1f fps\n",
                static_cast<long long>(summary.gaussians),
                static_cast<long long>(summary.seed_points),
                summary.cap_reached ? "the cap bit" : "under the cap", summary.megabytes,
                summary.render_fps);
    if (args->profile) std::printf("profile      %s", FormatSplatProfile(summary.profile).c_str());
    if (summary.temporal) {
      double largest = 0, later_s = 0;
      for (size_t f = 1; f < summary.frames.size(); ++f) {
        largest = std::max(largest, summary.frames[f].megabytes);
        later_s += summary.frames[f].seconds;
      }
      const size_t later = std::max<size_t>(1, summary.frames.size() - 1);
      std::printf(
          "frames       %zu: after frame 0 %.1f s per frame, largest delta %.3f MB, last "
          "frame held-out %.2f dB (subject %.2f dB)\n",
          summary.frames.size(), later_s / later, largest, summary.frames.back().heldout_psnr_db,
          summary.frames.back().heldout_psnr_fg_db);
    }
    std::printf("model: %s\nreport: %s\n", out.c_str(), ReportWhere(out, report).c_str());
    EndCommand(summary, "training");
  });
}

const bool kSplatMergeRegistered = [] {
  RunMergers()["train splat"] = [](const std::filesystem::path& out, Report* report) -> Summary {
    return MergeSplatFrames(out, report);
  };
  return true;
}();

// The methods `train` offers, as registered (nvol, rerender, splat), for its error lines.
std::string TrainingMethods(const CLI::App* train, const char* separator) {
  std::vector<std::string> names;
  for (const CLI::App* method : train->get_subcommands({})) names.push_back(method->get_name());
  std::sort(names.begin(), names.end());
  std::string joined;
  for (const auto& name : names) joined += (joined.empty() ? "" : separator) + name;
  return joined;
}

void AddTrainCommand(CLI::App& app) {
  auto* train = app.add_subcommand(
      "train",
      "Learn an avatar from a calibrated take: `train nvol`, `train rerender` or "
      "`train splat`");
  // A word that names no method reaches `train` itself: it ends with one line naming it and the
  // methods there are. The methods inherit this and refuse each other's flags themselves
  // (RefuseForeignFlags).
  train->allow_extras();
  AddSplatCommand(train);
  train->parse_complete_callback([train] {
    if (!train->get_subcommands().empty()) return;  // the method refuses what is not its own
    const std::vector<std::string> extras = train->remaining();
    if (extras.empty())
      Fail("train needs a method: holocap train ", TrainingMethods(train, "|"), " TAKE");
    Fail("unknown training method '", extras.front(), "' (known: ", TrainingMethods(train, ", "),
         ")");
  });
}

#if HOLOCAP_WITH_NEURAL

// The demo's short orbit of a trained model (context.out/method) into its orbit.mp4, its speed
// added to `metrics` (stored under the method's name); training's state stands unless playback
// failed.
Summary DemoOrbit(const std::string& method, const Summary& trained, nlohmann::json metrics,
                  DemoContext& context) {
  const std::filesystem::path model_dir = context.out / method;
  auto model = OpenModel(model_dir);
  OrbitOptions orbit;
  orbit.views = 24;
  orbit.width = 256;
  orbit.height = 256;
  PlaybackOptions playback;
  playback.out = model_dir / "orbit.mp4";
  PlaybackSummary rendered = RenderPath(*model, OrbitPath(*model, orbit), playback);
  metrics["orbit"] = playback.out.string();
  metrics["render_fps_256"] = rendered.render_fps;
  metrics["samples_per_ray"] = rendered.samples_per_ray;
  context.report->metrics()[method] = metrics;
  std::printf("[demo] %s orbit: %s -> %s\n\n", method.c_str(), rendered.message.c_str(),
              playback.out.c_str());
  Summary stage = trained;
  if (!rendered.IsUsable()) stage = rendered;
  stage.message = trained.message + "; " + rendered.message;
  return stage;
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
  Report report("train nvol");
  NeuralVolumeSummary summary = TrainNeuralVolume(context.take, model_dir, options, &report);
  std::printf("[demo] nvol: %s\n", summary.message.c_str());
  nlohmann::json metrics = {{"iterations", summary.iterations},
                            {"seconds", summary.seconds},
                            {"first_loss", summary.first_loss},
                            {"last_loss", summary.last_loss},
                            {"heldout_psnr_db", summary.heldout_psnr_db},
                            {"heldout_psnr_fg_db", summary.heldout_psnr_fg_db}};
  if (!summary.IsUsable()) {
    context.report->metrics()["nvol"] = metrics;
    return summary;
  }
  return DemoOrbit("nvol", summary, metrics, context);
}

// The demo's splats: frame 0 of the demo take, seeded from a reconstruction built without the
// held-out cameras, half a minute of training, then the same short orbit as Neural Volumes'.
Summary TrainDemoSplats(DemoContext& context) {
  SplatOptions options;
  options.image_width = 160;
  options.minutes = 0.5;
  options.eval_every_s = 10;
  options.take.last_frame = 1;
  const std::filesystem::path model_dir = context.out / "splat";
  Report report("train splat");
  SplatSummary summary = TrainSplats(context.take, model_dir, options, &report);
  std::printf("[demo] splat: %s\n", summary.message.c_str());
  nlohmann::json metrics = {{"iterations", summary.iterations},
                            {"seconds", summary.seconds},
                            {"gaussians", summary.gaussians},
                            {"megabytes", summary.megabytes},
                            {"heldout_psnr_db", summary.heldout_psnr_db},
                            {"heldout_psnr_fg_db", summary.heldout_psnr_fg_db},
                            {"background_psnr_fg_db", summary.background_psnr_fg_db}};
  if (!summary.IsUsable()) {
    context.report->metrics()["splat"] = metrics;
    return summary;
  }
  return DemoOrbit("splat", summary, metrics, context);
}

#endif  // HOLOCAP_WITH_NEURAL

}  // namespace

HOLOCAP_COMMAND(60, AddTrainCommand);
HOLOCAP_LIBTORCH_COMMAND(61, "train nvol",
                         "Neural Volumes: an RGBA voxel grid decoded per frame, ray-marched",
                         FillNvolCommand);
HOLOCAP_LIBTORCH_COMMAND(62, "train rerender",
                         "Neural rerendering (LookinGood): a U-Net that repairs renders of the "
                         "reconstruction, trained on witness cameras the reconstruction never saw",
                         FillRerenderCommand);
#if HOLOCAP_WITH_NEURAL
HOLOCAP_DEMO_STAGE(40, "nvol", TrainDemoAvatar);
HOLOCAP_DEMO_STAGE(45, "splat", TrainDemoSplats);
#endif

}  // namespace holocap
