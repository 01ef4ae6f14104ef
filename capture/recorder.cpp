#include "capture/recorder.h"

#include <pthread.h>
#include <sched.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstring>
#include <deque>
#include <mutex>
#include <thread>

#include "core/check_option.h"
#include "core/error.h"

namespace holocap {
namespace {

using Clock = std::chrono::steady_clock;

double SecondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

}  // namespace

void RecorderOptions::Check() const {
  HOLOCAP_CHECK_OPTION_GE(frames, 0);
  HOLOCAP_CHECK_OPTION_GE(seconds, 0);
  HOLOCAP_CHECK_OPTION(std::isfinite(seconds), seconds);
  HOLOCAP_CHECK_OPTION(frames != 0 || seconds != 0, frames, "give a frame count or a duration");
  HOLOCAP_CHECK_OPTION_GE(queue_frames, 1);
  HOLOCAP_CHECK_OPTION_GE(queue_sets, 1);
  HOLOCAP_CHECK_OPTION_IN(writer_threads, 1, 64);
  HOLOCAP_CHECK_OPTION_GE(warmup_s, 0);
  HOLOCAP_CHECK_OPTION_GE(drain_s, 0);
  HOLOCAP_CHECK_OPTION_IN(lost_after_periods, 1, 1000);
  HOLOCAP_CHECK_OPTION_GT(first_frame_s, 0);
  HOLOCAP_CHECK_OPTION(codec.empty() || IsOneOf(codec, {"png", "zstd"}), codec);
  HOLOCAP_CHECK_OPTION_GE(sync_tolerance_ns, 0);
  HOLOCAP_CHECK_OPTION_IN(trigger_priority, 0, 99);
  HOLOCAP_CHECK_OPTION_GE(first_trigger_realtime_ns, 0);
  HOLOCAP_CHECK_OPTION(metadata.is_object(), metadata);
}

nlohmann::json SensorLoss::ToJson() const {
  return {{"sensor", sensor},
          {"uri", uri},
          {"frame_set", frame_set},
          {"due_s", due_s},
          {"declared_s", declared_s},
          {"last_frame_s", last_frame_s},
          {"last_frame_timestamp_ns", last_frame_timestamp_ns},
          {"due_timestamp_ns", due_timestamp_ns},
          {"reason", reason}};
}

nlohmann::json RecorderSummary::Metrics() const {
  nlohmann::json per_sensor = nlohmann::json::object();
  for (const auto& s : sensors) {
    per_sensor[s.name] = {{"uri", s.uri},
                          {"triggers", s.triggers},
                          {"frames_captured", s.frames_captured},
                          {"frames_written", s.written},
                          {"lost_in_driver", s.lost_in_driver},
                          {"dropped_queue", s.dropped_queue},
                          {"dropped_sets", s.dropped_sets},
                          {"unmatched", s.unmatched},
                          {"frames_dropped", s.dropped()},
                          {"discarded", s.discarded},
                          {"lost", s.lost},
                          {"driver", s.driver}};
  }
  return {{"frame_sets_complete", frame_sets_complete},
          {"frame_sets_incomplete", frame_sets_incomplete},
          {"frame_sets_dropped", frame_sets_dropped},
          {"frames_dropped", frames_dropped},
          {"sync_spread_us_max", sync_spread_us_max},
          {"sync_spread_us_mean", sync_spread_us_mean},
          {"seconds", seconds},
          {"bytes_written", bytes_written},
          {"write_mb_s", write_mb_s},
          {"clock_offset_ns", clock_offset_ns},
          {"trigger_scheduling", trigger_scheduling},
          {"lost_sensor", lost ? lost->ToJson() : nlohmann::json(nullptr)},
          {"sensors", per_sensor}};
}

Recorder::Recorder(const RigDescription& rig, std::filesystem::path out, RecorderOptions options,
                   DriverRegistry& registry)
    : rig_(rig), out_(std::move(out)), options_(std::move(options)) {
  options_.Check();
  rig_.Check();
  if (rig_.sensors.empty()) Fail("rig '", rig_.name, "' has no sensors");
  // Refused before any sensor opens; the take's writer claims it again when it starts.
  ClaimTakeDirectory(out_, {options_.take.command, options_.take.overwrite, options_.take.inputs});
  for (const SensorSpec& rig_spec : rig_.sensors) {
    SensorSpec spec = rig_spec;
    if (!spec.options.is_object()) spec.options = nlohmann::json::object();
    if (!spec.options.contains("sync")) spec.options["sync"] = ToString(rig_.sync);
    if (!spec.options.contains("fps")) spec.options["fps"] = rig_.fps;
    try {
      sensors_.push_back(registry.Open(spec));
    } catch (const Error& e) {
      const std::string what = e.what();
      // Driver messages usually name the URI already.
      if (what.find(spec.uri) != std::string::npos) Fail("sensor '", spec.name, "': ", what);
      Fail("sensor '", spec.name, "' (", spec.uri, "): ", what);
    }
    StreamInfo stream = sensors_.back()->stream();
    stream.name = spec.name;
    stream.uri = spec.uri;
    stream.role = spec.role;
    if (!spec.paired_with.empty()) stream.paired_with = spec.paired_with;
    if (options_.codec == "png" && stream.pixel_format != "depth_m")
      stream.codec = ImageCodec::kPng;
    if (options_.codec == "zstd" && stream.pixel_format != "depth_m")
      stream.codec = ImageCodec::kZstd;
    streams_.push_back(stream);
    if (rig_.sync == SyncMode::kSoftwareTrigger && !sensors_.back()->supports_software_trigger()) {
      Fail("sensor '", spec.name, "' (", spec.uri,
           ") cannot be software-triggered; give the rig sync: free-run", " or hardware");
    }
  }
}

Recorder::~Recorder() = default;

// One run of the recorder. Each thread's body is one method:
//   CaptureLoop   one per sensor: grab, stamp, queue; never blocks on anything downstream
//   TriggerLoop   one per sensor when software-triggered: fires on the shared clock ticks
//   AssembleLoop  frame queue -> FrameSetAssembler -> set queue
//   WriteLoop     writer_threads of them: set queue -> TakeWriter
//   Supervise     the calling thread: decides when to stop and reports progress
// What one sensor's threads count lives in its SensorState; the queues and the failure are
// shared by all.
class Recorder::Session {
 public:
  Session(Recorder& recorder, Report* report);
  RecorderSummary Run(const std::function<void(const RecorderStatus&)>& on_status);

