// The recorder's handling of a sensor that stops delivering, on scripted in-process sensors (no
// hardware, no privileges): when it is declared lost, what is counted against whom, and that the
// take does not wait for a sensor hung in a driver call.
#include "capture/recorder.h"

#include <gtest/gtest.h>

#include <chrono>
#include <condition_variable>
#include <deque>
#include <map>
#include <mutex>
#include <thread>

#include "core/error.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::TempDir;

// What a test tells one scripted sensor and reads back from it.
struct Script {
  int64_t answers = -1;      // frames it delivers (software trigger: triggers it answers,
                             // warm-up ones included); -1: no end
  bool hang = false;         // after the last answer, Trigger() blocks until released
  double interval_s = 0.05;  // free run: its own frame interval
  std::mutex mutex;
  std::condition_variable released_cv;
  bool released = false;                // lets a hung Trigger() return
  std::atomic<bool> in_trigger{false};  // a Trigger() is hung now
  std::atomic<bool> abandoned{false};   // Abandon() was called
  std::atomic<bool> destroyed{false};
};

// A sensor that answers each software trigger with a frame stamped when the trigger came, or
// free-runs at Script::interval_s, until Script::answers frames.
class ScriptedSensor : public Sensor {
 public:
  ScriptedSensor(const SensorSpec& spec, std::shared_ptr<Script> script)
      : script_(std::move(script)), software_(spec.options.value("sync", "") == "software") {
    stream_.name = spec.name;
    stream_.uri = spec.uri;
    stream_.width = 8;
    stream_.height = 8;
    stream_.pixel_format = "mono8";
    stream_.clock = "CLOCK_REALTIME";
  }
  ~ScriptedSensor() override { script_->destroyed = true; }

  const StreamInfo& stream() const override { return stream_; }
  void Start() override { start_ = std::chrono::steady_clock::now(); }
  void Stop() override {}
  void Abandon() override { script_->abandoned = true; }
  bool supports_software_trigger() const override { return software_; }

  void Trigger() override {
    std::unique_lock lock(script_->mutex);
    if (script_->answers >= 0 && sent_ >= script_->answers) {
      if (!script_->hang) return;
      // A camera gone mid-trigger: the driver waits out its retries (bounded here).
      script_->in_trigger = true;
      script_->released_cv.wait_for(lock, std::chrono::seconds(30),
                                    [&] { return script_->released; });
      script_->in_trigger = false;
      Fail("scripted sensor: no acknowledgement");
    }
    ++sent_;
    pending_.push_back(Now());
    ready_.notify_one();
  }

  bool Grab(Frame* frame, std::chrono::milliseconds timeout) override {
    int64_t timestamp = 0;
    if (software_) {
      std::unique_lock lock(script_->mutex);
      if (!ready_.wait_for(lock, timeout, [&] { return !pending_.empty(); })) return false;
      timestamp = pending_.front();
      pending_.pop_front();
    } else {
      if (script_->answers >= 0 && sent_ >= script_->answers) {
        std::this_thread::sleep_for(timeout);
        return false;
      }
      const auto due = start_ + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                    std::chrono::duration<double>(script_->interval_s * sent_));
      if (due > std::chrono::steady_clock::now() + timeout) {
        std::this_thread::sleep_for(timeout);
        return false;
      }
      std::this_thread::sleep_until(due);
      ++sent_;
      timestamp = Now();
    }
    frame->image = cv::Mat(8, 8, CV_8UC1, cv::Scalar(static_cast<int>(delivered_ % 256)));
    frame->timestamp_ns = timestamp;
    frame->sequence = static_cast<uint64_t>(delivered_++);
    return true;
  }

 private:
  static int64_t Now() {
    return std::chrono::duration_cast<std::chrono::nanoseconds>(
               std::chrono::system_clock::now().time_since_epoch())
        .count();
  }

  std::shared_ptr<Script> script_;
  bool software_;
  StreamInfo stream_;
  std::chrono::steady_clock::time_point start_;
  int64_t sent_ = 0;  // triggers answered (software) or frames due so far (free run)
  int64_t delivered_ = 0;
  std::deque<int64_t> pending_;  // software: timestamps of answered triggers not yet grabbed
  std::condition_variable ready_;
};

