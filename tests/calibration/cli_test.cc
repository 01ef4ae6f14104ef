// End to end through the CLI on small simulated studio8 board takes, and its bad-input errors.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <numbers>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include "core/camera.h"
#include "core/fs.h"
#include "core/pose.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::ExpectOneLineError;
using testing::RunCli;
using testing::RunShell;
using testing::TempDir;

// One small board take shared by the tests of this file (simulating is the slow part).
const std::filesystem::path& BoardTake() {
  static TempDir dir("holocap-calib-cli");
  static const bool made = [] {
    const auto result =
        RunCli("sim --rig studio8 --board --frames 48 --size 640 --out " + (dir / "take").string());
    EXPECT_EQ(result.exit_code, 0) << result.output;
    return true;
  }();
  (void)made;
  static const std::filesystem::path take = dir / "take";
  return take;
}

TEST(CalibrateCli, CalibratesASimulatedBoardTake) {
  const auto result = RunCli("calibrate " + BoardTake().string() + " --no-pictures");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  for (int i = 0; i < 8; ++i) {
    EXPECT_TRUE(std::filesystem::exists(BoardTake() / "calib" /
                                        ("cam" + std::to_string(i) + ".cameramodel")))
        << i;
  }
  const auto report =
      nlohmann::json::parse(ReadFileToString(BoardTake() / "calib" / "report.json"));
  const auto& m = report["metrics"];
  EXPECT_LT(m["rms_reprojection_px"].get<double>(), 0.6);
  EXPECT_GT(m["timing"]["solve_s"].get<double>(), 0);
  EXPECT_TRUE(m["cameras"]["cam3"].contains("outliers"));
  EXPECT_GT(m["uncertainty"]["worst_observed_px"].get<double>(), 0);
  EXPECT_FALSE(report["series"].empty());
  // Against the simulated truth; this reduced take (48 sets, ~10 views per camera) is held to
  // looser bounds than the full studio8 figures the benchmark prints.
  EXPECT_LT(m["gt"]["projection_diff_rms_observed_px"].get<double>(), 0.3);
  EXPECT_LT(m["gt"]["focal_rel_err_max"].get<double>(), 0.005);
  EXPECT_GE(m["gt"]["within_3sigma_fraction"].get<double>(), 0.8);
  // Both depth sensors aligned from board planes, up to 4.9 m away (0.03 deg and 2.4 mm here;
  // 0.33 deg and 71 mm while a plane was fitted to the depth noise's mode).
  ASSERT_EQ(m["depth"].size(), 2u);
  for (const auto& depth : m["depth"]) EXPECT_EQ(depth["termination"], "SUCCESS") << depth.dump();
  EXPECT_LT(m["gt"]["depth_rotation_err_deg_max"].get<double>(), 0.1);
  EXPECT_LT(m["gt"]["depth_translation_err_mm_max"].get<double>(), 6.0);
}

// Without mrcal's regularisation an OPENCV8 lens is often singular however well the board
// moved: in this studio8 board take (seed 3) a camera's views-alone focal sigma cannot be
// computed, while the solve puts it 0.25 % from the truth. Such a figure decides nothing: the
// take calibrates (it was DEGENERATE while an infinite sigma counted as unconstrained).
TEST(CalibrateCli, ALensSingularWithoutRegularisationIsJudgedByItsViewsAndUncertainty) {
  TempDir dir("holocap-calib-seed3");
  const std::string take = (dir.path() / "take").string();
  const auto sim =
      RunCli("sim --rig studio8 --board --frames 48 --size 640 --seed 3 --out " + take);
  ASSERT_EQ(sim.exit_code, 0) << sim.output;
  const auto result = RunCli("calibrate " + take + " --no-pictures");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  const auto report = nlohmann::json::parse(
      ReadFileToString(std::filesystem::path(take) / "calib" / "report.json"));
  EXPECT_EQ(report["summary"]["termination"], "CONVERGENCE");
  int not_computed = 0;
  for (const auto& [name, camera] : report["metrics"]["cameras"].items()) {
    if (camera.contains("focal_sigma_views_rel") && camera["focal_sigma_views_rel"].is_null())
      ++not_computed;
  }
  EXPECT_GE(not_computed, 1) << "the case this test is about did not occur";
  EXPECT_LT(report["metrics"]["gt"]["focal_rel_err_max"].get<double>(), 0.005);
}

// A ring of `cameras` cameras placed as studio8's first ones (45 degrees apart, alternately low
// and high, ~3 m from the stage) with plain OPENCV4 and OPENCV5 lenses, as a sim rig file: rigs
// as small as what a test shows, so that simulating and detecting stay cheap.
std::string WriteRingRig(const std::filesystem::path& dir, int cameras) {
  const std::filesystem::path file = dir / ("ring" + std::to_string(cameras) + ".yaml");
  std::ofstream out(file);
  out << "name: ring\nfps: 30\nsensors:\n";
  for (int i = 0; i < cameras; ++i) {
    const double azimuth = (22.5 + 45.0 * i) * std::numbers::pi / 180;
    const double radius = 3.0 + 0.1 * (i % 3);
    const bool low = i % 2 == 0;
    out << "  - name: cam" << i << "\n    uri: sim:ring#cam" << i
        << "\n    role: color\n    options:\n"
        << (low ? "      lens: LENSMODEL_OPENCV4\n"
                  "      intrinsics: [520.3, 519.1, 322.4, 236.9, -0.082, 0.031, 0.0006, -0.0004]\n"
                : "      lens: LENSMODEL_OPENCV5\n"
                  "      intrinsics: [561.7, 560.2, 316.8, 243.5, -0.121, 0.094, -0.0003, 0.0007, "
                  "-0.021]\n")
        << "      size: [640, 480]\n      position: [" << radius * std::cos(azimuth) << ", "
        << radius * std::sin(azimuth) << ", " << (low ? 1.45 : 2.1) << "]\n      look_at: [0, 0, "
        << (low ? 1.0 : 0.9) << "]\n";
  }
  return file.string();
}

