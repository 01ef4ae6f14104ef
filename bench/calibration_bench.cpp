// Calibration on the simulated studio8 board sequence: holocap's figures against the
// targets, and peers on the same detections in the same run: OpenCV calibrateCamera /
// stereoCalibrate, and mrcal's own mrcal-calibrate-cameras on the same corners (corners.vnl).
//
//   calibration_bench [--take DIR | --planned] [--frames 288] [--corner-noise 0.3] [--seed 1]
//                     [--noise-seed 7] [--tags WxH] [--spacing M] [--true-corners] [--no-mrcal]
//                     [--no-peers]
//                     [--lens-model CAMERA=MODEL]... [--width W]
// Each camera is solved in the model its rig entry asks for (calib_lensmodel, else OPENCV8)
// unless --lens-model names another.
// Without --take it simulates `holocap sim --rig studio8 --board --frames N` into a temporary
// directory first (288 sets: about 60 board views per camera). The rendered corners are found
// to a few hundredths of a pixel, so Gaussian noise is added to every detected corner until
// the total detection noise is --corner-noise per coordinate (the target's 0.3 px).
// --true-corners replaces every detected corner by its exact projection before the noise is
// added (detection bias removed: what is left is the board sequence's statistics);
// --planned renders nothing: the sim's board poses for --frames sets are projected through the
// true models (a camera sees a pose when the whole board lies in its image, facing it, with
// tags of at least 12 px), so the sequence's information is measured in seconds.
// --tags and --spacing give the simulated board other tags and grid spacing (margin = spacing);
// --width renders (or plans) every camera's imager W pixels wide, its lens rescaled: the same
// rig and board sequence at another sensor resolution, for the same detection noise in pixels;
// --seed the sim's seed (board poses), --noise-seed the added noise's (another draw of the same
// noise); --no-peers leaves OpenCV and mrcal out.
// Next to each error it prints the solve's own 1-sigma of that parameter: errors of a few
// sigma are what the board views can tell, not a fault of the solve.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <limits>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <random>
#include <string>

#include "calibration/calibration.h"
#include "core/error.h"
#include "core/take.h"
#include "sim/sim.h"
#include "sim/world.h"

