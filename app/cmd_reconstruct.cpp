// holocap reconstruct: meshes per frame set from a calibrated take (visual hull, depth fusion
// or multi-view stereo), plus the reconstruction stage of `holocap demo`.
#include <cmath>
#include <cstdio>
#include <sstream>

#include "app/commands.h"
#include "app/options.h"
#include "core/error.h"
#include "core/report.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

namespace {

struct ReconstructArgs {
  std::string take;
  std::string out;
  bool overwrite = false;
  TakeSelectionFlags selection;
  SceneFlags scene;
  std::vector<std::string> heldout;
  std::string method = "auto";
  std::string silhouette_morphology = "auto";
  std::string voxel;
  std::string simplify;
  int conservative = 0;
  int stereo_views = MvsOptions().max_reference_views;
  int threads = 0;
  bool no_glb = false;
  bool no_atlas = false;
  bool no_sweep = false;
  bool no_completion = false;
  std::string shard;
  bool redo = false;
};

void PrintSummary(const ReconstructionSummary& summary, const Report& report) {
  for (const FrameResult& f : summary.frames) {
    std::printf("  set %06lld: %-11s %7lld vertices %7lld triangles %6.2f s",
                static_cast<long long>(f.set), ToString(f.termination),
                static_cast<long long>(f.vertices), static_cast<long long>(f.faces), f.seconds);
    if (f.metrics.contains("gt")) {
      std::printf("  chamfer %.2f mm  F@5mm %.3f", f.metrics["gt"]["chamfer_mm"].get<double>(),
                  f.metrics["gt"]["fscore_5mm"].get<double>());
    }
    std::printf("\n");
    if (f.metrics.contains("heldout_iou")) {
      for (auto& [name, iou] : f.metrics["heldout_iou"].items())
        std::printf("    held-out %s: IoU %.4f\n", name.c_str(), iou.get<double>());
    }
  }
  const auto& metrics = report.json()["metrics"];
  if (metrics.contains("gt") && metrics["gt"].contains("voxel_sweep")) {
    for (const auto& point : metrics["gt"]["voxel_sweep"]) {
      std::printf("  voxel %5.1f mm: %6.2f s/frame, chamfer %.2f mm\n",
                  point["voxel_mm"].get<double>(), point["seconds"].get<double>(),
                  point["chamfer_mm"].get<double>());
    }
  }
  std::printf("reconstructed in %.1f s\n", summary.seconds);
}

void AddReconstructCommand(CLI::App& app) {
  auto* command = app.add_subcommand(
      "reconstruct",
      "Meshes per frame set from a calibrated take: visual hull, TSDF fusion of depth, or "
      "multi-view stereo; PLY and textured glTF into TAKE/recon/");
  auto args = std::make_shared<ReconstructArgs>();
  command->add_option("take", args->take, "The take directory")->required();
  command->add_option("--out", args->out, "Output directory (default TAKE/recon)");
  AddOverwriteFlag(command, &args->overwrite);
  AddTakeSelectionFlags(command, &args->selection);
  command->add_option("--method", args->method, "auto (depth -> tsdf, else mvs), hull, tsdf or mvs")
      ->capture_default_str();
  command
      ->add_option("--silhouette-morphology", args->silhouette_morphology,
                   "Thresholded (otsu, threshold) silhouettes: auto (the smallest closing that "
                   "makes the views' silhouettes agree through their hull, measured on the first "
                   "frame set; none where the boundary is clean), recipe (Middlebury's dilate 10, "
                   "erode 7 at 640 px) or none")
      ->capture_default_str();
  command->add_option("--voxel", args->voxel,
                      "Voxel size (4mm, 0.5cm, 0.004; default: implied by the bounds and lenses)");
  AddSceneFlags(command, &args->scene);
  command
      ->add_option("--heldout-names", args->heldout,
                   "Colour cameras never reconstructed from (comma-separated); the mesh's "
                   "silhouette in each is scored against its own (IoU)")
      ->delimiter(',');
  command
      ->add_option("--conservative", args->conservative,
                   "Silhouettes the hull may ignore per point (1 tolerates one bad camera)")
      ->capture_default_str();
  command->add_option("--simplify", args->simplify,
                      "Vertex-clustering cell for simplification (e.g. 8mm)");
  command
      ->add_option("--stereo-views", args->stereo_views,
                   "Multi-view stereo searches the depth of at most this many views, spread over "
                   "the directions they see the subject from (every view is still matched "
                   "against); 0: every view")
      ->capture_default_str();
  command->add_option("--threads", args->threads, "Threads (0: all cores)")->capture_default_str();
  command->add_option("--shard", args->shard,
                      "Do task K of N of the run (K from 0): the K-th of N contiguous blocks of "
                      "its frame sets (those --frames selects); the first task plans the run "
                      "into OUT/plan, the others read it; report.json is merged when every "
                      "frame is done (holocap report OUT --merge)");
  command->add_flag("--redo", args->redo,
                    "Reconstruct frame sets whose outputs are complete from an earlier run too");
  command->add_flag("--no-glb", args->no_glb, "Write PLY only");
  command->add_flag("--no-atlas", args->no_atlas, "Vertex colours only, no texture atlas");
  command->add_flag("--no-sweep", args->no_sweep,
                    "Skip the voxel-size sweep on takes with ground truth");
  command->add_flag(
      "--no-completion", args->no_completion,
      "TSDF: mesh only what the depth sensors saw (no completion from the visual hull)");
  NameFieldFlags(command, {{"tolerated_bad_views", "--conservative"},
                           {"simplify_cell_m", "--simplify"},
                           {"max_reference_views", "--stereo-views"}});
  command->callback([args] {
    ReconstructionOptions options;
    options.method = ReconstructionMethodFromString(args->method);
    options.silhouette_morphology = SilhouetteMorphologyFromString(args->silhouette_morphology);
    if (!args->voxel.empty()) options.voxel_m = ParseLength(args->voxel, "--voxel");
    TakeSelection selection = args->selection.Parse();
    args->scene.Apply(&selection);
    selection.heldout = args->heldout;
    options.hull.tolerated_bad_views = args->conservative;
    if (!args->simplify.empty())
      options.meshing.simplify_cell_m = ParseLength(args->simplify, "--simplify");
    options.mvs.max_reference_views = args->stereo_views;
    options.threads = args->threads;
    options.write_glb = !args->no_glb;
    options.texture.atlas = !args->no_atlas;
    if (args->no_sweep) options.sweep_voxels_m.clear();
    options.tsdf_hull_completion = !args->no_completion;
    if (!args->shard.empty()) options.tasks.shard = Shard::Parse(args->shard);
    options.tasks.redo = args->redo;
    const OutputDirectory claimed = OutputDirectory::Claim(
        args->out.empty() ? std::filesystem::path(args->take) / "recon"
                          : std::filesystem::path(args->out),
        {"reconstruct", args->overwrite, {}, !options.tasks.shard.whole(), args->take});
    const std::filesystem::path& out = claimed.path();
    Report report("reconstruct");
    report.SetFailureDestination(TaskReportPath(out, options.tasks.shard));
    ReconstructionSummary summary = ReconstructTake(args->take, selection, out, options, &report);
    PrintSummary(summary, report);
    std::printf("meshes and report: %s\n", out.c_str());
    EndCommand(summary, "reconstruction");
  });
}

Summary ReconstructDemoTake(DemoContext& context) {
  ReconstructionOptions options;
  options.sweep_voxels_m = {0.008};
  Report report("reconstruct");
  const std::filesystem::path out = context.out / "recon";
  ReconstructionSummary summary =
      ReconstructTake(context.take, TakeSelection{}, out, options, &report);
  PrintSummary(summary, report);
  context.report->metrics()["reconstruct"] = {{"method", summary.plan["method"]},
                                              {"cameras", summary.plan["cameras"]},
                                              {"timing", report.json()["metrics"]["timing"]},
                                              {"out", out.string()}};
  if (report.json()["metrics"].contains("gt")) {
    context.report->metrics()["reconstruct"]["gt"] = report.json()["metrics"]["gt"];
  }
  std::printf("[demo] reconstruct: meshes in %s\n\n", out.c_str());
  return summary;
}

}  // namespace

HOLOCAP_COMMAND(50, AddReconstructCommand);
HOLOCAP_DEMO_STAGE(30, "reconstruct", ReconstructDemoTake);

}  // namespace holocap