// A square chessboard (7 x 7 inner corners) is the same board turned by 180 degrees: cam1 and
// cam3, mounted upside down, see it numbered from the other end than their neighbours cam0 and
// cam2 do in every view they share. The solve turns those views to agree and calibrates to the
// truth.
TEST(CalibrateCli, ASquareChessboardSeenUpsideDownCalibrates) {
  TempDir dir("holocap-calib-square");
  {
    std::ofstream(dir / "square.yaml")
        << "type: chessboard\nchessboard_width_n: 7\nchessboard_height_n: 7\n"
           "spacing: 0.1\nmargin: 0.2\n";
  }
  const std::string take = (dir / "take").string();
  auto r = RunCli("sim --rig " + WriteRingRig(dir.path(), 4) + " --board --board-layout " +
                  (dir / "square.yaml").string() +
                  " --upside-down cam1,cam3 --frames 36 --size 480 --out " + take);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = RunCli("calibrate " + take + " --no-pictures");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("views turned to agree"), std::string::npos) << r.output;
  const auto report =
      nlohmann::json::parse(ReadFileToString(dir / "take" / "calib" / "report.json"));
  const auto& m = report["metrics"];
  EXPECT_EQ(report["summary"]["termination"], "CONVERGENCE") << report["summary"].dump();
  // Every shared view pairs an upright camera with an upside-down one: 24 frame sets are
  // planned shared, and each of the 20 that both cameras detect has one view turned.
  EXPECT_GE(m["reordered_views"].get<int>(), 16);
  EXPECT_EQ(m["dropped_views"].size(), 0u) << m["dropped_views"].dump();
  // Measured 0.018 % and 0.04 px; a view left numbered from the other end gives tens of %.
  EXPECT_LT(m["gt"]["focal_rel_err_max"].get<double>(), 0.002);
  EXPECT_LT(m["gt"]["principal_point_err_px_max"].get<double>(), 0.5);
  EXPECT_LT(m["gt"]["projection_diff_rms_observed_px"].get<double>(), 0.3);
  EXPECT_GE(m["gt"]["within_3sigma_fraction"].get<double>(), 0.6);
  for (const auto& [name, camera] : m["cameras"].items()) {
    EXPECT_GT(camera["pose_spread"]["normal_spread_deg"].get<double>(), 20) << name;
    EXPECT_GT(camera["pose_spread"]["coverage"].get<double>(), 0.2) << name;
  }
}

