#include "capture/aravis/aravis_driver.h"

#include <arv.h>

#include <algorithm>
#include <atomic>
#include <deque>
#include <mutex>
#include <opencv2/imgproc.hpp>
#include <thread>

#include "core/error.h"

namespace holocap {
namespace {

// GVSP 1.x block ids are 16-bit and skip 0, so they wrap from 65535 to 1.
constexpr uint64_t kGvBlockIdPeriod = 65535;

std::string TakeMessage(GError* error) {
  std::string message =
      error != nullptr && error->message != nullptr ? error->message : "unknown error";
  g_clear_error(&error);
  return message;
}

// Throws when an aravis call set `error`; `what` names the call for the message.
void ThrowIf(GError* error, const std::string& uri, const std::string& what) {
  if (error != nullptr) Fail(uri, ": ", what, ": ", TakeMessage(error));
}

std::string JoinStrings(const char** items, guint n) {
  std::string joined;
  for (guint i = 0; i < n; ++i) joined += (i ? ", " : "") + std::string(items[i]);
  return joined;
}

// Aravis keeps one device list per process; updating it from two threads at once is unsafe.
std::mutex& AravisListMutex() {
  static std::mutex mutex;
  return mutex;
}

// What libaravis logs through GLib (domain "Aravis": warnings of lost control, timeouts) goes to
// the report (each open sensor's driver details, "aravis_log") instead of stderr, where it would
// come between holocap's own lines. ARV_DEBUG's debug output, asked for by name, is left alone.
class AravisLog {
 public:
  static AravisLog& Get() {
    static AravisLog* log = new AravisLog;  // never destroyed: GLib may call it at exit
    return *log;
  }
  // Messages logged since the n-th (0: all kept).
  std::vector<std::string> Since(uint64_t n) const {
    std::lock_guard lock(mutex_);
    std::vector<std::string> messages;
    const uint64_t first = count_ - messages_.size();
    for (uint64_t i = std::max(n, first); i < count_; ++i) messages.push_back(messages_[i - first]);
    return messages;
  }
  uint64_t count() const {
    std::lock_guard lock(mutex_);
    return count_;
  }

