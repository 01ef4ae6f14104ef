// Live free-viewpoint video from one fixed RGB-D sensor: a simulated walk seen by depth0 + cam0
// (the single-rgbd sensor) and by two held-out colour cameras 90 and 180 degrees around the
// subject, completed by a scan of the same subject (sim --trajectory turn + holocap scan).
// PSNR inside the subject's true silhouette in the held-out cameras of
//   (a) the live frame alone (its depth meshed, coloured from cam0),
//   (b) live + the scan aligned rigidly only, and rigidly and non-rigidly (the deformation
//       started from the scan at rest each frame: the command's; or from the frame before's),
//   (c) live + scan + a rerender network trained on the scan take alone (holocap train rerender
//       SCAN_TAKE --scan SCAN), applied to the command's compositions (beside the same
//       compositions rasterised as the network sees them),
// with each frame's alignment residual, inlier fraction, deformation and seconds; then
// `holocap live`'s own run (LiveTake) on the take with this scan and with a scan of another
// subject (the object scene), which it must refuse. Every take is calibrated as a user's is:
// a board take of its rig, solved, its models taken over (bench/calibrated_sim.h); the truth only
// scores.
//
//   build/bench/live_bench [--frames N] [--scan-frames M] [--width W] [--keep DIR]
//                          [--rerender-minutes T] [--rerender-iterations I] [--rerender-lr R]
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "bench/calibrated_sim.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/take.h"
#include "live/live.h"
#include "neural/live_rerender.h"
#include "playback/playback.h"
#include "scan/scan.h"
#include "sim/sim.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;
using Json = nlohmann::json;

// The load averages: a timing on a shared machine is read beside them.
std::string LoadAverages() {
  std::ifstream in("/proc/loadavg");
  std::string one, five, fifteen;
  in >> one >> five >> fifteen;
  return one + " " + five + " " + fifteen;
}

struct Args {
  int64_t frames = 16;
  int64_t scan_frames = 72;
  int width = 320;
  fs::path keep;
  double rerender_minutes = 5;
  int64_t rerender_iterations = 0;
  double rerender_lr = LiveRerenderOptions{}.learning_rate;
};

// single-rgbd's sensor pair and two pinhole colour cameras at the same distance and height,
// turned 90 and 180 degrees about the vertical axis through the centre of the subject's walk.
void WriteRig(const fs::path& file) {
  const Eigen::Vector3d centre(0, 0, 0.95);
  const Eigen::Vector3d sensor(2.4, -1.3, 1.15);
  Json sensors = Json::array();
  auto color = [&](const std::string& name, double degrees, const std::string& lens,
                   std::vector<double> intrinsics) {
    const Eigen::Vector3d eye =
        Eigen::AngleAxisd(degrees * M_PI / 180, Eigen::Vector3d::UnitZ()) * sensor;
    sensors.push_back({{"name", name},
                       {"uri", "sim:live-rig#" + name},
                       {"role", "color"},
                       {"options",
                        {{"lens", lens},
                         {"intrinsics", intrinsics},
                         {"size", {640, 480}},
                         {"position", {eye.x(), eye.y(), eye.z()}},
                         {"look_at", {centre.x(), centre.y(), centre.z()}}}}});
  };
  color("cam0", 0, "LENSMODEL_OPENCV5",
        {535.4, 534.8, 320.6, 238.3, 0.08, -0.18, 0.0004, -0.0002, 0.09});
  sensors.push_back({{"name", "depth0"},
                     {"uri", "sim:live-rig#depth0"},
                     {"role", "depth"},
                     {"paired_with", "cam0"},
                     {"options",
                      {{"lens", "LENSMODEL_OPENCV4"},
                       {"intrinsics", {570.3, 570.9, 319.2, 241.6, 0.01, -0.02, 0.0002, -0.0001}},
                       {"size", {640, 480}},
                       {"depth_from_color", {0.0015, -0.002, 0.001, -0.045, 0.0002, 0.0008}}}}});
  color("cam90", 90, "LENSMODEL_PINHOLE", {535, 535, 319.5, 239.5});
  color("cam180", 180, "LENSMODEL_PINHOLE", {535, 535, 319.5, 239.5});
  WriteFileAtomic(
      file, Json({{"name", "live-rig"}, {"sync", "hardware"}, {"fps", 10}, {"sensors", sensors}})
                .dump(2));
}