class ScriptedDriver : public Driver {
 public:
  explicit ScriptedDriver(std::map<std::string, std::shared_ptr<Script>> scripts)
      : scripts_(std::move(scripts)) {}
  std::string scheme() const override { return "script"; }
  std::string description() const override { return "scripted sensors (tests)"; }
  std::vector<DeviceInfo> Enumerate() override { return {}; }
  std::unique_ptr<Sensor> Open(const SensorSpec& spec) override {
    return std::make_unique<ScriptedSensor>(spec, scripts_.at(ParseSensorUri(spec.uri).path));
  }

 private:
  std::map<std::string, std::shared_ptr<Script>> scripts_;
};

struct ScriptedRig {
  std::map<std::string, std::shared_ptr<Script>> scripts;
  RigDescription rig;
  DriverRegistry registry;

  ScriptedRig(SyncMode sync, double fps, int sensors) {
    rig.name = "scripted";
    rig.sync = sync;
    rig.fps = fps;
    for (int i = 0; i < sensors; ++i) {
      const std::string name = "cam" + std::to_string(i);
      scripts[name] = std::make_shared<Script>();
      SensorSpec spec;
      spec.name = name;
      spec.uri = "script:" + name;
      rig.sensors.push_back(spec);
    }
  }
  Script& operator[](const std::string& name) { return *scripts.at(name); }
  RecorderSummary Record(const std::filesystem::path& take, RecorderOptions options) {
    registry.Register(std::make_unique<ScriptedDriver>(scripts));
    Recorder recorder(rig, take, options, registry);
    return recorder.Run();
  }
};

const SensorRecord& Record(const RecorderSummary& summary, const std::string& name) {
  for (const auto& sensor : summary.sensors) {
    if (sensor.name == name) return sensor;
  }
  Fail("no sensor ", name);
}

// A software-triggered camera answers 20 triggers of the take and then hangs in its 21st, as a
// GigE camera killed mid-take holds aravis' trigger call for seconds.
TEST(RecorderLoss, SilentTriggeredSensorIsLostWithinThreePeriodsAndOwesItsFrames) {
  ScriptedRig rig(SyncMode::kSoftwareTrigger, 20, 2);
  rig["cam1"].answers = 2 + 20;  // the two warm-up triggers, then 20 of the take
  rig["cam1"].hang = true;
  TempDir dir;
  RecorderOptions options;
  options.frames = 400;  // 20 s: far more than the take will last
  options.trigger_priority = 0;
  const RecorderSummary summary = rig.Record(dir / "take", options);
  // Run() returned while cam1's trigger call still hung: the take did not wait for it.
  EXPECT_TRUE(rig["cam1"].in_trigger);
  EXPECT_TRUE(rig["cam1"].abandoned);
  {
    std::lock_guard lock(rig["cam1"].mutex);
    rig["cam1"].released = true;
  }
  rig["cam1"].released_cv.notify_all();

  ASSERT_EQ(summary.termination, Termination::kFailure) << summary.message;
  ASSERT_TRUE(summary.lost.has_value()) << summary.message;
  const SensorLoss& lost = *summary.lost;
  EXPECT_EQ(lost.sensor, "cam1");
  EXPECT_EQ(lost.uri, "script:cam1");
  // Its last frame answered trigger 19, so the first trigger after it is 20 or, where the
  // host was slow to see that frame, a later one.
  EXPECT_GE(lost.frame_set, 20);
  EXPECT_NEAR(lost.due_s, lost.frame_set / 20.0, 1e-6);
  EXPECT_EQ(summary.message.rfind(Cat("sensor 'cam1' (script:cam1) was lost mid-take at frame set ",
                                      lost.frame_set, " ("),
                                  0),
            0u)
      << summary.message;
  EXPECT_NE(summary.message.find("no frame for 3 frame periods (150 ms)"), std::string::npos)
      << summary.message;

  const SensorRecord& survivor = Record(summary, "cam0");
  const SensorRecord& killed = Record(summary, "cam1");
  // No trigger went out once cam1 had been silent for 3 periods: at most 3 after its last
  // frame, and at least the one it hung in.
  EXPECT_GE(survivor.triggers - lost.frame_set, 1);
  EXPECT_LE(survivor.triggers - lost.frame_set, 3);
  // Every frame set after its 20th is its loss: counted against it, and the survivor's frames
  // of those sets are discarded, not the survivor's drops.
  EXPECT_TRUE(killed.lost);
  EXPECT_FALSE(survivor.lost);
  EXPECT_EQ(killed.frames_captured, 20);
  EXPECT_EQ(killed.triggers, survivor.triggers);
  EXPECT_EQ(killed.lost_in_driver, survivor.triggers - 20);
  EXPECT_EQ(killed.dropped(), survivor.triggers - 20);
  EXPECT_EQ(survivor.discarded, survivor.triggers - 20);
  EXPECT_EQ(survivor.dropped(), 0);
  EXPECT_EQ(summary.frame_sets_complete, 20);
  EXPECT_EQ(summary.frames_dropped, 2 * (survivor.triggers - 20));
  EXPECT_EQ(Take::Open(dir / "take").size(), 20u);

  // The hung call returns, and the thread that made it lets go of the sensor.
  for (int i = 0; i < 500 && !rig["cam1"].destroyed; ++i)
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  EXPECT_TRUE(rig["cam1"].destroyed);
}