 private:
  static constexpr size_t kKept = 32;
  AravisLog() {
    g_log_set_handler("Aravis",
                      static_cast<GLogLevelFlags>(G_LOG_LEVEL_MASK | G_LOG_FLAG_RECURSION),
                      &AravisLog::Handle, this);
  }
  static void Handle(const gchar*, GLogLevelFlags level, const gchar* message, gpointer self) {
    const char* name = (level & G_LOG_LEVEL_ERROR)      ? "error"
                       : (level & G_LOG_LEVEL_CRITICAL) ? "critical"
                       : (level & G_LOG_LEVEL_WARNING)  ? "warning"
                                                        : "message";
    auto& log = *static_cast<AravisLog*>(self);
    std::lock_guard lock(log.mutex_);
    log.messages_.push_back(Cat(name, ": ", message != nullptr ? message : ""));
    if (log.messages_.size() > kKept) log.messages_.pop_front();
    ++log.count_;
  }
  mutable std::mutex mutex_;
  std::deque<std::string> messages_;
  uint64_t count_ = 0;
};

std::vector<std::string> KnownDeviceIds() {
  std::lock_guard lock(AravisListMutex());
  arv_update_device_list();
  std::vector<std::string> ids;
  for (unsigned i = 0; i < arv_get_n_devices(); ++i) ids.emplace_back(arv_get_device_id(i));
  return ids;
}

class AravisSensor : public Sensor {
 public:
  explicit AravisSensor(const SensorSpec& spec)
      : uri_(spec.uri), log_from_(AravisLog::Get().count()) {
    const std::string id = ParseSensorUri(spec.uri).path;
    if (id.empty()) Fail("'", spec.uri, "': no device id (expected aravis:<device-id>)");
    if (id.rfind("Fake_", 0) == 0) arv_enable_interface("Fake");
    const nlohmann::json& options = spec.options;
    GError* error = nullptr;
    {
      std::lock_guard lock(AravisListMutex());
      camera_ = arv_camera_new(id.c_str(), &error);
    }
    if (camera_ == nullptr) {
      g_clear_error(&error);
      std::string seen;
      for (const auto& known : KnownDeviceIds()) seen += (seen.empty() ? "" : ", ") + known;
      Fail("'", spec.uri, "': no such camera (aravis sees: ", seen.empty() ? "none" : seen, ")");
    }
    device_ = arv_camera_get_device(camera_);
    lost_handler_ =
        g_signal_connect(device_, "control-lost", G_CALLBACK(&AravisSensor::OnControlLost), this);

    ConfigurePixelFormat(options.value("pixel_format", ""), options.value("debayer", true));
    if (options.contains("roi")) ConfigureRoi(options["roi"]);
    if (spec.exposure_us > 0)
      ConfigureFloat("exposure", spec.exposure_us, &arv_camera_get_exposure_time_bounds,
                     &arv_camera_set_exposure_time);
    if (spec.gain_db > 0)
      ConfigureFloat("gain", spec.gain_db, &arv_camera_get_gain_bounds, &arv_camera_set_gain);
    ConfigureTrigger(options.value("sync", "free-run"), options.value("trigger_source", "Line0"),
                     options.value("fps", 0.0));
    ConfigurePtp(options.value("ptp", false));
    const std::string timestamp = options.value("timestamp", "device");
    if (timestamp != "device" && timestamp != "host" && timestamp != "raw-device") {
      Fail("'", uri_, "': option timestamp must be \"device\", \"host\" or \"raw-device\"");
    }
    device_clock_ = timestamp != "host";
    map_device_to_host_ = timestamp == "device" && !options.value("ptp", false);

    gint x = 0, y = 0, width = 0, height = 0;
    arv_camera_get_region(camera_, &x, &y, &width, &height, &error);
    ThrowIf(error, uri_, "reading the region");
    stream_info_.name = spec.name;
    stream_info_.uri = spec.uri;
    stream_info_.role = spec.role;
    stream_info_.width = width;
    stream_info_.height = height;
    stream_info_.pixel_format = layout_.stored;
    stream_info_.codec = ImageCodec::kZstd;
    stream_info_.clock = !device_clock_ || map_device_to_host_
                             ? "CLOCK_REALTIME"
                             : (ptp_enabled_ ? "PTP" : "device:" + id);

    is_gige_ = arv_camera_is_gv_device(camera_);
    if (is_gige_ && !options.value("packet_socket", false)) {
      arv_camera_gv_set_stream_options(camera_, ARV_GV_STREAM_OPTION_PACKET_SOCKET_DISABLED);
    }
    stream_ = arv_camera_create_stream(camera_, nullptr, nullptr, &error);
    if (stream_ == nullptr) ThrowIf(error, uri_, "creating the stream");
    const guint payload = arv_camera_get_payload(camera_, &error);
    ThrowIf(error, uri_, "reading the payload size");
    if (is_gige_) {
      // A few frames of kernel buffer absorb scheduling hiccups of the stream thread; one frame
      // (aravis' automatic size) loses packets when many cameras share two cores.
      const int64_t socket_buffer = std::max<int64_t>(int64_t{payload} * 4, 1 << 20);
      g_object_set(stream_, "socket-buffer", ARV_GV_STREAM_SOCKET_BUFFER_FIXED,
                   "socket-buffer-size", static_cast<gint>(socket_buffer), "packet-resend",
                   options.value("packet_resend", true) ? ARV_GV_STREAM_PACKET_RESEND_ALWAYS
                                                        : ARV_GV_STREAM_PACKET_RESEND_NEVER,
                   nullptr);
      if (options.contains("packet_timeout_ms")) {
        g_object_set(stream_, "packet-timeout",
                     static_cast<guint>(options["packet_timeout_ms"].get<double>() * 1000),
                     nullptr);
      }
      if (options.contains("frame_retention_ms")) {
        g_object_set(stream_, "frame-retention",
                     static_cast<guint>(options["frame_retention_ms"].get<double>() * 1000),
                     nullptr);
      }
    }
    const int buffers = options.value("buffers", 16);
    if (buffers < 2) Fail("'", uri_, "': option buffers must be at least 2");
    for (int i = 0; i < buffers; ++i)
      arv_stream_push_buffer(stream_, arv_buffer_new(payload, nullptr));
  }

  ~AravisSensor() override {
    if (lost_handler_ != 0) g_signal_handler_disconnect(device_, lost_handler_);
    if (abandoned_) {
      // Releasing a GigE camera talks to it (closing its stream channel, leaving control), and
      // each unanswered GVCP request waits out aravis' retries (2.5 s in 0.8): let a thread of
      // its own wait for a camera that is gone.
      std::thread([camera = camera_, stream = stream_] {
        if (stream != nullptr) g_object_unref(stream);
        g_object_unref(camera);
      }).detach();
      return;
    }
    if (started_) arv_camera_stop_acquisition(camera_, nullptr);
    if (stream_ != nullptr) g_object_unref(stream_);
    g_object_unref(camera_);
  }