namespace holocap {
namespace {

double Seconds(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

std::map<int64_t, Pose> TrueBoardPoses(const Take& take) {
  std::map<int64_t, Pose> poses;
  const auto json = nlohmann::json::parse(std::ifstream(take.gt_dir() / "board.json"));
  for (const auto& e : json["world_from_board"]) {
    const auto rt = e["rt"].get<std::vector<double>>();
    poses[e["set"].get<int64_t>()] = PoseFromRt({rt[0], rt[1], rt[2], rt[3], rt[4], rt[5]});
  }
  return poses;
}

// Projection difference of two models of one camera over its imager, after the rotation the
// two frames imply is fitted out (mrcal's projection_diff at the given distance).
double ProjectionDiffRms(const CameraModel& a, const CameraModel& b, double distance) {
  Eigen::Matrix2Xd pixels(2, 16 * 12);
  for (int k = 0; k < pixels.cols(); ++k) {
    const int column = k % 16;
    const int row = k / 16;
    pixels.col(k) << (column + 0.5) * a.width() / 16 - 0.5, (row + 0.5) * a.height() / 12 - 0.5;
  }
  const Eigen::Matrix3Xd ra = a.UnprojectMany(pixels), rb = b.UnprojectMany(pixels);
  Eigen::Matrix3d h = Eigen::Matrix3d::Zero();
  for (int k = 0; k < pixels.cols(); ++k) {
    if (ra.col(k).allFinite() && rb.col(k).allFinite()) h += ra.col(k) * rb.col(k).transpose();
  }
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(h, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d fix = Eigen::Matrix3d::Identity();
  fix(2, 2) = (svd.matrixV() * svd.matrixU().transpose()).determinant() < 0 ? -1 : 1;
  const Eigen::Matrix3d rotation = svd.matrixV() * fix * svd.matrixU().transpose();
  double sum2 = 0;
  int n = 0;
  for (int k = 0; k < pixels.cols(); ++k) {
    Eigen::Vector2d q;
    if (!ra.col(k).allFinite() || !b.Project(rotation * ra.col(k) * distance, &q)) continue;
    sum2 += (q - pixels.col(k)).squaredNorm();
    ++n;
  }
  return n > 0 ? std::sqrt(sum2 / n) : NAN;
}

// Observations of the planned board poses: the exact projections of the grid for every camera
// that sees the whole board in its image, facing it, with grid spacing of at least 12 px (the
// tags' decoding limit), as the detector would accept them.
std::vector<BoardObservation> PlannedObservations(const Board& board,
                                                  const std::vector<std::string>& sensors,
                                                  const std::map<std::string, CameraModel>& truth,
                                                  const std::map<int64_t, Pose>& world_from_board) {
  std::vector<BoardObservation> observations;
  const int n = board.width_n() * board.height_n();
  for (const auto& [set, pose] : world_from_board) {
    for (const auto& name : sensors) {
      const CameraModel& cam = truth.at(name);
      const Pose view = cam.cam_from_world() * pose;
      // The board's front faces the camera: its normal (+z) points away from it.
      if (view.linear().col(2).dot(view.translation()) <= 0) continue;
      BoardObservation obs;
      obs.sensor = name;
      obs.frame_set = set;
      obs.points.resize(n, 3);
      bool ok = true;
      double spacing = std::numeric_limits<double>::infinity();
      for (int r = 0; r < n && ok; ++r) {
        const int i = r % board.width_n(), j = r / board.width_n();
        Eigen::Vector2d q, qn;
        ok = (view * board.GridPoint(i, j)).z() > 0.05 &&
             cam.Project(view * board.GridPoint(i, j), &q) && cam.InImage(q, 2) &&
             cam.Project(view * board.GridPoint(i == 0 ? 1 : i - 1, j), &qn);
        if (!ok) break;
        spacing = std::min(spacing, (qn - q).norm());
        obs.points.row(r) << q.x(), q.y(), 1.0;
      }
      if (ok && spacing >= 12) observations.push_back(std::move(obs));
    }
  }
  return observations;
}

// The command line.
struct BenchArguments {
  std::filesystem::path take_dir;
  int frames = 288;
  uint64_t seed = 1, noise_seed = 7;
  double corner_noise = 0.3;
  bool mrcal = true, peers = true, planned = false, true_corners = false;
  std::string tags;    // the simulated board's tags across x down ("8x6"); empty: the sim's
  double spacing = 0;  // its grid spacing in metres; 0: the sim's
  int width = 0;       // > 0: every camera's imager this wide (lens rescaled); 0: the rig's
  std::map<std::string, std::string> lens_models;  // per camera, over the rig's choice
};

BenchArguments ParseArguments(int argc, char** argv) {
  BenchArguments args;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg == "--take" && i + 1 < argc)
      args.take_dir = argv[++i];
    else if (arg == "--frames" && i + 1 < argc)
      args.frames = std::atoi(argv[++i]);
    else if (arg == "--seed" && i + 1 < argc)
      args.seed = std::strtoull(argv[++i], nullptr, 10);
    else if (arg == "--noise-seed" && i + 1 < argc)
      args.noise_seed = std::strtoull(argv[++i], nullptr, 10);
    else if (arg == "--corner-noise" && i + 1 < argc)
      args.corner_noise = std::atof(argv[++i]);
    else if (arg == "--no-mrcal")
      args.mrcal = false;
    else if (arg == "--no-peers")
      args.peers = args.mrcal = false;
    else if (arg == "--planned")
      args.planned = true;
    else if (arg == "--tags" && i + 1 < argc)
      args.tags = argv[++i];
    else if (arg == "--spacing" && i + 1 < argc)
      args.spacing = std::atof(argv[++i]);
    else if (arg == "--true-corners")
      args.true_corners = true;
    else if (arg == "--width" && i + 1 < argc)
      args.width = std::atoi(argv[++i]);
    else if (arg == "--lens-model" && i + 1 < argc) {
      const std::string value = argv[++i];
      const size_t eq = value.find('=');
      if (eq == std::string::npos) Fail("--lens-model takes CAMERA=MODEL, got '", value, "'");
      args.lens_models[value.substr(0, eq)] = value.substr(eq + 1);
    } else {
      Fail(
          "usage: calibration_bench [--take DIR | --planned] [--frames N] [--seed N] [--tags WxH] "
          "[--spacing M] "
          "[--corner-noise PX] [--noise-seed N] [--true-corners] [--width W] "
          "[--no-mrcal] [--no-peers] [--lens-model CAMERA=MODEL]...");
    }
  }
  if (args.planned && !args.take_dir.empty()) Fail("--planned and --take exclude each other");
  return args;
}

// The simulated board take the arguments describe.
SimOptions BoardSimOptions(const BenchArguments& args) {
  SimOptions sim;
  sim.scene = "board";
  sim.frames = args.frames;
  sim.seed = args.seed;
  sim.overwrite = true;
  sim.image_width = args.width;
  if (!args.tags.empty()) {
    if (std::sscanf(args.tags.c_str(), "%dx%d", &sim.board.tags_across, &sim.board.tags_down) !=
        2) {
      Fail("--tags takes ACROSSxDOWN, got '", args.tags, "'");
    }
  }
  if (args.spacing > 0) sim.board.spacing = sim.board.margin = args.spacing;
  sim.board.Check();
  return sim;
}

// What the solves are given and judged against: the board, the cameras, the truth and the
// board observations, planned or detected.
struct BenchInput {
  BoardLayout layout;
  std::vector<std::string> sensors;
  std::vector<CalibrationCamera> cameras;
  std::map<std::string, CameraModel> truth;
  std::map<int64_t, Pose> world_from_board;
  std::vector<BoardObservation> observations;
  DetectionSummary detection;
};

// The sim's board poses projected through the true models: nothing rendered.
BenchInput PlannedInput(const BenchArguments& args, const SimOptions& sim) {
  BenchInput in;
  in.layout = sim.board;
  const sim::SimWorld world(sim);
  for (int i = 0; i < world.size(); ++i) {
    const auto& sensor = world.sensor(i);
    if (sensor.spec.role != SensorRole::kColor) continue;
    in.sensors.push_back(sensor.spec.name);
    std::string model =
        sensor.spec.options.value("calib_lensmodel", std::string("LENSMODEL_OPENCV8"));
    if (args.lens_models.count(sensor.spec.name)) model = args.lens_models.at(sensor.spec.name);
    in.cameras.push_back({sensor.spec.name, sensor.model.width(), sensor.model.height(), model});
    in.truth.emplace(sensor.spec.name, sensor.model);
  }
  for (int64_t set = 0; set < args.frames; ++set)
    in.world_from_board[set] = world.scene().WorldFromBoard(set);
  in.observations =
      PlannedObservations(Board(in.layout), in.sensors, in.truth, in.world_from_board);
  in.detection.frames = args.frames * static_cast<int64_t>(in.sensors.size());
  in.detection.views = static_cast<int64_t>(in.observations.size());
  for (const auto& obs : in.observations) ++in.detection.views_per_sensor[obs.sensor];
  std::printf(
      "planned studio8 board sequence (seed %llu): %d frame sets, true corners, nothing rendered\n",
      static_cast<unsigned long long>(args.seed), args.frames);
  return in;
}

// The boards detected in a take's images (simulated first when no take is given).
BenchInput DetectedInput(const BenchArguments& args, const SimOptions& sim) {
  std::filesystem::path take_dir = args.take_dir;
  if (take_dir.empty()) {
    take_dir = std::filesystem::temp_directory_path() / "holocap-calibration-bench";
    const auto start = std::chrono::steady_clock::now();
    const SimSummary s = SimulateTake(sim, take_dir);
    std::printf("simulated studio8 board take: %lld frame sets in %.1f s -> %s\n",
                static_cast<long long>(s.frame_sets), Seconds(start), take_dir.c_str());
  }
  BenchInput in;
  const Take take = Take::Open(take_dir);
  in.layout = BoardLayout::FromJson(
      nlohmann::json::parse(std::ifstream(take.gt_dir() / "board.json"))["layout"]);
  for (const auto& s : take.streams()) {
    if (s.role != SensorRole::kColor) continue;
    in.sensors.push_back(s.name);
    in.cameras.push_back({s.name, s.width, s.height,
                          args.lens_models.count(s.name) ? args.lens_models.at(s.name)
                                                         : RigLensModel(take, s.name)});
    in.truth.emplace(s.name, take.Camera(s.name, true));
  }
  in.observations = DetectBoardsInTake(take, in.layout, in.sensors, {}, &in.detection);
  in.world_from_board = TrueBoardPoses(take);
  return in;
}

// The bench's steps on one input: the corners' noise brought to --corner-noise, holocap's
// solve and its tables, then the peers on the same corners.
class CalibrationBench {
 public:
  CalibrationBench(const BenchArguments& args, BenchInput input)
      : args_(args), in_(std::move(input)), board_(in_.layout) {}

