// Captures a user brings, as simulator variants: each is simulated on studio8 and
// reconstructed with reconstruct's defaults (no bounds, voxel, up axis or silhouette threshold;
// what `holocap reconstruct TAKE --no-sweep --no-glb` does), and the table shows the plan the
// take got (bounds, up axis, silhouette source, voxel), the termination, the quality against the
// truth (mean Chamfer over the frame sets, in the take's millimetres, and as a multiple of the
// plan's voxel) and the time. Each variant stands for a take another tool recorded and
// calibrated in its own axes and units (holocap's own calibration always gives z up, metres), so
// the simulation's true cameras stand in for that tool's calibration here, asked for
// (--ground-truth-cameras) and said in the table's head.
// Usage: variants_bench [size=320] [frames=2] [threads=2] [work_dir=/tmp/holocap-variants-bench]
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "core/error.h"
#include "reconstruction/reconstruction.h"
#include "sim/sim.h"

namespace fs = std::filesystem;
using namespace holocap;

namespace {

struct Variant {
  std::string name;
  std::string flags;  // `holocap sim` flags, as the table prints them
  SimOptions options;
};

double Now() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

std::vector<Variant> Variants(int size, int frames, int threads) {
  SimOptions base;
  base.image_width = size;
  base.seed = 3;
  base.threads = threads;
  base.frames = frames;
  auto with_plate = [&](SimOptions o) {
    o.clean_plate_frames = 1;
    o.frames = frames + 1;
    return o;
  };
  SimOptions plate = with_plate(base);
  std::vector<Variant> variants;
  auto add = [&](const std::string& name, const std::string& flags, SimOptions o) {
    variants.push_back({name, flags, o});
  };
  add("studio", "--clean-plate 1", plate);
  SimOptions o = plate;
  o.world_scale = 0.05;
  add("scale", "--clean-plate 1 --world-scale 0.05", o);
  o = plate;
  o.color_only = true;
  add("ring", "--clean-plate 1 --color-only", o);
  o.world_scale = 0.05;
  add("ring-scale", "--clean-plate 1 --color-only --world-scale 0.05", o);
  o = plate;
  o.up = -Eigen::Vector3d::UnitY();
  add("up-y", "--clean-plate 1 --up -y", o);
  add("no-plate", "", base);
  o = base;
  o.subject_albedo = 0.5;
  o.background_albedo = 0.1;
  add("dark", "--dark", o);
  o = plate;
  o.subject_albedo = 0.5;
  o.background_albedo = 0.1;
  add("dark-plate", "--clean-plate 1 --dark", o);
  o = base;
  o.alpha = true;
  add("alpha", "--alpha", o);
  o = plate;
  o.alpha = true;
  add("alpha-plate", "--clean-plate 1 --alpha", o);
  // The three captures as the simulator can stage them.
  o = base;
  o.color_only = true;
  o.world_scale = 0.05;
  o.subject_albedo = 0.5;
  o.background_albedo = 0.1;
  add("object-ring", "--color-only --world-scale 0.05 --dark", o);
  o = base;
  o.color_only = true;
  o.up = -Eigen::Vector3d::UnitY();
  add("dome-y-down", "--color-only --up -y", o);
  o = base;
  o.color_only = true;
  o.alpha = true;
  add("alpha-object", "--color-only --alpha", o);
  return variants;
}

std::string Axis(const nlohmann::json& up) {
  const char* names = "xyz";
  for (int i = 0; i < 3; ++i) {
    const double v = up[i].get<double>();
    if (std::abs(std::abs(v) - 1) < 1e-9) return Cat(v > 0 ? "+" : "-", names[i]);
  }
  return up.dump();
}

std::string BoundsSize(const nlohmann::json& box) {
  char text[64];
  std::snprintf(text, sizeof(text), "%.3gx%.3gx%.3g",
                box["max"][0].get<double>() - box["min"][0].get<double>(),
                box["max"][1].get<double>() - box["min"][1].get<double>(),
                box["max"][2].get<double>() - box["min"][2].get<double>());
  return text;
}

// Runs one variant and returns its row of the table.
std::string RunVariant(const Variant& variant, const fs::path& work, int threads) {
  const fs::path take = work / variant.name;
  std::error_code ignored;
  fs::remove_all(take, ignored);
  SimulateTake(variant.options, take);
  ReconstructionOptions options;
  options.sweep_voxels_m.clear();
  options.write_glb = false;
  options.threads = threads;
  Report report("reconstruct");
  const double start = Now();
  std::string termination, quality = "-", plan = "-";
  try {
    TakeSelection selection;
    selection.ground_truth_cameras = true;  // another tool's calibration, in its own world
    const ReconstructionSummary summary =
        ReconstructTake(take, selection, take / "recon", options, &report);
    termination = ToString(summary.termination);
    const nlohmann::json& p = summary.plan;
    const double voxel_mm = 1000 * p["voxel"]["m"].get<double>();
    plan = Cat(BoundsSize(p["bounds"]["box"]), " m ", Axis(p["up"]["axis"]), " ",
               p["silhouettes"]["source"].get<std::string>(), " ", voxel_mm, "mm ",
               p.value("method", "?"));
    const nlohmann::json& metrics = report.json()["metrics"];
    if (metrics.contains("gt") && metrics["gt"].contains("chamfer_mm")) {
      const double chamfer = metrics["gt"]["chamfer_mm"].get<double>();
      char text[64];
      std::snprintf(text, sizeof(text), "%.3f mm (%.2f vox)", chamfer, chamfer / voxel_mm);
      quality = text;
    }
  } catch (const Error& e) {
    termination = Cat("ERROR: ", e.what());
  }
  char row[512];
  std::snprintf(row, sizeof(row), "%-12s %-46s %-50s %-11s %-20s %6.1f", variant.name.c_str(),
                ("sim " + variant.flags).c_str(), plan.c_str(),
                termination.substr(0, termination.rfind("ERROR", 0) == 0 ? 60 : 11).c_str(),
                quality.c_str(), Now() - start);
  return row;
}

}  // namespace

