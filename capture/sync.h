// Frame sets from N streams.
//
// Hardware-triggered rigs: every camera counts the same trigger pulses, so frames group by
// trigger index (Frame::sequence minus the sensor's count before the first trigger). Software-
// triggered cameras whose frame counters count triggers can be grouped the same way
// (SyncOptions::match_by_sequence), which host scheduling delays cannot disturb. A set whose
// spread exceeds the tolerance is still rejected as incomplete: a camera that folded two
// triggers into one frame never joins frames of different instants.
// Software-triggered and free-running rigs: frames group by nearest timestamp within a
// tolerance, after removing each sensor's clock offset to the first sensor, estimated from the
// sets matched so far. Each set's spread is measured in the first sensor's clock; a set missing
// a sensor is counted incomplete and not emitted. A set owns the half period after its first
// frame: a frame there that is too far to join it, or that arrives after the set was given up
// on, is counted unmatched against its sensor and never opens a second set for one instant.
#pragma once

#include <cstdint>
#include <deque>
#include <optional>
#include <string>
#include <vector>

#include "core/rig.h"
#include "core/take.h"

namespace holocap {

struct SyncOptions {
  SyncMode mode = SyncMode::kSoftwareTrigger;  // how frames are grouped (see above)
  double fps = 30;                             // expected set rate; sets the default tolerance
  // Largest distance of a frame from its set's first frame, in the first sensor's clock.
  // 0: 0.4 of the frame period.
  int64_t tolerance_ns = 0;
  // How long (in stream time) to wait for a late sensor before a set is given up. 0: 3 periods.
  int64_t max_latency_ns = 0;
  // Group by trigger index even when software-triggered (always for hardware trigger).
  bool match_by_sequence = false;
  // Estimate per-sensor clock offsets (free-run and software trigger); hardware sets need none.
  bool estimate_offsets = true;
  // Weight of each new complete set in the running offset estimate (0 < w <= 1).
  double offset_smoothing = 0.1;

  void Check() const;  // throws Error explaining a bad value
  int64_t tolerance() const;
  int64_t latency() const;
};

struct SyncStats {
  int64_t sets_complete = 0;
  int64_t sets_incomplete = 0;   // sets in which at least one sensor had no frame
  int64_t frames_unmatched = 0;  // frames that belonged to no complete set
  int64_t spread_max_ns = 0;
  double spread_mean_ns = 0;
  std::vector<int64_t> offset_ns;  // per sensor: its clock minus the first sensor's clock
  std::vector<int64_t> unmatched_per_sensor;
};

// Not thread-safe: one thread feeds it (the recorder's sync thread).
class FrameSetAssembler {
 public:
  FrameSetAssembler(std::vector<std::string> sensors, std::vector<std::string> clocks,
                    SyncOptions options);

  // The sensor's frame counter just before the first trigger of the take (e.g. the frame of a
  // warm-up trigger). Without it, the counter of the sensor's first frame counts as index 0.
  void SetSequenceBase(int stream, uint64_t sequence_before_first);
  // The time each sensor stamped one event they all saw (a warm-up trigger), in its own clock:
  // seeds the clock offsets of sensors whose clocks differ. Call before the first Add();
  // sensors without one are seeded from their first frames.
  void SeedClocks(const std::vector<std::optional<int64_t>>& event_ns);
  // Adds frame from sensor `stream` (index into the sensors given to the constructor).
  void Add(int stream, Frame frame);
  // Complete sets ready now, in order. Their frames keep their own timestamps when every sensor
  // shares one clock; otherwise timestamps are mapped to the first sensor's clock.
  std::vector<FrameSet> Pop();
  // Ends the input: groups what is buffered and returns the remaining complete sets.
  std::vector<FrameSet> Flush();

  const SyncStats& stats() const { return stats_; }
  size_t buffered() const;

 private:
  std::vector<FrameSet> Assemble(bool flushing);
  void AssembleByTriggerIndex(bool flushing, std::vector<FrameSet>* out);
  void AssembleByTimestamp(bool flushing, std::vector<FrameSet>* out);
  void Emit(std::vector<Frame> frames, std::vector<int64_t> corrected, std::vector<FrameSet>* out);
  int64_t Corrected(int stream, int64_t t) const { return t - offsets_[stream]; }

  std::vector<std::string> sensors_;
  SyncOptions options_;
  bool common_clock_ = true;
  std::vector<std::deque<Frame>> queues_;
  std::vector<int64_t> offsets_;  // ns, sensor clock minus sensor 0's clock
  std::vector<bool> offset_seeded_;
  std::vector<int64_t> newest_;  // newest corrected timestamp seen per sensor
  std::vector<bool> seen_;
  std::vector<uint64_t> sequence_base_;  // by sequence: each sensor's count at trigger index 0
  std::vector<bool> base_set_;
  static constexpr size_t kSeedSets = 5;
  std::vector<std::vector<int64_t>> seed_samples_;  // by sequence, different clocks
  bool decided_any_ = false;  // by timestamp: whether a set (complete or not) was decided yet
  int64_t last_anchor_ = 0;   // the first frame's corrected time in the last set decided
  int64_t next_index_ = 0;
  double spread_sum_ns_ = 0;
  SyncStats stats_;
  std::vector<FrameSet> ready_;
};

}  // namespace holocap
