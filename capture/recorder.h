// The recorder: a rig's sensors into a take, every frame either written or counted.
//
//   sensor ─► capture thread ─► bounded frame queue ─┐
//   sensor ─► capture thread ─► bounded frame queue ─┼─► sync thread ─► bounded set queue ─► writer
//   threads ─► take (software trigger: one trigger thread per sensor, all on the same clock ticks)
//
// Back-pressure never reaches a driver: a full queue drops the newest frame (or set) and
// counts it against its sensor. A frame is lost in the driver (incomplete, never arrived), in a
// queue, in an incomplete set, or written. A write failure (full disk) ends the take cleanly:
// the sets already in the index stay readable and the failure is the summary's message.
//
// A sensor that delivers nothing (no frame, not even an incomplete one) for lost_after_periods
// frame periods while frames are due is declared lost, and so is one whose driver reports it
// gone; the take then ends as a failure that names it (RecorderSummary::lost). Frames are due
// from a software-triggered sensor once a trigger went out after its last frame, from a free-
// running one always, and from a hardware-triggered one while another sensor still delivers.
// Without triggers of its own, a sensor's frame period is the rig's or, where it delivers
// slower (a renderer), its own mean frame interval. A software trigger goes out only while no
// sensor has been silent that long, so a lost sensor misses at most lost_after_periods
// triggers after its last frame. What the lost sensor did not deliver is counted against it;
// the frames the others delivered after it fell silent are "discarded", not their drops.
//
// Each sensor is opened with the rig's sync mode and rate as SensorSpec::options "sync"
// ("software" | "hardware" | "free-run") and "fps", unless its own options set them.
#pragma once

#include <atomic>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "capture/hal.h"
#include "capture/sync.h"
#include "core/report.h"
#include "core/take.h"

namespace holocap {

struct RecorderOptions {
  int64_t frames =
      0;  // stop after this many frame sets (triggers when software-triggered); 0: no limit
  double seconds = 0;      // stop after this long; 0: no limit (one of frames/seconds must be set)
  int queue_frames = 32;   // per-sensor frames waiting for the sync thread before drops
  int queue_sets = 16;     // complete sets waiting for a writer before drops
  int writer_threads = 2;  // threads encoding and writing frames
  double warmup_s = 0.3;   // after starting the sensors, before the first trigger
  // >= 0: software triggers fire when CLOCK_REALTIME is a multiple of the frame period plus
  // this phase, so that hosts sharing a clock (PTP, NTP) trigger their cameras in step, and
  // cameras that sample triggers on a clock grid of their own see them mid-interval.
  // < 0: the first trigger fires warmup_s after start.
  double trigger_phase_s = -1;
  // > 0: the first software trigger fires at this CLOCK_REALTIME instant or, where the warm-up
  // ends later, at the first instant of the trigger_phase_s grid after it. Recorders on hosts
  // that share a clock and are given the same instant fire the same triggers.
  int64_t first_trigger_realtime_ns = 0;
  // Kept under the take's metadata beside "capture" (e.g. the capture host and its clock).
  nlohmann::json metadata = nlohmann::json::object();
  double drain_s = 1.0;  // after the last trigger, how long late frames may still arrive
  // A sensor silent for this many frame periods while frames are due is declared lost (see
  // above). Before its first frame a sensor is silent from the first trigger (software) or the
  // end of the warm-up.
  int lost_after_periods = 3;
  // Free run and hardware trigger: how long a sensor may take to deliver its first frame after
  // the warm-up, and its second after that (cameras that start streaming late, renderers).
  double first_frame_s = 5.0;
  std::string codec;              // "png" | "zstd" | "" (each driver's choice)
  int64_t sync_tolerance_ns = 0;  // SyncOptions::tolerance_ns (0: 0.4 frame periods)
  // SCHED_FIFO priority of the software-trigger threads, where the process may use it (root,
  // CAP_SYS_NICE or an rtprio limit; refused: normal scheduling, named in the summary).
  // 0: normal scheduling.
  int trigger_priority = 10;
  TakeWriterOptions take;  // crash-safety and compression of the take
  // Called by a writer thread once a complete set is in the take (its frames written, its index
  // line after them), with the set's frames as the sensors delivered them. It must return
  // quickly (hand the set over, never process it there): the writers wait for it.
  std::function<void(const FrameSet&)> on_set_written;

