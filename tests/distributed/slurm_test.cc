// holocap submit slurm on a real one-node Slurm cluster that the test starts on localhost
// (munged, slurmctld and slurmd as root, with their own key, sockets, ports, state and logs in a
// temporary directory, stopped by their pids however the test ends), and the submit command's
// scripts and errors without one.
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <fstream>
#include <random>
#include <thread>

#include "core/error.h"
#include "core/frame_tasks.h"
#include "core/fs.h"
#include "distributed/slurm.h"
#include "tests/distributed/shard_compare.h"
#include "tests/distributed/slurm_cluster.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::ExpectOneLineError;
using testing::ExpectSameModel;
using testing::ExpectSameRun;
using testing::ExpectSameSite;
using testing::FindProgram;
using testing::LocalSlurm;
using testing::ReadJson;
using testing::RunCli;
using testing::RunShell;
using testing::Sleep;
using testing::TempDir;
namespace fs = std::filesystem;

// The array and merge job ids of a submission's output.
std::pair<std::string, std::string> JobIds(const std::string& output) {
  const size_t array = output.find("array job ");
  const size_t merge = output.find("merge job ");
  if (array == std::string::npos || merge == std::string::npos) return {};
  auto number = [&](size_t at) {
    return output.substr(at, output.find_first_not_of("0123456789", at) - at);
  };
  return {number(array + 10), number(merge + 10)};
}

TEST(SubmitSlurm, OneShardPerArrayTaskAndAMergeAfterThem) {
  TempDir dir("holocap-submit");
  const std::string take = (dir.path() / "take").string();
  auto dry = RunCli("submit slurm reconstruct " + take + " --voxel 8mm --tasks 3 --cpus 2 " +
                    "--partition gpu --time 1:30:00 --mem 4G --dry-run");
  ASSERT_EQ(dry.exit_code, 0) << dry.output;
  for (const char* line :
       {"#SBATCH --array=0-2\n", "#SBATCH --cpus-per-task=2\n", "#SBATCH --partition=gpu\n",
        "#SBATCH --time=1:30:00\n", "#SBATCH --mem=4G\n", "reconstruct '",
        "' '--voxel' '8mm' --threads \"$OMP_NUM_THREADS\" --shard "
        "\"${SLURM_ARRAY_TASK_ID}/3\"\n",
        "report '"}) {
    EXPECT_NE(dry.output.find(line), std::string::npos) << line << " in\n" << dry.output;
  }
  EXPECT_NE(dry.output.find(take + "/recon' --merge\n"), std::string::npos) << dry.output;
  EXPECT_FALSE(fs::exists(take)) << "a dry run writes nothing";
  // Without sbatch on PATH: one line, nothing written.
  ExpectOneLineError(RunShell("PATH=/nonexistent '" + testing::CliPath() +
                              "' submit slurm reconstruct " + take + " --tasks 2"),
                     "needs Slurm's sbatch on PATH");
  EXPECT_FALSE(fs::exists(take));
  ExpectOneLineError(RunCli("submit slurm render " + take + " --dry-run"),
                     "'render' is not a per-frame command");
  ExpectOneLineError(RunCli("submit slurm reconstruct " + take + " --tasks 0 --dry-run"),
                     "--tasks 0 violates tasks in [1, 100000]");
  ExpectOneLineError(RunCli("submit slurm reconstruct " + take + " --time '1 day' --dry-run"),
                     "--time '1 day' holds ' '");
  ExpectOneLineError(RunCli("submit slurm reconstruct " + take + " --shard 0/2 --dry-run"),
                     "leave it out of the command's flags");
  // A command of two words: train splat, a per-frame run of segments.
  auto splat = RunCli("submit slurm train splat " + take +
                      " --segment-frames 4 --iterations 300 --frame-iterations 50 --tasks 2 "
                      "--dry-run");
  ASSERT_EQ(splat.exit_code, 0) << splat.output;
  for (const char* line :
       {"#SBATCH --job-name=holocap-train-splat\n",
        "#SBATCH --job-name=holocap-train-splat-merge\n", " train splat '",
        "' '--segment-frames' '4' '--iterations' '300' '--frame-iterations' '50' "
        "--threads \"$OMP_NUM_THREADS\" --shard \"${SLURM_ARRAY_TASK_ID}/2\"\n"}) {
    EXPECT_NE(splat.output.find(line), std::string::npos) << line << " in\n" << splat.output;
  }
  EXPECT_NE(splat.output.find(take + "/models/splat' --merge\n"), std::string::npos)
      << splat.output;
  ExpectOneLineError(RunCli("submit slurm train splat " + take + " --tasks 2 --dry-run"),
                     "give --segment-frames S");
}