  void Run() {
    if (!args_.planned) PrintDetectionErrors();
    SetCornerNoise();
    SolveHolocap();
    PrintHolocapTables();
    PrintSigmaTable();
    if (!args_.peers) return;
    RunCalibrateCamera();
    RunStereoCalibrate();
    if (args_.mrcal) RunMrcal();
  }

 private:
  // Observation row r's grid point on the board.
  Eigen::Vector3d GridPointOfRow(int r) const {
    return board_.GridPoint(r % board_.width_n(), r / board_.width_n());
  }

  nlohmann::json TruthComparisonOf(const std::string& name) const {
    return comparison_.per_camera.count(name) ? comparison_.per_camera.at(name)
                                              : nlohmann::json::object();
  }

  // Detection noise actually present: detected corners against the true projections
  // (replaced by them with `replace`).
  double MeasureNoise(bool replace) {
    double noise2 = 0;
    int64_t noise_n = 0;
    for (auto& obs : in_.observations) {
      const CameraModel& cam = in_.truth.at(obs.sensor);
      auto truth_pose = in_.world_from_board.find(obs.frame_set);
      if (truth_pose == in_.world_from_board.end()) continue;
      const Pose view = cam.cam_from_world() * truth_pose->second;
      for (int r = 0; r < obs.points.rows(); ++r) {
        if (obs.points(r, 2) <= 0) continue;
        Eigen::Vector2d q;
        if (!cam.Project(view * GridPointOfRow(r), &q)) continue;
        noise2 += (obs.points.row(r).head<2>().transpose() - q).squaredNorm();
        ++noise_n;
        if (replace) obs.points.row(r).head<2>() = q.transpose();
      }
    }
    return std::sqrt(noise2 / (2.0 * noise_n));
  }

