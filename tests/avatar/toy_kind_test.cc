// A new avatar kind is one folder (tests/avatar/toy_kind/) and one registration line: once
// registered, the toy ball opens by its model.json like any kind, renders through playback's
// camera paths and streams in a web site, with nothing else changed.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>

#include "avatar/avatar.h"
#include "core/error.h"
#include "playback/playback.h"
#include "tests/avatar/toy_kind/toy_kind.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::RunCli;
using testing::TempDir;

const Eigen::Vector3d kCenter(0, 0, 1.0);
const Eigen::Vector3d kBgr(0.2, 0.5, 0.8);

TEST(ToyAvatarKind, UnknownUntilRegisteredThenOpensByItsModelJson) {
  TempDir dir("holocap-toy-kind");
  toy::WriteToyModel(dir.path() / "ball", kCenter, 0.3, kBgr);
  AvatarKindRegistry registry;
  try {
    registry.Open(dir.path() / "ball");
    FAIL() << "an unregistered kind opened";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("unknown model method 'toy'"), std::string::npos)
        << e.what();
  }
  toy::RegisterToyAvatarKind(registry);  // the one line a new kind adds
  EXPECT_TRUE(registry.has("toy"));
  auto model = registry.Open(dir.path() / "ball");
  EXPECT_EQ(model->method(), "toy");
  EXPECT_NEAR(model->box().size().x(), 0.6, 1e-12);
}

// Rendered along an orbit by playback, every view shows the ball in its colour at its centre
// and nothing in the corners; the depth at the centre is the distance to the ball's surface.
TEST(ToyAvatarKind, RendersAlongAnOrbit) {
  TempDir dir("holocap-toy-kind");
  toy::WriteToyModel(dir.path() / "ball", kCenter, 0.3, kBgr);
  toy::RegisterToyAvatarKind(AvatarKindRegistry::Global());
  auto model = OpenModel(dir.path() / "ball");
  OrbitOptions orbit;
  orbit.views = 6;
  orbit.width = 64;
  orbit.height = 48;
  const CameraPath path = OrbitPath(*model, orbit);
  PlaybackOptions playback;
  playback.out = dir.path() / "frames";
  const PlaybackSummary summary = RenderPath(*model, path, playback);
  ASSERT_TRUE(summary.IsUsable()) << summary.message;
  EXPECT_EQ(summary.views, 6);
  for (size_t v = 0; v < path.size(); ++v) {
    const RenderedView view = model->Render(path.cameras[v], 0, {});
    Eigen::Vector2d pixel;
    ASSERT_TRUE(path.cameras[v].ProjectWorld(kCenter, &pixel));
    const cv::Vec3f centre =
        view.color.at<cv::Vec3f>(static_cast<int>(pixel.y()), static_cast<int>(pixel.x()));
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(centre[c], kBgr[c], 1e-6) << "view " << v;
    EXPECT_EQ(view.alpha.at<float>(0, 0), 0.0f) << "view " << v;
    const double distance = (path.cameras[v].center_in_world() - kCenter).norm();
    EXPECT_NEAR(view.depth.at<float>(static_cast<int>(pixel.y()), static_cast<int>(pixel.x())),
                distance - 0.3, 0.02)
        << "view " << v;
  }
  EXPECT_TRUE(std::filesystem::exists(dir.path() / "frames" / "000000.png"));
}

// Exported into a web site beside a simulated take, the ball is one volume stream whose decoded
// chunks match the uncompressed ball.
TEST(ToyAvatarKind, StreamsInAWebSite) {
  TempDir dir("holocap-toy-kind");
  const auto sim =
      RunCli("sim --rig studio8 --scene object --frames 1 --size 160 --seed 3 --out '" +
             (dir.path() / "take").string() + "'");
  ASSERT_EQ(sim.exit_code, 0) << sim.output;
  toy::WriteToyModel(dir.path() / "ball", kCenter, 0.3, kBgr);
  toy::RegisterToyAvatarKind(AvatarKindRegistry::Global());
  WebExportOptions options;
  options.models = {dir.path() / "ball"};
  options.meshes = false;
  options.take.ground_truth_cameras = true;
  const WebExportSummary summary = ExportWebSite(dir.path() / "take", dir.path() / "site", options);
  ASSERT_TRUE(summary.IsUsable()) << summary.message;
  ASSERT_EQ(summary.streams.size(), 1u);
  EXPECT_EQ(summary.streams[0].kind, "volume");
  EXPECT_EQ(summary.streams[0].name, "toy-medium");
  EXPECT_GT(summary.streams[0].psnr_db, 30) << "decoded against uncompressed";
  EXPECT_TRUE(std::filesystem::exists(dir.path() / "site" / "manifest.json"));
}

}  // namespace
}  // namespace holocap
