// Reconstruction: accuracy against time on the simulated studio8 rig and a real capture.
//   1. TSDF fusion of the two depth sensors, holocap against Open3D's ScalableTSDFVolume on
//      identical depth maps (resampled to pinhole, Open3D has no lens distortion) and poses,
//      both on the same number of threads.
//   2. holocap's TSDF as the voxel size varies (error against time, memory, peak RSS).
//   3. Visual hull (containment of the true surface) and multi-view stereo from colour alone.
//   4. Middlebury dinoSparseRing: leave-one-out hull silhouettes, IoU per held-out view.
//   5. The same leave-one-out through ReconstructTake with no options set (what `holocap
//      reconstruct TAKE --heldout-names VIEW --no-glb` does): the plan's bounds, voxel,
//      silhouettes and method; IoU against the plan's own silhouette and the README's recipe.
// Usage: recon_bench [frames=2] [threads=2] [work_dir=/tmp/holocap-recon-bench] [sections=1234]
#include <sys/resource.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>

#include "core/error.h"
#include "core/mesh.h"
#include "core/take.h"
#include "interop/interop.h"
#include "reconstruction/reconstruction.h"
#include "sim/sim.h"

namespace fs = std::filesystem;
using namespace holocap;

namespace {

double Now() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

double PeakRssMb() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return usage.ru_maxrss / 1024.0;
}

std::string SetName(int64_t set) {
  char name[32];
  std::snprintf(name, sizeof(name), "%06lld", static_cast<long long>(set));
  return name;
}

struct DepthInput {
  CameraModel camera;
  cv::Mat depth;  // foreground only, NaN elsewhere
};

// The same depth seen through a pinhole with the lens's fx, fy, cx, cy (nearest sample).
DepthInput ToPinhole(const DepthInput& in) {
  const auto& k = in.camera.intrinsics();
  CameraModel pinhole("LENSMODEL_PINHOLE", {k[0], k[1], k[2], k[3]}, in.camera.width(),
                      in.camera.height(), in.camera.cam_from_world());
  const int w = in.camera.width(), h = in.camera.height();
  Eigen::Matrix3Xd rays(3, w * h);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) rays.col(y * w + x) << (x - k[2]) / k[0], (y - k[3]) / k[1], 1;
  Eigen::Matrix2Xd source = in.camera.ProjectMany(rays);
  cv::Mat out(h, w, CV_32F, cv::Scalar(std::numeric_limits<float>::quiet_NaN()));
  for (int i = 0; i < w * h; ++i) {
    int sx = static_cast<int>(std::lround(source(0, i))),
        sy = static_cast<int>(std::lround(source(1, i)));
    if (sx >= 0 && sy >= 0 && sx < w && sy < h)
      out.at<float>(i / w, i % w) = in.depth.at<float>(sy, sx);
  }
  return {pinhole, out};
}

struct BenchFrame {
  int64_t set;
  std::vector<DepthInput> depth;
  Mesh truth;
  std::function<bool(const Eigen::Vector3d&)> seen;
  std::function<bool(const Eigen::Vector3d&)> outer;  // the union's surface, not buried faces
};

void PrintErrors(const char* label, double voxel, double integrate_s, double mesh_s,
                 size_t triangles, const SurfaceErrors& all, const SurfaceErrors& seen,
                 const std::string& extra = "") {
  std::printf("%-22s %6.1f %11.4f %8.3f %9zu %9.2f %9.2f %9.2f %9.2f %7.3f %s\n", label,
              voxel * 1e3, integrate_s, mesh_s, triangles, all.chamfer_mm, all.accuracy_mm,
              all.completeness_mm, seen.chamfer_mm, seen.fscore, extra.c_str());
}

const char* kHeader = "%-22s %6s %11s %8s %9s %9s %9s %9s %9s %7s %s\n";

