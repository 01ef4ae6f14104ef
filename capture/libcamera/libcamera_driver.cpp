#include "capture/libcamera/libcamera_driver.h"

#include <sys/mman.h>

#include <libcamera/libcamera.h>
#include <condition_variable>
#include <cstdlib>
#include <deque>
#include <mutex>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "core/error.h"

namespace holocap {
namespace {

namespace lc = libcamera;

// libcamera allows one CameraManager per process; sensors and enumeration share it.
std::shared_ptr<lc::CameraManager> Manager() {
  static std::mutex mutex;
  static std::weak_ptr<lc::CameraManager> shared;
  std::lock_guard lock(mutex);
  if (auto manager = shared.lock()) return manager;
  // libcamera logs every start (its version, a missing IPA module) to stderr, which would
  // interleave with holocap's own output: only its errors are shown, unless the user chose
  // levels. Its logger reads LIBCAMERA_LOG_LEVELS once, when the first CameraManager creates
  // it, and logSetLevel() reaches only the log categories that exist already, so the default
  // goes in through the variable, before the first manager.
  setenv("LIBCAMERA_LOG_LEVELS", "*:ERROR", /*overwrite=*/0);
  auto manager =
      std::shared_ptr<lc::CameraManager>(new lc::CameraManager(), [](lc::CameraManager* m) {
        m->stop();
        delete m;
      });
  if (int ret = manager->start(); ret < 0)
    Fail("libcamera: the camera manager did not start (error ", ret, ")");
  shared = manager;
  return manager;
}

std::string CameraList(const lc::CameraManager& manager) {
  std::string list;
  for (const auto& camera : manager.cameras()) list += (list.empty() ? "" : ", ") + camera->id();
  return list.empty() ? "none; libcamera " + lc::CameraManager::version() +
                            " found no camera on this machine"
                      : list;
}

class LibcameraSensor : public Sensor {
 public:
  explicit LibcameraSensor(const SensorSpec& spec) : uri_(spec.uri), manager_(Manager()) {
    const std::string id = ParseSensorUri(spec.uri).path;
    camera_ = manager_->get(id);
    if (!camera_)
      Fail("'", uri_, "': no camera '", id, "' (libcamera sees: ", CameraList(*manager_), ")");
    if (camera_->acquire() < 0) Fail("'", uri_, "': the camera is in use by another process");
    acquired_ = true;
    try {
      Configure(spec);
    } catch (...) {
      Release();
      throw;
    }
  }

  ~LibcameraSensor() override { Release(); }

  const StreamInfo& stream() const override { return info_; }

  void Start() override {
    if (camera_->start() < 0) Fail("'", uri_, "': the camera did not start");
    started_ = true;
    for (auto& request : requests_) {
      if (camera_->queueRequest(request.get()) < 0)
        Fail("'", uri_, "': a capture request was refused");
    }
  }

  void Stop() override {
    if (!started_) return;
    started_ = false;
    camera_->stop();  // completes every queued request as cancelled
    std::lock_guard lock(mutex_);
    completed_.clear();
  }

  bool Grab(Frame* frame, std::chrono::milliseconds timeout) override {
    lc::Request* request = nullptr;
    {
      std::unique_lock lock(mutex_);
      if (!cv_.wait_for(lock, timeout, [&] { return !completed_.empty() || disconnected_; }))
        return false;
      if (disconnected_) Fail("'", uri_, "': the camera was unplugged");
      request = completed_.front();
      completed_.pop_front();
    }
    lc::FrameBuffer* buffer = request->buffers().begin()->second;
    const lc::FrameMetadata& metadata = buffer->metadata();
    bool ok = metadata.status == lc::FrameMetadata::FrameSuccess;
    if (ok) {
      const auto& mapping = mappings_.at(buffer);
      const size_t used =
          metadata.planes().empty() ? mapping.second : metadata.planes()[0].bytesused;
      try {
        frame->image = Convert(static_cast<const uint8_t*>(mapping.first), used);
      } catch (const Error&) {
        ok = false;
      }
      const auto sensor_time = request->metadata().get(lc::controls::SensorTimestamp);
      frame->timestamp_ns = sensor_time ? *sensor_time : static_cast<int64_t>(metadata.timestamp);
      frame->sequence = metadata.sequence;
      frame->sensor = info_.name;
    }
    request->reuse(lc::Request::ReuseBuffers);
    if (started_) camera_->queueRequest(request);
    if (!ok) {
      ++lost_;
      return Grab(frame, std::chrono::milliseconds(0));
    }
    ++delivered_;
    return true;
  }

