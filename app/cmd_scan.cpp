// holocap scan: one moving RGB-D sensor tracked and fused into a textured model.
#include <cstdio>

#include "app/commands.h"
#include "app/options.h"
#include "core/error.h"
#include "core/output.h"
#include "core/report.h"
#include "scan/scan.h"

namespace holocap {

namespace {

struct ScanArgs {
  std::string take;
  std::string out;
  bool overwrite = false;
  TakeSelectionFlags selection;
  SceneFlags scene;
  ScanOptions options;
  std::string voxel;
  bool no_refine = false;
  bool no_glb = false;
};

void PrintScan(const ScanSummary& summary) {
  for (const ScanFrame& f : summary.frames) {
    if (f.state == TrackingState::kTracked || f.state == TrackingState::kFirst) continue;
    std::printf("  set %06lld: %-10s %s\n", static_cast<long long>(f.set), ToString(f.state),
                f.why.c_str());
  }
  std::printf(
      "%lld frames: %lld tracked, %lld degenerate, %lld lost, %lld fused; %lld keyframes, "
      "%lld loop edges\n",
      static_cast<long long>(summary.frames.size()), static_cast<long long>(summary.tracked),
      static_cast<long long>(summary.degenerate), static_cast<long long>(summary.lost),
      static_cast<long long>(summary.fused), static_cast<long long>(summary.keyframes),
      static_cast<long long>(summary.loops));
  std::printf(
      "tracking %.2f s + fusion %.2f s: %.1f frames/s (%.1f ms of CPU a frame); mesh %lld "
      "vertices\n",
      summary.tracking_seconds, summary.fusion_seconds, summary.frames_per_second,
      1e3 * summary.cpu_seconds_per_frame, static_cast<long long>(summary.vertices));
  if (summary.errors) {
    std::printf(
        "against the true trajectory (%lld frames): ATE RMSE %.2f cm (max %.2f cm), "
        "RPE %.2f mm / %.3f deg per frame\n",
        static_cast<long long>(summary.errors->matched), 100 * summary.errors->ate_rmse_m,
        100 * summary.errors->ate_max_m, 1e3 * summary.errors->rpe_trans_m,
        summary.errors->rpe_rot_deg);
  }
  if (summary.metrics.contains("lighting")) {
    const auto& light = summary.metrics["lighting"];
    if (light["observed"].get<bool>()) {
      std::printf("light: %.2f of the ambient, log-intensity residual %.3f (%.3f unlit)\n",
                  light["strength"].get<double>(), light["rms_lit"].get<double>(),
                  light["rms_flat"].get<double>());
    } else {
      std::printf("light: none found (%s)\n", light["why"].get<std::string>().c_str());
    }
  }
}

void AddScanCommand(CLI::App& app) {
  auto* command = app.add_subcommand(
      "scan",
      "Track one moving RGB-D sensor (ICP + photometric, frame to model) and fuse a textured "
      "model: TAKE/scan/{trajectory.tum, mesh.ply, mesh.glb, report.json}");
  auto args = std::make_shared<ScanArgs>();
  ScanOptions& o = args->options;
  command->add_option("take", args->take, "The take directory")->required();
  command->add_option("--out", args->out, "Output directory (default TAKE/scan)");
  AddOverwriteFlag(command, &args->overwrite);
  AddTakeSelectionFlags(command, &args->selection);
  AddSceneFlags(command, &args->scene);
  command->add_option("--voxel", args->voxel, "TSDF voxel (e.g. 6mm)");
  command
      ->add_option("--volume-side", o.volume_side_m,
                   "Side of the cube scanned around what the first frame sees (metres), "
                   "when no --bounds")
      ->capture_default_str();
  command->add_option("--depth-max", o.depth_max_m, "Farthest depth tracked and fused (metres)")
      ->capture_default_str();
  command
      ->add_option("--photometric-weight", o.photometric_weight_m,
                   "Metres of point-to-plane error one full-scale intensity step weighs (0: ICP "
                   "only)")
      ->capture_default_str();
  command->add_option("--max-lost", o.max_lost_frames, "Lost frames in a row that end the scan")
      ->capture_default_str();
  command
      ->add_option("--max-lost-fraction", o.max_lost_fraction,
                   "Fraction of lost frames above which the scan ends DEGENERATE")
      ->capture_default_str();
  command
      ->add_option("--light-views", o.light_views,
                   "Fused frames whose colours give the scan's light and albedo")
      ->capture_default_str();
  command->add_flag("--turn", o.subject_turns,
                    "The subject turned before a still sensor: the floor is left out and the "
                    "light found");
  command->add_flag("--no-refine", args->no_refine, "No keyframe pose graph at the end");
  command->add_flag("--no-glb", args->no_glb, "Write the PLY only (no texture)");
  command->add_option("--threads", o.threads, "Threads (0: all cores)")->capture_default_str();
  NameFieldFlags(command, {{"max_lost_frames", "--max-lost"}});
  command->callback([args] {
    ScanOptions options = args->options;
    if (!args->voxel.empty()) options.voxel_m = ParseLength(args->voxel, "--voxel");
    if (args->no_refine) options.refine_poses = false;
    if (args->no_glb) options.write_glb = false;
    options.Check();
    TakeSelection selection = args->selection.Parse();
    args->scene.Apply(&selection);
    const OutputDirectory claimed =
        OutputDirectory::Claim(args->out.empty() ? std::filesystem::path(args->take) / "scan"
                                                 : std::filesystem::path(args->out),
                               {"scan", args->overwrite, {}});
    const std::filesystem::path& out = claimed.path();
    Report report("scan");
    report.SetFailureDestination(out / "report.json");
    const ScanSummary summary = ScanTake(args->take, selection, out, options, &report);
    // Nothing fused (no frame had depth to start a model): the input cannot be scanned, and
    // the one error line says why (report.json holds every frame's reason).
    if (summary.fused == 0) FailUnlessUsable(summary, "scan");
    PrintScan(summary);
    std::printf("trajectory, mesh and report: %s\n", out.c_str());
    EndCommand(summary, "scan");
  });
}

}  // namespace

HOLOCAP_COMMAND(52, AddScanCommand);

}  // namespace holocap
