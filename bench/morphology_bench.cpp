// Thresholded silhouettes' morphology by leave-one-out on every object ring: each view held out
// of a reconstruction with reconstruct's defaults (what `holocap reconstruct TAKE
// --heldout-names VIEW --no-glb --no-sweep --silhouette-morphology M` does) for M = recipe (the
// Middlebury README's dilate 10 / erode 7 at 640 px), auto (the closing measured on the
// silhouettes' boundaries) and none. The mesh's silhouette in the held-out view is scored (IoU)
// against:
//   own      that view's silhouette as the run makes it (its row's morphology): the figure
//            reconstruct reports, but each row is scored against its own morphology, so it
//            rewards growth (a hull of grown silhouettes against grown silhouettes);
//   recipe   the view's Otsu silhouette with the recipe's morphology, and
//   unclosed the same without morphology: each favours one row; cross, their mean, favours
//            neither;
//   truth    on simulated takes, the true silhouette (gt/masks: it only scores);
// and, on simulated takes, the share of the true surface inside the mesh (inside), which sees
// the tunnels a view's holes and cracks carve and no silhouette shows, and rewards growth.
// Sets (each calibrated from a board take of the same rig, bench/calibrated_sim.h, except dino):
//   dino         Middlebury dinoSparseRing (16 real views, Middlebury's calibration);
//   ring-dark    `holocap sim --rig studio8 --size SIZE --seed 3 --frames 1 --color-only
//                --world-scale 0.05 --dark` (subject albedo x0.5, room x0.1);
//   ring-ragged  ring-dark with holes and cracks cut into every view's subject (black discs of
//                1-2 px radius and a 2 px line across it, drawn into the frames as a threshold
//                loses a subject's dark patches); the truth is ring-dark's;
//   knot         `holocap sim --rig studio8 --size SIZE --seed 5 --frames 1 --color-only
//                --scene object --world-scale 0.05` with the room x0.15 (the knot on its
//                pedestal: a subject with gaps of its own).
// Usage: morphology_bench [threads=2] [work_dir=/tmp/holocap-morphology-bench]
//                         [sets=dino,ring-dark,ring-ragged,knot] [size=320] [dino_stride=2]
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <map>
#include <random>
#include <string>
#include <vector>

#include <opencv2/imgproc.hpp>

#include "bench/calibrated_sim.h"
#include "core/error.h"
#include "core/image.h"
#include "core/mesh.h"
#include "core/rig_alignment.h"
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
    if (count == 0) return "-";
    char text[48];
    std::snprintf(text, sizeof(text), "%.4f / %.4f", sum / count, worst);
    return text;
  }
};

struct Row {
  Score own, recipe, unclosed, cross, truth, inside;
  std::vector<std::string> choices;  // what each run's plan chose
  std::string note;
};

// The fraction of `points` inside the closed `mesh` (a ray's crossings counted, odd = inside):
// a visual hull holds the subject, and a tunnel that a crack or hole in one view carves through
// it leaves the subject's surface outside, where no other view's silhouette shows it.
double InsideFraction(const Mesh& mesh, const std::vector<Eigen::Vector3d>& points) {
  const Eigen::Vector3d ray = Eigen::Vector3d(0.123, 0.456, 0.881).normalized();
  int64_t inside = 0;
  for (const Eigen::Vector3d& point : points) {
    int crossings = 0;
    for (const Eigen::Vector3i& face : mesh.faces) {
      const Eigen::Vector3d a = mesh.vertices[face[0]].cast<double>();
      const Eigen::Vector3d ab = mesh.vertices[face[1]].cast<double>() - a;
      const Eigen::Vector3d ac = mesh.vertices[face[2]].cast<double>() - a;
      const Eigen::Vector3d p = ray.cross(ac);
      const double det = ab.dot(p);
      if (std::abs(det) < 1e-18) continue;
      const Eigen::Vector3d t = point - a;
      const double u = t.dot(p) / det;
      if (u < 0 || u > 1) continue;
      const Eigen::Vector3d q = t.cross(ab);
      const double v = ray.dot(q) / det;
      if (v < 0 || u + v > 1) continue;
      if (ac.dot(q) / det > 0) ++crossings;
    }
    inside += crossings % 2;
  }
  return points.empty() ? 0 : static_cast<double>(inside) / static_cast<double>(points.size());
}

SilhouetteOptions Otsu(bool recipe) {
  SilhouetteOptions options;
  options.mode = SilhouetteMode::kOtsu;
  options.open_px = 0;
  options.dilate_px = recipe ? 10 : 0;
  options.erode_px = recipe ? 7 : 0;
  options.morphology_width = recipe ? 640 : 0;
  return options;
}