 private:
  // Written by the sensor's capture and trigger threads, read by the others.
  struct SensorState {
    std::atomic<int64_t> triggers{0};       // software triggers sent (or tried) after the warm-up
    std::atomic<int64_t> captured{0};       // frames delivered after the warm-up
    std::atomic<int64_t> dropped_queue{0};  // its frame queue was full
    std::atomic<int64_t> dropped_sets{0};   // in a set dropped because the writers fell behind
    std::atomic<int64_t> written{0};
    std::atomic<int64_t> sequence_gaps{0};     // frames its sequence counter skipped
    std::atomic<int64_t> after_end{0};         // free run with a frame limit: after the last set
    std::atomic<int64_t> warmup_frames{0};     // answers to the warm-up triggers (discarded)
    std::atomic<int64_t> warmup_timestamp{0};  // the last of them: ties the clocks together
    std::atomic<int64_t> lost_before_first_trigger{0};  // the driver's lost count by then
    std::atomic<bool> ended{false};                     // a finite source has no more frames
    // When it last showed life (a frame, a warm-up frame or one lost in the driver), in ns of
    // the steady clock since start_; set to the take's start before the first.
    std::atomic<int64_t> last_activity_ns{0};
    std::atomic<int64_t> first_frame_ns{-1};       // arrival of its first frame after the warm-up
    std::atomic<int64_t> last_frame_ns{-1};        // arrival of its last frame after the warm-up
    std::atomic<int64_t> last_frame_timestamp{0};  // that frame's own timestamp
    std::atomic<uint64_t> lost_seen{0};  // stats().frames_lost at the last look (Supervise)
    std::deque<int64_t> arrivals;        // capture thread only: arrival (ns) of its last frames
    int queued = 0;                      // its frames in the frame queue (frame_mutex_)
  };
  // Frames a sensor keeps the arrival times of: more than a lost sensor's silence can hold.
  static constexpr size_t kArrivalHistory = 4096;

  void StartSensorsAndOpenTake();
  Clock::time_point FirstTriggerTick() const;
  void RecordFailure(const std::string& message);
  int64_t NowNs() const;
  int64_t TickNs(int64_t k) const;
  int64_t TicksUpTo(int64_t at_ns) const;
  void NoteActivity(size_t s, int64_t at_ns);
  void NoteDriverLosses();
  std::optional<size_t> SilentSensor(int64_t at_ns) const;
  void DeclareLost(size_t s, const std::string& reason);
  std::string SilenceReason(size_t s) const;
  std::string failure_message();

  // A trigger thread's call into its sensor. A sensor that vanished may hold Trigger() for the
  // driver's whole timeout; once the sensor is declared lost, StopAndJoin lets go of a thread
  // still in that call instead of waiting, and the thread, on its return, touches nothing of
  // the session (it shares the sensor, so the sensor outlives the call).
  struct TriggerCall {
    std::mutex mutex;
    bool in_call = false;
    bool released = false;  // the session no longer waits for this thread
  };
  enum class TriggerOutcome { kSent, kFailed, kReleased };
  static TriggerOutcome CallTrigger(Sensor& sensor, TriggerCall& call, std::string* error);

  void CaptureLoop(size_t s);
  void TriggerLoop(size_t s);
  void AssembleLoop();
  void EnqueueSet(FrameSet set);
  void WriteLoop();
  void Supervise(const std::function<void(const RecorderStatus&)>& on_status);
  bool AllTriggersAnswered() const;
  void SendStatus(const std::function<void(const RecorderStatus&)>& on_status, double elapsed,
                  double dt);
  void StopAndJoin();

  int64_t LostInDriver(size_t s, bool final) const;
  int64_t TakeTriggers() const;
  int64_t SilenceBoundNs(size_t s) const;
  void UpdateTakeDrops(bool final);
  size_t IndexOf(const std::string& name) const;
  std::vector<SensorRecord> FinalRecords() const;
  RecorderSummary Summarize() const;

  Recorder& recorder_;
  const RecorderOptions& options_;
  const std::vector<std::shared_ptr<Sensor>>& sensors_;
  const std::vector<StreamInfo>& streams_;
  Report* report_;
  const size_t n_;
  const bool software_;
  const double period_s_;
  const int64_t period_ns_;
  const int64_t lost_after_ns_;  // lost_after_periods frame periods
  const int64_t trigger_count_;  // software triggers to send (frames, or seconds x fps)
  const bool free_run_limit_;    // not software-triggered, stopping after options_.frames sets
  std::vector<std::string> names_;
  FrameSetAssembler assembler_;  // used by the assembler thread only, read after it ends
  std::vector<SensorState> state_;