void TsdfSections(const std::vector<BenchFrame>& frames, int threads, const fs::path& work,
                  bool peer, bool sweep) {
  auto run_holocap = [&](const std::vector<std::vector<DepthInput>>& inputs, TsdfOptions options,
                         double* integrate_s, double* mesh_s, std::vector<Mesh>* meshes,
                         size_t* blocks, double* memory_mb) {
    options.threads = threads;
    *integrate_s = *mesh_s = 0;
    *blocks = 0;
    *memory_mb = 0;
    meshes->clear();
    for (const auto& frame : inputs) {
      TsdfVolume tsdf(options);
      for (const auto& d : frame) *integrate_s += tsdf.Integrate(d.depth, d.camera).seconds;
      double t0 = Now();
      meshes->push_back(ExtractMesh(tsdf.volume()));
      *mesh_s += Now() - t0;
      *blocks = std::max(*blocks, tsdf.volume().block_count());
      *memory_mb = std::max(*memory_mb, tsdf.volume().memory_bytes() / 1048576.0);
    }
    *integrate_s /= inputs.size();
    *mesh_s /= inputs.size();
  };
  auto errors = [&](const std::vector<Mesh>& meshes, SurfaceErrors* all, SurfaceErrors* seen) {
    *all = *seen = SurfaceErrors{};
    for (size_t i = 0; i < meshes.size(); ++i) {
      SurfaceErrors a = CompareSurfaces(meshes[i], frames[i].truth, 0.005, 40000, frames[i].outer),
                    s = CompareSurfaces(meshes[i], frames[i].truth, 0.005, 40000, frames[i].seen);
      all->chamfer_mm += a.chamfer_mm / meshes.size();
      all->accuracy_mm += a.accuracy_mm / meshes.size();
      all->completeness_mm += a.completeness_mm / meshes.size();
      seen->chamfer_mm += s.chamfer_mm / meshes.size();
      seen->fscore += s.fscore / meshes.size();
    }
  };
  std::vector<std::vector<DepthInput>> original, pinhole;
  for (const BenchFrame& f : frames) {
    original.push_back(f.depth);
    pinhole.emplace_back();
    for (const auto& d : f.depth) pinhole.back().push_back(ToPinhole(d));
  }
  // Warm the per-lens tables (built once per camera, then reused for every frame).
  {
    double t0 = Now();
    TsdfOptions options;
    for (const auto& d : pinhole[0]) TsdfVolume(options).Integrate(d.depth, d.camera);
    for (const auto& d : original[0]) TsdfVolume(options).Integrate(d.depth, d.camera);
    std::printf("one-time projection tables for 4 lenses: %.2f s\n\n", Now() - t0);
  }
  if (peer) {
    std::printf(
        "== TSDF: holocap vs Open3D ScalableTSDFVolume, %zu frame(s) x %zu depth maps, pinhole, %d "
        "threads\n",
        frames.size(), frames[0].depth.size(), threads);
    std::printf(kHeader, "method", "voxmm", "integr_s/fr", "mesh_s", "triangles", "chamfer",
                "accuracy", "complete", "seen_ch", "F@5seen", "");
    for (double voxel : {0.008, 0.004}) {
      TsdfOptions plain;
      plain.voxel_m = voxel;
      plain.smoothing_radius_px = 0;
      plain.max_incidence_deg = 90;
      TsdfOptions full = plain;
      full.smoothing_radius_px = TsdfOptions{}.smoothing_radius_px;
      full.max_incidence_deg = TsdfOptions{}.max_incidence_deg;
      for (auto [label, options] :
           {std::pair{"holocap (plain)", plain}, std::pair{"holocap (filtered)", full}}) {
        double integrate_s, mesh_s, memory;
        size_t blocks;
        std::vector<Mesh> meshes;
        run_holocap(pinhole, options, &integrate_s, &mesh_s, &meshes, &blocks, &memory);
        SurfaceErrors all, seen;
        errors(meshes, &all, &seen);
        PrintErrors(label, voxel, integrate_s, mesh_s, meshes[0].faces.size(), all, seen);
      }
      // Open3D on the same pinhole depth maps, one process per frame.
      double integrate_s = 0, mesh_s = 0;
      std::vector<Mesh> meshes;
      for (size_t f = 0; f < pinhole.size(); ++f) {
        fs::path dir = work / ("open3d-" + std::to_string(f));
        fs::create_directories(dir);
        nlohmann::json spec = {{"frames", nlohmann::json::array()}};
        for (size_t i = 0; i < pinhole[f].size(); ++i) {
          const DepthInput& d = pinhole[f][i];
          cv::Mat zeroed = d.depth.clone();
          zeroed.setTo(0, zeroed != zeroed);
          std::string file = "depth" + std::to_string(i) + ".f32";
          std::ofstream(dir / file, std::ios::binary)
              .write(reinterpret_cast<const char*>(zeroed.data), zeroed.total() * sizeof(float));
          Eigen::Matrix4d m = d.camera.cam_from_world().matrix();
          std::vector<double> rows;
          for (int r = 0; r < 4; ++r)
            for (int c = 0; c < 4; ++c) rows.push_back(m(r, c));
          const auto& k = d.camera.intrinsics();
          spec["frames"].push_back({{"file", file},
                                    {"width", d.depth.cols},
                                    {"height", d.depth.rows},
                                    {"fx", k[0]},
                                    {"fy", k[1]},
                                    {"cx", k[2]},
                                    {"cy", k[3]},
                                    {"cam_from_world", rows}});
        }
        std::ofstream(dir / "frames.json") << spec.dump();
        std::string command = "OMP_NUM_THREADS=" + std::to_string(threads) + " /usr/bin/python3 '" +
                              std::string(HOLOCAP_BENCH_DIR) + "/open3d_tsdf.py' '" + dir.string() +
                              "' " + std::to_string(voxel) + " '" + (dir / "mesh.ply").string() +
                              "'";
        FILE* pipe = popen(command.c_str(), "r");
        char line[256] = {};
        double a = 0, b = 0;
        long triangles = 0;
        while (pipe && std::fgets(line, sizeof(line), pipe))
          std::sscanf(line, "open3d %lf %lf %ld", &a, &b, &triangles);
        if (pipe) pclose(pipe);
        integrate_s += a / pinhole.size();
        mesh_s += b / pinhole.size();
        meshes.push_back(ReadPly(dir / "mesh.ply"));
      }
      SurfaceErrors all, seen;
      errors(meshes, &all, &seen);
      PrintErrors("Open3D Scalable", voxel, integrate_s, mesh_s, meshes[0].faces.size(), all, seen);
    }
    std::printf("\n");
  }
  if (sweep) {
    std::printf("== holocap TSDF as the voxel varies (true lenses, filtered; %d threads)\n",
                threads);
    std::printf(kHeader, "method", "voxmm", "integr_s/fr", "mesh_s", "triangles", "chamfer",
                "accuracy", "complete", "seen_ch", "F@5seen", "blocks  MB  peakRSS_MB");
    for (double voxel : {0.016, 0.008, 0.004, 0.002, 0.001}) {
      TsdfOptions options;
      options.voxel_m = voxel;
      double integrate_s, mesh_s, memory;
      size_t blocks;
      std::vector<Mesh> meshes;
      run_holocap(original, options, &integrate_s, &mesh_s, &meshes, &blocks, &memory);
      SurfaceErrors all, seen;
      errors(meshes, &all, &seen);
      char extra[96];
      std::snprintf(extra, sizeof(extra), "%6zu %5.0f %8.0f", blocks, memory, PeakRssMb());
      PrintErrors("holocap", voxel, integrate_s, mesh_s, meshes[0].faces.size(), all, seen, extra);
    }
    std::printf("\n");
  }
}