  // Where the detected corners miss the truth, per camera: their RMS, 99th percentile and the
  // mean radial component (outward +) by distance from the imager's centre, which shows a
  // bias under lens distortion.
  void PrintDetectionErrors() const {
    std::printf(
        "detected corners against the truth, per camera: RMS, 99th percentile, mean radial error "
        "(px) "
        "in 4 rings from the imager centre out\n");
    for (const auto& name : in_.sensors) {
      const CameraModel& cam = in_.truth.at(name);
      const Eigen::Vector2d centre(0.5 * (cam.width() - 1), 0.5 * (cam.height() - 1));
      const double corner_radius = centre.norm();
      std::vector<double> errors;
      double radial[4] = {0, 0, 0, 0};
      int in_ring[4] = {0, 0, 0, 0};
      for (const auto& obs : in_.observations) {
        auto pose = in_.world_from_board.find(obs.frame_set);
        if (obs.sensor != name || pose == in_.world_from_board.end()) continue;
        const Pose view = cam.cam_from_world() * pose->second;
        for (int r = 0; r < obs.points.rows(); ++r) {
          Eigen::Vector2d q;
          if (obs.points(r, 2) <= 0 || !cam.Project(view * GridPointOfRow(r), &q)) continue;
          const Eigen::Vector2d e = obs.points.row(r).head<2>().transpose() - q;
          errors.push_back(e.norm());
          const Eigen::Vector2d out = q - centre;
          const int ring = std::min(3, static_cast<int>(4 * out.norm() / corner_radius));
          radial[ring] += out.norm() > 1 ? e.dot(out.normalized()) : 0;
          ++in_ring[ring];
        }
      }
      if (errors.empty()) continue;
      double sum2 = 0;
      for (double e : errors) sum2 += e * e;
      std::sort(errors.begin(), errors.end());
      std::printf("  %s: %.3f px RMS, 99%% under %.3f px; radial", name.c_str(),
                  std::sqrt(sum2 / errors.size()),
                  errors[static_cast<size_t>(0.99 * (errors.size() - 1))]);
      for (int k = 0; k < 4; ++k)
        std::printf(" %+.3f (%d)", in_ring[k] ? radial[k] / in_ring[k] : NAN, in_ring[k]);
      std::printf("\n");
    }
  }

