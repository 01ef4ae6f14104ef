// Captures a user brings, as simulator variants: `holocap reconstruct TAKE` with no
// bounds, voxel, up axis or silhouette threshold given must end with a correct result or
// DEGENERATE with its reason, never SUCCESS on a wrong surface. "Correct": the mean symmetric
// Chamfer to the true mesh (in the take's own units) within two of the voxels the plan chose
// (a voxel is 2/3 of a pixel's footprint on the subject; on the plain studio depth fusion
// reaches 0.74 voxel and colour-only stereo 1.1-1.3). Each take: studio8 at 160 px, one frame
// set to reconstruct.
//
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "core/image.h"
#include "core/take.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;
using testing::RunCli;
using testing::TempDir;

// A test's value: what the json and string members throw (allocation) ends the test.
struct Outcome {  // NOLINT(bugprone-exception-escape)
  testing::CommandResult cli;
  nlohmann::json report;  // TAKE/recon/report.json; null when none was written
};

// Simulates a small studio8 take with `sim_flags` into `dir`/`name`; returns its folder.
fs::path Simulate(const TempDir& dir, const std::string& sim_flags,
                  const std::string& name = "take") {
  fs::path take = dir / name;
  const auto sim = RunCli("sim --rig studio8 --size 160 --seed 3 " + sim_flags + " --out '" +
                          take.string() + "'");
  EXPECT_EQ(sim.exit_code, 0) << sim.output;
  return take;
}

// Reconstructs `take` with the CLI's defaults (the voxel sweep and glTF left out: neither
// changes the mesh) and any `flags`.
Outcome Reconstruct(const fs::path& take, const std::string& flags = "") {
  Outcome outcome;
  outcome.cli = RunCli("reconstruct '" + take.string() +
                       "' --ground-truth-cameras --no-sweep --no-glb " + flags);
  std::ifstream file(take / "recon" / "report.json");
  if (file) outcome.report = nlohmann::json::parse(file);
  return outcome;
}

Outcome SimulateAndReconstruct(const TempDir& dir, const std::string& sim_flags) {
  return Reconstruct(Simulate(dir, sim_flags));
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
  const auto cli =
      RunCli("reconstruct '" + take.string() + "' --ground-truth-cameras --no-sweep --no-glb");
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
  // A clean plate holds the whole subject: stereo carves inside the hull, and the plan says so.
  EXPECT_EQ(outcome.report["plan"]["stereo_inside_hull"]["chosen"], true);
  EXPECT_NE(outcome.cli.output.find("stereo inside the hull: chosen: the silhouettes hold"),
            std::string::npos)
      << outcome.cli.output;
}