// A two-camera ring at 640 px films the board of `layout` (DIR/take; `sim_flags`: 16 frame sets
// unless told), and `holocap calibrate --board` solves it, writing the corners it used to
// DIR/corners.vnl.
void CalibrateRingTake(const std::filesystem::path& dir, const std::filesystem::path& layout,
                       nlohmann::json* report, const std::string& sim_flags = "--frames 16") {
  const std::string take = (dir / "take").string();
  auto r = RunCli("sim --rig " + WriteRingRig(dir, 2) + " --board --board-layout " +
                  layout.string() + " " + sim_flags + " --size 640 --out " + take);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = RunCli("calibrate " + take + " --no-pictures --board " + layout.string() +
             " --write-corners " + (dir / "corners.vnl").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  *report = nlohmann::json::parse(ReadFileToString(dir / "take" / "calib" / "report.json"));
}

// The corners a calibration used (its --write-corners file) against the true grid (width_n
// points per row, `spacing` apart) projected by the take's true cameras and board poses.
struct CornerTruth {
  int count = 0;
  double mean_px = 0, max_px = 0;
  double rms_px = 0;  // per coordinate
  std::map<std::string, int> seen_in_view;
};

CornerTruth CornersAgainstTruth(const std::filesystem::path& take,
                                const std::filesystem::path& corners_file, int width_n,
                                double spacing) {
  const nlohmann::json board = nlohmann::json::parse(ReadFileToString(take / "gt/board.json"));
  std::map<int64_t, Pose> world_from_board;
  for (const auto& entry : board["world_from_board"]) {
    const auto rt = entry["rt"].get<std::vector<double>>();
    world_from_board[entry["set"].get<int64_t>()] =
        PoseFromRt({rt[0], rt[1], rt[2], rt[3], rt[4], rt[5]});
  }
  CornerTruth result;
  std::map<std::string, int> row_of_view;
  double error_sum = 0, error_square_sum = 0;
  std::istringstream vnl(ReadFileToString(corners_file));
  for (std::string line; std::getline(vnl, line);) {
    if (line.empty() || line[0] == '#') continue;
    std::istringstream fields(line);
    std::string name, x, y;
    fields >> name >> x >> y;
    const int row = row_of_view[name]++;
    if (x == "-") continue;
    ++result.seen_in_view[name];
    const std::string camera = name.substr(0, name.find('/'));
    const int64_t set = std::stoll(name.substr(name.find('/') + 1));
    const CameraModel truth = CameraModel::Read(take / "gt/cameras" / (camera + ".cameramodel"));
    const int i = row % width_n, j = row / width_n;
    const Eigen::Vector3d point(i * spacing, j * spacing, 0);
    Eigen::Vector2d pixel;
    EXPECT_TRUE(truth.Project(truth.cam_from_world() * world_from_board.at(set) * point, &pixel));
    const double error = (pixel - Eigen::Vector2d(std::stod(x), std::stod(y))).norm();
    error_sum += error;
    error_square_sum += error * error;
    result.max_px = std::max(result.max_px, error);
    ++result.count;
  }
  if (result.count > 0) {
    result.mean_px = error_sum / result.count;
    result.rms_px = std::sqrt(error_square_sum / (2.0 * result.count));
  }
  return result;
}

// Each camera's focal length and principal point against the truth, within 4 of the solve's
// 1-sigma. That 1-sigma assumes the residuals' noise (~0.002 px on noise-free renders); the
// corners lie further from the truth than that, by a bias the residuals cannot show. The
// uncertainty scales with the noise, so the bounds scale it to the corners' RMS error.
void ExpectIntrinsicsWithinTheirSigma(const nlohmann::json& m, const CornerTruth& corners,
                                      int min_views) {
  const double noise_scale = std::max(1.0, corners.rms_px / m["rms_reprojection_px"].get<double>());
  std::printf(
      "residuals %.4f px RMS, corners %.4f px RMS from the truth (per coordinate); "
      "projection %.4f px RMS from the truth where seen\n",
      m["rms_reprojection_px"].get<double>(), corners.rms_px,
      m["gt"]["projection_diff_rms_observed_px"].get<double>());
  for (const auto& [name, camera] : m["cameras"].items()) {
    ASSERT_TRUE(camera["solved"].get<bool>()) << name;
    EXPECT_GE(camera["views"].get<int>(), min_views) << name;
    // fx, fy, cx, cy and their 1-sigma from the solve's own noise model.
    const auto& sigma = camera["intrinsics_sigma"];
    const double focal_sigma_px = std::max(sigma[0].get<double>(), sigma[1].get<double>());
    const double centre_sigma_px = std::hypot(sigma[2].get<double>(), sigma[3].get<double>());
    const auto& truth = m["gt"]["cameras"][name];
    const double focal_err_px =
        truth["focal_rel_err"].get<double>() * camera["intrinsics"][0].get<double>();
    std::printf(
        "%s: focal %.3f px (1-sigma %.3f, at the corners' noise %.3f), principal point "
        "%.3f px (1-sigma %.3f, %.3f)\n",
        name.c_str(), focal_err_px, focal_sigma_px, noise_scale * focal_sigma_px,
        truth["principal_point_err_px"].get<double>(), centre_sigma_px,
        noise_scale * centre_sigma_px);
    EXPECT_LT(focal_err_px, 4 * noise_scale * focal_sigma_px) << name;
    EXPECT_LT(truth["principal_point_err_px"].get<double>(), 4 * noise_scale * centre_sigma_px)
        << name;
  }
}

const char* const kCharucoLayout =
    "type: charuco\nsquares_across: 6\nsquares_down: 5\nspacing: 0.16\nmarker_side: 0.12\n"
    "dictionary: DICT_4X4_50\nmargin: 0.16\n";

// A ChArUco board (6 x 5 squares of 16 cm, 4x4 markers) filmed by a two-camera ring at 640 px:
// the corners of partial views count as the AprilTag boards' do, and the solve lands on the true
// lenses within its own uncertainty. The same take with ChArUco corner ids turned into the wrong
// grid points (transposed) ends far from the truth, which the bounds here catch.
TEST(CalibrateCli, CalibratesAChArUcoBoardTake) {
  TempDir dir("holocap-calib-charuco");
  const std::filesystem::path layout = dir / "charuco.yaml";
  std::ofstream(layout) << kCharucoLayout;
  nlohmann::json report;
  ASSERT_NO_FATAL_FAILURE(CalibrateRingTake(dir.path(), layout, &report));
  const auto& m = report["metrics"];
  EXPECT_EQ(report["summary"]["termination"], "CONVERGENCE") << report["summary"].dump();

  const CornerTruth corners = CornersAgainstTruth(dir / "take", dir / "corners.vnl", 5, 0.16);
  int partial_views = 0;
  for (const auto& [name, seen] : corners.seen_in_view) partial_views += seen < 20;
  std::printf("ChArUco take: %d corners in %zu views (%d partial): mean %.4f px, max %.4f px\n",
              corners.count, corners.seen_in_view.size(), partial_views, corners.mean_px,
              corners.max_px);
  EXPECT_GE(corners.count, 20 * 16);
  // Measured 0.013 px on average, 0.096 px at most.
  EXPECT_LT(corners.mean_px, 0.05);
  EXPECT_LT(corners.max_px, 0.25);
  ExpectIntrinsicsWithinTheirSigma(m, corners, 10);
  EXPECT_LT(m["rms_reprojection_px"].get<double>(), 0.3);
  EXPECT_LT(m["gt"]["projection_diff_rms_observed_px"].get<double>(), 0.3);
}

// Many views show the ChArUco board only partly, the rest of it beyond the image's edge (sim
// --board-partial: every single-camera view, a third of the frame sets): their corners go
// through the solve as the whole views' do (the corners not seen weighted below zero), and it
// lands on the true lenses within its own uncertainty.
TEST(CalibrateCli, CalibratesAChArUcoTakeOfPartialViews) {
  TempDir dir("holocap-calib-charuco-partial");
  const std::filesystem::path layout = dir / "charuco.yaml";
  std::ofstream(layout) << kCharucoLayout;
  nlohmann::json report;
  ASSERT_NO_FATAL_FAILURE(
      CalibrateRingTake(dir.path(), layout, &report, "--board-partial 1 --frames 30"));
  EXPECT_EQ(report["summary"]["termination"], "CONVERGENCE") << report["summary"].dump();
  const CornerTruth corners = CornersAgainstTruth(dir / "take", dir / "corners.vnl", 5, 0.16);
  int partial_views = 0;
  for (const auto& [name, seen] : corners.seen_in_view) partial_views += seen < 20;
  std::printf("ChArUco partial views: %d corners in %zu views (%d partial): mean %.4f px\n",
              corners.count, corners.seen_in_view.size(), partial_views, corners.mean_px);
  // 10 of the 30 frame sets are single-camera views, each showing 35-85 % of the grid; 6 of
  // them held 6 or more ChArUco corners (a corner needs both markers beside it) and went into
  // the solve, as none did while views of fewer than 12 points were left out.
  EXPECT_GE(partial_views, 5);
  EXPECT_LT(corners.mean_px, 0.05);
  ExpectIntrinsicsWithinTheirSigma(report["metrics"], corners, 8);
}

// Kalibr's aprilgrid (4 x 3 tags of 15 cm, gaps of 0.3 tags; its YAML as Kalibr reads it)
// filmed by a two-camera ring at 640 px: the tag corners are 48 of the 50 x 37 points of the
// grid spaced a tenth of a tag that holds them all, the others never seen, and the solve lands
// on the true lenses within its own uncertainty. Kalibr's numbering (tag 0 at the bottom left)
// is checked by the truth: a corner put on the wrong grid point ends far from it.
TEST(CalibrateCli, CalibratesAKalibrAprilgridTake) {
  TempDir dir("holocap-calib-kalibr");
  const std::filesystem::path layout = dir / "kalibr.yaml";
  std::ofstream(layout) << "target_type: 'aprilgrid'\ntagCols: 4\ntagRows: 3\ntagSize: 0.15\n"
                           "tagSpacing: 0.3\n";
  nlohmann::json report;
  ASSERT_NO_FATAL_FAILURE(CalibrateRingTake(dir.path(), layout, &report));
  const auto& m = report["metrics"];
  EXPECT_EQ(report["summary"]["termination"], "CONVERGENCE") << report["summary"].dump();
  EXPECT_EQ(report["options"]["board"]["width_n"], 50);
  EXPECT_EQ(report["options"]["board"]["height_n"], 37);

  const CornerTruth corners = CornersAgainstTruth(dir / "take", dir / "corners.vnl", 50, 0.015);
  std::printf("Kalibr aprilgrid take: %d corners in %zu views: mean %.4f px, max %.4f px\n",
              corners.count, corners.seen_in_view.size(), corners.mean_px, corners.max_px);
  for (const auto& [name, seen] : corners.seen_in_view) EXPECT_LE(seen, 48) << name;
  EXPECT_GE(corners.count, 20 * 24);
  // Measured 0.017 px on average, 0.215 px at most (a tag seen at a slant near the image's edge).
  EXPECT_LT(corners.mean_px, 0.05);
  EXPECT_LT(corners.max_px, 0.3);
  ExpectIntrinsicsWithinTheirSigma(m, corners, 10);
  EXPECT_LT(m["rms_reprojection_px"].get<double>(), 0.3);
  EXPECT_LT(m["gt"]["projection_diff_rms_observed_px"].get<double>(), 0.3);

  // A Kalibr field holocap does not read, or another target type: one error naming it.
  std::ofstream(dir / "offset.yaml") << "target_type: 'aprilgrid'\ntagCols: 4\ntagRows: 3\n"
                                        "tagSize: 0.15\ntagSpacing: 0.3\ncodeOffset: 12\n";
  ExpectOneLineError(RunCli("calibrate " + (dir / "take").string() + " --no-pictures --board " +
                            (dir / "offset.yaml").string()),
                     "field 'codeOffset' of a Kalibr aprilgrid is not supported");
  std::ofstream(dir / "circles.yaml") << "target_type: 'circlegrid'\ntargetCols: 6\n";
  ExpectOneLineError(RunCli("sim --rig " + WriteRingRig(dir.path(), 2) + " --board --frames 1 " +
                            "--board-layout " + (dir / "circles.yaml").string() + " --out " +
                            (dir / "circles").string()),
                     "Kalibr's 'circlegrid' is not supported");
}

// The same aprilgrid as Kalibr's kalibr_create_target_pdf prints it (sim --board-print kalibr:
// tags with two-bit black borders, black squares at the gaps' crossings touching the tags'
// corners), calibrated with the same Kalibr YAML, which does not say how the board was printed:
// every view is found with the two-bit border, its corners lie on the true grid (Kalibr's
// numbering, checked by the truth as above), and the solve lands on the true lenses within its
// own uncertainty.
TEST(CalibrateCli, CalibratesAKalibrPrintedAprilgridTake) {
  TempDir dir("holocap-calib-kalibr-print");
  const std::filesystem::path layout = dir / "kalibr.yaml";
  std::ofstream(layout) << "target_type: 'aprilgrid'\ntagCols: 4\ntagRows: 3\ntagSize: 0.15\n"
                           "tagSpacing: 0.3\n";
  nlohmann::json report;
  ASSERT_NO_FATAL_FAILURE(
      CalibrateRingTake(dir.path(), layout, &report, "--frames 16 --board-print kalibr"));
  const auto& m = report["metrics"];
  EXPECT_EQ(report["summary"]["termination"], "CONVERGENCE") << report["summary"].dump();
  const auto& detection = m["detection"];
  EXPECT_EQ(detection["views_per_tag_border_bits"],
            nlohmann::json({{"2", detection["views"].get<int>()}}))
      << detection.dump();

  const CornerTruth corners = CornersAgainstTruth(dir / "take", dir / "corners.vnl", 50, 0.015);
  std::printf("Kalibr-printed aprilgrid take: %d corners in %zu views: mean %.4f px, max %.4f px\n",
              corners.count, corners.seen_in_view.size(), corners.mean_px, corners.max_px);
  // As many views as of holocap's print of the YAML (26), nearly every tag in each.
  EXPECT_GE(corners.count, 20 * 24);
  // Measured 0.016 px on average, 0.067 px at most.
  EXPECT_LT(corners.mean_px, 0.05);
  EXPECT_LT(corners.max_px, 0.3);
  ExpectIntrinsicsWithinTheirSigma(m, corners, 10);
  EXPECT_LT(m["rms_reprojection_px"].get<double>(), 0.3);
  EXPECT_LT(m["gt"]["projection_diff_rms_observed_px"].get<double>(), 0.3);

  // Kalibr's print is a tag36h11 AprilTag board's; another print is refused by name.
  const std::string sim = "sim --rig " + WriteRingRig(dir.path(), 2) + " --board --frames 1 ";
  std::ofstream(dir / "chessboard.yaml") << "type: chessboard\n";
  ExpectOneLineError(RunCli(sim + "--board-layout " + (dir / "chessboard.yaml").string() +
                            " --board-print kalibr --out " + (dir / "chess").string()),
                     "--board-print kalibr prints tag36h11 AprilTag boards, not a chessboard");
  ExpectOneLineError(RunCli(sim + "--board-print pdf --out " + (dir / "pdf").string()),
                     "--board-print must be holocap or kalibr, got 'pdf'");
}

// A take of a two-camera ring (studio8's cam0 and cam1) at 480 px: the board moving, or never
// moving.
std::string PairTake(const std::filesystem::path& dir, bool still) {
  std::string take = (dir / (still ? "still" : "moving")).string();
  const auto r =
      RunCli("sim --rig " + WriteRingRig(dir, 2) + " --board" +
             (still ? " --board-still --frames 10" : " --frames 16") + " --size 480 --out " + take);
  EXPECT_EQ(r.exit_code, 0) << r.output;
  return take;
}

// A board that never moves fixes no lens, whatever the model: DEGENERATE with the reason, and a
// report; the same two cameras calibrate from the board moving (16 frame sets).
TEST(CalibrateCli, ABoardThatNeverMovesIsDegenerateForEveryLensModel) {
  TempDir dir("holocap-calib-still");
  const std::string still = PairTake(dir.path(), true);
  const std::string calibrate_still = "calibrate " + still + " --no-pictures --lens-model ";
  for (const std::string model :
       {"LENSMODEL_STEREOGRAPHIC", "LENSMODEL_OPENCV4", "LENSMODEL_OPENCV8",
        "LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=16_Ny=12_fov_x_deg=120"}) {
    std::filesystem::remove_all(std::filesystem::path(still) / "calib");
    const auto r = RunCli(calibrate_still + model);
    EXPECT_NE(r.exit_code, 0) << model;
    EXPECT_NE(r.output.find("DEGENERATE"), std::string::npos) << model << r.output;
    EXPECT_NE(r.output.find("show the board in one pose"), std::string::npos) << model << r.output;
    const auto report = nlohmann::json::parse(
        ReadFileToString(std::filesystem::path(still) / "calib" / "report.json"));
    EXPECT_EQ(report["summary"]["termination"], "DEGENERATE") << model;
    for (const auto& [name, camera] : report["metrics"]["cameras"].items()) {
      EXPECT_EQ(camera["views"].get<int>(), 10) << model << name;  // enough views, one pose
      EXPECT_LT(camera["pose_spread"]["normal_spread_deg"].get<double>(), 1.0) << model << name;
    }
  }
  // Names mrcal parses but cannot optimise are bad input: one line, before any solve.
  for (const auto& [model, needle] : std::vector<std::pair<std::string, std::string>>{
           {"LENSMODEL_CAHVORE_linearity=0.00", "mrcal does not optimise CAHVORE"},
           {"LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=3_Ny=12_fov_x_deg=120",
            "a control grid of at least 4 x 4"}}) {
    testing::ExpectOneLineError(RunCli(calibrate_still + model), needle);
  }
  const std::string moving = PairTake(dir.path(), false);
  const auto r = RunCli("calibrate " + moving + " --no-pictures");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto report = nlohmann::json::parse(
      ReadFileToString(std::filesystem::path(moving) / "calib" / "report.json"));
  EXPECT_EQ(report["summary"]["termination"], "CONVERGENCE") << report["summary"].dump();
  // Measured: normals within ~48 and ~50 degrees, focal lengths 0.23 % from the truth.
  for (const auto& [name, camera] : report["metrics"]["cameras"].items())
    EXPECT_GT(camera["pose_spread"]["normal_spread_deg"].get<double>(), 20) << name;
  EXPECT_LT(report["metrics"]["gt"]["focal_rel_err_max"].get<double>(), 0.005);
}

// A camera left with too few views says why when its views show the board's tags small: studio8
// at 320 px sees the default board's 10 cm tags 13-16 px across where it finds them (measured from
// the detected corners), within 1.5 times the 12 px detection keeps a tag from, and finds cam0's
// board twice in 40 frame sets. At 640 px and 6 frame sets the cameras have as few views, of tags
// over 18 px (1.5 x 12): the cause is the frame count, and the message does not blame the tags.
TEST(CalibrateCli, TooFewViewsOfSmallTagsSaySo) {
  TempDir dir("holocap-calib-small-tags");
  // Simulates and calibrates a studio8 board take; returns the output (the calibration must end
  // DEGENERATE naming cam0's `views`) and cam0's measured tag sides.
  const auto degenerate = [&](const std::string& name, const std::string& flags,
                              const std::string& views) {
    const std::string take = (dir.path() / name).string();
    const auto sim = RunCli("sim --rig studio8 --board " + flags + " --out " + take);
    EXPECT_EQ(sim.exit_code, 0) << sim.output;
    const auto r = RunCli("calibrate " + take + " --no-pictures");
    EXPECT_NE(r.exit_code, 0) << r.output;
    EXPECT_NE(r.output.find("DEGENERATE: reference camera cam0: only " + views +
                            " usable board views (needs 8)"),
              std::string::npos)
        << r.output;
    const auto report = nlohmann::json::parse(
        ReadFileToString(std::filesystem::path(take) / "calib" / "report.json"));
    EXPECT_EQ(report["summary"]["termination"], "DEGENERATE");
    return std::make_pair(r.output, report["metrics"]["cameras"]["cam0"]["feature_side_px"]);
  };
  const auto [small, small_px] = degenerate("320", "--frames 40 --size 320", "2");
  EXPECT_NE(small.find("usable board views (needs 8); the board's tags were "), std::string::npos)
      << small;
  EXPECT_NE(small.find("and a tag is read from 12 px (min_tag_side_px): print larger tags, bring "
                       "the board closer, or capture the board at full resolution"),
            std::string::npos)
      << small;
  EXPECT_LT(small_px["median"].get<double>(), 18) << small_px.dump();
  EXPECT_LE(small_px["min"].get<double>(), small_px["median"].get<double>());

  const auto [few, few_px] = degenerate("640", "--frames 6 --size 640 --color-only", "1");
  EXPECT_EQ(few.find("is read from"), std::string::npos) << few;
  EXPECT_GE(few_px["median"].get<double>(), 18) << few_px.dump();
}

// A lens model that cannot describe the lens converges all the same; its residuals give it away:
// far above the corners' noise, which the same corners solved in a richer model show. The ring's
// lenses are OPENCV4 and OPENCV5 with real distortion (k1 -0.08 and -0.12): PINHOLE, LONLAT and
// LATLON end DEGENERATE naming the model, its RMS and the noise, and suggest a richer model;
// OPENCV5, which describes both, stays CONVERGENCE with its residuals at the noise.
TEST(CalibrateCli, ALensModelThatCannotDescribeTheLensIsDegenerate) {
  TempDir dir("holocap-calib-model-fit");
  const std::string take = PairTake(dir.path(), false);
  const auto calibrate = [&](const std::string& model) {
    std::filesystem::remove_all(std::filesystem::path(take) / "calib");
    const auto r =
        RunCli("calibrate " + take + " --no-pictures --no-uncertainty --lens-model " + model);
    const auto report = nlohmann::json::parse(
        ReadFileToString(std::filesystem::path(take) / "calib" / "report.json"));
    return std::make_pair(r, report);
  };
  for (const std::string model : {"LENSMODEL_PINHOLE", "LENSMODEL_LONLAT", "LENSMODEL_LATLON"}) {
    const auto [r, report] = calibrate(model);
    EXPECT_NE(r.exit_code, 0) << model << r.output;
    EXPECT_EQ(report["summary"]["termination"], "DEGENERATE") << model << report["summary"].dump();
    const std::string message = report["summary"]["message"].get<std::string>();
    EXPECT_NE(message.find(model + " cannot describe the lens of"), std::string::npos) << message;
    EXPECT_NE(message.find("against the expected corner noise"), std::string::npos) << message;
    EXPECT_NE(message.find("use a richer lens model"), std::string::npos) << message;
    const auto& fit = report["metrics"]["model_fit"];
    ASSERT_TRUE(fit["checked"].get<bool>()) << fit.dump();
    for (const auto& [name, camera] : fit["cameras"].items()) {
      EXPECT_GT(camera["ratio"].get<double>(), camera["limit"].get<double>()) << model << name;
    }
  }
  const auto [r, report] = calibrate("LENSMODEL_OPENCV5");
  EXPECT_EQ(r.exit_code, 0) << r.output;
  EXPECT_EQ(report["summary"]["termination"], "CONVERGENCE") << report["summary"].dump();
  const auto& fit = report["metrics"]["model_fit"];
  ASSERT_TRUE(fit["checked"].get<bool>()) << fit.dump();
  ASSERT_EQ(fit["cameras"].size(), 2u) << fit.dump();
  for (const auto& [name, camera] : fit["cameras"].items()) {
    EXPECT_LE(camera["ratio"].get<double>(), camera["limit"].get<double>()) << name;
  }
}

// Whatever throws inside the solve is its ending, not a crash: a board layout written in
// micrometres (spacing 100000) puts cam1 2.1e6 m from cam0, beyond what a camera model may be
// (1e6 m). FAILURE with the reason, the solve's figures in report.json, one error line, exit 1
// (docs/command-line.md), and no model written.
TEST(CalibrateCli, AnImpossibleModelFromTheSolveEndsFailureWithAReport) {
  TempDir dir("holocap-calib-throw");
  const std::string take = PairTake(dir.path(), false);
  {
    std::ofstream(dir / "micrometres.yaml")
        << "type: apriltag\nfamily: tag36h11\ntags_across: 5\ntags_down: 4\n"
           "spacing: 100000\nmargin: 100000\n";
  }
  const auto r =
      RunCli("calibrate " + take + " --no-pictures --board " + (dir / "micrometres.yaml").string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  size_t errors = 0;
  for (size_t at = r.output.find("holocap: error:"); at != std::string::npos;
       at = r.output.find("holocap: error:", at + 1))
    ++errors;
  EXPECT_EQ(errors, 1u) << r.output;
  EXPECT_NE(r.output.find("calibration ended FAILURE: the solve gave no usable model"),
            std::string::npos)
      << r.output;
  const std::filesystem::path calib = std::filesystem::path(take) / "calib";
  ASSERT_TRUE(std::filesystem::exists(calib / "report.json"));
  const auto report = nlohmann::json::parse(ReadFileToString(calib / "report.json"));
  EXPECT_EQ(report["summary"]["termination"], "FAILURE");
  const std::string message = report["summary"]["message"];
  EXPECT_NE(message.find("translation reaches"), std::string::npos) << message;
  // The solve ran: its figures are reported though no model is usable.
  for (const auto& [name, camera] : report["metrics"]["cameras"].items()) {
    EXPECT_GE(camera["views"].get<int>(), 8) << name;
    EXPECT_FALSE(camera.contains("intrinsics")) << name;
  }
  for (const auto& entry : std::filesystem::directory_iterator(calib))
    EXPECT_NE(entry.path().extension(), ".cameramodel") << entry.path();
}

TEST(CalibrateCli, BadInputGivesOneClearError) {
  TempDir dir;
  const std::string take = BoardTake().string();
  // A camera absent from the take.
  auto r = RunCli("calibrate " + take + " --sensors cam9 --no-pictures");
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("holocap: error: camera 'cam9' is not in the take"), std::string::npos)
      << r.output;
  // A board file that does not match the prints.
  {
    std::ofstream(dir / "other.yaml")
        << "type: apriltag\nfamily: tag36h11\ntags_across: 5\ntags_down: 4\n"
           "spacing: 0.08\nmargin: 0.08\nfirst_id: 200\n";
  }
  r = RunCli("calibrate " + take + " --board " + (dir / "other.yaml").string() +
             " --sensors cam0 --no-pictures");
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("does not match the prints"), std::string::npos) << r.output;
  // Missing frames: a copy of the take whose frame files are gone.
  std::filesystem::copy(BoardTake(), dir / "gutted", std::filesystem::copy_options::recursive);
  std::filesystem::remove_all(dir / "gutted" / "frames");
  r = RunCli("calibrate " + (dir / "gutted").string() + " --no-pictures");
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("holocap: error:"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("no complete frame sets"), std::string::npos) << r.output;
  // No board visible: a take of the static object.
  r = RunCli("sim --rig single-rgbd --scene object --frames 2 --size 160 --out " +
             (dir / "object").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  std::filesystem::copy_file(BoardTake() / "gt" / "board.json", dir / "board.json");
  r = RunCli("calibrate " + (dir / "object").string() + " --board " +
             (dir / "board.json").string());
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("no board visible"), std::string::npos) << r.output;
}

