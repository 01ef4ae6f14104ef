// Captures a user brings, as simulator variants (issue 19): `holocap reconstruct TAKE` with no
// bounds, voxel, up axis or silhouette threshold given must end with a correct result or
// DEGENERATE with its reason, never SUCCESS on a wrong surface. "Correct": the mean symmetric
// Chamfer to the true mesh (in the take's own units) within two of the voxels the plan chose
// (a voxel is 2/3 of a pixel's footprint on the subject; on the plain studio depth fusion
// reaches 0.74 voxel and colour-only stereo 1.1-1.3). Each take: studio8 at 160 px, one frame
// set to reconstruct.
//
// Tests named DISABLED_ reproduce a variant whose default commands end SUCCESS on a wrong
// surface or with an error today; their comments give the numbers measured and where the fault
// lies (run them with --gtest_also_run_disabled_tests).
#include <gtest/gtest.h>

#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "core/image.h"
#include "core/take.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;
using testing::RunCli;
using testing::TempDir;

struct Outcome {
  testing::CommandResult cli;
  nlohmann::json report;  // TAKE/recon/report.json; null when none was written
};

// Simulates a small studio8 take with `sim_flags` into `dir`/take and reconstructs it with the
// CLI's defaults (the voxel sweep and glTF left out: neither changes the mesh).
Outcome SimulateAndReconstruct(const TempDir& dir, const std::string& sim_flags) {
  const fs::path take = dir / "take";
  const auto sim = RunCli("sim --rig studio8 --size 160 --seed 3 " + sim_flags + " --out '" +
                          take.string() + "'");
  EXPECT_EQ(sim.exit_code, 0) << sim.output;
  Outcome outcome;
  outcome.cli = RunCli("reconstruct '" + take.string() + "' --no-sweep --no-glb");
  std::ifstream file(take / "recon" / "report.json");
  if (file) outcome.report = nlohmann::json::parse(file);
  return outcome;
}

// A correct surface (Chamfer within two of the plan's voxels) or DEGENERATE with its reason.
void ExpectCorrectOrDegenerate(const Outcome& outcome) {
  ASSERT_FALSE(outcome.report.is_null()) << "no report.json: " << outcome.cli.output;
  const nlohmann::json& report = outcome.report;
  const std::string termination = report["summary"]["termination"];
  if (termination == "DEGENERATE") {
    EXPECT_EQ(outcome.cli.exit_code, 1);
    EXPECT_NE(outcome.cli.output.find("holocap: error: reconstruction ended DEGENERATE: "),
              std::string::npos)
        << outcome.cli.output;
    EXPECT_FALSE(report["summary"]["message"].get<std::string>().empty());
    return;
  }
  ASSERT_EQ(termination, "SUCCESS") << outcome.cli.output;
  EXPECT_EQ(outcome.cli.exit_code, 0) << outcome.cli.output;
  const double voxel_mm = 1000 * report["plan"]["voxel"]["m"].get<double>();
  const double chamfer_mm = report["metrics"]["gt"]["chamfer_mm"].get<double>();
  std::printf("SUCCESS: chamfer %.3f mm, voxel %.3f mm\n", chamfer_mm, voxel_mm);
  EXPECT_LE(chamfer_mm, 2 * voxel_mm) << "SUCCESS on a surface " << chamfer_mm
                                      << " mm (mean) from the truth: " << report["plan"].dump();
}

// The plain studio: a clean plate, z up, metres. The reference the variants are measured by.
TEST(VariantsTest, StudioWithCleanPlateIsCorrect) {
  TempDir dir;
  const Outcome outcome = SimulateAndReconstruct(dir, "--frames 2 --clean-plate 1");
  ExpectCorrectOrDegenerate(outcome);
  EXPECT_EQ(outcome.report["summary"]["termination"], "SUCCESS");
}

