// Reconstruction: accuracy against time on the simulated studio8 rig and a real capture.
//   1. TSDF fusion, holocap against Open3D's tensor VoxelBlockGrid and legacy
//      ScalableTSDFVolume (bench/open3d_tsdf.py) on identical depth maps (resampled to pinhole:
//      Open3D has no lens distortion) and poses, the same voxel, truncation and depth limit,
//      the same thread count and OMP_WAIT_POLICY=PASSIVE for every side, repeats interleaved
//      (median and range); then each one's peak memory at 2 mm in a process of its own.
//   2. holocap's TSDF as the voxel size varies (error against time, memory, peak RSS), and the
//      pipeline's TSDF with and without hull completion.
//   3. Visual hull (containment of the true surface) and multi-view stereo from colour alone.
//   4. Middlebury dinoSparseRing: leave-one-out hull silhouettes, IoU per held-out view.
//   5. The same leave-one-out through ReconstructTake with no options set (what `holocap
//      reconstruct TAKE --heldout-names VIEW --no-glb` does): the plan's bounds, voxel,
//      silhouettes and method; IoU against the plan's own silhouette and the README's recipe.
//   6. Larger fusion cases: studio8 with a depth sensor beside each of its 8 cameras at 4 and
//      2 mm against both peers, and 60 frame sets fused into one growing volume.
//   m. Section 1's peak memory alone (each method in a process of its own, equal reservations).
// Usage: recon_bench [frames=2] [threads=2] [work_dir=/tmp/holocap-recon-bench]
//                    [sections=1234] [repeats=5]
// (bench/recon_bench_results.txt: `recon_bench 2 2 /tmp/holocap-recon-bench 16 7`).
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>

#include "bench/calibrated_sim.h"
#include "core/error.h"
#include "core/mesh.h"
#include "core/rig_alignment.h"
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

std::string SetName(int64_t set) {
  char name[32];
  std::snprintf(name, sizeof(name), "%06lld", static_cast<long long>(set));
  return name;
}