TEST(BoardCli, PrintsABoardToScale) {
  TempDir dir;
  std::ofstream(dir / "board.yaml")
      << "type: apriltag\nfamily: tagStandard41h12\ntags_across: 4\ntags_down: 3\n"
         "spacing: 0.05\nmargin: 0.05\n";
  auto r =
      RunCli("board " + (dir / "board.yaml").string() + " --out " + (dir / "board.pdf").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_GT(std::filesystem::file_size(dir / "board.pdf"), 500u);
  r = RunCli("board " + (dir / "board.yaml").string() + " --out " + (dir / "board.png").string() +
             " --dpi 150");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = RunCli("board " + (dir / "missing.yaml").string() + " --out " + (dir / "x.png").string());
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("holocap: error:"), std::string::npos);
}

// A four-camera ring at 480 px filming a square chessboard (7 x 7 inner corners): the board
// mrgingham finds. Shared by the detector tests below.
const std::filesystem::path& SquareChessboardTake() {
  static TempDir dir("holocap-calib-finders");
  static const bool made = [] {
    std::ofstream(dir / "square.yaml")
        << "type: chessboard\nchessboard_width_n: 7\nchessboard_height_n: 7\n"
           "spacing: 0.1\nmargin: 0.2\n";
    std::ofstream(dir / "wide.yaml")
        << "type: chessboard\nchessboard_width_n: 8\nchessboard_height_n: 7\n"
           "spacing: 0.1\nmargin: 0.2\n";
    const auto r = RunCli("sim --rig " + WriteRingRig(dir.path(), 4) + " --board --board-layout " +
                          (dir / "square.yaml").string() + " --frames 36 --size 480 --out " +
                          (dir / "take").string());
    EXPECT_EQ(r.exit_code, 0) << r.output;
    return true;
  }();
  (void)made;
  static const std::filesystem::path take = dir / "take";
  return take;
}

