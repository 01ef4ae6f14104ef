// A simulated take exported to COLMAP and NeRF and imported back equals the true cameras;
// cameras a format cannot hold are refused by name. Runs the CLI end to end.
#include <gtest/gtest.h>

#include <algorithm>
#include <set>

#include "core/error.h"
#include "core/take.h"
#include "interop/interop.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::RunCli;
using testing::TempDir;

// Largest differences between two models: relative intrinsics, pose, and projections of points
// spread through the camera's view.
struct ModelDifference {
  double intrinsics = 0;
  double rotation_deg = 0;
  double translation_m = 0;
  double pixel = 0;
};

ModelDifference Compare(const CameraModel& a, const CameraModel& b) {
  ModelDifference d;
  EXPECT_EQ(a.lensmodel(), b.lensmodel());
  EXPECT_EQ(a.width(), b.width());
  EXPECT_EQ(a.height(), b.height());
  if (a.intrinsics().size() != b.intrinsics().size()) {
    d.intrinsics = 1e300;
    return d;
  }
  for (size_t i = 0; i < a.intrinsics().size(); ++i) {
    d.intrinsics = std::max(d.intrinsics, std::abs(a.intrinsics()[i] - b.intrinsics()[i]) /
                                              std::max(1.0, std::abs(a.intrinsics()[i])));
  }
  Pose delta = a.cam_from_world() * b.cam_from_world().inverse();
  d.rotation_deg = RotationAngleDeg(delta.linear());
  d.translation_m = (a.cam_from_world().translation() - b.cam_from_world().translation()).norm();
  for (double u : {0.1, 0.5, 0.9})
    for (double v : {0.1, 0.5, 0.9})
      for (double depth : {0.5, 3.0}) {
        Eigen::Vector3d ray =
            a.Unproject(Eigen::Vector2d(u * (a.width() - 1), v * (a.height() - 1)));
        Eigen::Vector3d point = a.world_from_cam() * (depth * ray / ray.z());
        Eigen::Vector2d pa, pb;
        EXPECT_TRUE(a.ProjectWorld(point, &pa));
        EXPECT_TRUE(b.ProjectWorld(point, &pb));
        d.pixel = std::max(d.pixel, (pa - pb).norm());
      }
  return d;
}

class InteropRoundTrip : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new TempDir("holocap-interop");
    auto result = RunCli("sim --rig studio8 --frames 2 --size 96 --no-noise --out '" +
                         (dir_->path() / "sim").string() + "'");
    ASSERT_EQ(result.exit_code, 0) << result.output;
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }
  static std::filesystem::path Sim() { return dir_->path() / "sim"; }
  static std::filesystem::path Path(const std::string& name) { return dir_->path() / name; }

  // Exports with --skip-unrepresentable, re-imports, and compares every exported camera with
  // the take's true one. Returns the cameras compared.
  int RoundTrip(const std::string& format, const std::set<std::string>& expected_lenses) {
    auto exported =
        RunCli("export " + format + " '" + Sim().string() +
               "' --ground-truth --skip-unrepresentable --out '" + Path(format).string() + "'");
    EXPECT_EQ(exported.exit_code, 0) << exported.output;
    auto imported = RunCli("import " + format + " '" + Path(format).string() + "' --out '" +
                           Path(format + "-take").string() + "'");
    EXPECT_EQ(imported.exit_code, 0) << imported.output;
    Take original = Take::Open(Sim());
    Take back = Take::Open(Path(format + "-take"));
    int compared = 0;
    double worst_intrinsics = 0, worst_rotation = 0, worst_translation = 0, worst_pixel = 0;
    for (const auto& stream : back.streams()) {
      CameraModel truth = original.Camera(stream.name, true);
      EXPECT_TRUE(expected_lenses.count(truth.lensmodel()))
          << stream.name << " " << truth.lensmodel();
      ModelDifference d = Compare(truth, back.Camera(stream.name));
      worst_intrinsics = std::max(worst_intrinsics, d.intrinsics);
      worst_rotation = std::max(worst_rotation, d.rotation_deg);
      worst_translation = std::max(worst_translation, d.translation_m);
      worst_pixel = std::max(worst_pixel, d.pixel);
      // The frames come back bit for bit, in the same sets.
      EXPECT_EQ(back.size(), original.size());
      for (size_t i = 0; i < std::min(back.size(), original.size()); ++i) {
        cv::Mat a = original.ReadFrame(i, stream.name), b = back.ReadFrame(i, stream.name);
        EXPECT_EQ(cv::countNonZero(a.reshape(1) != b.reshape(1)), 0) << stream.name << " set " << i;
      }
      ++compared;
    }
    EXPECT_LT(worst_intrinsics, 1e-12) << format;
    EXPECT_LT(worst_rotation, 1e-9) << format;
    EXPECT_LT(worst_translation, 1e-12) << format;
    EXPECT_LT(worst_pixel, 1e-9) << format;
    std::printf(
        "%s round trip: %d cameras, worst intrinsics %.3g (relative), rotation %.3g deg, "
        "translation %.3g m, projection %.3g px\n",
        format.c_str(), compared, worst_intrinsics, worst_rotation, worst_translation, worst_pixel);
    return compared;
  }

  static TempDir* dir_;
};