  SensorStats stats() const override {
    SensorStats stats;
    stats.frames_delivered = delivered_;
    stats.frames_lost = lost_;
    stats.details = {{"pixel_format", pixel_format_.toString()}};
    return stats;
  }

 private:
  void Configure(const SensorSpec& spec) {
    config_ = camera_->generateConfiguration({lc::StreamRole::VideoRecording});
    if (!config_ || config_->empty())
      Fail("'", uri_, "': the camera offers no video configuration");
    lc::StreamConfiguration& stream_config = config_->at(0);
    // Formats OpenCV takes without an ISP-specific conversion, best first.
    const std::vector<lc::PixelFormat> preferred = {lc::formats::RGB888, lc::formats::BGR888,
                                                    lc::formats::YUYV, lc::formats::MJPEG,
                                                    lc::formats::R8};
    const auto offered = stream_config.formats().pixelformats();
    bool found = false;
    for (const auto& format : preferred) {
      if (std::find(offered.begin(), offered.end(), format) != offered.end()) {
        stream_config.pixelFormat = format;
        found = true;
        break;
      }
    }
    if (!found) {
      std::string list;
      for (const auto& format : offered) list += (list.empty() ? "" : ", ") + format.toString();
      Fail("'", uri_, "': no pixel format holocap can store (it offers ", list, ")");
    }
    const int width = spec.options.value("width", 0), height = spec.options.value("height", 0);
    if (width > 0 && height > 0) stream_config.size = lc::Size(width, height);
    if (spec.options.contains("buffers"))
      stream_config.bufferCount = spec.options["buffers"].get<unsigned>();
    if (config_->validate() == lc::CameraConfiguration::Invalid)
      Fail("'", uri_, "': the configuration is invalid");
    if (camera_->configure(config_.get()) < 0)
      Fail("'", uri_, "': the camera refused its configuration");
    stream_ = stream_config.stream();
    pixel_format_ = stream_config.pixelFormat;
    stride_ = static_cast<int>(stream_config.stride);

    allocator_ = std::make_unique<lc::FrameBufferAllocator>(camera_);
    if (allocator_->allocate(stream_) < 0) Fail("'", uri_, "': cannot allocate frame buffers");
    for (const auto& buffer : allocator_->buffers(stream_)) {
      const auto& plane = buffer->planes().front();
      void* data = mmap(nullptr, plane.length, PROT_READ, MAP_SHARED, plane.fd.get(), plane.offset);
      if (data == MAP_FAILED) Fail("'", uri_, "': cannot map a frame buffer");
      mappings_[buffer.get()] = {data, plane.length};
      std::unique_ptr<lc::Request> request = camera_->createRequest();
      if (!request || request->addBuffer(stream_, buffer.get()) < 0)
        Fail("'", uri_, "': cannot create a request");
      requests_.push_back(std::move(request));
    }
    camera_->requestCompleted.connect(this, &LibcameraSensor::OnRequestCompleted);
    camera_->disconnected.connect(this, &LibcameraSensor::OnDisconnected);

    info_.name = spec.name;
    info_.uri = spec.uri;
    info_.role = spec.role;
    info_.width = static_cast<int>(stream_config.size.width);
    info_.height = static_cast<int>(stream_config.size.height);
    info_.pixel_format = pixel_format_ == lc::formats::R8 ? "mono8" : "bgr8";
    info_.codec = ImageCodec::kPng;
    info_.clock = "CLOCK_MONOTONIC";
  }

