// Scanning with one moving RGB-D sensor against Open3D's dense RGB-D SLAM on the same simulated
// frames: trajectory error of every frame (ATE RMSE after rigid alignment, RPE between
// consecutive frames), frames per second of the per-frame loop (tracking + fusion), and the
// scanned mesh against the true surface beside a studio8 reconstruction of the same subject pose.
//
//   build/bench/scan_bench [--frames N] [--fps F] [--sizes 320x240,640x480]
//                          [--trajectories orbit,handheld,turn] [--threads T] [--repeats R]
//                          [--photometric W] [--keep DIR]
//
// The cameras are calibrated as a user must: a board take of the same rig at the same size is
// simulated and calibrated (CalibrateTake), and its calib/*.cameramodel copied into the scan
// take's calib/. Open3D (bench/open3d_slam.py, /usr/bin/python3, o3d.t.pipelines.slam.Model:
// track_frame_to_model, integrate, synthesize_model_frame) reads the take's depth maps as they
// are (float metres, no resampling, no rounding) with the colour registered to the depth pixels;
// it takes only a pinhole camera, so holocap is given the same one (the calibrated depth lens
// with its distortion dropped: both see the same intrinsics). Open3D's tracking is geometric
// (point to plane); a row gives holocap's with its photometric term off, and another holocap's
// scan with the calibrated lens, as a user runs it. Turn takes scan with
// ScanOptions::subject_turns set, and Open3D gets their depth without the floor that holocap's
// turntable mode leaves out (the sensor stands still: the floor does not turn with the subject).
// Every frame counts for both: a frame holocap
// loses keeps the pose it gave it (the last good one), and after a stopped scan the last pose
// holds. The methods run one after another, R times (interleaved; holocap in this process,
// Open3D in its own), with the same threads and OMP_WAIT_POLICY=PASSIVE; fps and CPU ms are the
// medians.
#include <omp.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <map>
#include <optional>
#include <sstream>

#include "bench/calibrated_sim.h"
#include "calibration/calibration.h"
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
  // The sensor's own rate (the rig's 30 fps) for 6 s at 30 deg/s: half an orbit, 1 degree a
  // frame. Open3D's dense SLAM starts each frame from the previous pose with a few iterations
  // (6/3/1); at 10 fps (3 degrees, ~11.5 cm a frame) it recovered 2.3 cm of the first step.
  int64_t frames = 180;
  double fps = 30;
  std::vector<std::pair<int, int>> sizes = {{320, 240}, {640, 480}};
  std::vector<std::string> trajectories = {"orbit", "handheld"};
  int threads = 2;
  int repeats = 3;
  double photometric_weight_m = ScanOptions().photometric_weight_m;
  fs::path keep;
};

std::string Uptime() {
  std::ifstream in("/proc/loadavg");
  std::string a, b, c;
  in >> a >> b >> c;
  return a + " " + b + " " + c;
}

double Median(std::vector<double> values) {
  if (values.empty()) return 0;
  std::sort(values.begin(), values.end());
  const size_t n = values.size();
  return n % 2 == 1 ? values[n / 2] : 0.5 * (values[n / 2 - 1] + values[n / 2]);
}

// A board take of the same rig at the same size, calibrated; the scan take takes its models over
// (`holocap calibrate SCAN_TAKE --from BOARD_TAKE`).
void CalibrateLikeAUser(const fs::path& board_dir, const fs::path& scan_dir, int width, int height,
                        int threads) {
  SimOptions sim;
  sim.rig = "single-rgbd";
  sim.scene = "board";
  sim.frames = 30;
  sim.image_width = width;
  sim.image_height = height;
  sim.seed = 3;
  sim.overwrite = true;
  sim.threads = threads;
  std::printf("(board take %s: %s)\n", board_dir.filename().c_str(),
              bench::CalibrateBoardTake(sim, board_dir).c_str());
  AdoptCalibration(scan_dir, board_dir);
}