struct DepthInput {
  CameraModel camera;
  cv::Mat depth;       // foreground only, NaN elsewhere
  cv::Mat raw;         // the whole map, the room included
  cv::Mat foreground;  // CV_8U, 255 = the subject (DepthForeground against the clean plate)
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
  auto resample = [&](const cv::Mat& image, const cv::Scalar& outside) {
    cv::Mat out(h, w, image.type(), outside);
    for (int i = 0; i < w * h; ++i) {
      int sx = static_cast<int>(std::lround(source(0, i))),
          sy = static_cast<int>(std::lround(source(1, i)));
      if (sx < 0 || sy < 0 || sx >= w || sy >= h) continue;
      if (image.type() == CV_32F)
        out.at<float>(i / w, i % w) = image.at<float>(sy, sx);
      else
        out.at<uint8_t>(i / w, i % w) = image.at<uint8_t>(sy, sx);
    }
    return out;
  };
  const cv::Scalar nan(std::numeric_limits<float>::quiet_NaN());
  return {pinhole, resample(in.depth, nan), resample(in.raw, nan),
          resample(in.foreground, cv::Scalar(0))};
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

// Mean errors of frame i's mesh against frame i's truth: on the outer surface, and on what a
// sensor saw.
void MeanErrors(const std::vector<Mesh>& meshes, const std::vector<BenchFrame>& frames,
                SurfaceErrors* all, SurfaceErrors* seen) {
  *all = *seen = SurfaceErrors{};
  for (size_t i = 0; i < meshes.size(); ++i) {
    SurfaceErrors a = CompareSurfaces(meshes[i], frames[i].truth, 0.005, 40000, frames[i].outer),
                  s = CompareSurfaces(meshes[i], frames[i].truth, 0.005, 40000, frames[i].seen);
    all->chamfer_mm += a.chamfer_mm / meshes.size();
    all->accuracy_mm += a.accuracy_mm / meshes.size();
    all->completeness_mm += a.completeness_mm / meshes.size();
    all->fscore += a.fscore / meshes.size();
    seen->chamfer_mm += s.chamfer_mm / meshes.size();
    seen->fscore += s.fscore / meshes.size();
  }
}

// One fused volume per frame (every depth map of the frame), meshed: seconds per frame.
// bench/open3d_tsdf.py's VoxelBlockGrid block_count.
constexpr size_t kPeerBlockCount = 50000;

struct HolocapRun {
  double integrate_s = 0, mesh_s = 0;
  std::vector<Mesh> meshes;
  size_t blocks = 0;
  double memory_mb = 0;
};
// With `masked`, each map whole with its foreground mask (the background's measurements carve
// free space); else the subject's depth alone, as the peers get it.
HolocapRun RunHolocap(const std::vector<std::vector<DepthInput>>& inputs, TsdfOptions options,
                      int threads, bool masked = false) {
  options.threads = threads;
  HolocapRun run;
  for (const auto& frame : inputs) {
    TsdfVolume tsdf(options);
    double t0 = Now();
    for (const auto& d : frame) {
      if (masked)
        tsdf.Integrate(d.raw, d.camera, d.foreground);
      else
        tsdf.Integrate(d.depth, d.camera);
    }
    double t1 = Now();
    run.meshes.push_back(ExtractMesh(tsdf.volume()));
    run.integrate_s += (t1 - t0) / inputs.size();
    run.mesh_s += (Now() - t1) / inputs.size();
    run.blocks = std::max(run.blocks, tsdf.volume().block_count());
    run.memory_mb = std::max(run.memory_mb, tsdf.volume().memory_bytes() / 1048576.0);
  }
  return run;
}

// holocap's TSDF as the peers are run: the maps as they are (no smoothing, no grazing filter),
// 4-voxel truncation, depth up to 8 m.
TsdfOptions PlainTsdf(double voxel) {
  TsdfOptions plain;
  plain.voxel_m = voxel;
  plain.smoothing_radius_px = 0;
  plain.max_incidence_deg = 90;
  return plain;
}

// Writes the pinhole maps as bench/open3d_tsdf.py reads them (dir/frames.json, raw float32).
void WriteOpen3dInput(const std::vector<std::vector<DepthInput>>& frames, const fs::path& dir) {
  fs::create_directories(dir);
  nlohmann::json spec = {{"frames", nlohmann::json::array()}};
  for (size_t f = 0; f < frames.size(); ++f) {
    nlohmann::json maps = nlohmann::json::array();
    for (size_t i = 0; i < frames[f].size(); ++i) {
      const DepthInput& d = frames[f][i];
      cv::Mat zeroed = d.depth.clone();
      cv::patchNaNs(zeroed, 0);  // 0 = no measurement (a NaN compares unequal to nothing)
      std::string file = "depth" + std::to_string(f) + "-" + std::to_string(i) + ".f32";
      std::ofstream(dir / file, std::ios::binary)
          .write(reinterpret_cast<const char*>(zeroed.data), zeroed.total() * sizeof(float));
      Eigen::Matrix4d m = d.camera.cam_from_world().matrix();
      std::vector<double> rows;
      for (int r = 0; r < 4; ++r)
        for (int c = 0; c < 4; ++c) rows.push_back(m(r, c));
      const auto& k = d.camera.intrinsics();
      maps.push_back({{"file", file},
                      {"width", d.depth.cols},
                      {"height", d.depth.rows},
                      {"fx", k[0]},
                      {"fy", k[1]},
                      {"cx", k[2]},
                      {"cy", k[3]},
                      {"cam_from_world", rows}});
    }
    spec["frames"].push_back(maps);
  }
  std::ofstream(dir / "frames.json") << spec.dump();
}

// The maps WriteOpen3dInput wrote, read back (the peak-memory mode fuses exactly the peers'
// input).
std::vector<std::vector<DepthInput>> ReadOpen3dInput(const fs::path& dir) {
  nlohmann::json spec = nlohmann::json::parse(std::ifstream(dir / "frames.json"));
  std::vector<std::vector<DepthInput>> frames;
  for (const auto& maps : spec["frames"]) {
    frames.emplace_back();
    for (const auto& m : maps) {
      const int w = m["width"], h = m["height"];
      cv::Mat depth(h, w, CV_32F);
      std::ifstream(dir / m["file"].get<std::string>(), std::ios::binary)
          .read(reinterpret_cast<char*>(depth.data), depth.total() * sizeof(float));
      depth.setTo(std::numeric_limits<float>::quiet_NaN(), depth == 0);
      auto rows = m["cam_from_world"].get<std::vector<double>>();
      Eigen::Matrix4d matrix =
          Eigen::Map<Eigen::Matrix<double, 4, 4, Eigen::RowMajor>>(rows.data());
      Pose cam_from_world(matrix);
      CameraModel camera("LENSMODEL_PINHOLE", {m["fx"], m["fy"], m["cx"], m["cy"]}, w, h,
                         cam_from_world);
      frames.back().push_back({camera, depth, {}, {}});
    }
  }
  return frames;
}

struct PeerResult {
  double integrate_s = 0, mesh_s = 0, peak_mb = 0;
  long triangles = 0;
  long blocks = 0;  // the most blocks one volume held (0: the method does not say)
};

// Runs bench/open3d_tsdf.py for `peers` ("vbg", "legacy", comma-separated, in that order) on
// `threads` OpenMP threads that wait passively; meshes go to dir/mesh-PEER-i.ply. VoxelBlockGrid
// is made with `block_count` blocks (0: the script's 50000).
std::map<std::string, PeerResult> RunOpen3d(const fs::path& dir, double voxel,
                                            const std::string& peers, int threads,
                                            size_t block_count = 0) {
  const TsdfOptions defaults;
  std::string command =
      "OMP_NUM_THREADS=" + std::to_string(threads) + " OMP_WAIT_POLICY=PASSIVE /usr/bin/python3 '" +
      std::string(HOLOCAP_BENCH_DIR) + "/open3d_tsdf.py' '" + dir.string() + "' " +
      std::to_string(voxel) + " " + std::to_string(defaults.truncation_voxels) + " " +
      std::to_string(defaults.depth_max_m) + " " + peers + " '" + (dir / "mesh").string() + "'" +
      (block_count > 0 ? " " + std::to_string(block_count) : "");
  FILE* pipe = popen(command.c_str(), "r");
  if (pipe == nullptr) Fail("cannot run ", command);
  std::map<std::string, PeerResult> results;
  char line[512] = {};
  while (std::fgets(line, sizeof(line), pipe)) {
    char name[32] = {};
    PeerResult r;
    if (std::sscanf(line, "%31s %lf %lf %ld %lf %ld", name, &r.integrate_s, &r.mesh_s, &r.triangles,
                    &r.peak_mb, &r.blocks) >= 5)
      results[name] = r;
  }
  if (pclose(pipe) != 0 ||
      results.size() != static_cast<size_t>(1 + std::count(peers.begin(), peers.end(), ',')))
    Fail("open3d_tsdf.py failed: ", command);
  return results;
}

struct Spread {
  double median = 0, min = 0, max = 0;
};
Spread SpreadOf(std::vector<double> values) {
  std::sort(values.begin(), values.end());
  const size_t n = values.size();
  double median = n % 2 ? values[n / 2] : 0.5 * (values[n / 2 - 1] + values[n / 2]);
  return {median, values.front(), values.back()};
}

std::string LoadNow() {
  double load[3] = {};
  getloadavg(load, 3);
  char text[64];
  std::snprintf(text, sizeof(text), "%.2f %.2f %.2f", load[0], load[1], load[2]);
  return text;
}

// holocap (as the peers run, and with its filters), VoxelBlockGrid and ScalableTSDFVolume on the
// same pinhole maps, `repeats` times interleaved (the order alternating), median and range of
// the seconds per frame; errors of the last repeat's meshes (every method is deterministic).
void FusionAgainstOpen3d(const std::string& title, const std::vector<BenchFrame>& frames,
                         const std::vector<std::vector<DepthInput>>& pinhole,
                         const std::vector<double>& voxels, int threads, int repeats,
                         const fs::path& work) {
  std::printf(
      "== %s: %zu frame(s) x %zu depth maps, pinhole, %d threads, OMP_WAIT_POLICY=%s, "
      "%d interleaved repeats (median [min-max]); load %s\n",
      title.c_str(), pinhole.size(), pinhole[0].size(), threads, std::getenv("OMP_WAIT_POLICY"),
      repeats, LoadNow().c_str());
  std::printf("%-20s %5s %23s %23s %9s %8s %8s %8s %8s %7s %8s\n", "method", "voxmm",
              "integrate_s/frame", "mesh_s/frame", "triangles", "chamfer", "accuracy", "complete",
              "seen_ch", "F@5", "speed");
  for (double voxel : voxels) {
    const fs::path dir = work / ("open3d-" + std::to_string(static_cast<int>(voxel * 1e4)));
    WriteOpen3dInput(pinhole, dir);
    // The per-lens projection tables are built once per camera, before any timing.
    for (const auto& d : pinhole[0]) TsdfVolume(PlainTsdf(voxel)).Integrate(d.depth, d.camera);
    // holocap on the peers' maps; with each map's foreground mask (the background carves free
    // space); and as the pipeline runs it (smoothing, grazing filter, mask).
    const std::vector<std::string> methods = {
        "holocap",        "holocap +mask",    "holocap filt+mask", "Open3D VBG",
        "Open3D VBG NaN", "Open3D VBG dense", "Open3D Scalable"};
    const std::vector<std::pair<std::string, std::string>> peers = {{"vbg", methods[3]},
                                                                    {"vbg-nan", methods[4]},
                                                                    {"vbg-dense", methods[5]},
                                                                    {"legacy", methods[6]}};
    std::map<std::string, std::vector<double>> integrate, mesh;
    std::map<std::string, std::vector<Mesh>> meshes;
    std::map<std::string, long> triangles;
    auto run_holocap = [&] {
      for (int variant = 0; variant < 3; ++variant) {
        TsdfOptions options = variant < 2 ? PlainTsdf(voxel) : TsdfOptions{};
        options.voxel_m = voxel;
        // As VoxelBlockGrid, which allocates and zeroes its block_count blocks when it is made
        // (205 MB for 50000 blocks: outside its timing), holocap's volume is made with the same
        // number of blocks ready.
        options.reserve_blocks = kPeerBlockCount;
        HolocapRun run = RunHolocap(pinhole, options, threads, variant > 0);
        const std::string& label = methods[variant];
        integrate[label].push_back(run.integrate_s);
        mesh[label].push_back(run.mesh_s);
        triangles[label] = static_cast<long>(run.meshes[0].faces.size());
        meshes[label] = std::move(run.meshes);
      }
    };
    for (int r = 0; r < repeats; ++r) {
      if (r % 2 == 0) run_holocap();
      auto results = RunOpen3d(
          dir, voxel, r % 2 == 0 ? "vbg,vbg-nan,vbg-dense,legacy" : "legacy,vbg-dense,vbg-nan,vbg",
          threads);
      for (const auto& [name, label] : peers) {
        integrate[label].push_back(results[name].integrate_s);
        mesh[label].push_back(results[name].mesh_s);
        triangles[label] = results[name].triangles;
      }
      if (r % 2 == 1) run_holocap();
    }
    for (const auto& [name, label] : peers) {
      meshes[label].clear();
      for (size_t f = 0; f < pinhole.size(); ++f)
        meshes[label].push_back(ReadPly(dir / ("mesh-" + name + "-" + std::to_string(f) + ".ply")));
    }
    const double vbg_s = SpreadOf(integrate[methods[3]]).median;
    for (const std::string& label : methods) {
      SurfaceErrors all, seen;
      MeanErrors(meshes[label], frames, &all, &seen);
      Spread i = SpreadOf(integrate[label]), m = SpreadOf(mesh[label]);
      std::printf(
          "%-20s %5.1f %7.4f [%6.4f-%6.4f] %7.4f [%6.4f-%6.4f] %9ld %8.2f %8.2f %8.2f %8.2f %7.3f "
          "%7.2fx\n",
          label.c_str(), voxel * 1e3, i.median, i.min, i.max, m.median, m.min, m.max,
          triangles[label], all.chamfer_mm, all.accuracy_mm, all.completeness_mm, seen.chamfer_mm,
          seen.fscore, vbg_s / i.median);
    }
    std::fflush(stdout);
  }
  std::printf(
      "(speed: VoxelBlockGrid's median integration time over the method's; load after: "
      "%s)\n\n",
      LoadNow().c_str());
}

// Where holocap's integration spends its time: each stage's seconds per frame (median of
// `repeats`), the blocks and voxels it touched.
void IntegrationStages(const std::vector<std::vector<DepthInput>>& pinhole,
                       const std::vector<double>& voxels, int threads, int repeats) {
  std::printf("== holocap integration by stage, s per frame, median of %d; load %s\n", repeats,
              LoadNow().c_str());
  std::printf("%-14s %5s %9s %9s %9s %9s %8s %10s %10s\n", "input", "voxmm", "prepare", "allocate",
              "fuse", "total", "blocks", "updated", "carved");
  const bool has_masks = !pinhole[0][0].foreground.empty();
  for (double voxel : voxels) {
    for (bool masked : {false, true}) {
      if (masked && !has_masks) continue;
      std::vector<double> prepare, allocate, fuse, total;
      TsdfFrameStats sum;
      for (int r = 0; r < repeats; ++r) {
        TsdfFrameStats frame_sum;
        for (const auto& frame : pinhole) {
          TsdfOptions options = PlainTsdf(voxel);
          options.threads = threads;
          TsdfVolume tsdf(options);
          for (const auto& d : frame) {
            TsdfFrameStats s = masked ? tsdf.Integrate(d.raw, d.camera, d.foreground)
                                      : tsdf.Integrate(d.depth, d.camera);
            frame_sum.prepare_seconds += s.prepare_seconds / pinhole.size();
            frame_sum.allocate_seconds += s.allocate_seconds / pinhole.size();
            frame_sum.fuse_seconds += s.fuse_seconds / pinhole.size();
            frame_sum.seconds += s.seconds / pinhole.size();
            frame_sum.blocks_touched += s.blocks_touched;
            frame_sum.voxels_updated += s.voxels_updated;
            frame_sum.voxels_carved += s.voxels_carved;
          }
        }
        prepare.push_back(frame_sum.prepare_seconds);
        allocate.push_back(frame_sum.allocate_seconds);
        fuse.push_back(frame_sum.fuse_seconds);
        total.push_back(frame_sum.seconds);
        sum = frame_sum;
      }
      const double n = static_cast<double>(pinhole.size());
      std::printf("%-14s %5.1f %9.4f %9.4f %9.4f %9.4f %8.0f %10.0f %10.0f\n",
                  masked ? "map + mask" : "peers' maps", voxel * 1e3, SpreadOf(prepare).median,
                  SpreadOf(allocate).median, SpreadOf(fuse).median, SpreadOf(total).median,
                  sum.blocks_touched / n, sum.voxels_updated / n, sum.voxels_carved / n);
    }
  }
  std::printf("\n");
}

double RssMb() {
  long pages = 0, resident = 0;
  std::ifstream("/proc/self/statm") >> pages >> resident;
  return resident * (sysconf(_SC_PAGESIZE) / 1048576.0);
}

// The peak-memory mode (a process of its own): fuses and meshes the peers' input at one voxel
// size, with `reserve_blocks` blocks made ready in each volume (TsdfOptions::reserve_blocks), and
// prints "holocap integrate_s mesh_s triangles peak_rss_growth_mb blocks", as open3d_tsdf.py.
int PeakMemoryMode(const fs::path& dir, double voxel, int threads, size_t reserve_blocks) {
  auto inputs = ReadOpen3dInput(dir);
  const double base = RssMb();
  TsdfOptions options = PlainTsdf(voxel);
  options.reserve_blocks = reserve_blocks;
  HolocapRun run = RunHolocap(inputs, options, threads);
  std::printf("holocap %.6f %.6f %zu %.1f %zu\n", run.integrate_s, run.mesh_s,
              run.meshes[0].faces.size(), PeakRssMb() - base, run.blocks);
  return 0;
}

PeerResult RunHolocapPeakMemory(const fs::path& dir, double voxel, int threads,
                                size_t reserve_blocks, const char* self) {
  const std::string command = "OMP_WAIT_POLICY=PASSIVE '" + std::string(self) +
                              "' --peak-memory '" + dir.string() + "' " + std::to_string(voxel) +
                              " " + std::to_string(threads) + " " + std::to_string(reserve_blocks);
  FILE* pipe = popen(command.c_str(), "r");
  if (pipe == nullptr) Fail("cannot run ", command);
  PeerResult r;
  bool read = false;
  char line[512] = {};
  while (std::fgets(line, sizeof(line), pipe)) {
    char name[32] = {};
    read = read || std::sscanf(line, "%31s %lf %lf %ld %lf %ld", name, &r.integrate_s, &r.mesh_s,
                               &r.triangles, &r.peak_mb, &r.blocks) == 6;
  }
  if (pclose(pipe) != 0 || !read) Fail("recon_bench --peak-memory failed: ", command);
  return r;
}

// Peak memory of each method at `voxel`, each in a process of its own (peak RSS less the RSS
// before the first volume), on the maps FusionAgainstOpen3d wrote for that voxel size.
// VoxelBlockGrid allocates and zeroes its block_count blocks when it is made; holocap's volume
// does so when asked (reserve_blocks). So each is measured with the same reservation: the
// script's 50000 blocks for both, then each sized to the blocks the scene needs of it (the most
// one volume held in a first run, 50000 reserved) plus the same headroom, kSizedHeadroom.
constexpr double kSizedHeadroom = 0.1;
void PeakMemory(const std::vector<std::vector<DepthInput>>& pinhole, double voxel, int threads,
                const fs::path& work, const char* self) {
  const fs::path dir = work / ("open3d-memory-" + std::to_string(static_cast<int>(voxel * 1e4)));
  WriteOpen3dInput(pinhole, dir);
  std::printf(
      "== peak memory at %.0f mm: %zu frame(s) x %zu depth maps, each method in its own "
      "process (peak RSS growth while fusing and meshing; reserved: blocks allocated and zeroed "
      "when a volume is made, sized: the blocks the scene needs of that method plus %.0f%%); "
      "load %s\n",
      voxel * 1e3, pinhole.size(), pinhole[0].size(), 100 * kSizedHeadroom, LoadNow().c_str());
  std::printf("%-20s %9s %9s %12s %10s %10s %10s\n", "method", "reserved", "held", "peak_MB",
              "integr_s", "mesh_s", "triangles");
  const auto row = [](const char* label, size_t reserved, const PeerResult& r) {
    std::printf("%-20s %9zu %9ld %12.1f %10.3f %10.3f %10ld\n", label, reserved, r.blocks,
                r.peak_mb, r.integrate_s, r.mesh_s, r.triangles);
  };
  const auto sized = [](long blocks) {
    return static_cast<size_t>(std::ceil((1 + kSizedHeadroom) * static_cast<double>(blocks)));
  };
  const PeerResult holocap_grown = RunHolocapPeakMemory(dir, voxel, threads, 0, self);
  const PeerResult holocap_reserved =
      RunHolocapPeakMemory(dir, voxel, threads, kPeerBlockCount, self);
  const PeerResult vbg_reserved = RunOpen3d(dir, voxel, "vbg", threads, kPeerBlockCount).at("vbg");
  const PeerResult dense_reserved =
      RunOpen3d(dir, voxel, "vbg-dense", threads, kPeerBlockCount).at("vbg-dense");
  row("holocap", kPeerBlockCount, holocap_reserved);
  row("Open3D VBG", kPeerBlockCount, vbg_reserved);
  row("Open3D VBG dense", kPeerBlockCount, dense_reserved);
  const size_t holocap_blocks = sized(holocap_reserved.blocks);
  const size_t vbg_blocks = sized(vbg_reserved.blocks);
  const size_t dense_blocks = sized(dense_reserved.blocks);
  row("holocap sized", holocap_blocks,
      RunHolocapPeakMemory(dir, voxel, threads, holocap_blocks, self));
  row("Open3D VBG sized", vbg_blocks, RunOpen3d(dir, voxel, "vbg", threads, vbg_blocks).at("vbg"));
  row("Open3D VBG dense sz", dense_blocks,
      RunOpen3d(dir, voxel, "vbg-dense", threads, dense_blocks).at("vbg-dense"));
  row("holocap as touched", 0, holocap_grown);
  row("Open3D Scalable", 0, RunOpen3d(dir, voxel, "legacy", threads).at("legacy"));
  std::printf(
      "(Scalable and holocap as touched reserve nothing: they take each block's memory "
      "when a frame first touches it)\n\n");
}

// Fuses a sequence into one volume (the subject walks, the volume grows): seconds per frame
// set (all its maps) at points along it, holocap against both peers, and the final mesh.
void FusionSequence(const std::vector<std::vector<DepthInput>>& pinhole, double voxel, int threads,
                    const fs::path& work) {
  const fs::path dir = work / "open3d-sequence";
  WriteOpen3dInput(pinhole, dir);
  std::printf(
      "== a sequence fused into one volume: %zu frame sets x %zu depth maps, %.0f mm, %d "
      "threads, OMP_WAIT_POLICY=%s; load %s\n",
      pinhole.size(), pinhole[0].size(), voxel * 1e3, threads, std::getenv("OMP_WAIT_POLICY"),
      LoadNow().c_str());
  TsdfOptions options = PlainTsdf(voxel);
  options.threads = threads;
  TsdfVolume tsdf(options);
  std::vector<double> holocap_s;
  std::vector<size_t> blocks;
  for (const auto& frame : pinhole) {
    double t0 = Now();
    for (const auto& d : frame) tsdf.Integrate(d.depth, d.camera);
    holocap_s.push_back(Now() - t0);
    blocks.push_back(tsdf.volume().block_count());
  }
  double t0 = Now();
  Mesh mesh = ExtractMesh(tsdf.volume());
  const double holocap_mesh_s = Now() - t0;
  std::map<std::string, std::vector<double>> peer_s;
  std::map<std::string, double> peer_mesh_s;
  std::string command =
      "OMP_NUM_THREADS=" + std::to_string(threads) + " OMP_WAIT_POLICY=PASSIVE /usr/bin/python3 '" +
      std::string(HOLOCAP_BENCH_DIR) + "/open3d_tsdf.py' '" + dir.string() + "' " +
      std::to_string(voxel) + " " + std::to_string(options.truncation_voxels) + " " +
      std::to_string(options.depth_max_m) + " vbg-sequence,vbg-dense-sequence,legacy-sequence '" +
      (dir / "mesh").string() + "'";
  FILE* pipe = popen(command.c_str(), "r");
  std::string text;
  char buffer[4096];
  size_t n;
  while (pipe && (n = std::fread(buffer, 1, sizeof(buffer), pipe)) > 0) text.append(buffer, n);
  if (pipe) pclose(pipe);
  std::istringstream lines(text);
  std::string line;
  while (std::getline(lines, line)) {
    std::istringstream words(line);
    std::string name;
    words >> name;
    double value;
    if (name.ends_with("-times")) {
      while (words >> value) peer_s[name.substr(0, name.size() - 6)].push_back(value);
    } else if (words >> value >> value) {
      peer_mesh_s[name] = value;
    }
  }
  std::printf("%12s %12s %8s %16s %16s %16s\n", "frame_sets", "holocap_s", "blocks", "VBG_s",
              "VBG_dense_s", "Scalable_s");
  auto mean = [](const std::vector<double>& v, size_t from, size_t to) {
    double sum = 0;
    for (size_t i = from; i < to && i < v.size(); ++i) sum += v[i];
    return to > from && !v.empty() ? sum / (std::min(to, v.size()) - from) : 0.0;
  };
  for (size_t end = 10; end <= pinhole.size(); end += 10) {
    std::printf("%5zu-%-6zu %12.4f %8zu %16.4f %16.4f %16.4f\n", end - 9, end,
                mean(holocap_s, end - 10, end), blocks[end - 1],
                mean(peer_s["vbg-sequence"], end - 10, end),
                mean(peer_s["vbg-dense-sequence"], end - 10, end),
                mean(peer_s["legacy-sequence"], end - 10, end));
  }
  std::printf(
      "%-12s %12.4f %8s %16.4f %16.4f %16.4f   (s, the final volume; holocap %zu triangles)\n\n",
      "mesh", holocap_mesh_s, "", peer_mesh_s["vbg-sequence"], peer_mesh_s["vbg-dense-sequence"],
      peer_mesh_s["legacy-sequence"], mesh.faces.size());
}

// studio8 with a depth sensor beside every one of its eight colour cameras (depth0's lens and
// offset), written as a sim rig file.
fs::path Studio8WithEightDepthSensors(const fs::path& work) {
  nlohmann::json rig = BuiltinRig("studio8").ToJson();
  fs::path file = work / "studio8-depth8.json";
  nlohmann::json sensors = nlohmann::json::array(), depth;
  for (const auto& sensor : rig["sensors"]) {
    if (sensor["role"] == "depth") {
      if (depth.is_null()) depth = sensor;
      continue;
    }
    sensors.push_back(sensor);
  }
  for (int i = 0; i < 8; ++i) {
    nlohmann::json d = depth;
    d["name"] = "depth" + std::to_string(i);
    d["uri"] = "sim:" + file.string() + "#depth" + std::to_string(i);
    d["paired_with"] = "cam" + std::to_string(i);
    sensors.push_back(d);
  }
  rig["name"] = "studio8-depth8";
  rig["sensors"] = sensors;
  std::ofstream(file) << rig.dump(2);
  return file;
}

void VoxelSweep(const std::vector<BenchFrame>& frames, int threads) {
  std::vector<std::vector<DepthInput>> original;
  original.reserve(frames.size());
  for (const BenchFrame& f : frames) original.push_back(f.depth);
  for (const auto& d : original[0]) TsdfVolume(TsdfOptions{}).Integrate(d.depth, d.camera);
  std::printf("== holocap TSDF as the voxel varies (true lenses, filtered; %d threads)\n", threads);
  std::printf(kHeader, "method", "voxmm", "integr_s/fr", "mesh_s", "triangles", "chamfer",
              "accuracy", "complete", "seen_ch", "F@5seen", "blocks  MB  peakRSS_MB");
  for (double voxel : {0.016, 0.008, 0.004, 0.002, 0.001}) {
    TsdfOptions options;
    options.voxel_m = voxel;
    HolocapRun run = RunHolocap(original, options, threads);
    SurfaceErrors all, seen;
    MeanErrors(run.meshes, frames, &all, &seen);
    char extra[96];
    std::snprintf(extra, sizeof(extra), "%6zu %5.0f %8.0f", run.blocks, run.memory_mb, PeakRssMb());
    PrintErrors("holocap", voxel, run.integrate_s, run.mesh_s, run.meshes[0].faces.size(), all,
                seen, extra);
  }
  std::printf("\n");
}

// The target figure: the pipeline's TSDF from the depth sensors, with and without the
// hull-constrained completion of what they did not see, every frame against the whole truth.
void PipelineTsdf(const fs::path& take_dir, int frame_count, int threads) {
  std::printf(
      "== studio8 TSDF from the depth sensors through the pipeline (holocap reconstruct --method "
      "tsdf), "
      "%d frame(s), %d threads\n",
      frame_count, threads);
  std::printf(
      "(bg: the background carves free space in the fusion itself, "
      "TsdfOptions::carve_background)\n");
  std::printf("%-30s %6s %9s %9s %9s %9s %9s %9s %8s %10s\n", "completion", "voxmm", "frame_s",
              "hull+fill", "chamfer", "accuracy", "complete", "seen_ch", "F@5mm", "ch_buried");
  for (double voxel : {0.008, 0.004}) {
    for (auto [complete, carve] : {std::pair{false, false}, std::pair{false, true},
                                   std::pair{true, false}, std::pair{true, true}}) {
      ReconstructionOptions options;
      options.tsdf.carve_background = carve;
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
      std::printf(
          "%-30s %6.1f %9.2f %9.2f %9.2f %9.2f %9.2f %9.2f %8.3f %10.2f\n",
          Cat(complete ? "hull carved by free space" : "none (sensors only)", carve ? ", bg" : "")
              .c_str(),
          voxel * 1e3, metrics["timing"]["mean_frame_s"].get<double>(), completion_s,
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
        View view{s.name, take.Camera(s.name), take.ReadFrame(frame.set, s.name), {}};
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
  const auto& streams = take.streams();
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

// Simulates a take once (reused when there).
void SimulateOnce(const std::string& rig, const fs::path& dir, int frame_sets) {
  if (fs::exists(dir / "take.json")) return;
  SimOptions sim;
  sim.rig = rig;
  sim.frames = frame_sets + 1;
  sim.clean_plate_frames = 1;
  sim.seed = 7;
  sim.overwrite = true;
  SimulateTake(sim, dir);
  // Calibrated as a user's take is (a board take of the rig, its models taken over); the truth
  // only scores.
  std::printf("%s: %s\n", dir.c_str(), bench::CalibrateFromBoardTake(sim, dir).c_str());
}

// Frame sets 1..count of a take: each depth map's foreground (against the clean plate of set 0),
// the true mesh and the truth filters.
std::vector<BenchFrame> LoadFrames(const fs::path& take_dir, int count) {
  const Take take = Take::Open(take_dir);
  // The inputs are the calibration's cameras, in the world it chose; the truth is laid into that
  // world to score (the rigid motion that best lays the true rig onto the solved one, as the
  // pipeline's own scores do), so every side is scored alike.
  std::map<std::string, CameraModel> solved;
  std::map<std::string, CameraModel> truth;
  for (const StreamInfo& s : take.streams()) {
    solved.emplace(s.name, take.Camera(s.name));
    truth.emplace(s.name, take.Camera(s.name, true));
  }
  const Pose solved_from_true = AlignRigs(truth, solved);
  std::vector<BenchFrame> frames;
  for (int64_t set = 1; set <= count && set < static_cast<int64_t>(take.size()); ++set) {
    BenchFrame frame;
    frame.set = set;
    frame.truth = ReadPly(take.gt_dir() / "meshes" / (SetName(set) + ".ply"));
    const Eigen::Isometry3f moved = solved_from_true.cast<float>();
    for (auto& v : frame.truth.vertices) v = moved * v;
    for (auto& n : frame.truth.normals) n = moved.linear() * n;
    std::vector<std::pair<CameraModel, cv::Mat>> seen;
    for (const StreamInfo& s : take.streams()) {
      if (s.role != SensorRole::kDepth) continue;
      const CameraModel& camera = solved.at(s.name);
      cv::Mat raw = take.ReadFrame(set, s.name);
      cv::Mat foreground =
          DepthForeground(raw, take.ReadFrame(0, s.name), TsdfOptions{}.depth_noise_k);
      cv::Mat depth = raw.clone();
      depth.setTo(std::numeric_limits<float>::quiet_NaN(), foreground == 0);
      frame.depth.push_back({camera, depth, raw, foreground});
      // The true depth was rendered by the true camera: the same camera in the solved world.
      CameraModel true_camera = truth.at(s.name);
      true_camera.set_cam_from_world(true_camera.cam_from_world() * solved_from_true.inverse());
      seen.emplace_back(true_camera,
                        ReadImage(take.gt_dir() / "depth" / s.name / (SetName(set) + ".exr")));
    }
    frame.seen = SeenInDepthMaps(seen);
    frame.outer = OnOuterSurface(frame.truth);
    frames.push_back(std::move(frame));
  }
  return frames;
}

std::vector<std::vector<DepthInput>> Pinhole(const std::vector<BenchFrame>& frames) {
  std::vector<std::vector<DepthInput>> pinhole;
  for (const BenchFrame& f : frames) {
    pinhole.emplace_back();
    for (const auto& d : f.depth) pinhole.back().push_back(ToPinhole(d));
  }
  return pinhole;
}

// Section 6: studio8 with eight depth sensors at 4 and 2 mm, and a 60-set sequence.
void LargerFusionCases(const fs::path& work, int threads, int repeats) {
  const fs::path eight = work / "studio8-depth8";
  SimulateOnce(Studio8WithEightDepthSensors(work).string(), eight, 1);
  std::vector<BenchFrame> frames = LoadFrames(eight, 1);
  FusionAgainstOpen3d("studio8 with a depth sensor beside each of its 8 cameras", frames,
                      Pinhole(frames), {0.004, 0.002}, threads, repeats, work);
  const fs::path walk = work / "studio8-60";
  SimulateOnce("studio8", walk, 60);
  std::vector<BenchFrame> sequence = LoadFrames(walk, 60);
  FusionSequence(Pinhole(sequence), 0.004, threads, work);
}

// Usage: recon_bench [frames=2] [threads=2] [work_dir] [sections=1234] [repeats=5]
//        recon_bench --peak-memory DIR VOXEL_M THREADS RESERVE_BLOCKS  (one process per
//                    measurement)
//        recon_bench --stages DIR VOXEL_M THREADS REPEATS  (integration by stage)
int Main(int argc, char** argv) {
  // Every side of the comparisons waits passively: libgomp's spinning threads on a shared
  // machine measure the load, not the code. The variable is read when libgomp loads.
  if (std::getenv("OMP_WAIT_POLICY") == nullptr) {
    setenv("OMP_WAIT_POLICY", "PASSIVE", 1);
    execv("/proc/self/exe", argv);
  }
  if (argc == 6 && std::string(argv[1]) == "--stages") {
    IntegrationStages(ReadOpen3dInput(argv[2]), {std::atof(argv[3])}, std::atoi(argv[4]),
                      std::atoi(argv[5]));
    return 0;
  }
  if (argc == 6 && std::string(argv[1]) == "--peak-memory")
    return PeakMemoryMode(argv[2], std::atof(argv[3]), std::atoi(argv[4]),
                          std::strtoull(argv[5], nullptr, 10));
  const int frame_count = argc > 1 ? std::atoi(argv[1]) : 2;
  const int threads = argc > 2 ? std::atoi(argv[2]) : 2;
  const fs::path work = argc > 3 ? argv[3] : "/tmp/holocap-recon-bench";
  const std::string sections = argc > 4 ? argv[4] : "1234";
  const int repeats = argc > 5 ? std::atoi(argv[5]) : 5;
  try {
    fs::create_directories(work);
    if (sections.find('5') != std::string::npos) MiddleburyNoFlags(work, threads);
    if (sections.find('6') != std::string::npos) LargerFusionCases(work, threads, repeats);
    if (sections.find_first_of("1234m") == std::string::npos) return 0;
    const fs::path take_dir = work / "studio8";
    SimulateOnce("studio8", take_dir, frame_count);
    std::vector<BenchFrame> frames = LoadFrames(take_dir, frame_count);
    std::printf("recon_bench: %zu frame(s) of %s, %d threads\n", frames.size(), take_dir.c_str(),
                threads);
    std::printf(
        "chamfer/accuracy/complete in mm against gt/meshes, completeness on the subject's outer "
        "surface (the "
        "body parts' faces buried inside other parts left out; ch_buried keeps them); seen_ch and "
        "F@5seen only "
        "on the true surface a depth sensor saw\n\n");
    if (sections.find('1') != std::string::npos) {
      const auto pinhole = Pinhole(frames);
      if (sections.find('p') == std::string::npos) {
        FusionAgainstOpen3d("studio8 depth fusion, holocap against Open3D", frames, pinhole,
                            {0.008, 0.004}, threads, repeats, work);
      }
      IntegrationStages(pinhole, {0.008, 0.004}, threads, repeats);
      if (sections.find('p') == std::string::npos)
        PeakMemory(pinhole, 0.002, threads, work, argv[0]);
    } else if (sections.find('m') != std::string::npos) {
      PeakMemory(Pinhole(frames), 0.002, threads, work, argv[0]);
    }
    if (sections.find('2') != std::string::npos) VoxelSweep(frames, threads);
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

}  // namespace

int main(int argc, char** argv) {
  try {
    return Main(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "recon_bench: error: %s\n", e.what());
  } catch (...) {
    std::fprintf(stderr, "recon_bench: error: an unknown exception\n");
  }
  return 1;
}