// The figure: the pipeline's TSDF from the depth sensors, with and without the
// hull-constrained completion of what they did not see, every frame against the whole truth.
void PipelineTsdf(const fs::path& take_dir, int frame_count, int threads) {
  std::printf(
      "== studio8 TSDF from the depth sensors through the pipeline (holocap reconstruct --method "
      "tsdf), "
      "%d frame(s), %d threads\n",
      frame_count, threads);
  std::printf("%-26s %6s %9s %9s %9s %9s %9s %9s %8s %10s\n", "completion", "voxmm", "frame_s",
              "hull+fill", "chamfer", "accuracy", "complete", "seen_ch", "F@5mm", "ch_buried");
  for (double voxel : {0.008, 0.004}) {
    for (bool complete : {false, true}) {
      ReconstructionOptions options;
      options.method = ReconstructionMethod::kTsdf;
      options.voxel_m = voxel;
      options.threads = threads;
      options.write_glb = false;
      options.texture.atlas = false;
      options.sweep_voxels_m.clear();
      options.tsdf_hull_completion = complete;
      Report report("reconstruct");
      TakeSelection frames;
      frames.last_frame = frame_count;
      ReconstructTake(take_dir, frames,
                      take_dir / ("bench-tsdf-" + std::to_string(static_cast<int>(voxel * 1e3))),
                      options, &report);
      const auto& metrics = report.json()["metrics"];
      double completion_s = 0, seen = 0;
      for (const auto& f : metrics["frames"]) {
        if (f["metrics"].contains("completion")) {
          completion_s += (f["metrics"]["hull"]["seconds"].get<double>() +
                           f["metrics"]["completion"]["seconds"].get<double>()) /
                          metrics["frames"].size();
        }
        seen +=
            f["metrics"]["gt"]["observed"]["chamfer_mm"].get<double>() / metrics["frames"].size();
      }
      const auto& gt = metrics["gt"];
      std::printf("%-26s %6.1f %9.2f %9.2f %9.2f %9.2f %9.2f %9.2f %8.3f %10.2f\n",
                  complete ? "hull carved by free space" : "none (sensors only)", voxel * 1e3,
                  metrics["timing"]["mean_frame_s"].get<double>(), completion_s,
                  gt["chamfer_mm"].get<double>(), gt["accuracy_mm"].get<double>(),
                  gt["completeness_mm"].get<double>(), seen, gt["fscore_5mm"].get<double>(),
                  gt["chamfer_with_buried_faces_mm"].get<double>());
    }
  }
  std::printf("\n");
}

