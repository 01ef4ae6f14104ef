// Scanning with one moving RGB-D sensor against Open3D's tensor odometry and dense SLAM on the
// same simulated frames: trajectory error (ATE RMSE after rigid alignment, RPE between
// consecutive frames), frames per second of tracking + fusion, and the scanned mesh against the
// true surface beside a studio8 reconstruction of the same subject pose.
//
//   build/bench/scan_bench [--frames N] [--sizes 320x240,640x480] [--trajectories orbit,handheld]
//                          [--threads T] [--photometric W] [--keep DIR]
//
// Open3D runs in /usr/bin/python3 (bench/open3d_odometry.py) with OMP_WAIT_POLICY=PASSIVE and
// the same thread count. Open3D is given the depth resampled into a pinhole camera of the
// depth sensor's size and the colour registered to it (its RGB-D tracking needs aligned,
// undistorted images); holocap reads the take as it is.
#include <omp.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <sstream>

#include "core/error.h"
#include "core/fs.h"
#include "core/mesh.h"
#include "core/take.h"
#include "core/trajectory.h"
#include "reconstruction/reconstruction.h"
#include "scan/scan.h"
#include "sim/sim.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;
using Json = nlohmann::json;

struct Args {
  int64_t frames = 60;
  std::vector<std::pair<int, int>> sizes = {{320, 240}, {640, 480}};
  std::vector<std::string> trajectories = {"orbit", "handheld"};
  int threads = 2;
  double photometric_weight_m = ScanOptions().photometric_weight_m;
  fs::path keep;
};

std::string Uptime() {
  std::ifstream in("/proc/loadavg");
  std::string a, b, c;
  in >> a >> b >> c;
  return a + " " + b + " " + c;
}

// The take's depth resampled into a pinhole camera of the same size (nearest measurement) and
// the colour each depth pixel's point sees, as open3d_odometry.py reads them.
void ExportForOpen3d(const Take& take, const TakePlan& plan, const fs::path& dir) {
  const std::string depth_name = plan.depth_sensors.front();
  const std::string color_name = take.stream(depth_name).paired_with;
  const CameraModel depth_lens = plan.cameras.at(depth_name);
  const CameraModel color_lens = plan.cameras.at(color_name);
  const Pose color_from_depth = color_lens.cam_from_world() * depth_lens.world_from_cam();
  const double f = depth_lens.intrinsics()[0];
  const int w = depth_lens.width(), h = depth_lens.height();
  const double cx = depth_lens.intrinsics()[2], cy = depth_lens.intrinsics()[3];
  // Where each pinhole pixel's ray falls in the real lens.
  std::vector<Eigen::Vector2d> source(static_cast<size_t>(w) * h);
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      Eigen::Vector2d pixel(-1, -1);
      depth_lens.Project(Eigen::Vector3d((x - cx) / f, (y - cy) / f, 1), &pixel);
      source[static_cast<size_t>(y) * w + x] = pixel;
    }
  }
  CreateDirectories(dir);
  Json frames = Json::array();
  for (int64_t set : plan.sets) {
    const cv::Mat depth = take.ReadFrame(static_cast<size_t>(set), depth_name);
    const cv::Mat color = take.ReadFrame(static_cast<size_t>(set), color_name);
    std::vector<float> out_depth(static_cast<size_t>(w) * h, 0.0f);
    std::vector<uint8_t> out_color(static_cast<size_t>(w) * h * 3, 0);
    for (int y = 0; y < h; ++y) {
      for (int x = 0; x < w; ++x) {
        const size_t i = static_cast<size_t>(y) * w + x;
        const int sx = static_cast<int>(std::lround(source[i].x()));
        const int sy = static_cast<int>(std::lround(source[i].y()));
        if (sx < 0 || sy < 0 || sx >= w || sy >= h) continue;
        const float d = depth.at<float>(sy, sx);
        if (!(d > 0)) continue;
        out_depth[i] = d;
        Eigen::Vector2d pc;
        const Eigen::Vector3d p(d * (x - cx) / f, d * (y - cy) / f, d);
        if (!color_lens.Project(color_from_depth * p, &pc)) continue;
        const int u = static_cast<int>(std::lround(pc.x())),
                  v = static_cast<int>(std::lround(pc.y()));
        if (u < 0 || v < 0 || u >= color.cols || v >= color.rows) continue;
        const uint8_t* bgr = color.ptr<uint8_t>(v) + u * color.channels();
        for (int c = 0; c < 3; ++c) out_color[3 * i + c] = bgr[2 - c];
      }
    }
    const std::string name = Cat(set);
    WriteFileAtomic(dir / (name + ".depth"),
                    std::string_view(reinterpret_cast<const char*>(out_depth.data()),
                                     out_depth.size() * sizeof(float)));
    WriteFileAtomic(
        dir / (name + ".rgb"),
        std::string_view(reinterpret_cast<const char*>(out_color.data()), out_color.size()));
    const int64_t stamp = take.entry(static_cast<size_t>(set)).Find(depth_name)->timestamp_ns;
    frames.push_back({{"time_s", 1e-9 * static_cast<double>(stamp)},
                      {"depth", name + ".depth"},
                      {"color", name + ".rgb"}});
  }
  const Eigen::Matrix4d first = depth_lens.world_from_cam().matrix();
  std::vector<double> rows;
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) rows.push_back(first(r, c));
  const Json meta = {{"width", w}, {"height", h}, {"fx", f},          {"fy", f},
                     {"cx", cx},   {"cy", cy},    {"frames", frames}, {"world_from_cam", rows}};
  WriteFileAtomic(dir / "frames.json", meta.dump());
}

