// Per-frame commands as Slurm job arrays: one array task per shard of the run
// (SLURM_ARRAY_TASK_ID -> --shard K/N), and a final job, dependent on the array (afterany),
// that merges the frames' reports into the run's report.json. holocap schedules nothing itself:
// Slurm does, and the same shards run under any other launcher (`--shard K/N`). Progress is
// read from the run's own per-frame records (core/frame_tasks.h), never from Slurm's
// accounting.
#pragma once

#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "core/frame_tasks.h"
#include "core/report.h"

namespace holocap {

// The per-frame commands a job array can run, with where each writes by default (under the
// take) and whether it takes --threads.
struct PerFrameCommand {
  const char* name;         // "reconstruct"
  const char* default_out;  // "recon": TAKE/recon unless the command's --out says otherwise
  bool has_threads;         // the task's CPUs are passed as --threads
};
// Throws Error listing the known ones when `name` is none of them.
const PerFrameCommand& FindPerFrameCommand(const std::string& name);
// Where a per-frame command run with `args` writes: the value of its --out, else TAKE/<default>.
std::filesystem::path PerFrameOutput(const PerFrameCommand& command,
                                     const std::filesystem::path& take,
                                     const std::vector<std::string>& args);

struct SlurmOptions {
  std::string command = "reconstruct";  // the per-frame command each array task runs
  std::filesystem::path take;           // the take, on a filesystem every node sees
  std::vector<std::string> args;        // the command's own flags, passed to every task as given
  int tasks = 1;                        // array tasks, one shard of the run each (--tasks)
  std::string partition;                // sbatch --partition (empty: the cluster's default)
  std::string time;                     // sbatch --time per task, e.g. 2:00:00 (empty: the
                                        // partition's limit)
  std::string mem;                      // sbatch --mem per task, e.g. 8G (empty: the default)
  int cpus = 1;                         // sbatch --cpus-per-task; also the command's --threads
  std::filesystem::path holocap;        // the program the tasks run (absolute; every node sees it)

  void Check() const;  // throws Error naming the flag
  nlohmann::json ToJson() const;
};

// The two batch scripts of a submission: the array (one shard per task) and the merge.
struct SlurmScripts {
  std::filesystem::path out;  // the run's output directory
  std::string array;          // OUT/slurm/array.sbatch
  std::string merge;          // OUT/slurm/merge.sbatch
};
SlurmScripts MakeSlurmScripts(const SlurmOptions& options);

// SUCCESS when both jobs were submitted (their ids in the summary); FAILURE with sbatch's own
// words when it refused one (the array is cancelled when the merge job is refused).
struct SubmitSummary : Summary {
  std::filesystem::path out;
  std::filesystem::path array_script;
  std::filesystem::path merge_script;
  std::string array_job_id;
  std::string merge_job_id;
};

// The directory of a run's scripts, logs and submissions.
std::filesystem::path SlurmDirectory(const std::filesystem::path& out);

// Writes the scripts into OUT/slurm/ and submits them with sbatch (the array, then the merge
// with --dependency=afterany on it); each submission is appended to OUT/slurm/submissions.jsonl.
// Throws Error, before writing anything, when sbatch is not on PATH.
SubmitSummary SubmitToSlurm(const SlurmOptions& options);

// Whether an executable of this name is on PATH.
bool OnPath(const std::string& program);
// Throws Error saying so (and how to run the shards without Slurm) when sbatch is not on PATH.
void RequireSbatch(const std::string& command);

// The output of a run as a table a person reads: per frame set, complete (by which task, how
// long) or why not; the tasks' own reports; the run's merged report if any.
std::string DescribeRunProgress(const RunState& run);

}  // namespace holocap