// The plan with the depth sensor's lens reduced to its pinhole part (fx, fy, cx, cy): the camera
// Open3D is given, so that holocap can be given the same.
TakePlan WithPinholeDepth(TakePlan plan) {
  CameraModel& lens = plan.cameras.at(plan.depth_sensors.front());
  const std::vector<double>& k = lens.intrinsics();
  if (lens.lensmodel() != "LENSMODEL_PINHOLE" && lens.lensmodel().rfind("LENSMODEL_OPENCV", 0) != 0)
    Fail("scan_bench: the depth lens ", lens.lensmodel(), " has no pinhole part to give Open3D");
  lens = CameraModel("LENSMODEL_PINHOLE", {k[0], k[1], k[2], k[3]}, lens.width(), lens.height(),
                     lens.cam_from_world());
  return plan;
}

// The take's depth maps as they are (float32 metres; no measurement: 0, Open3D's convention)
// and the colour each depth pixel's point sees, through the pinhole depth camera of `plan`, for
// open3d_slam.py. With `floor_margin_m` (a turntable take: the sensor stands still and the floor
// does not turn with the subject) the points within it of the plan's floor are left out, as
// holocap's scan leaves them out of tracking and fusion (ScanOptions::floor_margin_m).
void ExportForOpen3d(const Take& take, const TakePlan& plan, const fs::path& dir,
                     std::optional<double> floor_margin_m) {
  const std::string depth_name = plan.depth_sensors.front();
  const std::string color_name = take.stream(depth_name).paired_with;
  const CameraModel& depth_lens = plan.cameras.at(depth_name);
  const CameraModel& color_lens = plan.cameras.at(color_name);
  const Pose color_from_depth = color_lens.cam_from_world() * depth_lens.world_from_cam();
  const std::vector<double>& k = depth_lens.intrinsics();
  const int w = depth_lens.width(), h = depth_lens.height();
  if (floor_margin_m && !std::isfinite(plan.floor_m))
    Fail("scan_bench: the plan of ", take.dir().string(), " found no floor to leave out");
  const Pose world_from_depth = depth_lens.world_from_cam();
  CreateDirectories(dir);
  Json frames = Json::array();
  for (int64_t set : plan.sets) {
    const cv::Mat depth = take.ReadFrame(static_cast<size_t>(set), depth_name);
    const cv::Mat color = take.ReadFrame(static_cast<size_t>(set), color_name);
    if (depth.cols != w || depth.rows != h || depth.type() != CV_32F)
      Fail("scan_bench: depth frame of set ", set, " is not ", w, "x", h, " float");
    std::vector<float> out_depth(static_cast<size_t>(w) * h, 0.0f);
    std::vector<float> out_color(static_cast<size_t>(w) * h * 3, 0.0f);
    for (int y = 0; y < h; ++y) {
      for (int x = 0; x < w; ++x) {
        const float d = depth.at<float>(y, x);
        if (!(d > 0) || !std::isfinite(d)) continue;
        const size_t i = static_cast<size_t>(y) * w + x;
        const Eigen::Vector3d p(d * (x - k[2]) / k[0], d * (y - k[3]) / k[1], d);
        if (floor_margin_m && plan.up.dot(world_from_depth * p) < plan.floor_m + *floor_margin_m)
          continue;
        out_depth[i] = d;
        Eigen::Vector2d pc;
        if (!color_lens.Project(color_from_depth * p, &pc)) continue;
        const int u = static_cast<int>(std::lround(pc.x())),
                  v = static_cast<int>(std::lround(pc.y()));
        if (u < 0 || v < 0 || u >= color.cols || v >= color.rows) continue;
        const uint8_t* bgr = color.ptr<uint8_t>(v) + static_cast<ptrdiff_t>(u) * color.channels();
        for (int c = 0; c < 3; ++c) out_color[3 * i + c] = bgr[2 - c] / 255.0f;
      }
    }
    const std::string name = Cat(set);
    WriteFileAtomic(dir / (name + ".depth"),
                    std::string_view(reinterpret_cast<const char*>(out_depth.data()),
                                     out_depth.size() * sizeof(float)));
    WriteFileAtomic(dir / (name + ".rgb"),
                    std::string_view(reinterpret_cast<const char*>(out_color.data()),
                                     out_color.size() * sizeof(float)));
    const int64_t stamp = take.entry(static_cast<size_t>(set)).Find(depth_name)->timestamp_ns;
    frames.push_back({{"time_s", 1e-9 * static_cast<double>(stamp)},
                      {"depth", name + ".depth"},
                      {"color", name + ".rgb"}});
  }
  const Eigen::Matrix4d first = depth_lens.world_from_cam().matrix();
  std::vector<double> rows;
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) rows.push_back(first(r, c));
  const Json meta = {{"width", w}, {"height", h}, {"fx", k[0]},       {"fy", k[1]},
                     {"cx", k[2]}, {"cy", k[3]},  {"frames", frames}, {"world_from_cam", rows}};
  WriteFileAtomic(dir / "frames.json", meta.dump());
}