  Clock::time_point start_;
  Clock::time_point first_tick_;
  int64_t take_start_ns_ = 0;  // the first trigger (software) or the warm-up's end, since start_
  int64_t realtime_at_start_ns_ = 0;  // CLOCK_REALTIME at start_
  std::unique_ptr<TakeWriter> writer_;
  std::vector<std::thread> capture_threads_, trigger_threads_, writer_threads_;
  std::vector<std::shared_ptr<TriggerCall>> trigger_calls_;  // one per trigger thread
  std::thread assemble_thread_;
  std::string trigger_scheduling_;
  std::vector<int64_t> counted_drops_;  // per sensor, already passed to TakeWriter::CountDropped
  std::vector<int64_t> last_captured_;  // per sensor, at the previous status

  std::mutex frame_mutex_;
  std::condition_variable frame_cv_;
  std::deque<std::pair<int, Frame>> frames_;
  bool capture_done_ = false;

  std::mutex set_mutex_;
  std::condition_variable set_cv_;
  std::deque<FrameSet> sets_;
  bool assemble_done_ = false;

  std::atomic<bool> stop_triggers_{false};
  std::atomic<bool> stop_capture_{false};
  std::atomic<bool> failed_{false};
  std::mutex failure_mutex_;
  std::string failure_;
  std::optional<SensorLoss> loss_;  // failure_mutex_; read after the threads end
  size_t lost_index_ = 0;           // loss_'s sensor

  std::atomic<int64_t> sets_complete_{0}, sets_dropped_{0};
  std::atomic<int64_t> spread_last_ns_{0}, spread_max_ns_{0};
};

namespace {

std::vector<std::string> StreamNames(const std::vector<StreamInfo>& streams) {
  std::vector<std::string> names;
  for (const auto& stream : streams) names.push_back(stream.name);
  return names;
}

std::vector<std::string> StreamClocks(const std::vector<StreamInfo>& streams) {
  std::vector<std::string> clocks;
  for (const auto& stream : streams) clocks.push_back(stream.clock);
  return clocks;
}

SyncOptions AssemblerOptions(const RigDescription& rig, const RecorderOptions& options) {
  SyncOptions sync_options;
  sync_options.mode = rig.sync;
  sync_options.fps = rig.fps;
  sync_options.tolerance_ns = options.sync_tolerance_ns;
  return sync_options;
}

}  // namespace

Recorder::Session::Session(Recorder& recorder, Report* report)
    : recorder_(recorder),
      options_(recorder.options_),
      sensors_(recorder.sensors_),
      streams_(recorder.streams_),
      report_(report),
      n_(recorder.sensors_.size()),
      software_(recorder.rig_.sync == SyncMode::kSoftwareTrigger),
      period_s_(1.0 / recorder.rig_.fps),
      period_ns_(static_cast<int64_t>(std::llround(1e9 / recorder.rig_.fps))),
      lost_after_ns_(period_ns_ * recorder.options_.lost_after_periods),
      trigger_count_(options_.frames > 0 ? options_.frames
                                         : static_cast<int64_t>(
                                               std::llround(options_.seconds * recorder.rig_.fps))),
      free_run_limit_(!software_ && options_.frames > 0),
      names_(StreamNames(streams_)),
      assembler_(names_, StreamClocks(streams_), AssemblerOptions(recorder.rig_, options_)),
      state_(n_),
      trigger_scheduling_(software_ ? "normal" : "none (not software-triggered)"),
      counted_drops_(n_, 0),
      last_captured_(n_, 0) {}

void Recorder::Session::RecordFailure(const std::string& message) {
  std::lock_guard lock(failure_mutex_);
  if (failure_.empty()) failure_ = message;
  failed_ = true;
  stop_triggers_ = true;
  stop_capture_ = true;
}

int64_t Recorder::Session::NowNs() const {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now() - start_).count();
}

// Software trigger k goes out at this instant (ns since start_), as TriggerLoop computes it.
int64_t Recorder::Session::TickNs(int64_t k) const {
  return take_start_ns_ +
         static_cast<int64_t>(std::llround(static_cast<double>(k) * period_s_ * 1e9));
}

// How many software triggers were due at or before `at_ns`.
int64_t Recorder::Session::TicksUpTo(int64_t at_ns) const {
  if (at_ns < take_start_ns_) return 0;
  int64_t k = (at_ns - take_start_ns_) / period_ns_ + 1;
  while (k > 0 && TickNs(k - 1) > at_ns) --k;
  while (TickNs(k) <= at_ns) ++k;
  return k;
}

void Recorder::Session::NoteActivity(size_t s, int64_t at_ns) {
  std::atomic<int64_t>& last = state_[s].last_activity_ns;
  int64_t seen = last.load();
  while (seen < at_ns && !last.compare_exchange_weak(seen, at_ns)) {
  }
}

// Frames the driver saw but threw away (incomplete) show that a sensor is alive too.
void Recorder::Session::NoteDriverLosses() {
  const int64_t now = NowNs();
  for (size_t s = 0; s < n_; ++s) {
    const uint64_t lost = sensors_[s]->stats().frames_lost;
    if (lost != state_[s].lost_seen.exchange(lost)) NoteActivity(s, now);
  }
}

