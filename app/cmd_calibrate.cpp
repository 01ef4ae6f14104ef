// holocap calibrate: detect the board in a take, solve the rig with mrcal, write
// calib/<sensor>.cameramodel and calib/report.json; the demo's calibration stage.
#include <cstdio>
#include <iostream>

#include "app/commands.h"
#include "app/options.h"
#include "calibration/calibration.h"
#include "calibration/chessboard_finders.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/take.h"
#include "interop/interop.h"
#include "sim/sim.h"

namespace holocap {
namespace {

struct CalibrateArgs {
  std::string take;
  std::string from;
  std::string board;
  std::string lensmodel;
  std::vector<std::string> sensors;
  std::string reference;
  std::string detector = "holocap";
  bool compare_detectors = false;
  int64_t floor_board_set = -1;
  bool no_uncertainty = false;
  bool cross_validation = false;
  bool board_warp = false;
  bool no_pictures = false;
  std::string write_corners;
  int threads = 0;
};

void PrintSummary(const TakeCalibrationSummary& s) {
  const CalibrationSummary& c = s.calibration;
  std::string borders;
  for (const auto& [bits, views] : s.detection.views_per_tag_border_bits) {
    borders += Cat(borders.empty() ? "; tags with " : ", ", bits, "-bit borders",
                   bits == 2 ? " (Kalibr's print)" : "", " in ", views);
  }
  std::printf("detected %lld board views in %lld frames (%.1f frames/s%s)\n",
              static_cast<long long>(s.detection.views), static_cast<long long>(s.detection.frames),
              s.detection.frames_per_second, borders.c_str());
  if (c.reordered_views > 0 || !c.dropped_views.empty()) {
    std::printf(
        "board numbering: %d views turned to agree with their frame set's other cameras, %zu "
        "left out (no turn agreed)\n",
        c.reordered_views, c.dropped_views.size());
  }
  std::printf("%s: %s\n", ToString(c.termination), c.message.c_str());
  std::printf("lens model %s, reference %s, solve %.2f s, uncertainty %.2f s\n",
              c.lensmodel.c_str(), c.reference_camera.c_str(), c.solve_seconds,
              c.uncertainty_seconds);
  for (const auto& stage : c.stages) {
    if (stage.name != "everything") continue;
    std::printf(
        "mrcal final stage: %s, rms %.3f px, cost %.6g, %d outliers, one more step would "
        "remove %.2g of the cost\n",
        ToString(stage.termination), stage.rms_px, stage.cost, stage.outliers,
        stage.expected_decrease);
  }
  std::printf("world: %s (%s)\n", s.world_frame.c_str(), s.world_reason.c_str());
  std::printf("%-8s %6s %7s %8s %9s %11s  %s\n", "camera", "views", "points", "outliers", "rms_px",
              "sigma_seen", "flag");
  for (const auto& cam : c.cameras) {
    std::printf("%-8s %6d %7d %8d %9.3f %11.3f  %s\n", cam.name.c_str(), cam.views, cam.points,
                cam.outliers, cam.rms_px, cam.uncertainty.worst_observed_px, cam.flag.c_str());
  }
  for (const auto& d : s.depth) {
    std::printf("%s from %s: %s: %s\n", d.depth_sensor.c_str(), d.color_sensor.c_str(),
                ToString(d.termination), d.message.c_str());
  }
  if (s.has_ground_truth) {
    const auto& g = s.ground_truth;
    std::printf(
        "vs truth: focal %.4f%%, principal point %.3f px, rotation %.4f deg, translation %.3f mm, "
        "projection %.3f px RMS, within 3 sigma %.1f%%; world up %.3f deg, floor %.1f mm\n",
        100 * g.focal_rel_err_max, g.principal_point_err_px_max, g.rotation_err_deg_max,
        g.translation_err_mm_max, g.projection_diff_rms_px, 100 * g.within_3sigma_fraction,
        g.world_up_err_deg, g.world_floor_err_mm);
    if (!s.depth.empty()) {
      std::printf("depth sensors vs truth: rotation %.4f deg, translation %.2f mm\n",
                  g.depth_rotation_err_deg_max, g.depth_translation_err_mm_max);
    }
  }
}

void AddCalibrateCommand(CLI::App& app) {
  auto* command = app.add_subcommand(
      "calibrate",
      "Calibrate a take's cameras from board views (AprilTag/chessboard/ChArUco, mrcal)");
  auto args = std::make_shared<CalibrateArgs>();
  command->add_option("take", args->take, "The take directory")->required();
  command->add_option("--from", args->from,
                      "Take over the calibration of another take of the same rig (a calibrated "
                      "board take, or a folder of <sensor>.cameramodel files) instead of solving");
  command->add_option(
      "--board", args->board,
      "Board layout YAML, holocap's or Kalibr's target YAML (target_type: aprilgrid) "
      "(default: the take's gt/board.json)");
  command->add_option("--lens-model", args->lensmodel,
                      "mrcal lens model for every camera (default: per camera from the rig, "
                      "else LENSMODEL_OPENCV8)");
  command
      ->add_option("--sensors", args->sensors,
                   "Cameras to calibrate, comma-separated (default: all colour cameras)")
      ->delimiter(',');
  command->add_option("--reference", args->reference, "Reference camera (default: the first)");
  command->add_option("--floor-board-set", args->floor_board_set,
                      "Frame set whose board lies flat on the floor, printed side up: the world's "
                      "floor and origin (default: the take's metadata floor_board_set, else the "
                      "floor seen by depth sensors, else the cameras' up and the lowest board "
                      "point)");
  CLI::Option* detector =
      command
          ->add_option("--detector", args->detector,
                       "Chessboard finder: holocap (OpenCV's, refined on the image edges) or "
                       "mrgingham (mrcal's; square chessboards, the mrgingham program). With "
                       "--from, the finder the board take's calibration must have used")
          ->capture_default_str();
  command->add_flag("--compare-detectors", args->compare_detectors,
                    "Also run every detector that reads the board (chessboards: holocap's, "
                    "OpenCV's and mrgingham's finders; ChArUco: holocap's and OpenCV's) on every "
                    "view and report how far their corners lie apart (and from the truth on a "
                    "simulated take); the solve is unchanged. Refused on AprilTag boards");
  command->add_flag("--no-uncertainty", args->no_uncertainty, "Skip the projection uncertainty");
  command->add_flag("--cross-validate", args->cross_validation,
                    "Also solve two halves of the frames");
  command->add_flag("--board-warp", args->board_warp,
                    "Also solve the board's warp (mrcal's calobject_warp: a printed board that "
                    "bows along each axis)");
  command->add_flag("--no-pictures", args->no_pictures,
                    "Skip the residual/coverage/uncertainty PNGs");
  command->add_option(
      "--write-corners", args->write_corners,
      "Also write the corners the solve used as mrcal's corners.vnl, each view's image named "
      "<camera>/<frame set, 6 digits>.png as `export images --format png` names it (for "
      "mrcal-calibrate-cameras --corners-cache FILE 'CAMERA/*.png' ...)");
  command->add_option("--threads", args->threads, "Detection threads (0: all cores)")
      ->capture_default_str();
  command->callback([args, detector] {
    // Calibration writes the take's calib/: one writer at a time, never through a link.
    const TakeLock lock = TakeLock::Acquire(args->take, "calibrate");
    const std::filesystem::path calib = std::filesystem::path(args->take) / "calib";
    if (std::error_code ec; std::filesystem::is_symlink(calib, ec)) {
      Fail("'", calib.string(), "' is a symbolic link (to '",
           std::filesystem::read_symlink(calib, ec).string(),
           "'); calibrate writes the take's own calib/ folder, never through a link (remove the "
           "link first)");
    }
    if (!args->from.empty()) {
      Report report("calibrate");
      report.SetFailureDestination(calib / "report.json");
      std::optional<ChessboardFinder> finder;
      if (detector->count() > 0) finder = ParseChessboardFinder(args->detector);
      const TakeCalibrationSummary summary =
          AdoptCalibration(args->take, args->from, &report, finder);
      std::printf("%s: %s\nreport: %s\n", ToString(summary.termination), summary.message.c_str(),
                  summary.report_file.c_str());
      FailUnlessUsable(summary, "calibration");
      return;
    }
    TakeCalibrationOptions options;
    options.detection.chessboard_finder = ParseChessboardFinder(args->detector);
    options.board_file = args->board;
    options.lensmodel = args->lensmodel;
    options.sensors = args->sensors;
    options.solve.reference_camera = args->reference;
    options.floor_board_set = args->floor_board_set;
    options.solve.uncertainty = !args->no_uncertainty;
    options.solve.cross_validation = args->cross_validation;
    options.solve.solve_board_warp = args->board_warp;
    options.pictures = !args->no_pictures;
    options.detection.threads = args->threads;
    options.compare_detectors = args->compare_detectors;
    Report report("calibrate");
    report.SetFailureDestination(std::filesystem::path(args->take) / "calib" / "report.json");
    const TakeCalibrationSummary summary = CalibrateTake(args->take, options, &report);
    PrintSummary(summary);
    if (!args->write_corners.empty()) {
      WriteCornersVnl(
          summary.calibration.solved_views,
          [](const BoardObservation& view) {
            return view.sensor + "/" + ExportedImageName(view.frame_set, "png");
          },
          args->write_corners);
      std::printf("corners: %zu views written to %s\n", summary.calibration.solved_views.size(),
                  args->write_corners.c_str());
    }
    if (args->compare_detectors) {
      std::printf("%s corners, detector against detector:\n%s",
                  summary.detector_agreement.value("board", std::string()).c_str(),
                  summary.detector_table.c_str());
    }
    std::printf("report: %s\n", summary.report_file.c_str());
    // The state line is printed above; an unusable state ends in one error line and exit 1.
    FailUnlessUsable(summary, "calibration");
  });
}

// The demo's calibration stage: a small board take of the demo's rig, calibrated.
Summary CalibrateDemoTake(DemoContext& context) {
  SimOptions sim;
  sim.rig = "studio8";
  sim.scene = "board";
  sim.frames = 48;  // about 10 board views per camera
  sim.seed = context.seed;
  sim.overwrite = true;
  const std::filesystem::path take = context.out / "board-take";
  const SimSummary simulated = SimulateTake(sim, take);
  if (!IsUsable(simulated.termination)) return {simulated.termination, simulated.message};
  TakeCalibrationOptions options;
  options.solve.uncertainty_grid_x = 12;
  options.solve.uncertainty_grid_y = 9;
  Report report("calibrate");
  TakeCalibrationSummary summary = CalibrateTake(take, options, &report);
  PrintSummary(summary);
  nlohmann::json metrics = {{"termination", ToString(summary.termination)},
                            {"rms_reprojection_px", summary.calibration.rms_reprojection_px},
                            {"solve_s", summary.calibration.solve_seconds},
                            {"take", take.string()}};
  if (summary.has_ground_truth) {
    metrics["gt"] = summary.ground_truth.ToJson();
    metrics["gt"].erase("cameras");
  }
  context.report->metrics()["calibration"] = metrics;
  // The demo's own take is of the same rig: it gets these models, as a studio's takes get the
  // calibration of its board take.
  if (IsUsable(summary.termination) && std::filesystem::exists(context.take / "take.json")) {
    const TakeCalibrationSummary adopted = AdoptCalibration(context.take, take);
    std::printf("%s\n", adopted.message.c_str());
  }
  return summary;
}
HOLOCAP_DEMO_STAGE(20, "calibration", CalibrateDemoTake);

}  // namespace

HOLOCAP_COMMAND(40, AddCalibrateCommand);

}  // namespace holocap