  // Gaussian noise added to every corner until the total is --corner-noise per coordinate.
  void SetCornerNoise() {
    const double found_noise = MeasureNoise(args_.true_corners);
    const double present = args_.true_corners ? 0.0 : found_noise;
    const double added =
        std::sqrt(std::max(0.0, args_.corner_noise * args_.corner_noise - present * present));
    std::mt19937_64 random(args_.noise_seed);
    std::normal_distribution<double> gauss(0, added);
    for (auto& obs : in_.observations) {
      for (int r = 0; r < obs.points.rows(); ++r) {
        if (obs.points(r, 2) <= 0 || added <= 0) continue;
        obs.points(r, 0) += gauss(random);
        obs.points(r, 1) += gauss(random);
      }
    }
    noise_ = MeasureNoise(false);
    const DetectionSummary& detection = in_.detection;
    std::printf(
        "detection: %lld views of %lld frames, %.1f frames/s, corners found to %.3f px per "
        "coordinate "
        "against the truth%s; %.3f px added, %.3f px in all\n",
        static_cast<long long>(detection.views), static_cast<long long>(detection.frames),
        detection.frames_per_second, found_noise,
        args_.true_corners ? " (replaced by the truth)" : "", added, noise_);
    for (const auto& [name, n] : detection.views_per_sensor)
      std::printf("  %s: %lld views\n", name.c_str(), static_cast<long long>(n));
  }

  void SolveHolocap() {
    const auto start = std::chrono::steady_clock::now();
    summary_ = Calibrate(in_.layout, in_.cameras, in_.observations, {});
    holocap_seconds_ = Seconds(start);
    comparison_ = CompareWithTruth(summary_, in_.truth, in_.world_from_board, in_.layout);
  }

  // holocap's ending, its stages and its figures against its targets.
  void PrintHolocapTables() const {
    const CalibrationSummary& s = summary_;
    const GroundTruthComparison& g = comparison_;
    std::printf("\nholocap: %s: %s\n", ToString(s.termination), s.message.c_str());
    for (const auto& note : s.notes) std::printf("  %s\n", note.c_str());
    for (const auto& stage : s.stages) {
      std::printf("  stage %s (%s): %.3f px RMS, %d outliers, at %.1f s\n", stage.name.c_str(),
                  stage.lensmodel.c_str(), stage.rms_px, stage.outliers, stage.seconds);
    }
    std::printf("| figure | measured | target |\n|---|---|---|\n");
    std::printf("| RMS reprojection / corner noise | %.3f / %.3f px (%.1f%%) | within 20%% |\n",
                s.rms_reprojection_px, noise_, 100 * (s.rms_reprojection_px / noise_ - 1));
    std::printf("| focal relative error, max | %.4f%% | <= 0.05%% |\n", 100 * g.focal_rel_err_max);
    std::printf("| principal point error, max | %.3f px | <= 0.5 px |\n",
                g.principal_point_err_px_max);
    std::printf(
        "| rotation error, max (solved rig laid onto the true one) | %.4f deg (cam_from_reference: "
        "%.4f) | <= 0.02 deg |\n",
        g.rotation_err_deg_max, g.rotation_err_deg_max_from_reference);
    std::printf(
        "| translation error, max (same) | %.3f mm (cam_from_reference: %.3f) | <= 1 mm |\n",
        g.translation_err_mm_max, g.translation_err_mm_max_from_reference);
    std::printf("| true vs solved projection, RMS | %.3f px (where seen: %.3f px) | <= 0.2 px |\n",
                g.projection_diff_rms_px, g.projection_diff_rms_observed_px);
    std::printf("| within 3x reported 1-sigma | %.1f%% | >= 90%% |\n",
                100 * g.within_3sigma_fraction);
    std::printf(
        "| solve (+ uncertainty) | %.1f s (+ %.1f s), %.1f s in all | <= 60 s on 2 cores |\n",
        s.solve_seconds, s.uncertainty_seconds, holocap_seconds_);
    for (const auto& [name, j] : g.per_camera)
      std::printf("  %s %s\n", name.c_str(), j.dump().c_str());
  }