Row LeaveOneOut(const fs::path& take_dir, const fs::path& work, SilhouetteMorphology morphology,
                int threads, int stride) {
  const Take take = Take::Open(take_dir);
  fs::path truth_mesh = take_dir / "gt" / "meshes" / "000000.ply";
  if (!fs::exists(truth_mesh)) truth_mesh = take_dir / "gt" / "meshes" / "static.ply";
  std::vector<Eigen::Vector3d> truth_points;
  if (fs::exists(truth_mesh)) {
    // Into the calibration's world, where the meshes are.
    std::map<std::string, CameraModel> calibrated, truth;
    for (const StreamInfo& stream : take.streams()) {
      calibrated.emplace(stream.name, take.Camera(stream.name));
      truth.emplace(stream.name, take.Camera(stream.name, true));
    }
    const Pose calibrated_from_truth = AlignRigs(truth, calibrated);
    for (const Eigen::Vector3d& point : ReadPly(truth_mesh).SampleSurface(2000, 1))
      truth_points.push_back(calibrated_from_truth * point);
  }
  Row row;
  const std::vector<StreamInfo>& streams = take.streams();
  for (size_t index = 0; index < streams.size(); index += static_cast<size_t>(stride)) {
    const StreamInfo& held = streams[index];
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
    const nlohmann::json& plan = report.json()["plan"];
    row.choices.push_back(plan["silhouettes"].contains("morphology")
                              ? plan["silhouettes"]["morphology"]["choice"].get<std::string>()
                              : "-");
    double own = 0, against_recipe = 0, against_unclosed = 0, against_truth = 0, inside = 0;
    if (summary.IsUsable()) {
      own = report.json()["metrics"]["heldout_iou_mean"].get<double>();
      const int64_t set = take.metadata().value("clean_plate_frames", int64_t{0});
      const cv::Mat image = take.ReadFrame(static_cast<size_t>(set), held.name);
      const Mesh mesh = ReadPly(out / "000000.ply");
      const cv::Mat rendered = RenderSilhouette(mesh, take.Camera(held.name));
      inside = InsideFraction(mesh, truth_points);
      against_recipe = MaskIoU(rendered, ExtractSilhouette(image, cv::Mat(), Otsu(true)));
      against_unclosed = MaskIoU(rendered, ExtractSilhouette(image, cv::Mat(), Otsu(false)));
      const fs::path truth = take_dir / "gt" / "masks" / held.name / "000000.png";
      if (fs::exists(truth)) against_truth = MaskIoU(rendered, ReadImage(truth));
    }
    std::printf(
        "  %-6s held out %-11s %-10s %-14s own %.4f  recipe %.4f  unclosed %.4f  truth %.4f  "
        "inside %.4f  %.1f s\n",
        ToString(morphology), held.name.c_str(), ToString(summary.termination),
        row.choices.back().c_str(), own, against_recipe, against_unclosed, against_truth, inside,
        summary.seconds);
    std::fflush(stdout);
    row.own.Add(own);
    row.recipe.Add(against_recipe);
    row.unclosed.Add(against_unclosed);
    row.cross.Add(0.5 * (against_recipe + against_unclosed));
    if (fs::exists(take_dir / "gt")) row.truth.Add(against_truth);
    if (!truth_points.empty()) row.inside.Add(inside);
  }
  return row;
}

std::string Choices(const std::vector<std::string>& choices) {
  std::vector<std::string> distinct = choices;
  std::sort(distinct.begin(), distinct.end());
  distinct.erase(std::unique(distinct.begin(), distinct.end()), distinct.end());
  std::string text;
  for (const std::string& choice : distinct) text += (text.empty() ? "" : "|") + choice;
  return text;
}

void Table(const std::string& name, const fs::path& take_dir, const fs::path& work, int threads,
           int stride, std::vector<std::string>* lines) {
  const Row automatic = LeaveOneOut(take_dir, work, SilhouetteMorphology::kAuto, threads, stride);
  Row none;
  if (Choices(automatic.choices) == "none") {
    // The same options as auto's runs, which chose none in every one: the same meshes.
    none = automatic;
    none.note = "(auto's runs)";
  } else {
    none = LeaveOneOut(take_dir, work, SilhouetteMorphology::kNone, threads, stride);
  }
  const Row recipe = LeaveOneOut(take_dir, work, SilhouetteMorphology::kRecipe, threads, stride);
  const auto line = [&](const char* asked, const Row& row) {
    char text[400];
    std::snprintf(text, sizeof(text), "%-12s %-7s %-5d %-16s %-16s %-16s %-16s %-16s %-35s %s",
                  name.c_str(), asked, row.own.count, Choices(row.choices).c_str(),
                  row.own.Text().c_str(), row.cross.Text().c_str(), row.truth.Text().c_str(),
                  row.inside.Text().c_str(),
                  (row.recipe.Text() + " | " + row.unclosed.Text()).c_str(), row.note.c_str());
    lines->push_back(text);
  };
  line("recipe", recipe);
  line("auto", automatic);
  line("none", none);
}

