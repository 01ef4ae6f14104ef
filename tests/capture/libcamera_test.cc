#include "capture/libcamera/libcamera_driver.h"

#include <gtest/gtest.h>

#include <sstream>

#include "core/error.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

// libcamera 0.0.3 has no virtual camera and this machine no camera: what must hold is that
// enumeration is empty rather than an error, and that opening says clearly there is none.
TEST(LibcameraDriver, WithoutACameraSaysSoClearly) {
  DriverRegistry registry;
  RegisterLibcameraDriver(registry);
  Driver& driver = registry.ForUri("libcamera:x");
  const auto devices = driver.Enumerate();
  try {
    registry.Open({.name = "cam", .uri = "libcamera:/base/soc/i2c0mux/i2c@1/imx477@1a"});
    FAIL() << "opened a camera that is not there";
  } catch (const Error& e) {
    const std::string message = e.what();
    EXPECT_NE(message.find("no camera '/base/soc/i2c0mux/i2c@1/imx477@1a'"), std::string::npos)
        << message;
    if (devices.empty()) {
      EXPECT_NE(message.find("found no camera on this machine"), std::string::npos) << message;
    }
  }
  EXPECT_NE(driver.description().find("libcamera"), std::string::npos);
}

// libcamera logs its version and a missing IPA module to stderr whenever its camera manager
// starts; `holocap devices` must print only its own lines: one per driver ("scheme:  what it
// drives"), each followed by its sensors or "(none found)", indented.
TEST(DevicesCli, PrintsCleanLinesWithoutLibcameraLogging) {
  const std::string cli =
      "env -u LIBCAMERA_LOG_LEVELS HOLOCAP_NO_PROGRESS=1 '" + testing::CliPath() + "' devices";
  const auto stderr_only = testing::RunShell(cli + " 2>&1 >/dev/null; echo exit=$?");
  EXPECT_EQ(stderr_only.output, "exit=0\n");
  const auto listing = testing::RunShell(cli + " 2>&1");
  ASSERT_EQ(listing.exit_code, 0) << listing.output;
  std::istringstream lines(listing.output);
  std::string line, libcamera_next;
  bool after_libcamera = false;
  int drivers = 0;
  while (std::getline(lines, line)) {
    if (after_libcamera) libcamera_next = line;
    after_libcamera = line.rfind("libcamera:  ", 0) == 0;
    if (line.rfind("    ", 0) == 0) continue;
    ++drivers;
    const size_t colon = line.find(":  ");
    ASSERT_NE(colon, std::string::npos) << "not a driver line: '" << line << "'\n"
                                        << listing.output;
    EXPECT_EQ(line.find_first_not_of("abcdefghijklmnopqrstuvwxyz0123456789"), colon) << line;
  }
  EXPECT_GE(drivers, 4) << listing.output;  // aravis, v4l2, libcamera, replay at least
  EXPECT_TRUE(libcamera_next == "    (none found)" ||
              libcamera_next.rfind("    libcamera:", 0) == 0)
      << listing.output;
}

}  // namespace
}  // namespace holocap