nlohmann::json CalibrateSquareTake(const std::string& flags) {
  const auto r = RunCli("calibrate " + SquareChessboardTake().string() + " --no-pictures " + flags);
  EXPECT_EQ(r.exit_code, 0) << r.output;
  return nlohmann::json::parse(ReadFileToString(SquareChessboardTake() / "calib" / "report.json"));
}

// The take calibrated with the default detector, once.
const nlohmann::json& DefaultSquareReport() {
  static const nlohmann::json report = CalibrateSquareTake("");
  return report;
}

double TruthMean(const nlohmann::json& agreement, const std::string& detector) {
  for (const auto& t : agreement["truth"]) {
    if (t["detector"] == detector) return t["mean_px"].get<double>();
  }
  ADD_FAILURE() << "no truth row for " << detector << ": " << agreement.dump();
  return NAN;
}

// Every pair of finders and each finder against the truth, over corners each found; the solve
// is the one without the comparison. On these rendered images (antialiased edges, no blur)
// every finder lies within half a pixel of the truth on average and holocap's within a tenth
// (measured 0.01, OpenCV's recipe 0.05, mrgingham 0.13 px at 640 px).
TEST(CalibrateCli, CompareDetectorsReportsEveryPairAndTheTruth) {
  const nlohmann::json& plain = DefaultSquareReport();
  const auto r =
      RunCli("calibrate " + SquareChessboardTake().string() + " --no-pictures --compare-detectors");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("holocap - mrgingham"), std::string::npos) << r.output;
  const auto report =
      nlohmann::json::parse(ReadFileToString(SquareChessboardTake() / "calib" / "report.json"));
  EXPECT_EQ(report["summary"]["termination"], "CONVERGENCE");
  EXPECT_EQ(report["metrics"]["gt"]["focal_rel_err_max"],
            plain["metrics"]["gt"]["focal_rel_err_max"]);
  EXPECT_EQ(report["metrics"]["rms_reprojection_px"], plain["metrics"]["rms_reprojection_px"]);
  const auto& a = report["metrics"]["detector_agreement"];
  ASSERT_EQ(a["pairs"].size(), 3u) << a.dump();
  ASSERT_EQ(a["truth"].size(), 3u) << a.dump();
  std::vector<std::string> pairs;
  for (const auto& p : a["pairs"]) {
    pairs.push_back(p["a"].get<std::string>() + "-" + p["b"].get<std::string>());
    EXPECT_GT(p["corners"].get<int>(), 49 * 20) << p.dump();
    EXPECT_TRUE(std::isfinite(p["mean_px"].get<double>())) << p.dump();
    EXPECT_LT(p["mean_px"].get<double>(), 0.5) << p.dump();
  }
  EXPECT_EQ(pairs,
            (std::vector<std::string>{"holocap-opencv", "holocap-mrgingham", "opencv-mrgingham"}));
  for (const auto& t : a["truth"]) {
    EXPECT_GT(t["corners"].get<int>(), 49 * 20) << t.dump();
    EXPECT_LT(t["mean_px"].get<double>(), 0.5) << t.dump();
    EXPECT_LT(t["p95_px"].get<double>(), 1.0) << t.dump();
  }
  EXPECT_LT(TruthMean(a, "holocap"), 0.1) << a.dump();
}