  const StreamInfo& stream() const override { return stream_info_; }

  void Start() override {
    GError* error = nullptr;
    arv_camera_start_acquisition(camera_, &error);
    ThrowIf(error, uri_, "starting acquisition");
    started_ = true;
  }

  void Stop() override {
    if (!started_) return;
    started_ = false;
    GError* error = nullptr;
    arv_camera_stop_acquisition(camera_, &error);
    if (error != nullptr && !control_lost_) ThrowIf(error, uri_, "stopping acquisition");
    g_clear_error(&error);
  }

  // The camera stopped answering: stop nothing on it, and release it in the background.
  void Abandon() override {
    started_ = false;
    abandoned_ = true;
  }

  bool Grab(Frame* frame, std::chrono::milliseconds timeout) override {
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    while (true) {
      if (control_lost_)
        Fail(uri_, ": the camera stopped answering (control lost; unplugged or powered off?)");
      auto left = std::chrono::duration_cast<std::chrono::microseconds>(
          deadline - std::chrono::steady_clock::now());
      if (left.count() <= 0) return false;
      // Short waits so that a lost camera is noticed while no frames come.
      const guint64 wait_us = std::min<int64_t>(left.count(), 100000);
      ArvBuffer* buffer = arv_stream_timeout_pop_buffer(stream_, wait_us);
      if (buffer == nullptr) continue;
      const bool complete = arv_buffer_get_status(buffer) == ARV_BUFFER_STATUS_SUCCESS &&
                            arv_buffer_get_payload_type(buffer) == ARV_BUFFER_PAYLOAD_TYPE_IMAGE;
      if (!complete) {
        ++frames_incomplete_;
        arv_stream_push_buffer(stream_, buffer);
        continue;
      }
      size_t size = 0;
      const void* data = arv_buffer_get_image_data(buffer, &size);
      const int width = arv_buffer_get_image_width(buffer);
      const int height = arv_buffer_get_image_height(buffer);
      const size_t expected = static_cast<size_t>(width) * height * CV_ELEM_SIZE(layout_.raw_type);
      if (data == nullptr || size < expected || width != stream_info_.width ||
          height != stream_info_.height) {
        ++frames_incomplete_;
        arv_stream_push_buffer(stream_, buffer);
        continue;
      }
      cv::Mat wire(height, width, layout_.raw_type, const_cast<void*>(data));
      frame->image = ConvertAravisImage(wire, layout_);
      if (frame->image.data == wire.data) frame->image = frame->image.clone();
      frame->sensor = stream_info_.name;
      const int64_t device_ns = static_cast<int64_t>(arv_buffer_get_timestamp(buffer));
      const int64_t host_ns = static_cast<int64_t>(arv_buffer_get_system_timestamp(buffer));
      frame->timestamp_ns = !device_clock_        ? host_ns
                            : map_device_to_host_ ? MapToHost(device_ns, host_ns)
                                                  : device_ns;
      frame->sequence = UnwrapFrameId(arv_buffer_get_frame_id(buffer));
      // The buffer goes back before the frame leaves, so the driver's queue never waits on us.
      arv_stream_push_buffer(stream_, buffer);
      ++frames_delivered_;
      return true;
    }
  }

  bool supports_software_trigger() const override { return software_trigger_; }

  void Trigger() override {
    GError* error = nullptr;
    arv_camera_software_trigger(camera_, &error);
    ThrowIf(error, uri_, "software trigger");
  }

  SensorStats stats() const override {
    SensorStats stats;
    stats.frames_delivered = frames_delivered_;
    guint64 completed = 0, failures = 0, underruns = 0;
    arv_stream_get_statistics(stream_, &completed, &failures, &underruns);
    // Failures are the buffers Grab() saw incomplete; underruns are frames that found no
    // buffer. Both were lost inside the driver.
    stats.frames_lost = std::max<uint64_t>(frames_incomplete_, failures) + underruns;
    for (guint i = 0; i < arv_stream_get_n_infos(stream_); ++i) {
      const char* name = arv_stream_get_info_name(stream_, i);
      if (arv_stream_get_info_type(stream_, i) == G_TYPE_UINT64) {
        stats.details[name] = arv_stream_get_info_uint64(stream_, i);
      } else {
        stats.details[name] = arv_stream_get_info_double(stream_, i);
      }
    }
    stats.details["ptp"] = ptp_status_;
    stats.details["control_lost"] = control_lost_.load();
    if (auto messages = AravisLog::Get().Since(log_from_); !messages.empty())
      stats.details["aravis_log"] = messages;
    return stats;
  }