// How long sensor s may be silent. Software trigger: lost_after_periods of the trigger period.
// Otherwise as many of its own frame periods (the rig's, or its mean frame interval where that
// is longer), or first_frame_s before its second frame.
int64_t Recorder::Session::SilenceBoundNs(size_t s) const {
  if (software_) return lost_after_ns_;
  const SensorState& state = state_[s];
  const int64_t first = state.first_frame_ns, last = state.last_frame_ns;
  const int64_t frames = state.captured;
  // Its own rate is known from its second frame on.
  if (first < 0 || frames < 2)
    return static_cast<int64_t>(std::llround(options_.first_frame_s * 1e9));
  const int64_t mean_interval = (last - first) / (frames - 1);
  return std::max(period_ns_, mean_interval) * options_.lost_after_periods;
}

// The first sensor that at `at_ns` has been silent for lost_after_periods frame periods while
// frames were due from it (see recorder.h), if any.
std::optional<size_t> Recorder::Session::SilentSensor(int64_t at_ns) const {
  const RigDescription& rig = recorder_.rig_;
  int64_t newest = 0;
  for (const SensorState& state : state_)
    newest = std::max<int64_t>(newest, state.last_activity_ns);
  for (size_t s = 0; s < n_; ++s) {
    const SensorState& state = state_[s];
    if (state.ended) continue;
    const int64_t last = state.last_activity_ns;
    if (at_ns - last < SilenceBoundNs(s)) continue;
    bool due = true;
    if (software_) {
      // A trigger went out to it after it last showed life.
      due = state.triggers > 0 && TickNs(state.triggers - 1) > last;
    } else if (rig.sync == SyncMode::kHardwareTrigger) {
      // Without a trigger of its own to go by: the others went on seeing trigger pulses.
      due = newest - last >= lost_after_ns_;
    }
    if (due) return s;
  }
  return std::nullopt;
}

std::string Recorder::Session::SilenceReason(size_t s) const {
  if (!software_ && state_[s].captured == 0)
    return Cat("no frame within ", options_.first_frame_s, " s of the warm-up");
  if (!software_ && state_[s].captured == 1)
    return Cat("no second frame within ", options_.first_frame_s, " s of its first");
  return Cat("no frame for ", options_.lost_after_periods, " frame periods (",
             std::round(static_cast<double>(SilenceBoundNs(s)) / 1e5) / 10, " ms)");
}

void Recorder::Session::DeclareLost(size_t s, const std::string& reason) {
  const int64_t now = NowNs();
  const SensorState& state = state_[s];
  SensorLoss loss;
  loss.sensor = streams_[s].name;
  loss.uri = streams_[s].uri;
  const int64_t last = state.last_activity_ns;
  int64_t due_ns = last + period_ns_;
  if (software_) {
    loss.frame_set = TicksUpTo(last);
    due_ns = TickNs(loss.frame_set);
  } else {
    loss.frame_set = state.captured + static_cast<int64_t>(state.lost_seen.load());
  }
  loss.due_s = static_cast<double>(due_ns - take_start_ns_) / 1e9;
  loss.declared_s = static_cast<double>(now - take_start_ns_) / 1e9;
  if (state.last_frame_ns >= 0) {
    loss.last_frame_s = static_cast<double>(state.last_frame_ns - take_start_ns_) / 1e9;
    loss.last_frame_timestamp_ns = state.last_frame_timestamp;
  }
  loss.due_timestamp_ns = realtime_at_start_ns_ + due_ns;
  loss.reason = reason;
  const std::string message =
      Cat("sensor '", loss.sensor, "' (", loss.uri, ") was lost mid-take at frame set ",
          loss.frame_set, " (", std::round(loss.due_s * 1e3) / 1e3, " s): ", reason);
  std::lock_guard lock(failure_mutex_);
  if (!failure_.empty()) return;  // the take already ended for another reason
  loss_ = loss;
  lost_index_ = s;
  failure_ = message;
  failed_ = true;
  stop_triggers_ = true;
  stop_capture_ = true;
}

std::string Recorder::Session::failure_message() {
  std::lock_guard lock(failure_mutex_);
  return failure_;
}

size_t Recorder::Session::IndexOf(const std::string& name) const {
  return static_cast<size_t>(
      std::distance(names_.begin(), std::find(names_.begin(), names_.end(), name)));
}

void Recorder::Session::StartSensorsAndOpenTake() {
  start_ = Clock::now();
  realtime_at_start_ns_ = std::chrono::duration_cast<std::chrono::nanoseconds>(
                              std::chrono::system_clock::now().time_since_epoch())
                              .count();
  size_t started = 0;
  try {
    for (; started < n_; ++started) sensors_[started]->Start();
  } catch (const Error&) {
    for (size_t i = 0; i < started; ++i) sensors_[i]->Stop();
    throw;
  }
  const RigDescription& rig = recorder_.rig_;
  try {
    nlohmann::json metadata = {{"capture",
                                {{"sync", ToString(rig.sync)},
                                 {"fps", rig.fps},
                                 {"frames", options_.frames},
                                 {"seconds", options_.seconds},
                                 {"sync_tolerance_ns", options_.sync_tolerance_ns}}}};
    for (const auto& [key, value] : options_.metadata.items()) {
      if (key != "capture") metadata[key] = value;
    }
    writer_ = std::make_unique<TakeWriter>(recorder_.out_, rig, streams_, metadata, options_.take);
  } catch (const Error&) {
    for (auto& sensor : sensors_) sensor->Stop();
    throw;
  }
}

