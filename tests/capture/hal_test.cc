#include "capture/hal.h"

#include <gtest/gtest.h>

#include "capture/replay/replay_driver.h"
#include "core/error.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::TempDir;

TEST(DriverRegistry, UnknownSchemesAndMalformedUrisAreClearErrors) {
  DriverRegistry registry;
  RegisterReplayDriver(registry);
  try {
    registry.ForUri("gopro:cam1");
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("unknown URI scheme 'gopro'"), std::string::npos);
    EXPECT_NE(std::string(e.what()).find("replay"), std::string::npos);
  }
  EXPECT_THROW(registry.ForUri("no-scheme-here"), Error);
  EXPECT_THROW(registry.Open({.name = "a", .uri = "replay:/nonexistent#cam0"}), Error);
  EXPECT_THROW(registry.Open({.name = "a", .uri = "replay:/tmp"}), Error);
  ParsedUri uri = ParseSensorUri("sim:studio8#cam3");
  EXPECT_EQ(uri.scheme, "sim");
  EXPECT_EQ(uri.path, "studio8");
  EXPECT_EQ(uri.fragment, "cam3");
}

TEST(ReplayDriver, ReplaysATakeBitExactlyAtEitherPace) {
  TempDir dir;
  RigDescription rig;
  rig.sensors = {{.name = "cam0", .uri = "sim:x#cam0"}};
  StreamInfo stream{
      .name = "cam0", .width = 16, .height = 8, .pixel_format = "mono16", .clock = "sim"};
  std::vector<cv::Mat> images;
  {
    TakeWriter writer(dir / "take", rig, {stream});
    for (int i = 0; i < 6; ++i) {
      cv::Mat image(8, 16, CV_16UC1);
      cv::randu(image, 0, 65535);
      images.push_back(image);
      writer.Append(
          {.index = i, .frames = {{"cam0", image, 20'000'000LL * i, static_cast<uint64_t>(i)}}});
    }
  }
  DriverRegistry registry;
  RegisterReplayDriver(registry);
  for (std::string pace : {"fast", "recorded"}) {
    SensorSpec spec{.name = "cam0", .uri = "replay:" + (dir / "take").string() + "#cam0"};
    spec.options["pace"] = pace;
    auto sensor = registry.Open(spec);
    EXPECT_EQ(sensor->stream().pixel_format, "mono16");
    sensor->Start();
    auto start = std::chrono::steady_clock::now();
    Frame frame;
    int count = 0;
    while (sensor->Grab(&frame, std::chrono::milliseconds(500))) {
      ASSERT_LT(count, 6);
      EXPECT_EQ(cv::countNonZero(frame.image != images[count]), 0);
      EXPECT_EQ(frame.timestamp_ns, 20'000'000LL * count);
      ++count;
    }
    double seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    EXPECT_EQ(count, 6);
    EXPECT_TRUE(sensor->ended());
    if (pace == "recorded") EXPECT_GE(seconds, 0.095);  // 5 intervals of 20 ms
  }
  SensorSpec bad{.name = "cam0", .uri = "replay:" + (dir / "take").string() + "#cam7"};
  EXPECT_THROW(registry.Open(bad), Error);
}

}  // namespace
}  // namespace holocap
