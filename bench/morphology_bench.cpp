// Thresholded silhouettes' morphology by leave-one-out on every object ring: each view held out
// of a reconstruction with reconstruct's defaults (what `holocap reconstruct TAKE
// --heldout-names VIEW --no-glb --no-sweep --silhouette-morphology M` does) for M = recipe (the
// Middlebury README's dilate 10 / erode 7 at 640 px), auto (the closing measured on the take)
// and none. The mesh's silhouette in the held-out view is scored (IoU) against that view's own
// silhouette as the run makes it (its morphology), against the unclosed Otsu silhouette (one
// reference for every M) and, on simulated takes, against the true silhouette (gt/masks, which
// only scores).
//   dino: Middlebury dinoSparseRing (16 real views, Middlebury's calibration).
//   object-ring: `holocap sim --color-only --world-scale 0.05 --dark --size SIZE --seed 3
//     --frames 1`, calibrated from a board take of the same rig (bench/calibrated_sim.h).
// Usage: morphology_bench [threads=2] [work_dir=/tmp/holocap-morphology-bench] [sets=dino,ring]
//                         [size=320] [morphologies=recipe,auto,none]
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <string>
#include <vector>

#include "bench/calibrated_sim.h"
#include "core/error.h"
#include "core/image.h"
#include "core/mesh.h"
#include "core/take.h"
#include "interop/interop.h"
#include "reconstruction/reconstruction.h"
#include "sim/sim.h"

namespace fs = std::filesystem;
using namespace holocap;

namespace {

struct Score {
  double sum = 0, worst = 1;
  int count = 0;
  void Add(double iou) {
    sum += iou;
    worst = std::min(worst, iou);
    ++count;
  }
  std::string Text() const {
    char text[48];
    std::snprintf(text, sizeof(text), "%.4f / %.4f", count ? sum / count : 0.0, worst);
    return text;
  }
};

struct Row {
  Score own, unclosed, truth;
  std::string choice;
  double seconds = 0;
};

Row LeaveOneOut(const fs::path& take_dir, const fs::path& work, SilhouetteMorphology morphology,
                int threads) {
  const Take take = Take::Open(take_dir);
  SilhouetteOptions unclosed;
  unclosed.mode = SilhouetteMode::kOtsu;
  unclosed.open_px = 0;
  unclosed.dilate_px = 0;
  unclosed.erode_px = 0;
  Row row;
  for (const StreamInfo& held : take.streams()) {
    TakeSelection selection;
    selection.heldout = {held.name};
    ReconstructionOptions options;
    options.write_glb = false;
    options.sweep_voxels_m.clear();
    options.threads = threads;
    options.silhouette_morphology = morphology;
    Report report("reconstruct");
    const fs::path out =
        work / Cat(take_dir.filename().string(), "-", ToString(morphology)) / held.name;
    const ReconstructionSummary summary =
        ReconstructTake(take_dir, selection, out, options, &report);
    row.seconds += summary.seconds;
    const nlohmann::json& plan = report.json()["plan"];
    if (row.choice.empty() && plan["silhouettes"].contains("morphology"))
      row.choice = plan["silhouettes"]["morphology"]["choice"].get<std::string>();
    double own = 0, against_unclosed = 0, against_truth = 0;
    const int64_t set = take.metadata().value("clean_plate_frames", int64_t{0});
    if (summary.IsUsable()) {
      own = report.json()["metrics"]["heldout_iou_mean"].get<double>();
      const cv::Mat image = take.ReadFrame(static_cast<size_t>(set), held.name);
      const cv::Mat rendered =
          RenderSilhouette(ReadPly(out / "000000.ply"), take.Camera(held.name));
      against_unclosed = MaskIoU(rendered, ExtractSilhouette(image, cv::Mat(), unclosed));
      const fs::path truth = take_dir / "gt" / "masks" / held.name / "000000.png";
      if (fs::exists(truth)) against_truth = MaskIoU(rendered, ReadImage(truth));
    }
    std::printf("  %-6s held out %-11s %-10s own %.4f  unclosed %.4f  truth %.4f  %.1f s\n",
                ToString(morphology), held.name.c_str(), ToString(summary.termination), own,
                against_unclosed, against_truth, summary.seconds);
    std::fflush(stdout);
    row.own.Add(own);
    row.unclosed.Add(against_unclosed);
    if (fs::exists(take_dir / "gt")) row.truth.Add(against_truth);
    if (row.choice.empty()) row.choice = "-";
  }
  row.seconds /= static_cast<double>(take.streams().size());
  return row;
}

void Table(const std::string& name, const fs::path& take_dir, const fs::path& work, int threads,
           const std::string& morphologies, std::vector<std::string>* lines) {
  for (SilhouetteMorphology m :
       {SilhouetteMorphology::kRecipe, SilhouetteMorphology::kAuto, SilhouetteMorphology::kNone}) {
    if (morphologies.find(ToString(m)) == std::string::npos) continue;
    const Row row = LeaveOneOut(take_dir, work, m, threads);
    char line[256];
    std::snprintf(line, sizeof(line), "%-12s %-7s %-12s %-16s %-16s %-16s %6.1f", name.c_str(),
                  ToString(m), row.choice.c_str(), row.own.Text().c_str(),
                  row.unclosed.Text().c_str(), row.truth.count ? row.truth.Text().c_str() : "-",
                  row.seconds);
    lines->push_back(line);
  }
}

}  // namespace

int main(int argc, char** argv) {
  const int threads = argc > 1 ? std::atoi(argv[1]) : 2;
  const fs::path work = argc > 2 ? fs::path(argv[2]) : fs::path("/tmp/holocap-morphology-bench");
  const std::string sets = argc > 3 ? argv[3] : "dino,ring";
  const int size = argc > 4 ? std::atoi(argv[4]) : 320;
  const std::string morphologies = argc > 5 ? argv[5] : "recipe,auto,none";
  try {
    fs::create_directories(work);
    std::vector<std::string> lines;
    if (sets.find("ring") != std::string::npos) {
      SimOptions sim;
      sim.image_width = size;
      sim.seed = 3;
      sim.threads = threads;
      sim.frames = 1;
      sim.color_only = true;
      sim.world_scale = 0.05;
      sim.subject_albedo = 0.5;
      sim.background_albedo = 0.1;
      sim.overwrite = true;
      const fs::path take = work / "object-ring";
      SimulateTake(sim, take);
      std::printf("object-ring: %s\n", bench::CalibrateFromBoardTake(sim, take).c_str());
      Table("object-ring", take, work, threads, morphologies, &lines);
    }
    if (sets.find("dino") != std::string::npos) {
      ImportOptions import;
      import.format = InteropFormat::kMiddlebury;
      import.overwrite = true;
      const fs::path take = work / "dino";
      ImportTake(fs::path(HOLOCAP_TEST_DATA_DIR) / "middlebury" / "dinoSparseRing", take, import);
      Table("dino", take, work, threads, morphologies, &lines);
    }
    std::printf(
        "\nleave-one-out held-out IoU, mean / worst over the views; own: against the view's "
        "silhouette with the row's morphology; unclosed: against its Otsu silhouette without "
        "morphology; truth: against gt/masks; time: s per run\n");
    std::printf("%-12s %-7s %-12s %-16s %-16s %-16s %6s\n", "set", "asked", "chosen", "own",
                "unclosed", "truth", "time");
    for (const std::string& line : lines) std::printf("%s\n", line.c_str());
  } catch (const std::exception& e) {
    std::fprintf(stderr, "morphology_bench: %s\n", e.what());
    return 1;
  }
  return 0;
}
