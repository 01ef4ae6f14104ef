// The `replay:` driver: a recorded take played back as live sensors.
//   replay:/path/to/take#cam3            one sensor of a take
// SensorSpec::options["pace"]: "recorded" (frames released at their recorded intervals) or
// "fast" (as fast as they can be read; the default). options["loop"]: start over at the end.
#pragma once

#include "capture/hal.h"

namespace holocap {

void RegisterReplayDriver(DriverRegistry& registry);

}  // namespace holocap