// A 9 cm subject seen from 15 cm (--world-scale 0.05): bounds, voxel and the depth range
// fused follow the rig. With the fixed 0.2 m minimum depth every measurement (0.15 m) was
// dropped and the result was the colour cameras' hull alone (Chamfer 0.92 mm); fused, 0.59 mm.
TEST(VariantsTest, WorldScaleFiveHundredthsIsCorrectOrDegenerate) {
  TempDir dir;
  const Outcome outcome =
      SimulateAndReconstruct(dir, "--frames 2 --clean-plate 1 --world-scale 0.05");
  ExpectCorrectOrDegenerate(outcome);
  const nlohmann::json& plan = outcome.report["plan"];
  EXPECT_LT(plan["depth_range"]["min_m"].get<double>(), 0.1) << plan["depth_range"];
  EXPECT_FALSE(plan.contains("depth_fusion")) << plan["depth_fusion"];
  for (const auto& frame : outcome.report["metrics"]["frames"]) {
    const auto& tsdf = frame["metrics"]["tsdf"];
    EXPECT_GT(tsdf["valid_pixels"].get<double>(), 0.9 * tsdf["measured_pixels"].get<double>());
  }
  ASSERT_TRUE(plan.contains("bounds")) << outcome.cli.output;
  for (int axis = 0; axis < 3; ++axis) {
    const double side = plan["bounds"]["box"]["max"][axis].get<double>() -
                        plan["bounds"]["box"]["min"][axis].get<double>();
    EXPECT_LT(side, 0.2) << "bounds of a 9 cm subject seen from 15 cm: " << plan["bounds"];
  }
  EXPECT_LE(plan["voxel"]["m"].get<double>(), 0.001);
}

// Depth maps that lie wholly out of the scene's range (each measurement moved 100x farther, as a
// sensor in the wrong unit would give): nothing is fused, and the run says that its surface is
// the colour cameras' hull, in the plan and the summary, rather than a fusion.
TEST(VariantsTest, DepthOutOfRangeFallsBackToTheHullAndSaysSo) {
  TempDir dir;
  const fs::path take = dir / "take";
  ASSERT_EQ(RunCli("sim --rig studio8 --size 160 --seed 3 --frames 2 --clean-plate 1 --out '" +
                   take.string() + "'")
                .exit_code,
            0);
  for (const auto& sensor : {"depth0", "depth1"}) {
    for (const auto& entry : fs::directory_iterator(take / "frames" / sensor)) {
      if (entry.path().filename() == "000000.exr") continue;  // the clean plate stays
      cv::Mat depth = ReadImage(entry.path());
      WriteExrDepth(entry.path(), depth * 100);
    }
  }
  const auto cli = RunCli("reconstruct '" + take.string() + "' --no-sweep --no-glb");
  std::ifstream file(take / "recon" / "report.json");
  ASSERT_TRUE(file) << cli.output;
  const nlohmann::json report = nlohmann::json::parse(file);
  ASSERT_TRUE(report["plan"].contains("depth_fusion")) << cli.output;
  EXPECT_NE(report["plan"]["depth_fusion"].get<std::string>().find("visual hull"),
            std::string::npos);
  EXPECT_NE(report["summary"]["message"].get<std::string>().find("fell back"), std::string::npos);
  EXPECT_EQ(report["metrics"]["frames"][0]["metrics"]["tsdf"]["valid_pixels"], 0);
}

// The same ring without depth sensors (Middlebury's 16-view object ring): multi-view stereo.
// The stereo's depth (0.15 m) was fused with the fixed 0.2 m minimum depth, which dropped all of
// it: SUCCESS with 110 vertices and Chamfer 19.07 mm on a 9 cm subject (voxel 1 mm). With the
// scene's range, its nearest search depth and plane step relative to depth: 1.03 mm.
TEST(VariantsTest, WorldScaleColourRingIsCorrectOrDegenerate) {
  TempDir dir;
  const Outcome outcome =
      SimulateAndReconstruct(dir, "--frames 2 --clean-plate 1 --color-only --world-scale 0.05");
  ExpectCorrectOrDegenerate(outcome);
  EXPECT_EQ(outcome.report["plan"]["method"], "mvs");
  EXPECT_EQ(outcome.report["summary"]["termination"], "SUCCESS");
}

