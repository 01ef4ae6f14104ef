#include "capture/libcamera/libcamera_driver.h"

#include <gtest/gtest.h>

#include "core/error.h"

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
    EXPECT_NE(message.find("no camera '/base/soc/i2c0mux/i2c@1/imx477@1a'"), std::string::npos) << message;
    if (devices.empty()) EXPECT_NE(message.find("found no camera on this machine"), std::string::npos) << message;
  }
  EXPECT_NE(driver.description().find("libcamera"), std::string::npos);
}

}  // namespace
}  // namespace holocap