 private:
  static void OnControlLost(ArvDevice*, gpointer self) {
    static_cast<AravisSensor*>(self)->control_lost_ = true;
  }

  void ConfigurePixelFormat(const std::string& wanted, bool debayer) {
    GError* error = nullptr;
    if (!wanted.empty()) {
      guint n = 0;
      const char** available =
          arv_camera_dup_available_pixel_formats_as_strings(camera_, &n, &error);
      ThrowIf(error, uri_, "listing pixel formats");
      bool offered = false;
      for (guint i = 0; i < n; ++i) offered |= wanted == available[i];
      std::string list = JoinStrings(available, n);
      g_free(available);
      if (!offered)
        Fail("'", uri_, "': the camera has no pixel format '", wanted, "' (it offers ", list, ")");
      layout_ = AravisLayoutFor(wanted, debayer);
      arv_camera_set_pixel_format_from_string(camera_, wanted.c_str(), &error);
      ThrowIf(error, uri_, "setting pixel format " + wanted);
    } else {
      const char* current = arv_camera_get_pixel_format_as_string(camera_, &error);
      ThrowIf(error, uri_, "reading the pixel format");
      layout_ = AravisLayoutFor(current != nullptr ? current : "", debayer);
    }
  }

  void ConfigureRoi(const nlohmann::json& roi) {
    if (!roi.is_array() || roi.size() != 4)
      Fail("'", uri_, "': option roi must be [x, y, width, height]");
    const int x = roi[0], y = roi[1], width = roi[2], height = roi[3];
    GError* error = nullptr;
    gint xmin, xmax, ymin, ymax, wmin, wmax, hmin, hmax;
    arv_camera_get_x_offset_bounds(camera_, &xmin, &xmax, &error);
    if (error == nullptr) arv_camera_get_y_offset_bounds(camera_, &ymin, &ymax, &error);
    if (error == nullptr) arv_camera_get_width_bounds(camera_, &wmin, &wmax, &error);
    if (error == nullptr) arv_camera_get_height_bounds(camera_, &hmin, &hmax, &error);
    ThrowIf(error, uri_, "reading region bounds");
    if (width < wmin || width > wmax || height < hmin || height > hmax || x < 0 || y < 0 ||
        x + width > wmax || y + height > hmax) {
      Fail("'", uri_, "': roi [", x, ", ", y, ", ", width, ", ", height,
           "] is outside the sensor (width ", wmin, "..", wmax, ", height ", hmin, "..", hmax, ")");
    }
    arv_camera_set_region(camera_, x, y, width, height, &error);
    ThrowIf(error, uri_, "setting the region");
  }

  using BoundsFn = void (*)(ArvCamera*, double*, double*, GError**);
  using SetFn = void (*)(ArvCamera*, double, GError**);
  void ConfigureFloat(const char* what, double value, BoundsFn bounds, SetFn set) {
    GError* error = nullptr;
    double lo = 0, hi = 0;
    bounds(camera_, &lo, &hi, &error);
    ThrowIf(error, uri_, std::string("reading ") + what + " bounds");
    if (value < lo || value > hi)
      Fail("'", uri_, "': ", what, " ", value, " is outside ", lo, "..", hi);
    set(camera_, value, &error);
    ThrowIf(error, uri_, std::string("setting ") + what);
  }

