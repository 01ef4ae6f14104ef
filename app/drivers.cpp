#include "app/commands.h"
#include "capture/aravis/aravis_driver.h"
#include "capture/hal.h"
#include "capture/libcamera/libcamera_driver.h"
#include "capture/replay/replay_driver.h"
#include "capture/v4l2/v4l2_driver.h"
#include "sim/sim.h"

namespace holocap {

void RegisterBuiltinDrivers() {
  DriverRegistry& registry = DriverRegistry::Global();
  RegisterReplayDriver(registry);
  RegisterSimDriver(registry);
  RegisterAravisDriver(registry);
  RegisterV4l2Driver(registry);
  RegisterLibcameraDriver(registry);
}

}  // namespace holocap