// One run of one method on one take.
struct MethodRun {
  TrajectoryErrors errors;  // every frame of the plan
  double fps = 0;           // frames / seconds of the per-frame loop (tracking + fusion)
  double cpu_ms = 0;        // process CPU a frame in that loop, every thread
  double standin_ms = 0;    // Open3D: of which its numpy stand-ins (open3d_slam.py)
  std::string note;
};

// Every frame of the plan with the pose the scan gave it; a frame the scan never reached (it
// stopped) keeps the last pose it gave.
std::vector<StampedPose> EveryFrame(const Take& take, const TakePlan& plan,
                                    const ScanSummary& scan) {
  std::map<int64_t, Pose> by_set;
  for (const ScanFrame& frame : scan.frames) {
    if (frame.state != TrackingState::kSkipped) by_set[frame.set] = frame.world_from_cam;
  }
  const std::string depth_name = plan.depth_sensors.front();
  Pose last = plan.cameras.at(depth_name).world_from_cam();
  std::vector<StampedPose> poses;
  for (int64_t set : plan.sets) {
    const auto* item = take.entry(static_cast<size_t>(set)).Find(depth_name);
    if (item == nullptr) continue;
    if (const auto found = by_set.find(set); found != by_set.end()) last = found->second;
    poses.push_back({1e-9 * static_cast<double>(item->timestamp_ns), last});
  }
  return poses;
}

MethodRun RunHolocap(const Take& take, const TakePlan& plan, const ScanOptions& options,
                     const fs::path& out, const std::vector<StampedPose>& truth) {
  const ScanSummary scan = ScanTake(take, plan, out, options);
  MethodRun run;
  run.errors = CompareTrajectories(EveryFrame(take, plan, scan), truth);
  run.fps = scan.frames_per_second;
  run.cpu_ms = 1e3 * scan.cpu_seconds_per_frame;
  run.note = Cat(ToString(scan.termination), ", lost ", scan.lost, " of ", scan.frames.size(),
                 ", loops ", scan.loops);
  return run;
}

MethodRun RunOpen3d(const fs::path& dir, const ScanOptions& options, int threads,
                    const std::vector<StampedPose>& truth) {
  // dense_slam.py's own settings: truncation 8 voxels, odometry_distance_thr 0.07 m; a first
  // budget of 16^3-voxel blocks that its hash map grows past when the scene needs more.
  const std::string command =
      Cat("OMP_WAIT_POLICY=PASSIVE OMP_NUM_THREADS=", threads, " /usr/bin/python3 ",
          HOLOCAP_BENCH_DIR, "/open3d_slam.py ", dir.string(), " ", options.voxel_m, " 8 ",
          options.depth_min_m, " ", options.depth_max_m, " 10000 0.07 2>&1");
  FILE* pipe = popen(command.c_str(), "r");
  if (pipe == nullptr) Fail("scan_bench: cannot run ", command);
  MethodRun run;
  bool ran = false;
  char line[512];
  while (std::fgets(line, sizeof(line), pipe) != nullptr) {
    std::istringstream fields(line);
    std::string name;
    double seconds = 0, cpu_seconds = 0, standin_seconds = 0;
    int64_t frames = 0;
    if (fields >> name >> seconds >> frames >> cpu_seconds >> standin_seconds && name == "slam") {
      run.fps = 1.0 / std::max(1e-9, seconds);
      run.cpu_ms = 1e3 * cpu_seconds;
      run.standin_ms = 1e3 * standin_seconds;
      ran = true;
    } else {
      std::printf("  open3d: %s", line);
    }
  }
  if (pclose(pipe) != 0 || !ran) Fail("scan_bench: open3d_slam.py failed: ", command);
  const fs::path tum = dir / "slam.tum";
  run.errors = CompareTrajectories(ParseTum(ReadFileToString(tum), tum.string()), truth);
  run.note = "no lost state: every frame's pose counts";
  return run;
}

