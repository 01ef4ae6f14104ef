// Per-frame tasks: shards that split a run deterministically, records that make a frame
// complete only with the bytes they name, and reconstruct runs split into shards, re-run after
// losses and killed mid-frame, each ending with the same bytes as one process's run.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <fstream>
#include <thread>

#include "core/error.h"
#include "core/frame_tasks.h"
#include "core/fs.h"
#include "tests/distributed/shard_compare.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::ExpectOneLineError;
using testing::ExpectSameRun;
using testing::ReadJson;
using testing::RecordTimes;
using testing::RunCli;
using testing::TempDir;
namespace fs = std::filesystem;

TEST(Shard, BlocksCoverEverySetOnceInOrderAndDifferByOneAtMost) {
  for (int n = 0; n <= 23; ++n) {
    std::vector<int64_t> sets(n);
    for (int i = 0; i < n; ++i) sets[i] = 3 + 2 * i;
    for (int count = 1; count <= 7; ++count) {
      std::vector<int64_t> joined;
      size_t smallest = n, largest = 0;
      for (int k = 0; k < count; ++k) {
        const Shard shard{k, count};
        const std::vector<int64_t> part = shard.Of(sets);
        EXPECT_EQ(part, shard.Of(sets)) << "the same K/N names the same sets";
        joined.insert(joined.end(), part.begin(), part.end());
        smallest = std::min(smallest, part.size());
        largest = std::max(largest, part.size());
      }
      EXPECT_EQ(joined, sets) << n << " sets in " << count << " shards";
      EXPECT_LE(largest - smallest, 1u) << n << " sets in " << count << " shards";
    }
  }
}

TEST(Shard, ParsesKOfNAndRefusesAnythingElse) {
  const Shard shard = Shard::Parse("2/8");
  EXPECT_EQ(shard.index, 2);
  EXPECT_EQ(shard.count, 8);
  EXPECT_EQ(shard.ToString(), "2/8");
  EXPECT_TRUE(Shard::Parse("0/1").whole());
  for (const char* bad : {"3/3", "-1/2", "a/b", "2", "1/0", "1/", "/2", "1/2/3", " 1/2"})
    EXPECT_THROW(Shard::Parse(bad), Error) << bad;
}

class Records : public ::testing::Test {
 protected:
  void SetUp() override {
    CreateDirectories(dir_.path());
    WriteFileAtomic(dir_ / "000007.ply", "seven meshes", true);
    records_.WriteRun({{"options", {{"voxel_m", 0.004}}}});
  }
  std::string Why(const FrameRecords& records, int64_t set) const {
    std::string why;
    EXPECT_FALSE(records.Complete(set, &why).has_value());
    return why;
  }
  TempDir dir_{"holocap-records"};
  FrameRecords records_{dir_.path(), "reconstruct", {{"voxel_m", 0.004}}, {7, 8}};
};

TEST_F(Records, AFrameIsCompleteOnlyWithTheBytesItsRecordNames) {
  EXPECT_EQ(Why(records_, 7), "no record");  // outputs written, the task killed before recording
  records_.Record(7, {{"vertices", 12}}, {"000007.ply"}, UnixSeconds(), "test");
  const auto record = records_.Complete(7);
  ASSERT_TRUE(record.has_value());
  EXPECT_EQ((*record)["result"]["vertices"], 12);
  EXPECT_EQ((*record)["outputs"][0]["bytes"], 12);

  WriteFileAtomic(dir_ / "000007.ply", "seven meshe");  // cut short
  EXPECT_EQ(Why(records_, 7), "output '000007.ply' has another size than recorded");
  WriteFileAtomic(dir_ / "000007.ply", "seven meshex");  // same size, one byte changed
  EXPECT_EQ(Why(records_, 7), "output '000007.ply' has another hash than recorded");
  fs::remove(dir_ / "000007.ply");
  EXPECT_EQ(Why(records_, 7), "output '000007.ply' is missing");

  WriteFileAtomic(dir_ / "000007.ply", "seven meshes");
  EXPECT_TRUE(records_.Complete(7).has_value());
  const FrameRecords other(dir_.path(), "reconstruct", {{"voxel_m", 0.008}}, {7, 8});
  EXPECT_NE(other.fingerprint(), records_.fingerprint());
  EXPECT_EQ(Why(other, 7), "its record is another run's");
  WriteFileAtomic(FrameRecordPath(dir_.path(), 8), "{\"fingerprint\": ");  // torn by hand
  EXPECT_EQ(Why(records_, 8), "its record is not a frame record");

  const RunState run = ReadRunState(dir_.path());
  EXPECT_EQ(run.fingerprint, records_.fingerprint());
  EXPECT_EQ(run.sets, (std::vector<int64_t>{7, 8}));
  EXPECT_EQ(run.complete.size(), 1u);
  EXPECT_EQ(run.incomplete.at(8), "its record is not a frame record");
  EXPECT_FALSE(run.done());
  EXPECT_EQ(run.Describe(),
            "1 of 2 frame sets complete; incomplete: 8 (its record is not a frame record)");
}