Clock::time_point Recorder::Session::FirstTriggerTick() const {
  const auto after_warmup = start_ + std::chrono::duration_cast<Clock::duration>(
                                         std::chrono::duration<double>(options_.warmup_s));
  if (options_.trigger_phase_s < 0 && options_.first_trigger_realtime_ns <= 0) return after_warmup;
  // The first grid instant after the warm-up, carried over to the steady clock.
  const int64_t period_ns = static_cast<int64_t>(std::llround(period_s_ * 1e9));
  const int64_t phase_ns =
      options_.trigger_phase_s < 0
          ? options_.first_trigger_realtime_ns % period_ns
          : static_cast<int64_t>(std::llround(options_.trigger_phase_s * 1e9)) % period_ns;
  const int64_t realtime_ns = std::chrono::duration_cast<std::chrono::nanoseconds>(
                                  std::chrono::system_clock::now().time_since_epoch())
                                  .count();
  const int64_t steady_now_ns =
      std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now() - start_).count();
  const int64_t earliest =
      std::max(realtime_ns - steady_now_ns + static_cast<int64_t>(options_.warmup_s * 1e9),
               options_.first_trigger_realtime_ns);
  const int64_t grid = (earliest - phase_ns + period_ns - 1) / period_ns * period_ns + phase_ns;
  return start_ + std::chrono::nanoseconds(grid - (realtime_ns - steady_now_ns));
}

void Recorder::Session::CaptureLoop(size_t s) {
  Sensor& sensor = *sensors_[s];
  SensorState& state = state_[s];
  bool have_sequence = false;
  uint64_t last_sequence = 0;
  while (!stop_capture_) {
    Frame frame;
    bool got = false;
    try {
      got = sensor.Grab(&frame, std::chrono::milliseconds(100));
    } catch (const std::exception& e) {
      DeclareLost(s, e.what());
      break;
    }
    if (!got) {
      if (sensor.ended()) {
        state.ended = true;
        break;
      }
      continue;
    }
    const int64_t arrival = NowNs();
    NoteActivity(s, arrival);
    if (software_ && arrival < take_start_ns_) {
      ++state.warmup_frames;
      state.warmup_timestamp = frame.timestamp_ns;
      continue;
    }
    ++state.captured;
    if (state.first_frame_ns < 0) state.first_frame_ns = arrival;
    state.last_frame_ns = arrival;
    state.last_frame_timestamp = frame.timestamp_ns;
    state.arrivals.push_back(arrival);
    if (state.arrivals.size() > kArrivalHistory) state.arrivals.pop_front();
    if (have_sequence && frame.sequence > last_sequence + 1) {
      state.sequence_gaps += static_cast<int64_t>(frame.sequence - last_sequence - 1);
    }
    have_sequence = true;
    last_sequence = frame.sequence;
    frame.sensor = streams_[s].name;
    {
      std::lock_guard lock(frame_mutex_);
      if (state.queued >= options_.queue_frames) {
        ++state.dropped_queue;
        continue;
      }
      ++state.queued;
      frames_.emplace_back(static_cast<int>(s), std::move(frame));
    }
    frame_cv_.notify_one();
  }
}

Recorder::Session::TriggerOutcome Recorder::Session::CallTrigger(Sensor& sensor, TriggerCall& call,
                                                                 std::string* error) {
  {
    std::lock_guard lock(call.mutex);
    call.in_call = true;
  }
  try {
    sensor.Trigger();
  } catch (const std::exception& e) {
    *error = e.what();
  }
  std::lock_guard lock(call.mutex);
  call.in_call = false;
  if (call.released) return TriggerOutcome::kReleased;
  return error->empty() ? TriggerOutcome::kSent : TriggerOutcome::kFailed;
}

// One thread per sensor, all firing on the same ticks, so that a slow or dead camera delays
// only itself. A trigger sent late exposes its camera late, so the threads ask for real-time
// scheduling: other work on the host cannot hold them back.
void Recorder::Session::TriggerLoop(size_t s) {
  // Owned with the thread: after a released call it may outlive the session.
  const std::shared_ptr<Sensor> sensor = sensors_[s];
  const std::shared_ptr<TriggerCall> call = trigger_calls_[s];
  if (options_.trigger_priority > 0) {
    sched_param param{};
    param.sched_priority = options_.trigger_priority;
    const int refused = pthread_setschedparam(pthread_self(), SCHED_FIFO, &param);
    if (s == 0) {  // read after the threads are joined
      trigger_scheduling_ = refused == 0
                                ? Cat("SCHED_FIFO ", options_.trigger_priority)
                                : Cat("normal (SCHED_FIFO refused: ", std::strerror(refused), ")");
    }
  }
  std::string error;
  // Two triggers during the warm-up, their frames discarded: the first wakes up cameras that
  // start streaming late, the second is one instant every camera stamps, which ties their
  // clocks together (FrameSetAssembler::SeedClocks).
  for (double at : {0.0, 0.5}) {
    std::this_thread::sleep_until(start_ +
                                  std::chrono::duration_cast<Clock::duration>(
                                      std::chrono::duration<double>(at * options_.warmup_s)));
    const TriggerOutcome outcome = CallTrigger(*sensor, *call, &error);
    if (outcome == TriggerOutcome::kReleased) return;
    if (outcome == TriggerOutcome::kFailed) {
      DeclareLost(s, Cat("it did not take a software trigger: ", error));
      return;
    }
  }
  // Incomplete frames of the warm-up triggers are no frames of the take.
  state_[s].lost_before_first_trigger = static_cast<int64_t>(sensor->stats().frames_lost);
  for (int64_t k = 0; k < trigger_count_ && !stop_triggers_; ++k) {
    const auto tick = start_ + std::chrono::nanoseconds(TickNs(k));
    while (Clock::now() < tick && !stop_triggers_) {
      std::this_thread::sleep_for(
          std::min<Clock::duration>(tick - Clock::now(), std::chrono::milliseconds(20)));
    }
    if (stop_triggers_) break;
    // Judged at the tick's own instant, so that every trigger thread decides alike and a lost
    // sensor misses no more triggers than lost_after_periods after it last showed life.
    if (const auto silent = SilentSensor(TickNs(k))) {
      DeclareLost(*silent, SilenceReason(*silent));
      break;
    }
    // Counted before it goes out: a trigger the camera never acknowledges was still sent.
    ++state_[s].triggers;
    const TriggerOutcome outcome = CallTrigger(*sensor, *call, &error);
    if (outcome == TriggerOutcome::kReleased) return;
    if (outcome == TriggerOutcome::kFailed) {
      DeclareLost(s, Cat("it did not take a software trigger: ", error));
      break;
    }
  }
}