// A newline in a take's path broke the #SBATCH --output line and made the rest of the path a
// command of the script (touch PWNED ran on the cluster). Control characters are refused in
// everything the script carries, blanks and quotes in the #SBATCH line's path.
TEST(SubmitSlurm, APathThatWouldBreakTheScriptIsRefused) {
  TempDir dir("holocap-submit");
  const std::string injected = (dir.path() / "E/nl\ntouch PWNED\n#x/take").string();
  ExpectOneLineError(RunCli("submit slurm reconstruct '" + injected + "' --tasks 2 --dry-run"),
                     "holds a control character (byte 10)");
  ExpectOneLineError(RunCli("submit slurm reconstruct '" + (dir.path() / "my take").string() +
                            "' --tasks 2 --dry-run"),
                     "which an #SBATCH --output line cannot carry");
  ExpectOneLineError(RunCli("submit slurm reconstruct '" + (dir.path() / "take").string() +
                            "' --voxel \"$(printf '8mm\\nx')\" --tasks 2 --dry-run"),
                     "the argument '8mm");
  EXPECT_FALSE(fs::exists(dir.path() / "E"));
}

// A simulated take reconstructed by 3 array tasks; one is cancelled in the middle of its second
// frame; the merge job reports the run incomplete; a resubmission redoes only what was lost,
// and the merged meshes and report are those of one process's run. Then the take's splats by 2
// array tasks (train splat --segment-frames): the merged model is one process's; and its site
// by 2 array tasks (export web): one process's site.
TEST(SlurmCluster, ACancelledTaskIsRedoneAndTheMergeIsTheOneProcessRun) {
  if (geteuid() != 0) GTEST_SKIP() << "starting munged, slurmctld and slurmd needs root";
  for (const char* program :
       {"munged", "slurmctld", "slurmd", "sbatch", "scancel", "squeue", "sinfo", "setpriv"}) {
    if (FindProgram(program).empty())
      GTEST_SKIP() << program << " is not installed (scripts/setup.sh --tests installs "
                   << "slurm-wlm and munge)";
  }
  TempDir dir("holocap-slurm");
  chmod(dir.path().c_str(), 0755);  // munged checks every folder above its socket
  const std::string take = (dir.path() / "take").string();
  const std::string whole = (dir.path() / "whole").string();
  const std::string split = (dir.path() / "split").string();
  auto sim = RunCli("sim --rig studio8 --frames 7 --clean-plate 1 --size 192 --out " + take);
  ASSERT_EQ(sim.exit_code, 0) << sim.output;
  auto one = RunCli("reconstruct " + take + " --ground-truth-cameras --out " + whole);
  ASSERT_EQ(one.exit_code, 0) << one.output;

  LocalSlurm cluster(dir.path() / "cluster");
  std::string why;
  ASSERT_TRUE(cluster.Start(&why)) << why;
  const std::string submit = "submit slurm reconstruct " + take + " --ground-truth-cameras --out " +
                             split + " --tasks 3 --cpus 1";
  auto first = RunCli(submit);
  ASSERT_EQ(first.exit_code, 0) << first.output;
  const auto [array_job, merge_job] = JobIds(first.output);
  ASSERT_FALSE(array_job.empty()) << first.output;

  // Task 1 holds sets 3 and 4: cancelled once set 3 is recorded, while it works on set 4.
  int polls = 0;
  while (polls++ < 3000 && !fs::exists(FrameRecordPath(split, 3))) Sleep(20);
  ASSERT_TRUE(fs::exists(FrameRecordPath(split, 3))) << cluster.ReadLog("slurmctld.log");
  auto cancel = RunShell("scancel " + array_job + "_1");
  ASSERT_EQ(cancel.exit_code, 0) << cancel.output;
  ASSERT_TRUE(LocalSlurm::WaitForJob(array_job)) << "the array did not end";
  ASSERT_TRUE(LocalSlurm::WaitForJob(merge_job)) << "the merge job did not end";
  const RunState cancelled = ReadRunState(split);
  ASSERT_EQ(cancelled.incomplete.count(4), 1u) << cancelled.Describe();
  EXPECT_EQ(cancelled.complete.size(), 5u) << cancelled.Describe();
  const nlohmann::json failed = ReadJson(split + "/report.json");
  EXPECT_EQ(failed["summary"]["termination"], "FAILURE");
  EXPECT_NE(failed["summary"]["message"].get<std::string>().find("incomplete: 4 ("),
            std::string::npos)
      << failed["summary"]["message"];
  auto status = RunCli("submit status " + take + " --out " + split);
  ASSERT_EQ(status.exit_code, 0) << status.output;
  EXPECT_NE(status.output.find("set 000004  incomplete"), std::string::npos) << status.output;
  EXPECT_NE(status.output.find("5 of 6 frame sets complete"), std::string::npos) << status.output;
  std::map<int64_t, double> before;
  for (const auto& [set, record] : cancelled.complete) before[set] = record["finished_unix_s"];

  auto again = RunCli(submit);
  ASSERT_EQ(again.exit_code, 0) << again.output;
  const auto [array_again, merge_again] = JobIds(again.output);
  ASSERT_TRUE(LocalSlurm::WaitForJob(array_again)) << "the second array did not end";
  ASSERT_TRUE(LocalSlurm::WaitForJob(merge_again)) << "the second merge job did not end";
  const RunState done = ReadRunState(split);
  ASSERT_TRUE(done.done()) << done.Describe() << cluster.ReadLog("slurmd.log");
  for (const auto& [set, finished] : before)
    EXPECT_EQ(done.complete.at(set)["finished_unix_s"], finished) << "set " << set << " redone";
  EXPECT_EQ(ReadJson(split + "/report.json")["summary"]["termination"], "SUCCESS");
  EXPECT_EQ(ExpectSameRun(whole, split), 12u);  // 6 PLY + 6 glTF, the same bytes

  // The take's splats as 2 array tasks (frame 0, then segments {1, 2, 3} and {4, 5}), merged
  // by the merge job into the model of one process's run.
  const std::string splats = " --recon " + whole +
                             " --segment-frames 3 --iterations 20 --frame-iterations 6 "
                             "--width 48 --seed-points 800 --heldout 1";
  const std::string splat_whole = (dir.path() / "splat-whole").string();
  const std::string splat_split = (dir.path() / "splat-split").string();
  auto one_splat =
      RunCli("train splat " + take + " --ground-truth-cameras --out " + splat_whole + splats);
  ASSERT_EQ(one_splat.exit_code, 0) << one_splat.output;
  auto splat = RunCli("submit slurm train splat " + take + " --ground-truth-cameras --out " +
                      splat_split + splats + " --tasks 2 --cpus 1");
  ASSERT_EQ(splat.exit_code, 0) << splat.output;
  const auto [splat_array, splat_merge] = JobIds(splat.output);
  ASSERT_TRUE(LocalSlurm::WaitForJob(splat_array)) << "the splat array did not end";
  ASSERT_TRUE(LocalSlurm::WaitForJob(splat_merge)) << "the splat merge job did not end";
  EXPECT_EQ(ReadJson(splat_split + "/report.json")["summary"]["termination"], "NO_CONVERGENCE");
  EXPECT_EQ(ReadRunState(splat_split).frames_by_task.size(), 2u);
  ExpectSameModel(splat_whole, splat_split);

  // The site of the meshes and the splats as 2 array tasks (groups {1, 2} and {3, 4}, {5, 6}),
  // its manifest written by the task that completes it: one process's site.
  const std::string web = " --recon " + whole + " --model " + splat_whole +
                          " --quality low --key-every 2 --ground-truth";
  const std::string site_whole = (dir.path() / "site-whole").string();
  const std::string site_split = (dir.path() / "site-split").string();
  auto one_site = RunCli("export web " + take + " --out " + site_whole + web);
  ASSERT_EQ(one_site.exit_code, 0) << one_site.output;
  auto site = RunCli("submit slurm export web " + take + " --out " + site_split + web +
                     " --tasks 2 --cpus 1");
  ASSERT_EQ(site.exit_code, 0) << site.output;
  const auto [site_array, site_merge] = JobIds(site.output);
  ASSERT_TRUE(LocalSlurm::WaitForJob(site_array)) << "the site's array did not end";
  ASSERT_TRUE(LocalSlurm::WaitForJob(site_merge)) << "the site's merge job did not end";
  EXPECT_EQ(ReadJson(site_split + "/report.json")["summary"]["termination"], "SUCCESS");
  EXPECT_EQ(ReadRunState(site_split).frames_by_task.size(), 2u);
  ExpectSameSite(site_whole, site_split);
}

}  // namespace
}  // namespace holocap