struct PeerRun {
  std::string name;
  double seconds_per_frame = 0;
  double cpu_seconds_per_frame = 0;
  TrajectoryErrors errors;
};

std::vector<PeerRun> RunOpen3d(const fs::path& dir, double voxel_m, double depth_max_m, int threads,
                               const std::vector<StampedPose>& truth) {
  const std::string command = Cat("OMP_WAIT_POLICY=PASSIVE OMP_NUM_THREADS=", threads,
                                  " /usr/bin/python3 ", HOLOCAP_BENCH_DIR, "/open3d_odometry.py ",
                                  dir.string(), " odometry ", voxel_m, " ", depth_max_m, " 2>&1");
  std::vector<PeerRun> runs;
  FILE* pipe = popen(command.c_str(), "r");
  if (pipe == nullptr) return runs;
  char line[512];
  while (std::fgets(line, sizeof(line), pipe) != nullptr) {
    std::istringstream fields(line);
    PeerRun run;
    int64_t frames = 0;
    if (!(fields >> run.name >> run.seconds_per_frame >> frames >> run.cpu_seconds_per_frame)) {
      std::printf("  open3d: %s", line);
      continue;
    }
    const fs::path tum = dir / (run.name + ".tum");
    run.errors = CompareTrajectories(ParseTum(ReadFileToString(tum), tum.string()), truth);
    runs.push_back(run);
  }
  pclose(pipe);
  return runs;
}

// The scanned mesh's part above the floor and near the subject against the true subject.
SurfaceErrors ScanQuality(const Mesh& scanned, const Mesh& truth) {
  Eigen::AlignedBox3f box;
  for (const auto& v : truth.vertices) box.extend(v);
  box.min() -= Eigen::Vector3f(0.05f, 0.05f, 0.0f);
  box.max() += Eigen::Vector3f::Constant(0.05f);
  box.min().z() = box.min().z() + 0.02f;  // the floor is scanned too: not the subject
  Mesh cropped;
  std::vector<int> index(scanned.vertices.size(), -1);
  for (const auto& face : scanned.faces) {
    bool inside = true;
    for (int k = 0; k < 3; ++k) inside = inside && box.contains(scanned.vertices[face[k]]);
    if (!inside) continue;
    Eigen::Vector3i f;
    for (int k = 0; k < 3; ++k) {
      if (index[face[k]] < 0) {
        index[face[k]] = static_cast<int>(cropped.vertices.size());
        cropped.vertices.push_back(scanned.vertices[face[k]]);
      }
      f[k] = index[face[k]];
    }
    cropped.faces.push_back(f);
  }
  return CompareSurfaces(cropped, truth, 0.005, 40000, OnOuterSurface(truth));
}

