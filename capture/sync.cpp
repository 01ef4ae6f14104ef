#include "capture/sync.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "core/check_option.h"
#include "core/error.h"

namespace holocap {

void SyncOptions::Check() const {
  HOLOCAP_CHECK_OPTION_GT(fps, 0);
  HOLOCAP_CHECK_OPTION(std::isfinite(fps), fps);
  HOLOCAP_CHECK_OPTION_GE(tolerance_ns, 0, "0 picks 0.4 of the frame period");
  HOLOCAP_CHECK_OPTION_GE(max_latency_ns, 0, "0 picks 3 frame periods");
  HOLOCAP_CHECK_OPTION_GT(offset_smoothing, 0);
  HOLOCAP_CHECK_OPTION_LE(offset_smoothing, 1);
  const int64_t period = static_cast<int64_t>(1e9 / fps);
  HOLOCAP_CHECK_OPTION(tolerance() * 2 < period, tolerance_ns,
                       Cat("a tolerance of ", tolerance() / 1e3,
                           " us would let one set take two frames of a sensor at ", fps,
                           " fps: keep it under half the ", period / 1e3, " us period"));
}

int64_t SyncOptions::tolerance() const {
  return tolerance_ns > 0 ? tolerance_ns : static_cast<int64_t>(0.4e9 / fps);
}

int64_t SyncOptions::latency() const {
  return max_latency_ns > 0 ? max_latency_ns : static_cast<int64_t>(3e9 / fps);
}

FrameSetAssembler::FrameSetAssembler(std::vector<std::string> sensors,
                                     std::vector<std::string> clocks, SyncOptions options)
    : sensors_(std::move(sensors)), options_(options) {
  options_.Check();
  if (sensors_.empty()) Fail("sync: no sensors");
  if (clocks.size() != sensors_.size()) Fail("sync: one clock name per sensor expected");
  for (const auto& clock : clocks) common_clock_ &= clock == clocks.front();
  const size_t n = sensors_.size();
  queues_.resize(n);
  offsets_.assign(n, 0);
  offset_seeded_.assign(n, common_clock_);
  offset_seeded_[0] = true;
  newest_.assign(n, std::numeric_limits<int64_t>::min());
  seen_.assign(n, false);
  sequence_base_.assign(n, 0);
  base_set_.assign(n, false);
  stats_.offset_ns.assign(n, 0);
  stats_.unmatched_per_sensor.assign(n, 0);
}

size_t FrameSetAssembler::buffered() const {
  size_t total = 0;
  for (const auto& queue : queues_) total += queue.size();
  return total;
}

void FrameSetAssembler::SetSequenceBase(int stream, uint64_t sequence_before_first) {
  if (stream < 0 || stream >= static_cast<int>(queues_.size())) Fail("sync: no stream ", stream);
  sequence_base_[stream] = sequence_before_first + 1;
  base_set_[stream] = true;
}

void FrameSetAssembler::SeedClocks(const std::vector<std::optional<int64_t>>& event_ns) {
  if (event_ns.size() != queues_.size()) Fail("sync: one event time per sensor expected");
  if (common_clock_ || !event_ns[0]) return;
  for (size_t s = 1; s < queues_.size(); ++s) {
    if (!event_ns[s] || offset_seeded_[s]) continue;
    offsets_[s] = *event_ns[s] - *event_ns[0];
    offset_seeded_[s] = true;
  }
}

void FrameSetAssembler::Add(int stream, Frame frame) {
  if (stream < 0 || stream >= static_cast<int>(queues_.size())) Fail("sync: no stream ", stream);
  if (!seen_[stream]) {
    seen_[stream] = true;
    if (!base_set_[stream]) sequence_base_[stream] = frame.sequence;
    // Different clocks: the first frames of two sensors are taken to be near-simultaneous;
    // the running estimate refines that from then on. (By sequence, the first complete set
    // seeds them instead.)
    const bool by_sequence =
        options_.mode == SyncMode::kHardwareTrigger || options_.match_by_sequence;
    if (!by_sequence && !offset_seeded_[stream] && seen_[0]) {
      offsets_[stream] =
          frame.timestamp_ns - (queues_[0].empty() ? newest_[0] : queues_[0].front().timestamp_ns);
      offset_seeded_[stream] = true;
    }
    if (!by_sequence && stream == 0) {
      for (size_t s = 1; s < queues_.size(); ++s) {
        if (!offset_seeded_[s] && !queues_[s].empty()) {
          offsets_[s] = queues_[s].front().timestamp_ns - frame.timestamp_ns;
          offset_seeded_[s] = true;
        }
      }
    }
  }
  newest_[stream] = std::max(newest_[stream], frame.timestamp_ns);
  queues_[stream].push_back(std::move(frame));
  auto sets = Assemble(false);
  for (auto& set : sets) ready_.push_back(std::move(set));
}

std::vector<FrameSet> FrameSetAssembler::Pop() {
  std::vector<FrameSet> out;
  out.swap(ready_);
  return out;
}

std::vector<FrameSet> FrameSetAssembler::Flush() {
  std::vector<FrameSet> out = Pop();
  for (auto& set : Assemble(true)) out.push_back(std::move(set));
  for (size_t s = 0; s < queues_.size(); ++s) {
    stats_.frames_unmatched += static_cast<int64_t>(queues_[s].size());
    stats_.unmatched_per_sensor[s] += static_cast<int64_t>(queues_[s].size());
    queues_[s].clear();
  }
  return out;
}

std::vector<FrameSet> FrameSetAssembler::Assemble(bool flushing) {
  std::vector<FrameSet> out;
  if (options_.mode == SyncMode::kHardwareTrigger || options_.match_by_sequence) {
    AssembleByTriggerIndex(flushing, &out);
    return out;
  }
  for (size_t s = 0; s < queues_.size(); ++s) {
    if (!offset_seeded_[s]) return out;  // no common time base yet
  }
  { AssembleByTimestamp(flushing, &out); }
  return out;
}

void FrameSetAssembler::AssembleByTriggerIndex(bool flushing, std::vector<FrameSet>* out) {
  const size_t n = queues_.size();
  auto key = [&](size_t s, const Frame& f) {
    return static_cast<int64_t>(f.sequence) - static_cast<int64_t>(sequence_base_[s]);
  };
  const int64_t latency_sets =
      std::max<int64_t>(2, static_cast<int64_t>(options_.latency() * options_.fps / 1e9));
  while (true) {
    int64_t lowest = std::numeric_limits<int64_t>::max(),
            highest = std::numeric_limits<int64_t>::min();
    for (size_t s = 0; s < n; ++s) {
      if (queues_[s].empty()) continue;
      lowest = std::min(lowest, key(s, queues_[s].front()));
      highest = std::max(highest, key(s, queues_[s].back()));
    }
    if (lowest == std::numeric_limits<int64_t>::max()) return;
    bool complete = true, decided = true;
    for (size_t s = 0; s < n; ++s) {
      if (!queues_[s].empty() && key(s, queues_[s].front()) == lowest) continue;
      complete = false;
      // A sensor whose queue is empty may still deliver trigger `lowest`, unless it is past it.
      if (queues_[s].empty()) decided &= flushing || highest - lowest > latency_sets;
    }
    if (!complete && !decided) return;
    std::vector<Frame> frames;
    std::vector<int64_t> corrected;
    for (size_t s = 0; s < n; ++s) {
      if (queues_[s].empty() || key(s, queues_[s].front()) != lowest) continue;
      corrected.push_back(Corrected(static_cast<int>(s), queues_[s].front().timestamp_ns));
      frames.push_back(std::move(queues_[s].front()));
      queues_[s].pop_front();
      if (!complete) ++stats_.unmatched_per_sensor[s];
    }
    if (complete) {
      // Frames of one trigger index share an instant: that is what seeds the offsets between
      // different clocks, and what a set far wider than the tolerance contradicts.
      // The offsets start as the median over the first few sets, so that one late frame
      // cannot skew them.
      bool seeding = !common_clock_ && seed_samples_.size() < kSeedSets;
      if (seeding) {
        std::vector<int64_t> sample(n);
        for (size_t s = 0; s < n; ++s) sample[s] = frames[s].timestamp_ns - frames[0].timestamp_ns;
        seed_samples_.push_back(sample);
        for (size_t s = 1; s < n; ++s) {
          std::vector<int64_t> values;
          for (const auto& row : seed_samples_) values.push_back(row[s]);
          std::nth_element(values.begin(), values.begin() + values.size() / 2, values.end());
          offsets_[s] = values[values.size() / 2];
          offset_seeded_[s] = true;
        }
        for (size_t s = 0; s < n; ++s)
          corrected[s] = Corrected(static_cast<int>(s), frames[s].timestamp_ns);
      }
      const auto [lo, hi] = std::minmax_element(corrected.begin(), corrected.end());
      if (seeding || *hi - *lo <= options_.tolerance()) {
        Emit(std::move(frames), std::move(corrected), out);
        continue;
      }
      for (size_t s = 0; s < n; ++s) ++stats_.unmatched_per_sensor[s];
    }
    ++stats_.sets_incomplete;
    stats_.frames_unmatched += static_cast<int64_t>(frames.size());
  }
}

void FrameSetAssembler::AssembleByTimestamp(bool flushing, std::vector<FrameSet>* out) {
  const size_t n = queues_.size();
  const int64_t tolerance = options_.tolerance();
  // Each set owns the instants nearer to its first frame than to the next set's, half a period
  // on: a frame there belongs to this set's trigger, also when it is too far to join the set.
  const int64_t window = std::max(tolerance, static_cast<int64_t>(0.5e9 / options_.fps));
  auto count_unmatched = [&](size_t s) {
    ++stats_.frames_unmatched;
    ++stats_.unmatched_per_sensor[s];
  };
  while (true) {
    // A frame of an instant already decided (its sensor was given up on after the latency and
    // delivered it later) is counted against its sensor; it opens no set of its own, which would
    // count that instant twice.
    if (decided_any_) {
      for (size_t s = 0; s < n; ++s) {
        while (!queues_[s].empty() &&
               Corrected(static_cast<int>(s), queues_[s].front().timestamp_ns) - last_anchor_ <=
                   window) {
          queues_[s].pop_front();
          count_unmatched(s);
        }
      }
    }
    int64_t anchor = std::numeric_limits<int64_t>::max();
    int64_t newest = std::numeric_limits<int64_t>::min();
    for (size_t s = 0; s < n; ++s) {
      if (!queues_[s].empty())
        anchor = std::min(anchor, Corrected(static_cast<int>(s), queues_[s].front().timestamp_ns));
      if (seen_[s]) newest = std::max(newest, Corrected(static_cast<int>(s), newest_[s]));
    }
    if (anchor == std::numeric_limits<int64_t>::max()) return;
    bool waiting = false;
    for (size_t s = 0; s < n; ++s) {
      if (!queues_[s].empty()) continue;
      // Frames of one sensor arrive in order: once it is past the anchor, it has none for it.
      const bool passed =
          seen_[s] && Corrected(static_cast<int>(s), newest_[s]) > anchor + tolerance;
      if (!passed && !flushing && newest - anchor <= options_.latency()) waiting = true;
    }
    if (waiting) return;
    std::vector<Frame> frames;
    std::vector<int64_t> corrected;
    std::vector<size_t> members, outside;
    for (size_t s = 0; s < n; ++s) {
      if (queues_[s].empty()) continue;
      const int64_t t = Corrected(static_cast<int>(s), queues_[s].front().timestamp_ns);
      if (t - anchor > window) continue;
      if (t - anchor > tolerance) {
        // This instant's frame, beyond the tolerance: the set is incomplete.
        queues_[s].pop_front();
        outside.push_back(s);
        continue;
      }
      corrected.push_back(t);
      frames.push_back(std::move(queues_[s].front()));
      queues_[s].pop_front();
      members.push_back(s);
    }
    decided_any_ = true;
    last_anchor_ = anchor;
    if (frames.size() == n) {
      Emit(std::move(frames), std::move(corrected), out);
    } else {
      ++stats_.sets_incomplete;
      for (size_t s : members) count_unmatched(s);
      for (size_t s : outside) count_unmatched(s);
    }
  }
}

void FrameSetAssembler::Emit(std::vector<Frame> frames, std::vector<int64_t> corrected,
                             std::vector<FrameSet>* out) {
  // Frames arrive here in sensor order with every sensor present.
  const double w = stats_.sets_complete == 0 ? 1.0 : options_.offset_smoothing;
  for (size_t s = 1; s < frames.size(); ++s) {
    const double raw_offset = static_cast<double>(frames[s].timestamp_ns - frames[0].timestamp_ns);
    if (options_.estimate_offsets) {
      if (common_clock_) {
        stats_.offset_ns[s] = static_cast<int64_t>(
            std::llround(stats_.offset_ns[s] + w * (raw_offset - stats_.offset_ns[s])));
      } else {
        offsets_[s] += static_cast<int64_t>(
            std::llround(options_.offset_smoothing * (raw_offset - offsets_[s])));
      }
    }
    if (!common_clock_) stats_.offset_ns[s] = offsets_[s];
  }
  FrameSet set;
  set.index = next_index_++;
  int64_t lo = *std::min_element(corrected.begin(), corrected.end());
  int64_t hi = *std::max_element(corrected.begin(), corrected.end());
  for (size_t s = 0; s < frames.size(); ++s) {
    if (!common_clock_) frames[s].timestamp_ns = corrected[s];
    set.frames.push_back(std::move(frames[s]));
  }
  const int64_t spread = hi - lo;
  ++stats_.sets_complete;
  spread_sum_ns_ += static_cast<double>(spread);
  stats_.spread_max_ns = std::max(stats_.spread_max_ns, spread);
  stats_.spread_mean_ns = spread_sum_ns_ / static_cast<double>(stats_.sets_complete);
  out->push_back(std::move(set));
}

}  // namespace holocap
