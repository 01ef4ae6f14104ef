#include "capture/v4l2/v4l2_driver.h"

#include <gtest/gtest.h>
#include <linux/videodev2.h>

#include <cmath>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "core/error.h"

namespace holocap {
namespace {

using namespace v4l2;

TEST(V4l2Negotiation, PicksByRoleSizeAndRate) {
  const uint32_t yuyv = V4L2_PIX_FMT_YUYV, mjpg = V4L2_PIX_FMT_MJPEG, z16 = V4L2_PIX_FMT_Z16;
  std::vector<FormatOption> offered = {{mjpg, 1920, 1080, {30, 60}},
                                       {yuyv, 640, 480, {30, 15}},
                                       {yuyv, 1280, 720, {10}},
                                       {z16, 848, 480, {30, 90}},
                                       {V4L2_PIX_FMT_NV12, 1920, 1080, {30}}};
  NegotiatedFormat colour = Negotiate(offered, {.fps = 30});
  EXPECT_EQ(FourccToString(colour.fourcc), "YUYV");
  EXPECT_EQ(colour.width, 1280);
  EXPECT_EQ(colour.fps, 10);
  NegotiatedFormat small =
      Negotiate(offered, {.fourcc = yuyv, .width = 600, .height = 460, .fps = 25});
  EXPECT_EQ(small.width, 640);
  EXPECT_EQ(small.fps, 30);
  NegotiatedFormat depth = Negotiate(offered, {.fps = 60, .role = SensorRole::kDepth});
  EXPECT_EQ(depth.pixel_format, "depth_m");
  EXPECT_EQ(depth.fps, 30);  // 30 and 90 are equally near 60: the first offered wins
  EXPECT_EQ(Negotiate(offered, {.fourcc = mjpg}).pixel_format, "bgr8");
  try {
    Negotiate(offered, {.fourcc = V4L2_PIX_FMT_GREY});
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("no 'GREY' format (it offers MJPG 1920x1080"),
              std::string::npos)
        << e.what();
  }
  EXPECT_THROW(Negotiate(offered, {.fourcc = V4L2_PIX_FMT_NV12}), Error);  // offered, not storable
  EXPECT_THROW(Negotiate({{V4L2_PIX_FMT_NV12, 640, 480, {}}}, {}), Error);
  EXPECT_THROW(Negotiate({}, {}), Error);
  EXPECT_EQ(FourccFromString("Z16 "), z16);
  EXPECT_THROW(FourccFromString("Z16"), Error);
}

TEST(V4l2Conversion, YuyvGreyY16Z16AndMjpeg) {
  // YUYV of a flat grey (Y=128, U=V=128) is grey in BGR.
  std::vector<uint8_t> yuyv(4 * 2 * 2);
  for (size_t i = 0; i < yuyv.size(); ++i) yuyv[i] = 128;
  cv::Mat bgr = ConvertFrame(V4L2_PIX_FMT_YUYV, yuyv.data(), yuyv.size(), 4, 2, 8);
  ASSERT_EQ(bgr.type(), CV_8UC3);
  EXPECT_NEAR(bgr.at<cv::Vec3b>(1, 3)[1], 128, 2);
  EXPECT_THROW(ConvertFrame(V4L2_PIX_FMT_YUYV, yuyv.data(), yuyv.size() - 1, 4, 2, 8), Error);

  // Rows padded to 8 bytes: the padding must not leak into the image.
  std::vector<uint8_t> grey = {1, 2, 3, 99, 99, 99, 99, 99, 4, 5, 6};
  cv::Mat mono = ConvertFrame(V4L2_PIX_FMT_GREY, grey.data(), grey.size(), 3, 2, 8);
  EXPECT_EQ(mono.at<uint8_t>(1, 2), 6);
  EXPECT_EQ(cv::sum(mono)[0], 21);

  std::vector<uint16_t> z16 = {0, 1000, 2500, 65535};
  cv::Mat depth =
      ConvertFrame(V4L2_PIX_FMT_Z16, reinterpret_cast<const uint8_t*>(z16.data()), 8, 2, 2, 4);
  ASSERT_EQ(depth.type(), CV_32FC1);
  EXPECT_TRUE(std::isnan(depth.at<float>(0, 0)));
  EXPECT_FLOAT_EQ(depth.at<float>(0, 1), 1.0f);
  EXPECT_FLOAT_EQ(depth.at<float>(1, 0), 2.5f);
  EXPECT_FLOAT_EQ(depth.at<float>(1, 1), 65.535f);
  cv::Mat y16 =
      ConvertFrame(V4L2_PIX_FMT_Y16, reinterpret_cast<const uint8_t*>(z16.data()), 8, 2, 2, 0);
  EXPECT_EQ(y16.at<uint16_t>(1, 1), 65535);

  cv::Mat picture(16, 32, CV_8UC3, cv::Scalar(10, 200, 60));
  std::vector<uint8_t> jpeg;
  cv::imencode(".jpg", picture, jpeg, {cv::IMWRITE_JPEG_QUALITY, 95});
  cv::Mat decoded = ConvertFrame(V4L2_PIX_FMT_MJPEG, jpeg.data(), jpeg.size(), 32, 16, 0);
  EXPECT_LT(cv::norm(decoded, picture, cv::NORM_INF), 6);
  EXPECT_THROW(ConvertFrame(V4L2_PIX_FMT_MJPEG, jpeg.data(), jpeg.size(), 64, 16, 0), Error);
  std::vector<uint8_t> junk = {0x00, 0x11, 0x22, 0x33, 0x44};
  EXPECT_THROW(ConvertFrame(V4L2_PIX_FMT_MJPEG, junk.data(), junk.size(), 32, 16, 0), Error);
}

TEST(V4l2Timestamps, ClockFollowsTheBufferFlags) {
  BufferTime mono =
      MapTimestamp(12, 345678, V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC | V4L2_BUF_FLAG_TSTAMP_SRC_SOE);
  EXPECT_EQ(mono.ns, 12345678000);
  EXPECT_EQ(mono.clock, "CLOCK_MONOTONIC");
  EXPECT_EQ(MapTimestamp(0, 1, V4L2_BUF_FLAG_TIMESTAMP_COPY).clock.rfind("unknown", 0), 0u);
  EXPECT_EQ(MapTimestamp(0, 1, V4L2_BUF_FLAG_TIMESTAMP_UNKNOWN).clock, "unknown");
}

TEST(V4l2BufferQueue, StateMachineAndSequenceGaps) {
  BufferQueue queue(3);
  EXPECT_EQ(queue.queued(), 0);
  queue.Queued(0);
  queue.Queued(1);
  EXPECT_THROW(queue.Queued(1), Error);    // twice to the driver
  EXPECT_THROW(queue.Dequeued(2), Error);  // never queued
  EXPECT_THROW(queue.Queued(3), Error);    // no such buffer
  queue.Dequeued(0);
  EXPECT_EQ(queue.state(0), BufferQueue::State::kDequeued);
  EXPECT_EQ(queue.queued(), 1);
  EXPECT_EQ(queue.Sequence(10), 0u);
  EXPECT_EQ(queue.Sequence(11), 0u);
  EXPECT_EQ(queue.Sequence(14), 2u);
  EXPECT_EQ(queue.Sequence(0xffffffffu), 0u);  // went backwards: a restart, not 4 billion drops
  EXPECT_EQ(queue.Sequence(1), 1u);            // wrapped past 0
  EXPECT_EQ(queue.frames_skipped(), 3u);
}

TEST(V4l2Driver, MissingAndNonVideoDevicesAreClearErrors) {
  DriverRegistry registry;
  RegisterV4l2Driver(registry);
  try {
    registry.Open({.name = "cam", .uri = "v4l2:/dev/video97"});
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("cannot open /dev/video97"), std::string::npos)
        << e.what();
  }
  try {
    registry.Open({.name = "cam", .uri = "v4l2:/dev/null"});
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("/dev/null is not a V4L2 device"), std::string::npos)
        << e.what();
  }
  EXPECT_THROW(registry.Open({.name = "cam", .uri = "v4l2:"}), Error);
  // No /dev/video* here; on a machine with cameras this lists them.
  for (const auto& device : registry.ForUri("v4l2:x").Enumerate())
    EXPECT_EQ(device.uri.rfind("v4l2:/dev/video", 0), 0u);
}

}  // namespace
}  // namespace holocap
