// Multi-view stereo over many views: which views each reference view is matched against
// (nearest by the angle at the subject, never one too close, opposite or at a grazing angle),
// which views are searched at all (spread over the sphere), and what `holocap reconstruct`
// says of both, with progress lines within a frame set.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <nlohmann/json.hpp>
#include <numbers>

#include "core/pose.h"
#include "reconstruction/reconstruction.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;

constexpr double kDegree = std::numbers::pi / 180;

// A pinhole camera `distance_m` from the origin, `angle_deg` from +x about +z, looking at the
// origin (or at `look_at`).
CameraModel CameraAt(double angle_deg, double distance_m,
                     const Eigen::Vector3d& look_at = Eigen::Vector3d::Zero()) {
  const Eigen::Vector3d eye =
      distance_m * Eigen::Vector3d(std::cos(angle_deg * kDegree), std::sin(angle_deg * kDegree), 0);
  return CameraModel::Pinhole(60, 64, 64, CamFromWorldLookAt(eye, look_at));
}

double AngleDeg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::acos(std::clamp(a.normalized().dot(b.normalized()), -1.0, 1.0)) / kDegree;
}

// The reference (view 0) at +x, 2 m out. Of the others, the three nearest by angle within
// [3, 60] degrees at similar distances are its sources, nearest first: not the one 1 degree
// away (no baseline), not the opposite one, not the one at a grazing 85 degrees, not one 12
// degrees away at three times the distance, not one that looks away from the subject. Views
// beyond 60 degrees serve only a view with fewer than three within it, and never from 90.
TEST(StereoViewsTest, SourcesAreTheNearestByAngleAndBaseline) {
  const std::vector<CameraModel> cameras = {
      CameraAt(0, 2),                             // 0: the reference
      CameraAt(1, 2),                             // 1: too close to triangulate
      CameraAt(180, 2),                           // 2: opposite
      CameraAt(85, 2),                            // 3: grazing
      CameraAt(12, 6),                            // 4: three times as far
      CameraAt(15, 2, Eigen::Vector3d(0, 5, 0)),  // 5: does not see the subject
      CameraAt(-20, 2),                           // 6
      CameraAt(10, 2),                            // 7
      CameraAt(40, 2.2),                          // 8
      CameraAt(55, 2),                            // 9: within the angle, but a fourth
  };
  MvsOptions options;
  options.neighbors = 3;
  options.max_reference_views = 0;
  const MvsViewChoice choice = ChooseMvsViews(cameras, Eigen::Vector3d::Zero(), options);
  EXPECT_EQ(choice.sources[0], (std::vector<int>{7, 6, 8}));
  // View 5 does not see the subject: it searches nothing and is no one's partner.
  EXPECT_TRUE(std::find(choice.references.begin(), choice.references.end(), 5) ==
              choice.references.end());
  // Every partner of every view lies within the angles asked for, or (a view with fewer than
  // three there, such as the one at 85 degrees) short of 90 degrees: never opposite.
  for (int r : choice.references) {
    const std::vector<int>& sources = choice.sources[r];
    for (size_t k = 0; k < sources.size(); ++k) {
      const double angle =
          AngleDeg(cameras[r].center_in_world(), cameras[sources[k]].center_in_world());
      EXPECT_GE(angle, options.min_angle_deg) << r << " " << sources[k];
      EXPECT_LT(angle, 90) << r << " " << sources[k];
      // The views within the angles come first.
      if (k > 0 && angle <= options.max_angle_deg) {
        EXPECT_LE(AngleDeg(cameras[r].center_in_world(), cameras[sources[k - 1]].center_in_world()),
                  options.max_angle_deg)
            << r;
      }
    }
  }
}

