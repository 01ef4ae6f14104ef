// `holocap export web --shard K/N`: a site as a per-frame run of groups (a splat key frame and
// its deltas). Three shards, a damaged group, a shard killed mid-group: each ends with the bytes
// of one process's site, complete groups skipped, and no manifest until every group is done.
#include <gtest/gtest.h>

#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>

#include "core/fs.h"
#include "splat/splat.h"
#include "tests/distributed/shard_compare.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;
using testing::ExpectOneLineError;
using testing::ExpectSameSite;
using testing::ReadJson;
using testing::RecordTimes;
using testing::RunCli;
using testing::TempDir;

// 6 frame sets after the clean plate, key frames every 2: three groups of two frames each.
class ShardedWebExport : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new TempDir("holocap-web-shards");
    auto result = RunCli("sim --rig studio8 --frames 7 --clean-plate 1 --size 96 --seed 8 --out " +
                         take() + " --threads 2");
    ASSERT_EQ(result.exit_code, 0) << result.output;
    result = RunCli("reconstruct " + take() +
                    " --ground-truth-cameras --voxel 10mm --no-sweep --threads 2");
    ASSERT_EQ(result.exit_code, 0) << result.output;
    // Splats frame to frame, seeded from the take's reconstruction (a few iterations).
    SplatOptions splats;
    splats.take.ground_truth_cameras = true;
    splats.recon_dir = take() + "/recon";
    splats.image_width = 48;
    splats.max_seed_points = 1500;
    splats.iterations = 40;
    splats.frame_iterations = 8;
    splats.minutes = splats.frame_minutes = 10;
    splats.eval_every_s = 1000;
    splats.threads = 1;
    TrainSplats(take(), out("splat"), splats);
    ASSERT_TRUE(fs::exists(out("splat") + "/deltas"));
    result = RunCli(Export("whole", ""));
    ASSERT_EQ(result.exit_code, 0) << result.output;
  }
  static void TearDownTestSuite() { delete dir_; }
  static std::string take() { return (dir_->path() / "take").string(); }
  static std::string out(const std::string& name) { return (dir_->path() / name).string(); }
  static std::string Export(const std::string& name, const std::string& extra) {
    return "export web " + take() + " --ground-truth-cameras --model " + out("splat") +
           " --quality medium --key-every 2 --ground-truth --out " + out(name) + extra;
  }
  static TempDir* dir_;
};
TempDir* ShardedWebExport::dir_ = nullptr;

TEST_F(ShardedWebExport, ThreeShardsMergeIntoTheOneProcessSite) {
  const nlohmann::json manifest = ReadJson(out("whole") + "/manifest.json");
  ASSERT_EQ(manifest["frames"].size(), 6u);
  ASSERT_EQ(manifest["streams"].size(), 2u);  // mesh-medium, splat-medium
  std::vector<bool> keys;
  for (const auto& chunk : manifest["streams"][1]["chunks"]) keys.push_back(chunk["key"]);
  EXPECT_EQ(keys, (std::vector<bool>{true, false, true, false, true, false}));
  EXPECT_EQ(ReadRunState(out("whole")).sets, (std::vector<int64_t>{1, 3, 5}));

  auto first = RunCli(Export("split", " --shard 0/3"));
  ASSERT_EQ(first.exit_code, 0) << first.output;
  EXPECT_NE(first.output.find("plan: made by this task"), std::string::npos) << first.output;
  EXPECT_FALSE(fs::exists(out("split") + "/manifest.json")) << "a site of 1 of 3 groups";
  EXPECT_TRUE(fs::exists(out("split") + "/tasks/shard-0-of-3/report.json"));
  auto second = RunCli(Export("split", " --shard 1/3"));
  ASSERT_EQ(second.exit_code, 0) << second.output;
  EXPECT_NE(second.output.find("plan: read from"), std::string::npos) << second.output;
  // Merging two thirds of a run: FAILURE naming what is missing, and no manifest.
  ExpectOneLineError(RunCli("report " + out("split") + " --merge"), "2 of 3 frame sets complete");
  EXPECT_EQ(ReadJson(out("split") + "/report.json")["summary"]["termination"], "FAILURE");
  EXPECT_FALSE(fs::exists(out("split") + "/manifest.json"));

  auto third = RunCli(Export("split", " --shard 2/3"));
  ASSERT_EQ(third.exit_code, 0) << third.output;
  EXPECT_NE(third.output.find("the run is complete"), std::string::npos) << third.output;
  ExpectSameSite(out("whole"), out("split"));
  auto merged = RunCli("report " + out("split") + " --merge");
  ASSERT_EQ(merged.exit_code, 0) << merged.output;
  ExpectSameSite(out("whole"), out("split"));
}

TEST_F(ShardedWebExport, ARerunSkipsCompleteGroupsAndRedoesDamagedOnes) {
  fs::copy(out("whole"), out("damaged"), fs::copy_options::recursive);
  const std::map<int64_t, double> before = RecordTimes(out("damaged"));
  ASSERT_EQ(before.size(), 3u);
  auto again = RunCli(Export("damaged", ""));
  ASSERT_EQ(again.exit_code, 0) << again.output;
  EXPECT_NE(again.output.find("3 of 3 group(s) skipped"), std::string::npos) << again.output;
  EXPECT_EQ(RecordTimes(out("damaged")), before) << "complete groups are skipped";

  // Group 1 (sets 3, 4): its delta chunk cut short; group 2 (sets 5, 6): its record lost.
  const std::string chunk = out("damaged") + "/streams/splat-medium/000004.hcc";
  fs::resize_file(chunk, fs::file_size(chunk) / 2);
  fs::remove(FrameRecordPath(out("damaged"), 5));
  auto rerun = RunCli(Export("damaged", " --shard 1/2"));
  ASSERT_EQ(rerun.exit_code, 0) << rerun.output;
  EXPECT_NE(rerun.output.find("wrote 2 and skipped 0 of its 2 group(s)"), std::string::npos)
      << rerun.output;
  const std::map<int64_t, double> after = RecordTimes(out("damaged"));
  EXPECT_EQ(after.at(1), before.at(1));
  EXPECT_GT(after.at(3), before.at(3));
  EXPECT_GT(after.at(5), before.at(5));
  ExpectSameSite(out("whole"), out("damaged"));
}

