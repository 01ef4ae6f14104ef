// Merging node parts: parts written here with known clock offsets and known missing sets.
#include "distributed/merge.h"

#include <gtest/gtest.h>

#include <fstream>
#include <optional>
#include <set>
#include <sstream>

#include "core/error.h"
#include "core/rig.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::TempDir;

constexpr double kFps = 30;
constexpr int64_t kPeriodNs = 33333333;
constexpr int64_t kStartNs = 1'700'000'000'000'000'000;

std::string ReadAll(const std::filesystem::path& file) {
  std::ifstream in(file);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

// A part of node `node` with sensors `sensors`: one set per slot in [0, slots) except `missing`,
// stamped in a clock `offset_ns` ahead of the common one (and recorded as such), each frame's
// pixels holding its slot number so that the merged sets can be checked.
void WritePart(const std::filesystem::path& dir, const std::string& node,
               const std::vector<std::string>& sensors, int slots, const std::set<int>& missing,
               int64_t offset_ns, int64_t jitter_ns = 0,
               std::optional<int64_t> recorded_offset_ns = std::nullopt) {
  RigDescription rig;
  rig.name = "two-hosts";
  rig.fps = kFps;
  std::vector<StreamInfo> streams;
  for (const auto& name : sensors) {
    SensorSpec spec;
    spec.name = name;
    spec.uri = "aravis:" + name;
    spec.host = node;
    rig.sensors.push_back(spec);
    StreamInfo stream;
    stream.name = name;
    stream.uri = spec.uri;
    stream.width = 8;
    stream.height = 4;
    stream.pixel_format = "mono8";
    stream.clock = "CLOCK_REALTIME";
    streams.push_back(stream);
  }
  rig.hosts = {{node, "tcp://127.0.0.1:5601"}};
  nlohmann::json metadata = {
      {"node",
       {{"name", node},
        {"clock",
         {{"offset_ns", recorded_offset_ns.value_or(offset_ns)}, {"offset_source", "test"}}}}}};
  TakeWriter writer(dir, rig, streams, metadata);
  int64_t index = 0;
  for (int slot = 0; slot < slots; ++slot) {
    if (missing.count(slot)) continue;
    FrameSet set;
    set.index = index++;
    for (size_t s = 0; s < sensors.size(); ++s) {
      Frame frame;
      frame.sensor = sensors[s];
      frame.image = cv::Mat(4, 8, CV_8UC1, cv::Scalar(slot));
      frame.timestamp_ns = kStartNs + slot * kPeriodNs + offset_ns +
                           static_cast<int64_t>(s) * jitter_ns * ((slot % 3) - 1);
      frame.sequence = static_cast<uint64_t>(100 + slot);
      set.frames.push_back(frame);
    }
    writer.Append(set);
  }
  writer.Close();
}

TEST(Merge, SetsFormedAfterClockOffsetsAndMissedSetsCounted) {
  TempDir dir("holocap-merge");
  // Node B's clock runs 20 ms ahead: more than half a period, so only the recorded offset puts
  // its sets in the right slots. B missed slots 5 and 6, A missed slot 17.
  WritePart(dir / "A", "nodeA", {"cam0", "cam1"}, 40, {17}, -1'500'000, 200'000);
  WritePart(dir / "B", "nodeB", {"cam2", "cam3"}, 40, {5, 6}, 20'000'000, 300'000);
  const std::string index_a = ReadAll(dir / "A" / "index.jsonl");
  const std::string manifest_b = ReadAll(dir / "B" / "take.json");

  MergeSummary summary = MergeParts({dir / "A", dir / "B"}, dir / "merged", {});
  ASSERT_EQ(summary.termination, Termination::kSuccess) << summary.message;
  EXPECT_EQ(summary.match, "timestamp");
  EXPECT_EQ(summary.slots, 40);
  EXPECT_EQ(summary.sets_complete, 37);
  EXPECT_EQ(summary.sets_incomplete, 3);
  ASSERT_EQ(summary.parts.size(), 2u);
  EXPECT_EQ(summary.parts[0].missed, 1);
  EXPECT_EQ(summary.parts[0].discarded, 2);
  EXPECT_EQ(summary.parts[1].missed, 2);
  EXPECT_EQ(summary.parts[1].discarded, 1);
  EXPECT_LT(summary.spread_us_max, 1000);  // the 21.5 ms between the clocks removed

  Take merged = Take::Open(dir / "merged");
  EXPECT_NO_THROW(merged.Verify());
  ASSERT_EQ(merged.size(), 37u);
  EXPECT_EQ(merged.streams().size(), 4u);
  EXPECT_EQ(merged.dropped().at("cam2"), 2);
  EXPECT_EQ(merged.dropped().at("cam0"), 1);
  // Every merged set holds the four frames of one slot, never frames of two.
  std::set<int> slots;
  for (size_t i = 0; i < merged.size(); ++i) {
    FrameSet set = merged.Read(i);
    ASSERT_EQ(set.frames.size(), 4u);
    const int slot = set.frames[0].image.at<uint8_t>(0, 0);
    for (const Frame& frame : set.frames) EXPECT_EQ(frame.image.at<uint8_t>(0, 0), slot);
    slots.insert(slot);
  }
  EXPECT_EQ(slots.size(), 37u);
  EXPECT_FALSE(slots.count(5) || slots.count(6) || slots.count(17));
  // The parts are recordings: untouched.
  EXPECT_EQ(ReadAll(dir / "A" / "index.jsonl"), index_a);
  EXPECT_EQ(ReadAll(dir / "B" / "take.json"), manifest_b);
}

// How many merged sets hold frames of one slot only.
int ConsistentSets(const Take& take) {
  int consistent = 0;
  for (size_t i = 0; i < take.size(); ++i) {
    FrameSet set = take.Read(i);
    bool same = true;
    for (const Frame& frame : set.frames)
      same &= frame.image.at<uint8_t>(0, 0) == set.frames[0].image.at<uint8_t>(0, 0);
    consistent += same;
  }
  return consistent;
}

TEST(Merge, TheRecordedClockOffsetIsWhatJoinsTheRightFrames) {
  TempDir dir("holocap-merge");
  WritePart(dir / "A", "nodeA", {"cam0"}, 20, {}, 0);
  WritePart(dir / "B", "nodeB", {"cam1"}, 20, {}, 24'000'000);
  WritePart(dir / "B-unknown", "nodeB", {"cam1"}, 20, {}, 24'000'000, 0, 0);
  MergeSummary corrected = MergeParts({dir / "A", dir / "B"}, dir / "merged", {});
  EXPECT_EQ(corrected.sets_complete, 20);
  EXPECT_EQ(ConsistentSets(Take::Open(dir / "merged")), 20);
  // The same timestamps with no offset recorded: a 24 ms clock error joins each frame to the
  // next instant's, which is why every node's clock state is recorded.
  MergeSummary uncorrected = MergeParts({dir / "A", dir / "B-unknown"}, dir / "merged2", {});
  EXPECT_EQ(uncorrected.sets_complete, 19);
  EXPECT_EQ(ConsistentSets(Take::Open(dir / "merged2")), 0);
  // Frame counters (shared triggers): aligned once by time, then matched by counter.
  MergeOptions by_counter;
  by_counter.match = "sequence";
  MergeSummary sequence = MergeParts({dir / "A", dir / "B"}, dir / "merged3", by_counter);
  EXPECT_EQ(sequence.match, "sequence");
  EXPECT_EQ(sequence.sets_complete, 20);
  EXPECT_EQ(ConsistentSets(Take::Open(dir / "merged3")), 20);
}

TEST(Merge, BadInputIsOneClearError) {
  TempDir dir("holocap-merge");
  WritePart(dir / "A", "nodeA", {"cam0"}, 5, {}, 0);
  WritePart(dir / "B", "nodeB", {"cam0"}, 5, {}, 0);
  try {
    MergeParts({dir / "A", dir / "B"}, dir / "merged", {});
    FAIL() << "merged two parts holding the same sensor";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("sensor 'cam0' is in two parts"), std::string::npos)
        << e.what();
  }
  EXPECT_FALSE(std::filesystem::exists(dir / "merged"));
  // The output may not lie inside a part.
  WritePart(dir / "C", "nodeC", {"cam1"}, 5, {}, 0);
  EXPECT_THROW(MergeParts({dir / "A", dir / "C"}, dir / "A" / "frames" / "merged", {}), Error);
  const auto cli =
      testing::RunCli("merge " + (dir / "A").string() + " " + (dir / "nothing").string() +
                      " --out " + (dir / "merged").string());
  testing::ExpectOneLineError(cli, "nothing");
}

TEST(Merge, RigHostsAreChecked) {
  const std::string rig = R"(
name: two
hosts: {nodeA: "tcp://127.0.0.2:5601"}
sensors:
  - {name: cam0, uri: "aravis:x", host: nodeA}
  - {name: cam1, uri: "aravis:y", host: nodeB}
)";
  try {
    RigDescription::ParseYaml(rig, "rig.yaml");
    FAIL() << "accepted a sensor on an unknown host";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("host 'nodeB' is not in the rig's hosts (nodeA)"),
              std::string::npos)
        << e.what();
  }
  RigDescription parsed = RigDescription::ParseYaml(
      R"(
hosts: {nodeA: "tcp://127.0.0.2:5601", nodeB: "tcp://127.0.0.3:5601"}
sensors:
  - {name: cam0, uri: "aravis:x", host: nodeA}
  - {name: cam1, uri: "aravis:y", host: nodeB}
)",
      "rig.yaml");
  EXPECT_EQ(parsed.hosts.at("nodeB"), "tcp://127.0.0.3:5601");
  EXPECT_EQ(RigDescription::FromJson(parsed.ToJson()).sensors[1].host, "nodeB");
  EXPECT_THROW(RigDescription::ParseYaml(R"(
hosts: {nodeA: "tcp://127.0.0.2:5601"}
sensors:
  - {name: cam0, uri: "aravis:x"}
)",
                                         "rig.yaml"),
               Error);
}

}  // namespace
}  // namespace holocap