TEST(RecorderLoss, FreeRunningSensorThatStopsIsLostAndOwesWhatTheOtherDelivered) {
  ScriptedRig rig(SyncMode::kFreeRun, 20, 2);
  rig["cam1"].answers = 15;
  TempDir dir;
  RecorderOptions options;
  options.seconds = 20;
  options.sync_tolerance_ns = 5'000'000;
  const RecorderSummary summary = rig.Record(dir / "take", options);
  ASSERT_EQ(summary.termination, Termination::kFailure) << summary.message;
  ASSERT_TRUE(summary.lost.has_value()) << summary.message;
  EXPECT_EQ(summary.lost->sensor, "cam1");
  EXPECT_EQ(summary.lost->frame_set, 15);  // the frames it delivered
  const SensorRecord& survivor = Record(summary, "cam0");
  const SensorRecord& killed = Record(summary, "cam1");
  EXPECT_EQ(killed.frames_captured, 15);
  EXPECT_GE(survivor.discarded, 1);
  // It owes every frame the survivor delivered after its last one.
  EXPECT_GE(killed.lost_in_driver, survivor.discarded);
  EXPECT_LT(survivor.dropped(), killed.dropped());
}

// A renderer (the sim: driver) may deliver slower than the rig's rate: judged by its own frame
// interval, it is not lost for that.
TEST(RecorderLoss, FreeRunningSensorSlowerThanTheRigIsNotLost) {
  ScriptedRig rig(SyncMode::kFreeRun, 30, 1);
  rig["cam0"].interval_s = 0.2;  // 6 of the rig's frame periods
  TempDir dir;
  RecorderOptions options;
  options.frames = 8;
  const RecorderSummary summary = rig.Record(dir / "take", options);
  EXPECT_EQ(summary.termination, Termination::kSuccess) << summary.message;
  EXPECT_FALSE(summary.lost.has_value());
  EXPECT_EQ(summary.frame_sets_complete, 8);
}

TEST(RecorderLoss, LostAfterPeriodsIsChecked) {
  RecorderOptions options;
  options.frames = 1;
  options.lost_after_periods = 0;
  try {
    options.Check();
    FAIL();
  } catch (const Error& e) {
    EXPECT_STREQ(
        e.what(),
        "RecorderOptions::lost_after_periods = 0 violates lost_after_periods in [1, 1000]");
  }
}

}  // namespace
}  // namespace holocap