void HullAndMvs(const fs::path& take_dir, const std::vector<BenchFrame>& frames, int threads) {
  const Take take = Take::Open(take_dir);
  std::printf("== studio8 visual hull (background-subtracted silhouettes, 8 cameras, %d threads)\n",
              threads);
  std::printf("%6s %8s %12s %12s %10s %9s\n", "voxmm", "hull_s", "contained", "within_vox/2",
              "litres", "mask_IoU");
  for (double voxel : {0.016, 0.008, 0.004}) {
    double seconds = 0, contained = 0, near = 0, litres = 0, iou = 0;
    int masks = 0;
    for (const BenchFrame& frame : frames) {
      std::vector<View> views;
      for (const StreamInfo& s : take.streams()) {
        if (s.role != SensorRole::kColor) continue;
        View view{s.name, take.Camera(s.name, true), take.ReadFrame(frame.set, s.name), {}};
        view.mask = ExtractSilhouette(view.image, take.ReadFrame(0, s.name), SilhouetteOptions{});
        iou += MaskIoU(view.mask,
                       ReadImage(take.gt_dir() / "masks" / s.name / (SetName(frame.set) + ".png")));
        ++masks;
        views.push_back(view);
      }
      HullOptions options;
      options.voxel_m = voxel;
      options.threads = threads;
      HullSummary summary;
      VisualHull hull = ComputeVisualHull(views, options, &summary);
      seconds += summary.seconds / frames.size();
      litres += summary.volume_m3 * 1e3 / frames.size();
      auto points = frame.truth.SampleSurface(20000, 3);
      int64_t in = 0, in_near = 0;
      for (const auto& p : points)
        in += hull.Contains(p, 0), in_near += hull.Contains(p, 0.5 * voxel);
      contained += static_cast<double>(in) / points.size() / frames.size();
      near += static_cast<double>(in_near) / points.size() / frames.size();
    }
    std::printf("%6.1f %8.3f %12.4f %12.4f %10.1f %9.4f\n", voxel * 1e3, seconds, contained, near,
                litres, iou / masks);
  }
  std::printf("\n== studio8 multi-view stereo from colour alone (pipeline, 1 frame, %d threads)\n",
              threads);
  std::printf("%6s %9s %9s %9s %9s %8s %10s %12s\n", "voxmm", "frame_s", "mvs_s", "chamfer",
              "accuracy", "complete", "F@5mm", "consistent");
  for (double voxel : {0.008, 0.004}) {
    ReconstructionOptions options;
    options.method = ReconstructionMethod::kMvs;
    options.voxel_m = voxel;
    options.threads = threads;
    options.write_glb = false;
    options.sweep_voxels_m.clear();
    Report report("reconstruct");
    TakeSelection first_set;
    first_set.last_frame = 1;
    ReconstructTake(take_dir, first_set,
                    take_dir / ("bench-mvs-" + std::to_string(static_cast<int>(voxel * 1e3))),
                    options, &report);
    const auto& f = report.json()["metrics"]["frames"][0];
    const auto& gt = f["metrics"]["gt"];
    std::printf("%6.1f %9.2f %9.2f %9.2f %9.2f %8.2f %10.3f %12lld\n", voxel * 1e3,
                f["seconds"].get<double>(), f["metrics"]["mvs"]["seconds"].get<double>(),
                gt["chamfer_mm"].get<double>(), gt["accuracy_mm"].get<double>(),
                gt["completeness_mm"].get<double>(), gt["fscore_5mm"].get<double>(),
                f["metrics"]["mvs"]["pixels_consistent"].get<long long>());
  }
  std::printf("\n");
}

