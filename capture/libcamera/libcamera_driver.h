// The `libcamera:` driver: cameras behind libcamera's pipeline handlers (Raspberry Pi, CSI
// sensors through ISPs, UVC), written against Debian 12's libcamera 0.0.3 API.
//
//   libcamera:<camera id>     as `holocap devices` lists it
//
// SensorSpec::options (all optional): "width", "height" (default: the pipeline's choice for
// video recording), "buffers" (default: the pipeline's). Frames are stored as bgr8 (RGB888,
// BGR888, YUYV or MJPEG from the camera) or mono8 (R8); timestamps are the request's
// SensorTimestamp (start of exposure, CLOCK_MONOTONIC), else the buffer's.
#pragma once

#include "capture/hal.h"

namespace holocap {

void RegisterLibcameraDriver(DriverRegistry& registry);

}  // namespace holocap
