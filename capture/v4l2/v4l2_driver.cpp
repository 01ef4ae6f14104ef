#include "capture/v4l2/v4l2_driver.h"

#include <fcntl.h>
#include <libv4l2.h>
#include <linux/videodev2.h>
#include <poll.h>
#include <sys/mman.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <limits>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "core/error.h"

namespace holocap {
namespace v4l2 {
namespace {

// Colour preference when the rig does not name a format: uncompressed first (no decode cost,
// no compression artefacts), MJPEG when that is all a USB 2 camera can do at full size.
const std::vector<uint32_t> kColorPreference = {V4L2_PIX_FMT_YUYV, V4L2_PIX_FMT_MJPEG,
                                                V4L2_PIX_FMT_GREY, V4L2_PIX_FMT_Y16};
const std::vector<uint32_t> kDepthPreference = {V4L2_PIX_FMT_Z16};

}  // namespace

uint32_t FourccFromString(const std::string& text) {
  if (text.size() != 4)
    Fail("a fourcc has four characters ('", text, "'; pad with spaces: \"Z16 \")");
  return v4l2_fourcc(text[0], text[1], text[2], text[3]);
}

std::string FourccToString(uint32_t fourcc) {
  std::string text(4, ' ');
  for (int i = 0; i < 4; ++i) text[i] = static_cast<char>((fourcc >> (8 * i)) & 0xff);
  return text;
}

bool IsSupportedFourcc(uint32_t fourcc) {
  return fourcc == V4L2_PIX_FMT_YUYV || fourcc == V4L2_PIX_FMT_MJPEG ||
         fourcc == V4L2_PIX_FMT_GREY || fourcc == V4L2_PIX_FMT_Y16 || fourcc == V4L2_PIX_FMT_Z16;
}

std::string StoredPixelFormat(uint32_t fourcc) {
  switch (fourcc) {
    case V4L2_PIX_FMT_YUYV:
    case V4L2_PIX_FMT_MJPEG:
      return "bgr8";
    case V4L2_PIX_FMT_GREY:
      return "mono8";
    case V4L2_PIX_FMT_Y16:
      return "mono16";
    case V4L2_PIX_FMT_Z16:
      return "depth_m";
  }
  Fail("unsupported V4L2 pixel format '", FourccToString(fourcc),
       "' (supported: YUYV, MJPG, GREY, Y16, Z16)");
}

NegotiatedFormat Negotiate(const std::vector<FormatOption>& offered, const FormatRequest& request) {
  std::string offered_text;
  for (const auto& option : offered) {
    offered_text += (offered_text.empty() ? "" : ", ") + FourccToString(option.fourcc) + " " +
                    std::to_string(option.width) + "x" + std::to_string(option.height);
  }
  if (offered_text.empty()) offered_text = "nothing";
  uint32_t fourcc = request.fourcc;
  if (fourcc != 0) {
    if (!IsSupportedFourcc(fourcc)) StoredPixelFormat(fourcc);
    if (std::none_of(offered.begin(), offered.end(),
                     [&](const auto& o) { return o.fourcc == fourcc; })) {
      Fail("the device has no '", FourccToString(fourcc), "' format (it offers ", offered_text,
           ")");
    }
  } else {
    const auto& preference =
        request.role == SensorRole::kDepth ? kDepthPreference : kColorPreference;
    for (uint32_t candidate : preference) {
      if (std::any_of(offered.begin(), offered.end(),
                      [&](const auto& o) { return o.fourcc == candidate; })) {
        fourcc = candidate;
        break;
      }
    }
    if (fourcc == 0) {
      Fail("the device offers no format holocap can store as ", ToString(request.role),
           " (it offers ", offered_text,
           "; supported: ", request.role == SensorRole::kDepth ? "Z16" : "YUYV, MJPG, GREY, Y16",
           ")");
    }
  }
  // Size: the exact one asked for, else the nearest in pixel count; with none asked, the largest.
  const FormatOption* best = nullptr;
  double best_cost = std::numeric_limits<double>::infinity();
  for (const auto& option : offered) {
    if (option.fourcc != fourcc) continue;
    const double area = static_cast<double>(option.width) * option.height;
    double cost;
    if (request.width > 0 && request.height > 0) {
      cost = std::abs(option.width - request.width) + std::abs(option.height - request.height) +
             std::abs(std::log(area / (static_cast<double>(request.width) * request.height)));
    } else {
      cost = -area;
    }
    // Among equal sizes, prefer the one offering the asked rate.
    if (!option.fps.empty() && request.fps > 0) {
      double nearest = std::numeric_limits<double>::infinity();
      for (double f : option.fps) nearest = std::min(nearest, std::abs(f - request.fps));
      cost += 1e-6 * nearest;
    }
    if (cost < best_cost) {
      best_cost = cost;
      best = &option;
    }
  }
  NegotiatedFormat result;
  result.fourcc = fourcc;
  result.width = best->width;
  result.height = best->height;
  result.pixel_format = StoredPixelFormat(fourcc);
  if (!best->fps.empty()) {
    result.fps = best->fps.front();
    for (double f : best->fps) {
      if (std::abs(f - request.fps) < std::abs(result.fps - request.fps)) result.fps = f;
    }
  }
  return result;
}

cv::Mat ConvertFrame(uint32_t fourcc, const uint8_t* data, size_t bytesused, int width, int height,
                     int bytes_per_line) {
  if (width <= 0 || height <= 0) Fail("V4L2 frame without a size");
  auto need = [&](int bytes_per_pixel) {
    const int stride = bytes_per_line > 0 ? bytes_per_line : width * bytes_per_pixel;
    if (stride < width * bytes_per_pixel)
      Fail("V4L2 frame: bytes per line ", stride, " < ", width * bytes_per_pixel);
    const size_t bytes =
        static_cast<size_t>(stride) * (height - 1) + static_cast<size_t>(width) * bytes_per_pixel;
    if (bytesused < bytes) {
      Fail("truncated V4L2 ", FourccToString(fourcc), " frame: ", bytesused, " bytes, ", width, "x",
           height, " needs ", bytes);
    }
    return static_cast<size_t>(stride);
  };
  void* pixels = const_cast<uint8_t*>(data);
  switch (fourcc) {
    case V4L2_PIX_FMT_YUYV: {
      if (width % 2 != 0) Fail("YUYV frame of odd width ", width);
      cv::Mat yuyv(height, width, CV_8UC2, pixels, need(2));
      cv::Mat bgr;
      cv::cvtColor(yuyv, bgr, cv::COLOR_YUV2BGR_YUYV);
      return bgr;
    }
    case V4L2_PIX_FMT_MJPEG: {
      if (bytesused < 4 || data[0] != 0xff || data[1] != 0xd8)
        Fail("MJPEG frame does not start with a JPEG marker");
      cv::Mat bytes(1, static_cast<int>(bytesused), CV_8UC1, pixels);
      cv::Mat bgr = cv::imdecode(bytes, cv::IMREAD_COLOR);
      if (bgr.empty()) Fail("MJPEG frame of ", bytesused, " bytes does not decode");
      if (bgr.cols != width || bgr.rows != height) {
        Fail("MJPEG frame decodes to ", bgr.cols, "x", bgr.rows, ", the format says ", width, "x",
             height);
      }
      return bgr;
    }
    case V4L2_PIX_FMT_GREY:
      return cv::Mat(height, width, CV_8UC1, pixels, need(1)).clone();
    case V4L2_PIX_FMT_Y16:
      return cv::Mat(height, width, CV_16UC1, pixels, need(2)).clone();
    case V4L2_PIX_FMT_Z16: {
      cv::Mat millimetres(height, width, CV_16UC1, pixels, need(2));
      cv::Mat metres(height, width, CV_32FC1);
      for (int y = 0; y < height; ++y) {
        const uint16_t* in = millimetres.ptr<uint16_t>(y);
        float* out = metres.ptr<float>(y);
        for (int x = 0; x < width; ++x) {
          out[x] = in[x] == 0 ? std::numeric_limits<float>::quiet_NaN()
                              : static_cast<float>(in[x]) * 1e-3f;
        }
      }
      return metres;
    }
  }
  StoredPixelFormat(fourcc);  // throws naming the format
  return {};
}

BufferTime MapTimestamp(int64_t tv_sec, int64_t tv_usec, uint32_t flags) {
  BufferTime time;
  time.ns = tv_sec * 1000000000LL + tv_usec * 1000LL;
  switch (flags & V4L2_BUF_FLAG_TIMESTAMP_MASK) {
    case V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC:
      time.clock = "CLOCK_MONOTONIC";
      break;
    case V4L2_BUF_FLAG_TIMESTAMP_COPY:
      time.clock = "unknown (copied from output)";
      break;
    default:
      time.clock = "unknown";
      break;
  }
  return time;
}

BufferQueue::BufferQueue(int count) { Reset(count); }

void BufferQueue::Reset(int count) {
  states_.assign(count, State::kIdle);
  have_sequence_ = false;
  skipped_ = 0;
}

BufferQueue::State BufferQueue::state(int index) const {
  if (index < 0 || index >= size())
    Fail("V4L2 buffer ", index, " does not exist (", size(), " buffers)");
  return states_[index];
}

void BufferQueue::Queued(int index) {
  if (state(index) == State::kQueued) Fail("V4L2 buffer ", index, " is already queued");
  states_[index] = State::kQueued;
}

void BufferQueue::Dequeued(int index) {
  if (state(index) != State::kQueued)
    Fail("the driver returned V4L2 buffer ", index, ", which was not queued");
  states_[index] = State::kDequeued;
}

int BufferQueue::queued() const {
  return static_cast<int>(std::count(states_.begin(), states_.end(), State::kQueued));
}

uint64_t BufferQueue::Sequence(uint32_t sequence) {
  uint64_t gap = 0;
  // 32-bit counter: unsigned subtraction handles the wrap.
  if (have_sequence_) gap = static_cast<uint32_t>(sequence - last_sequence_ - 1);
  if (gap > (1u << 30)) gap = 0;  // the counter went backwards (restart): not a loss
  have_sequence_ = true;
  last_sequence_ = sequence;
  skipped_ += gap;
  return gap;
}

}  // namespace v4l2

namespace {

int Ioctl(int fd, unsigned long request, void* arg) {
  int result;
  do {
    result = v4l2_ioctl(fd, request, arg);
  } while (result == -1 && errno == EINTR);
  return result;
}

class V4l2Sensor : public Sensor {
 public:
  explicit V4l2Sensor(const SensorSpec& spec) : uri_(spec.uri) {
    path_ = ParseSensorUri(spec.uri).path;
    if (path_.empty()) Fail("'", uri_, "': no device path (expected v4l2:/dev/videoN)");
    fd_ = v4l2_open(path_.c_str(), O_RDWR | O_NONBLOCK);
    if (fd_ < 0 && errno == ENOTTY) Fail("'", uri_, "': ", path_, " is not a V4L2 device");
    if (fd_ < 0) Fail("'", uri_, "': cannot open ", path_, ": ", std::strerror(errno));
    try {
      Configure(spec);
    } catch (...) {
      v4l2_close(fd_);
      throw;
    }
  }

