// The `v4l2:` driver: UVC webcams and depth sensors through Video4Linux2 (libv4l2), MMAP
// streaming.
//
//   v4l2:/dev/videoN
//
// SensorSpec::options (all optional):
//   "fourcc"   "YUYV" | "MJPG" | "GREY" | "Y16 " | "Z16 " (default: the best the device offers
//              for the sensor's role: Z16 for depth, then YUYV, MJPG, GREY, Y16 for colour)
//   "width", "height"  wanted size (default: the largest offered in that format)
//   "fps"      wanted rate (default 30; the nearest the device offers)
//   "buffers"  MMAP buffers, default 4
// Stored as: YUYV and MJPG -> bgr8, GREY -> mono8, Y16 -> mono16, Z16 -> depth_m (millimetres
// to metres, 0 = no measurement -> NaN). Timestamps are the driver's buffer timestamps in the
// clock its flags name (CLOCK_MONOTONIC for every modern driver). A device that disappears
// (ENODEV) makes Grab throw an Error saying it was unplugged.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "capture/hal.h"

namespace holocap {

void RegisterV4l2Driver(DriverRegistry& registry);

// The pure parts of the driver, testable without a device.
namespace v4l2 {

uint32_t FourccFromString(
    const std::string& text);                 // "YUYV" -> V4L2_PIX_FMT_YUYV; Error if not 4 chars
std::string FourccToString(uint32_t fourcc);  // "Z16 "

// One size and its frame rates as the device enumerates them for a format.
struct FormatOption {
  uint32_t fourcc = 0;
  int width = 0;
  int height = 0;
  std::vector<double> fps;  // empty: the device did not say
};

struct FormatRequest {
  uint32_t fourcc = 0;  // 0: pick by role
  int width = 0;        // 0: the largest
  int height = 0;
  double fps = 30;
  SensorRole role = SensorRole::kColor;
};

struct NegotiatedFormat {
  uint32_t fourcc = 0;
  int width = 0;
  int height = 0;
  double fps = 0;            // 0: the device offers no rate choice
  std::string pixel_format;  // how frames are stored (StreamInfo::pixel_format)
};

// The formats holocap can store, and how.
bool IsSupportedFourcc(uint32_t fourcc);
std::string StoredPixelFormat(uint32_t fourcc);  // Error for an unsupported fourcc

// Chooses a format, size and rate among those offered. Throws Error naming what was asked and
// what the device offers when nothing fits (an explicit fourcc it lacks, no supported format).
NegotiatedFormat Negotiate(const std::vector<FormatOption>& offered, const FormatRequest& request);

// Decodes one buffer (bytesused bytes at data, rows of bytes_per_line) into the stored image.
// Throws Error for a truncated buffer or an undecodable MJPEG frame.
cv::Mat ConvertFrame(uint32_t fourcc, const uint8_t* data, size_t bytesused, int width, int height,
                     int bytes_per_line);

// Buffer timestamp (v4l2_buffer::timestamp and ::flags) to nanoseconds and the clock's name.
struct BufferTime {
  int64_t ns = 0;
  std::string clock;  // "CLOCK_MONOTONIC", or "unknown" for copied/unknown timestamps
};
BufferTime MapTimestamp(int64_t tv_sec, int64_t tv_usec, uint32_t flags);

// Who holds each MMAP buffer. A buffer is queued to the driver, or dequeued and held by us
// until it is queued again; streaming needs at least one queued buffer.
class BufferQueue {
 public:
  enum class State { kIdle, kQueued, kDequeued };
  explicit BufferQueue(int count = 0);
  int size() const { return static_cast<int>(states_.size()); }
  State state(int index) const;
  // Marks buffer `index` handed to the driver (VIDIOC_QBUF). Error if it is already queued.
  void Queued(int index);
  // Marks buffer `index` returned by the driver (VIDIOC_DQBUF). Error if it was not queued.
  void Dequeued(int index);
  int queued() const;
  // Frame sequence bookkeeping: returns how many frames the driver skipped before `sequence`.
  uint64_t Sequence(uint32_t sequence);
  uint64_t frames_skipped() const { return skipped_; }
  void Reset(int count);

 private:
  std::vector<State> states_;
  bool have_sequence_ = false;
  uint32_t last_sequence_ = 0;
  uint64_t skipped_ = 0;
};

}  // namespace v4l2
}  // namespace holocap
