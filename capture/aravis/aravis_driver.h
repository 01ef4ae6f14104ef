// The `aravis:` driver: GigE Vision and USB3 Vision cameras through libaravis 0.8.
//
//   aravis:<device-id>      as `holocap devices` lists it (e.g. aravis:Aravis-Fake-CAM2), or
//                           the camera's IP address; aravis:Fake_1 is aravis' in-process camera
//
// SensorSpec::exposure_us and gain_db set ExposureTime and Gain when non-zero.
// SensorSpec::options (every key optional):
//   "pixel_format"   GenICam name: "Mono8", "Mono16", "RGB8", "BGR8", "Bayer{RG,GR,GB,BG}{8,16}"
//   "roi"            [x, y, width, height] in sensor pixels
//   "sync"           "software" | "hardware" | "free-run" (the recorder passes the rig's mode)
//   "fps"            free-running frame rate (the recorder passes the rig's rate)
//   "trigger_source" hardware trigger line, default "Line0"
//   "ptp"            true: enable IEEE 1588 (PtpEnable or GevIEEE1588) where the device has it
//   "timestamp"      "device" (default): the camera's own stamp (start of exposure), carried
//                    into CLOCK_REALTIME by the smallest recent (host - device) difference, so
//                    that every camera shares one clock without the host's scheduling delays;
//                    "host": CLOCK_REALTIME when the host saw the first packet (late by however
//                    long the stream thread waited for a core); "raw-device": the camera's clock
//                    as is (named "PTP" when PTP is enabled, which also keeps it raw)
//   "buffers"        size of the buffer pool handed to the stream, default 16
//   "debayer"        true (default): Bayer frames become bgr8/bgr16; false: stored raw as mono
//   "packet_resend"  true (default): ask GigE cameras to resend lost packets
//   "packet_socket"  false (default): use plain UDP sockets; packet sockets fail in containers
//   "packet_timeout_ms", "frame_retention_ms": how long a GigE frame waits for lost packets
//
// What libaravis logs through GLib goes to each open sensor's SensorStats::details
// ("aravis_log", the last 32 messages), not to stderr.
#pragma once

#include <string>

#include <opencv2/core.hpp>

#include "capture/hal.h"

namespace holocap {

void RegisterAravisDriver(DriverRegistry& registry);

// How a GenICam pixel format is stored in a take, or an Error listing the supported ones.
struct AravisPixelLayout {
  std::string genicam;      // "BayerRG8"
  std::string stored;       // StreamInfo::pixel_format: "bgr8", "mono8", ...
  int raw_type = 0;         // cv type of the wire image (CV_8UC1 for Bayer8, CV_8UC3 for RGB8)
  int bayer_to_bgr = -1;    // OpenCV conversion code when debayering, else -1
  bool rgb_to_bgr = false;  // RGB8/RGB16 on the wire
};
AravisPixelLayout AravisLayoutFor(const std::string& genicam_format, bool debayer);

// Turns one wire image (raw_type, rows x cols) into the stored image.
cv::Mat ConvertAravisImage(const cv::Mat& wire, const AravisPixelLayout& layout);

}  // namespace holocap
