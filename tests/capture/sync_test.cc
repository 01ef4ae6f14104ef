#include "capture/sync.h"

#include <gtest/gtest.h>

#include <random>

#include "core/error.h"

namespace holocap {
namespace {

Frame MakeFrame(int64_t t_ns, uint64_t sequence) {
  Frame frame;
  frame.timestamp_ns = t_ns;
  frame.sequence = sequence;
  return frame;
}

TEST(FrameSetAssembler, NearestTimestampWithJitterAndALostFrame) {
  SyncOptions options;
  options.mode = SyncMode::kSoftwareTrigger;
  options.fps = 30;
  FrameSetAssembler assembler({"a", "b", "c"},
                              {"CLOCK_REALTIME", "CLOCK_REALTIME", "CLOCK_REALTIME"}, options);
  std::mt19937 rng(3);
  std::normal_distribution<double> jitter(0, 300e3);  // 0.3 ms
  const int64_t period = 33333333;
  const int64_t latency[3] = {0, 2000000, -1000000};  // constant per-sensor delays
  std::vector<FrameSet> sets;
  for (int k = 0; k < 100; ++k) {
    for (int s = 0; s < 3; ++s) {
      if (s == 1 && k == 40) continue;  // sensor b loses frame 40
      assembler.Add(s, MakeFrame(k * period + latency[s] + static_cast<int64_t>(jitter(rng)), k));
    }
    for (auto& set : assembler.Pop()) sets.push_back(std::move(set));
  }
  for (auto& set : assembler.Flush()) sets.push_back(std::move(set));
  EXPECT_EQ(sets.size(), 99u);
  EXPECT_EQ(assembler.stats().sets_complete, 99);
  EXPECT_EQ(assembler.stats().sets_incomplete, 1);
  EXPECT_EQ(assembler.stats().frames_unmatched, 2);
  EXPECT_EQ(assembler.stats().unmatched_per_sensor[1], 0);
  for (size_t i = 1; i < sets.size(); ++i) EXPECT_EQ(sets[i].index, sets[i - 1].index + 1);
  for (const auto& set : sets) {
    ASSERT_EQ(set.frames.size(), 3u);
    EXPECT_EQ(set.frames[0].sequence, set.frames[1].sequence);
    EXPECT_EQ(set.frames[0].sequence, set.frames[2].sequence);
  }
  // Same clock: the offsets are measured (the sensors' latencies) but not removed.
  EXPECT_NEAR(assembler.stats().offset_ns[1], 2e6, 3e5);
  EXPECT_NEAR(assembler.stats().offset_ns[2], -1e6, 3e5);
  EXPECT_NEAR(assembler.stats().spread_mean_ns, 3e6, 5e5);
}

TEST(FrameSetAssembler, DifferentClocksAreAlignedAndSpreadIsMeasuredInTheFirst) {
  SyncOptions options;
  options.mode = SyncMode::kFreeRun;
  options.fps = 25;
  FrameSetAssembler assembler({"a", "b"}, {"device:a", "device:b"}, options);
  const int64_t period = 40000000;
  const int64_t offset_b = 123456789012;  // b's clock started elsewhere
  std::vector<FrameSet> sets;
  for (int k = 0; k < 50; ++k) {
    assembler.Add(0, MakeFrame(k * period, k));
    // b drifts by 10 us per frame (250 ppm) and runs 0.5 ms behind.
    assembler.Add(1, MakeFrame(offset_b + k * period + 500000 + k * 10000, 1000 + k));
    for (auto& set : assembler.Pop()) sets.push_back(std::move(set));
  }
  for (auto& set : assembler.Flush()) sets.push_back(std::move(set));
  ASSERT_EQ(sets.size(), 50u);
  // Timestamps come out in a's clock, within the drift the running estimate lags by.
  for (const auto& set : sets)
    EXPECT_LT(std::abs(set.frames[1].timestamp_ns - set.frames[0].timestamp_ns), 200000);
  EXPECT_NEAR(static_cast<double>(assembler.stats().offset_ns[1] - offset_b), 500000 + 49 * 10000,
              150000);
}

TEST(FrameSetAssembler, HardwareTriggerGroupsByTriggerIndexAndCountsGaps) {
  SyncOptions options;
  options.mode = SyncMode::kHardwareTrigger;
  options.fps = 30;
  FrameSetAssembler assembler({"a", "b"}, {"PTP", "PTP"}, options);
  std::vector<FrameSet> sets;
  for (uint64_t k = 0; k < 20; ++k) {
    assembler.Add(0, MakeFrame(static_cast<int64_t>(k) * 33333333, 500 + k));
    if (k != 7 && k != 8)
      assembler.Add(1, MakeFrame(static_cast<int64_t>(k) * 33333333 + 2000, 9000 + k));
    for (auto& set : assembler.Pop()) sets.push_back(std::move(set));
  }
  for (auto& set : assembler.Flush()) sets.push_back(std::move(set));
  EXPECT_EQ(sets.size(), 18u);
  EXPECT_EQ(assembler.stats().sets_incomplete, 2);
  EXPECT_EQ(assembler.stats().spread_max_ns, 2000);
  for (const auto& set : sets)
    EXPECT_EQ(set.frames[0].sequence - 500, set.frames[1].sequence - 9000);
}

// Software trigger, one clock: sensor c's capture falls behind and delivers its frames of
// triggers 10..13 only after a and b delivered trigger 13, more than the 3-period latency on in
// stream time. Trigger 10's set is given up without c; c's late frame of trigger 10 is counted
// against c and must not open a second, one-frame set for the same trigger: 30 triggers are 30
// sets, complete or not.
TEST(FrameSetAssembler, FrameArrivingAfterItsSetWasGivenUpOpensNoSecondSet) {
  SyncOptions options;
  options.mode = SyncMode::kSoftwareTrigger;
  options.fps = 30;
  options.tolerance_ns = 16'666'666;
  FrameSetAssembler assembler({"a", "b", "c"},
                              {"CLOCK_REALTIME", "CLOCK_REALTIME", "CLOCK_REALTIME"}, options);
  const int64_t period = 33'333'333;
  const int64_t delay[3] = {0, 4'000'000, 9'000'000};  // each camera's answer to a trigger
  auto stamp = [&](int k, int s) { return 1'000'000'000 + k * period + delay[s]; };
  std::vector<FrameSet> sets;
  auto pop = [&] {
    for (auto& set : assembler.Pop()) sets.push_back(std::move(set));
  };
  for (int k = 0; k < 30; ++k) {
    assembler.Add(0, MakeFrame(stamp(k, 0), k));
    assembler.Add(1, MakeFrame(stamp(k, 1), k));
    if (k < 10 || k > 13) assembler.Add(2, MakeFrame(stamp(k, 2), k));
    if (k == 13) {
      // Trigger 10's set was given up when b delivered trigger 13; trigger 11's still waits.
      EXPECT_EQ(assembler.stats().sets_incomplete, 1);
      for (int late = 10; late <= 13; ++late) assembler.Add(2, MakeFrame(stamp(late, 2), late));
    }
    pop();
  }
  for (auto& set : assembler.Flush()) sets.push_back(std::move(set));
  const SyncStats& stats = assembler.stats();
  EXPECT_EQ(stats.sets_complete, 29);
  EXPECT_EQ(stats.sets_incomplete, 1);
  EXPECT_EQ(stats.sets_complete + stats.sets_incomplete, 30);
  EXPECT_EQ(stats.unmatched_per_sensor, (std::vector<int64_t>{1, 1, 1}));
  EXPECT_EQ(stats.frames_unmatched, 3);
  ASSERT_EQ(sets.size(), 29u);
  for (const auto& set : sets) {
    ASSERT_EQ(set.frames.size(), 3u);
    EXPECT_NE(set.frames[0].sequence, 10u);
    EXPECT_EQ(set.frames[0].sequence, set.frames[2].sequence);
    EXPECT_EQ(set.frames[1].sequence, set.frames[2].sequence);
  }
}

// The default tolerance (0.4 of the period) with one camera answering trigger 5 15 ms late: its
// frame is too far to join the set, yet nearer to trigger 5 than to trigger 6. Trigger 5 is one
// incomplete set, whichever of the two sensors' frames arrives first.
TEST(FrameSetAssembler, FrameBeyondTheToleranceLeavesOneIncompleteSetForItsInstant) {
  for (const bool late_first : {false, true}) {
    SyncOptions options;
    options.mode = SyncMode::kSoftwareTrigger;
    options.fps = 30;
    FrameSetAssembler assembler({"a", "b"}, {"CLOCK_REALTIME", "CLOCK_REALTIME"}, options);
    const int64_t period = 33'333'333;
    std::vector<FrameSet> sets;
    for (int k = 0; k < 12; ++k) {
      const int64_t t = 2'000'000'000 + k * period;
      const int64_t t_b = t + (k == 5 ? 15'000'000 : 1'000'000);
      if (late_first) {
        assembler.Add(1, MakeFrame(t_b, k));
        assembler.Add(0, MakeFrame(t, k));
      } else {
        assembler.Add(0, MakeFrame(t, k));
        assembler.Add(1, MakeFrame(t_b, k));
      }
      for (auto& set : assembler.Pop()) sets.push_back(std::move(set));
    }
    for (auto& set : assembler.Flush()) sets.push_back(std::move(set));
    const SyncStats& stats = assembler.stats();
    EXPECT_EQ(stats.sets_complete, 11) << late_first;
    EXPECT_EQ(stats.sets_incomplete, 1) << late_first;
    EXPECT_EQ(stats.unmatched_per_sensor, (std::vector<int64_t>{1, 1})) << late_first;
    EXPECT_LE(stats.spread_max_ns, 1'000'000) << late_first;
    ASSERT_EQ(sets.size(), 11u);
    for (const auto& set : sets) EXPECT_EQ(set.frames[0].sequence, set.frames[1].sequence);
  }
}

TEST(SyncOptions, BadValuesAreExplained) {
  SyncOptions options;
  options.fps = 0;
  EXPECT_THROW(options.Check(), Error);
  options.fps = 30;
  options.tolerance_ns = 20000000;  // more than half of 33 ms
  try {
    options.Check();
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("half"), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace holocap
