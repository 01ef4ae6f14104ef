#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <vector>

#include "calibration/calibration.h"
#include "calibration/internal/common.h"
#include "core/error.h"
#include "tests/calibration/synthetic_rig.h"

namespace holocap {
namespace {

using testing::MakeSyntheticRig;
using testing::SyntheticOptions;
using testing::SyntheticRig;

std::vector<CameraModel> StudioLenses(int count) {
  const std::vector<CameraModel> lenses = {
      CameraModel(
          "LENSMODEL_OPENCV8",
          {498.6, 499.4, 321.0, 238.2, 0.35, -0.05, 0.0004, 0.0002, 0.01, 0.42, -0.02, 0.015}, 640,
          480),
      CameraModel("LENSMODEL_OPENCV4", {520.3, 519.1, 322.4, 236.9, -0.082, 0.031, 0.0006, -0.0004},
                  640, 480),
      CameraModel("LENSMODEL_OPENCV5",
                  {561.7, 560.2, 316.8, 243.5, -0.121, 0.094, -0.0003, 0.0007, -0.021}, 640, 480),
      CameraModel("LENSMODEL_OPENCV8",
                  {541.2, 540.5, 317.5, 242.8, -0.2, 0.05, -0.0003, 0.0004, 0.0, 0.1, 0.02, 0.0},
                  640, 480),
  };
  std::vector<CameraModel> out;
  out.reserve(static_cast<size_t>(count));
  for (int i = 0; i < count; ++i) out.push_back(lenses[i % lenses.size()]);
  return out;
}

// Three studio lenses on a 60-degree arc, the board 0.6..1.2 m from the camera it faces.
SyntheticOptions ReducedRig() {
  SyntheticOptions options;
  options.lenses = StudioLenses(3);
  options.arc_deg = 60;
  options.frames = 150;
  options.min_distance = 0.6;
  options.max_distance = 1.2;
  options.max_tilt_deg = 45;
  return options;
}

GroundTruthComparison Compare(const SyntheticRig& rig, const CalibrationSummary& summary) {
  return CompareWithTruth(summary, rig.truth, rig.world_from_board, rig.layout);
}

void Print(const char* name, const CalibrationSummary& s, const GroundTruthComparison& g) {
  std::printf(
      "[%s] %s: %s\n  rms %.4f px, focal %.5f%%, pp %.3f px, rot %.5f deg, trans %.3f mm, "
      "proj %.4f px rms (max %.4f, where seen %.4f), within 3 sigma %.3f, solve %.2f s, "
      "uncertainty %.2f s\n",
      name, ToString(s.termination), s.message.c_str(), s.rms_reprojection_px,
      100 * g.focal_rel_err_max, g.principal_point_err_px_max, g.rotation_err_deg_max,
      g.translation_err_mm_max, g.projection_diff_rms_px, g.projection_diff_max_px,
      g.projection_diff_rms_observed_px, g.within_3sigma_fraction, s.solve_seconds,
      s.uncertainty_seconds);
}

// The calibration targets on a reduced problem (3 cameras, ~75 views each, 0.3 px noise). The
// principal point and the rotation are entangled (0.5 px at f = 500 is 0.057 degrees), and
// at this noise and view count their error is ~0.3-0.6 px and ~0.03 degrees: the bounds below
// are what this data supports, and the report in the closing note says so.
TEST(Calibrate, RecoversTheTruthOnAReducedRig) {
  const SyntheticOptions options = ReducedRig();
  const SyntheticRig rig = MakeSyntheticRig(options);
  const CalibrationSummary s = Calibrate(rig.layout, rig.cameras, rig.observations, {});
  const GroundTruthComparison g = Compare(rig, s);
  Print("reduced", s, g);
  ASSERT_TRUE(IsUsable(s.termination)) << s.message;
  EXPECT_EQ(s.lensmodel, "LENSMODEL_OPENCV8");
  EXPECT_NEAR(s.rms_reprojection_px, options.noise_px, 0.2 * options.noise_px);
  EXPECT_LE(g.focal_rel_err_max, 0.0005);
  EXPECT_LE(g.principal_point_err_px_max, 1.0);
  EXPECT_LE(g.rotation_err_deg_max, 0.06);
  EXPECT_LE(g.translation_err_mm_max, 3.0);
  EXPECT_LE(g.projection_diff_rms_px, 0.2);
  EXPECT_GE(g.within_3sigma_fraction, 0.9);
  ASSERT_EQ(s.stages.size(), 4u);
  EXPECT_GT(s.stages[0].rms_px, s.stages[3].rms_px);  // the cost falls stage by stage
}

// The predicted 1-sigma against the spread of repeated solves with fresh noise.
TEST(Calibrate, UncertaintyMatchesTheSpreadOfRepeatedSolves) {
  SyntheticOptions options;
  options.lenses = StudioLenses(2);
  options.arc_deg = 40;
  options.frames = 30;
  options.min_distance = 0.6;
  options.max_distance = 1.2;
  CalibrationOptions solve;
  solve.uncertainty_grid_x = 8;
  solve.uncertainty_grid_y = 6;
  double diff2 = 0, predicted2 = 0;
  int n = 0;
  double core_error2 = 0, core_sigma2 = 0;  // fx, fy, cx, cy against their own 1-sigma
  for (uint64_t trial = 0; trial < 6; ++trial) {
    options.seed = 100 + trial;  // fresh noise and fresh board poses, as a new calibration
    const SyntheticRig rig = MakeSyntheticRig(options);
    const CalibrationSummary s = Calibrate(rig.layout, rig.cameras, rig.observations, solve);
    ASSERT_TRUE(IsUsable(s.termination)) << s.message;
    const GroundTruthComparison g = Compare(rig, s);
    for (const auto& cam : s.cameras) {
      const double rms = g.per_camera.at(cam.name).at("projection_diff_rms_px").get<double>();
      diff2 += rms * rms;
      double trace = 0;
      for (const auto& cov : cam.uncertainty.covariance)
        trace += cov.trace() / cam.uncertainty.covariance.size();
      predicted2 += trace;
      ++n;
      ASSERT_EQ(cam.intrinsics_sigma.size(), cam.model.intrinsics().size());
      for (int k = 0; k < 4; ++k) {
        ASSERT_GT(cam.intrinsics_sigma[k], 0) << cam.name << " intrinsic " << k;
        const double error = cam.model.intrinsics()[k] - rig.truth.at(cam.name).intrinsics()[k];
        core_error2 += error * error;
        core_sigma2 += cam.intrinsics_sigma[k] * cam.intrinsics_sigma[k];
      }
      if (cam.name == s.reference_camera) {
        EXPECT_TRUE(std::isnan(cam.rotation_sigma_deg));  // the reference's pose is not solved for
      } else {
        EXPECT_GT(cam.rotation_sigma_deg, 0);
        EXPECT_GT(cam.center_sigma_mm, 0);
        // Within 5 sigma: a wrong propagation is off by far more.
        EXPECT_LE(g.per_camera.at(cam.name).at("rotation_err_deg_from_reference").get<double>(),
                  5 * cam.rotation_sigma_deg);
        EXPECT_LE(g.per_camera.at(cam.name).at("translation_err_mm_from_reference").get<double>(),
                  5 * cam.center_sigma_mm);
      }
    }
  }
  const double ratio = std::sqrt(diff2 / predicted2);
  const double core_ratio = std::sqrt(core_error2 / core_sigma2);
  std::printf(
      "[monte carlo] observed / predicted projection error: %.3f over %d solves; "
      "focal and principal point errors / their 1-sigma: %.3f\n",
      ratio, n, core_ratio);
  EXPECT_GT(ratio, 0.5);
  EXPECT_LT(ratio, 1.8);
  EXPECT_GT(core_ratio, 0.5);
  EXPECT_LT(core_ratio, 1.8);
}

TEST(Calibrate, FrontoParallelViewsAreIllConditionedNotSuccess) {
  SyntheticOptions options;
  options.lenses = {StudioLenses(2)[1]};
  options.frames = 30;
  options.fronto_parallel = true;
  const SyntheticRig rig = MakeSyntheticRig(options);
  const CalibrationSummary s = Calibrate(rig.layout, rig.cameras, rig.observations, {});
  std::printf("[fronto-parallel] %s: %s\n", ToString(s.termination), s.message.c_str());
  EXPECT_EQ(s.termination, Termination::kDegenerate);
  EXPECT_NE(s.message.find("ill-conditioned"), std::string::npos) << s.message;
  EXPECT_GT(s.cameras[0].uncertainty.worst_px, 1.0);
}

// Wrong ids (two tags' corners swapped) and shifted corners in 5% of the views.
TEST(Calibrate, RejectsCorruptedDetections) {
  SyntheticOptions options = ReducedRig();
  options.frames = 60;
  SyntheticRig rig = MakeSyntheticRig(options);
  const CalibrationSummary clean = Calibrate(rig.layout, rig.cameras, rig.observations, {});
  std::mt19937_64 random(5);
  int corrupted_points = 0;
  const int width_n = Board(rig.layout).width_n();
  for (size_t k = 0; k < rig.observations.size(); k += 20) {
    auto& points = rig.observations[k].points;
    if (k % 40 == 0) {
      // Tag (0,0) and tag (2,1) swap ids: their corners land on each other's grid points.
      for (int c = 0; c < 4; ++c) {
        const int a = (c / 2) * width_n + c % 2;
        const int b = (2 + c / 2) * width_n + 4 + c % 2;
        if (points(a, 2) > 0 && points(b, 2) > 0) {
          points.row(a).swap(points.row(b));
          corrupted_points += 2;
        }
      }
    } else {
      for (int r = 0; r < points.rows(); r += 7) {
        if (points(r, 2) <= 0) continue;
        points(r, 0) += 4 + 4 * std::uniform_real_distribution<double>(0, 1)(random);
        ++corrupted_points;
      }
    }
  }
  const CalibrationSummary s = Calibrate(rig.layout, rig.cameras, rig.observations, {});
  const GroundTruthComparison g = Compare(rig, s);
  const GroundTruthComparison g_clean = Compare(rig, clean);
  Print("corrupted", s, g);
  std::printf("  %d corrupted points, %d outliers (clean solve: %d)\n", corrupted_points,
              s.outliers, clean.outliers);
  ASSERT_TRUE(IsUsable(s.termination)) << s.message;
  EXPECT_GE(s.outliers, corrupted_points * 8 / 10);
  EXPECT_NEAR(s.rms_reprojection_px, options.noise_px, 0.2 * options.noise_px);
  EXPECT_LE(g.projection_diff_rms_px, g_clean.projection_diff_rms_px + 0.05);
  EXPECT_LE(g.focal_rel_err_max, 0.001);
}

TEST(Calibrate, FlagsACameraWithOnlyThreeViews) {
  SyntheticOptions options = ReducedRig();
  options.frames = 60;
  SyntheticRig rig = MakeSyntheticRig(options);
  std::vector<BoardObservation> kept;
  int cam2 = 0;
  for (const auto& obs : rig.observations) {
    if (obs.sensor == "cam2" && ++cam2 > 3) continue;
    kept.push_back(obs);
  }
  CalibrationOptions solve;
  solve.uncertainty = false;
  const CalibrationSummary s = Calibrate(rig.layout, rig.cameras, kept, solve);
  EXPECT_EQ(s.termination, Termination::kDegenerate);
  EXPECT_NE(s.message.find("cam2 (only 3 usable board views"), std::string::npos) << s.message;
  EXPECT_FALSE(s.Find("cam2")->solved);
  EXPECT_TRUE(s.Find("cam0")->solved);
  EXPECT_TRUE(s.Find("cam1")->solved);
  // Its tags were large where found (6 cm at 0.6-1.2 m at f ~ 500 px): too few views is then
  // not the board's size, and the flag does not blame it.
  EXPECT_GT(s.Find("cam2")->feature_side_px_min, 20);
  EXPECT_EQ(s.message.find("is read from"), std::string::npos) << s.message;
}

// The same camera with its three views' corners drawn in to a quarter about each view's centre
// (as a board four times as far would show its tags, ~6-12 px): the flag says the tags were small
// where found, measured from the views' own pixels (a quarter of the same views' sizes unshrunk).
TEST(Calibrate, ACameraWithFewViewsOfSmallTagsIsToldSo) {
  SyntheticOptions options = ReducedRig();
  options.frames = 60;
  SyntheticRig rig = MakeSyntheticRig(options);
  std::vector<BoardObservation> kept;
  std::vector<BoardObservation> shrunk;
  int cam2 = 0;
  for (auto obs : rig.observations) {
    if (obs.sensor == "cam2" && ++cam2 > 3) continue;
    kept.push_back(obs);
    if (obs.sensor == "cam2") {
      Eigen::Vector2d centre = Eigen::Vector2d::Zero();
      int seen = 0;
      for (int r = 0; r < obs.points.rows(); ++r) {
        if (obs.points(r, 2) <= 0) continue;
        centre += obs.points.row(r).head<2>().transpose();
        ++seen;
      }
      centre /= seen;
      for (int r = 0; r < obs.points.rows(); ++r) {
        obs.points.row(r).head<2>() =
            (centre + 0.25 * (obs.points.row(r).head<2>().transpose() - centre)).transpose();
      }
    }
    shrunk.push_back(obs);
  }
  CalibrationOptions solve;
  solve.uncertainty = false;
  const CalibrationSummary large = Calibrate(rig.layout, rig.cameras, kept, solve);
  const CalibrationSummary s = Calibrate(rig.layout, rig.cameras, shrunk, solve);
  EXPECT_EQ(s.termination, Termination::kDegenerate);
  const CalibratedCamera& flagged = *s.Find("cam2");
  EXPECT_FALSE(flagged.solved);
  // 6 cm tags 0.6-1.2 m away at f ~ 500 px are 25-50 px; a quarter of that here.
  const CalibratedCamera& unshrunk = *large.Find("cam2");
  EXPECT_GT(unshrunk.feature_side_px_min, 20);
  EXPECT_LT(unshrunk.feature_side_px_median, 60);
  EXPECT_NEAR(flagged.feature_side_px_min, 0.25 * unshrunk.feature_side_px_min, 1e-9);
  EXPECT_NEAR(flagged.feature_side_px_median, 0.25 * unshrunk.feature_side_px_median, 1e-9);
  EXPECT_LT(flagged.feature_side_px_median, 18);  // 1.5 times the 12 px a tag is kept from
  EXPECT_NE(s.message.find("cam2 (only 3 usable board views (needs 8); the board's tags were "),
            std::string::npos)
      << s.message;
  EXPECT_NE(
      s.message.find("px across where found (the smallest and the median view), and a tag "
                     "is read from 12 px (min_tag_side_px): print larger tags, bring the board "
                     "closer, "
                     "or capture the board at full resolution"),
      std::string::npos)
      << s.message;
  EXPECT_EQ(large.message.find("is read from"), std::string::npos) << large.message;
}

TEST(Calibrate, ReportsACameraThatNeverSharesAView) {
  SyntheticOptions options = ReducedRig();
  options.frames = 60;
  SyntheticRig rig = MakeSyntheticRig(options);
  // cam1 keeps only the frames no other camera saw, renamed so nothing is shared.
  std::map<int64_t, int> seen_by;
  for (const auto& obs : rig.observations) ++seen_by[obs.frame_set];
  std::vector<BoardObservation> kept;
  for (auto obs : rig.observations) {
    if (obs.sensor == "cam1") {
      if (seen_by[obs.frame_set] > 1) continue;
      obs.frame_set += 100000;
    }
    kept.push_back(obs);
  }
  CalibrationOptions solve;
  solve.uncertainty = false;
  solve.min_views_per_camera = 5;
  const CalibrationSummary s = Calibrate(rig.layout, rig.cameras, kept, solve);
  EXPECT_EQ(s.termination, Termination::kDegenerate);
  EXPECT_NE(s.message.find("cam1 (never shares a board view"), std::string::npos) << s.message;
  EXPECT_FALSE(s.Find("cam1")->solved);
}

// Mrcal works in double precision around the reference camera, so moving the whole scene a
// kilometre away changes nothing but rounding.
TEST(Calibrate, ARigOneKilometreFromTheOriginKeepsItsAccuracy) {
  SyntheticOptions options = ReducedRig();
  options.frames = 60;
  const SyntheticRig near = MakeSyntheticRig(options);
  options.origin = Eigen::Vector3d(1000, -600, 30);
  const SyntheticRig far = MakeSyntheticRig(options);
  const CalibrationSummary a = Calibrate(near.layout, near.cameras, near.observations, {});
  const CalibrationSummary b = Calibrate(far.layout, far.cameras, far.observations, {});
  const GroundTruthComparison ga = Compare(near, a);
  const GroundTruthComparison gb = Compare(far, b);
  Print("1 km", b, gb);
  ASSERT_TRUE(IsUsable(b.termination)) << b.message;
  EXPECT_NEAR(gb.projection_diff_rms_px, ga.projection_diff_rms_px, 0.01);
  EXPECT_NEAR(gb.focal_rel_err_max, ga.focal_rel_err_max, 1e-5);
  EXPECT_NEAR(gb.translation_err_mm_max, ga.translation_err_mm_max, 0.05);
  EXPECT_LE(gb.projection_diff_rms_px, 0.2);
}

// A 170-degree stereographic fisheye (r = 2 f tan(theta / 2)) solved with the splined model.
// A spline has a few hundred parameters: ~100 views (150 poses, those that show at least half
// the board) and knots every ~17 degrees pin it down where the board was seen; 35 views and
// 12x9 knots left the edge cells of the seen region at ~0.3 px.
TEST(Calibrate, SolvesA170DegreeFisheyeWithTheSplinedModel) {
  SyntheticOptions options;
  const double f = 320.0 / (2 * std::tan(85.0 * M_PI / 180 / 2));  // 170 degrees across 640 px
  options.lenses = {CameraModel("LENSMODEL_STEREOGRAPHIC", {f, f, 321.3, 238.6}, 640, 480)};
  options.frames = 150;
  options.min_distance = 0.5;
  options.max_distance = 0.9;
  options.pixel_margin = 0.1;
  options.max_tilt_deg = 50;
  const SyntheticRig rig = MakeSyntheticRig(options);
  std::vector<CalibrationCamera> cameras = rig.cameras;
  cameras[0].lensmodel = "LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=10_Ny=7_fov_x_deg=175";
  CalibrationOptions solve;
  solve.uncertainty_grid_x = 12;
  solve.uncertainty_grid_y = 9;
  const CalibrationSummary s = Calibrate(rig.layout, cameras, rig.observations, solve);
  const GroundTruthComparison g = Compare(rig, s);
  Print("fisheye", s, g);
  ASSERT_TRUE(IsUsable(s.termination)) << s.message;
  EXPECT_EQ(s.lensmodel, cameras[0].lensmodel);
  EXPECT_NEAR(s.rms_reprojection_px, options.noise_px, 0.2 * options.noise_px);
  // The imager's corners lie beyond 90 degrees, where no board can be: judged where it was seen.
  EXPECT_LE(g.projection_diff_rms_observed_px, 0.2);
  EXPECT_GE(g.within_3sigma_fraction, 0.9);
}

// mrcal 2.2 solves one lens model per problem: the rig is solved in OPENCV8, then the camera
// that asks for a splined model is re-solved alone in it against the rig's board poses.
TEST(Calibrate, ReSolvesACameraThatAsksForAnotherModelAlone) {
  SyntheticOptions options = ReducedRig();
  const double f = 320.0 / (2 * std::tan(56.0 * M_PI / 180 / 2));  // 112 degrees across 640 px
  options.lenses[1] = CameraModel("LENSMODEL_STEREOGRAPHIC", {f, f, 318.2, 241.1}, 640, 480);
  options.frames = 100;
  const SyntheticRig rig = MakeSyntheticRig(options);
  std::vector<CalibrationCamera> cameras = rig.cameras;
  cameras[1].lensmodel = "LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=8_Ny=6_fov_x_deg=120";
  const CalibrationSummary s = Calibrate(rig.layout, cameras, rig.observations, {});
  const GroundTruthComparison g = Compare(rig, s);
  Print("re-solved alone", s, g);
  ASSERT_TRUE(IsUsable(s.termination)) << s.message;
  EXPECT_EQ(s.lensmodel, "LENSMODEL_OPENCV8");
  EXPECT_EQ(s.Find("cam1")->model.lensmodel(), cameras[1].lensmodel);
  EXPECT_EQ(s.Find("cam0")->model.lensmodel(), "LENSMODEL_OPENCV8");
  ASSERT_EQ(s.notes.size(), 1u);
  EXPECT_NE(s.notes[0].find("cam1 (LENSMODEL_SPLINED"), std::string::npos) << s.notes[0];
  EXPECT_EQ(s.stages.size(), 7u);  // the rig's four, then cam1's core, intrinsics, everything
  EXPECT_NEAR(s.Find("cam1")->rms_px, options.noise_px, 0.2 * options.noise_px);
  EXPECT_LE(g.per_camera.at("cam1")["projection_diff_rms_observed_px"].get<double>(), 0.2);
  EXPECT_LE(g.per_camera.at("cam1")["rotation_err_deg"].get<double>(), 0.1);
  EXPECT_GE(g.within_3sigma_fraction, 0.9);
}

TEST(Calibrate, SolvesAnEightKImager) {
  SyntheticOptions options;
  options.lenses = {
      CameraModel("LENSMODEL_OPENCV4", {5600, 5605, 3841.2, 2158.7, -0.06, 0.02, 0.0003, -0.0002},
                  7680, 4320),
      CameraModel("LENSMODEL_OPENCV4", {5800, 5795, 3838.9, 2161.4, -0.05, 0.015, -0.0002, 0.0001},
                  7680, 4320)};
  options.arc_deg = 30;
  options.frames = 60;
  options.min_distance = 1.5;
  options.max_distance = 3.0;
  const SyntheticRig rig = MakeSyntheticRig(options);
  const CalibrationSummary s = Calibrate(rig.layout, rig.cameras, rig.observations, {});
  const GroundTruthComparison g = Compare(rig, s);
  Print("8K", s, g);
  ASSERT_TRUE(IsUsable(s.termination)) << s.message;
  EXPECT_LE(g.focal_rel_err_max, 0.0005);
  EXPECT_LE(g.projection_diff_rms_px, 0.3);
  EXPECT_GE(g.within_3sigma_fraction, 0.9);
}

// Two studio cameras and 120 board poses, and a solve that cross-validates on an 8x6 grid.
SyntheticOptions CrossValidationRig() {
  SyntheticOptions options = ReducedRig();
  options.lenses = StudioLenses(2);
  options.frames = 120;
  return options;
}
CalibrationOptions CrossValidated() {
  CalibrationOptions solve;
  solve.cross_validation = true;
  solve.uncertainty_grid_x = 8;
  solve.uncertainty_grid_y = 6;
  return solve;
}

TEST(Calibrate, CrossValidationHalvesAgreeWithinTheirUncertainty) {
  const SyntheticRig rig = MakeSyntheticRig(CrossValidationRig());
  const CalibrationOptions solve = CrossValidated();
  const CalibrationSummary s = Calibrate(rig.layout, rig.cameras, rig.observations, solve);
  ASSERT_TRUE(IsUsable(s.termination)) << s.message;
  std::printf("[cross-validation] %s\n", s.cross_validation.dump().c_str());
  ASSERT_TRUE(s.cross_validation.contains("cameras"));
  EXPECT_EQ(s.cross_validation["cameras"].size(), 2u);
  for (const auto& [name, j] : s.cross_validation["cameras"].items()) {
    EXPECT_GE(j["within_sigma_sum_fraction"].get<double>(), 0.7) << name;
    EXPECT_LT(j["diff_rms_px"].get<double>(), 0.3) << name;
    EXPECT_LE(j["ratio_to_predicted"].get<double>(), solve.max_cross_validation_ratio) << name;
  }
}

// The same rig with the corner noise stated six times too small (0.05 px for the 0.3 px the
// observations carry): the uncertainty predicts a sixth of the halves' real difference, the
// cross-validation sees them differ by far more than twice that, and the solve, converged as
// it is, ends DEGENERATE naming the cameras.
TEST(Calibrate, CrossValidationBeyondThePredictionIsDegenerate) {
  const SyntheticOptions options = CrossValidationRig();
  const SyntheticRig rig = MakeSyntheticRig(options);
  CalibrationOptions solve = CrossValidated();
  solve.observed_pixel_sigma = options.noise_px / 6;
  solve.max_uncertainty_px = 1e9;  // the understated noise judged by the halves alone
  const CalibrationSummary s = Calibrate(rig.layout, rig.cameras, rig.observations, solve);
  std::printf("[cross-validation, noise understated] %s\n", s.cross_validation.dump().c_str());
  EXPECT_EQ(s.termination, Termination::kDegenerate) << s.message;
  EXPECT_NE(s.message.find("cross-validation: the halves differ beyond what the uncertainty "
                           "predicts in cam0 ("),
            std::string::npos)
      << s.message;
  EXPECT_GT(s.cross_validation["worst_ratio_to_predicted"].get<double>(),
            2 * solve.max_cross_validation_ratio);
}

// Each ending of a solve, from its residuals and Jacobian: a linear least-squares problem
// x(p) = J p - b, judged away from its minimum, at it, and with mrcal's failure signals.
TEST(SolverEnd, EachStateFromTheResidualsAndTheJacobian) {
  Eigen::MatrixXd j(20, 3);
  Eigen::VectorXd b(20);
  for (int r = 0; r < 20; ++r) {
    j.row(r) << 1.0, r * 0.1, std::sin(r * 0.7);
    b(r) = 2.0 + 0.3 * r + std::cos(r * 1.3);
  }
  const Eigen::SparseMatrix<double> jt = Eigen::MatrixXd(j.transpose()).sparseView();
  const Eigen::VectorXd at_seed = -b;  // p = 0: the cost still falls
  const calibration_internal::SolverEnd seed =
      calibration_internal::JudgeSolverEnd(jt, at_seed, 1.0);
  EXPECT_EQ(seed.termination, Termination::kNoConvergence);
  EXPECT_GT(seed.expected_decrease, 0.5);
  const Eigen::Vector3d best = j.colPivHouseholderQr().solve(b);
  const Eigen::VectorXd at_minimum = j * best - b;
  const calibration_internal::SolverEnd done =
      calibration_internal::JudgeSolverEnd(jt, at_minimum, 1.0);
  EXPECT_EQ(done.termination, Termination::kConvergence);
  EXPECT_LE(done.expected_decrease, calibration_internal::kCostTolerance);
  EXPECT_NEAR(done.cost, at_minimum.squaredNorm(), 1e-12);
  // mrcal_optimize's failure: a negative RMS; NaN anywhere.
  EXPECT_EQ(calibration_internal::JudgeSolverEnd(jt, at_minimum, -1.0).termination,
            Termination::kFailure);
  EXPECT_EQ(calibration_internal::JudgeSolverEnd(jt, at_minimum, std::nan("")).termination,
            Termination::kFailure);
  Eigen::VectorXd with_nan = at_minimum;
  with_nan(3) = std::nan("");
  EXPECT_EQ(calibration_internal::JudgeSolverEnd(jt, with_nan, 1.0).termination,
            Termination::kFailure);
}

SyntheticRig SmallRig() {
  SyntheticOptions options = ReducedRig();
  options.frames = 60;
  return MakeSyntheticRig(options);
}

// A clean rig: every mrcal stage converged, its own figures in the summary.
TEST(Calibrate, ReportsMrcalsOwnEndingOfEveryStage) {
  const SyntheticRig rig = SmallRig();
  CalibrationOptions solve;
  solve.uncertainty = false;
  const CalibrationSummary s = Calibrate(rig.layout, rig.cameras, rig.observations, solve);
  EXPECT_EQ(s.termination, Termination::kConvergence) << s.message;
  EXPECT_EQ(ExitStatus(s.termination), 0);
  ASSERT_EQ(s.stages.size(), 4u);
  for (const auto& stage : s.stages) {
    EXPECT_EQ(stage.termination, Termination::kConvergence) << stage.name;
    EXPECT_GT(stage.cost, 0) << stage.name;
    EXPECT_LE(stage.expected_decrease, calibration_internal::kCostTolerance) << stage.name;
  }
  const nlohmann::json j = s.ToJson();
  ASSERT_TRUE(j.contains("mrcal"));
  EXPECT_EQ(j["mrcal"]["termination"], "CONVERGENCE");
  EXPECT_NEAR(j["mrcal"]["rms_px"].get<double>(), s.stages.back().rms_px, 1e-12);
}

// A seed that cannot fit the observations stops the solve: FAILURE, exit status 1.
TEST(Calibrate, ASeedThatDoesNotFitIsFailure) {
  const SyntheticRig rig = SmallRig();
  CalibrationOptions solve;
  solve.uncertainty = false;
  solve.max_seed_rms_px = 0.01;  // below the detections' own noise
  const CalibrationSummary s = Calibrate(rig.layout, rig.cameras, rig.observations, solve);
  EXPECT_EQ(s.termination, Termination::kFailure);
  EXPECT_EQ(ExitStatus(s.termination), 1);
  EXPECT_NE(s.message.find("the seed does not fit"), std::string::npos) << s.message;
  EXPECT_EQ(s.stages.size(), 2u);
}

TEST(Calibrate, BadInputIsAnError) {
  const SyntheticRig rig = MakeSyntheticRig(ReducedRig());
  EXPECT_THROW(Calibrate(rig.layout, {}, rig.observations, {}), Error);
  std::vector<CalibrationCamera> cameras = rig.cameras;
  cameras.pop_back();  // an observation of a camera not in the list
  EXPECT_THROW(Calibrate(rig.layout, cameras, rig.observations, {}), Error);
  cameras = rig.cameras;
  cameras[0].lensmodel = "LENSMODEL_NOPE";
  EXPECT_THROW(Calibrate(rig.layout, cameras, rig.observations, {}), Error);
  CalibrationOptions options;
  options.reference_camera = "cam9";
  EXPECT_THROW(Calibrate(rig.layout, rig.cameras, rig.observations, options), Error);
}

}  // namespace
}  // namespace holocap
