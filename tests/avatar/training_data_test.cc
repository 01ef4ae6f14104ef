// The training data's thresholded silhouettes (what Neural Volumes and splats train against
// and are scored inside) close as reconstruction closes them: the radius measured on the
// boundaries, none where they are clean, not one dataset's recipe.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "avatar/training_data.h"
#include "reconstruction/reconstruction.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;
using testing::RunCli;
using testing::TempDir;

// The frames' Otsu silhouettes closed by a disk of `close_px` (0: no morphology at all).
cv::Mat Closed(const cv::Mat& image, int close_px) {
  SilhouetteOptions options;
  options.mode = SilhouetteMode::kOtsu;
  options.open_px = 0;
  options.dilate_px = options.erode_px = close_px;
  return ExtractSilhouette(image, cv::Mat(), options);
}
cv::Mat Unclosed(const cv::Mat& image) { return Closed(image, 0); }

// The dark object ring (colour only, no plate, so Otsu's silhouettes): clean boundaries take no
// closing, where the Middlebury recipe grew every silhouette by a rim; with holes and a crack
// cut into the views the training data closes by the radius reconstruction measures on the
// same take.
TEST(TrainingData, ThresholdedSilhouettesCloseAsReconstructionMeasuresNotByARecipe) {
  TempDir dir;
  const fs::path take = dir / "ring";
  const auto sim = RunCli(
      "sim --rig studio8 --size 320 --seed 3 --frames 1 --color-only --world-scale 0.05 --dark "
      "--out '" +
      take.string() + "'");
  ASSERT_EQ(sim.exit_code, 0) << sim.output;
  TrainingDataOptions options;
  options.image_width = 0;                // native: the pixels reconstruction measures
  options.take = testing::TrueCameras();  // the silhouettes measured apart from calibration
  const TrainingData clean = LoadTrainingData(take, options);
  ASSERT_TRUE(clean.plan.contains("silhouette_morphology")) << clean.plan.dump();
  EXPECT_EQ(clean.plan["silhouette_morphology"]["chosen"], "none") << clean.plan.dump();
  for (size_t v = 0; v < clean.views.size(); ++v)
    EXPECT_EQ(cv::norm(clean.masks[0][v], Unclosed(clean.images[0][v]), cv::NORM_INF), 0)
        << clean.views[v].name;

  testing::CutHolesAndCrack(take);
  const TrainingData ragged = LoadTrainingData(take, options);
  const std::string chosen = ragged.plan["silhouette_morphology"]["chosen"];
  const auto recon =
      RunCli("reconstruct '" + take.string() + "' --out '" + (dir / "recon").string() +
             "' --ground-truth-cameras --no-sweep --no-glb");
  ASSERT_EQ(recon.exit_code, 0) << recon.output;
  std::ifstream file(dir / "recon" / "report.json");
  const nlohmann::json report = nlohmann::json::parse(file);
  const nlohmann::json& measured = report["plan"]["silhouettes"]["morphology"];
  const int close_px = measured["measured"]["close_px"];
  EXPECT_GE(close_px, 2) << measured;  // a 2 px crack needs a disk 5 px across
  EXPECT_EQ(chosen, "closing " + std::to_string(close_px) + " px") << ragged.plan.dump();
  // Closed by that radius and no more (no growth), each training silhouette holds its unclosed
  // one and fills what the cuts took.
  for (size_t v = 0; v < ragged.views.size(); ++v) {
    EXPECT_EQ(cv::norm(ragged.masks[0][v], Closed(ragged.images[0][v], close_px), cv::NORM_INF), 0)
        << ragged.views[v].name;
    const cv::Mat unclosed = Unclosed(ragged.images[0][v]);
    cv::Mat lost;
    cv::subtract(unclosed, ragged.masks[0][v], lost);
    EXPECT_EQ(cv::countNonZero(lost), 0) << ragged.views[v].name;
    EXPECT_GT(cv::countNonZero(ragged.masks[0][v]), cv::countNonZero(unclosed))
        << ragged.views[v].name;
  }
}

}  // namespace
}  // namespace holocap
