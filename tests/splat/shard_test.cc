// `holocap train splat --segment-frames`: a dynamic take's splats as a per-frame run. Frame 0 is
// the run's plan, trained once; the later frames form segments that shards split; a run split
// into shards, one killed mid-frame, or one whose outputs were damaged, ends with the same bytes
// as one process's run, and a complete frame is skipped; the model plays along its deltas' bases.
#include <gtest/gtest.h>

#include <chrono>
#include <filesystem>
#include <map>

#include "core/fs.h"
#include "splat/splat.h"
#include "tests/distributed/shard_compare.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;
using testing::ExpectOneLineError;
using testing::ExpectSameModel;
using testing::ReadJson;
using testing::RecordTimes;
using testing::RunCli;
using testing::TempDir;

// A short budget in iterations, 2 frames a segment: the take's 5 frames are frame 0 and the
// segments {1, 2} and {3, 4}.
const char* const kBudget =
    " --segment-frames 2 --iterations 30 --frame-iterations 8 --segment-start-iterations 16 "
    "--width 64 --seed-points 1500 --heldout 1";

class ShardedSplats : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new TempDir("holocap-splat-shards");
    auto result = RunCli(
        "sim --rig studio8 --frames 6 --clean-plate 1 --size 128 --no-noise "
        "--seed 2 --threads 2 --out " +
        take());
    ASSERT_EQ(result.exit_code, 0) << result.output;
    // The seeds from one reconstruction (a run without --recon reconstructs its own first).
    result = RunCli("reconstruct " + take() + " --ground-truth-cameras --out " + out("recon") +
                    " --voxel 12mm --no-sweep --no-glb --threads 2");
    ASSERT_EQ(result.exit_code, 0) << result.output;
    result = RunCli(Train("whole", " --threads 2"));
    ASSERT_EQ(result.exit_code, 0) << result.output;
  }
  static void TearDownTestSuite() { delete dir_; }
  static std::string take() { return (dir_->path() / "take").string(); }
  static std::string out(const std::string& name) { return (dir_->path() / name).string(); }
  static std::string Train(const std::string& name, const std::string& extra) {
    return "train splat " + take() + " --ground-truth-cameras --out " + out(name) + " --recon " +
           out("recon") + kBudget + extra;
  }
  static TempDir* dir_;
};
TempDir* ShardedSplats::dir_ = nullptr;

TEST_F(ShardedSplats, SegmentsStartFromFrameZeroAndPlayBack) {
  const SplatModel model = SplatModel::Load(out("whole"));
  EXPECT_EQ(model.frames, 5);
  EXPECT_EQ(model.bases, (std::vector<int64_t>{-1, 0, 1, 0, 3}));
  const nlohmann::json json = ReadJson(out("whole") + "/model.json");
  EXPECT_EQ(json["format_version"], 2);
  const nlohmann::json report = ReadJson(out("whole") + "/report.json");
  EXPECT_EQ(report["summary"]["termination"], "NO_CONVERGENCE");
  ASSERT_EQ(report["metrics"]["frames"].size(), 5u);
  EXPECT_EQ(report["metrics"]["frames"][1]["iterations"], 16);  // a segment's first frame
  EXPECT_EQ(report["metrics"]["frames"][2]["iterations"], 8);
  EXPECT_EQ(report["metrics"]["frames"][3]["base"], 0);
  // Frame 4 played from frame 3 (its base) is frame 4 decoded from frame 0 along its bases.
  const splat::Gaussians three = model.Frame(out("whole"), 3);
  EXPECT_EQ(model.Frame(out("whole"), 4, &three, 3).position,
            model.Frame(out("whole"), 4).position);
  // Frame 2 is not on frame 3's way: asked after it, frame 3 is decoded from frame 0 again.
  const splat::Gaussians two = model.Frame(out("whole"), 2);
  EXPECT_EQ(model.Frame(out("whole"), 3, &two, 2).position, three.position);
  EXPECT_NE(two.position, three.position);

  // The web stream: a delta where the frame before is the delta's base, a key frame where a
  // segment starts again from frame 0; the export decodes each chunk as the player does.
  auto site = RunCli("export web " + take() + " --ground-truth-cameras --model " + out("whole") +
                     " --no-meshes --quality medium --out " + out("site"));
  ASSERT_EQ(site.exit_code, 0) << site.output;
  const nlohmann::json manifest = ReadJson(out("site") + "/manifest.json");
  ASSERT_EQ(manifest["streams"].size(), 1u);
  std::vector<bool> keys;
  for (const auto& chunk : manifest["streams"][0]["chunks"]) keys.push_back(chunk["key"]);
  EXPECT_EQ(keys, (std::vector<bool>{true, false, false, true, false}));
}