// report SITE --merge believed a tampered frame record: the manifest listed the chunk
// '../../../../etc/passwd' and a PSNR of -3026 dB, SUCCESS. Records are checked before they are
// merged, and the site's manifest is left as it was.
TEST_F(ShardedWebExport, AMergeRefusesATamperedFrameRecord) {
  struct Tamper {
    std::string field, value, expected;
  };
  for (const Tamper& t :
       {Tamper{"file", "\"../../../../etc/passwd\"", "which is no plain file name"},
        Tamper{"squared", "1e300", "which no image gives"},
        Tamper{"bytes", "7", "holds another size"}}) {
    fs::remove_all(out("tampered"));
    fs::copy(out("whole"), out("tampered"), fs::copy_options::recursive);
    const fs::path record = FrameRecordPath(out("tampered"), 3);
    nlohmann::json json = nlohmann::json::parse(ReadFileToString(record));
    nlohmann::json& frame = json["result"]["streams"].begin().value()[0];
    ASSERT_TRUE(frame["chunk"].is_object()) << json.dump();
    nlohmann::json& target = t.field == "squared" ? frame : frame["chunk"];
    target[t.field] = nlohmann::json::parse(t.value);
    WriteFileAtomic(record, json.dump());
    const std::string manifest = ReadFileToString(out("tampered") + "/manifest.json");
    ExpectOneLineError(RunCli("report " + out("tampered") + " --merge"), t.expected);
    EXPECT_EQ(ReadFileToString(out("tampered") + "/manifest.json"), manifest) << t.field;
  }
}

TEST_F(ShardedWebExport, AShardKilledMidGroupRedoesOnlyItsUnfinishedGroup) {
  const std::string dir = out("killed");
  auto first = RunCli(Export("killed", " --shard 0/2"));
  ASSERT_EQ(first.exit_code, 0) << first.output;
  // Kill -9 as soon as group 1 is recorded: group 2's chunks are being written.
  ASSERT_TRUE(testing::KillWhenRecorded(Export("killed", " --shard 1/2"), FrameRecordPath(dir, 3)))
      << "the task ended before it was killed";
  const RunState killed = ReadRunState(dir);
  ASSERT_EQ(killed.complete.size(), 2u) << killed.Describe();
  EXPECT_FALSE(fs::exists(dir + "/manifest.json"));

  auto rerun = RunCli(Export("killed", " --shard 1/2"));
  ASSERT_EQ(rerun.exit_code, 0) << rerun.output;
  EXPECT_NE(rerun.output.find("wrote 1 and skipped 1 of its 2 group(s)"), std::string::npos)
      << rerun.output;
  ExpectSameSite(out("whole"), dir);
}

TEST_F(ShardedWebExport, FramesSelectTheTimelineAndBadFlagsEndInOneLine) {
  auto part = RunCli(Export("part", " --frames 2-3 --shard 0/1"));
  ASSERT_EQ(part.exit_code, 0) << part.output;
  const nlohmann::json manifest = ReadJson(out("part") + "/manifest.json");
  ASSERT_EQ(manifest["frames"].size(), 2u);
  EXPECT_EQ(manifest["frames"][0]["set"], 3);
  EXPECT_EQ(manifest["frames"][1]["set"], 4);

  ExpectOneLineError(RunCli(Export("bad", " --shard 2/2")),
                     "--shard 2/2 violates index < count (2) (K/N needs 0 <= K < N)");
  ExpectOneLineError(RunCli(Export("bad", " --shard half")), "--shard must be K/N");
  ExpectOneLineError(RunCli(Export("bad", " --frames 40-49")), "--frames lists frame set 40");
  ExpectOneLineError(RunCli("export colmap " + take() + " --out " + out("bad") + " --shard 0/2"),
                     "are options of export web only");
  // The output rules hold for every task: a folder another command made is refused.
  fs::create_directories(out("other"));
  WriteFileAtomic(out("other") + "/notes.txt", "kept\n");
  ExpectOneLineError(RunCli(Export("other", " --shard 0/2")),
                     "is not empty and holocap export web did not make it");
  EXPECT_EQ(ReadFileToString(out("other") + "/notes.txt"), "kept\n");
  ExpectOneLineError(RunCli("report " + out("splat") + " --merge"), "holds no run.json");
  ExpectOneLineError(
      RunCli("submit slurm export web " + take() + " --model " + out("splat") + " --tasks 2"),
      "needs the site's --out DIR");
  auto scripts = RunCli("submit slurm export web " + take() + " --model " + out("splat") +
                        " --key-every 2 --out " + out("slurm") + " --tasks 3 --dry-run");
  ASSERT_EQ(scripts.exit_code, 0) << scripts.output;
  EXPECT_NE(scripts.output.find(" export web '"), std::string::npos) << scripts.output;
  EXPECT_NE(scripts.output.find("--shard \"${SLURM_ARRAY_TASK_ID}/3\""), std::string::npos)
      << scripts.output;
  EXPECT_EQ(scripts.output.find("--threads"), std::string::npos) << scripts.output;
  EXPECT_NE(scripts.output.find("report '" + out("slurm") + "' --merge"), std::string::npos)
      << scripts.output;
}

}  // namespace
}  // namespace holocap