void PrintRow(const std::string& trajectory, const std::string& size, const std::string& method,
              const std::vector<MethodRun>& runs, const std::string& load) {
  std::vector<double> fps, cpu, standin, ate;
  for (const MethodRun& run : runs) {
    fps.push_back(run.fps);
    cpu.push_back(run.cpu_ms);
    standin.push_back(run.standin_ms);
    ate.push_back(100 * run.errors.ate_rmse_m);
  }
  const TrajectoryErrors& e = runs.front().errors;
  const std::string note = Median(standin) > 0
                               ? Cat(runs.front().note, "; of the CPU ms, ",
                                     std::lround(Median(standin)), " in the numpy stand-ins")
                               : runs.front().note;
  std::printf(
      "| %-8s | %-7s | %-36s | %7.2f | %5.2f-%-5.2f | %7.2f | %7.3f | %6.1f | %7.1f | %s; frames "
      "%lld; load %s |\n",
      trajectory.c_str(), size.c_str(), method.c_str(), 100 * e.ate_rmse_m,
      *std::min_element(ate.begin(), ate.end()), *std::max_element(ate.begin(), ate.end()),
      1e3 * e.rpe_trans_m, e.rpe_rot_deg, Median(fps), Median(cpu), note.c_str(),
      static_cast<long long>(e.matched), load.c_str());
  std::fflush(stdout);
}

