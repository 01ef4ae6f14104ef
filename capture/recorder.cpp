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

#include "core/error.h"

namespace holocap {
namespace {

using Clock = std::chrono::steady_clock;

double SecondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

}  // namespace

void RecorderOptions::Check() const {
  if (frames < 0) Fail("capture: frames must be >= 0");
  if (seconds < 0 || !std::isfinite(seconds)) Fail("capture: seconds must be >= 0");
  if (frames == 0 && seconds == 0) Fail("capture: give a frame count or a duration");
  if (queue_frames < 1) Fail("capture: queue_frames must be >= 1");
  if (queue_sets < 1) Fail("capture: queue_sets must be >= 1");
  if (writer_threads < 1 || writer_threads > 64) Fail("capture: writer_threads must be 1..64");
  if (warmup_s < 0 || drain_s < 0) Fail("capture: warmup_s and drain_s must be >= 0");
  if (!(stall_s > 0)) Fail("capture: stall_s must be positive");
  if (!codec.empty() && codec != "png" && codec != "zstd") Fail("capture: codec must be png or zstd (not '", codec, "')");
  if (sync_tolerance_ns < 0) Fail("capture: sync_tolerance_ns must be >= 0");
  if (trigger_priority < 0 || trigger_priority > 99) Fail("capture: trigger_priority must be 0..99");
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
          {"sensors", per_sensor}};
}

Recorder::Recorder(const RigDescription& rig, std::filesystem::path out, RecorderOptions options,
                   DriverRegistry& registry)
    : rig_(rig), out_(std::move(out)), options_(std::move(options)) {
  options_.Check();
  rig_.Check();
  if (rig_.sensors.empty()) Fail("rig '", rig_.name, "' has no sensors");
  std::error_code ec;
  if (std::filesystem::exists(out_, ec) &&
      (!std::filesystem::is_directory(out_, ec) || (!std::filesystem::is_empty(out_, ec) && !options_.take.overwrite))) {
    Fail("'", out_.string(), "' exists and is not an empty directory (refusing to overwrite a take)");
  }
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
    if (options_.codec == "png" && stream.pixel_format != "depth_m") stream.codec = ImageCodec::kPng;
    if (options_.codec == "zstd" && stream.pixel_format != "depth_m") stream.codec = ImageCodec::kZstd;
    streams_.push_back(stream);
    if (rig_.sync == SyncMode::kSoftwareTrigger && !sensors_.back()->supports_software_trigger()) {
      Fail("sensor '", spec.name, "' (", spec.uri, ") cannot be software-triggered; give the rig sync: free-run",
           " or hardware");
    }
  }
}

Recorder::~Recorder() = default;

struct Recorder::Shared {
  explicit Shared(size_t n)
      : queued(n, 0), triggers(n), captured(n), dropped_queue(n), dropped_sets(n), unmatched(n), written(n),
        sequence_gaps(n), after_end(n), warmup_frames(n), warmup_sequence(n), warmup_timestamp(n),
        lost_before_first_trigger(n), ended(n) {}

  void Failure(const std::string& message) {
    std::lock_guard lock(failure_mutex);
    if (failure.empty()) failure = message;
    failed = true;
    stop_triggers = true;
    stop_capture = true;
  }
  std::string failure_message() {
    std::lock_guard lock(failure_mutex);
    return failure;
  }

  std::mutex frame_mutex;
  std::condition_variable frame_cv;
  std::deque<std::pair<int, Frame>> frames;
  std::vector<int> queued;
  bool capture_done = false;

  std::mutex set_mutex;
  std::condition_variable set_cv;
  std::deque<FrameSet> sets;
  bool sync_done = false;

  std::atomic<bool> stop_triggers{false};
  std::atomic<bool> stop_capture{false};
  std::atomic<bool> failed{false};
  std::mutex failure_mutex;
  std::string failure;

  std::vector<std::atomic<int64_t>> triggers, captured, dropped_queue, dropped_sets, unmatched, written,
      sequence_gaps, after_end, warmup_frames, warmup_sequence, warmup_timestamp, lost_before_first_trigger;
  std::vector<std::atomic<bool>> ended;
  std::atomic<int64_t> sets_complete{0}, sets_incomplete{0}, sets_dropped{0};
  std::atomic<int64_t> spread_last_ns{0}, spread_max_ns{0};
};