void Recorder::Session::AssembleLoop() {
  bool seeded = false;
  while (true) {
    std::deque<std::pair<int, Frame>> batch;
    {
      std::unique_lock lock(frame_mutex_);
      frame_cv_.wait_for(lock, std::chrono::milliseconds(50),
                         [&] { return !frames_.empty() || capture_done_; });
      batch.swap(frames_);
      for (auto& state : state_) state.queued = 0;
      if (batch.empty() && capture_done_) break;
    }
    if (!batch.empty() && !seeded) {
      // Every camera stamped the warm-up trigger: the one event that ties their clocks.
      seeded = true;
      std::vector<std::optional<int64_t>> events(n_);
      for (size_t s = 0; s < n_; ++s) {
        if (state_[s].warmup_frames > 0) events[s] = state_[s].warmup_timestamp.load();
      }
      assembler_.SeedClocks(events);
    }
    for (auto& [s, frame] : batch) {
      if (free_run_limit_ && sets_complete_ >= options_.frames) {
        ++state_[s].after_end;
        continue;
      }
      assembler_.Add(s, std::move(frame));
    }
    for (auto& set : assembler_.Pop()) EnqueueSet(std::move(set));
  }
  for (auto& set : assembler_.Flush()) EnqueueSet(std::move(set));
  {
    std::lock_guard lock(set_mutex_);
    assemble_done_ = true;
  }
  set_cv_.notify_all();
}

void Recorder::Session::EnqueueSet(FrameSet set) {
  if (free_run_limit_ && sets_complete_ >= options_.frames) {
    for (const auto& frame : set.frames) ++state_[IndexOf(frame.sensor)].after_end;
    return;
  }
  const int64_t spread = set.SpreadNs();
  if (report_ != nullptr)
    report_->AddPoint("sync_spread_us", static_cast<double>(spread) / 1e3, set.index);
  spread_last_ns_ = spread;
  spread_max_ns_ = std::max<int64_t>(spread_max_ns_, spread);
  ++sets_complete_;
  if (free_run_limit_ && sets_complete_ >= options_.frames) stop_capture_ = true;
  std::unique_lock lock(set_mutex_);
  if (failed_ || static_cast<int>(sets_.size()) >= options_.queue_sets) {
    lock.unlock();
    ++sets_dropped_;
    for (size_t s = 0; s < n_; ++s) {
      if (set.Find(names_[s]) != nullptr) ++state_[s].dropped_sets;
    }
    return;
  }
  sets_.push_back(std::move(set));
  lock.unlock();
  set_cv_.notify_one();
}

std::map<std::string, CameraModel> Recorder::KnownModels() const {
  std::map<std::string, CameraModel> models;
  for (size_t s = 0; s < sensors_.size(); ++s) {
    if (auto model = sensors_[s]->known_model()) models.emplace(streams_[s].name, *model);
  }
  return models;
}

std::set<std::string> Recorder::TrueModelSensors() const {
  std::set<std::string> names;
  for (size_t s = 0; s < sensors_.size(); ++s) {
    if (sensors_[s]->known_model_is_truth()) names.insert(streams_[s].name);
  }
  return names;
}

void Recorder::Session::WriteLoop() {
  while (true) {
    FrameSet set;
    {
      std::unique_lock lock(set_mutex_);
      set_cv_.wait(lock, [&] { return !sets_.empty() || assemble_done_; });
      if (sets_.empty()) break;
      set = std::move(sets_.front());
      sets_.pop_front();
    }
    if (!failed_) {
      try {
        writer_->Append(set);
        for (const auto& frame : set.frames) ++state_[IndexOf(frame.sensor)].written;
        if (options_.on_set_written) options_.on_set_written(set);
        continue;
      } catch (const std::exception& e) {
        RecordFailure(Cat("writing frame set ", set.index, " failed: ", e.what(),
                          "; the take keeps every", " frame set written before"));
      }
    }
    ++sets_dropped_;
    for (const auto& frame : set.frames) ++state_[IndexOf(frame.sensor)].dropped_sets;
  }
}

