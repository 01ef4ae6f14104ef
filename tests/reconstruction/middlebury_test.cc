// A real capture: the Middlebury dinoSparseRing (16 views of a dark-background object),
// imported with `holocap import middlebury`. The hull of 15 views must predict the silhouette
// of the held-out 16th.
#include <gtest/gtest.h>

#include <fstream>
#include <nlohmann/json.hpp>

#include "core/take.h"
#include "reconstruction/reconstruction.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;

// The README's tight box of the dinosaur, grown by 1 cm.
Box DinoBounds() {
  Box box;
  box.min = Eigen::Vector3d(-0.061897, -0.018874, -0.057845) - Eigen::Vector3d::Constant(0.01);
  box.max = Eigen::Vector3d(0.010897, 0.068227, 0.015495) + Eigen::Vector3d::Constant(0.01);
  return box;
}

// The README's recipe: threshold at 0.19, dilate 10, erode 7.
SilhouetteOptions DinoSilhouettes() {
  SilhouetteOptions options;
  options.mode = SilhouetteMode::kThreshold;
  options.threshold = 0.19;
  options.open_px = 0;
  options.dilate_px = 10;
  options.erode_px = 7;
  return options;
}

class MiddleburyTest : public ::testing::Test {
 protected:
  void SetUp() override {
    const fs::path source = testing::TestDataDir() / "middlebury" / "dinoSparseRing";
    ASSERT_TRUE(fs::exists(source / "dinoSR_par.txt")) << "the data set is missing: " << source;
    auto imported = testing::RunCli("import middlebury '" + source.string() + "' --out '" +
                                    (dir_ / "dino").string() + "'");
    ASSERT_EQ(imported.exit_code, 0) << imported.output;
    const Take take = Take::Open(dir_ / "dino");
    ASSERT_TRUE(take.has_calibration());
    for (const StreamInfo& stream : take.streams()) {
      View view{stream.name, take.Camera(stream.name), take.ReadFrame(0, stream.name), {}};
      view.mask = ExtractSilhouette(view.image, cv::Mat(), DinoSilhouettes());
      views_.push_back(view);
    }
    ASSERT_EQ(views_.size(), 16u);
  }
  testing::TempDir dir_;
  std::vector<View> views_;
};

TEST_F(MiddleburyTest, HullOfFifteenViewsPredictsTheSixteenth) {
  const size_t held_out = 15;
  std::vector<View> training;
  for (size_t i = 0; i < views_.size(); ++i) {
    if (i != held_out) training.push_back(views_[i]);
  }
  HullOptions options;
  options.voxel_m = 0.0005;
  options.bounds = DinoBounds();
  // The object leaves the frame in some views: those views do not carve what they miss.
  options.min_views = 3;
  HullSummary summary;
  VisualHull hull = ComputeVisualHull(training, options, &summary);
  ASSERT_EQ(summary.termination, Termination::kSuccess) << summary.message;
  Mesh mesh = ExtractMesh(*hull.volume);
  cv::Mat predicted = RenderSilhouette(mesh, views_[held_out].camera);
  double iou = MaskIoU(predicted, views_[held_out].mask);
  std::printf(
      "dinoSparseRing: hull of 15 views (%.1f s, %zu triangles), IoU in held-out %s = %.4f\n",
      summary.seconds, mesh.faces.size(), views_[held_out].name.c_str(), iou);
  EXPECT_GE(iou, 0.95);
}

TEST_F(MiddleburyTest, CliReconstructsTheImportedTakeWithThresholdSilhouettes) {
  const std::string bounds = "-0.072,-0.029,-0.068,0.021,0.079,0.026";
  auto result = testing::RunCli("reconstruct '" + (dir_ / "dino").string() +
                                "' --method hull --silhouettes threshold --voxel 1mm --bounds " +
                                bounds + " --out '" + (dir_ / "recon").string() + "'");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  EXPECT_TRUE(fs::exists(dir_ / "recon" / "000000.glb"));
  Mesh mesh = ReadPly(dir_ / "recon" / "000000.ply");
  EXPECT_GT(mesh.faces.size(), 1000u);
  EXPECT_EQ(mesh.colors.size(), mesh.vertices.size());
}

// With no flags but the held-out camera, the plan finds the dinosaur itself: bounds from the
// cameras tightened by a coarse hull (the README's box is inside them, and they are not much
// larger), silhouettes by a threshold chosen per image (no clean plate), the visual hull; its
// silhouette predicts the held-out view's (recon_bench section 5 runs all 16 views).
TEST_F(MiddleburyTest, CliWithNoFlagsFindsTheObjectAndPredictsAHeldOutView) {
  const size_t held_out = 15;
  auto result =
      testing::RunCli("reconstruct '" + (dir_ / "dino").string() + "' --heldout-names " +
                      views_[held_out].name + " --no-glb --out '" + (dir_ / "auto").string() + "'");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  std::ifstream file(dir_ / "auto" / "report.json");
  const nlohmann::json report = nlohmann::json::parse(file);
  const nlohmann::json& plan = report["plan"];
  EXPECT_EQ(plan["method"], "hull") << plan["method_reason"];
  EXPECT_EQ(plan["silhouettes"]["source"], "otsu");
  EXPECT_EQ(plan["bounds"]["source"].get<std::string>().rfind("cameras + coarse hull", 0), 0u)
      << plan["bounds"];
  Box readme = DinoBounds();  // grown by 1 cm: back to the README's own box
  readme.min += Eigen::Vector3d::Constant(0.01);
  readme.max -= Eigen::Vector3d::Constant(0.01);
  for (int axis = 0; axis < 3; ++axis) {
    const double lo = plan["bounds"]["box"]["min"][axis].get<double>();
    const double hi = plan["bounds"]["box"]["max"][axis].get<double>();
    EXPECT_LE(lo, readme.min(axis) + 0.002) << "axis " << axis;
    EXPECT_GE(hi, readme.max(axis) - 0.002) << "axis " << axis;
    EXPECT_LT(hi - lo, 2 * (readme.max(axis) - readme.min(axis))) << "axis " << axis;
  }
  const double own = report["metrics"]["heldout_iou_mean"].get<double>();
  const Mesh mesh = ReadPly(dir_ / "auto" / "000000.ply");
  const double recipe =
      MaskIoU(RenderSilhouette(mesh, views_[held_out].camera), views_[held_out].mask);
  std::printf(
      "dinoSparseRing, no flags: held-out %s IoU %.4f (its Otsu silhouette), %.4f (the "
      "README's recipe)\n",
      views_[held_out].name.c_str(), own, recipe);
  EXPECT_GE(own, 0.9);
  EXPECT_GE(recipe, 0.9);
}

}  // namespace
}  // namespace holocap