  ~V4l2Sensor() override {
    if (streaming_) {
      v4l2_buf_type type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
      Ioctl(fd_, VIDIOC_STREAMOFF, &type);
    }
    for (auto& mapping : mappings_) v4l2_munmap(mapping.first, mapping.second);
    v4l2_close(fd_);
  }

  const StreamInfo& stream() const override { return info_; }

  void Start() override {
    for (int i = 0; i < queue_.size(); ++i) QueueBuffer(i);
    v4l2_buf_type type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (Ioctl(fd_, VIDIOC_STREAMON, &type) < 0) ThrowErrno("VIDIOC_STREAMON");
    streaming_ = true;
  }

  void Stop() override {
    if (!streaming_) return;
    v4l2_buf_type type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    streaming_ = false;
    if (Ioctl(fd_, VIDIOC_STREAMOFF, &type) < 0 && errno != ENODEV) ThrowErrno("VIDIOC_STREAMOFF");
    queue_.Reset(queue_.size());  // STREAMOFF returns every buffer to us
  }

  bool Grab(Frame* frame, std::chrono::milliseconds timeout) override {
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    while (true) {
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
          deadline - std::chrono::steady_clock::now());
      if (left.count() < 0) return false;
      pollfd pfd{fd_, POLLIN, 0};
      int ready = poll(&pfd, 1, static_cast<int>(left.count()));
      if (ready < 0 && errno == EINTR) continue;
      if (ready < 0) ThrowErrno("poll");
      if (ready == 0) return false;
      if (pfd.revents & (POLLERR | POLLHUP)) ThrowLost();
      v4l2_buffer buffer{};
      buffer.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
      buffer.memory = V4L2_MEMORY_MMAP;
      if (Ioctl(fd_, VIDIOC_DQBUF, &buffer) < 0) {
        if (errno == EAGAIN) continue;
        if (errno == ENODEV) ThrowLost();
        if (errno == EIO) {  // a transfer error; the buffer comes back flagged
          ++lost_;
          continue;
        }
        ThrowErrno("VIDIOC_DQBUF");
      }
      queue_.Dequeued(static_cast<int>(buffer.index));
      const uint64_t skipped = queue_.Sequence(buffer.sequence);
      lost_ += skipped;
      if (buffer.flags & V4L2_BUF_FLAG_ERROR) {
        ++lost_;
        QueueBuffer(static_cast<int>(buffer.index));
        continue;
      }
      cv::Mat image;
      try {
        image = v4l2::ConvertFrame(
            format_.fourcc, static_cast<const uint8_t*>(mappings_[buffer.index].first),
            buffer.bytesused, format_.width, format_.height, bytes_per_line_);
      } catch (const Error&) {
        ++lost_;  // a corrupt MJPEG frame is a lost frame, not the end of the take
        QueueBuffer(static_cast<int>(buffer.index));
        continue;
      }
      v4l2::BufferTime time =
          v4l2::MapTimestamp(buffer.timestamp.tv_sec, buffer.timestamp.tv_usec, buffer.flags);
      QueueBuffer(static_cast<int>(buffer.index));
      frame->sensor = info_.name;
      frame->image = std::move(image);
      frame->timestamp_ns = time.ns;
      frame->sequence = buffer.sequence;
      ++delivered_;
      return true;
    }
  }

