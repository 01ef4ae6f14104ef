// neural/live_rerender.h from the CLI: a network trained on a small simulated scan take (a half
// turn before single-rgbd, 160x120) rerenders `holocap live`'s compositions of a walk before
// the same sensor; a missing scan, a scan without its trajectory and a model of another kind
// are refused with one error line.
#include <gtest/gtest.h>

#include <fstream>
#include <nlohmann/json.hpp>

#include "core/fs.h"
#include "core/image.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;

// A half turn scanned.
void ScanHalfTurn(const fs::path& turn) {
  ASSERT_EQ(testing::RunCli("sim --rig single-rgbd --trajectory turn --fps 10 --frames 36 "
                            "--trajectory-speed 50 --size 160x120 --out " +
                            turn.string())
                .exit_code,
            0);
  const testing::CommandResult scan =
      testing::RunCli("scan " + turn.string() + " --ground-truth-cameras --turn");
  ASSERT_EQ(scan.exit_code, 0) << scan.output;
}

TEST(LiveRerenderCli, TrainsOnTheScanTakeAndRerendersTheLiveCompositions) {
  testing::TempDir dir("holocap-live-rerender");
  const fs::path turn = dir / "turn", walk = dir / "walk", model = dir / "model";
  ScanHalfTurn(turn);
  // The same sensor, fixed, sees the subject walk; its own colour camera stands in for a
  // held-out one here (the command is what is tested, not the score).
  ASSERT_EQ(
      testing::RunCli("sim --rig single-rgbd --frames 2 --size 160x120 --out " + walk.string())
          .exit_code,
      0);
  ASSERT_EQ(testing::RunCli("live " + walk.string() + " --ground-truth-cameras --scan " +
                            (turn / "scan").string())
                .exit_code,
            0);
  const testing::CommandResult train = testing::RunCli(
      "train rerender " + turn.string() + " --ground-truth-cameras --scan " +
      (turn / "scan").string() + " --out " + model.string() +
      " --iterations 120 --validate-every 40 --lr 1e-3 --live-frames 8 --targets-per-frame 2 "
      "--crop 32 --unet-width 8 --unet-depth 3 --threads 2");
  ASSERT_EQ(train.exit_code, 0) << train.output;
  const auto report = nlohmann::json::parse(ReadFileToString(model / "report.json"));
  const auto& metrics = report["metrics"];
  EXPECT_EQ(metrics["composed_frames"], 8);
  EXPECT_EQ(metrics["iterations"], 120);
  // Two of the eight compositions validate (the 3rd and 7th), each at two frames turned away.
  EXPECT_EQ(metrics["validation_pairs"], 4);
  EXPECT_EQ(metrics["train_pairs"], 12);
  // 120 iterations lift the validation pairs 0.9 dB above the raw composition (21.3 dB).
  EXPECT_GT(metrics["validation_psnr_db"].get<double>(),
            metrics["raw_psnr_db"].get<double>() + 0.5);
  EXPECT_GT(metrics["raw_psnr_db"].get<double>(), 15);
  int validation_points = 0, loss_points = 0;
  for (const auto& point : report["series"]) {
    validation_points += point["metric"] == "validation_psnr_db";
    loss_points += point["metric"] == "loss";
  }
  EXPECT_EQ(validation_points, 4);  // iterations 0, 40, 80 and 120
  EXPECT_EQ(loss_points, 12);
  EXPECT_EQ(nlohmann::json::parse(ReadFileToString(model / "model.json"))["method"],
            "live-rerender");
  EXPECT_EQ(ReadImage(model / "validation.png").cols, 3 * 160);

  const fs::path out = dir / "rerendered";
  const testing::CommandResult render = testing::RunCli(
      "render " + walk.string() + " --ground-truth-cameras --model " + model.string() +
      " --recon " + (walk / "live" / "recon").string() + " --cameras cam0 --out " + out.string());
  ASSERT_EQ(render.exit_code, 0) << render.output;
  const cv::Mat image = ReadImage(out / "cam0" / "000001.png");
  ASSERT_EQ(image.cols, 160);
  ASSERT_EQ(image.rows, 120);
  // The subject is drawn: a good part of the image is not the black background.
  cv::Mat gray;
  image.convertTo(gray, CV_32F);
  EXPECT_GT(cv::countNonZero(gray.reshape(1) > 10), 160 * 120 / 20);
  EXPECT_EQ(nlohmann::json::parse(ReadFileToString(out / "report.json"))["metrics"]["images"], 2);

  // A model of another kind is refused.
  fs::create_directories(dir / "nvol");
  std::ofstream(dir / "nvol" / "model.json") << R"({"method": "nvol"})";
  testing::ExpectOneLineError(
      testing::RunCli("render " + walk.string() + " --ground-truth-cameras --model " +
                      (dir / "nvol").string() + " --recon " + (walk / "live" / "recon").string() +
                      " --cameras cam0 --out " + (dir / "refused").string()),
      "is a nvol model, not one trained on a scan take");
  EXPECT_FALSE(fs::exists(dir / "refused" / "cam0"));
}

TEST(LiveRerenderCli, RefusesAMissingScanOrOneWithoutItsTrajectory) {
  testing::TempDir dir("holocap-live-rerender");
  fs::create_directories(dir / "take");
  testing::ExpectOneLineError(testing::RunCli("train rerender " + (dir / "take").string() +
                                              " --ground-truth-cameras --scan " +
                                              (dir / "none").string() + " --iterations 5"),
                              "is not a directory");
  EXPECT_FALSE(fs::exists(dir / "take" / "models"));
  const fs::path turn = dir / "turn";
  ScanHalfTurn(turn);
  fs::remove(turn / "scan" / "trajectory.json");
  testing::ExpectOneLineError(
      testing::RunCli("train rerender " + turn.string() + " --ground-truth-cameras --scan " +
                      (turn / "scan").string() + " --iterations 5 --out " +
                      (dir / "model").string()),
      "holds no trajectory.json");
}

}  // namespace
}  // namespace holocap