TexturedMeshFrame Corners(const Mesh& mesh) {
  TexturedMeshFrame frame;
  for (const Eigen::Vector3i& face : mesh.faces) {
    for (int c = 0; c < 3; ++c) {
      frame.positions.push_back(mesh.vertices[face[c]]);
      frame.colors.push_back(mesh.colors.empty() ? Eigen::Matrix<uint8_t, 3, 1>(128, 128, 128)
                                                 : mesh.colors[face[c]]);
    }
  }
  return frame;
}

// PSNR (peak 1) of a render against the camera's frame over the true silhouette's pixels.
double PsnrInMask(const RenderedView& view, const cv::Mat& reference_bgr, const cv::Mat& mask) {
  cv::Mat reference;
  reference_bgr.convertTo(reference, CV_32FC3, 1.0 / 255);
  double squared = 0;
  int64_t count = 0;
  for (int y = 0; y < mask.rows; ++y) {
    for (int x = 0; x < mask.cols; ++x) {
      if (mask.at<uint8_t>(y, x) == 0) continue;
      const cv::Vec3f d = view.color.at<cv::Vec3f>(y, x) - reference.at<cv::Vec3f>(y, x);
      squared += d.dot(d) / 3;
      ++count;
    }
  }
  return count == 0 ? NAN : 10 * std::log10(1.0 / std::max(1e-12, squared / count));
}

// Where a render's error lies inside the true silhouette: pixels the render leaves uncovered
// (alpha below a half: black there) and the rest.
struct Coverage {
  int64_t pixels = 0, uncovered = 0;
  double squared = 0, uncovered_squared = 0;
  void Add(const RenderedView& view, const cv::Mat& reference_bgr, const cv::Mat& mask) {
    cv::Mat reference;
    reference_bgr.convertTo(reference, CV_32FC3, 1.0 / 255);
    for (int y = 0; y < mask.rows; ++y) {
      for (int x = 0; x < mask.cols; ++x) {
        if (mask.at<uint8_t>(y, x) == 0) continue;
        const cv::Vec3f d = view.color.at<cv::Vec3f>(y, x) - reference.at<cv::Vec3f>(y, x);
        const double e = d.dot(d) / 3;
        ++pixels;
        squared += e;
        if (view.alpha.empty() || view.alpha.at<float>(y, x) < 0.5f) {
          ++uncovered;
          uncovered_squared += e;
        }
      }
    }
  }
};

// The methods compared: (a) the live frame alone; (b) live + scan aligned rigidly only, and
// non-rigidly from the scan at rest each frame (the command's default) or from the frame
// before's deformation (--carry); the command's compositions rasterised as the rerender network
// sees them (supersampled), and (c) the network's output on them.
constexpr int kMethods = 7;
const char* const kMethodNames[kMethods] = {"(a) live frame alone",
                                            "(b) live + scan, rigid only",
                                            "(b) live + scan, non-rigid from rest",
                                            "(b) live + scan, non-rigid carried",
                                            "(b) live + scan, non-rigid from rest, not relit",
                                            "(b) non-rigid from rest, rasterised for the network",
                                            "(c) live + scan + rerender network"};
constexpr int kCommand = 2;      // the command's own: non-rigid from rest
constexpr int kCompositors = 5;  // methods 1-4 compose; 5 and 6 render the command's compositions

// PSNR sums per method x (cam90, cam180) and the frames summed, over every frame the method
// composed ([0]) and over the frames every compositor composed ([1]).
struct Row {
  double psnr[2][kMethods][2] = {};
  int64_t counted[2][kMethods] = {};
  int64_t frames = 0;  // composed by the command's compositor (non-rigid from rest)
  double inliers = 0, residual_mm = 0, rigid_residual_mm = 0, deformation_mm = 0, seconds = 0;
  std::vector<std::string> refused;
  Coverage coverage[2];  // the command's composition at cam90 and cam180
};

cv::Mat Bgr(const cv::Mat& frame) {
  if (frame.channels() == 3) return frame;
  cv::Mat out;
  cv::cvtColor(frame, out, frame.channels() == 4 ? cv::COLOR_BGRA2BGR : cv::COLOR_GRAY2BGR);
  return out;
}