  // The errors against the solve's own 1-sigma (relative to the reference camera, the frame
  // the solve states its poses in): errors of a few sigma are the data's limit.
  void PrintSigmaTable() const {
    std::printf(
        "\n| camera | focal err (1-sigma) | pp err px (1-sigma cx, cy) | rotation from ref err deg "
        "(1-sigma) | centre from ref err mm (1-sigma) |\n|---|---|---|---|---|\n");
    for (const auto& cam : summary_.cameras) {
      if (!cam.solved) continue;
      const nlohmann::json pc = TruthComparisonOf(cam.name);
      const auto& sigma = cam.intrinsics_sigma;
      const double f_sigma = sigma.size() >= 4 ? std::max(sigma[0] / cam.model.intrinsics()[0],
                                                          sigma[1] / cam.model.intrinsics()[1])
                                               : NAN;
      std::printf("| %s | %.4f%% (%.4f%%) | %.3f (%.3f, %.3f) | %.4f (%.4f) | %.3f (%.3f) |\n",
                  cam.name.c_str(), 100 * pc.value("focal_rel_err", NAN), 100 * f_sigma,
                  pc.value("principal_point_err_px", NAN), sigma.size() >= 4 ? sigma[2] : NAN,
                  sigma.size() >= 4 ? sigma[3] : NAN,
                  pc.value("rotation_err_deg_from_reference", NAN), cam.rotation_sigma_deg,
                  pc.value("translation_err_mm_from_reference", NAN), cam.center_sigma_mm);
    }
  }

  // OpenCV on the same detections: one calibrateCamera per camera with the rational model
  // (the same 8 distortion terms as OPENCV8).
  void RunCalibrateCamera() {
    std::printf(
        "\n| camera | holocap focal err | OpenCV focal err | holocap pp err | OpenCV pp err | "
        "OpenCV rms px | OpenCV s |\n|---|---|---|---|---|---|---|\n");
    double opencv_seconds = 0;
    for (const auto& cam : in_.cameras) {
      std::vector<std::vector<cv::Point3f>> object;
      std::vector<std::vector<cv::Point2f>> image;
      for (const auto& obs : in_.observations) {
        if (obs.sensor != cam.name) continue;
        std::vector<cv::Point3f> o;
        std::vector<cv::Point2f> i;
        for (int r = 0; r < obs.points.rows(); ++r) {
          if (obs.points(r, 2) <= 0) continue;
          const Eigen::Vector3d p = GridPointOfRow(r);
          o.emplace_back(p.x(), p.y(), 0);
          i.emplace_back(obs.points(r, 0), obs.points(r, 1));
        }
        object.push_back(o);
        image.push_back(i);
      }
      cv::Mat K, dist;
      std::vector<cv::Mat> rvecs, tvecs;
      const auto t0 = std::chrono::steady_clock::now();
      const double rms = cv::calibrateCamera(object, image, cv::Size(cam.width, cam.height), K,
                                             dist, rvecs, tvecs, cv::CALIB_RATIONAL_MODEL);
      const double seconds = Seconds(t0);
      opencv_seconds += seconds;
      opencv_K_[cam.name] = K;
      opencv_dist_[cam.name] = dist;
      const auto& t = in_.truth.at(cam.name).intrinsics();
      const double focal = std::max(std::abs(K.at<double>(0, 0) - t[0]) / t[0],
                                    std::abs(K.at<double>(1, 1) - t[1]) / t[1]);
      const double pp = std::hypot(K.at<double>(0, 2) - t[2], K.at<double>(1, 2) - t[3]);
      const nlohmann::json pc = TruthComparisonOf(cam.name);
      std::printf("| %s | %.4f%% | %.4f%% | %.3f | %.3f | %.3f | %.2f |\n", cam.name.c_str(),
                  100 * pc.value("focal_rel_err", NAN), 100 * focal,
                  pc.value("principal_point_err_px", NAN), pp, rms / std::sqrt(2.0), seconds);
    }
    std::printf(
        "OpenCV calibrateCamera, 8 cameras one by one (no rig, no uncertainty): %.1f s; holocap "
        "joint solve: %.1f s; time ratio holocap/OpenCV %.2f\n",
        opencv_seconds, holocap_seconds_, holocap_seconds_ / opencv_seconds);
  }