// The plan made by one of two tasks that ask for it at once (the other waits for the lock and
// reads it), remade when the run differs or a file it lists changed.
TEST(PlanOnce, OneTaskMakesThePlanAndTheOthersReadAndVerifyIt) {
  TempDir dir("holocap-plan-once");
  std::atomic<int> made{0};
  auto make = [&](std::vector<std::string>* files) {
    ++made;
    // Long enough for the other task to find no plan and wait for the lock.
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    files->push_back("model.bin");
    WriteFileAtomic(dir.path() / kPlanDir / "model.bin", "0123456789");
    return nlohmann::json{{"bounds", {1.0 / 3, 2.0}}};
  };
  StoredPlan a, b;
  std::thread other([&] { b = PlanOnce(dir.path(), "reconstruct", "f1", "task b", make); });
  a = PlanOnce(dir.path(), "reconstruct", "f1", "task a", make);
  other.join();
  EXPECT_EQ(made.load(), 1);
  EXPECT_NE(a.made, b.made);
  EXPECT_EQ(a.plan, b.plan);
  EXPECT_EQ(a.plan["bounds"][0].get<double>(), 1.0 / 3);  // doubles come back exactly
  EXPECT_EQ(a.made_by, a.made ? "task a" : "task b");
  EXPECT_EQ(b.made_by, a.made_by);
  const auto stored = ReadJson(dir.path() / kPlanDir / "plan.json");
  EXPECT_EQ(stored["made_by"], a.made ? "task a" : "task b");
  EXPECT_EQ(stored["files"][0]["bytes"], 10);

  StoredPlan again = PlanOnce(dir.path(), "reconstruct", "f1", "task c", make);
  EXPECT_FALSE(again.made);
  EXPECT_EQ(made.load(), 1);
  again = PlanOnce(dir.path(), "reconstruct", "f2", "task c", make);
  EXPECT_TRUE(again.made);
  EXPECT_EQ(again.why, "the plan is another run's");
  WriteFileAtomic(dir.path() / kPlanDir / "model.bin", "0123456780");
  again = PlanOnce(dir.path(), "reconstruct", "f2", "task c", make);
  EXPECT_TRUE(again.made);
  EXPECT_EQ(again.why, "the plan's file 'model.bin' has another hash than recorded");
  WriteFileAtomic(dir.path() / kPlanDir / "model.bin", "012");
  again = PlanOnce(dir.path(), "reconstruct", "f2", "task c", make);
  EXPECT_EQ(again.why, "the plan's file 'model.bin' has another size than recorded");
  EXPECT_EQ(made.load(), 4);
}

// One take, reconstructed once by one process; every other run is compared with it.
class ShardedReconstruct : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new TempDir("holocap-shards");
    auto result = RunCli(
        "sim --rig studio8 --frames 6 --clean-plate 1 --size 128 --threads 2 --out " + take());
    ASSERT_EQ(result.exit_code, 0) << result.output;
    result = RunCli("reconstruct " + take() + " --ground-truth-cameras --out " + out("whole"));
    ASSERT_EQ(result.exit_code, 0) << result.output;
  }
  static void TearDownTestSuite() { delete dir_; }
  static std::string take() { return (dir_->path() / "take").string(); }
  static std::string out(const std::string& name) { return (dir_->path() / name).string(); }
  static TempDir* dir_;
};
TempDir* ShardedReconstruct::dir_ = nullptr;

