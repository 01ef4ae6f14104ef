// Playback of a trained model: orbit and JSON camera paths, PNG/EXR frames, MP4 through
// ffmpeg, skipping that changes no pixel, and the `holocap render` command.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>

#include "core/error.h"
#include "core/image.h"
#include "neural/neural.h"
#include "playback/playback.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

// The avatar kinds these tests open.
const bool kAvatarKindsRegistered = [] {
  RegisterNeuralVolumeAvatarKind(AvatarKindRegistry::Global());
  return true;
}();

using testing::RunCli;
using testing::RunShell;
using testing::TempDir;

class PlaybackTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new TempDir("holocap-playback");
    auto sim = RunCli(
        "sim --rig studio8 --scene object --frames 2 --clean-plate 1 --size 160 --seed 6 --out '" +
        (dir_->path() / "take").string() + "'");
    ASSERT_EQ(sim.exit_code, 0) << sim.output;
    NeuralVolumeOptions options;
    options.take.ground_truth_cameras = true;
    options.grid = 32;
    options.image_width = 96;
    options.iterations = 250;
    options.eval_every_s = 1000;
    NeuralVolumeSummary summary =
        TrainNeuralVolume(dir_->path() / "take", dir_->path() / "model", options);
    ASSERT_TRUE(IsUsable(summary.termination)) << summary.message;
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }
  static std::filesystem::path Dir() { return dir_->path(); }
  static TempDir* dir_;
};
TempDir* PlaybackTest::dir_ = nullptr;

TEST_F(PlaybackTest, OrbitCirclesTheBoxAndLooksAtItsCentre) {
  auto model = OpenModel(Dir() / "model");
  OrbitOptions orbit;
  orbit.views = 12;
  orbit.width = 64;
  orbit.height = 48;
  CameraPath path = OrbitPath(*model, orbit);
  ASSERT_EQ(path.size(), 12u);
  const Eigen::Vector3d center = model->box().center();
  const Eigen::Vector3d up = ModelUp(*model);
  EXPECT_GT(up.z(), 0.9);  // studio8's cameras stand upright in a z-up world
  double radius0 = -1;
  for (const auto& camera : path.cameras) {
    Eigen::Vector2d pixel;
    ASSERT_TRUE(camera.ProjectWorld(center, &pixel));
    EXPECT_NEAR(pixel.x(), 31.5, 1e-6);
    EXPECT_NEAR(pixel.y(), 23.5, 1e-6);
    const Eigen::Vector3d offset = camera.center_in_world() - center;
    const double radius = (offset - offset.dot(up) * up).norm();
    if (radius0 < 0) radius0 = radius;
    EXPECT_NEAR(radius, radius0, 1e-9);
  }
  // Consecutive views are 30 degrees apart.
  const Eigen::Vector3d a = path.cameras[0].center_in_world() - center,
                        b = path.cameras[1].center_in_world() - center;
  const Eigen::Vector3d fa = a - a.dot(up) * up, fb = b - b.dot(up) * up;
  EXPECT_NEAR(std::acos(fa.normalized().dot(fb.normalized())) * 180 / M_PI, 30.0, 1e-6);
  orbit.width = 63;
  EXPECT_THROW(OrbitPath(*model, orbit), Error);
}