TempDir* InteropRoundTrip::dir_ = nullptr;

TEST_F(InteropRoundTrip, ColmapHoldsEveryOpenCvLensExactly) {
  EXPECT_EQ(RoundTrip("colmap", {"LENSMODEL_OPENCV4", "LENSMODEL_OPENCV5", "LENSMODEL_OPENCV8"}),
            7);
}

TEST_F(InteropRoundTrip, NerfHoldsOpenCv4And5Exactly) {
  EXPECT_EQ(RoundTrip("nerf", {"LENSMODEL_OPENCV4", "LENSMODEL_OPENCV5"}), 4);
}

TEST_F(InteropRoundTrip, CamerasAFormatLacksAreRefusedByName) {
  auto colmap = RunCli("export colmap '" + Sim().string() + "' --ground-truth --out '" +
                       Path("refused-colmap").string() + "'");
  EXPECT_NE(colmap.exit_code, 0);
  EXPECT_NE(
      colmap.output.find("holocap: error: 1 camera(s) cannot be exported exactly to colmap: cam1 "
                         "(lens model LENSMODEL_STEREOGRAPHIC"),
      std::string::npos)
      << colmap.output;
  auto nerf = RunCli("export nerf '" + Sim().string() + "' --ground-truth --out '" +
                     Path("refused-nerf").string() + "'");
  EXPECT_NE(nerf.exit_code, 0);
  EXPECT_NE(nerf.output.find("4 camera(s) cannot be exported exactly to nerf"), std::string::npos)
      << nerf.output;
  EXPECT_NE(nerf.output.find("OPENCV8's rational terms"), std::string::npos) << nerf.output;
  // Nothing was written.
  EXPECT_FALSE(std::filesystem::exists(Path("refused-nerf") / "transforms.json"));
  // A take without calibration says so.
  auto uncalibrated = RunCli("export colmap '" + Sim().string() + "' --out '" +
                             Path("uncalibrated").string() + "'");
  EXPECT_NE(uncalibrated.exit_code, 0);
  EXPECT_NE(uncalibrated.output.find("has no calibration for"), std::string::npos)
      << uncalibrated.output;
}

TEST_F(InteropRoundTrip, BadCommandLinesGiveOneErrorLine) {
  for (const std::string& args :
       {std::string("import bogus x --out y"),
        "import colmap /nonexistent --out " + Path("x").string(),
        "export krt " + Sim().string() + " --out " + Path("y").string()}) {
    auto result = RunCli(args);
    EXPECT_NE(result.exit_code, 0) << args;
    EXPECT_EQ(result.output.rfind("holocap: error: ", 0), 0u) << args << "\n" << result.output;
    EXPECT_EQ(std::count(result.output.begin(), result.output.end(), '\n'), 1) << result.output;
  }
}

}  // namespace
}  // namespace holocap