// Lost inside the driver. Software trigger: every trigger not answered by a frame. Free run and
// hardware trigger: the driver's count or the gaps in the frame counter.
int64_t Recorder::Session::LostInDriver(size_t s, bool final) const {
  const SensorState& state = state_[s];
  const int64_t reported = static_cast<int64_t>(sensors_[s]->stats().frames_lost);
  if (software_) {
    // Every trigger the take sent and no complete frame answered; while frames may still be
    // on their way, only those the driver already saw incomplete. A lost sensor owes a frame
    // for every trigger of the take, those it could no longer be sent too.
    const int64_t triggers =
        final && loss_ && s == lost_index_ ? TakeTriggers() : state.triggers.load();
    const int64_t unanswered = std::max<int64_t>(0, triggers - state.captured);
    return final ? unanswered : std::min(unanswered, reported - state.lost_before_first_trigger);
  }
  return std::max<int64_t>(reported, state.sequence_gaps);
}

// Software triggers the take sent: the most any sensor was sent.
int64_t Recorder::Session::TakeTriggers() const {
  int64_t most = 0;
  for (const SensorState& state : state_) most = std::max<int64_t>(most, state.triggers);
  return most;
}

void Recorder::Session::UpdateTakeDrops(bool final) {
  const std::vector<SensorRecord> records = final ? FinalRecords() : std::vector<SensorRecord>();
  for (size_t s = 0; s < n_; ++s) {
    const int64_t now =
        final ? records[s].dropped()
              : LostInDriver(s, false) + state_[s].dropped_queue + state_[s].dropped_sets;
    if (now > counted_drops_[s]) writer_->CountDropped(streams_[s].name, now - counted_drops_[s]);
    counted_drops_[s] = std::max(counted_drops_[s], now);
  }
}

// Each sensor's record once every thread has ended. With a lost sensor, the others' frames
// that arrived after it last showed life are discarded rather than unmatched, and in free run
// and hardware trigger the lost sensor owes as many frames as the busiest of them delivered.
std::vector<SensorRecord> Recorder::Session::FinalRecords() const {
  const SyncStats& sync = assembler_.stats();
  std::vector<SensorRecord> records(n_);
  int64_t delivered_after_loss = 0;
  for (size_t s = 0; s < n_; ++s) {
    const SensorState& state = state_[s];
    SensorRecord& record = records[s];
    record.name = streams_[s].name;
    record.uri = streams_[s].uri;
    record.triggers = state.triggers;
    record.frames_captured = state.captured;
    record.lost_in_driver = LostInDriver(s, true);
    record.dropped_queue = state.dropped_queue;
    record.dropped_sets = state.dropped_sets;
    record.unmatched = sync.unmatched_per_sensor[s];
    record.written = state.written;
    if (loss_ && s != lost_index_) {
      const int64_t silent_since = state_[lost_index_].last_activity_ns;
      const int64_t after = std::count_if(state.arrivals.begin(), state.arrivals.end(),
                                          [&](int64_t at) { return at > silent_since; });
      record.discarded = std::min(record.unmatched, after);
      record.unmatched -= record.discarded;
      delivered_after_loss = std::max(delivered_after_loss, after);
    }
  }
  if (loss_) {
    SensorRecord& record = records[lost_index_];
    record.lost = true;
    if (software_) {
      record.triggers = TakeTriggers();
      record.driver["triggers_not_sent"] = record.triggers - state_[lost_index_].triggers;
    } else {
      record.lost_in_driver += delivered_after_loss;
    }
  }
  return records;
}

// Software trigger: every trigger sent is answered by a frame or by a frame the driver lost.
bool Recorder::Session::AllTriggersAnswered() const {
  for (size_t s = 0; s < n_; ++s) {
    const int64_t lost = static_cast<int64_t>(sensors_[s]->stats().frames_lost) -
                         state_[s].lost_before_first_trigger;
    if (state_[s].captured + lost < trigger_count_) return false;
  }
  return true;
}

void Recorder::Session::Supervise(const std::function<void(const RecorderStatus&)>& on_status) {
  auto last_status = Clock::now();
  bool triggers_done_at_set = false;
  Clock::time_point triggers_done;
  while (!stop_capture_) {
    std::this_thread::sleep_for(std::chrono::milliseconds(std::clamp<int64_t>(
        period_ns_ / 4'000'000, 1, 20)));  // a few looks per frame period, for free run
    const double elapsed = SecondsSince(start_);
    if (recorder_.stop_requested_) {
      stop_triggers_ = true;
      stop_capture_ = true;
    }
    NoteDriverLosses();
    if (const auto silent = SilentSensor(NowNs())) {
      DeclareLost(*silent, SilenceReason(*silent));
      break;
    }
    if (std::all_of(state_.begin(), state_.end(),
                    [](const SensorState& state) { return state.ended.load(); })) {
      stop_capture_ = true;
    }
    if (software_) {
      bool all_sent = true;
      for (const SensorState& state : state_) all_sent &= state.triggers >= trigger_count_;
      if (all_sent && !triggers_done_at_set) {
        triggers_done_at_set = true;
        triggers_done = Clock::now();
      }
      if (triggers_done_at_set &&
          (AllTriggersAnswered() || SecondsSince(triggers_done) > options_.drain_s)) {
        stop_capture_ = true;
      }
    } else if (options_.seconds > 0 && elapsed >= options_.seconds + options_.warmup_s) {
      stop_capture_ = true;
    }
    if (Clock::now() - last_status >= std::chrono::milliseconds(500)) {
      const double dt = SecondsSince(last_status);
      last_status = Clock::now();
      UpdateTakeDrops(false);
      if (on_status) SendStatus(on_status, elapsed, dt);
    }
  }
}

