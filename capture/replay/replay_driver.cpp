#include "capture/replay/replay_driver.h"

#include <filesystem>
#include <thread>

#include "core/error.h"

namespace holocap {
namespace {

class ReplaySensor : public Sensor {
 public:
  ReplaySensor(Take take, const std::string& sensor, bool recorded_pace, bool loop,
               bool true_cameras)
      : take_(std::move(take)),
        recorded_pace_(recorded_pace),
        loop_(loop),
        true_cameras_(true_cameras) {
    stream_ = take_.stream(sensor);
    stream_.uri = "replay:" + take_.dir().string() + "#" + sensor;
    for (size_t i = 0; i < take_.size(); ++i) {
      if (take_.entry(i).Find(sensor) != nullptr) sets_with_frame_.push_back(i);
    }
    // Pace against the take's first timestamp, so sensors of one take stay aligned.
    if (take_.size() > 0) {
      first_timestamp_ns_ = take_.entry(0).items.front().timestamp_ns;
      for (const auto& item : take_.entry(0).items)
        first_timestamp_ns_ = std::min(first_timestamp_ns_, item.timestamp_ns);
    }
  }

  const StreamInfo& stream() const override { return stream_; }
  void Start() override {
    started_ = true;
    start_wall_ = std::chrono::steady_clock::now();
  }
  void Stop() override { started_ = false; }
  bool ended() const override { return !loop_ && next_ >= sets_with_frame_.size(); }

  bool Grab(Frame* frame, std::chrono::milliseconds timeout) override {
    if (!started_) Fail("replay sensor '", stream_.name, "' was not started");
    if (sets_with_frame_.empty()) return false;
    if (next_ >= sets_with_frame_.size()) {
      if (!loop_) return false;
      next_ = 0;
      ++loops_;
      start_wall_ = std::chrono::steady_clock::now();
    }
    size_t set = sets_with_frame_[next_];
    const FrameSetEntry::Item* item = take_.entry(set).Find(stream_.name);
    if (recorded_pace_) {
      auto due = start_wall_ + std::chrono::nanoseconds(item->timestamp_ns - first_timestamp_ns_);
      auto now = std::chrono::steady_clock::now();
      if (due - now > timeout) {
        std::this_thread::sleep_for(timeout);
        return false;
      }
      std::this_thread::sleep_until(due);
    }
    frame->sensor = stream_.name;
    frame->image = ReadImage(take_.dir() / item->file, stream_.shape());
    frame->timestamp_ns = item->timestamp_ns;
    frame->sequence = item->sequence;
    ++next_;
    return true;
  }

  // The take's calibration; a simulated take's true model only when the rig asks for it
  // (option cameras: truth): the truth never stands in for a calibration by itself.
  std::optional<CameraModel> known_model() const override {
    const std::filesystem::path file =
        (true_cameras_ ? take_.gt_dir() / "cameras" : take_.calib_dir()) /
        (stream_.name + ".cameramodel");
    if (std::filesystem::exists(file)) return CameraModel::Read(file);
    return std::nullopt;
  }
  bool known_model_is_truth() const override { return true_cameras_; }

 private:
  Take take_;
  StreamInfo stream_;
  bool recorded_pace_;
  bool loop_;
  bool true_cameras_;
  bool started_ = false;
  std::vector<size_t> sets_with_frame_;
  size_t next_ = 0;
  int loops_ = 0;
  int64_t first_timestamp_ns_ = 0;
  std::chrono::steady_clock::time_point start_wall_;
};

class ReplayDriver : public Driver {
 public:
  std::string scheme() const override { return "replay"; }
  std::string description() const override {
    return "recorded takes played back (replay:<take>#<sensor>)";
  }
  std::vector<DeviceInfo> Enumerate() override { return {}; }

  std::unique_ptr<Sensor> Open(const SensorSpec& spec) override {
    ParsedUri uri = ParseSensorUri(spec.uri);
    if (uri.path.empty() || uri.fragment.empty()) {
      Fail("replay URI '", spec.uri, "' must name a take and a sensor: replay:<take>#<sensor>");
    }
    std::string pace = spec.options.value("pace", "fast");
    if (pace != "fast" && pace != "recorded")
      Fail("replay pace must be 'fast' or 'recorded', got '", pace, "'");
    const std::string cameras = spec.options.value("cameras", "calib");
    if (cameras != "calib" && cameras != "truth")
      Fail("replay cameras must be 'calib' or 'truth' (a simulated take's gt/), got '", cameras,
           "'");
    Take take = Take::Open(uri.path);
    take.stream(uri.fragment);  // a clear error if the take lacks that sensor
    return std::make_unique<ReplaySensor>(std::move(take), uri.fragment, pace == "recorded",
                                          spec.options.value("loop", false), cameras == "truth");
  }
};

}  // namespace

void RegisterReplayDriver(DriverRegistry& registry) {
  registry.Register(std::make_unique<ReplayDriver>());
}

}  // namespace holocap