// cpu_ms: CPU time a frame (every thread); fusion_ms: of which fusion (negative: none).
void PrintRow(const std::string& trajectory, const std::string& size, const std::string& method,
              const TrajectoryErrors& e, double fps, double cpu_ms, double fusion_ms,
              const std::string& note) {
  const std::string fusion = fusion_ms < 0 ? "-" : Cat(std::lround(fusion_ms));
  std::printf(
      "| %-8s | %-7s | %-34s | %7.2f | %7.2f | %7.3f | %6.1f | %7.1f | %6s | %6.1f | %s |\n",
      trajectory.c_str(), size.c_str(), method.c_str(), 100 * e.ate_rmse_m, 1e3 * e.rpe_trans_m,
      e.rpe_rot_deg, fps, cpu_ms, fusion.c_str(), cpu_ms > 0 ? 1e3 / cpu_ms : 0.0, note.c_str());
  std::fflush(stdout);
}

void TrackingSection(const Args& args, const fs::path& work) {
  std::printf(
      "\n## Tracking: ATE RMSE (cm, rigid alignment), RPE per frame (mm, deg), fps of "
      "tracking + fusion (wall clock, shared machine); CPU ms a frame (process CPU time, every "
      "thread; fusion: of which fusing); 1-core fps = 1000 / CPU ms, the rate on one idle core; "
      "%lld frames at 10 fps, 30 deg/s around the subject, %d threads, OMP_WAIT_POLICY=%s\n\n",
      static_cast<long long>(args.frames), args.threads,
      std::getenv("OMP_WAIT_POLICY") ? std::getenv("OMP_WAIT_POLICY") : "(unset)");
  std::printf(
      "| traj.    | size    | method                             | ATE cm  | RPE mm  | RPE deg | "
      "fps    | CPU ms  | fusion | 1-core fps | note |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|---|\n");
  for (const std::string& trajectory : args.trajectories) {
    for (const auto& [w, h] : args.sizes) {
      const std::string size = Cat(w, "x", h);
      const fs::path take_dir = work / Cat(trajectory, "-", size);
      SimOptions sim;
      sim.rig = "single-rgbd";
      sim.trajectory = trajectory;
      sim.frames = args.frames;
      sim.fps = 10;
      sim.image_width = w;
      sim.image_height = h;
      sim.seed = 3;
      sim.overwrite = true;
      sim.threads = args.threads;
      SimulateTake(sim, take_dir);
      const Take take = Take::Open(take_dir);
      const TakePlan plan = PlanTake(take, TakeSelection{});
      ScanOptions options;
      options.threads = args.threads;
      options.photometric_weight_m = args.photometric_weight_m;
      const std::string load_before = Uptime();
      const ScanSummary scan = ScanTake(take, plan, take_dir / "scan", options);
      const std::vector<StampedPose> truth = TrueTrajectory(take, plan.depth_sensors.front());
      PrintRow(trajectory, size, "holocap scan (ICP+photometric)",
               scan.errors.value_or(TrajectoryErrors{}), scan.frames_per_second,
               1e3 * scan.cpu_seconds_per_frame, 1e3 * scan.fusion_cpu_seconds_per_frame,
               Cat(ToString(scan.termination), ", lost ", scan.lost, ", loops ", scan.loops,
                   ", load ", load_before));
      ExportForOpen3d(take, plan, take_dir / "open3d");
      for (const PeerRun& peer : RunOpen3d(take_dir / "open3d", options.voxel_m,
                                           options.depth_max_m, args.threads, truth)) {
        PrintRow(trajectory, size,
                 peer.name == "slam" ? "Open3D slam.Model (frame to model)"
                                     : "Open3D rgbd odometry (hybrid, f2f)",
                 peer.errors, 1.0 / std::max(1e-9, peer.seconds_per_frame),
                 1e3 * peer.cpu_seconds_per_frame, -1.0,
                 Cat("matched ", peer.errors.matched, ", load ", Uptime()));
      }
    }
  }
}