Row Measure(const fs::path& live_take, const fs::path& scan_dir, const LiveRerenderModel& model,
            const fs::path& coverage_dir) {
  const Take take = Take::Open(live_take);
  const TakePlan plan = PlanTake(take, TakeSelection{});
  const Mesh scan = ReadScan(scan_dir);
  std::string unlit;
  const std::optional<ScanAlbedo> albedo = ReadScanAlbedo(scan_dir, scan, &unlit);
  if (albedo) {
    const Eigen::Vector3d& l = albedo->light.light;
    std::printf("scan light (depth sensor frame): [%.3f %.3f %.3f], strength %.2f of the ambient\n",
                l.x(), l.y(), l.z(), l.norm());
  } else {
    std::printf("scan light: none (%s)\n", unlit.c_str());
  }
  LiveOptions options[kCompositors];
  options[1].nonrigid = false;
  options[3].carry_deformation = true;
  options[4].relight = false;
  std::vector<LiveCompositor> compositors;
  for (int m = 1; m < kCompositors; ++m)
    compositors.emplace_back(scan, options[m], plan.up, plan.floor_m, albedo);
  const CameraModel& depth_camera = plan.cameras.at("depth0");
  const CameraModel& color_camera = plan.cameras.at("cam0");
  const std::string held_out[2] = {"cam90", "cam180"};
  Row row;
  for (int64_t set : plan.sets) {
    const cv::Mat depth = take.ReadFrame(static_cast<size_t>(set), "depth0");
    const cv::Mat color = Bgr(take.ReadFrame(static_cast<size_t>(set), "cam0"));
    std::vector<LiveResult> results;
    bool all = true;
    for (int m = 1; m < kCompositors; ++m) {
      results.push_back(compositors[m - 1].Process(set, depth, depth_camera, color, color_camera));
      if (results.back().frame.state == LiveState::kComposed) continue;
      all = false;
      row.refused.push_back(Cat(set, " ", kMethodNames[m], ": ", results.back().frame.why));
    }
    const LiveResult& n = results[kCommand - 1];
    const Mesh* meshes[kCompositors] = {&n.live, &results[0].composed, &results[1].composed,
                                        &results[2].composed, &results[3].composed};
    bool composed[kMethods] = {n.frame.state == LiveState::kComposed};
    for (int m = 1; m < kCompositors; ++m)
      composed[m] = results[m - 1].frame.state == LiveState::kComposed;
    for (int m = kCompositors; m < kMethods; ++m) composed[m] = composed[kCommand];
    if (composed[kCommand]) {
      ++row.frames;
      row.inliers += n.frame.inlier_fraction;
      row.residual_mm += 1e3 * n.frame.residual_m;
      row.rigid_residual_mm += 1e3 * n.frame.rigid_residual_m;
      row.deformation_mm += 1e3 * n.frame.deformation_rms_m;
      row.seconds += n.frame.seconds;
    }
    for (int c = 0; c < 2; ++c) {
      const cv::Mat reference = Bgr(take.ReadFrame(static_cast<size_t>(set), held_out[c]));
      char name[32];
      std::snprintf(name, sizeof(name), "%06lld.png", static_cast<long long>(set));
      const cv::Mat mask = cv::imread((live_take / "gt" / "masks" / held_out[c] / name).string(),
                                      cv::IMREAD_GRAYSCALE);
      if (mask.empty()) Fail("live_bench: no true mask of ", held_out[c], " set ", set);
      RenderedView views[kMethods];
      for (int m = 0; m < kCompositors; ++m) {
        if (composed[m])
          views[m] = RenderTexturedMesh(Corners(*meshes[m]), plan.cameras.at(held_out[c]));
      }
      if (composed[kCommand]) {
        views[kCompositors + 1] = model.Render(*meshes[kCommand], plan.cameras.at(held_out[c]),
                                               &views[kCompositors].color);
      }
      if (composed[kCommand]) {
        row.coverage[c].Add(views[kCommand], reference, mask);
        if (!coverage_dir.empty()) {
          // Beside the true frame: the command's render, and its coverage (green: covered inside
          // the true silhouette, red: uncovered inside it, blue: covered outside it).
          cv::Mat render, map(mask.size(), CV_8UC3, cv::Scalar::all(0));
          views[kCommand].color.convertTo(render, CV_8UC3, 255);
          for (int y = 0; y < mask.rows; ++y) {
            for (int x = 0; x < mask.cols; ++x) {
              const bool in = mask.at<uint8_t>(y, x) != 0;
              const bool covered = views[kCommand].alpha.at<float>(y, x) >= 0.5f;
              if (in || covered)
                map.at<cv::Vec3b>(y, x) = !in       ? cv::Vec3b(255, 0, 0)
                                          : covered ? cv::Vec3b(0, 160, 0)
                                                    : cv::Vec3b(0, 0, 255);
            }
          }
          cv::Mat row_image;
          cv::hconcat(std::vector<cv::Mat>{reference, render, map}, row_image);
          cv::imwrite((coverage_dir / (held_out[c] + "-" + name)).string(), row_image);
        }
      }
      for (int m = 0; m < kMethods; ++m) {
        if (!composed[m]) continue;
        const double psnr = PsnrInMask(views[m], reference, mask);
        row.psnr[0][m][c] += psnr;
        if (all) row.psnr[1][m][c] += psnr;
        if (c == 0) {
          ++row.counted[0][m];
          if (all) ++row.counted[1][m];
        }
      }
    }
  }
  return row;
}

