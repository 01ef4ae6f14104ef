// A whole take: detection, the solve, depth sensors, outputs and the comparison with truth.
#include <cmath>
#include <fstream>
#include <opencv2/imgproc.hpp>

#include "calibration/calibration.h"
#include "calibration/chessboard_finders.h"
#include "calibration/internal/common.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/image.h"
#include "core/take.h"
#include "core/take_plan.h"

namespace holocap {
namespace {

// Residual vectors (magnified) over the imager, coloured by magnitude.
cv::Mat ResidualPicture(const CalibratedCamera& cam) {
  cv::Mat image(cam.model.height(), cam.model.width(), CV_8UC3, cv::Scalar(255, 255, 255));
  double rms = std::max(1e-6, cam.rms_px);
  const double gain = 0.04 * std::max(cam.model.width(), cam.model.height()) / (3 * rms);
  for (size_t k = 0; k < cam.observed.size(); ++k) {
    const Eigen::Vector2d a = cam.observed[k];
    const Eigen::Vector2d b = a + cam.residuals[k] * gain;
    const double t = std::min(1.0, cam.residuals[k].norm() / (3 * rms));
    const cv::Scalar colour(255 * (1 - t), 0, 255 * t);
    cv::line(image, cv::Point2d(a.x(), a.y()), cv::Point2d(b.x(), b.y()), colour, 1, cv::LINE_AA);
  }
  cv::putText(image,
              Cat(cam.name, " residuals x", static_cast<int>(gain), ", rms ", cam.rms_px, " px"),
              cv::Point(5, 15), cv::FONT_HERSHEY_SIMPLEX, 0.4, cv::Scalar(0, 0, 0), 1, cv::LINE_AA);
  return image;
}

// Where the board was seen: darker = more observations.
cv::Mat CoveragePicture(const CalibratedCamera& cam) {
  const int cell = 8;
  const int gw = (cam.model.width() + cell - 1) / cell, gh = (cam.model.height() + cell - 1) / cell;
  cv::Mat counts = cv::Mat::zeros(gh, gw, CV_32F);
  for (const auto& q : cam.observed) {
    const int x = static_cast<int>(std::lround(q.x())) / cell,
              y = static_cast<int>(std::lround(q.y())) / cell;
    if (x >= 0 && y >= 0 && x < gw && y < gh) counts.at<float>(y, x) += 1;
  }
  cv::GaussianBlur(counts, counts, cv::Size(5, 5), 1.0);
  double peak = 0;
  cv::minMaxLoc(counts, nullptr, &peak);
  cv::Mat grey;
  counts.convertTo(grey, CV_8U, peak > 0 ? -255.0 / peak : 0, 255);
  cv::Mat image;
  cv::resize(grey, image, cv::Size(gw * cell, gh * cell), 0, 0, cv::INTER_NEAREST);
  image = image(cv::Rect(0, 0, cam.model.width(), cam.model.height())).clone();
  cv::cvtColor(image, image, cv::COLOR_GRAY2BGR);
  for (const auto& q : cam.observed)
    cv::circle(image, cv::Point2d(q.x(), q.y()), 1, cv::Scalar(0, 128, 0), -1);
  cv::putText(image, Cat(cam.name, " coverage: ", cam.views, " views, ", cam.points, " points"),
              cv::Point(5, 15), cv::FONT_HERSHEY_SIMPLEX, 0.4, cv::Scalar(0, 0, 255), 1,
              cv::LINE_AA);
  return image;
}

// Worst-direction 1-sigma over the imager, a colour map with its scale written on it.
cv::Mat UncertaintyPicture(const CalibratedCamera& cam) {
  const CameraUncertainty& u = cam.uncertainty;
  cv::Mat sigma(u.grid_y, u.grid_x, CV_32F);
  double worst = 1e-9;
  for (int y = 0; y < u.grid_y; ++y) {
    for (int x = 0; x < u.grid_x; ++x) {
      const double s = u.worst_sigma_px(y, x);
      sigma.at<float>(y, x) = std::isfinite(s) ? static_cast<float>(s) : 0.f;
      if (std::isfinite(s)) worst = std::max(worst, s);
    }
  }
  cv::Mat grey, big, colour;
  sigma.convertTo(grey, CV_8U, 255.0 / worst);
  cv::resize(grey, big, cv::Size(cam.model.width(), cam.model.height()), 0, 0, cv::INTER_LINEAR);
  cv::applyColorMap(big, colour, cv::COLORMAP_VIRIDIS);
  cv::putText(
      colour, Cat(cam.name, " projection 1-sigma at ", u.distance_m, " m: max ", u.worst_px, " px"),
      cv::Point(5, 15), cv::FONT_HERSHEY_SIMPLEX, 0.4, cv::Scalar(255, 255, 255), 1, cv::LINE_AA);
  return colour;
}

BoardLayout FindBoard(const Take& take, const TakeCalibrationOptions& options) {
  if (!options.board_file.empty()) return BoardLayout::Load(options.board_file);
  const fs::path gt_board = take.gt_dir() / "board.json";
  if (fs::exists(gt_board)) {
    const nlohmann::json json = nlohmann::json::parse(ReadFileToString(gt_board), nullptr, false);
    if (json.is_discarded() || !json.contains("layout"))
      Fail(gt_board.string(), ": no board layout");
    return BoardLayout::FromJson(json["layout"], gt_board.string());
  }
  Fail("take ", take.dir().string(), " names no board: pass --board BOARD.yaml");
}

std::map<int64_t, Pose> TrueBoardPoses(const Take& take) {
  std::map<int64_t, Pose> poses;
  const fs::path file = take.gt_dir() / "board.json";
  if (!fs::exists(file)) return poses;
  const nlohmann::json json = nlohmann::json::parse(ReadFileToString(file), nullptr, false);
  if (json.is_discarded() || !json.contains("world_from_board")) return poses;
  for (const auto& entry : json["world_from_board"]) {
    const auto rt = entry.at("rt").get<std::vector<double>>();
    if (rt.size() != 6) continue;
    poses[entry.at("set").get<int64_t>()] = PoseFromRt({rt[0], rt[1], rt[2], rt[3], rt[4], rt[5]});
  }
  return poses;
}

}  // namespace

std::string RigLensModel(const Take& take, const std::string& sensor) {
  const int in_rig = take.rig().IndexOf(sensor);
  if (in_rig >= 0 && take.rig().sensors[in_rig].options.contains("calib_lensmodel")) {
    std::string model = take.rig().sensors[in_rig].options["calib_lensmodel"].get<std::string>();
    calibration_internal::CheckLensmodelName(model);
    return model;
  }
  return "LENSMODEL_OPENCV8";
}

void TakeCalibrationOptions::Check() const {
  detection.Check();
  solve.Check();
  depth.Check();
  if (!lensmodel.empty()) calibration_internal::CheckLensmodelName(lensmodel);
}

namespace {

// The colour cameras to calibrate (all when none are named) with their lens models.
std::vector<CalibrationCamera> CamerasToCalibrate(const Take& take,
                                                  const TakeCalibrationOptions& options,
                                                  std::vector<std::string>* sensors) {
  *sensors = ChooseColorSensors(take, options.sensors);
  std::vector<CalibrationCamera> cameras;
  for (const auto& name : *sensors) {
    const StreamInfo& stream = take.stream(name);
    cameras.push_back({name, stream.width, stream.height,
                       options.lensmodel.empty() ? RigLensModel(take, name) : options.lensmodel});
  }
  return cameras;
}

// The solve against the simulation's truth (gt/cameras), when the take has it: for measuring
// only, the written models stay in the take's own world.
void CompareTakeWithTruth(const Take& take, const BoardLayout& layout, const Pose& world_from_ref,
                          const std::map<std::string, CameraModel>& depth_in_ref,
                          TakeCalibrationSummary* result) {
  const CalibrationSummary& cal = result->calibration;
  result->has_ground_truth = take.has_ground_truth() && fs::exists(take.gt_dir() / "cameras");
  std::map<std::string, CameraModel> truth;
  if (result->has_ground_truth) {
    for (const auto& c : cal.cameras) {
      const fs::path file = take.gt_dir() / "cameras" / (c.name + ".cameramodel");
      if (fs::exists(file)) truth.emplace(c.name, CameraModel::Read(file));
    }
    result->has_ground_truth = truth.count(cal.reference_camera) > 0;
    for (const auto& [name, model] : depth_in_ref) {
      const fs::path file = take.gt_dir() / "cameras" / (name + ".cameramodel");
      if (fs::exists(file)) truth.emplace(name, CameraModel::Read(file));
    }
  }
  // Without a solved board pose there is nothing to compare: no figures, not zeros.
  result->has_ground_truth = result->has_ground_truth && !cal.ref_from_board.empty();
  if (result->has_ground_truth) {
    result->ground_truth =
        CompareWithTruth(cal, truth, TrueBoardPoses(take), layout, world_from_ref, depth_in_ref);
  }
}

// calib/<sensor>.cameramodel of every trusted camera and aligned depth sensor (in the take's
// world) and the pictures of every solved camera.
void WriteModelsAndPictures(const Take& take, const Pose& world_from_ref,
                            const std::map<std::string, CameraModel>& depth_in_ref, bool pictures,
                            TakeCalibrationSummary* result) {
  CreateDirectories(take.calib_dir());
  for (const auto& [name, in_ref] : depth_in_ref) {
    CameraModel model = in_ref;
    model.set_cam_from_world(in_ref.cam_from_world() * world_from_ref.inverse());
    const fs::path file = take.calib_dir() / (name + ".cameramodel");
    model.Write(file);
    result->written.push_back(file);
  }
  for (const auto& c : result->calibration.cameras) {
    if (!c.solved) continue;
    if (c.flag.empty()) {
      CameraModel model = c.model;
      model.set_cam_from_world(c.model.cam_from_world() * world_from_ref.inverse());
      const fs::path file = take.calib_dir() / (c.name + ".cameramodel");
      model.Write(file);
      result->written.push_back(file);
    }
    if (!pictures) continue;
    const fs::path residuals = take.calib_dir() / (c.name + ".residuals.png");
    WritePng(residuals, ResidualPicture(c));
    const fs::path coverage = take.calib_dir() / (c.name + ".coverage.png");
    WritePng(coverage, CoveragePicture(c));
    result->written.push_back(residuals);
    result->written.push_back(coverage);
    if (c.uncertainty.grid_x > 0 && std::isfinite(c.uncertainty.worst_px)) {
      const fs::path picture = take.calib_dir() / (c.name + ".uncertainty.png");
      WritePng(picture, UncertaintyPicture(c));
      result->written.push_back(picture);
    }
  }
}

// depth_from_color of every depth sensor paired with a trusted camera; the models of those
// aligned, in the reference camera's frame.
std::map<std::string, CameraModel> AlignDepthSensors(const Take& take, const BoardLayout& layout,
                                                     const TakeCalibrationOptions& options,
                                                     TakeCalibrationSummary* result) {
  const CalibrationSummary& cal = result->calibration;
  std::map<std::string, CameraModel> depth_in_ref;
  for (const auto& stream : take.streams()) {
    if (stream.role != SensorRole::kDepth || stream.paired_with.empty()) continue;
    const CalibratedCamera* colour = cal.Find(stream.paired_with);
    if (colour == nullptr || !colour->solved || !colour->flag.empty()) continue;
    const int in_rig = take.rig().IndexOf(stream.name);
    DepthAlignmentSummary depth;
    depth.depth_sensor = stream.name;
    depth.color_sensor = stream.paired_with;
    if (in_rig < 0 || !take.rig().sensors[in_rig].options.contains("intrinsics")) {
      depth.End(Termination::kDegenerate,
                "the rig gives no depth intrinsics (sensor options lens/intrinsics/size)");
      result->depth.push_back(depth);
      continue;
    }
    const auto& o = take.rig().sensors[in_rig].options;
    const auto size = o.value("size", std::vector<int>{stream.width, stream.height});
    CameraModel depth_model(o.value("lens", std::string("LENSMODEL_OPENCV4")),
                            o["intrinsics"].get<std::vector<double>>(), size.at(0), size.at(1));
    if (depth_model.width() != stream.width) {
      depth_model = depth_model.Scaled(static_cast<double>(stream.width) / depth_model.width());
    }
    std::map<int64_t, Pose> colour_from_board;
    for (const auto& [set, pose] : cal.ref_from_board)
      colour_from_board[set] = colour->model.cam_from_world() * pose;
    depth = AlignDepthToColor(take, stream.name, depth_model, stream.paired_with, colour->model,
                              colour_from_board, layout, options.depth);
    if (IsUsable(depth.termination)) {
      CameraModel model = depth_model;
      model.set_cam_from_world(depth.depth_from_color * colour->model.cam_from_world());
      depth_in_ref.emplace(stream.name, model);
    }
    result->depth.push_back(depth);
  }
  return depth_in_ref;
}

// The plan, metrics and summary of calib/report.json.
void FillReport(const TakeCalibrationOptions& options, const std::vector<std::string>& sensors,
                const TakeCalibrationSummary& result, Report& r) {
  const CalibrationSummary& cal = result.calibration;
  r.plan()["lensmodel"] = cal.lensmodel;
  if (!cal.notes.empty()) r.plan()["lens_models"] = cal.notes;
  r.plan()["reference_camera"] = cal.reference_camera;
  r.plan()["world_frame"] = result.world_frame;
  r.plan()["world_reason"] = result.world_reason;
  r.plan()["cameras"] = sensors;
  r.plan()["stages"] = {
      "detect",
      "seed (solvePnP + camera graph)",
      "geometry (stereographic)",
      "core (stereographic)",
      "intrinsics (" + cal.lensmodel + ")",
      "everything (regularised, outliers rejected)",
      options.solve.uncertainty ? "uncertainty" : "no uncertainty",
      options.solve.cross_validation ? "cross-validation" : "no cross-validation"};
  nlohmann::json& m = r.metrics();
  const nlohmann::json cal_json = cal.ToJson();
  m["rms_reprojection_px"] = cal.rms_reprojection_px;
  m["observed_pixel_sigma"] = cal.observed_pixel_sigma;
  m["outliers"] = cal.outliers;
  m["reordered_views"] = cal_json["reordered_views"];
  m["dropped_views"] = cal_json["dropped_views"];
  m["board_warp_m"] = cal_json["board_warp_m"];
  m["cameras"] = cal_json["cameras"];
  m["stages"] = cal_json["stages"];
  if (cal_json.contains("mrcal")) m["mrcal"] = cal_json["mrcal"];
  m["warnings"] = cal.warnings;
  m["notes"] = cal.notes;
  m["detection"] = result.detection.ToJson();
  m["timing"] = {{"solve_s", cal.solve_seconds},
                 {"uncertainty_s", cal.uncertainty_seconds},
                 {"detect_s", result.detection.seconds},
                 {"detect_frames_per_s", result.detection.frames_per_second}};
  double worst_sigma = 0, worst_observed = 0;
  for (const auto& c : cal.cameras) {
    if (!c.solved || c.uncertainty.grid_x == 0) continue;
    worst_sigma = std::max(worst_sigma, c.uncertainty.worst_px);
    worst_observed = std::max(worst_observed, c.uncertainty.worst_observed_px);
  }
  m["uncertainty"] = {{"worst_px", worst_sigma},
                      {"worst_observed_px", worst_observed},
                      {"observed_pixel_sigma", cal.observed_pixel_sigma}};
  if (!cal.cross_validation.is_null()) m["cross_validation"] = cal.cross_validation;
  if (!cal.model_fit.is_null()) m["model_fit"] = cal.model_fit;
  nlohmann::json depth_json = nlohmann::json::array();
  for (const auto& d : result.depth) depth_json.push_back(d.ToJson());
  m["depth"] = depth_json;
  if (result.has_ground_truth) m["gt"] = result.ground_truth.ToJson();
  if (options.compare_detectors) m["detector_agreement"] = result.detector_agreement;
  r.SetSummary(result);
}

}  // namespace

TakeCalibrationSummary CalibrateTake(const fs::path& take_dir,
                                     const TakeCalibrationOptions& options, Report* report) {
  options.Check();
  const Take take = Take::Open(take_dir);
  const BoardLayout layout = FindBoard(take, options);
  if (options.compare_detectors) CheckDetectorsComparable(layout);
  std::vector<std::string> sensors;
  const std::vector<CalibrationCamera> cameras = CamerasToCalibrate(take, options, &sensors);

  CalibrationOptions solve = options.solve;
  if (solve.tag_read_px == 0) solve.tag_read_px = options.detection.min_tag_side_px;
  TakeCalibrationSummary result;
  if (report != nullptr) {
    report->options() = {{"take", take_dir.string()},
                         {"board", layout.ToJson()},
                         {"detector", ToString(options.detection.chessboard_finder)},
                         {"detection", options.detection.ToJson()},
                         {"solve", solve.ToJson()},
                         {"lensmodel", options.lensmodel}};
  }
  std::vector<BoardObservation> observations =
      DetectBoardsInTake(take, layout, sensors, options.detection, &result.detection);
  result.calibration = Calibrate(layout, cameras, observations, solve, report);
  CalibrationSummary& cal = result.calibration;

  std::map<std::string, CameraModel> depth_in_ref;
  if (options.depth_sensors) depth_in_ref = AlignDepthSensors(take, layout, options, &result);
  const calibration_internal::TakeWorld world = calibration_internal::ChooseTakeWorld(
      take, layout, cal, depth_in_ref, options.floor_board_set);
  result.world_frame = world.frame;
  result.world_reason = world.why;
  CompareTakeWithTruth(take, layout, world.world_from_ref, depth_in_ref, &result);
  if (options.compare_detectors) {
    result.detector_agreement = CompareBoardDetectors(
        take_dir, layout, options.sensors, options.detection.threads, &result.detector_table);
  }
  WriteModelsAndPictures(take, world.world_from_ref, depth_in_ref, options.pictures, &result);

  result.End(cal.termination, cal.message);
  for (const auto& d : result.depth) {
    if (!IsUsable(d.termination)) cal.warnings.push_back(d.depth_sensor + ": " + d.message);
  }

  Report local("calibrate");
  Report& r = report != nullptr ? *report : local;
  FillReport(options, sensors, result, r);
  const fs::path report_file = take.calib_dir() / "report.json";
  // A failed run's report goes beside a previous good one (calib/report.failed.json).
  result.report_file = r.Write(report_file);
  result.written.push_back(result.report_file);
  return result;
}

}  // namespace holocap