TEST_F(PlaybackTest, JsonPathInterpolatesKeysAndReadsCameraModels) {
  auto model = OpenModel(Dir() / "model");
  const auto file = Dir() / "path.json";
  std::ofstream(file) << R"({"fps": 24, "views": 5, "keys": [
      {"eye": [3, 0, 1.5], "look_at": [0, 0, 0.8], "fov_deg": 40, "frame": 0},
      {"eye": [0, 3, 1.5], "look_at": [0, 0, 0.8], "fov_deg": 60, "frame": 0}]})";
  CameraPath path = ReadCameraPath(file, *model, 64, 48);
  ASSERT_EQ(path.size(), 5u);
  EXPECT_EQ(path.fps, 24);
  EXPECT_LT((path.cameras[0].center_in_world() - Eigen::Vector3d(3, 0, 1.5)).norm(), 1e-9);
  EXPECT_LT((path.cameras[2].center_in_world() - Eigen::Vector3d(1.5, 1.5, 1.5)).norm(), 1e-9);
  EXPECT_LT((path.cameras[4].center_in_world() - Eigen::Vector3d(0, 3, 1.5)).norm(), 1e-9);
  // The middle key's focal length is the one of a 50-degree field of view.
  EXPECT_NEAR(path.cameras[2].intrinsics()[0], 32.0 / std::tan(25 * M_PI / 180), 1e-6);

  // Keys through real lens models (distortion kept), rescaled to the output width.
  const CameraModel lens = model->cameras().front();
  lens.Write(Dir() / "lens.cameramodel");
  std::ofstream(Dir() / "lens.json")
      << R"({"keys": [{"cameramodel": "lens.cameramodel", "frame": 0}]})";
  CameraPath through = ReadCameraPath(Dir() / "lens.json", *model, 48, 36);
  ASSERT_EQ(through.size(), 1u);
  EXPECT_EQ(through.cameras[0].lensmodel(), lens.lensmodel());
  EXPECT_EQ(through.cameras[0].width(), 48);

  std::ofstream(Dir() / "bad.json") << R"({"keys": [{"eye": [1, 2], "look_at": [0, 0, 0]}]})";
  try {
    ReadCameraPath(Dir() / "bad.json", *model, 64, 48);
    FAIL() << "a malformed key was accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("eye"), std::string::npos) << e.what();
  }
}

TEST_F(PlaybackTest, FramesHoldColourAlphaAndDepthAndSkippingChangesNoPixel) {
  auto model = OpenModel(Dir() / "model");
  OrbitOptions orbit;
  orbit.views = 3;
  orbit.width = 96;
  orbit.height = 72;
  CameraPath path = OrbitPath(*model, orbit);
  PlaybackOptions options;
  options.out = Dir() / "frames";
  PlaybackSummary summary = RenderPath(*model, path, options);
  ASSERT_TRUE(IsUsable(summary.termination));
  EXPECT_EQ(summary.views, 3);
  EXPECT_GT(summary.render_fps, 0);
  cv::Mat png = ReadImage(options.out / "000002.png");
  ASSERT_EQ(png.type(), CV_8UC4);
  double alpha_sum = 0;
  for (int y = 0; y < png.rows; ++y)
    for (int x = 0; x < png.cols; ++x) alpha_sum += png.at<cv::Vec4b>(y, x)[3];
  EXPECT_GT(alpha_sum / (255.0 * png.total()), 0.01);  // the object covers part of the view
  EXPECT_LT(alpha_sum / (255.0 * png.total()), 0.9);
  ASSERT_TRUE(std::filesystem::exists(options.out / "000002.exr"));
  EXPECT_GT(std::filesystem::file_size(options.out / "000002.exr"), 1000u);
  RenderedView skipped = model->Render(path.cameras[1], 0, {});
  ViewRenderOptions no_skip;
  no_skip.skip_empty = false;
  RenderedView full = model->Render(path.cameras[1], 0, no_skip);
  EXPECT_LT(skipped.samples_per_ray, full.samples_per_ray);
  double worst = 0;
  for (int y = 0; y < full.alpha.rows; ++y) {
    for (int x = 0; x < full.alpha.cols; ++x) {
      worst = std::max(worst, static_cast<double>(std::abs(full.alpha.at<float>(y, x) -
                                                           skipped.alpha.at<float>(y, x))));
    }
  }
  EXPECT_LT(worst, 1e-5);
}

