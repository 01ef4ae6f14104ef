// SimulateTake end to end: the take opens, ground truth agrees with itself (masks vs the
// projected ground-truth mesh), dropped frames are counted, and the sim: driver delivers the
// same sensors.
#include <gtest/gtest.h>

#include <opencv2/imgproc.hpp>

#include "capture/hal.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/image.h"
#include "core/mesh.h"
#include "core/take.h"
#include "sim/sim.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

TEST(SimulateTakeTest, GroundTruthMasksMatchTheProjectedMesh) {
  testing::TempDir dir;
  SimOptions options;
  options.rig = "single-rgbd";
  options.frames = 3;
  options.clean_plate_frames = 1;
  options.image_width = 160;
  options.noise = false;
  const SimSummary summary = SimulateTake(options, dir / "take");
  ASSERT_EQ(summary.termination, Termination::kSuccess) << summary.message;
  EXPECT_EQ(summary.frame_sets, 3);
  EXPECT_EQ(summary.frames_written, 6);

  const Take take = Take::Open(dir / "take");
  ASSERT_EQ(take.size(), 3u);
  EXPECT_TRUE(take.has_ground_truth());
  EXPECT_EQ(take.stream("depth0").pixel_format, "depth_m");
  EXPECT_EQ(take.stream("cam0").clock, "sim");
  EXPECT_FALSE(std::filesystem::exists(dir / "take" / "gt" / "meshes" / "000000.ply"));
  for (const std::string sensor : {"cam0", "depth0"}) {
    const CameraModel camera = take.Camera(sensor, /*ground_truth=*/true);
    EXPECT_EQ(cv::countNonZero(ReadImage(dir / "take" / "gt" / "masks" / sensor / "000000.png")),
              0);  // the clean plate
    for (const std::string set : {"000001", "000002"}) {
      const Mesh mesh = ReadPly(dir / "take" / "gt" / "meshes" / (set + ".ply"));
      cv::Mat projected = cv::Mat::zeros(camera.height(), camera.width(), CV_8U);
      for (const Eigen::Vector3i& face : mesh.faces) {
        std::vector<cv::Point> corners;
        for (int k = 0; k < 3; ++k) {
          Eigen::Vector2d pixel;
          if (!camera.ProjectWorld(mesh.vertices[face[k]].cast<double>(), &pixel)) break;
          // fillPoly works in 1/256 px fixed point.
          corners.emplace_back(std::lround(pixel.x() * 256), std::lround(pixel.y() * 256));
        }
        if (corners.size() == 3) cv::fillConvexPoly(projected, corners, 255, cv::LINE_8, 8);
      }
      // Masks sample pixel centres, fillPoly covers boundary pixels generously: they agree up
      // to one pixel along the outline.
      const cv::Mat mask = ReadImage(dir / "take" / "gt" / "masks" / sensor / (set + ".png"));
      cv::Mat grown, shrunk;
      cv::dilate(projected, grown, cv::Mat());
      cv::erode(projected, shrunk, cv::Mat());
      const int area = cv::countNonZero(mask);
      ASSERT_GT(area, 100) << sensor << " " << set;
      EXPECT_LE(cv::countNonZero(mask & ~grown), area / 100) << sensor << " " << set;
      EXPECT_LE(cv::countNonZero(shrunk & ~mask), area / 100) << sensor << " " << set;
      EXPECT_GT(cv::countNonZero(mask & projected), 0.85 * area) << sensor << " " << set;
    }
  }
  const cv::Mat depth = take.ReadFrame(1, "depth0");
  const cv::Mat truth = ReadImage(dir / "take" / "gt" / "depth" / "depth0" / "000001.exr");
  const cv::Mat subject = ReadImage(dir / "take" / "gt" / "masks" / "depth0" / "000001.png");
  ASSERT_EQ(depth.type(), CV_32F);
  int valid = 0, valid_on_subject = 0;
  for (int y = 0; y < depth.rows; ++y) {
    for (int x = 0; x < depth.cols; ++x) {
      const float d = depth.at<float>(y, x);
      if (!std::isfinite(d)) continue;
      ++valid;
      valid_on_subject += subject.at<uint8_t>(y, x) != 0;
      EXPECT_NEAR(d, truth.at<float>(y, x), 0.0006);  // noise off: millimetre quantisation
    }
  }
  // The far walls lie beyond the sensor's range; the subject is mostly measured, less its
  // outline (depth edges) and grazing parts.
  EXPECT_GT(valid, depth.rows * depth.cols / 10);
  EXPECT_GT(valid_on_subject, 0.5 * cv::countNonZero(subject));
  const nlohmann::json sim =
      nlohmann::json::parse(ReadFileToString(dir / "take" / "gt" / "sim.json"));
  EXPECT_EQ(sim["sensors"]["depth0"]["paired_with"], "cam0");
  EXPECT_EQ(sim["frames"].size(), 6u);
}