// The same ring with the subject's pixels replaced by noise that differs from view to view:
// the silhouettes and the hull are the subject's, but the views do not see one surface. A few
// pixels stay consistent by chance (77 of 5939 here), far below the tenth of the hull's pixels
// a subject keeps (56 % on the ring above): the stereo, and so the run, is DEGENERATE.
TEST(VariantsTest, StereoOfViewsThatDoNotMatchIsDegenerate) {
  TempDir dir;
  const fs::path take =
      Simulate(dir, "--frames 2 --clean-plate 1 --color-only --world-scale 0.05 --no-noise");
  cv::RNG rng(1);
  for (const auto& camera : fs::directory_iterator(take / "frames")) {
    const cv::Mat plate = ReadImage(camera.path() / "000000.png");
    cv::Mat image = ReadImage(camera.path() / "000001.png");
    cv::Mat difference;
    cv::absdiff(plate, image, difference);
    cv::Mat subject;
    cv::cvtColor(difference, subject, cv::COLOR_BGR2GRAY);
    subject = subject > 8;
    cv::Mat noise(image.size(), image.type());
    rng.fill(noise, cv::RNG::UNIFORM, 0, 256);
    noise.copyTo(image, subject);
    WriteImage(camera.path() / "000001.png", image);
  }
  const Outcome outcome = Reconstruct(take, "--ground-truth-cameras");
  ASSERT_FALSE(outcome.report.is_null()) << outcome.cli.output;
  EXPECT_EQ(outcome.report["plan"]["method"], "mvs");
  EXPECT_EQ(outcome.cli.exit_code, 1) << outcome.cli.output;
  EXPECT_EQ(outcome.report["summary"]["termination"], "DEGENERATE");
  const nlohmann::json& mvs = outcome.report["metrics"]["frames"][0]["metrics"]["mvs"];
  EXPECT_GT(mvs["pixels_consistent"].get<int64_t>(), 0) << mvs;
  EXPECT_LT(mvs["pixels_consistent"].get<int64_t>(), mvs["pixels_searched"].get<int64_t>() / 10)
      << mvs;
  EXPECT_NE(outcome.cli.output.find("mvs: too few consistent depths"), std::string::npos)
      << outcome.cli.output;
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

// A moving subject, no clean plate, and a take long enough for a background model: each
// camera's per-pixel median over the take's 30 sets is its plate (Chamfer 18.6 mm at 16 mm
// voxels; with a recorded clean plate 12.0 mm).
TEST(VariantsTest, MovingSubjectWithoutCleanPlateLearnsItsBackground) {
  TempDir dir;
  const Outcome outcome = Reconstruct(Simulate(dir, "--frames 30"), "--frames 15:16");
  ExpectCorrectOrDegenerate(outcome);
  const nlohmann::json& silhouettes = outcome.report["plan"]["silhouettes"];
  EXPECT_EQ(silhouettes["source"], "background model") << silhouettes;
  EXPECT_EQ(silhouettes["sets"].size(), 30u) << silhouettes;
  EXPECT_EQ(outcome.report["summary"]["termination"], "SUCCESS");
}

// A still subject (the static object scene) leaves the median holding it: the plan falls back
// to a threshold chosen per image and says why, rather than carving from empty silhouettes.
TEST(VariantsTest, StillSubjectFallsBackFromTheBackgroundModelAndSaysWhy) {
  TempDir dir;
  const Outcome outcome = Reconstruct(Simulate(dir, "--frames 16 --scene object"), "--frames 0:1");
  ASSERT_FALSE(outcome.report.is_null()) << outcome.cli.output;
  const nlohmann::json& silhouettes = outcome.report["plan"]["silhouettes"];
  EXPECT_EQ(silhouettes["source"], "otsu") << silhouettes;
  EXPECT_NE(silhouettes["why"].get<std::string>().find("the subject does not move"),
            std::string::npos)
      << silhouettes;
  // --silhouettes median on a take too short for one is one error line naming the count.
  const auto refused = Reconstruct(Simulate(dir, "--frames 2", "short"), "--silhouettes median");
  EXPECT_EQ(refused.cli.exit_code, 1);
  EXPECT_NE(refused.cli.output.find("holocap: error: silhouettes from a background model"),
            std::string::npos)
      << refused.cli.output;
}

// A dark subject on a near-black room, no clean plate (--dark): silhouettes from a threshold
// chosen per image. Was SUCCESS at 48.6 mm (16 mm voxels): Otsu's hysteresis joined the floor
// the subject stands on, and the Middlebury recipe's morphology (net 3 px, for 640-pixel
// images) doubled a limb's width at 160 px. Now 16.4 mm, and a hull that explains its
// silhouettes poorly ends DEGENERATE (the next test).
TEST(VariantsTest, DarkSubjectOnDarkBackgroundIsCorrectOrDegenerate) {
  TempDir dir;
  const Outcome outcome = SimulateAndReconstruct(dir, "--frames 1 --dark");
  ExpectCorrectOrDegenerate(outcome);
  EXPECT_EQ(outcome.report["plan"]["silhouettes"]["source"], "otsu");
}

// The dark object ring (a 9 cm object of columns on a near-black backdrop, colour only, no
// plate): with no flags its Otsu silhouettes take the closing measured on their boundaries,
// said in the plan and its printed lines, the same on a second run. Their boundary is clean
// (no jump in what closing fills), so none: the Middlebury recipe (--silhouette-morphology
// recipe) grows every silhouette by a rim and fills the gaps between the columns, a hull
// further from the truth. With holes and cracks cut into its views (below), a closing.
TEST(VariantsTest, ObjectRingSilhouettesTakeTheMeasuredMorphologyNotTheRecipe) {
  TempDir dir;
  const fs::path take = dir / "ring";
  const auto sim = RunCli(
      "sim --rig studio8 --size 320 --seed 3 --frames 1 --color-only "
      "--world-scale 0.05 --dark --out '" +
      take.string() + "'");
  ASSERT_EQ(sim.exit_code, 0) << sim.output;
  const Outcome automatic = Reconstruct(take);
  ASSERT_EQ(automatic.cli.exit_code, 0) << automatic.cli.output;
  const nlohmann::json& morphology = automatic.report["plan"]["silhouettes"]["morphology"];
  EXPECT_EQ(automatic.report["plan"]["silhouettes"]["source"], "otsu");
  EXPECT_EQ(morphology["asked"], "auto") << morphology;
  EXPECT_EQ(morphology["choice"], "none") << morphology;
  EXPECT_EQ(morphology["measured"]["close_px"], 0) << morphology;
  EXPECT_EQ(morphology["measured"]["fill_px"].size(), 6u) << morphology;  // 0..5 px at 320
  EXPECT_NE(automatic.cli.output.find("silhouette morphology: none: the boundary is clean"),
            std::string::npos)
      << automatic.cli.output;
  // Thresholded silhouettes may lose the subject's darkest parts: no stereo inside their hull.
  EXPECT_EQ(automatic.report["plan"]["stereo_inside_hull"]["chosen"], false);
  EXPECT_NE(automatic.cli.output.find("stereo inside the hull: not chosen: thresholded"),
            std::string::npos)
      << automatic.cli.output;
  const Outcome again = Reconstruct(take, "--overwrite");
  EXPECT_EQ(again.report["plan"]["silhouettes"]["morphology"], morphology);

  const Outcome recipe = Reconstruct(take, "--overwrite --silhouette-morphology recipe");
  ASSERT_EQ(recipe.cli.exit_code, 0) << recipe.cli.output;
  EXPECT_EQ(recipe.report["plan"]["silhouettes"]["morphology"]["choice"], "recipe");
  const double automatic_mm = automatic.report["metrics"]["gt"]["chamfer_mm"].get<double>();
  const double recipe_mm = recipe.report["metrics"]["gt"]["chamfer_mm"].get<double>();
  std::printf("chamfer: %.3f mm (auto), %.3f mm (recipe)\n", automatic_mm, recipe_mm);
  EXPECT_LT(automatic_mm, 0.8 * recipe_mm);

  // The same ring with holes and a crack cut into every view's subject (black discs of 1 and
  // 2 px radius and a line 2 px wide across it, as a threshold loses a subject's dark patches):
  // the fill curve jumps at the closing that spans them, which the plan takes, and the hull
  // carved from the closed silhouettes is the clean take's again (the same distance from the
  // truth within 2 %), where the unclosed ones carve a tunnel along every crack and hole (on
  // this fat 8-view hull that moves the distance by over 5 %, here down: a tunnel carves fat
  // and subject alike).
  testing::CutHolesAndCrack(take);
  const Outcome ragged = Reconstruct(take, "--overwrite");
  ASSERT_EQ(ragged.cli.exit_code, 0) << ragged.cli.output;
  const nlohmann::json& closing = ragged.report["plan"]["silhouettes"]["morphology"];
  const int close_px = closing["measured"]["close_px"].get<int>();
  EXPECT_GE(close_px, 2) << closing;  // a 2 px crack needs a disk 5 px across
  EXPECT_LE(close_px, 3) << closing;
  EXPECT_EQ(closing["choice"], "closing " + std::to_string(close_px) + " px") << closing;
  EXPECT_NE(ragged.cli.output.find("silhouette morphology: closing " + std::to_string(close_px) +
                                   " px: the closing that fills the jump in"),
            std::string::npos)
      << ragged.cli.output;
  const Outcome unclosed = Reconstruct(take, "--overwrite --silhouette-morphology none");
  ASSERT_EQ(unclosed.cli.exit_code, 0) << unclosed.cli.output;
  const double ragged_mm = ragged.report["metrics"]["gt"]["chamfer_mm"].get<double>();
  const double unclosed_mm = unclosed.report["metrics"]["gt"]["chamfer_mm"].get<double>();
  std::printf("ragged: chamfer %.3f mm (auto), %.3f mm (none); clean %.3f mm\n", ragged_mm,
              unclosed_mm, automatic_mm);
  EXPECT_NEAR(ragged_mm, automatic_mm, 0.02 * automatic_mm);
  EXPECT_GT(std::abs(unclosed_mm - automatic_mm), 0.05 * automatic_mm);

  const Outcome unknown = Reconstruct(take, "--overwrite --silhouette-morphology open");
  EXPECT_NE(unknown.cli.exit_code, 0);
  EXPECT_NE(unknown.cli.output.find("holocap: error: unknown silhouette morphology 'open'"),
            std::string::npos)
      << unknown.cli.output;
}

// The same take with two views' silhouettes spoiled by a bright patch of background that the
// other views do not see: the hull cannot explain those silhouettes, and the run ends
// DEGENERATE rather than SUCCESS on a hull swollen where only those views could carve.
TEST(VariantsTest, SilhouettesThatDisagreeBetweenViewsAreDegenerate) {
  TempDir dir;
  const fs::path take = Simulate(dir, "--frames 1 --dark");
  for (const auto& camera : {"cam4", "cam5"}) {
    const fs::path file = take / "frames" / camera / "000000.png";
    cv::Mat image = ReadImage(file);
    cv::rectangle(image, {0, image.rows / 2}, {image.cols / 2, image.rows - 1}, cv::Scalar::all(40),
                  -1);
    WriteImage(file, image);
  }
  const Outcome outcome = Reconstruct(take);
  const nlohmann::json& report = outcome.report;
  ASSERT_FALSE(report.is_null()) << outcome.cli.output;
  EXPECT_EQ(report["summary"]["termination"], "DEGENERATE") << outcome.cli.output;
  EXPECT_EQ(outcome.cli.exit_code, 1);
  EXPECT_NE(outcome.cli.output.find("explains its silhouettes poorly"), std::string::npos)
      << outcome.cli.output;
  const auto& agreement = report["metrics"]["frames"][0]["metrics"]["silhouette_agreement"];
  EXPECT_LT(agreement["views"]["cam4"].get<double>(), 0.5) << agreement;
  EXPECT_GT(agreement["views"]["cam0"].get<double>(), 0.5) << agreement;
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
