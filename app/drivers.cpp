#include "app/commands.h"
#include "capture/drivers_built.h"
#include "capture/hal.h"
#include "capture/replay/replay_driver.h"
#include "sim/sim.h"

#if HOLOCAP_DRIVER_ARAVIS
#include "capture/aravis/aravis_driver.h"
#endif
#if HOLOCAP_DRIVER_V4L2
#include "capture/v4l2/v4l2_driver.h"
#endif
#if HOLOCAP_DRIVER_LIBCAMERA
#include "capture/libcamera/libcamera_driver.h"
#endif

namespace holocap {

void RegisterBuiltinDrivers() {
  DriverRegistry& registry = DriverRegistry::Global();
  RegisterReplayDriver(registry);
  RegisterSimDriver(registry);
#if HOLOCAP_DRIVER_ARAVIS
  RegisterAravisDriver(registry);
#endif
#if HOLOCAP_DRIVER_V4L2
  RegisterV4l2Driver(registry);
#endif
#if HOLOCAP_DRIVER_LIBCAMERA
  RegisterLibcameraDriver(registry);
#endif
}

}  // namespace holocap