void Middlebury(const fs::path& work, int threads) {
  const fs::path source = fs::path(HOLOCAP_TEST_DATA_DIR) / "middlebury" / "dinoSparseRing";
  if (!fs::exists(source)) {
    std::printf("== Middlebury: %s missing, skipped\n", source.c_str());
    return;
  }
  const fs::path take_dir = work / "dino";
  ImportOptions import;
  import.format = InteropFormat::kMiddlebury;
  import.overwrite = true;
  ImportTake(source, take_dir, import);
  const Take take = Take::Open(take_dir);
  SilhouetteOptions silhouettes;
  silhouettes.mode = SilhouetteMode::kThreshold;
  silhouettes.open_px = 0;
  silhouettes.dilate_px = 10;
  silhouettes.erode_px = 7;
  std::vector<View> views;
  for (const StreamInfo& s : take.streams()) {
    View view{s.name, take.Camera(s.name), take.ReadFrame(0, s.name), {}};
    view.mask = ExtractSilhouette(view.image, cv::Mat(), silhouettes);
    views.push_back(view);
  }
  Box bounds;
  bounds.min = Eigen::Vector3d(-0.071897, -0.028874, -0.067845);
  bounds.max = Eigen::Vector3d(0.020897, 0.078227, 0.025495);
  std::printf(
      "== Middlebury dinoSparseRing: hull of 15 views, IoU with the held-out view's silhouette (%d "
      "threads)\n",
      threads);
  for (double voxel : {0.001, 0.0005, 0.00025}) {
    double sum = 0, worst = 1, seconds = 0;
    std::string worst_view;
    std::string row;
    for (size_t held = 0; held < views.size(); ++held) {
      std::vector<View> training;
      for (size_t i = 0; i < views.size(); ++i)
        if (i != held) training.push_back(views[i]);
      HullOptions options;
      options.voxel_m = voxel;
      options.bounds = bounds;
      options.min_views = 3;
      options.threads = threads;
      HullSummary summary;
      VisualHull hull = ComputeVisualHull(training, options, &summary);
      seconds += summary.seconds / views.size();
      double iou = MaskIoU(RenderSilhouette(ExtractMesh(*hull.volume), views[held].camera),
                           views[held].mask);
      sum += iou;
      if (iou < worst) worst = iou, worst_view = views[held].name;
      char cell[16];
      std::snprintf(cell, sizeof(cell), " %.3f", iou);
      row += cell;
    }
    std::printf("voxel %.2f mm: hull %.2f s, IoU mean %.4f, min %.4f (%s); per view:%s\n",
                voxel * 1e3, seconds, sum / views.size(), worst, worst_view.c_str(), row.c_str());
  }
  std::printf("\n");
}