  SensorStats stats() const override {
    SensorStats stats;
    stats.frames_delivered = delivered_;
    stats.frames_lost = lost_;
    stats.details = {{"fourcc", v4l2::FourccToString(format_.fourcc)}, {"fps", format_.fps}};
    return stats;
  }

 private:
  [[noreturn]] void ThrowErrno(const char* what) {
    if (errno == ENODEV) ThrowLost();
    Fail("'", uri_, "': ", what, " failed: ", std::strerror(errno));
  }
  [[noreturn]] void ThrowLost() { Fail("'", uri_, "': the device was unplugged (ENODEV)"); }

  void QueueBuffer(int index) {
    v4l2_buffer buffer{};
    buffer.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    buffer.memory = V4L2_MEMORY_MMAP;
    buffer.index = static_cast<uint32_t>(index);
    if (Ioctl(fd_, VIDIOC_QBUF, &buffer) < 0) ThrowErrno("VIDIOC_QBUF");
    queue_.Queued(index);
  }

  void Configure(const SensorSpec& spec) {
    v4l2_capability caps{};
    if (Ioctl(fd_, VIDIOC_QUERYCAP, &caps) < 0) {
      if (errno == ENOTTY || errno == EINVAL)
        Fail("'", uri_, "': ", path_, " is not a V4L2 device");
      ThrowErrno("VIDIOC_QUERYCAP");
    }
    const uint32_t device_caps =
        (caps.capabilities & V4L2_CAP_DEVICE_CAPS) ? caps.device_caps : caps.capabilities;
    if (!(device_caps & V4L2_CAP_VIDEO_CAPTURE))
      Fail("'", uri_, "': ", path_, " cannot capture video");
    if (!(device_caps & V4L2_CAP_STREAMING))
      Fail("'", uri_, "': ", path_, " cannot stream (no MMAP I/O)");

    std::vector<v4l2::FormatOption> offered;
    v4l2_fmtdesc desc{};
    desc.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    for (desc.index = 0; Ioctl(fd_, VIDIOC_ENUM_FMT, &desc) == 0; ++desc.index) {
      v4l2_frmsizeenum size{};
      size.pixel_format = desc.pixelformat;
      for (size.index = 0; Ioctl(fd_, VIDIOC_ENUM_FRAMESIZES, &size) == 0; ++size.index) {
        v4l2::FormatOption option;
        option.fourcc = desc.pixelformat;
        if (size.type == V4L2_FRMSIZE_TYPE_DISCRETE) {
          option.width = static_cast<int>(size.discrete.width);
          option.height = static_cast<int>(size.discrete.height);
        } else {
          option.width = static_cast<int>(size.stepwise.max_width);
          option.height = static_cast<int>(size.stepwise.max_height);
        }
        v4l2_frmivalenum interval{};
        interval.pixel_format = desc.pixelformat;
        interval.width = static_cast<uint32_t>(option.width);
        interval.height = static_cast<uint32_t>(option.height);
        for (interval.index = 0; Ioctl(fd_, VIDIOC_ENUM_FRAMEINTERVALS, &interval) == 0;
             ++interval.index) {
          if (interval.type == V4L2_FRMIVAL_TYPE_DISCRETE && interval.discrete.numerator > 0) {
            option.fps.push_back(static_cast<double>(interval.discrete.denominator) /
                                 interval.discrete.numerator);
          }
          if (interval.type != V4L2_FRMIVAL_TYPE_DISCRETE) break;
        }
        offered.push_back(option);
        if (size.type != V4L2_FRMSIZE_TYPE_DISCRETE) break;
      }
    }
    v4l2::FormatRequest request;
    const nlohmann::json& options = spec.options;
    if (options.contains("fourcc"))
      request.fourcc = v4l2::FourccFromString(options["fourcc"].get<std::string>());
    request.width = options.value("width", 0);
    request.height = options.value("height", 0);
    request.fps = options.value("fps", 30.0);
    request.role = spec.role;
    try {
      format_ = v4l2::Negotiate(offered, request);
    } catch (const Error& e) {
      Fail("'", uri_, "': ", e.what());
    }

    v4l2_format fmt{};
    fmt.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    fmt.fmt.pix.pixelformat = format_.fourcc;
    fmt.fmt.pix.width = static_cast<uint32_t>(format_.width);
    fmt.fmt.pix.height = static_cast<uint32_t>(format_.height);
    fmt.fmt.pix.field = V4L2_FIELD_NONE;
    if (Ioctl(fd_, VIDIOC_S_FMT, &fmt) < 0) ThrowErrno("VIDIOC_S_FMT");
    if (fmt.fmt.pix.pixelformat != format_.fourcc) {
      Fail("'", uri_, "': asked for ", v4l2::FourccToString(format_.fourcc), ", the driver set ",
           v4l2::FourccToString(fmt.fmt.pix.pixelformat));
    }
    format_.width = static_cast<int>(fmt.fmt.pix.width);
    format_.height = static_cast<int>(fmt.fmt.pix.height);
    bytes_per_line_ = static_cast<int>(fmt.fmt.pix.bytesperline);
    if (format_.fps > 0) {
      v4l2_streamparm parm{};
      parm.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
      parm.parm.capture.timeperframe.numerator = 1000;
      parm.parm.capture.timeperframe.denominator =
          static_cast<uint32_t>(std::lround(format_.fps * 1000));
      Ioctl(fd_, VIDIOC_S_PARM, &parm);  // not every driver lets the rate be set; keep its own
    }

    const int count = options.value("buffers", 4);
    if (count < 2) Fail("'", uri_, "': option buffers must be at least 2");
    v4l2_requestbuffers request_buffers{};
    request_buffers.count = static_cast<uint32_t>(count);
    request_buffers.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    request_buffers.memory = V4L2_MEMORY_MMAP;
    if (Ioctl(fd_, VIDIOC_REQBUFS, &request_buffers) < 0) ThrowErrno("VIDIOC_REQBUFS");
    if (request_buffers.count < 2)
      Fail("'", uri_, "': the driver granted only ", request_buffers.count, " buffer(s)");
    queue_.Reset(static_cast<int>(request_buffers.count));
    for (uint32_t i = 0; i < request_buffers.count; ++i) {
      v4l2_buffer buffer{};
      buffer.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
      buffer.memory = V4L2_MEMORY_MMAP;
      buffer.index = i;
      if (Ioctl(fd_, VIDIOC_QUERYBUF, &buffer) < 0) ThrowErrno("VIDIOC_QUERYBUF");
      void* data = v4l2_mmap(nullptr, buffer.length, PROT_READ | PROT_WRITE, MAP_SHARED, fd_,
                             buffer.m.offset);
      if (data == MAP_FAILED) ThrowErrno("mmap");
      mappings_.emplace_back(data, buffer.length);
    }

    info_.name = spec.name;
    info_.uri = spec.uri;
    info_.role = spec.role;
    info_.width = format_.width;
    info_.height = format_.height;
    info_.pixel_format = format_.pixel_format;
    info_.codec = format_.pixel_format == "depth_m" ? ImageCodec::kExr : ImageCodec::kPng;
    // The clock is known only from the first buffer's flags; every UVC and modern driver
    // stamps CLOCK_MONOTONIC.
    info_.clock = "CLOCK_MONOTONIC";
  }