// A y-down world (--up -y, CMU Panoptic's): the plan's up axis comes from the rig.
TEST(VariantsTest, UpMinusYIsCorrectOrDegenerate) {
  TempDir dir;
  const Outcome outcome = SimulateAndReconstruct(dir, "--frames 2 --clean-plate 1 --up -y");
  ExpectCorrectOrDegenerate(outcome);
  EXPECT_EQ(outcome.report["plan"]["up"]["axis"], nlohmann::json({0.0, -1.0, 0.0}))
      << outcome.report["plan"]["up"];
}

// A moving subject and no clean plate (sim's default): the per-image threshold cannot separate
// the subject from the lit studio; the coarse hull fills the cameras' shared view.
TEST(VariantsTest, NoCleanPlateIsCorrectOrDegenerate) {
  TempDir dir;
  const Outcome outcome = SimulateAndReconstruct(dir, "--frames 1");
  ExpectCorrectOrDegenerate(outcome);
  EXPECT_EQ(outcome.report["plan"]["silhouettes"]["source"], "otsu");
}

// A dark subject on a near-black room, no clean plate (--dark): silhouettes from a threshold
// chosen per image. Today SUCCESS with Chamfer 48.6 mm (voxel 16 mm; 22.0 mm = 2.75 voxels at
// 320 px): the depth sensors now fuse only what lies in the colour cameras' hull (111 mm when
// every depth pixel was fused), but the Otsu silhouettes keep background, the hull that gates
// and completes the depth holds it, and no plausibility check in reconstruction/pipeline.cpp
// catches it.
TEST(VariantsTest, DISABLED_DarkSubjectOnDarkBackgroundIsCorrectOrDegenerate) {
  TempDir dir;
  ExpectCorrectOrDegenerate(SimulateAndReconstruct(dir, "--frames 1 --dark"));
}

// RGBA with the true silhouette in alpha, no clean plate (NeRF-synthetic's): the take holds the
// exact masks and the plan takes silhouettes from them. Without a depth clean plate the depth
// sensors' foreground is what lies in the colour cameras' hull (before alpha was read:
// silhouettes from Otsu and DEGENERATE; alpha with every depth pixel fused: 97 mm).
TEST(VariantsTest, AlphaWithoutCleanPlateIsCorrectOrDegenerate) {
  TempDir dir;
  const Outcome outcome = SimulateAndReconstruct(dir, "--frames 1 --alpha");
  const Take take = Take::Open(dir / "take");
  EXPECT_EQ(take.stream("cam0").pixel_format, "bgra8");
  std::vector<cv::Mat> channels;
  cv::split(take.ReadFrame(0, "cam0"), channels);
  ASSERT_EQ(channels.size(), 4u);
  const cv::Mat truth = ReadImage(take.gt_dir() / "masks" / "cam0" / "000000.png");
  EXPECT_EQ(cv::norm(channels[3], truth, cv::NORM_INF), 0);
  ExpectCorrectOrDegenerate(outcome);
  EXPECT_EQ(outcome.report["plan"]["silhouettes"]["source"], "alpha");
  EXPECT_EQ(outcome.report["summary"]["termination"], "SUCCESS");
}

// The same with a clean plate: alpha still comes first (it is exact; the plate's subtraction
// is not). Colour, texture and fusion read BGR with alpha dropped (before: an error, "colour
// frames of 'cam0' must be 8-bit", and no report.json).
TEST(VariantsTest, AlphaWithCleanPlateIsCorrectOrDegenerate) {
  TempDir dir;
  const Outcome outcome = SimulateAndReconstruct(dir, "--frames 2 --clean-plate 1 --alpha");
  ExpectCorrectOrDegenerate(outcome);
  EXPECT_EQ(outcome.report["plan"]["silhouettes"]["source"], "alpha");
  EXPECT_EQ(outcome.report["summary"]["termination"], "SUCCESS");
}

}  // namespace
}  // namespace holocap