void TrackingSection(const Args& args, const fs::path& work) {
  std::printf(
      "\n## Tracking: ATE RMSE (cm, rigid alignment) and RPE per frame (mm, deg) over every frame "
      "(run 1; ATE range: all runs); fps of the per-frame loop (tracking + fusion, wall clock, "
      "median of %d interleaved runs); CPU ms a frame (process CPU, every thread, median); "
      "%lld frames at %g fps, 30 deg/s around the subject, %d threads, OMP_WAIT_POLICY=%s\n\n",
      args.repeats, static_cast<long long>(args.frames), args.fps, args.threads,
      std::getenv("OMP_WAIT_POLICY") ? std::getenv("OMP_WAIT_POLICY") : "(unset)");
  std::printf(
      "| traj.    | size    | method                               | ATE cm  | ATE range   | "
      "RPE mm  | RPE deg | fps    | CPU ms  | note |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|\n");
  for (const auto& [w, h] : args.sizes) {
    const std::string size = Cat(w, "x", h);
    for (const std::string& trajectory : args.trajectories) {
      const fs::path take_dir = work / Cat(trajectory, "-", size);
      SimOptions sim;
      sim.rig = "single-rgbd";
      sim.trajectory = trajectory;
      sim.frames = args.frames;
      sim.fps = args.fps;
      sim.image_width = w;
      sim.image_height = h;
      sim.seed = 3;
      sim.overwrite = true;
      sim.threads = args.threads;
      fs::remove_all(take_dir);  // this bench's own take, with the outputs of its last run
      SimulateTake(sim, take_dir);
      CalibrateLikeAUser(work / Cat("board-", size), take_dir, w, h, args.threads);
      const Take take = Take::Open(take_dir);
      const TakePlan plan = PlanTake(take, TakeSelection{});
      const TakePlan pinhole = WithPinholeDepth(plan);
      ScanOptions options;
      options.threads = args.threads;
      options.photometric_weight_m = args.photometric_weight_m;
      options.write_glb = false;
      // The turntable mode is chosen, as a user chooses it (holocap scan --turn).
      options.subject_turns = trajectory == "turn";
      ExportForOpen3d(take, pinhole, take_dir / "open3d",
                      options.subject_turns ? std::optional(options.floor_margin_m) : std::nullopt);
      const std::vector<StampedPose> truth = TrueTrajectory(take, plan.depth_sensors.front());
      // Open3D's tracking is geometric (point to plane): holocap without its photometric term
      // is the same principle.
      ScanOptions geometric = options;
      geometric.photometric_weight_m = 0;
      std::vector<MethodRun> same_lens, same_lens_geometric, own_lens, open3d;
      const std::string load = Uptime();
      for (int r = 0; r < args.repeats; ++r) {
        same_lens.push_back(RunHolocap(take, pinhole, options, take_dir / "scan-pinhole", truth));
        open3d.push_back(RunOpen3d(take_dir / "open3d", options, args.threads, truth));
        same_lens_geometric.push_back(
            RunHolocap(take, pinhole, geometric, take_dir / "scan-geometric", truth));
        own_lens.push_back(RunHolocap(take, plan, options, take_dir / "scan", truth));
      }
      const std::string load_after = Uptime();
      PrintRow(trajectory, size, "holocap scan, Open3D's pinhole", same_lens, load);
      PrintRow(trajectory, size, "Open3D slam.Model (frame to model)", open3d, load);
      PrintRow(trajectory, size, "holocap, pinhole, no photometric", same_lens_geometric, load);
      PrintRow(trajectory, size, "holocap scan, calibrated lens", own_lens, load_after);
    }
  }
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

void QualitySection(const Args& args, const fs::path& work) {
  std::printf("\n## Scan quality against the true subject (outer surface, F-score at 5 mm)\n\n");
  std::printf(
      "| what | chamfer mm | accuracy mm | completeness mm | F@5mm |\n|---|---|---|---|---|\n");
  const fs::path orbit =
      work / Cat("orbit-", args.sizes.front().first, "x", args.sizes.front().second);
  const Mesh truth = ReadPly(orbit / "gt" / "meshes" / "000000.ply");
  if (fs::exists(orbit / "scan" / "mesh.ply")) {
    // The scan's world is the calibration's (its first frame where the calibrated depth sensor
    // stood); the truth's is the simulator's. The first frame's two poses map one to the other.
    const Take take = Take::Open(orbit);
    const TakePlan plan = PlanTake(take, TakeSelection{});
    const std::string depth_name = plan.depth_sensors.front();
    const std::vector<StampedPose> true_poses = TrueTrajectory(take, depth_name);
    if (true_poses.empty()) Fail("scan_bench: ", orbit.string(), " has no true trajectory");
    const Eigen::Isometry3f true_from_scan =
        (true_poses.front().world_from_cam * plan.cameras.at(depth_name).cam_from_world())
            .cast<float>();
    Mesh scanned = ReadPly(orbit / "scan" / "mesh.ply");
    for (auto& v : scanned.vertices) v = true_from_scan * v;
    const SurfaceErrors e = ScanQuality(scanned, truth);
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
  fs::remove_all(studio);  // this bench's own take, with the reconstruction of its last run
  SimulateTake(sim, studio);
  ReconstructionOptions options;
  options.sweep_voxels_m.clear();
  options.threads = args.threads;
  options.write_glb = false;
  // The reference rig's cameras are its true models (this section measures fusion, not its
  // calibration), asked for explicitly.
  TakeSelection selection;
  selection.ground_truth_cameras = true;
  const ReconstructionSummary recon = ReconstructTake(studio, selection, studio / "recon", options);
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

Args ParseArgs(int argc, char** argv) {
  Args args;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string flag = argv[i], value = argv[i + 1];
    if (flag == "--frames") args.frames = std::stoll(value);
    if (flag == "--fps") args.fps = std::stod(value);
    if (flag == "--threads") args.threads = std::stoi(value);
    if (flag == "--repeats") args.repeats = std::max(1, std::stoi(value));
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
  return args;
}

}  // namespace
}  // namespace holocap

int main(int argc, char** argv) {
  // Both sides wait passively: libgomp's spinning threads on a shared machine measure the load,
  // not the code. The variable is read when libgomp loads.
  if (std::getenv("OMP_WAIT_POLICY") == nullptr) {
    setenv("OMP_WAIT_POLICY", "PASSIVE", 1);
    execv("/proc/self/exe", argv);
  }
  try {
    const holocap::Args args = holocap::ParseArgs(argc, argv);
    const std::filesystem::path work =
        args.keep.empty() ? std::filesystem::temp_directory_path() / "holocap-scan-bench"
                          : args.keep;
    std::printf("# scan_bench: one moving RGB-D sensor (single-rgbd), load at start %s\n",
                holocap::Uptime().c_str());
    holocap::TrackingSection(args, work);
    holocap::QualitySection(args, work);
  } catch (const std::exception& e) {
    std::printf("error: %s\n", e.what());
    return 1;
  } catch (...) {
    std::printf("error: an unknown exception\n");
    return 1;
  }
  return 0;
}