  void Check() const;  // throws Error explaining a bad value
};

// What happened to one sensor's frames.
struct SensorRecord {
  std::string name;
  std::string uri;
  // Software triggers sent to it, or for a lost sensor every trigger of the take (those it
  // could no longer be sent included: driver["triggers_not_sent"]).
  int64_t triggers = 0;
  int64_t frames_captured = 0;  // delivered by the driver
  int64_t lost_in_driver = 0;  // incomplete, timed out, never arrived (triggers not answered), gaps
  int64_t dropped_queue = 0;   // frame queue full
  int64_t dropped_sets = 0;    // its frame was in a set dropped because the writers fell behind
  int64_t unmatched = 0;       // in no complete set
  // Delivered after another sensor fell silent and was declared lost: no complete set could
  // hold them. Not this sensor's drops, but not in the take either.
  int64_t discarded = 0;
  int64_t written = 0;
  bool lost = false;                                 // this is RecorderSummary::lost's sensor
  nlohmann::json driver = nlohmann::json::object();  // the driver's own counters
  // Frames not in the take that this sensor is to blame for (or shares, for dropped_sets).
  int64_t dropped() const { return lost_in_driver + dropped_queue + dropped_sets + unmatched; }
};

// Which sensor was lost mid-take, and when. Times are seconds after the take's first trigger
// (software trigger) or the end of the warm-up (free run, hardware trigger).
struct SensorLoss {
  std::string sensor;  // its name in the rig
  std::string uri;
  // The first frame set it did not deliver: the first trigger after its last frame (software
  // trigger), else the count of frames it delivered or lost in the driver.
  int64_t frame_set = 0;
  double due_s = 0;                     // when that frame was due
  double declared_s = 0;                // when the recorder gave up on it
  double last_frame_s = -1;             // when its last frame arrived (-1: none after start)
  int64_t last_frame_timestamp_ns = 0;  // that frame's own timestamp, in its stream's clock
  int64_t due_timestamp_ns = 0;         // due_s as CLOCK_REALTIME
  std::string reason;                   // "no frame for 3 frame periods (150 ms)", a driver error

  nlohmann::json ToJson() const;
};

struct RecorderSummary : Summary {
  int64_t frame_sets_complete = 0;    // written to the take
  int64_t frame_sets_incomplete = 0;  // a sensor had no frame for it
  int64_t frame_sets_dropped = 0;     // complete but dropped because the writers fell behind
  int64_t frames_dropped = 0;         // every frame not in the take, all causes (discarded too)
  double sync_spread_us_max = 0;
  double sync_spread_us_mean = 0;
  double seconds = 0;  // first sensor start to the take's close
  uint64_t bytes_written = 0;
  double write_mb_s = 0;                 // bytes_written / seconds
  std::vector<int64_t> clock_offset_ns;  // per sensor, its clock minus the first sensor's
  std::string trigger_scheduling;        // how the software-trigger threads were scheduled
  std::vector<SensorRecord> sensors;
  std::optional<SensorLoss> lost;  // the sensor that ended the take by falling silent or away

  nlohmann::json Metrics() const;  // the report's "metrics" object
};

// Live numbers for a display, sent about twice a second.
struct RecorderStatus {
  double elapsed_s = 0;
  int64_t frame_sets = 0;
  double write_mb_s = 0;
  double spread_us_last = 0;
  double spread_us_max = 0;
  struct PerSensor {
    std::string name;
    double fps = 0;
    int64_t dropped = 0;
  };
  std::vector<PerSensor> sensors;
};

class Recorder {
 public:
  // Opens every sensor of the rig (Error naming the sensor when one cannot be opened or
  // configured) and checks that `out` can become a take; nothing is written yet.
  Recorder(const RigDescription& rig, std::filesystem::path out, RecorderOptions options,
           DriverRegistry& registry = DriverRegistry::Global());
  ~Recorder();
  Recorder(const Recorder&) = delete;
  Recorder& operator=(const Recorder&) = delete;

  // Records until the frame/time limit, RequestStop() or a failure. A lost sensor or a
  // failed write is reported as Termination::kFailure with one clear message (a lost sensor's
  // names it, the frame set and the time); the take then
  // holds every complete set written before it. `report` (optional) receives a per-set sync
  // spread series.
  RecorderSummary Run(const std::function<void(const RecorderStatus&)>& on_status = {},
                      Report* report = nullptr);
  // Sets RecorderOptions::on_set_written (before Run()).
  void set_on_set_written(std::function<void(const FrameSet&)> callback) {
    options_.on_set_written = std::move(callback);
  }
  // Ends the recording early (thread-safe; safe from a signal handler).
  void RequestStop() { stop_requested_ = true; }

  const std::vector<StreamInfo>& streams() const { return streams_; }
  // The exact models the drivers know (simulation, a replayed take's calibration), by sensor.
  std::map<std::string, CameraModel> KnownModels() const;
  // The sensors whose known model is a simulation's truth, not a calibration.
  std::set<std::string> TrueModelSensors() const;

 private:
  class Session;  // one run: its threads and what they share (recorder.cpp)
  RigDescription rig_;
  std::filesystem::path out_;
  RecorderOptions options_;
  // Shared with a trigger thread that is left waiting on a lost sensor (recorder.cpp).
  std::vector<std::shared_ptr<Sensor>> sensors_;
  std::vector<StreamInfo> streams_;
  std::atomic<bool> stop_requested_{false};
};

}  // namespace holocap