TEST_F(ShardedReconstruct, TwoShardsMergeIntoTheOneProcessRunsBytes) {
  const RunState whole = ReadRunState(out("whole"));
  ASSERT_TRUE(whole.done());
  ASSERT_EQ(whole.sets.size(), 5u);
  EXPECT_EQ(ReadJson(out("whole") + "/report.json")["summary"]["termination"], "SUCCESS");

  auto first = RunCli("reconstruct " + take() + " --ground-truth-cameras --out " + out("split") +
                      " --shard 0/2");
  ASSERT_EQ(first.exit_code, 0) << first.output;
  EXPECT_NE(first.output.find("shard 0/2: 2 of the run's 5 frame set(s)"), std::string::npos)
      << first.output;
  EXPECT_FALSE(fs::exists(out("split") + "/report.json"));
  EXPECT_TRUE(fs::exists(out("split") + "/tasks/shard-0-of-2/report.json"));
  // Merging half a run: FAILURE naming what is missing, in the report and in one error line.
  auto early = RunCli("report " + out("split") + " --merge");
  ExpectOneLineError(early, "2 of 5 frame sets complete; incomplete: 3 (no record)");
  EXPECT_EQ(ReadJson(out("split") + "/report.json")["summary"]["termination"], "FAILURE");

  auto second = RunCli("reconstruct " + take() + " --ground-truth-cameras --out " + out("split") +
                       " --shard 1/2");
  ASSERT_EQ(second.exit_code, 0) << second.output;
  EXPECT_NE(second.output.find("the run is complete"), std::string::npos) << second.output;
  EXPECT_EQ(ExpectSameRun(out("whole"), out("split")), 10u);  // 5 PLY + 5 glTF
  auto merged = RunCli("report " + out("split") + " --merge");
  ASSERT_EQ(merged.exit_code, 0) << merged.output;
  ExpectSameRun(out("whole"), out("split"));
  const nlohmann::json report = ReadJson(out("split") + "/report.json");
  EXPECT_EQ(report["metrics"]["timing"]["frames_by_task"].size(), 2u);
  EXPECT_EQ(report["metrics"]["gt"]["voxel_sweep"].size(), 2u);  // 16 and 8 mm (the plan's)
}

TEST_F(ShardedReconstruct, ARerunRedoesOnlyTheFramesWhoseOutputsAreNotComplete) {
  fs::copy(out("whole"), out("damaged"), fs::copy_options::recursive);
  const std::map<int64_t, double> before = RecordTimes(out("damaged"));
  fs::remove(FrameRecordPath(out("damaged"), 2));
  const std::string glb = out("damaged") + "/000004.glb";
  fs::resize_file(glb, fs::file_size(glb) / 2);
  auto rerun = RunCli("reconstruct " + take() + " --ground-truth-cameras --out " + out("damaged"));
  ASSERT_EQ(rerun.exit_code, 0) << rerun.output;
  EXPECT_NE(rerun.output.find("3 of 5 frame set(s) skipped"), std::string::npos) << rerun.output;
  const std::map<int64_t, double> after = RecordTimes(out("damaged"));
  for (int64_t set : {1, 3, 5}) EXPECT_EQ(after.at(set), before.at(set)) << "set " << set;
  for (int64_t set : {2, 4}) EXPECT_GT(after.at(set), before.at(set)) << "set " << set;
  ExpectSameRun(out("whole"), out("damaged"));
  // Other options make another run: nothing of this one is taken as done.
  auto other = RunCli("reconstruct " + take() + " --ground-truth-cameras --out " + out("damaged") +
                      " --no-glb");
  ASSERT_EQ(other.exit_code, 0) << other.output;
  EXPECT_EQ(other.output.find("skipped"), std::string::npos) << other.output;
}

TEST_F(ShardedReconstruct, ATaskKilledMidFrameLeavesNothingTakenAsComplete) {
  const std::string dir = out("killed");
  const pid_t child = fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    const std::string cli = testing::CliPath();
    execl(cli.c_str(), cli.c_str(), "reconstruct", take().c_str(), "--ground-truth-cameras",
          "--out", dir.c_str(), "--threads", "1", static_cast<char*>(nullptr));
    _exit(127);
  }
  // Kill -9 as soon as the first frame is recorded: the second is being written.
  int polls = 0;
  while (polls++ < 6000 && !fs::exists(FrameRecordPath(dir, 1)))
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  ASSERT_EQ(kill(child, SIGKILL), 0);
  int status = 0;
  waitpid(child, &status, 0);
  ASSERT_TRUE(WIFSIGNALED(status)) << "the run ended before it was killed";
  const RunState killed = ReadRunState(dir);
  ASSERT_GE(killed.complete.size(), 1u);
  ASSERT_FALSE(killed.done());
  const size_t complete = killed.complete.size();
  auto rerun = RunCli("reconstruct " + take() + " --ground-truth-cameras --out " + dir);
  ASSERT_EQ(rerun.exit_code, 0) << rerun.output;
  EXPECT_NE(rerun.output.find(std::to_string(complete) + " of 5 frame set(s) skipped"),
            std::string::npos)
      << rerun.output;
  ExpectSameRun(out("whole"), dir);
}

