// `holocap export web` scored against the camera: a mesh stream drawn through camera cam1, held
// out of the reconstruction, against cam1's captured image inside the subject's true silhouette
// (report.json, per stream), and the export's check that ends a stream no closer to the camera
// than the clean plate alone DEGENERATE: the same meshes with their atlas painted one flat
// colour.
#include <gtest/gtest.h>

#include <nlohmann/json.hpp>

#include "core/fs.h"
#include "core/report.h"
#include "playback/playback.h"
#include "reconstruction/reconstruction.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;
using testing::RunCli;
using testing::TempDir;

class WebCameraTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new TempDir("holocap-web-camera");
    auto sim = RunCli("sim --rig studio8 --frames 2 --clean-plate 1 --size 128 --seed 8 --out '" +
                      Take().string() + "'");
    ASSERT_EQ(sim.exit_code, 0) << sim.output;
    auto recon = RunCli("reconstruct '" + Take().string() +
                        "' --voxel 8mm --no-sweep --heldout-names cam1 --ground-truth-cameras");
    ASSERT_EQ(recon.exit_code, 0) << recon.output;
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }
  static fs::path Take() { return dir_->path() / "take"; }
  static WebExportOptions Options(const fs::path& recon) {
    WebExportOptions options;
    options.qualities = {"low"};
    options.recon = recon;
    options.take.ground_truth_cameras = true;
    return options;
  }
  static TempDir* dir_;
};
TempDir* WebCameraTest::dir_ = nullptr;

TEST_F(WebCameraTest, MeshesBeatTheCleanPlateInTheHeldOutCamera) {
  Report report("export web");
  const fs::path site = dir_->path() / "site";
  const WebExportSummary summary = ExportWebSite(Take(), site, Options(Take() / "recon"), &report);
  ASSERT_EQ(summary.termination, Termination::kSuccess) << summary.message;
  const auto camera = nlohmann::json::parse(ReadFileToString(site / "report.json"))
                          .at("metrics")
                          .at("streams")
                          .at("mesh-low")
                          .at("camera");
  EXPECT_EQ(camera.at("heldout"), nlohmann::json({"cam1"}));
  EXPECT_GT(camera.at("pixels").get<int64_t>(), 100);
  // The subject's colours: well above the plate alone, and the low level close to the native.
  EXPECT_GT(camera.at("native_psnr_db").get<double>(),
            camera.at("background_psnr_db").get<double>() + 3.0);
  EXPECT_GT(camera.at("streamed_psnr_db").get<double>(),
            camera.at("native_psnr_db").get<double>() - 1.0);
  // The page draws the clean plate behind the subject through every capture camera.
  const auto manifest = nlohmann::json::parse(ReadFileToString(site / "manifest.json"));
  const auto& backgrounds = manifest.at("streams").at(0).at("backgrounds");
  EXPECT_EQ(backgrounds.size(), 8u);
  EXPECT_TRUE(fs::is_regular_file(site / backgrounds.at("cam1").get<std::string>()));
}

TEST_F(WebCameraTest, AStreamNoBetterThanTheBackgroundIsDegenerate) {
  // The same meshes with a flat magenta atlas: the subject's shape, none of its colours.
  const fs::path painted = dir_->path() / "painted";
  CreateDirectories(painted);
  for (const auto& entry : fs::directory_iterator(Take() / "recon")) {
    if (entry.path().extension() != ".glb") continue;
    const TexturedMeshFrame frame = ReadTexturedGlb(entry.path());
    TexturedMesh textured;
    for (size_t k = 0; k < frame.positions.size(); ++k) {
      textured.mesh.vertices.push_back(frame.positions[k]);
      textured.mesh.colors.push_back({255, 0, 255});
    }
    for (size_t f = 0; f < frame.faces(); ++f) {
      const int k = static_cast<int>(3 * f);
      textured.mesh.faces.emplace_back(k, k + 1, k + 2);
    }
    textured.mesh.ComputeNormals();
    WriteGlb(painted / entry.path().filename(), textured);
  }
  fs::copy_file(Take() / "recon" / "report.json", painted / "report.json");
  Report report("export web");
  const fs::path site = dir_->path() / "painted-site";
  const WebExportSummary summary = ExportWebSite(Take(), site, Options(painted), &report);
  EXPECT_EQ(summary.termination, Termination::kDegenerate) << summary.message;
  EXPECT_NE(summary.message.find("mesh-low"), std::string::npos) << summary.message;
  EXPECT_NE(summary.message.find("no better than the background alone"), std::string::npos)
      << summary.message;
  // The site is still written, its report saying why it is not usable.
  EXPECT_TRUE(fs::exists(site / "manifest.json"));
  const auto written = nlohmann::json::parse(ReadFileToString(site / "report.json"));
  EXPECT_EQ(written.at("summary").at("termination"), "DEGENERATE");
}

}  // namespace
}  // namespace holocap