// --compare-detectors on a ChArUco board compares the detectors that read one: holocap's and
// OpenCV's own (detectMarkers, interpolateCornersCharuco), corners matched by their ids, and
// names mrgingham as left out (chessboards only); the solve is the one without it. On an
// AprilTag board there is nothing to compare: one error line before any detection.
TEST(CalibrateCli, CompareDetectorsOnAChArUcoBoardComparesItsDetectors) {
  TempDir dir("holocap-calib-charuco-compare");
  const std::filesystem::path layout = dir / "charuco.yaml";
  std::ofstream(layout) << "type: charuco\nsquares_across: 6\nsquares_down: 5\nspacing: 0.16\n"
                           "marker_side: 0.12\ndictionary: DICT_4X4_50\nmargin: 0.16\n";
  const std::string rig = WriteRingRig(dir.path(), 2);
  const std::string take = (dir / "take").string();
  auto r = RunCli("sim --rig " + rig + " --board --board-layout " + layout.string() +
                  " --frames 16 --size 640 --out " + take);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = RunCli("calibrate " + take + " --no-pictures --board " + layout.string() +
             " --compare-detectors");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("charuco corners, detector against detector"), std::string::npos)
      << r.output;
  EXPECT_NE(r.output.find("holocap - opencv"), std::string::npos) << r.output;
  EXPECT_EQ(r.output.find("holocap - mrgingham"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("mrgingham left out: mrgingham finds chessboards only"),
            std::string::npos)
      << r.output;
  const auto report = nlohmann::json::parse(ReadFileToString(dir / "take/calib/report.json"));
  EXPECT_EQ(report["summary"]["termination"], "CONVERGENCE") << report["summary"].dump();
  const auto& a = report["metrics"]["detector_agreement"];
  EXPECT_EQ(a["board"], "charuco");
  ASSERT_EQ(a["pairs"].size(), 1u) << a.dump();
  const auto& pair = a["pairs"][0];
  EXPECT_EQ(pair["a"], "holocap");
  EXPECT_EQ(pair["b"], "opencv");
  // Both detectors read most views (27 of 32 here), and their shared corners, matched by id,
  // lie within 2 px of each other (measured 0.82 at most: OpenCV's own are left ~0.7 px off):
  // corners of different grid points would lie a square (over 20 px) apart.
  EXPECT_GE(pair["views"].get<int>(), 20) << pair.dump();
  EXPECT_GE(pair["corners"].get<int>(), 20 * 12) << pair.dump();
  EXPECT_LT(pair["max_px"].get<double>(), 2.0) << pair.dump();
  ASSERT_EQ(a["truth"].size(), 2u) << a.dump();
  // holocap's corners are refined past OpenCV's (measured 0.013 px from the truth on average,
  // OpenCV's own 0.69 px).
  EXPECT_LT(TruthMean(a, "holocap"), 0.05) << a.dump();
  EXPECT_LT(TruthMean(a, "holocap"), TruthMean(a, "opencv")) << a.dump();

  const std::string apriltag = (dir / "apriltag").string();
  r = RunCli("sim --rig " + rig + " --board --frames 2 --size 640 --out " + apriltag);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  ExpectOneLineError(RunCli("calibrate " + apriltag + " --no-pictures --compare-detectors"),
                     "compares chessboard and ChArUco detectors; this board is apriltag");
  EXPECT_FALSE(std::filesystem::exists(dir / "apriltag" / "calib" / "cam0.cameramodel"));
}