TEST_F(ShardedSplats, TwoShardsOnOtherThreadCountsMergeIntoTheOneProcessRunsBytes) {
  auto first = RunCli(Train("split", " --threads 1 --shard 0/2"));
  ASSERT_EQ(first.exit_code, 0) << first.output;
  EXPECT_NE(first.output.find("frame 0 (the run's plan): made by this task"), std::string::npos)
      << first.output;
  EXPECT_FALSE(fs::exists(out("split") + "/model.json"));
  EXPECT_TRUE(fs::exists(out("split") + "/tasks/shard-0-of-2/report.json"));
  // Merging half a run: FAILURE naming what is missing, and no model.
  auto early = RunCli("report " + out("split") + " --merge");
  ExpectOneLineError(early, "2 of 4 frame sets complete");
  EXPECT_EQ(ReadJson(out("split") + "/report.json")["summary"]["termination"], "FAILURE");
  EXPECT_FALSE(fs::exists(out("split") + "/model.json"));

  auto second = RunCli(Train("split", " --threads 2 --shard 1/2"));
  ASSERT_EQ(second.exit_code, 0) << second.output;
  EXPECT_NE(second.output.find("frame 0 (the run's plan): read from"), std::string::npos)
      << second.output;
  EXPECT_NE(second.output.find("the run is complete"), std::string::npos) << second.output;
  ExpectSameModel(out("whole"), out("split"));
  auto merged = RunCli("report " + out("split") + " --merge");
  ASSERT_EQ(merged.exit_code, 0) << merged.output;
  ExpectSameModel(out("whole"), out("split"));
}

TEST_F(ShardedSplats, ARerunSkipsCompleteFramesAndRedoesDamagedOnes) {
  fs::copy(out("whole"), out("damaged"), fs::copy_options::recursive);
  const std::map<int64_t, double> before = RecordTimes(out("damaged"));
  ASSERT_EQ(before.size(), 4u);
  auto again = RunCli(Train("damaged", " --threads 2"));
  ASSERT_EQ(again.exit_code, 0) << again.output;
  EXPECT_EQ(RecordTimes(out("damaged")), before) << "complete frames are skipped";

  const std::vector<int64_t> sets = ReadRunState(out("damaged")).sets;
  fs::remove(FrameRecordPath(out("damaged"), sets[1]));  // frame 2's record
  const std::string delta = out("damaged") + "/deltas/000003.bin";
  fs::resize_file(delta, fs::file_size(delta) / 2);  // frame 3, cut short
  auto rerun = RunCli(Train("damaged", " --threads 2"));
  ASSERT_EQ(rerun.exit_code, 0) << rerun.output;
  const std::map<int64_t, double> after = RecordTimes(out("damaged"));
  for (size_t f : {0u, 3u}) EXPECT_EQ(after.at(sets[f]), before.at(sets[f])) << "frame " << f + 1;
  for (size_t f : {1u, 2u}) EXPECT_GT(after.at(sets[f]), before.at(sets[f])) << "frame " << f + 1;
  ExpectSameModel(out("whole"), out("damaged"));
}

TEST_F(ShardedSplats, AShardKilledMidFrameRedoesOnlyItsUnfinishedFrames) {
  const std::string dir = out("killed");
  auto first = RunCli(Train("killed", " --threads 2 --shard 0/2"));
  ASSERT_EQ(first.exit_code, 0) << first.output;
  const std::vector<int64_t> sets = ReadRunState(dir).sets;
  // Kill -9 as soon as the segment's first frame is recorded: the second is being trained.
  ASSERT_TRUE(testing::KillWhenRecorded(Train("killed", " --threads 1 --shard 1/2"),
                                        FrameRecordPath(dir, sets[2])))
      << "the task ended before it was killed";
  const RunState killed = ReadRunState(dir);
  ASSERT_EQ(killed.complete.size(), 3u) << killed.Describe();
  EXPECT_FALSE(fs::exists(dir + "/model.json"));

  auto rerun = RunCli(Train("killed", " --threads 2 --shard 1/2"));
  ASSERT_EQ(rerun.exit_code, 0) << rerun.output;
  EXPECT_NE(rerun.output.find("trained 1 and skipped 1 frame(s)"), std::string::npos)
      << rerun.output;
  ExpectSameModel(out("whole"), dir);
}