// Leave-one-out with nothing hand-set: each view held out of a default reconstruction in turn.
void MiddleburyNoFlags(const fs::path& work, int threads) {
  const fs::path source = fs::path(HOLOCAP_TEST_DATA_DIR) / "middlebury" / "dinoSparseRing";
  if (!fs::exists(source)) {
    std::printf("== Middlebury (no flags): %s missing, skipped\n", source.c_str());
    return;
  }
  const fs::path take_dir = work / "dino";
  ImportOptions import;
  import.format = InteropFormat::kMiddlebury;
  import.overwrite = true;
  ImportTake(source, take_dir, import);
  const Take take = Take::Open(take_dir);
  SilhouetteOptions recipe;  // the README's: threshold 0.19, dilate 10, erode 7
  recipe.mode = SilhouetteMode::kThreshold;
  recipe.open_px = 0;
  recipe.dilate_px = 10;
  recipe.erode_px = 7;
  std::printf("== Middlebury dinoSparseRing, no flags: leave-one-out through ReconstructTake\n");
  double own_sum = 0, recipe_sum = 0, own_worst = 1, recipe_worst = 1, seconds = 0;
  std::string plan_line;
  const auto streams = take.streams();
  for (const StreamInfo& held : streams) {
    TakeSelection selection;
    selection.heldout = {held.name};
    ReconstructionOptions options;
    options.write_glb = false;
    options.threads = threads;
    Report report("reconstruct");
    const fs::path out = work / "dino-loo" / held.name;
    ReconstructionSummary summary = ReconstructTake(take_dir, selection, out, options, &report);
    seconds += summary.seconds;
    const nlohmann::json& plan = report.json()["plan"];
    if (plan_line.empty()) {
      plan_line = Cat("method ", plan["method"].get<std::string>(), ", voxel ",
                      plan["voxel"]["m"].get<double>() * 1e3, " mm, silhouettes ",
                      plan["silhouettes"]["source"].get<std::string>(), ", bounds ",
                      plan["bounds"]["box"].dump(), " (",
                      plan["bounds"]["source"].get<std::string>().substr(0, 60), "...)");
    }
    double own = 0, with_recipe = 0;
    if (summary.IsUsable()) {
      own = report.json()["metrics"]["heldout_iou_mean"].get<double>();
      const cv::Mat image = take.ReadFrame(0, held.name);
      with_recipe = MaskIoU(RenderSilhouette(ReadPly(out / "000000.ply"), take.Camera(held.name)),
                            ExtractSilhouette(image, cv::Mat(), recipe));
    }
    std::printf("  held out %s: %s, IoU %.4f (its own silhouette), %.4f (README recipe), %.1f s\n",
                held.name.c_str(), ToString(summary.termination), own, with_recipe,
                summary.seconds);
    std::fflush(stdout);
    own_sum += own;
    recipe_sum += with_recipe;
    own_worst = std::min(own_worst, own);
    recipe_worst = std::min(recipe_worst, with_recipe);
  }
  const double n = static_cast<double>(streams.size());
  std::printf("plan: %s\n", plan_line.c_str());
  std::printf(
      "IoU mean %.4f, worst %.4f (own silhouettes); mean %.4f, worst %.4f (README recipe); "
      "%.1f s per view\n\n",
      own_sum / n, own_worst, recipe_sum / n, recipe_worst, seconds / n);
}

}  // namespace

