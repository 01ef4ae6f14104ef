// holocap devices: every sensor every compiled-in driver can open now, and the hardware drivers
// this build left out (-DHOLOCAP_DRIVERS).
#include <iostream>
#include <opencv2/core.hpp>

#include "app/commands.h"
#include "capture/drivers_built.h"
#include "capture/hal.h"
#include "core/error.h"

namespace holocap {

namespace {

// Opens one sensor, grabs one frame and describes both: the quickest check that a URI works.
void Probe(const std::string& uri, double timeout_s) {
  SensorSpec spec{.name = "probe", .uri = uri};
  auto sensor = DriverRegistry::Global().Open(spec);
  const StreamInfo& stream = sensor->stream();
  std::cout << uri << ": " << stream.width << "x" << stream.height << " " << stream.pixel_format
            << ", clock " << stream.clock << "\n";
  if (auto model = sensor->known_model()) std::cout << "  lens " << model->lensmodel() << "\n";
  sensor->Start();
  if (sensor->supports_software_trigger()) sensor->Trigger();
  Frame frame;
  bool got =
      sensor->Grab(&frame, std::chrono::milliseconds(static_cast<int64_t>(timeout_s * 1000)));
  sensor->Stop();
  if (!got) Fail("'", uri, "' delivered no frame within ", timeout_s, " s");
  double lo, hi;
  cv::Mat values = frame.image.reshape(1);
  cv::Mat measured = values == values;  // NaN (no depth measurement) compares unequal
  cv::minMaxLoc(values, &lo, &hi, nullptr, nullptr, measured);
  std::cout << "  frame " << frame.sequence << " at " << frame.timestamp_ns << " ns, values " << lo
            << ".." << hi << "\n";
}

}  // namespace

static void AddDevicesCommand(CLI::App& app) {
  auto* command = app.add_subcommand("devices", "List the sensors of every driver compiled in");
  auto probe = std::make_shared<std::string>();
  auto timeout_s = std::make_shared<double>(5.0);
  command->add_option("--probe", *probe, "Open this sensor URI and grab one frame");
  command->add_option("--timeout", *timeout_s, "Seconds to wait for the probe's frame")
      ->capture_default_str();
  command->callback([probe, timeout_s] {
    if (!probe->empty()) return Probe(*probe, *timeout_s);
    for (Driver* driver : DriverRegistry::Global().drivers()) {
      std::cout << driver->scheme() << ":  " << driver->description() << "\n";
      std::vector<DeviceInfo> devices;
      try {
        devices = driver->Enumerate();
      } catch (const Error& e) {
        std::cout << "    (cannot enumerate: " << e.what() << ")\n";
        continue;
      }
      if (devices.empty()) std::cout << "    (none found)\n";
      for (const auto& device : devices) {
        std::cout << "    " << device.uri << "  [" << ToString(device.role) << "]  "
                  << device.description << "\n";
      }
    }
    // A driver line like the others, for each hardware driver this build left out.
    for (const BuiltDriver& built : kHardwareDrivers) {
      if (!built.compiled)
        std::cout << built.scheme << ":  not compiled in (" << built.why_not << ")\n";
    }
  });
}

HOLOCAP_COMMAND(5, AddDevicesCommand);

}  // namespace holocap
