#include "capture/aravis/aravis_driver.h"

#include <gtest/gtest.h>

#include <opencv2/imgproc.hpp>
#include <thread>

#include "capture/recorder.h"
#include "core/error.h"
#include "tests/capture/fake_gige.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::FakeGigeCameras;
using testing::TempDir;

// The fake cameras fill each frame with a diagonal ramp (c + x + y) mod 255 whose start c
// moves with every frame; a frame assembled from two frames' packets breaks the ramp.
int64_t BrokenRampPixels(const cv::Mat& mono8) {
  int64_t broken = 0;
  const int start = mono8.at<uint8_t>(0, 0);
  for (int y = 0; y < mono8.rows; ++y) {
    for (int x = 0; x < mono8.cols; ++x) broken += mono8.at<uint8_t>(y, x) != (start + x + y) % 255;
  }
  return broken;
}

RigDescription FakeRig(const FakeGigeCameras& cameras, int count, SyncMode sync, double fps,
                       nlohmann::json options = nlohmann::json::object()) {
  RigDescription rig;
  rig.name = "fake-gige";
  rig.sync = sync;
  rig.fps = fps;
  for (int i = 0; i < count; ++i) {
    rig.sensors.push_back({.name = "cam" + std::to_string(i), .uri = "aravis:" + cameras.id(i), .options = options});
  }
  return rig;
}

DriverRegistry& AravisOnly() {
  static DriverRegistry registry;
  if (!registry.has("aravis")) RegisterAravisDriver(registry);
  return registry;
}

TEST(AravisPixels, LayoutsAndUnsupportedFormats) {
  EXPECT_EQ(AravisLayoutFor("Mono8", true).stored, "mono8");
  EXPECT_EQ(AravisLayoutFor("Mono16", true).stored, "mono16");
  EXPECT_EQ(AravisLayoutFor("RGB8", true).stored, "bgr8");
  EXPECT_EQ(AravisLayoutFor("BayerGB16", true).stored, "bgr16");
  EXPECT_EQ(AravisLayoutFor("BayerGB16", false).stored, "mono16");
  EXPECT_EQ(AravisLayoutFor("BayerRG8", false).bayer_to_bgr, -1);
  try {
    AravisLayoutFor("YUV422_8", true);
    FAIL() << "YUV422_8 accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("unsupported pixel format 'YUV422_8'"), std::string::npos) << e.what();
  }
  EXPECT_THROW(AravisLayoutFor("BayerXY8", true), Error);
  EXPECT_THROW(AravisLayoutFor("", true), Error);
}

TEST(AravisPixels, DebayeringRecoversAFlatColourForEveryPattern) {
  const cv::Vec3b bgr(40, 120, 200);  // B, G, R
  // Where red, green and blue sit in each 2x2 cell, by GenICam name.
  const std::vector<std::pair<std::string, std::string>> patterns = {
      {"BayerRG8", "RGGB"}, {"BayerGR8", "GRBG"}, {"BayerGB8", "GBRG"}, {"BayerBG8", "BGGR"}};
  for (const auto& [name, cell] : patterns) {
    cv::Mat mosaic(16, 16, CV_8UC1);
    for (int y = 0; y < 16; ++y) {
      for (int x = 0; x < 16; ++x) {
        const char c = cell[(y % 2) * 2 + (x % 2)];
        mosaic.at<uint8_t>(y, x) = c == 'R' ? bgr[2] : c == 'G' ? bgr[1] : bgr[0];
      }
    }
    cv::Mat out = ConvertAravisImage(mosaic, AravisLayoutFor(name, true));
    ASSERT_EQ(out.type(), CV_8UC3);
    const cv::Vec3b centre = out.at<cv::Vec3b>(8, 8);
    for (int k = 0; k < 3; ++k) EXPECT_NEAR(centre[k], bgr[k], 1) << name << " channel " << k;
  }
  cv::Mat rgb(2, 2, CV_8UC3, cv::Scalar(10, 20, 30));
  EXPECT_EQ(ConvertAravisImage(rgb, AravisLayoutFor("RGB8", true)).at<cv::Vec3b>(1, 1), cv::Vec3b(30, 20, 10));
}