  cv::Mat Convert(const uint8_t* data, size_t used) const {
    void* pixels = const_cast<uint8_t*>(data);
    const int w = info_.width, h = info_.height;
    cv::Mat out;
    if (pixel_format_ == lc::formats::MJPEG) {
      out = cv::imdecode(cv::Mat(1, static_cast<int>(used), CV_8UC1, pixels), cv::IMREAD_COLOR);
      if (out.empty() || out.cols != w || out.rows != h) Fail("undecodable MJPEG frame");
      return out;
    }
    const int bytes = pixel_format_ == lc::formats::R8     ? 1
                      : pixel_format_ == lc::formats::YUYV ? 2
                                                           : 3;
    if (used < static_cast<size_t>(stride_) * (h - 1) + static_cast<size_t>(w) * bytes)
      Fail("truncated frame");
    if (pixel_format_ == lc::formats::RGB888)
      return cv::Mat(h, w, CV_8UC3, pixels, stride_).clone();  // B,G,R bytes
    if (pixel_format_ == lc::formats::BGR888)
      cv::cvtColor(cv::Mat(h, w, CV_8UC3, pixels, stride_), out, cv::COLOR_RGB2BGR);
    if (pixel_format_ == lc::formats::YUYV)
      cv::cvtColor(cv::Mat(h, w, CV_8UC2, pixels, stride_), out, cv::COLOR_YUV2BGR_YUYV);
    if (pixel_format_ == lc::formats::R8) out = cv::Mat(h, w, CV_8UC1, pixels, stride_).clone();
    return out;
  }

  void OnRequestCompleted(lc::Request* request) {
    if (request->status() == lc::Request::RequestCancelled) return;
    {
      std::lock_guard lock(mutex_);
      completed_.push_back(request);
    }
    cv_.notify_one();
  }

  void OnDisconnected() {
    {
      std::lock_guard lock(mutex_);
      disconnected_ = true;
    }
    cv_.notify_all();
  }

  void Release() {
    if (started_) Stop();
    if (camera_) {
      camera_->requestCompleted.disconnect(this);
      camera_->disconnected.disconnect(this);
    }
    requests_.clear();
    for (auto& [buffer, mapping] : mappings_) munmap(mapping.first, mapping.second);
    mappings_.clear();
    allocator_.reset();
    if (acquired_) camera_->release();
    acquired_ = false;
  }

  std::string uri_;
  std::shared_ptr<lc::CameraManager> manager_;
  std::shared_ptr<lc::Camera> camera_;
  bool acquired_ = false;
  bool started_ = false;
  std::unique_ptr<lc::CameraConfiguration> config_;
  lc::Stream* stream_ = nullptr;
  lc::PixelFormat pixel_format_;
  int stride_ = 0;
  std::unique_ptr<lc::FrameBufferAllocator> allocator_;
  std::map<const lc::FrameBuffer*, std::pair<void*, size_t>> mappings_;
  std::vector<std::unique_ptr<lc::Request>> requests_;
  StreamInfo info_;
  std::mutex mutex_;
  std::condition_variable cv_;
  std::deque<lc::Request*> completed_;
  bool disconnected_ = false;
  std::atomic<uint64_t> delivered_{0};
  std::atomic<uint64_t> lost_{0};
};

class LibcameraDriver : public Driver {
 public:
  std::string scheme() const override { return "libcamera"; }
  std::string description() const override {
    return "cameras behind libcamera " + lc::CameraManager::version() + " pipeline handlers";
  }
  std::vector<DeviceInfo> Enumerate() override {
    auto manager = Manager();
    std::vector<DeviceInfo> devices;
    for (const auto& camera : manager->cameras()) {
      const auto model = camera->properties().get(lc::properties::Model);
      devices.push_back(
          {"libcamera:" + camera->id(), model ? *model : "camera", SensorRole::kColor});
    }
    return devices;
  }
  std::unique_ptr<Sensor> Open(const SensorSpec& spec) override {
    return std::make_unique<LibcameraSensor>(spec);
  }
};

}  // namespace

void RegisterLibcameraDriver(DriverRegistry& registry) {
  registry.Register(std::make_unique<LibcameraDriver>());
}

}  // namespace holocap