TEST_F(PlaybackTest, CliRendersAnOrbitVideo) {
  const auto video = Dir() / "orbit.mp4";
  auto result =
      RunCli("render '" + (Dir() / "take").string() + "' --model '" + (Dir() / "model").string() +
             "' --path orbit --size 64 --views 8 --out '" + video.string() + "'");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  EXPECT_NE(result.output.find("fps"), std::string::npos);
  ASSERT_TRUE(std::filesystem::exists(video));
  auto probe = RunShell(
      "ffprobe -v error -count_frames -select_streams v:0 -show_entries "
      "stream=nb_read_frames,width "
      "-of csv=p=0 '" +
      video.string() + "'");
  EXPECT_NE(probe.output.find("64,8"), std::string::npos) << probe.output;
  auto missing = RunCli("render '" + (Dir() / "take").string() + "' --model '" +
                        (Dir() / "nope").string() + "' --out '" + (Dir() / "x").string() + "'");
  EXPECT_NE(missing.exit_code, 0);
  EXPECT_NE(missing.output.find("holocap: error: no model"), std::string::npos) << missing.output;
}

// A dynamic model plays back from one world-space grid per frame, the template resampled
// through the warp: its image stays within 40 dB PSNR (colour and alpha, where either render
// covers) of marching warp + template, and its skipping changes no pixel.
TEST(PlaybackDynamicTest, BakedFramesRenderLikeWarpAndTemplate) {
  TempDir dir("holocap-playback-dynamic");
  auto sim = RunCli("sim --rig studio8 --frames 3 --clean-plate 1 --size 128 --seed 8 --out '" +
                    (dir.path() / "take").string() + "'");
  ASSERT_EQ(sim.exit_code, 0) << sim.output;
  NeuralVolumeOptions options;
  options.take.ground_truth_cameras = true;
  options.grid = 32;
  options.image_width = 64;
  options.latent_dim = 32;
  options.decoder_channels = 32;
  options.warp_grid = 16;
  options.rays_per_batch = 1024;
  options.iterations = 60;
  options.eval_every_s = 1000;
  NeuralVolumeSummary summary =
      TrainNeuralVolume(dir.path() / "take", dir.path() / "model", options);
  ASSERT_TRUE(IsUsable(summary.termination)) << summary.message;
  ASSERT_TRUE(summary.built_warp);
  auto model = OpenModel(dir.path() / "model");
  OrbitOptions orbit;
  orbit.views = 3;
  orbit.width = 96;
  orbit.height = 72;
  CameraPath path = OrbitPath(*model, orbit);
  ViewRenderOptions direct_options;
  direct_options.bake = false;
  for (size_t i = 0; i < path.size(); ++i) {
    const RenderedView baked = model->Render(path.cameras[i], path.frames[i], {});
    const RenderedView direct = model->Render(path.cameras[i], path.frames[i], direct_options);
    double squared = 0, alpha_sum = 0;
    int64_t covered = 0;
    for (int y = 0; y < baked.alpha.rows; ++y) {
      for (int x = 0; x < baked.alpha.cols; ++x) {
        const float a = baked.alpha.at<float>(y, x), b = direct.alpha.at<float>(y, x);
        alpha_sum += b;
        if (a < 1.0f / 255 && b < 1.0f / 255) continue;
        ++covered;
        squared += (a - b) * (a - b);
        for (int c = 0; c < 3; ++c)
          squared +=
              std::pow(baked.color.at<cv::Vec3f>(y, x)[c] - direct.color.at<cv::Vec3f>(y, x)[c], 2);
      }
    }
    EXPECT_GT(alpha_sum / baked.alpha.total(), 0.01)
        << "view " << i << " shows too little of the volume to compare";
    ASSERT_GT(covered, 0);
    const double psnr = 10 * std::log10(1.0 / (squared / (4.0 * covered)));
    EXPECT_GT(psnr, 40.0) << "view " << i;
    std::printf(
        "view %zu (frame %lld): baked against warp + template %.1f dB over %lld covered pixels\n",
        i, static_cast<long long>(path.frames[i]), psnr, static_cast<long long>(covered));
    ViewRenderOptions no_skip;
    no_skip.skip_empty = false;
    const RenderedView full = model->Render(path.cameras[i], path.frames[i], no_skip);
    EXPECT_LT(baked.samples_per_ray, full.samples_per_ray);
    EXPECT_LT(cv::norm(full.alpha, baked.alpha, cv::NORM_INF), 1e-5);
    EXPECT_LT(cv::norm(full.color, baked.color, cv::NORM_INF), 1e-5);
  }
}

}  // namespace
}  // namespace holocap