TEST(AravisDriver, UnknownDeviceIsOneClearError) {
  ASSERT_EQ(testing::EnterPrivateNetwork(), "");
  DriverRegistry registry;
  RegisterAravisDriver(registry);
  try {
    registry.Open({.name = "cam0", .uri = "aravis:No-Such-Camera"});
    FAIL() << "opened a camera that does not exist";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("aravis:No-Such-Camera': no such camera"), std::string::npos) << e.what();
  }
}

TEST(AravisDriver, InProcessFakeCameraStreamsFreeRunning) {
  DriverRegistry registry;
  RegisterAravisDriver(registry);
  auto sensor = registry.Open({.name = "fake",
                               .uri = "aravis:Fake_1",
                               .options = {{"sync", "free-run"}, {"fps", 50}, {"pixel_format", "Mono8"},
                                           {"timestamp", "host"}}});
  EXPECT_EQ(sensor->stream().pixel_format, "mono8");
  EXPECT_EQ(sensor->stream().clock, "CLOCK_REALTIME");
  sensor->Start();
  std::vector<Frame> frames;
  const auto start = std::chrono::steady_clock::now();
  while (frames.size() < 10 && std::chrono::steady_clock::now() - start < std::chrono::seconds(5)) {
    Frame frame;
    if (sensor->Grab(&frame, std::chrono::milliseconds(500))) frames.push_back(frame);
  }
  sensor->Stop();
  ASSERT_EQ(frames.size(), 10u);
  for (size_t i = 1; i < frames.size(); ++i) {
    EXPECT_GT(frames[i].sequence, frames[i - 1].sequence);
    const double dt = (frames[i].timestamp_ns - frames[i - 1].timestamp_ns) * 1e-9;
    EXPECT_GT(dt, 0.0);
    EXPECT_LT(dt, 0.2);
  }
  EXPECT_EQ(frames[0].image.cols, sensor->stream().width);
  EXPECT_EQ(sensor->stats().frames_delivered, 10u);
  try {
    registry.Open({.name = "fake", .uri = "aravis:Fake_1", .options = {{"pixel_format", "YUV411"}}});
    FAIL() << "an unsupported pixel format was accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("no pixel format 'YUV411' (it offers"), std::string::npos) << e.what();
  }
}

// arv-fake-gv-camera-0.8 serves a software trigger only on its own 25 Hz ticks, which fall on
// multiples of 40 ms of CLOCK_REALTIME (its trigger_frequency, not reachable over GVCP): two
// triggers inside one tick make one frame, and a fake process that misses a tick under CPU load
// folds two triggers the same way. Triggers on the realtime grid, mid-tick, at 25 Hz must then
// come back as complete sets with a sub-tick spread, every trigger written or counted lost, and
// no set may mix frames of two ticks.
TEST(FakeGige, EightCamerasSoftwareTriggeredEveryFrameWrittenOrCounted) {
  FakeGigeCameras cameras(8);
  TempDir dir;
  RecorderOptions options;
  options.frames = 30;
  options.trigger_phase_s = 0.020;
  Recorder recorder(FakeRig(cameras, 8, SyncMode::kSoftwareTrigger, 25, {{"roi", {0, 0, 256, 256}}}),
                    dir / "take", options, AravisOnly());
  RecorderSummary summary = recorder.Run();
  ASSERT_EQ(summary.termination, Termination::kSuccess) << summary.message;
  EXPECT_GE(summary.frame_sets_complete, 24) << summary.Metrics().dump(1);
  for (const auto& sensor : summary.sensors) {
    EXPECT_EQ(sensor.triggers, 30) << sensor.name;
    EXPECT_EQ(sensor.written + sensor.dropped(), 30) << sensor.name;
    EXPECT_EQ(sensor.written, summary.frame_sets_complete) << sensor.name;
  }
  EXPECT_LT(summary.sync_spread_us_max, 16000);  // the tolerance: 0.4 of the 40 ms period
  Take take = Take::Open(dir / "take");
  EXPECT_EQ(take.state(), "complete");
  ASSERT_EQ(static_cast<int64_t>(take.size()), summary.frame_sets_complete);
  int64_t dropped_in_take = 0;
  for (const auto& [sensor, dropped] : take.dropped()) dropped_in_take += dropped;
  EXPECT_EQ(dropped_in_take, summary.frames_dropped);
  for (size_t i = 0; i < take.size(); ++i) {
    FrameSet set = take.Read(i);
    ASSERT_EQ(set.frames.size(), 8u);
    for (const auto& frame : set.frames) {
      EXPECT_EQ(frame.image.cols, 256);
      EXPECT_EQ(BrokenRampPixels(frame.image), 0) << frame.sensor << " set " << i;
    }
  }
}

TEST(FakeGige, UnderPacketLossEveryFrameIsCompleteOrCountedLost) {
  FakeGigeCameras cameras(3, /*lost_per_thousand=*/20);
  TempDir dir;
  RecorderOptions options;
  options.frames = 60;
  // Small frames (a handful of packets each) so that a fair share arrives whole.
  Recorder recorder(FakeRig(cameras, 3, SyncMode::kSoftwareTrigger, 30,
                            {{"roi", {0, 0, 128, 64}}, {"frame_retention_ms", 20}, {"packet_timeout_ms", 5}}),
                    dir / "take", options, AravisOnly());
  RecorderSummary summary = recorder.Run();
  ASSERT_EQ(summary.termination, Termination::kSuccess) << summary.message;
  int64_t resend_requests = 0, lost = 0;
  for (const auto& sensor : summary.sensors) {
    EXPECT_EQ(sensor.triggers, 60) << sensor.name;
    // Every trigger is accounted for: written, lost in the driver, or in an incomplete set.
    EXPECT_EQ(sensor.written + sensor.dropped(), sensor.triggers) << sensor.name;
    resend_requests += sensor.driver.value("n_resend_requests", int64_t{0});
    lost += sensor.lost_in_driver;
  }
  EXPECT_GT(resend_requests, 0) << "lost packets were never asked for again";
  EXPECT_GT(lost, 0) << "2% packet loss lost no frame at all";
  EXPECT_GT(summary.frame_sets_complete, 0);
  Take take = Take::Open(dir / "take");
  ASSERT_EQ(static_cast<int64_t>(take.size()), summary.frame_sets_complete);
  for (size_t i = 0; i < take.size(); ++i) {
    for (const auto& frame : take.Read(i).frames) {
      ASSERT_EQ(BrokenRampPixels(frame.image), 0) << "torn frame from " << frame.sensor << " in set " << i;
    }
  }
  int64_t dropped_in_take = 0;
  for (const auto& [sensor, dropped] : take.dropped()) dropped_in_take += dropped;
  EXPECT_EQ(dropped_in_take, summary.frames_dropped);
}

TEST(FakeGige, CameraVanishingMidTakeEndsItCleanly) {
  FakeGigeCameras cameras(3);
  TempDir dir;
  RecorderOptions options;
  options.seconds = 20;
  options.stall_s = 1.0;
  Recorder recorder(FakeRig(cameras, 3, SyncMode::kSoftwareTrigger, 30, {{"roi", {0, 0, 128, 128}}}), dir / "take",
                    options, AravisOnly());
  std::thread killer([&] {
    std::this_thread::sleep_for(std::chrono::milliseconds(1500));
    cameras.Kill(1);
  });
  const auto start = std::chrono::steady_clock::now();
  RecorderSummary summary = recorder.Run();
  killer.join();
  EXPECT_LT(std::chrono::steady_clock::now() - start, std::chrono::seconds(10));
  ASSERT_EQ(summary.termination, Termination::kFailure);
  EXPECT_NE(summary.message.find("sensor 'cam1'"), std::string::npos) << summary.message;
  EXPECT_NE(summary.message.find("lost mid-take"), std::string::npos) << summary.message;
  EXPECT_GT(summary.frame_sets_complete, 20);
  Take take = Take::Open(dir / "take");
  EXPECT_EQ(static_cast<int64_t>(take.size()), summary.frame_sets_complete);
  EXPECT_EQ(take.skipped_index_lines(), 0);
  take.Read(take.size() - 1);
}

}  // namespace
}  // namespace holocap