TEST(SimulateTakeTest, DroppedFramesAreCountedAndRecorded) {
  testing::TempDir dir;
  SimOptions options;
  options.rig = "studio8";
  options.scene = "board";
  options.frames = 4;
  options.image_width = 64;
  options.antialias = 2;
  options.drop_probability = 0.25;
  const SimSummary summary = SimulateTake(options, dir / "take");
  ASSERT_EQ(summary.termination, Termination::kSuccess) << summary.message;
  EXPECT_GT(summary.frames_dropped, 0);
  EXPECT_EQ(summary.frames_written + summary.frames_dropped, 4 * 10);
  const Take take = Take::Open(dir / "take");
  int64_t counted = 0;
  for (const auto& [sensor, count] : take.dropped()) counted += count;
  EXPECT_EQ(counted, summary.frames_dropped);
  int64_t present = 0;
  for (const FrameSetEntry& entry : take.entries()) present += entry.items.size();
  EXPECT_EQ(present, summary.frames_written);
  const nlohmann::json sim =
      nlohmann::json::parse(ReadFileToString(dir / "take" / "gt" / "sim.json"));
  EXPECT_EQ(static_cast<int64_t>(sim["dropped"].size()), summary.frames_dropped);
  const nlohmann::json board =
      nlohmann::json::parse(ReadFileToString(dir / "take" / "gt" / "board.json"));
  EXPECT_EQ(board["world_from_board"].size(), 4u);
  EXPECT_EQ(board["layout"]["width_n"], 10);
}

TEST(SimDriverTest, OpensSensorsThatShareOneWorld) {
  DriverRegistry registry;
  RegisterSimDriver(registry);
  const std::vector<DeviceInfo> devices = registry.ForUri("sim:studio8#cam0").Enumerate();
  EXPECT_EQ(devices.size(), 12u);  // studio8's 10 sensors and single-rgbd's 2
  SensorSpec spec;
  spec.name = "depth0";
  spec.uri = "sim:single-rgbd#depth0";
  spec.options = {{"width", 80}, {"frames", 2}};
  std::unique_ptr<Sensor> depth = registry.Open(spec);
  spec.name = "cam0";
  spec.uri = "sim:single-rgbd#cam0";
  std::unique_ptr<Sensor> color = registry.Open(spec);
  ASSERT_TRUE(depth->known_model().has_value());
  EXPECT_EQ(depth->stream().width, 80);
  EXPECT_EQ(depth->stream().pixel_format, "depth_m");
  depth->Start();
  color->Start();
  Frame frame;
  ASSERT_TRUE(color->Grab(&frame, std::chrono::milliseconds(1000)));
  EXPECT_EQ(frame.image.type(), CV_8UC3);
  EXPECT_EQ(frame.sequence, 0u);
  ASSERT_TRUE(depth->Grab(&frame, std::chrono::milliseconds(1000)));
  EXPECT_EQ(frame.image.type(), CV_32F);
  ASSERT_TRUE(depth->Grab(&frame, std::chrono::milliseconds(1000)));
  EXPECT_EQ(frame.sequence, 1u);
  EXPECT_FALSE(depth->Grab(&frame, std::chrono::milliseconds(1000)));
  EXPECT_TRUE(depth->ended());
  spec.uri = "sim:single-rgbd#cam9";
  EXPECT_THROW(registry.Open(spec), Error);
}

}  // namespace
}  // namespace holocap