// 50 cameras evenly over a sphere, at most 8 reference views: farthest-point sampling spreads
// them (no two closer than 50 degrees, every camera within 60 degrees of one; the first 8 by
// index are 25 degrees apart and leave cameras 123 degrees from any). Each reference view's
// depth is checked against reference views only.
TEST(StereoViewsTest, ReferenceViewsSpreadOverTheSphere) {
  std::vector<CameraModel> cameras;
  const int n = 50;
  for (int i = 0; i < n; ++i) {
    const double z = 1 - 2 * (i + 0.5) / n, r = std::sqrt(1 - z * z);
    const double azimuth = i * std::numbers::pi * (3 - std::sqrt(5.0));
    const Eigen::Vector3d eye =
        2 * Eigen::Vector3d(r * std::cos(azimuth), r * std::sin(azimuth), z);
    // Looking at the subject with an up that is never along the view.
    const Eigen::Vector3d up =
        std::abs(z) > 0.9 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitZ();
    cameras.push_back(CameraModel::Pinhole(60, 64, 64, CamFromWorldLookAt(eye, {0, 0, 0}, up)));
  }
  MvsOptions options;
  options.max_reference_views = 8;
  const MvsViewChoice choice = ChooseMvsViews(cameras, Eigen::Vector3d::Zero(), options);
  ASSERT_EQ(choice.references.size(), 8u);
  double closest = 180;
  for (int a : choice.references) {
    for (int b : choice.references) {
      if (a < b) {
        closest =
            std::min(closest, AngleDeg(cameras[a].center_in_world(), cameras[b].center_in_world()));
      }
    }
  }
  EXPECT_GT(closest, 50);
  double farthest = 0;
  for (const CameraModel& camera : cameras) {
    double nearest = 180;
    for (int r : choice.references)
      nearest = std::min(nearest, AngleDeg(camera.center_in_world(), cameras[r].center_in_world()));
    farthest = std::max(farthest, nearest);
  }
  EXPECT_LT(farthest, 60);
  for (int r : choice.references) {
    EXPECT_FALSE(choice.sources[r].empty()) << r;
    for (int c : choice.checks[r]) {
      EXPECT_TRUE(std::find(choice.references.begin(), choice.references.end(), c) !=
                  choice.references.end())
          << r << " is checked against " << c << ", which has no depth";
    }
  }
}

// `holocap reconstruct` on a sphere of 12 cameras with 6 stereo views: the plan names the six
// and why (and what was left out), gives an estimate of the sweeps' seconds, and a progress
// line counts the views within the frame set.
TEST(StereoViewsTest, CliPlansTheViewsEstimatesTheTimeAndShowsProgress) {
  testing::TempDir dir;
  const fs::path take = dir / "take";
  const auto sim = testing::RunCli(
      "sim --rig sphere12 --scene object --alpha --size 96 --frames 1 "
      "--no-noise --out '" +
      take.string() + "'");
  ASSERT_EQ(sim.exit_code, 0) << sim.output;
  const auto run = testing::RunShell("env -u HOLOCAP_NO_PROGRESS HOLOCAP_PROGRESS_SECONDS=0 '" +
                                     testing::CliPath() + "' reconstruct '" + take.string() +
                                     "' --ground-truth-cameras --no-glb --stereo-views 6");
  // One line per view as it finishes (HOLOCAP_PROGRESS_SECONDS=0), the last saying all six.
  EXPECT_NE(run.output.find("reconstruct 000000: stereo views: 1/6,"), std::string::npos)
      << run.output;
  EXPECT_NE(run.output.find("reconstruct 000000: stereo views: 6/6,"), std::string::npos)
      << run.output;
  std::ifstream file(take / "recon" / "report.json");
  ASSERT_TRUE(file) << run.output;
  const nlohmann::json report = nlohmann::json::parse(file);
  const nlohmann::json& plan = report["plan"];
  EXPECT_EQ(plan["method"], "mvs");
  ASSERT_TRUE(plan.contains("stereo_views")) << plan.dump(1);
  EXPECT_EQ(plan["stereo_views"]["references"].size(), 6u);
  EXPECT_NE(plan["stereo_views"]["why"].get<std::string>().find("farthest-point"),
            std::string::npos);
  ASSERT_TRUE(plan["left_out"].contains("stereo depth of every view")) << plan["left_out"];
  EXPECT_NE(plan["left_out"]["stereo depth of every view"].get<std::string>().find("6 of the 12"),
            std::string::npos);
  EXPECT_GT(plan["stereo_estimate"]["seconds"].get<double>(), 0);
  EXPECT_GT(plan["stereo_estimate"]["pixel_hypotheses"].get<int64_t>(), 0);
  EXPECT_NE(plan["stereo_estimate"]["basis"].get<std::string>().find("an estimate"),
            std::string::npos);
  EXPECT_NE(run.output.find("stereo views: 6 of 12 searched"), std::string::npos) << run.output;
  EXPECT_NE(run.output.find("): an estimate"), std::string::npos) << run.output;
  const nlohmann::json& mvs = report["metrics"]["frames"][0]["metrics"]["mvs"];
  EXPECT_EQ(mvs["reference_views"], 6) << mvs;
}

}  // namespace
}  // namespace holocap