// A model whose training did not finish is refused by render and export web in one line: a
// run with a frame's record gone (as a run killed mid-frame leaves it), a run whose
// report.json says FAILURE, and one a later failed run rewrote after its good report.
// --partial-model uses it, and the reports and output say so.
TEST_F(ShardedSplats, RenderAndExportRefuseAModelWhoseTrainingDidNotFinish) {
  fs::copy(out("whole"), out("partial"), fs::copy_options::recursive);
  const std::vector<int64_t> sets = ReadRunState(out("partial")).sets;
  fs::remove(FrameRecordPath(out("partial"), sets[2]));
  const std::string render =
      "render " + take() + " --model " + out("partial") + " --views 1 --size 32 --no-exr --out ";
  const std::string web = "export web " + take() + " --ground-truth-cameras --model " +
                          out("partial") + " --no-meshes --out ";
  ExpectOneLineError(RunCli(render + out("partial-frames")),
                     "is not a finished training: its report.json says FAILURE: the run is "
                     "incomplete: 3 of 4 frame sets complete");
  ExpectOneLineError(RunCli(web + out("partial-site")), "(--partial-model uses it as it is)");

  fs::copy(out("whole"), out("failed"), fs::copy_options::recursive);
  nlohmann::json report = ReadJson(out("failed") + "/report.json");
  report["summary"]["termination"] = "FAILURE";
  report["summary"]["message"] = "stopped by a signal";
  WriteFileAtomic(out("failed") + "/report.json", report.dump());
  ExpectOneLineError(RunCli("render " + take() + " --model " + out("failed") +
                            " --views 1 --size 32 --no-exr --out " + out("failed-frames")),
                     "its report.json says FAILURE: stopped by a signal");

  // A later run that failed beside the good report (report.failed.json) after rewriting the
  // model: the good report no longer describes it.
  fs::copy(out("whole"), out("rewritten"), fs::copy_options::recursive);
  report = ReadJson(out("rewritten") + "/report.json");
  report["summary"]["termination"] = "FAILURE";
  report["summary"]["message"] = "stopped by a signal";
  WriteFileAtomic(out("rewritten") + "/report.failed.json", report.dump());
  fs::last_write_time(
      out("rewritten") + "/model.json",
      fs::last_write_time(out("rewritten") + "/report.json") + std::chrono::seconds(5));
  ExpectOneLineError(RunCli("render " + take() + " --model " + out("rewritten") +
                            " --views 1 --size 32 --no-exr --out " + out("rewritten-frames")),
                     "its model.json was written after report.json, by a later run whose "
                     "report.failed.json says FAILURE: stopped by a signal");

  auto rendered = RunCli(render + out("partial-frames") + " --partial-model");
  ASSERT_EQ(rendered.exit_code, 0) << rendered.output;
  EXPECT_NE(rendered.output.find("is used as it is (--partial-model)"), std::string::npos)
      << rendered.output;
  const nlohmann::json render_report = ReadJson(out("partial-frames") + "/report.json");
  EXPECT_NE(render_report["plan"]["partial_model"].get<std::string>().find("3 of 4"),
            std::string::npos);
  EXPECT_EQ(render_report["options"]["partial_model"], true);
  auto site = RunCli(web + out("partial-site") + " --partial-model");
  ASSERT_EQ(site.exit_code, 0) << site.output;
  EXPECT_NE(site.output.find("is used as it is (--partial-model)"), std::string::npos)
      << site.output;
  EXPECT_EQ(ReadJson(out("partial-site") + "/report.json")["options"]["partial_models"], true);
}

TEST_F(ShardedSplats, WallClockBudgetsAndShardsWithoutSegmentsEndInOneLine) {
  ExpectOneLineError(RunCli(Train("bad", " --minutes 1")),
                     "--minutes is a wall-clock budget; a per-frame run");
  ExpectOneLineError(RunCli(Train("bad", " --frame-minutes 1")),
                     "--frame-minutes is a wall-clock budget");
  ExpectOneLineError(RunCli("train splat " + take() + " --ground-truth-cameras --out " +
                            out("bad") + " --iterations 10 --shard 0/2"),
                     "--shard splits a per-frame run: give --segment-frames too");
  ExpectOneLineError(RunCli("train splat " + take() + " --ground-truth-cameras --out " +
                            out("bad") + " --segment-frames 2 --iterations 10"),
                     "trains every frame for a number of iterations");
}

}  // namespace
}  // namespace holocap