// mrgingham's corners calibrate the take. They lie ~15 times farther from the truth than
// holocap's (0.13 px against 0.01 px), and a focal length's error from corner noise grows in
// proportion to it: held to three times the default's focal error scaled by that ratio, as
// measured on this take, and to 1 % (measured 0.36 %, the default 0.011 %). A numbering that
// is not a turn of the board (rows mirrored) gives no convergent solve.
TEST(CalibrateCli, TheMrginghamDetectorCalibratesASquareChessboard) {
  const double default_focal =
      DefaultSquareReport()["metrics"]["gt"]["focal_rel_err_max"].get<double>();
  const auto report = CalibrateSquareTake("--detector mrgingham --compare-detectors");
  EXPECT_EQ(report["options"]["detector"], "mrgingham");
  EXPECT_EQ(report["summary"]["termination"], "CONVERGENCE") << report["summary"].dump();
  const auto& m = report["metrics"];
  const double ratio = TruthMean(m["detector_agreement"], "mrgingham") /
                       TruthMean(m["detector_agreement"], "holocap");
  const double focal = m["gt"]["focal_rel_err_max"].get<double>();
  EXPECT_LT(focal, 3 * ratio * default_focal) << "default " << default_focal << ", ratio " << ratio;
  EXPECT_LT(focal, 0.01);
  EXPECT_LT(m["gt"]["projection_diff_rms_observed_px"].get<double>(), 0.5);
}