TEST_F(ShardedReconstruct, TheFirstTaskPlansTheRunAndTheOthersReadItsPlan) {
  const std::string dir = out("planned");
  auto first =
      RunCli("reconstruct " + take() + " --ground-truth-cameras --out " + dir + " --shard 0/2");
  ASSERT_EQ(first.exit_code, 0) << first.output;
  EXPECT_NE(first.output.find("plan: made by this task (no plan yet)"), std::string::npos)
      << first.output;
  ASSERT_TRUE(fs::exists(dir + "/plan/plan.json"));
  const auto plan = ReadJson(dir + "/plan/plan.json");
  EXPECT_NE(plan["plan"]["bounds_source"].get<std::string>().find("coarse hull"),
            std::string::npos);
  auto second =
      RunCli("reconstruct " + take() + " --ground-truth-cameras --out " + dir + " --shard 1/2");
  ASSERT_EQ(second.exit_code, 0) << second.output;
  EXPECT_NE(second.output.find("plan: read from " + dir + "/plan"), std::string::npos)
      << second.output;
  EXPECT_EQ(
      ReadJson(dir + "/tasks/shard-1-of-2/report.json")["metrics"]["plan"].get<std::string>().rfind(
          "read from", 0),
      0u);
  EXPECT_EQ(ExpectSameRun(out("whole"), dir), 10u);
  // A task that finds no plan plans itself, to the same bytes.
  fs::remove_all(dir + "/plan");
  auto alone = RunCli("reconstruct " + take() + " --ground-truth-cameras --out " + dir +
                      " --shard 1/2 --redo");
  ASSERT_EQ(alone.exit_code, 0) << alone.output;
  EXPECT_NE(alone.output.find("plan: made by this task (no plan yet)"), std::string::npos)
      << alone.output;
  ExpectSameRun(out("whole"), dir);
}

TEST_F(ShardedReconstruct, AFrameListIsARunThatShardsSplit) {
  const std::string frames = " --no-sweep --frames 0,2-3";
  auto whole =
      RunCli("reconstruct " + take() + " --ground-truth-cameras --out " + out("listed") + frames);
  ASSERT_EQ(whole.exit_code, 0) << whole.output;
  // After the clean plate (set 0): sets 1, 3 and 4 of the take.
  EXPECT_EQ(ReadRunState(out("listed")).sets, (std::vector<int64_t>{1, 3, 4}));
  for (const char* shard : {"0/2", "1/2"}) {
    auto task = RunCli("reconstruct " + take() + " --ground-truth-cameras --out " +
                       out("listed-split") + frames + " --shard " + shard);
    ASSERT_EQ(task.exit_code, 0) << task.output;
    const std::string part = std::string(shard) == "0/2" ? "1 of" : "2 of";
    EXPECT_NE(
        task.output.find("shard " + std::string(shard) + ": " + part + " the run's 3 frame set(s)"),
        std::string::npos)
        << task.output;
  }
  EXPECT_EQ(ExpectSameRun(out("listed"), out("listed-split")), 6u);
  EXPECT_EQ(ReadRunState(out("listed-split")).complete.begin()->first, 1);

  const std::string bad =
      "reconstruct " + take() + " --ground-truth-cameras --out " + out("bad-list") + " --frames ";
  ExpectOneLineError(RunCli(bad + "3-1"), "--frames: '3-1' is not a range A-B with 0 <= A <= B");
  ExpectOneLineError(RunCli(bad + "0,9"),
                     "--frames lists frame set 9; the take has 5 frame sets after its clean "
                     "plate (0 to 4)");
  ExpectOneLineError(RunCli(bad + "1,,2"), "--frames must be A:B, A:, A or a list");
  ExpectOneLineError(RunCli(bad + "1,2,"), "--frames must be A:B, A:, A or a list");
  ExpectOneLineError(RunCli(bad + "1-x"), "--frames must be A:B, A:, A or a list");
}

TEST_F(ShardedReconstruct, BadShardsAndMergesEndInOneLine) {
  ExpectOneLineError(RunCli("reconstruct " + take() + " --ground-truth-cameras --out " +
                            out("bad") + " --shard 2/2"),
                     "--shard 2/2 violates index < count (2) (K/N needs 0 <= K < N)");
  ExpectOneLineError(RunCli("reconstruct " + take() + " --ground-truth-cameras --out " +
                            out("bad") + " --shard two"),
                     "--shard must be K/N");
  ExpectOneLineError(RunCli("report " + take() + " --merge"), "holds no run.json");
  auto empty = RunCli("reconstruct " + take() + " --ground-truth-cameras --out " + out("wide") +
                      " --shard 0/7 --no-sweep");
  EXPECT_EQ(empty.exit_code, 0) << empty.output;
  EXPECT_NE(empty.output.find("holds none of the 5 frame sets"), std::string::npos) << empty.output;
}

}  // namespace
}  // namespace holocap