int main(int argc, char** argv) {
  const int frame_count = argc > 1 ? std::atoi(argv[1]) : 2;
  const int threads = argc > 2 ? std::atoi(argv[2]) : 2;
  const fs::path work = argc > 3 ? argv[3] : "/tmp/holocap-recon-bench";
  const std::string sections = argc > 4 ? argv[4] : "1234";
  try {
    fs::create_directories(work);
    if (sections.find('5') != std::string::npos) MiddleburyNoFlags(work, threads);
    if (sections.find_first_of("1234") == std::string::npos) return 0;
    const fs::path take_dir = work / "studio8";
    if (!fs::exists(take_dir / "take.json")) {
      SimOptions sim;
      sim.rig = "studio8";
      sim.frames = frame_count + 1;
      sim.clean_plate_frames = 1;
      sim.seed = 7;
      sim.overwrite = true;
      SimulateTake(sim, take_dir);
    }
    const Take take = Take::Open(take_dir);
    std::vector<BenchFrame> frames;
    for (int64_t set = 1; set <= frame_count && set < static_cast<int64_t>(take.size()); ++set) {
      BenchFrame frame;
      frame.set = set;
      frame.truth = ReadPly(take.gt_dir() / "meshes" / (SetName(set) + ".ply"));
      std::vector<std::pair<CameraModel, cv::Mat>> seen;
      for (const StreamInfo& s : take.streams()) {
        if (s.role != SensorRole::kDepth) continue;
        CameraModel camera = take.Camera(s.name, true);
        cv::Mat depth = take.ReadFrame(set, s.name).clone();
        cv::Mat foreground =
            DepthForeground(depth, take.ReadFrame(0, s.name), TsdfOptions{}.depth_noise_k);
        depth.setTo(std::numeric_limits<float>::quiet_NaN(), foreground == 0);
        frame.depth.push_back({camera, depth});
        seen.emplace_back(camera,
                          ReadImage(take.gt_dir() / "depth" / s.name / (SetName(set) + ".exr")));
      }
      frame.seen = SeenInDepthMaps(seen);
      frame.outer = OnOuterSurface(frame.truth);
      frames.push_back(std::move(frame));
    }
    std::printf("recon_bench: %zu frame(s) of %s, %d threads\n", frames.size(), take_dir.c_str(),
                threads);
    std::printf(
        "chamfer/accuracy/complete in mm against gt/meshes, completeness on the subject's outer "
        "surface (the "
        "body parts' faces buried inside other parts left out; ch_buried keeps them); seen_ch and "
        "F@5seen only "
        "on the true surface a depth sensor saw\n\n");
    if (sections.find('1') != std::string::npos || sections.find('2') != std::string::npos) {
      TsdfSections(frames, threads, work, sections.find('1') != std::string::npos,
                   sections.find('2') != std::string::npos);
    }
    if (sections.find('2') != std::string::npos)
      PipelineTsdf(take_dir, static_cast<int>(frames.size()), threads);
    if (sections.find('3') != std::string::npos) HullAndMvs(take_dir, frames, threads);
    if (sections.find('4') != std::string::npos) Middlebury(work, threads);
    std::printf("peak RSS %.0f MB\n", PeakRssMb());
  } catch (const Error& e) {
    std::fprintf(stderr, "recon_bench: error: %s\n", e.what());
    return 1;
  }
  return 0;
}