Args Parse(int argc, char** argv) {
  Args args;
  for (int i = 1; i < argc; ++i) {
    const std::string flag = argv[i];
    if (i + 1 >= argc) Fail("live_bench: ", flag, " needs a value");
    const std::string value = argv[++i];
    if (flag == "--frames") {
      args.frames = std::stoll(value);
    } else if (flag == "--scan-frames") {
      args.scan_frames = std::stoll(value);
    } else if (flag == "--width") {
      args.width = std::stoi(value);
    } else if (flag == "--keep") {
      args.keep = value;
    } else if (flag == "--rerender-minutes") {
      args.rerender_minutes = std::stod(value);
    } else if (flag == "--rerender-iterations") {
      args.rerender_iterations = std::stoll(value);
    } else if (flag == "--rerender-lr") {
      args.rerender_lr = std::stod(value);
    } else {
      Fail("live_bench: unknown flag ", flag);
    }
  }
  return args;
}

int Run(int argc, char** argv) {
  const Args args = Parse(argc, argv);
  const fs::path work =
      args.keep.empty() ? fs::temp_directory_path() / "holocap-live-bench" : args.keep;
  fs::remove_all(work);
  CreateDirectories(work);
  std::printf(
      "# live_bench: --frames %lld --scan-frames %lld --width %d --rerender-minutes %g "
      "--rerender-iterations %lld --rerender-lr %g, load at start %s\n\n",
      static_cast<long long>(args.frames), static_cast<long long>(args.scan_frames), args.width,
      args.rerender_minutes, static_cast<long long>(args.rerender_iterations), args.rerender_lr,
      LoadAverages().c_str());
  // The scan: the subject turning once before single-rgbd at 10 frames a second.
  SimOptions scan_sim;
  scan_sim.rig = "single-rgbd";
  scan_sim.trajectory = "turn";
  scan_sim.frames = args.scan_frames;
  scan_sim.fps = 10;
  scan_sim.trajectory_deg_per_s = 360.0 * scan_sim.fps / static_cast<double>(args.scan_frames);
  scan_sim.image_width = args.width;
  SimulateTake(scan_sim, work / "scan-take");
  std::printf("scan take: %s\n",
              bench::CalibrateFromBoardTake(scan_sim, work / "scan-take").c_str());
  ScanOptions turning;
  turning.subject_turns = true;  // holocap scan --turn
  const auto scan_start = std::chrono::steady_clock::now();
  const ScanSummary scan = ScanTake(work / "scan-take", TakeSelection{}, work / "scan", turning);
  std::printf("scan: %s (%s), %lld vertices, %.1f s\n", ToString(scan.termination),
              scan.message.c_str(), static_cast<long long>(scan.vertices),
              std::chrono::duration<double>(std::chrono::steady_clock::now() - scan_start).count());
  // (c)'s network, trained on the scan take alone.
  LiveRerenderOptions rerender;
  rerender.minutes = args.rerender_minutes;
  rerender.iterations = args.rerender_iterations;
  rerender.learning_rate = args.rerender_lr;
  const LiveRerenderSummary trained =
      TrainLiveRerender(work / "scan-take", work / "scan", work / "rerender", rerender);
  std::printf(
      "rerender network: %s (%s); %lld training and %lld validation pairs from %lld composed "
      "frames, %lld iterations in %.0f s (load %s)\n",
      ToString(trained.termination), trained.message.c_str(),
      static_cast<long long>(trained.train_pairs), static_cast<long long>(trained.validation_pairs),
      static_cast<long long>(trained.composed_frames), static_cast<long long>(trained.iterations),
      trained.seconds, LoadAverages().c_str());
  const LiveRerenderModel model(work / "rerender");
  // The live take: the subject walking before the fixed sensor, the held-out cameras beside.
  WriteRig(work / "live-rig.json");
  SimOptions live_sim;
  live_sim.rig = (work / "live-rig.json").string();
  live_sim.frames = args.frames;
  live_sim.fps = 10;
  live_sim.image_width = args.width;
  SimulateTake(live_sim, work / "live-take");
  std::printf("live take: %s\n",
              bench::CalibrateFromBoardTake(live_sim, work / "live-take").c_str());
  if (!args.keep.empty()) CreateDirectories(work / "coverage");
  const Row row =
      Measure(work / "live-take", work / "scan", model, args.keep.empty() ? "" : work / "coverage");
  const double n = static_cast<double>(std::max<int64_t>(1, row.frames));
  std::printf("\n%lld of %lld frames composed (walking 0.4 m/s, turning 46 deg/s), %dx%d\n\n",
              static_cast<long long>(row.frames), static_cast<long long>(args.frames), args.width,
              args.width * 3 / 4);
  for (const std::string& refused : row.refused) std::printf("  refused %s\n", refused.c_str());
  std::printf("| what | frames | PSNR cam90 dB | PSNR cam180 dB |\n|---|---|---|---|\n");
  const char* over[2] = {"frames each composed", "frames all composed"};
  for (int o = 0; o < 2; ++o) {
    for (int m = 0; m < kMethods; ++m) {
      const double k = static_cast<double>(std::max<int64_t>(1, row.counted[o][m]));
      std::printf("| %s (%s) | %lld | %.2f | %.2f |\n", kMethodNames[m], over[o],
                  static_cast<long long>(row.counted[o][m]), row.psnr[o][m][0] / k,
                  row.psnr[o][m][1] / k);
    }
  }
  for (int c = 0; c < 2; ++c) {
    const Coverage& k = row.coverage[c];
    const double covered = static_cast<double>(std::max<int64_t>(1, k.pixels - k.uncovered));
    std::printf(
        "%s the command's compositions: %.1f %% of the true silhouette uncovered, %.1f %% of the "
        "squared error; %.2f dB over the covered pixels\n",
        c == 0 ? "\ncam90:  " : "cam180: ", 100.0 * k.uncovered / std::max<int64_t>(1, k.pixels),
        100 * k.uncovered_squared / std::max(1e-12, k.squared),
        10 * std::log10(covered / std::max(1e-12, k.squared - k.uncovered_squared)));
  }
  std::printf(
      "\nalignment (means over frames): rigid residual %.2f mm; after non-rigid: residual %.2f "
      "mm, inliers %.1f %%, deformation %.1f mm RMS; %.2f s a frame (rigid + non-rigid + "
      "composition, load %s)\n",
      row.rigid_residual_mm / n, row.residual_mm / n, 100 * row.inliers / n, row.deformation_mm / n,
      row.seconds / n, LoadAverages().c_str());
  // The command's own path on the same take, with this scan and with a scan of another subject
  // (the static knot of the "object" scene, turned and scanned the same way).
  const LiveSummary same = LiveTake(work / "live-take", TakeSelection{}, work / "scan",
                                    work / "live-out", LiveOptions{});
  std::printf("\nholocap live with the subject's scan: %s (%s)\n", ToString(same.termination),
              same.message.c_str());
  SimOptions other = scan_sim;
  other.scene = "object";
  SimulateTake(other, work / "object-take");
  AdoptCalibration(work / "object-take", work / "scan-take-board");
  ScanTake(work / "object-take", TakeSelection{}, work / "object-scan", turning);
  const LiveSummary wrong = LiveTake(work / "live-take", TakeSelection{}, work / "object-scan",
                                     work / "live-wrong", LiveOptions{});
  std::printf("holocap live with a scan of the object scene: %s (%s)\n",
              ToString(wrong.termination), wrong.message.c_str());
  if (args.keep.empty()) fs::remove_all(work);
  return 0;
}

}  // namespace
}  // namespace holocap

int main(int argc, char** argv) {
  try {
    return holocap::Run(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "live_bench: %s\n", e.what());
    return 1;
  }
}
