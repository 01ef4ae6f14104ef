// The world of a calibration comes from the take, not from a simulation's truth: a studio8
// board take calibrated with its gt/ removed, then a walk take reconstructed with those models.
#include <gtest/gtest.h>

#include <cmath>
#include <nlohmann/json.hpp>

#include "core/camera.h"
#include "core/fs.h"
#include "core/rig_alignment.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::RunCli;
using testing::TempDir;

namespace fs = std::filesystem;

std::map<std::string, CameraModel> Models(const fs::path& folder) {
  std::map<std::string, CameraModel> models;
  for (const auto& entry : fs::directory_iterator(folder)) {
    if (entry.path().extension() == ".cameramodel")
      models.emplace(entry.path().stem().string(), CameraModel::Read(entry.path()));
  }
  return models;
}

double ChamferMm(const fs::path& recon) {
  const auto report = nlohmann::json::parse(ReadFileToString(recon / "report.json"));
  return report["metrics"]["gt"]["chamfer_mm"].get<double>();
}

bool Ran(const std::string& command) {
  const auto result = RunCli(command);
  EXPECT_EQ(result.exit_code, 0) << command << "\n" << result.output;
  return result.exit_code == 0;
}

TEST(CalibrationWorld, ATakeWithoutTruthComesOutZUpOnTheFloorAndReconstructsAsWell) {
  TempDir dir("holocap-calib-world");
  const fs::path cal = dir / "cal", walk = dir / "walk";
  ASSERT_TRUE(Ran("sim --rig studio8 --board --frames 48 --size 640 --out " + cal.string()));
  // As a real take: no gt/, the board layout given by the user.
  const auto board = nlohmann::json::parse(ReadFileToString(cal / "gt" / "board.json"));
  WriteFileAtomic(dir / "board.json", board["layout"].dump());
  const std::map<std::string, CameraModel> truth = Models(cal / "gt" / "cameras");
  fs::remove_all(cal / "gt");
  ASSERT_TRUE(Ran("calibrate " + cal.string() + " --board " + (dir / "board.json").string() +
                  " --no-pictures --no-uncertainty"));
  const auto report = nlohmann::json::parse(ReadFileToString(cal / "calib" / "report.json"));
  EXPECT_EQ(report["plan"]["world_frame"], "depth floor") << report["plan"]["world_reason"];
  EXPECT_FALSE(report["metrics"].contains("gt"));

  // The written world against the truth's (z up, floor at z = 0), after laying the rig on it.
  const std::map<std::string, CameraModel> solved = Models(cal / "calib");
  ASSERT_EQ(solved.size(), 10u);
  const Pose true_from_written = AlignRigs(solved, truth);
  const double up_err_deg =
      std::acos(std::clamp(true_from_written.linear()(2, 2), -1.0, 1.0)) * 180 / M_PI;
  const double floor_err_mm = 1000 * true_from_written.translation().z();
  // A world left in the reference camera's frame would be ~100 degrees and metres off; the depth
  // floor is as good as the depth sensors' extrinsics (0.02 deg and 1 mm here; 0.76 deg and
  // 30 mm while board planes 4 m away were fitted to the noise's mode).
  EXPECT_LT(up_err_deg, 0.2);
  EXPECT_LT(std::abs(floor_err_mm), 10.0);
  std::printf("written world: up %.3f deg, floor %.1f mm from the truth's\n", up_err_deg,
              floor_err_mm);

  // The walk take: with the true cameras, with these models (no flags), and with these models
  // laid on the true world (what the calibration of a simulated take wrote before).
  // The walk is recorded at half the board take's size: it takes the board take's calibration
  // over (`calibrate --from`), each lens scaled by 0.5, as a studio's takes do.
  ASSERT_TRUE(
      Ran("sim --rig studio8 --frames 2 --clean-plate 1 --size 320 --out " + walk.string()));
  const std::string walk_args = walk.string() + " --no-sweep --no-glb";
  ASSERT_TRUE(
      Ran("reconstruct " + walk_args + " --ground-truth-cameras --out " + (dir / "gt").string()));
  // Uncalibrated, the walk is refused; then it takes the board take's models.
  testing::ExpectOneLineError(RunCli("reconstruct " + walk_args), "run holocap calibrate first");
  // The truth is never taken over as a calibration.
  testing::ExpectOneLineError(
      RunCli("calibrate " + walk.string() + " --from " + (walk / "gt" / "cameras").string()),
      "is a simulated take's truth, not a calibration");
  EXPECT_FALSE(fs::exists(walk / "calib" / "cam0.cameramodel"));
  const auto adopted = RunCli("calibrate " + walk.string() + " --from " + cal.string());
  ASSERT_EQ(adopted.exit_code, 0) << adopted.output;
  EXPECT_NE(adopted.output.find("taken over for 10 sensors (scaled: cam0 x0.5"), std::string::npos)
      << adopted.output;
  const auto adopted_report =
      nlohmann::json::parse(ReadFileToString(walk / "calib" / "report.json"));
  EXPECT_EQ(adopted_report["plan"]["adopted"]["termination"], report["summary"]["termination"]);
  for (const auto& [name, model] : solved) {
    const CameraModel scaled = CameraModel::Read(walk / "calib" / (name + ".cameramodel"));
    EXPECT_EQ(scaled.width() * 2, model.width()) << name;
    EXPECT_LT((scaled.cam_from_world().matrix() - model.cam_from_world().matrix()).norm(), 1e-9);
  }
  ASSERT_TRUE(Ran("reconstruct " + walk_args + " --out " + (dir / "take-world").string()));
  for (auto [name, model] : solved) {
    model = model.Scaled(0.5);
    model.set_cam_from_world(model.cam_from_world() * true_from_written.inverse());
    model.Write(walk / "calib" / (name + ".cameramodel"));
  }
  ASSERT_TRUE(Ran("reconstruct " + walk_args + " --out " + (dir / "true-world").string()));
  const double with_truth = ChamferMm(dir / "gt"), take_world = ChamferMm(dir / "take-world"),
               true_world = ChamferMm(dir / "true-world");
  std::printf(
      "chamfer: true cameras %.3f mm, calibrated in the take's world %.3f mm, the same "
      "laid on the true world %.3f mm\n",
      with_truth, take_world, true_world);
  EXPECT_LT(std::abs(take_world - true_world), 0.1 * true_world);
  // Calibrated without gt/, the walk reconstructs as with the true cameras, within 10 %.
  EXPECT_LT(std::abs(take_world - with_truth), 0.1 * with_truth);
}

}  // namespace
}  // namespace holocap