  // The camera that shares the most board views with camera `a`.
  std::string BestConnected(const std::string& a) const {
    std::string b;
    size_t best = 0;
    for (size_t c = 1; c < in_.cameras.size(); ++c) {
      size_t shared = 0;
      for (const auto& oa : in_.observations) {
        if (oa.sensor != a) continue;
        for (const auto& ob : in_.observations)
          shared += ob.sensor == in_.cameras[c].name && ob.frame_set == oa.frame_set;
      }
      if (shared > best) {
        best = shared;
        b = in_.cameras[c].name;
      }
    }
    return b;
  }

  // stereoCalibrate of the reference camera with its best-connected neighbour.
  void RunStereoCalibrate() {
    const std::string a = in_.cameras[0].name;
    const std::string b = BestConnected(a);
    std::vector<std::vector<cv::Point3f>> object;
    std::vector<std::vector<cv::Point2f>> ia, ib;
    for (const auto& oa : in_.observations) {
      if (oa.sensor != a) continue;
      for (const auto& ob : in_.observations) {
        if (ob.sensor != b || ob.frame_set != oa.frame_set) continue;
        std::vector<cv::Point3f> o;
        std::vector<cv::Point2f> pa, pb;
        for (int r = 0; r < oa.points.rows(); ++r) {
          if (oa.points(r, 2) <= 0 || ob.points(r, 2) <= 0) continue;
          const Eigen::Vector3d p = GridPointOfRow(r);
          o.emplace_back(p.x(), p.y(), 0);
          pa.emplace_back(oa.points(r, 0), oa.points(r, 1));
          pb.emplace_back(ob.points(r, 0), ob.points(r, 1));
        }
        if (o.size() >= 8) {
          object.push_back(o);
          ia.push_back(pa);
          ib.push_back(pb);
        }
      }
    }
    if (object.size() < 3) return;
    cv::Mat R, T, E, F;
    const auto t0 = std::chrono::steady_clock::now();
    cv::stereoCalibrate(object, ia, ib, opencv_K_[a], opencv_dist_[a], opencv_K_[b],
                        opencv_dist_[b], cv::Size(in_.cameras[0].width, in_.cameras[0].height), R,
                        T, E, F,
                        // Without the rational flag it drops k4..k6 of the intrinsics it was given.
                        cv::CALIB_FIX_INTRINSIC | cv::CALIB_RATIONAL_MODEL);
    const double seconds = Seconds(t0);
    Pose b_from_a = Pose::Identity();
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) b_from_a.linear()(r, c) = R.at<double>(r, c);
      b_from_a.translation()(r) = T.at<double>(r);
    }
    const Pose true_b_from_a = in_.truth.at(b).cam_from_world() * in_.truth.at(a).world_from_cam();
    const Pose delta = b_from_a * true_b_from_a.inverse();
    const GroundTruthComparison& g = comparison_;
    std::printf(
        "OpenCV stereoCalibrate %s-%s (%zu shared views, %.2f s): rotation err %.4f deg, "
        "translation err %.3f mm; holocap %s from %s: %.4f deg, %.3f mm\n",
        a.c_str(), b.c_str(), object.size(), seconds, RotationAngleDeg(delta.linear()),
        1000 * (b_from_a.inverse().translation() - true_b_from_a.inverse().translation()).norm(),
        b.c_str(), a.c_str(),
        g.per_camera.count(b) ? g.per_camera.at(b).value("rotation_err_deg_from_reference", NAN)
                              : NAN,
        g.per_camera.count(b) ? g.per_camera.at(b).value("translation_err_mm_from_reference", NAN)
                              : NAN);
  }

  // The image name mrcal's tool knows an observation by.
  static std::string MrcalImageName(const BoardObservation& obs) {
    char name[64];
    std::snprintf(name, sizeof(name), "frame%06lld-%s.png", static_cast<long long>(obs.frame_set),
                  obs.sensor.c_str());
    return name;
  }

  void WriteMrcalCorners(const std::filesystem::path& dir) const {
    WriteCornersVnl(in_.observations, MrcalImageName, dir / "corners.vnl");
  }

