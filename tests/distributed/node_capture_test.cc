// Capture on several hosts, on loopback: capture-node processes on 127.0.0.2 and 127.0.0.3 in
// the test's private network namespace, 4 fake GigE cameras each, the coordinator run through
// the CLI. Every process is stopped by its pid, also when an assertion fails.
#include <gtest/gtest.h>

#include <fstream>
#include <sstream>
#include <thread>

#include "core/take.h"
#include "tests/capture/fake_gige.h"
#include "tests/distributed/node_process.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::FakeGigeCameras;
using testing::NodeProcess;
using testing::TempDir;

// Eight cameras (HC1..HC8 on 127.0.0.1..8) and two nodes; cameras 0-3 on nodeA, 4-7 on nodeB.
struct TwoHostRig {
  TwoHostRig() : cameras(8, 0, 100) {}
  FakeGigeCameras cameras;
  NodeProcess node_a{testing::CliPath(), "nodeA", "tcp://127.0.0.2:5601"};
  NodeProcess node_b{testing::CliPath(), "nodeB", "tcp://127.0.0.3:5601"};

  // The rig file; `extra` adds lines to its hosts.
  std::filesystem::path Write(const std::filesystem::path& dir, const std::string& extra = "") {
    std::ofstream out(dir / "rig.yaml");
    out << "name: two-hosts\nsync: software\nfps: 30\nhosts:\n"
        << "  nodeA: tcp://127.0.0.2:5601\n  nodeB: tcp://127.0.0.3:5601\n"
        << extra << "sensors:\n";
    for (int i = 0; i < 8; ++i) {
      out << "  - {name: cam" << i << ", uri: \"aravis:" << cameras.id(i)
          << "\", host: " << (i < 4 ? "nodeA" : "nodeB")
          << ", options: {roi: [0, 0, 128, 128], pixel_format: Mono8}}\n";
    }
    return dir / "rig.yaml";
  }
};

#define HOLOCAP_SKIP_WITHOUT_FAKE_CAMERAS()              \
  HOLOCAP_SKIP_WITHOUT_NETWORK_PRIVILEGE();              \
  if (!std::filesystem::exists(FakeGigeCameraProgram())) \
  GTEST_SKIP() << "the fake camera program " << FakeGigeCameraProgram() << " is not built"

nlohmann::json ReadReport(const std::filesystem::path& file) {
  std::ifstream in(file);
  return nlohmann::json::parse(in);
}

// A capture that ended in failure: non-zero exit, exactly one `holocap: error:` line (after the
// per-node lines on stdout), holding `needle`.
void ExpectErrorLine(const testing::CommandResult& result, const std::string& needle) {
  EXPECT_NE(result.exit_code, 0) << result.output;
  std::istringstream lines(result.output);
  int errors = 0;
  for (std::string line; std::getline(lines, line);) {
    if (line.rfind("holocap: error: ", 0) != 0) continue;
    ++errors;
    EXPECT_NE(line.find(needle), std::string::npos) << "expected '" << needle << "' in: " << line;
  }
  EXPECT_EQ(errors, 1) << result.output;
}

int64_t IndexLines(const std::filesystem::path& part) {
  std::ifstream in(part / "index.jsonl");
  int64_t lines = 0;
  for (std::string line; std::getline(in, line);) ++lines;
  return lines;
}

// The takes below allow a camera 30 silent periods (1 s) before it counts as lost: a stall of
// this shared host then costs counted frames instead of ending a node's take, and the tests
// judge the nodes, not the host's load.
TEST(NodeCapture, TwoNodesRecordOneMergedTake) {
  HOLOCAP_SKIP_WITHOUT_FAKE_CAMERAS();
  TempDir dir("holocap-nodes");
  TwoHostRig rig;
  const auto rig_file = rig.Write(dir.path());
  const auto take = dir / "take";
  const auto result = testing::RunCli("capture --rig " + rig_file.string() + " --out " +
                                      take.string() + " --frames 90 --lost-after-periods 30");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  const nlohmann::json report = ReadReport(take / "report.json");
  EXPECT_EQ(report["summary"]["termination"], "SUCCESS") << report["summary"];
  const nlohmann::json merge = report["metrics"]["merge"];
  // Every slot of the take's span is a complete set or counted.
  EXPECT_EQ(merge["sets_complete"].get<int64_t>() + merge["sets_incomplete"].get<int64_t>(),
            merge["slots"].get<int64_t>());
  EXPECT_GE(merge["sets_complete"].get<int64_t>(), 80) << result.output;
  EXPECT_LE(merge["slots"].get<int64_t>(), 92) << "the nodes did not start on the same trigger";
  // Both nodes' clocks were measured and said where the offset came from.
  for (const auto& node : report["metrics"]["nodes"]) {
    EXPECT_EQ(node["state"], "recorded") << node;
    EXPECT_EQ(node["clock"]["offset_source"], "control-channel") << node;
    EXPECT_LT(std::abs(node["clock"]["offset_ns"].get<int64_t>()), 1'000'000) << node;
    EXPECT_FALSE(node["clock"]["daemon"]["source"].get<std::string>().empty());
  }
  Take merged = Take::Open(take);
  EXPECT_NO_THROW(merged.Verify());
  EXPECT_EQ(static_cast<int64_t>(merged.size()), merge["sets_complete"].get<int64_t>());
  EXPECT_EQ(merged.streams().size(), 8u);
  for (size_t i = 0; i < merged.size(); ++i) {
    ASSERT_EQ(merged.entry(i).items.size(), 8u);
    EXPECT_LT(merged.entry(i).spread_ns, 13'333'334) << "set " << i;
  }
  const auto verify = testing::RunCli("info --verify " + take.string());
  EXPECT_EQ(verify.exit_code, 0) << verify.output;
  // The parts stay as the nodes recorded them.
  EXPECT_EQ(Take::Open(dir / "take.parts" / "nodeA").state(), "complete");
  EXPECT_EQ(Take::Open(dir / "take.parts" / "nodeB").streams().size(), 4u);
}