// Cuts holes (discs of 1-2 px radius) and a crack (a 2 px line across the subject) into every
// colour frame's subject, where the true mask says it is: what a threshold makes of a
// subject's dark patches.
void Roughen(const fs::path& take_dir) {
  std::mt19937 rng(11);
  for (const auto& entry : fs::directory_iterator(take_dir / "gt" / "masks")) {
    const fs::path frame = take_dir / "frames" / entry.path().filename() / "000000.png";
    const cv::Mat truth = ReadImage(entry.path() / "000000.png");
    cv::Mat image = ReadImage(frame);
    const cv::Rect box = cv::boundingRect(truth);
    std::uniform_int_distribution<int> x(box.x, box.x + box.width - 1);
    std::uniform_int_distribution<int> y(box.y, box.y + box.height - 1);
    for (int placed = 0, tries = 0; placed < 8 && tries < 1000; ++tries) {
      const cv::Point at(x(rng), y(rng));
      if (truth.at<uint8_t>(at) == 0) continue;
      cv::circle(image, at, 1 + placed % 2, cv::Scalar::all(0), -1);
      ++placed;
    }
    const int row = box.y + box.height / 3 + static_cast<int>(rng() % (box.height / 3 + 1));
    cv::line(image, cv::Point(box.x, row), cv::Point(box.x + box.width, row + box.height / 8),
             cv::Scalar::all(0), 2);
    WriteImage(frame, image);
  }
}

}  // namespace

int main(int argc, char** argv) {
  const int threads = argc > 1 ? std::atoi(argv[1]) : 2;
  const fs::path work = argc > 2 ? fs::path(argv[2]) : fs::path("/tmp/holocap-morphology-bench");
  const std::string sets = argc > 3 ? argv[3] : "dino,ring-dark,ring-ragged,knot";
  const int size = argc > 4 ? std::atoi(argv[4]) : 320;
  const int dino_stride = argc > 5 ? std::atoi(argv[5]) : 2;
  const auto wants = [&](const std::string& set) {
    return ("," + sets + ",").find("," + set + ",") != std::string::npos;
  };
  try {
    fs::create_directories(work);
    std::vector<std::string> lines;
    SimOptions ring;
    ring.image_width = size;
    ring.seed = 3;
    ring.threads = threads;
    ring.frames = 1;
    ring.color_only = true;
    ring.world_scale = 0.05;
    ring.subject_albedo = 0.5;
    ring.background_albedo = 0.1;
    ring.overwrite = true;
    for (const char* name : {"ring-dark", "ring-ragged"}) {
      if (!wants(name)) continue;
      const fs::path take = work / name;
      SimulateTake(ring, take);
      std::printf("%s: %s\n", name, bench::CalibrateFromBoardTake(ring, take).c_str());
      if (std::string(name) == "ring-ragged") Roughen(take);
      Table(name, take, work, threads, 1, &lines);
    }
    if (wants("knot")) {
      SimOptions knot = ring;
      knot.scene = "object";
      knot.seed = 5;
      knot.subject_albedo = 1;
      knot.background_albedo = 0.15;
      const fs::path take = work / "knot";
      SimulateTake(knot, take);
      std::printf("knot: %s\n", bench::CalibrateFromBoardTake(knot, take).c_str());
      Table("knot", take, work, threads, 1, &lines);
    }
    if (wants("dino")) {
      ImportOptions import;
      import.format = InteropFormat::kMiddlebury;
      import.overwrite = true;
      const fs::path take = work / "dino";
      ImportTake(fs::path(HOLOCAP_TEST_DATA_DIR) / "middlebury" / "dinoSparseRing", take, import);
      Table("dino", take, work, threads, dino_stride, &lines);
    }
    std::printf(
        "\nleave-one-out held-out IoU, mean / worst over the held-out views; own: against the "
        "view's silhouette with the row's morphology; cross: the mean of the IoUs against its "
        "Otsu silhouette with the recipe's morphology and without any (each listed last); "
        "truth: against gt/masks; inside: the share of the true surface inside the mesh\n");
    std::printf("%-12s %-7s %-5s %-16s %-16s %-16s %-16s %-16s %s\n", "set", "asked", "views",
                "chosen", "own", "cross", "truth", "inside", "recipe | unclosed");
    for (const std::string& line : lines) std::printf("%s\n", line.c_str());
  } catch (const std::exception& e) {
    std::fprintf(stderr, "morphology_bench: %s\n", e.what());
    return 1;
  }
  return 0;
}