// mrgingham finds square chessboards only, and needs its program.
TEST(CalibrateCli, TheMrginghamDetectorRefusesWhatItCannotFind) {
  const std::string take = SquareChessboardTake().string();
  const auto wide = SquareChessboardTake().parent_path() / "wide.yaml";
  ExpectOneLineError(
      RunCli("calibrate " + take + " --no-pictures --detector mrgingham --board " + wide.string()),
      "square grids only (N x N inner corners); this chessboard has 8 x 7");
  ExpectOneLineError(RunShell("PATH=/nonexistent HOLOCAP_NO_PROGRESS=1 '" + testing::CliPath() +
                              "' calibrate " + take + " --no-pictures --detector mrgingham"),
                     "the mrgingham program is not on PATH");
  ExpectOneLineError(RunCli("calibrate " + take + " --detector opencv"),
                     "unknown chessboard detector 'opencv'");
}

// The detector is part of the calibration request: the board take's report names it, a take
// given that calibration through --from names it too, and --from with --detector is refused
// unless the board take's corners came from that finder (it was once ignored there).
TEST(CalibrateCli, TheDetectorTravelsWithTheCalibrationThroughFrom) {
  TempDir dir("holocap-calib-from-detector");
  std::ofstream(dir / "chessboard.yaml")
      << "type: chessboard\nchessboard_width_n: 9\nchessboard_height_n: 6\nspacing: 0.1\n"
         "margin: 0.2\n";
  const std::string rig = WriteRingRig(dir.path(), 2);
  const std::string board = (dir / "board").string();
  const std::string other = (dir / "other").string();
  auto r = RunCli("sim --rig " + rig + " --board --board-layout " +
                  (dir / "chessboard.yaml").string() + " --frames 16 --size 480 --out " + board);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = RunCli("sim --rig " + rig + " --board --frames 1 --size 480 --out " + other);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = RunCli("calibrate " + board + " --no-pictures --no-uncertainty");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto board_report =
      nlohmann::json::parse(ReadFileToString(dir / "board" / "calib" / "report.json"));
  EXPECT_EQ(board_report["options"]["detector"], "holocap");
  EXPECT_EQ(board_report["options"]["detection"]["detector"], "holocap");

  ExpectOneLineError(RunCli("calibrate " + other + " --from " + board + " --detector mrgingham"),
                     "was solved on the holocap finder's corners");
  EXPECT_FALSE(std::filesystem::exists(dir / "other" / "calib" / "cam0.cameramodel"));
  const std::string adopt = "calibrate " + other + " --from " + board;
  for (const std::string flags : {"", " --detector holocap"}) {
    r = RunCli(adopt + flags);
    ASSERT_EQ(r.exit_code, 0) << flags << r.output;
    const auto report =
        nlohmann::json::parse(ReadFileToString(dir / "other" / "calib" / "report.json"));
    EXPECT_EQ(report["options"]["detector"], "holocap") << flags;
    EXPECT_EQ(report["plan"]["adopted"]["detector"], "holocap") << flags;
  }
  // A folder of models has no report to say which finder found its corners.
  std::filesystem::create_directories(dir / "models");
  for (const std::string camera : {"cam0", "cam1"}) {
    std::filesystem::copy_file(dir / "board" / "calib" / (camera + ".cameramodel"),
                               dir / "models" / (camera + ".cameramodel"));
  }
  ExpectOneLineError(
      RunCli("calibrate " + other + " --from " + (dir / "models").string() + " --detector holocap"),
      "does not say which detector found its corners");
  r = RunCli("calibrate " + other + " --from " + (dir / "models").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(nlohmann::json::parse(
                  ReadFileToString(dir / "other" / "calib" / "report.json"))["options"]["detector"]
                  .is_null());
}

}  // namespace
}  // namespace holocap