RecorderSummary Recorder::Run(const std::function<void(const RecorderStatus&)>& on_status, Report* report) {
  const size_t n = sensors_.size();
  const bool software = rig_.sync == SyncMode::kSoftwareTrigger;
  const double period_s = 1.0 / rig_.fps;
  Shared shared(n);
  RecorderSummary summary;

  const auto start = Clock::now();
  size_t started = 0;
  try {
    for (; started < n; ++started) sensors_[started]->Start();
  } catch (const Error&) {
    for (size_t i = 0; i < started; ++i) sensors_[i]->Stop();
    throw;
  }
  std::unique_ptr<TakeWriter> writer;
  try {
    nlohmann::json metadata = {{"capture",
                                {{"sync", ToString(rig_.sync)},
                                 {"fps", rig_.fps},
                                 {"frames", options_.frames},
                                 {"seconds", options_.seconds},
                                 {"sync_tolerance_ns", options_.sync_tolerance_ns}}}};
    writer = std::make_unique<TakeWriter>(out_, rig_, streams_, metadata, options_.take);
  } catch (const Error&) {
    for (auto& sensor : sensors_) sensor->Stop();
    throw;
  }

  const int64_t trigger_count =
      options_.frames > 0 ? options_.frames : static_cast<int64_t>(std::llround(options_.seconds * rig_.fps));
  auto first_tick = start + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(options_.warmup_s));
  if (options_.trigger_phase_s >= 0) {
    // The first grid instant after the warm-up, carried over to the steady clock.
    const int64_t period_ns = static_cast<int64_t>(std::llround(period_s * 1e9));
    const int64_t phase_ns = static_cast<int64_t>(std::llround(options_.trigger_phase_s * 1e9)) % period_ns;
    const int64_t realtime_ns = std::chrono::duration_cast<std::chrono::nanoseconds>(
                                    std::chrono::system_clock::now().time_since_epoch()).count();
    const int64_t steady_now_ns = std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now() - start).count();
    const int64_t earliest = realtime_ns - steady_now_ns + static_cast<int64_t>(options_.warmup_s * 1e9);
    int64_t grid = (earliest - phase_ns + period_ns - 1) / period_ns * period_ns + phase_ns;
    first_tick = start + std::chrono::nanoseconds(grid - (realtime_ns - steady_now_ns));
  }
  // Capture threads: grab, stamp, queue; never block on anything downstream.
  std::vector<std::thread> capture_threads;
  for (size_t s = 0; s < n; ++s) {
    capture_threads.emplace_back([&, s] {
      Sensor& sensor = *sensors_[s];
      auto last_frame = Clock::now();
      uint64_t last_lost = 0;
      bool have_sequence = false;
      uint64_t last_sequence = 0;
      while (!shared.stop_capture) {
        Frame frame;
        bool got = false;
        try {
          got = sensor.Grab(&frame, std::chrono::milliseconds(100));
        } catch (const std::exception& e) {
          shared.Failure(Cat("sensor '", streams_[s].name, "' was lost mid-take: ", e.what()));
          break;
        }
        if (!got) {
          if (sensor.ended()) {
            shared.ended[s] = true;
            break;
          }
          // Incomplete frames the driver throws away still show the camera is alive.
          const uint64_t lost = sensor.stats().frames_lost;
          const bool due = (!software || shared.triggers[s] > shared.captured[s]) && lost == last_lost;
          last_lost = lost;
          if (due && SecondsSince(last_frame) > options_.stall_s) {
            shared.Failure(Cat("sensor '", streams_[s].name, "' (", streams_[s].uri, ") delivered no frame for ",
                               options_.stall_s, " s; it was lost mid-take"));
            break;
          }
          if (!due) last_frame = Clock::now();
          continue;
        }
        last_frame = Clock::now();
        if (software && last_frame < first_tick) {
          ++shared.warmup_frames[s];
          shared.warmup_sequence[s] = static_cast<int64_t>(frame.sequence);
          shared.warmup_timestamp[s] = frame.timestamp_ns;
          continue;
        }
        ++shared.captured[s];
        if (have_sequence && frame.sequence > last_sequence + 1) {
          shared.sequence_gaps[s] += static_cast<int64_t>(frame.sequence - last_sequence - 1);
        }
        have_sequence = true;
        last_sequence = frame.sequence;
        frame.sensor = streams_[s].name;
        {
          std::lock_guard lock(shared.frame_mutex);
          if (shared.queued[s] >= options_.queue_frames) {
            ++shared.dropped_queue[s];
            continue;
          }
          ++shared.queued[s];
          shared.frames.emplace_back(static_cast<int>(s), std::move(frame));
        }
        shared.frame_cv.notify_one();
      }
    });
  }

  // Software trigger: one thread per sensor, all firing on the same ticks, so that a slow or
  // dead camera delays only itself. A trigger sent late exposes its camera late, so the
  // threads ask for real-time scheduling: other work on the host cannot hold them back.
  std::vector<std::thread> trigger_threads;
  std::string trigger_scheduling = software ? "normal" : "none (not software-triggered)";
  if (software) {
    for (size_t s = 0; s < n; ++s) {
      trigger_threads.emplace_back([&, s] {
        if (options_.trigger_priority > 0) {
          sched_param param{};
          param.sched_priority = options_.trigger_priority;
          const int refused = pthread_setschedparam(pthread_self(), SCHED_FIFO, &param);
          if (s == 0) {  // read after the threads are joined
            trigger_scheduling = refused == 0 ? Cat("SCHED_FIFO ", options_.trigger_priority)
                                              : Cat("normal (SCHED_FIFO refused: ", std::strerror(refused), ")");
          }
        }
        // Two triggers during the warm-up, their frames discarded: the first wakes up cameras
        // that start streaming late, the second is one instant every camera stamps, which
        // ties their clocks together (FrameSetAssembler::SeedClocks).
        for (double at : {0.0, 0.5}) {
          std::this_thread::sleep_until(start + std::chrono::duration_cast<Clock::duration>(
                                                    std::chrono::duration<double>(at * options_.warmup_s)));
          try {
            sensors_[s]->Trigger();
          } catch (const std::exception& e) {
            shared.Failure(Cat("sensor '", streams_[s].name, "' did not take a software trigger: ", e.what()));
            return;
          }
        }
        // Incomplete frames of the warm-up triggers are no frames of the take.
        shared.lost_before_first_trigger[s] = static_cast<int64_t>(sensors_[s]->stats().frames_lost);
        for (int64_t k = 0; k < trigger_count && !shared.stop_triggers; ++k) {
          const auto tick = first_tick + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(k * period_s));
          while (Clock::now() < tick && !shared.stop_triggers) {
            std::this_thread::sleep_for(std::min<Clock::duration>(tick - Clock::now(), std::chrono::milliseconds(20)));
          }
          if (shared.stop_triggers) break;
          try {
            sensors_[s]->Trigger();
          } catch (const std::exception& e) {
            shared.Failure(Cat("sensor '", streams_[s].name, "' was lost mid-take: ", e.what()));
            break;
          }
          ++shared.triggers[s];
        }
      });
    }
  }

  // Sync thread: frame queue -> frame sets -> set queue.
  SyncOptions sync_options;
  sync_options.mode = rig_.sync;
  sync_options.fps = rig_.fps;
  sync_options.tolerance_ns = options_.sync_tolerance_ns;
  std::vector<std::string> names, clocks;
  for (const auto& stream : streams_) {
    names.push_back(stream.name);
    clocks.push_back(stream.clock);
  }
  FrameSetAssembler assembler(names, clocks, sync_options);
  auto index_of = [&](const std::string& name) {
    return static_cast<size_t>(std::distance(names.begin(), std::find(names.begin(), names.end(), name)));
  };
  const bool free_run_limit = !software && options_.frames > 0;
  auto enqueue_set = [&](FrameSet set) {
    if (free_run_limit && shared.sets_complete >= options_.frames) {
      for (const auto& frame : set.frames) ++shared.after_end[index_of(frame.sensor)];
      return;
    }
    const int64_t spread = set.SpreadNs();
    if (report != nullptr) report->AddPoint("sync_spread_us", static_cast<double>(spread) / 1e3, set.index);
    shared.spread_last_ns = spread;
    shared.spread_max_ns = std::max<int64_t>(shared.spread_max_ns, spread);
    ++shared.sets_complete;
    if (free_run_limit && shared.sets_complete >= options_.frames) shared.stop_capture = true;
    std::unique_lock lock(shared.set_mutex);
    if (shared.failed || static_cast<int>(shared.sets.size()) >= options_.queue_sets) {
      lock.unlock();
      ++shared.sets_dropped;
      for (size_t s = 0; s < n; ++s) {
        if (set.Find(names[s]) != nullptr) ++shared.dropped_sets[s];
      }
      return;
    }
    shared.sets.push_back(std::move(set));
    lock.unlock();
    shared.set_cv.notify_one();
  };
  std::thread sync_thread([&] {
    bool seeded = false;
    while (true) {
      std::deque<std::pair<int, Frame>> batch;
      {
        std::unique_lock lock(shared.frame_mutex);
        shared.frame_cv.wait_for(lock, std::chrono::milliseconds(50),
                                 [&] { return !shared.frames.empty() || shared.capture_done; });
        batch.swap(shared.frames);
        std::fill(shared.queued.begin(), shared.queued.end(), 0);
        if (batch.empty() && shared.capture_done) break;
      }
      if (!batch.empty() && !seeded) {
        // Every camera stamped the warm-up trigger: the one event that ties their clocks.
        seeded = true;
        std::vector<std::optional<int64_t>> events(n);
        for (size_t s = 0; s < n; ++s) {
          if (shared.warmup_frames[s] > 0) events[s] = shared.warmup_timestamp[s].load();
        }
        assembler.SeedClocks(events);
      }
      for (auto& [s, frame] : batch) {
        if (free_run_limit && shared.sets_complete >= options_.frames) {
          ++shared.after_end[s];
          continue;
        }
        assembler.Add(s, std::move(frame));
      }
      for (auto& set : assembler.Pop()) enqueue_set(std::move(set));
    }
    for (auto& set : assembler.Flush()) enqueue_set(std::move(set));
    {
      std::lock_guard lock(shared.set_mutex);
      shared.sync_done = true;
    }
    shared.set_cv.notify_all();
  });

  std::vector<std::thread> writer_threads;
  for (int w = 0; w < options_.writer_threads; ++w) {
    writer_threads.emplace_back([&] {
      while (true) {
        FrameSet set;
        {
          std::unique_lock lock(shared.set_mutex);
          shared.set_cv.wait(lock, [&] { return !shared.sets.empty() || shared.sync_done; });
          if (shared.sets.empty()) break;
          set = std::move(shared.sets.front());
          shared.sets.pop_front();
        }
        if (!shared.failed) {
          try {
            writer->Append(set);
            for (const auto& frame : set.frames) {
              ++shared.written[index_of(frame.sensor)];
            }
            continue;
          } catch (const std::exception& e) {
            shared.Failure(Cat("writing frame set ", set.index, " failed: ", e.what(), "; the take keeps every",
                               " frame set written before"));
          }
        }
        ++shared.sets_dropped;
        for (const auto& frame : set.frames) {
          ++shared.dropped_sets[index_of(frame.sensor)];
        }
      }
    });
  }

  // Lost inside the driver. Software trigger: every trigger not answered by a frame. Free run
  // and hardware trigger: the driver's count or the gaps in the frame counter.
  auto lost_in_driver = [&](size_t s, bool final) -> int64_t {
    const int64_t reported = static_cast<int64_t>(sensors_[s]->stats().frames_lost);
    if (software) {
      // Every trigger the take sent and no complete frame answered; while frames may still be
      // on their way, only those the driver already saw incomplete.
      const int64_t unanswered = std::max<int64_t>(0, shared.triggers[s] - shared.captured[s]);
      return final ? unanswered : std::min(unanswered, reported - shared.lost_before_first_trigger[s]);
    }
    return std::max<int64_t>(reported, shared.sequence_gaps[s]);
  };
  std::vector<int64_t> counted_drops(n, 0);
  auto update_take_drops = [&](bool final) {
    for (size_t s = 0; s < n; ++s) {
      const int64_t now = lost_in_driver(s, final) + shared.dropped_queue[s] + shared.dropped_sets[s] +
                          (final ? static_cast<int64_t>(assembler.stats().unmatched_per_sensor[s]) : 0);
      if (now > counted_drops[s]) writer->CountDropped(streams_[s].name, now - counted_drops[s]);
      counted_drops[s] = std::max(counted_drops[s], now);
    }
  };

  // The calling thread decides when to stop and reports progress.
  std::vector<int64_t> last_captured(n, 0);
  auto last_status = Clock::now();
  bool triggers_done_at_set = false;
  Clock::time_point triggers_done;
  while (!shared.stop_capture) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    const double elapsed = SecondsSince(start);
    if (stop_requested_) {
      shared.stop_triggers = true;
      shared.stop_capture = true;
    }
    if (std::all_of(shared.ended.begin(), shared.ended.end(), [](const auto& e) { return e.load(); })) {
      shared.stop_capture = true;
    }
    if (software) {
      bool all_sent = true;
      for (size_t s = 0; s < n; ++s) all_sent &= shared.triggers[s] >= trigger_count;
      if (all_sent && !triggers_done_at_set) {
        triggers_done_at_set = true;
        triggers_done = Clock::now();
      }
      if (triggers_done_at_set) {
        bool all_answered = true;
        for (size_t s = 0; s < n; ++s) {
          all_answered &= shared.captured[s] + static_cast<int64_t>(sensors_[s]->stats().frames_lost) -
                              shared.lost_before_first_trigger[s] >=
                          trigger_count;
        }
        if (all_answered || SecondsSince(triggers_done) > options_.drain_s) shared.stop_capture = true;
      }
    } else if (options_.seconds > 0 && elapsed >= options_.seconds + options_.warmup_s) {
      shared.stop_capture = true;
    }
    if (Clock::now() - last_status >= std::chrono::milliseconds(500)) {
      const double dt = SecondsSince(last_status);
      last_status = Clock::now();
      update_take_drops(false);
      if (on_status) {
        RecorderStatus status;
        status.elapsed_s = elapsed;
        status.frame_sets = writer->sets_written();
        status.write_mb_s = elapsed > 0 ? static_cast<double>(writer->bytes_written()) / 1e6 / elapsed : 0;
        status.spread_us_last = static_cast<double>(shared.spread_last_ns) / 1e3;
        status.spread_us_max = static_cast<double>(shared.spread_max_ns) / 1e3;
        for (size_t s = 0; s < n; ++s) {
          const int64_t captured = shared.captured[s];
          status.sensors.push_back({streams_[s].name, static_cast<double>(captured - last_captured[s]) / dt,
                                    counted_drops[s]});
          last_captured[s] = captured;
        }
        on_status(status);
      }
    }
  }
  shared.stop_triggers = true;
  for (auto& thread : trigger_threads) thread.join();
  for (auto& thread : capture_threads) thread.join();
  {
    std::lock_guard lock(shared.frame_mutex);
    shared.capture_done = true;
  }
  shared.frame_cv.notify_all();
  sync_thread.join();
  for (auto& thread : writer_threads) thread.join();
  for (auto& sensor : sensors_) {
    try {
      sensor->Stop();
    } catch (const std::exception& e) {
      if (!shared.failed) shared.Failure(Cat("stopping sensor: ", e.what()));
    }
  }

  update_take_drops(true);
  try {
    writer->Close();
  } catch (const std::exception& e) {
    if (!shared.failed) shared.Failure(Cat("closing the take: ", e.what()));
  }

  const SyncStats& sync = assembler.stats();
  summary.seconds = SecondsSince(start);
  summary.frame_sets_complete = writer->sets_written();
  summary.frame_sets_incomplete = sync.sets_incomplete;
  summary.frame_sets_dropped = shared.sets_dropped;
  summary.sync_spread_us_max = static_cast<double>(shared.spread_max_ns) / 1e3;
  summary.sync_spread_us_mean = sync.spread_mean_ns / 1e3;
  summary.bytes_written = writer->bytes_written();
  summary.write_mb_s = summary.seconds > 0 ? static_cast<double>(summary.bytes_written) / 1e6 / summary.seconds : 0;
  summary.clock_offset_ns = sync.offset_ns;
  summary.trigger_scheduling = trigger_scheduling;
  for (size_t s = 0; s < n; ++s) {
    SensorRecord record;
    record.name = streams_[s].name;
    record.uri = streams_[s].uri;
    record.triggers = shared.triggers[s];
    record.frames_captured = shared.captured[s];
    record.lost_in_driver = lost_in_driver(s, true);
    record.dropped_queue = shared.dropped_queue[s];
    record.dropped_sets = shared.dropped_sets[s];
    record.unmatched = sync.unmatched_per_sensor[s];
    record.written = shared.written[s];
    record.driver = sensors_[s]->stats().details;
    if (shared.after_end[s] > 0) record.driver["frames_after_end"] = shared.after_end[s].load();
    if (shared.warmup_frames[s] > 0) record.driver["warmup_frames"] = shared.warmup_frames[s].load();
    summary.frames_dropped += record.dropped();
    summary.sensors.push_back(std::move(record));
  }
  if (shared.failed) {
    summary.termination = Termination::kFailure;
    summary.message = shared.failure_message() + Cat(" (", summary.frame_sets_complete, " complete frame sets kept)");
  } else {
    summary.termination = Termination::kSuccess;
    summary.message = Cat(summary.frame_sets_complete, " complete frame sets, ", summary.frames_dropped,
                          " frames dropped, sync spread max ", summary.sync_spread_us_max, " us");
  }
  return summary;
}

}  // namespace holocap