void Recorder::Session::SendStatus(const std::function<void(const RecorderStatus&)>& on_status,
                                   double elapsed, double dt) {
  RecorderStatus status;
  status.elapsed_s = elapsed;
  status.frame_sets = writer_->sets_written();
  status.write_mb_s =
      elapsed > 0 ? static_cast<double>(writer_->bytes_written()) / 1e6 / elapsed : 0;
  status.spread_us_last = static_cast<double>(spread_last_ns_) / 1e3;
  status.spread_us_max = static_cast<double>(spread_max_ns_) / 1e3;
  for (size_t s = 0; s < n_; ++s) {
    const int64_t captured = state_[s].captured;
    status.sensors.push_back({streams_[s].name,
                              static_cast<double>(captured - last_captured_[s]) / dt,
                              counted_drops_[s]});
    last_captured_[s] = captured;
  }
  on_status(status);
}

void Recorder::Session::StopAndJoin() {
  stop_triggers_ = true;
  std::optional<size_t> lost;
  {
    std::lock_guard lock(failure_mutex_);
    if (loss_) lost = lost_index_;
  }
  for (size_t s = 0; s < trigger_threads_.size(); ++s) {
    if (lost == s) {
      std::lock_guard lock(trigger_calls_[s]->mutex);
      if (trigger_calls_[s]->in_call) {
        trigger_calls_[s]->released = true;
        trigger_threads_[s].detach();
        continue;
      }
    }
    trigger_threads_[s].join();
  }
  for (auto& thread : capture_threads_) thread.join();
  {
    std::lock_guard lock(frame_mutex_);
    capture_done_ = true;
  }
  frame_cv_.notify_all();
  assemble_thread_.join();
  for (auto& thread : writer_threads_) thread.join();
  for (size_t s = 0; s < n_; ++s) {
    try {
      if (loss_ && s == lost_index_) {
        sensors_[s]->Abandon();
      } else {
        sensors_[s]->Stop();
      }
    } catch (const std::exception& e) {
      if (!failed_) RecordFailure(Cat("stopping sensor: ", e.what()));
    }
  }
  UpdateTakeDrops(true);
  try {
    writer_->Close();
  } catch (const std::exception& e) {
    if (!failed_) RecordFailure(Cat("closing the take: ", e.what()));
  }
}

RecorderSummary Recorder::Session::Summarize() const {
  RecorderSummary summary;
  const SyncStats& sync = assembler_.stats();
  summary.seconds = SecondsSince(start_);
  summary.frame_sets_complete = writer_->sets_written();
  summary.frame_sets_incomplete = sync.sets_incomplete;
  summary.frame_sets_dropped = sets_dropped_;
  summary.sync_spread_us_max = static_cast<double>(spread_max_ns_) / 1e3;
  summary.sync_spread_us_mean = sync.spread_mean_ns / 1e3;
  summary.bytes_written = writer_->bytes_written();
  summary.write_mb_s =
      summary.seconds > 0 ? static_cast<double>(summary.bytes_written) / 1e6 / summary.seconds : 0;
  summary.clock_offset_ns = sync.offset_ns;
  summary.trigger_scheduling = trigger_scheduling_;
  summary.sensors = FinalRecords();
  for (size_t s = 0; s < n_; ++s) {
    const SensorState& state = state_[s];
    SensorRecord& record = summary.sensors[s];
    record.driver.update(sensors_[s]->stats().details);
    if (state.after_end > 0) record.driver["frames_after_end"] = state.after_end.load();
    if (state.warmup_frames > 0) record.driver["warmup_frames"] = state.warmup_frames.load();
    summary.frames_dropped += record.dropped() + record.discarded;
  }
  summary.lost = loss_;
  return summary;
}

RecorderSummary Recorder::Session::Run(
    const std::function<void(const RecorderStatus&)>& on_status) {
  StartSensorsAndOpenTake();
  first_tick_ = FirstTriggerTick();
  take_start_ns_ =
      software_ ? std::chrono::duration_cast<std::chrono::nanoseconds>(first_tick_ - start_).count()
                : static_cast<int64_t>(std::llround(options_.warmup_s * 1e9));
  for (SensorState& state : state_) state.last_activity_ns = take_start_ns_;
  for (size_t s = 0; s < n_; ++s) capture_threads_.emplace_back([this, s] { CaptureLoop(s); });
  if (software_) {
    for (size_t s = 0; s < n_; ++s) {
      trigger_calls_.push_back(std::make_shared<TriggerCall>());
      trigger_threads_.emplace_back([this, s] { TriggerLoop(s); });
    }
  }
  assemble_thread_ = std::thread([this] { AssembleLoop(); });
  for (int w = 0; w < options_.writer_threads; ++w)
    writer_threads_.emplace_back([this] { WriteLoop(); });
  Supervise(on_status);
  StopAndJoin();

  RecorderSummary summary = Summarize();
  if (failed_) {
    summary.End(Termination::kFailure, failure_message() + Cat(" (", summary.frame_sets_complete,
                                                               " complete frame sets kept)"));
  } else {
    summary.End(Termination::kSuccess,
                Cat(summary.frame_sets_complete, " complete frame sets, ", summary.frames_dropped,
                    " frames dropped, sync spread max ", summary.sync_spread_us_max, " us"));
  }
  return summary;
}

RecorderSummary Recorder::Run(const std::function<void(const RecorderStatus&)>& on_status,
                              Report* report) {
  Session session(*this, report);
  return session.Run(on_status);
}

}  // namespace holocap
