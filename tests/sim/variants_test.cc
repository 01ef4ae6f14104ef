// The simulator's variants of a capture a user brings: a scaled and turned world changes only
// the numbers that describe the take (the images are the same), a dark scene darkens the
// subject and the room by the factors asked for, alpha carries the exact silhouette, and a
// colour-only rig has no depth sensor.
#include <gtest/gtest.h>

#include <cmath>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "core/image.h"
#include "core/mesh.h"
#include "core/take.h"
#include "sim/sim.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;
using testing::TempDir;

// A small studio8 take: a clean plate, then the walking subject.
SimOptions SmallStudio() {
  SimOptions options;
  options.frames = 2;
  options.clean_plate_frames = 1;
  options.image_width = 96;
  options.seed = 5;
  options.threads = 2;
  return options;
}

Take Simulate(const SimOptions& options, const fs::path& dir) {
  const SimSummary summary = SimulateTake(options, dir);
  EXPECT_EQ(summary.termination, Termination::kSuccess) << summary.message;
  return Take::Open(dir);
}

double MaxAbsDiff(const cv::Mat& a, const cv::Mat& b) {
  EXPECT_EQ(a.size(), b.size());
  EXPECT_EQ(a.type(), b.type());
  cv::Mat diff;
  cv::absdiff(a, b, diff);
  double most = 0;
  cv::minMaxIdx(diff.reshape(1), nullptr, &most);
  return most;
}

// Scale 0.05 and up -y: every camera centre, mesh vertex and depth is the base take's mapped by
// p -> 0.05 R p (R: +z to -y), and every image and silhouette is the same, bit for bit.
TEST(SimVariantsTest, AScaledTurnedWorldChangesOnlyTheNumbers) {
  TempDir dir;
  const Take base = Simulate(SmallStudio(), dir / "base");
  SimOptions options = SmallStudio();
  options.world_scale = 0.05;
  options.up = -Eigen::Vector3d::UnitY();
  const Take variant = Simulate(options, dir / "variant");
  const Eigen::Matrix3d turn =
      Eigen::AngleAxisd(0.5 * M_PI, Eigen::Vector3d::UnitX()).toRotationMatrix();
  ASSERT_NEAR((turn * Eigen::Vector3d::UnitZ() + Eigen::Vector3d::UnitY()).norm(), 0, 1e-12);
  auto map = [&](const Eigen::Vector3d& p) { return Eigen::Vector3d(0.05 * (turn * p)); };

  const Mesh base_mesh = ReadPly(base.gt_dir() / "meshes" / "000001.ply");
  const Mesh variant_mesh = ReadPly(variant.gt_dir() / "meshes" / "000001.ply");
  ASSERT_EQ(base_mesh.vertices.size(), variant_mesh.vertices.size());
  double mesh_error = 0;
  for (size_t i = 0; i < base_mesh.vertices.size(); ++i) {
    mesh_error = std::max(mesh_error, (map(base_mesh.vertices[i].cast<double>()) -
                                       variant_mesh.vertices[i].cast<double>())
                                          .norm());
  }
  EXPECT_LT(mesh_error, 1e-6);

  for (const StreamInfo& stream : base.streams()) {
    SCOPED_TRACE(stream.name);
    const CameraModel a = base.Camera(stream.name, true);
    const CameraModel b = variant.Camera(stream.name, true);
    EXPECT_LT((map(a.center_in_world()) - b.center_in_world()).norm(), 1e-9);
    // A vertex of the subject projects to the same pixel in both worlds.
    const Eigen::Vector3d point = base_mesh.vertices[0].cast<double>();
    Eigen::Vector2d pa, pb;
    ASSERT_EQ(a.ProjectWorld(point, &pa), b.ProjectWorld(map(point), &pb));
    EXPECT_LT((pa - pb).norm(), 1e-6);
    for (size_t set : {0, 1}) {
      const cv::Mat fa = base.ReadFrame(set, stream.name);
      const cv::Mat fb = variant.ReadFrame(set, stream.name);
      if (stream.role == SensorRole::kDepth) {
        cv::Mat scaled = fa * 0.05;
        cv::patchNaNs(scaled, 0);
        cv::Mat other = fb.clone();
        cv::patchNaNs(other, 0);
        EXPECT_LT(MaxAbsDiff(scaled, other), 1e-6);
      } else {
        EXPECT_EQ(MaxAbsDiff(fa, fb), 0);
      }
    }
  }
}

// --dark: the subject's pixels at about half their brightness, the room's at about a tenth.
TEST(SimVariantsTest, DarkScalesTheSubjectAndTheRoom) {
  TempDir dir;
  SimOptions options = SmallStudio();
  options.noise = false;
  const Take base = Simulate(options, dir / "base");
  options.subject_albedo = 0.5;
  options.background_albedo = 0.1;
  const Take dark = Simulate(options, dir / "dark");
  const cv::Mat mask = ReadImage(base.gt_dir() / "masks" / "cam3" / "000001.png");
  cv::Mat inner, background;
  cv::erode(mask, inner, cv::Mat::ones(3, 3, CV_8U));
  cv::dilate(mask, background, cv::Mat::ones(3, 3, CV_8U));
  background = background == 0;
  ASSERT_GT(cv::countNonZero(inner), 50);
  auto mean = [](const cv::Mat& image, const cv::Mat& where) {
    const cv::Scalar m = cv::mean(image, where);
    return (m[0] + m[1] + m[2]) / 3;
  };
  const cv::Mat a = base.ReadFrame(1, "cam3"), b = dark.ReadFrame(1, "cam3");
  EXPECT_NEAR(mean(b, inner) / mean(a, inner), 0.5, 0.03);
  EXPECT_NEAR(mean(b, background) / mean(a, background), 0.1, 0.02);
}

// --alpha: colour streams bgra8, colour the same as without alpha, alpha the true silhouette;
// --color-only: no depth sensor in the take.
TEST(SimVariantsTest, AlphaCarriesTheTrueSilhouetteAndColourOnlyHasNoDepth) {
  TempDir dir;
  SimOptions options = SmallStudio();
  options.color_only = true;
  const Take base = Simulate(options, dir / "base");
  options.alpha = true;
  const Take alpha = Simulate(options, dir / "alpha");
  int colour = 0;
  for (const StreamInfo& stream : alpha.streams()) {
    SCOPED_TRACE(stream.name);
    ASSERT_EQ(stream.role, SensorRole::kColor);
    ++colour;
    EXPECT_EQ(stream.pixel_format, "bgra8");
    const cv::Mat frame = alpha.ReadFrame(1, stream.name);
    ASSERT_EQ(frame.type(), CV_8UC4);
    std::vector<cv::Mat> channels;
    cv::split(frame, channels);
    const cv::Mat truth = ReadImage(alpha.gt_dir() / "masks" / stream.name / "000001.png");
    EXPECT_EQ(MaxAbsDiff(channels[3], truth), 0);
    EXPECT_GT(cv::countNonZero(truth), 0);
    cv::Mat bgr;
    cv::merge(std::vector<cv::Mat>(channels.begin(), channels.begin() + 3), bgr);
    EXPECT_EQ(MaxAbsDiff(bgr, base.ReadFrame(1, stream.name)), 0);
  }
  EXPECT_EQ(colour, 8);
}

}  // namespace
}  // namespace holocap