int main(int argc, char** argv) {
  const int size = argc > 1 ? std::atoi(argv[1]) : 320;
  const int frames = argc > 2 ? std::atoi(argv[2]) : 2;
  const int threads = argc > 3 ? std::atoi(argv[3]) : 2;
  const fs::path work = argc > 4 ? fs::path(argv[4]) : fs::path("/tmp/holocap-variants-bench");
  fs::create_directories(work);
  std::printf(
      "variants_bench: studio8 at %d px, %d frame set(s) reconstructed, seed 3, %d threads.\n"
      "Each row: holocap sim --rig studio8 --size %d --seed 3 --frames N FLAGS --out TAKE, then\n"
      "holocap reconstruct TAKE --ground-truth-cameras --no-sweep --no-glb (no bounds, voxel, up\n"
      "or threshold given; the true cameras stand for another tool's calibration in its own "
      "axes).\n"
      "plan: bounds size, up axis, silhouette source, voxel, method; quality: mean Chamfer to the\n"
      "true mesh in the take's mm (and in the plan's voxels: variants_test calls a surface within "
      "2\n"
      "correct); time: s.\n\n",
      size, frames, threads, size);
  char header[256];
  std::snprintf(header, sizeof(header), "%-12s %-46s %-50s %-11s %-20s %6s", "variant", "command",
                "plan", "termination", "quality", "time");
  // Each row as it ends (between the pipeline's own lines), then the whole table.
  std::vector<std::string> rows;
  for (const Variant& variant : Variants(size, frames, threads)) {
    try {
      rows.push_back(RunVariant(variant, work, threads));
    } catch (const Error& e) {
      rows.push_back(Cat(variant.name, ": simulation failed: ", e.what()));
    }
    std::printf("%s\n", rows.back().c_str());
    std::fflush(stdout);
  }
  std::printf("\n%s\n", header);
  for (const std::string& row : rows) std::printf("%s\n", row.c_str());
  return 0;
}
