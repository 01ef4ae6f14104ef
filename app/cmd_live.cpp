// holocap live: one fixed RGB-D sensor's frames completed by a scan of the subject.
#include <cstdio>

#include "app/commands.h"
#include "app/options.h"
#include "core/error.h"
#include "core/output.h"
#include "core/report.h"
#include "live/live.h"

namespace holocap {

namespace {

struct LiveArgs {
  std::string take;
  std::string scan;
  std::string out;
  bool overwrite = false;
  TakeSelectionFlags selection;
  SceneFlags scene;
  LiveOptions options;
  bool rigid_only = false;
  bool carry = false;
  bool no_relight = false;
  bool no_glb = false;
};

void PrintLive(const LiveSummary& summary) {
  for (const LiveFrame& f : summary.frames) {
    if (f.state == LiveState::kComposed) continue;
    std::printf("  set %06lld: %-9s %s\n", static_cast<long long>(f.set), ToString(f.state),
                f.why.c_str());
  }
  double inliers = 0, residual = 0, deformation = 0;
  for (const LiveFrame& f : summary.frames) {
    if (f.state != LiveState::kComposed) continue;
    inliers += f.inlier_fraction;
    residual += f.residual_m;
    deformation += f.deformation_rms_m;
  }
  const double n = static_cast<double>(std::max<int64_t>(1, summary.composed));
  std::printf(
      "%s + %s: %lld frames, %lld composed, %lld without depth, %lld refused; mean inliers "
      "%.1f %%, residual %.2f mm, deformation %.1f mm RMS; %.1f s\n",
      summary.depth_sensor.c_str(), summary.color_sensor.c_str(),
      static_cast<long long>(summary.frames.size()), static_cast<long long>(summary.composed),
      static_cast<long long>(summary.no_depth), static_cast<long long>(summary.refused),
      100 * inliers / n, 1e3 * residual / n, 1e3 * deformation / n, summary.seconds);
}

void AddLiveCommand(CLI::App& app) {
  auto* command = app.add_subcommand(
      "live",
      "Complete each frame of one fixed RGB-D sensor with a scan of the subject (rigid + "
      "non-rigid alignment): OUT/recon/<set>.{ply,glb}, report.json");
  auto args = std::make_shared<LiveArgs>();
  LiveOptions& o = args->options;
  command->add_option("take", args->take, "The take of the fixed sensor")->required();
  command->add_option("--scan", args->scan, "The subject's scan (a `holocap scan` output)")
      ->required();
  command->add_option("--out", args->out, "Output directory (default TAKE/live)");
  AddOverwriteFlag(command, &args->overwrite);
  AddTakeSelectionFlags(command, &args->selection);
  AddSceneFlags(command, &args->scene);
  command->add_option("--gate", o.gate_m, "Pairing distance of the final fit (metres)")
      ->capture_default_str();
  command
      ->add_option("--min-inliers", o.min_inlier_fraction,
                   "Fraction of the scan's visible points that must fit the live surface")
      ->capture_default_str();
  command
      ->add_option("--min-explained", o.min_explained_fraction,
                   "Fraction of the live surface joined to the fitted scan that must lie on it "
                   "(a scan of something smaller fits a part of the subject)")
      ->capture_default_str();
  command
      ->add_option("--max-residual", o.max_residual_m,
                   "Largest point-to-plane RMS of a fitting scan (metres)")
      ->capture_default_str();
  command
      ->add_option("--subject-reach", o.subject_reach_m,
                   "Live pixels joined to the fitted subject without a depth jump, within this "
                   "distance of the deformed scan, are the subject too (metres; 0: none)")
      ->capture_default_str();
  command->add_option("--node-spacing", o.node_spacing_m, "Deformation graph spacing (metres)")
      ->capture_default_str();
  command
      ->add_option("--arap-weight", o.arap_weight,
                   "Stiffness of the deformation (as-rigid-as-possible weight)")
      ->capture_default_str();
  command->add_flag("--rigid-only", args->rigid_only, "No non-rigid correction");
  command->add_flag("--carry", args->carry,
                    "Start each frame's deformation from the frame before's, not the scan at rest");
  command->add_flag("--no-relight", args->no_relight,
                    "Compose the scan in the colours it was seen in, not relit in its light");
  command->add_flag("--no-glb", args->no_glb, "Write the PLY meshes only");
  NameFieldFlags(command, {{"min_inlier_fraction", "--min-inliers"},
                           {"min_explained_fraction", "--min-explained"}});
  command->callback([args] {
    LiveOptions options = args->options;
    if (args->rigid_only) options.nonrigid = false;
    if (args->no_glb) options.write_glb = false;
    if (args->carry) options.carry_deformation = true;
    if (args->no_relight) options.relight = false;
    options.Check();
    TakeSelection selection = args->selection.Parse();
    args->scene.Apply(&selection);
    // A bad scan is refused before any output is claimed.
    ReadScanAlbedo(args->scan, ReadScan(args->scan));
    const OutputDirectory claimed =
        OutputDirectory::Claim(args->out.empty() ? std::filesystem::path(args->take) / "live"
                                                 : std::filesystem::path(args->out),
                               {"live", args->overwrite, {args->scan}});
    const std::filesystem::path& out = claimed.path();
    Report report("live");
    report.SetFailureDestination(out / "report.json");
    const LiveSummary summary = LiveTake(args->take, selection, args->scan, out, options, &report);
    PrintLive(summary);
    std::printf("meshes (recon/<set>.ply, .glb) and report: %s\n", out.c_str());
    EndCommand(summary, "live");
  });
}

}  // namespace

HOLOCAP_COMMAND(54, AddLiveCommand);

}  // namespace holocap