void QualitySection(const Args& args, const fs::path& work) {
  std::printf("\n## Scan quality against the true subject (outer surface, F-score at 5 mm)\n\n");
  std::printf(
      "| what | chamfer mm | accuracy mm | completeness mm | F@5mm |\n|---|---|---|---|---|\n");
  const fs::path orbit =
      work / Cat("orbit-", args.sizes.front().first, "x", args.sizes.front().second);
  const Mesh truth = ReadPly(orbit / "gt" / "meshes" / "000000.ply");
  if (fs::exists(orbit / "scan" / "mesh.ply")) {
    const SurfaceErrors e = ScanQuality(ReadPly(orbit / "scan" / "mesh.ply"), truth);
    std::printf("| scan, orbit %s, %lld frames | %.2f | %.2f | %.2f | %.3f |\n",
                orbit.filename().c_str(), static_cast<long long>(args.frames), e.chamfer_mm,
                e.accuracy_mm, e.completeness_mm, e.fscore);
  }
  SimOptions sim;
  sim.rig = "studio8";
  sim.clean_plate_frames = 1;
  sim.frames = 2;
  // The subject holds its first pose, as the scan take's does: a turn at 0 degrees a second
  // keeps every sensor fixed and the subject where it stood at t = 0.
  sim.trajectory = "turn";
  sim.trajectory_deg_per_s = 0;
  sim.seed = 3;
  sim.overwrite = true;
  sim.threads = args.threads;
  const fs::path studio = work / "studio8";
  SimulateTake(sim, studio);
  ReconstructionOptions options;
  options.sweep_voxels_m.clear();
  options.threads = args.threads;
  options.write_glb = false;
  const ReconstructionSummary recon =
      ReconstructTake(studio, TakeSelection{}, studio / "recon", options);
  for (const FrameResult& f : recon.frames) {
    if (!f.metrics.contains("gt")) continue;
    // The same subject pose: the two takes' true meshes, vertex by vertex.
    char name[32];
    std::snprintf(name, sizeof(name), "%06lld.ply", static_cast<long long>(f.set));
    const Mesh studio_truth = ReadPly(studio / "gt" / "meshes" / name);
    double apart_m = studio_truth.vertices.size() == truth.vertices.size() ? 0 : INFINITY;
    for (size_t i = 0; std::isfinite(apart_m) && i < truth.vertices.size(); ++i)
      apart_m = std::max<double>(apart_m, (studio_truth.vertices[i] - truth.vertices[i]).norm());
    std::printf(
        "(studio8 set %lld's true subject against the scan take's: %zu vs %zu vertices, "
        "%.2f mm apart at most)\n",
        static_cast<long long>(f.set), studio_truth.vertices.size(), truth.vertices.size(),
        1e3 * apart_m);
    const Json& gt = f.metrics["gt"];
    std::printf(
        "| studio8 reconstruct (8 colour + 2 depth, fixed), set %lld | %.2f | %.2f | %.2f | %.3f "
        "|\n",
        static_cast<long long>(f.set), gt["chamfer_mm"].get<double>(),
        gt["accuracy_mm"].get<double>(), gt["completeness_mm"].get<double>(),
        gt["fscore_5mm"].get<double>());
  }
}

}  // namespace
}  // namespace holocap

int main(int argc, char** argv) {
  using namespace holocap;
  Args args;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string flag = argv[i], value = argv[i + 1];
    if (flag == "--frames") args.frames = std::stoll(value);
    if (flag == "--threads") args.threads = std::stoi(value);
    if (flag == "--photometric") args.photometric_weight_m = std::stod(value);
    if (flag == "--keep") args.keep = value;
    if (flag == "--trajectories") {
      args.trajectories.clear();
      std::stringstream list(value);
      for (std::string item; std::getline(list, item, ',');) args.trajectories.push_back(item);
    }
    if (flag == "--sizes") {
      args.sizes.clear();
      std::stringstream list(value);
      for (std::string item; std::getline(list, item, ',');) {
        int w = 0, h = 0;
        if (std::sscanf(item.c_str(), "%dx%d", &w, &h) == 2) args.sizes.emplace_back(w, h);
      }
    }
  }
  const std::filesystem::path work =
      args.keep.empty() ? std::filesystem::temp_directory_path() / "holocap-scan-bench" : args.keep;
  std::printf("# scan_bench: one moving RGB-D sensor (single-rgbd), load at start %s\n",
              Uptime().c_str());
  try {
    TrackingSection(args, work);
    QualitySection(args, work);
  } catch (const Error& e) {
    std::printf("error: %s\n", e.what());
    return 1;
  }
  return 0;
}
