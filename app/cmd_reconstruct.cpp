// holocap reconstruct: meshes per frame set from a calibrated take (visual hull, depth fusion
// or multi-view stereo), plus the reconstruction stage of `holocap demo`.
#include <cmath>
#include <cstdio>
#include <sstream>

#include "app/commands.h"
#include "core/error.h"
#include "core/report.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

Box ParseBounds(const std::string& text, const char* option) {
  std::stringstream in(text);
  std::vector<double> v;
  std::string item;
  while (std::getline(in, item, ',')) {
    try {
      v.push_back(std::stod(item));
    } catch (const std::exception&) {
      Fail(option, " must be six numbers xmin,ymin,zmin,xmax,ymax,zmax (metres), got '", text, "'");
    }
  }
  if (v.size() != 6) Fail(option, " must be six numbers xmin,ymin,zmin,xmax,ymax,zmax (metres), got '", text, "'");
  Box box;
  box.min = Eigen::Vector3d(v[0], v[1], v[2]);
  box.max = Eigen::Vector3d(v[3], v[4], v[5]);
  if (!box.valid()) Fail(option, ": max must exceed min on every axis");
  return box;
}

namespace {

// "4mm", "4 mm", "0.4cm", "0.004m" or a bare number of metres.
double ParseLength(const std::string& text, const char* what) {
  size_t used = 0;
  double value = 0;
  try {
    value = std::stod(text, &used);
  } catch (const std::exception&) {
    Fail(what, " must be a length such as 4mm or 0.004, got '", text, "'");
  }
  std::string unit = text.substr(used);
  unit.erase(0, unit.find_first_not_of(' '));
  double scale = unit.empty() || unit == "m" ? 1 : unit == "cm" ? 1e-2 : unit == "mm" ? 1e-3 : -1;
  if (scale < 0) Fail(what, ": unknown unit '", unit, "' in '", text, "' (use m, cm or mm)");
  if (!(value > 0) || !std::isfinite(value)) Fail(what, " must be > 0, got '", text, "'");
  return value * scale;
}

// "a:b", "a:" or "a" (one frame set), counted after the clean plate.
void ParseFrames(const std::string& text, int64_t* first, int64_t* last) {
  if (text.empty()) return;
  auto colon = text.find(':');
  try {
    if (colon == std::string::npos) {
      *first = std::stoll(text);
      *last = *first + 1;
      return;
    }
    std::string a = text.substr(0, colon), b = text.substr(colon + 1);
    *first = a.empty() ? 0 : std::stoll(a);
    *last = b.empty() ? -1 : std::stoll(b);
  } catch (const std::exception&) {
    Fail("--frames must be A:B, A: or A, got '", text, "'");
  }
}

struct ReconstructArgs {
  std::string take;
  std::string out;
  std::string frames;
  std::string method = "auto";
  std::string voxel = "4mm";
  std::string bounds;
  std::string simplify;
  std::string silhouettes = "background";
  int64_t clean_plate = -1;
  int conservative = 0;
  int threads = 0;
  bool no_glb = false;
  bool no_atlas = false;
  bool no_sweep = false;
  bool no_completion = false;
};

void PrintSummary(const ReconstructionSummary& summary, const Report& report) {
  for (const FrameResult& f : summary.frames) {
    std::printf("  set %06lld: %-11s %7lld vertices %7lld triangles %6.2f s", static_cast<long long>(f.set),
                ToString(f.termination), static_cast<long long>(f.vertices), static_cast<long long>(f.faces),
                f.seconds);
    if (f.metrics.contains("gt")) {
      std::printf("  chamfer %.2f mm  F@5mm %.3f", f.metrics["gt"]["chamfer_mm"].get<double>(),
                  f.metrics["gt"]["fscore_5mm"].get<double>());
    }
    std::printf("\n");
  }
  const auto& metrics = report.json()["metrics"];
  if (metrics.contains("gt") && metrics["gt"].contains("voxel_sweep")) {
    for (const auto& point : metrics["gt"]["voxel_sweep"]) {
      std::printf("  voxel %5.1f mm: %6.2f s/frame, chamfer %.2f mm\n", point["voxel_mm"].get<double>(),
                  point["seconds"].get<double>(), point["chamfer_mm"].get<double>());
    }
  }
  std::printf("%s: %s (%.1f s)\n", ToString(summary.termination), summary.message.c_str(), summary.seconds);
}

void AddReconstructCommand(CLI::App& app) {
  auto* command = app.add_subcommand(
      "reconstruct", "Meshes per frame set from a calibrated take: visual hull, TSDF fusion of depth, or "
                     "multi-view stereo; PLY and textured glTF into TAKE/recon/");
  auto args = std::make_shared<ReconstructArgs>();
  command->add_option("take", args->take, "The take directory")->required();
  command->add_option("--out", args->out, "Output directory (default TAKE/recon)");
  command->add_option("--frames", args->frames, "Frame sets A:B after the clean plate (default: all)");
  command->add_option("--method", args->method, "auto (depth -> tsdf, else mvs), hull, tsdf or mvs")
      ->capture_default_str();
  command->add_option("--voxel", args->voxel, "Voxel size (4mm, 0.5cm, 0.004)")->capture_default_str();
  command->add_option("--bounds", args->bounds, "Capture volume xmin,ymin,zmin,xmax,ymax,zmax in metres "
                                                "(default -1.5,-1.5,0,1.5,1.5,2.5)");
  command->add_option("--clean-plate", args->clean_plate,
                      "Leading frame sets without the subject (default: from the take, else 0)");
  command->add_option("--silhouettes", args->silhouettes,
                      "background (subtract the clean plate) or threshold (bright subject, dark background)")
      ->capture_default_str();
  command->add_option("--conservative", args->conservative,
                      "Silhouettes the hull may ignore per point (1 tolerates one bad camera)")
      ->capture_default_str();
  command->add_option("--simplify", args->simplify, "Vertex-clustering cell for simplification (e.g. 8mm)");
  command->add_option("--threads", args->threads, "Threads (0: all cores)")->capture_default_str();
  command->add_flag("--no-glb", args->no_glb, "Write PLY only");
  command->add_flag("--no-atlas", args->no_atlas, "Vertex colours only, no texture atlas");
  command->add_flag("--no-sweep", args->no_sweep, "Skip the voxel-size sweep on takes with ground truth");
  command->add_flag("--no-completion", args->no_completion,
                    "TSDF: mesh only what the depth sensors saw (no completion from the visual hull)");
  command->callback([args] {
    ReconstructionOptions options;
    options.method = ReconstructionMethodFromString(args->method);
    options.voxel_m = ParseLength(args->voxel, "--voxel");
    ParseFrames(args->frames, &options.first_frame, &options.last_frame);
    if (!args->bounds.empty()) options.bounds = ParseBounds(args->bounds);
    options.clean_plate_frames = args->clean_plate;
    if (args->silhouettes == "threshold") {
      options.silhouette.mode = SilhouetteMode::kThreshold;
    } else if (args->silhouettes != "background") {
      Fail("--silhouettes must be background or threshold, got '", args->silhouettes, "'");
    }
    options.hull.tolerated_bad_views = args->conservative;
    if (!args->simplify.empty()) options.meshing.simplify_cell_m = ParseLength(args->simplify, "--simplify");
    options.threads = args->threads;
    options.write_glb = !args->no_glb;
    options.texture.atlas = !args->no_atlas;
    if (args->no_sweep) options.sweep_voxels_m.clear();
    options.tsdf_hull_completion = !args->no_completion;
    std::filesystem::path out = args->out.empty() ? std::filesystem::path(args->take) / "recon" : std::filesystem::path(args->out);
    Report report("reconstruct");
    ReconstructionSummary summary = ReconstructTake(args->take, out, options, &report);
    PrintSummary(summary, report);
    std::printf("meshes and report: %s\n", out.c_str());
    if (!IsUsable(summary.termination)) Fail("reconstruction failed: ", summary.message);
  });
}

Summary ReconstructDemoTake(DemoContext& context) {
  ReconstructionOptions options;
  options.sweep_voxels_m = {0.008};
  Report report("reconstruct");
  const std::filesystem::path out = context.out / "recon";
  ReconstructionSummary summary = ReconstructTake(context.take, out, options, &report);
  PrintSummary(summary, report);
  context.report->metrics()["reconstruct"] = {{"method", summary.plan["method"]},
                                              {"cameras", summary.plan["cameras"]},
                                              {"timing", report.json()["metrics"]["timing"]},
                                              {"out", out.string()}};
  if (report.json()["metrics"].contains("gt")) {
    context.report->metrics()["reconstruct"]["gt"] = report.json()["metrics"]["gt"];
  }
  std::printf("[demo] reconstruct: meshes in %s\n\n", out.c_str());
  return {summary.termination, summary.message};
}

}  // namespace

HOLOCAP_COMMAND(50, AddReconstructCommand);
HOLOCAP_DEMO_STAGE(30, "reconstruct", ReconstructDemoTake);

}  // namespace holocap