TEST(NodeCapture, NodeKilledMidTakeIsNamedAndCompleteSetsAreKept) {
  HOLOCAP_SKIP_WITHOUT_FAKE_CAMERAS();
  TempDir dir("holocap-nodes");
  TwoHostRig rig;
  const auto rig_file = rig.Write(dir.path());
  const auto take = dir / "take";
  testing::CommandResult result;
  std::thread coordinator([&] {
    result = testing::RunCli("capture --rig " + rig_file.string() + " --out " + take.string() +
                             " --frames 150 --lost-after-periods 30");
  });
  // Kill nodeB once its part holds 30 sets (its index is appended set by set).
  const auto part_b = dir / "take.parts" / "nodeB";
  int64_t seen = 0;
  for (int polls = 0; polls < 3000 && seen < 30; ++polls) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
    seen = IndexLines(part_b);
  }
  rig.node_b.Stop(SIGKILL);
  coordinator.join();
  ASSERT_GE(seen, 30) << result.output;
  EXPECT_NE(result.exit_code, 0);
  ExpectErrorLine(result, "node 'nodeB'");
  const nlohmann::json report = ReadReport(take / "report.json");
  EXPECT_EQ(report["summary"]["termination"], "FAILURE");
  for (const auto& node : report["metrics"]["nodes"])
    EXPECT_EQ(node["state"], node["name"] == "nodeB" ? "lost" : "recorded") << node;
  // nodeA recorded its whole take; nodeB's part holds what it wrote before the kill.
  Take part_a = Take::Open(dir / "take.parts" / "nodeA");
  Take part_b_take = Take::Open(part_b);
  EXPECT_GE(part_a.size(), 140u);
  EXPECT_EQ(part_b_take.state(), "recording");
  EXPECT_GE(part_b_take.size(), 30u);
  // The merged take: the complete sets before the kill, each with all eight frames.
  Take merged = Take::Open(take);
  EXPECT_NO_THROW(merged.Verify());
  EXPECT_LE(merged.size(), part_b_take.size());
  EXPECT_GE(merged.size() + 5, part_b_take.size());
  for (size_t i = 0; i < merged.size(); ++i) ASSERT_EQ(merged.entry(i).items.size(), 8u);
  const nlohmann::json merge = report["metrics"]["merge"];
  EXPECT_EQ(merge["sets_complete"].get<int64_t>() + merge["sets_incomplete"].get<int64_t>(),
            merge["slots"].get<int64_t>());
  EXPECT_GE(merge["parts"][1]["missed"].get<int64_t>(), 100);  // nodeB's sets after the kill
}

TEST(NodeCapture, SilentNodeAndClockBoundAreNamed) {
  HOLOCAP_SKIP_WITHOUT_FAKE_CAMERAS();
  TempDir dir("holocap-nodes");
  TwoHostRig rig;
  // nodeC is in the rig and owns a sensor, but nothing listens at its address.
  std::filesystem::path rig_file = rig.Write(dir.path(), "  nodeC: tcp://127.0.0.4:5609\n");
  {
    std::ofstream out(rig_file, std::ios::app);
    out << "  - {name: camX, uri: \"aravis:" << rig.cameras.id(7) << "\", host: nodeC}\n";
  }
  const auto take = dir / "take";
  const auto result = testing::RunCli("capture --rig " + rig_file.string() + " --out " +
                                      take.string() + " --frames 20 --node-timeout 1.5");
  EXPECT_NE(result.exit_code, 0);
  ExpectErrorLine(result, "node 'nodeC' (tcp://127.0.0.4:5609) unreachable");
  // The nodes that answered recorded, and their sets are merged.
  Take merged = Take::Open(take);
  EXPECT_NO_THROW(merged.Verify());
  EXPECT_EQ(merged.streams().size(), 8u);
  EXPECT_GE(merged.size(), 15u);

  // A bound no measured clock can meet (its round trip alone exceeds it): both named.
  const auto clock =
      testing::RunCli("capture --rig " + rig.Write(dir.path()).string() + " --out " +
                      (dir / "take2").string() + " --frames 20 --max-clock-offset-us 0");
  EXPECT_NE(clock.exit_code, 0);
  ExpectErrorLine(clock, "node 'nodeA'");
  EXPECT_NE(clock.output.find("node 'nodeB' (tcp://127.0.0.3:5601) clock: clock offset"),
            std::string::npos)
      << clock.output;
  EXPECT_FALSE(std::filesystem::exists(dir / "take2" / "take.json"));
}

}  // namespace
}  // namespace holocap