  void ConfigureTrigger(const std::string& sync, const std::string& source, double fps) {
    GError* error = nullptr;
    if ((sync == "software" || sync == "hardware") &&
        arv_camera_is_frame_rate_available(camera_, nullptr)) {
      // A triggered camera still paces itself by AcquisitionFrameRate and folds triggers that
      // come faster into one frame; its fastest rate makes the trigger alone decide. Set
      // before the trigger, since aravis turns triggering off when it sets a rate.
      double lo = 0, hi = 0;
      arv_camera_get_frame_rate_bounds(camera_, &lo, &hi, &error);
      if (error == nullptr && hi > 0)
        arv_camera_set_frame_rate(camera_, std::min(hi, 1000.0), &error);
      ThrowIf(error, uri_, "setting the frame-rate limit");
    }
    if (sync == "software") {
      arv_camera_set_trigger(camera_, "Software", &error);
      ThrowIf(error, uri_, "software trigger mode");
      software_trigger_ = true;
    } else if (sync == "hardware") {
      guint n = 0;
      const char** sources = arv_camera_dup_available_trigger_sources(camera_, &n, &error);
      ThrowIf(error, uri_, "listing trigger sources");
      bool offered = false;
      for (guint i = 0; i < n; ++i) offered |= source == sources[i];
      std::string list = JoinStrings(sources, n);
      g_free(sources);
      if (!offered) Fail("'", uri_, "': no trigger source '", source, "' (it offers ", list, ")");
      arv_camera_set_trigger(camera_, source.c_str(), &error);
      ThrowIf(error, uri_, "hardware trigger on " + source);
    } else if (sync == "free-run") {
      arv_camera_clear_triggers(camera_, &error);
      ThrowIf(error, uri_, "free-run mode");
      if (fps > 0 && arv_camera_is_frame_rate_available(camera_, nullptr)) {
        ConfigureFloat("frame rate", fps, &arv_camera_get_frame_rate_bounds,
                       &arv_camera_set_frame_rate);
      }
    } else {
      Fail("'", uri_, "': option sync must be software, hardware or free-run (not '", sync, "')");
    }
  }

  void ConfigurePtp(bool enable) {
    // SFNC 2.x names it PtpEnable; older GigE Vision cameras GevIEEE1588.
    const char* enable_feature = nullptr;
    const char* status_feature = nullptr;
    if (arv_device_is_feature_available(device_, "PtpEnable", nullptr)) {
      enable_feature = "PtpEnable";
      status_feature = "PtpStatus";
    } else if (arv_device_is_feature_available(device_, "GevIEEE1588", nullptr)) {
      enable_feature = "GevIEEE1588";
      status_feature = "GevIEEE1588Status";
    }
    if (enable_feature == nullptr) {
      ptp_status_ = "not offered by this device";
      return;
    }
    if (!enable) {
      ptp_status_ = "off";
      return;
    }
    GError* error = nullptr;
    arv_device_set_boolean_feature_value(device_, enable_feature, TRUE, &error);
    ThrowIf(error, uri_, std::string("enabling ") + enable_feature);
    ptp_enabled_ = true;
    ptp_status_ = "enabled";
    if (arv_device_is_feature_available(device_, status_feature, nullptr)) {
      const char* status = arv_device_get_string_feature_value(device_, status_feature, &error);
      if (error == nullptr && status != nullptr) ptp_status_ = status;
      g_clear_error(&error);
    }
  }

  // The host sees a frame some time after the camera stamped it, never before: the smallest
  // (host - device) over recent frames is the clock offset plus the shortest transfer, free of
  // the host's scheduling delays. Recent only, so that the camera clock's drift is followed.
  int64_t MapToHost(int64_t device_ns, int64_t host_ns) {
    host_minus_device_.push_back(host_ns - device_ns);
    if (host_minus_device_.size() > 128) host_minus_device_.pop_front();
    return device_ns + *std::min_element(host_minus_device_.begin(), host_minus_device_.end());
  }

  uint64_t UnwrapFrameId(uint64_t raw) {
    if (is_gige_ && raw <= 0xffff) {
      if (have_last_id_ && raw < last_raw_id_ && last_raw_id_ - raw > kGvBlockIdPeriod / 2) {
        id_base_ += kGvBlockIdPeriod;
      }
      last_raw_id_ = raw;
      have_last_id_ = true;
    }
    return id_base_ + raw;
  }