  std::string uri_;
  std::string path_;
  int fd_ = -1;
  bool streaming_ = false;
  v4l2::NegotiatedFormat format_;
  int bytes_per_line_ = 0;
  std::vector<std::pair<void*, size_t>> mappings_;
  v4l2::BufferQueue queue_;
  StreamInfo info_;
  std::atomic<uint64_t> delivered_{0};
  std::atomic<uint64_t> lost_{0};
};

class V4l2Driver : public Driver {
 public:
  std::string scheme() const override { return "v4l2"; }
  std::string description() const override {
    return "Video4Linux2 cameras and depth sensors (MMAP streaming)";
  }
  std::vector<DeviceInfo> Enumerate() override {
    std::vector<DeviceInfo> devices;
    std::error_code ec;
    for (const auto& entry : std::filesystem::directory_iterator("/dev", ec)) {
      const std::string name = entry.path().filename().string();
      if (name.rfind("video", 0) != 0) continue;
      int fd = v4l2_open(entry.path().c_str(), O_RDWR | O_NONBLOCK);
      if (fd < 0) continue;
      v4l2_capability caps{};
      if (Ioctl(fd, VIDIOC_QUERYCAP, &caps) == 0) {
        const uint32_t device_caps =
            (caps.capabilities & V4L2_CAP_DEVICE_CAPS) ? caps.device_caps : caps.capabilities;
        if (device_caps & V4L2_CAP_VIDEO_CAPTURE) {
          devices.push_back({"v4l2:" + entry.path().string(),
                             std::string(reinterpret_cast<const char*>(caps.card)) + " (" +
                                 reinterpret_cast<const char*>(caps.driver) + ")",
                             SensorRole::kColor});
        }
      }
      v4l2_close(fd);
    }
    std::sort(devices.begin(), devices.end(),
              [](const auto& a, const auto& b) { return a.uri < b.uri; });
    return devices;
  }
  std::unique_ptr<Sensor> Open(const SensorSpec& spec) override {
    return std::make_unique<V4l2Sensor>(spec);
  }
};

}  // namespace

void RegisterV4l2Driver(DriverRegistry& registry) {
  registry.Register(std::make_unique<V4l2Driver>());
}

}  // namespace holocap