  // The tool takes one --imagersize for all cameras but reads each camera's size from its
  // images when they exist, so every named image is written blank at its camera's size; its
  // seed is a focal length per camera (the truth's, 10% low, as a user would guess it).
  // Returns the tool's command line.
  std::string PrepareMrcal(const std::filesystem::path& dir) const {
    std::string focals;
    for (const auto& cam : in_.cameras) {
      const cv::Mat blank(cam.height, cam.width, CV_8UC1, cv::Scalar(0));
      for (const auto& obs : in_.observations) {
        if (obs.sensor != cam.name) continue;
        cv::imwrite((dir / MrcalImageName(obs)).string(), blank);
      }
      if (!focals.empty()) focals += ",";
      focals += std::to_string(in_.truth.at(cam.name).intrinsics()[0] * 0.9);
    }
    std::string command = "cd " + dir.string() +
                          " && /usr/bin/python3 /usr/bin/mrcal-calibrate-cameras --corners-cache "
                          "corners.vnl --lensmodel LENSMODEL_OPENCV8 --focal " +
                          focals + " --object-spacing " + std::to_string(in_.layout.spacing) +
                          " --object-width-n " + std::to_string(board_.width_n()) +
                          " --object-height-n " + std::to_string(board_.height_n()) + " --outdir " +
                          dir.string();
    for (const auto& cam : in_.cameras) command += " 'frame*-" + cam.name + ".png'";
    command += " > mrcal.log 2>&1";
    return command;
  }

  // mrcal's own tool on the same corners, its models against holocap's.
  void RunMrcal() const {
    const std::filesystem::path dir =
        std::filesystem::temp_directory_path() / "holocap-calibration-bench-mrcal";
    std::filesystem::remove_all(dir);
    std::filesystem::create_directories(dir);
    WriteMrcalCorners(dir);
    const std::string command = PrepareMrcal(dir);
    const auto t0 = std::chrono::steady_clock::now();
    const int rc = std::system(command.c_str());
    const double mrcal_seconds = Seconds(t0);
    if (rc != 0) {
      std::printf("mrcal-calibrate-cameras failed (exit %d): see %s\n", rc,
                  (dir / "mrcal.log").c_str());
      return;
    }
    std::printf(
        "\nmrcal-calibrate-cameras on the same corners: %.1f s (holocap %.1f s, ratio %.2f)\n",
        mrcal_seconds, holocap_seconds_, holocap_seconds_ / mrcal_seconds);
    std::printf(
        "| camera | holocap vs mrcal projection diff (px RMS, implied rotation fitted) | holocap "
        "1-sigma mean / worst where seen (px) | within? |\n|---|---|---|---|\n");
    for (size_t c = 0; c < in_.cameras.size(); ++c) {
      const CalibratedCamera* mine = summary_.Find(in_.cameras[c].name);
      const std::filesystem::path file = dir / ("camera-" + std::to_string(c) + ".cameramodel");
      if (mine == nullptr || !mine->solved || !std::filesystem::exists(file)) continue;
      const CameraModel theirs = CameraModel::Read(file);
      const double diff = ProjectionDiffRms(mine->model, theirs, mine->uncertainty.distance_m);
      std::printf("| %s | %.3f | %.3f / %.3f | %s |\n", in_.cameras[c].name.c_str(), diff,
                  mine->uncertainty.mean_px, mine->uncertainty.worst_observed_px,
                  diff <= 3 * mine->uncertainty.mean_px ? "yes" : "no");
    }
  }

  const BenchArguments args_;
  BenchInput in_;      // its corners carry the added noise once SetCornerNoise has run
  const Board board_;  // in_.layout's
  double noise_ = 0;   // the corners' noise per coordinate against the truth, all told
  CalibrationSummary summary_;
  double holocap_seconds_ = 0;
  GroundTruthComparison comparison_;
  std::map<std::string, cv::Mat> opencv_K_, opencv_dist_;  // calibrateCamera's, per camera
};

int Run(int argc, char** argv) {
  std::setvbuf(stdout, nullptr, _IOLBF, 0);
  const BenchArguments args = ParseArguments(argc, argv);
  const SimOptions sim = BoardSimOptions(args);
  CalibrationBench(args, args.planned ? PlannedInput(args, sim) : DetectedInput(args, sim)).Run();
  return 0;
}

}  // namespace
}  // namespace holocap

int main(int argc, char** argv) {
  try {
    return holocap::Run(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "calibration_bench: error: %s\n", e.what());
    return 1;
  }
}