  std::string uri_;
  uint64_t log_from_;  // AravisLog messages before this sensor opened are not its own
  ArvCamera* camera_ = nullptr;
  ArvDevice* device_ = nullptr;
  ArvStream* stream_ = nullptr;
  gulong lost_handler_ = 0;
  AravisPixelLayout layout_;
  StreamInfo stream_info_;
  bool is_gige_ = false;
  bool software_trigger_ = false;
  bool device_clock_ = false;
  bool map_device_to_host_ = false;
  std::deque<int64_t> host_minus_device_;
  bool ptp_enabled_ = false;
  bool started_ = false;
  std::atomic<bool> abandoned_{false};  // Abandon() may come while a Trigger() still waits
  std::string ptp_status_;
  std::atomic<bool> control_lost_{false};
  std::atomic<uint64_t> frames_delivered_{0};
  std::atomic<uint64_t> frames_incomplete_{0};
  uint64_t id_base_ = 0;
  uint64_t last_raw_id_ = 0;
  bool have_last_id_ = false;
};

class AravisDriver : public Driver {
 public:
  std::string scheme() const override { return "aravis"; }
  std::string description() const override {
    return "GigE Vision and USB3 Vision cameras (libaravis " +
           std::to_string(arv_get_major_version()) + "." + std::to_string(arv_get_minor_version()) +
           "." + std::to_string(arv_get_micro_version()) + ")";
  }
  std::vector<DeviceInfo> Enumerate() override {
    std::lock_guard lock(AravisListMutex());
    arv_update_device_list();
    std::vector<DeviceInfo> devices;
    for (unsigned i = 0; i < arv_get_n_devices(); ++i) {
      auto text = [](const char* s) { return std::string(s != nullptr ? s : "?"); };
      DeviceInfo info;
      info.uri = "aravis:" + text(arv_get_device_id(i));
      info.description = text(arv_get_device_vendor(i)) + " " + text(arv_get_device_model(i)) +
                         ", serial " + text(arv_get_device_serial_nbr(i)) + ", " +
                         text(arv_get_device_protocol(i)) + " " + text(arv_get_device_address(i));
      devices.push_back(std::move(info));
    }
    return devices;
  }
  std::unique_ptr<Sensor> Open(const SensorSpec& spec) override {
    return std::make_unique<AravisSensor>(spec);
  }
};

}  // namespace

AravisPixelLayout AravisLayoutFor(const std::string& genicam, bool debayer) {
  AravisPixelLayout layout;
  layout.genicam = genicam;
  // OpenCV names a Bayer pattern by its second row, so GenICam's RG (red at the origin) is
  // OpenCV's BG.
  static const std::vector<std::pair<std::string, int>> kBayer = {{"RG", cv::COLOR_BayerBG2BGR},
                                                                  {"GR", cv::COLOR_BayerGB2BGR},
                                                                  {"GB", cv::COLOR_BayerGR2BGR},
                                                                  {"BG", cv::COLOR_BayerRG2BGR}};
  if (genicam == "Mono8") {
    layout = {genicam, "mono8", CV_8UC1};
  } else if (genicam == "Mono16") {
    layout = {genicam, "mono16", CV_16UC1};
  } else if (genicam == "RGB8" || genicam == "RGB8Packed") {
    layout = {genicam, "bgr8", CV_8UC3, -1, true};
  } else if (genicam == "BGR8" || genicam == "BGR8Packed") {
    layout = {genicam, "bgr8", CV_8UC3};
  } else if (genicam.rfind("Bayer", 0) == 0 && genicam.size() >= 8) {
    const std::string pattern = genicam.substr(5, 2);
    const std::string bits = genicam.substr(7);
    auto it = std::find_if(kBayer.begin(), kBayer.end(),
                           [&](const auto& p) { return p.first == pattern; });
    if (it != kBayer.end() && (bits == "8" || bits == "16")) {
      const bool wide = bits == "16";
      layout = {genicam, debayer ? (wide ? "bgr16" : "bgr8") : (wide ? "mono16" : "mono8"),
                wide ? CV_16UC1 : CV_8UC1, debayer ? it->second : -1};
      return layout;
    }
    Fail("unsupported pixel format '", genicam,
         "' (supported: Mono8, Mono16, RGB8, BGR8, Bayer{RG,GR,GB,BG}{8,16})");
  } else {
    Fail("unsupported pixel format '", genicam.empty() ? "(none)" : genicam,
         "' (supported: Mono8, Mono16, RGB8, BGR8, Bayer{RG,GR,GB,BG}{8,16})");
  }
  return layout;
}

cv::Mat ConvertAravisImage(const cv::Mat& wire, const AravisPixelLayout& layout) {
  if (wire.type() != layout.raw_type)
    Fail("a ", layout.genicam, " frame has the wrong element type");
  cv::Mat out;
  if (layout.bayer_to_bgr >= 0) {
    cv::cvtColor(wire, out, layout.bayer_to_bgr);
  } else if (layout.rgb_to_bgr) {
    cv::cvtColor(wire, out, cv::COLOR_RGB2BGR);
  } else {
    out = wire;
  }
  return out;
}

void RegisterAravisDriver(DriverRegistry& registry) {
  AravisLog::Get();
  registry.Register(std::make_unique<AravisDriver>());
}

}  // namespace holocap
