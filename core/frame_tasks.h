// Per-frame tasks: a run's frame sets done by any number of independent, idempotent tasks (one
// process, the tasks of a Slurm job array, GNU parallel over SSH), so that a task killed at any
// point leaves nothing a later task takes as done, and the merged outputs are the same bytes as
// one process's.
//
// A run writes into its output directory OUT:
//   OUT/run.json                   the run: command, fingerprint, its frame sets, and the options
//                                  and plan its report shows (every task writes the same)
//   OUT/plan/plan.json             the run's plan where making it costs more than reading it
//                                  (a coarse hull over the take, a background model): made
//                                  once, by the first task to take OUT/plan/.lock, with the
//                                  files it lists beside it; every later task reads and
//                                  verifies it (its fingerprint, each file's size and hash)
//   OUT/<each frame's outputs>     written to a temporary sibling, fsync'ed and renamed
//   OUT/frame-reports/<set>.json   the frame's record, written last (atomically, durably): the
//                                  run's fingerprint, the frame's result (its own report), and
//                                  each output's size and hash
//   OUT/report.json                the run's report, merged from the records once all exist
// A frame is complete when its record parses, names the run's fingerprint, and every output it
// lists has the recorded size and hash. Complete frames are skipped on a re-run; anything else
// (no record, another run's record, an output missing, cut short or changed) is done again.
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <map>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace holocap {

// `--shard K/N`: task K (0-based) of N does the K-th of N contiguous blocks of the run's frame
// sets, their sizes differing by one at most. Deterministic: the same K/N always names the same
// sets, so a resubmitted task redoes exactly its own unfinished frames.
struct Shard {
  int index = 0;  // K, in [0, count)
  int count = 1;  // N >= 1; 1/1 ... 0/1: the whole run

  // "K/N" (e.g. "2/8"); throws Error naming `flag` for anything else.
  static Shard Parse(const std::string& text, const std::string& flag = "--shard");
  bool whole() const { return count == 1; }
  std::string ToString() const;  // "K/N"
  // The shard's sets out of a run's `sets`, in their order (empty when N exceeds the sets).
  std::vector<int64_t> Of(const std::vector<int64_t>& sets) const;
  void Check() const;  // throws Error naming --shard
};

// How a task of a per-frame command runs; never part of what decides a frame's bytes.
struct FrameTaskOptions {
  Shard shard;        // this task's part of the run's frame sets (--shard K/N)
  bool redo = false;  // do complete frames again (their records are replaced) (--redo)

  void Check() const;
  nlohmann::json ToJson() const;
};

// 64-bit FNV-1a of `bytes` as 16 hex digits: detects an output that was cut short or changed.
std::string HashBytes(std::string_view bytes);

// The folder of a run's per-frame records, and one set's record in it.
inline constexpr const char* kFrameReportsDir = "frame-reports";
std::filesystem::path FrameRecordPath(const std::filesystem::path& out, int64_t set);

// One run's records in its output directory (see the top of this file).
class FrameRecords {
 public:
  // `identity`: everything that decides the frames' bytes (the command's options less threads
  // and shard, and its plan); its hash is the run's fingerprint. `sets`: the run's frame sets.
  FrameRecords(std::filesystem::path out, std::string command, const nlohmann::json& identity,
               std::vector<int64_t> sets);

  // The records of a run whose fingerprint is known (read from its run.json).
  static FrameRecords OfRun(std::filesystem::path out, std::string command, std::string fingerprint,
                            std::vector<int64_t> sets);

  const std::string& fingerprint() const { return fingerprint_; }
  const std::vector<int64_t>& sets() const { return sets_; }
  const std::filesystem::path& out() const { return out_; }

  // Writes OUT/run.json atomically and durably: command, fingerprint, sets, and `header` (the
  // options and plan of the run's report). Every task of a run writes the same bytes.
  void WriteRun(const nlohmann::json& header) const;
  // The set's record when the frame is complete; otherwise nothing, and `why` says what is
  // missing (no record, another run's, an output missing or changed).
  std::optional<nlohmann::json> Complete(int64_t set, std::string* why = nullptr) const;
  // Records `set` as done, last of all its writes: `result` is the frame's own report,
  // `outputs` the files (relative to OUT) its task wrote there durably, each recorded with its
  // size and hash; `started_unix_s` when the frame began; `task` names who did it. The record
  // also holds the task's CPU seconds so far (task_cpu_s: a run's CPU per task is the largest).
  void Record(int64_t set, const nlohmann::json& result, const std::vector<std::string>& outputs,
              double started_unix_s, const std::string& task) const;

 private:
  std::filesystem::path out_;
  std::string command_;
  std::string fingerprint_;
  std::vector<int64_t> sets_;
};

// The run's plan, made once for every task of the run (see the top of this file).
struct StoredPlan {
  nlohmann::json plan;  // what `make` returned
  bool made = false;    // this task made it (else it was read, made by another task or run)
  std::string made_by;  // the task that made it (PlanOnce's `task`)
  std::string why;      // why it was made here ("no plan yet", "the plan is another run's", ...)
};
// The folder of a run's plan.
inline constexpr const char* kPlanDir = "plan";
// Returns OUT/plan/plan.json's plan when it names `fingerprint` (a hash of everything that
// decides the plan) and every file it lists is intact. Otherwise, holding OUT/plan/.lock
// (flock(2), so the run's other tasks wait for it and then read it), calls `make`, which plans
// and writes its files into OUT/plan/ durably, adding their names (relative to OUT/plan) to
// `files`; the plan, the files' sizes and hashes, `task` (who made it) and the CPU seconds it
// took (made_cpu_s) are then written, atomically, last. A plan another task made while this one
// waited for the lock is read, not made again.
StoredPlan PlanOnce(const std::filesystem::path& out, const std::string& command,
                    const std::string& fingerprint, const std::string& task,
                    const std::function<nlohmann::json(std::vector<std::string>* files)>& make);

// A run's progress read from its output directory alone (its run.json and records), never from
// a scheduler's accounting.
struct RunState {
  std::filesystem::path out;
  std::string command;
  std::string fingerprint;
  std::vector<int64_t> sets;
  nlohmann::json header;                          // run.json's options and plan
  std::map<int64_t, nlohmann::json> complete;     // set -> its record
  std::map<int64_t, std::string> incomplete;      // set -> why it is not complete
  std::map<std::string, int64_t> frames_by_task;  // who did the complete frames
  std::map<std::string, double> cpu_s_by_task;    // each one's CPU seconds at its last record

  bool done() const { return incomplete.empty(); }
  // "3 of 6 frame sets complete; incomplete: 2 (no record), 4 (...), ..." (at most `shown`).
  std::string Describe(size_t shown = 8) const;
};
// Throws Error when `out` holds no run.json (not the output of a per-frame command).
RunState ReadRunState(const std::filesystem::path& out);

// Where a task writes its own report.json: OUT/report.json for a whole run, else
// OUT/tasks/shard-K-of-N/report.json (the run's report.json is merged from the records).
std::filesystem::path TaskReportPath(const std::filesystem::path& out, const Shard& shard);

// This process as a task: "shard K/N, host H, pid P" (with the Slurm job and array task when
// it runs under Slurm).
std::string DescribeTask(const Shard& shard);
// Seconds since the Unix epoch (the records' times, comparable across hosts).
double UnixSeconds();
// This process's peak resident memory so far, in MB.
double PeakRssMb();
// The CPU time this process has used so far (user + system), in seconds.
double CpuSeconds();

// A run's CPU clock: this process's CPU seconds (user + system, every thread) since `origin`,
// less those spent inside its Excluded scopes (the held-out scoring, which a CPU budget of
// training does not pay for, so that how often a run is scored does not change what it learns).
class CpuClock {
 public:
  explicit CpuClock(double origin = CpuSeconds()) : origin_(origin) {}
  double Now() const { return CpuSeconds() - origin_ - excluded_; }
  double excluded() const { return excluded_; }

  // While it lives, the process's CPU seconds are not the clock's.
  class Excluded {
   public:
    explicit Excluded(CpuClock* clock) : clock_(clock), start_(CpuSeconds()) {}
    ~Excluded() { clock_->excluded_ += CpuSeconds() - start_; }
    Excluded(const Excluded&) = delete;
    Excluded& operator=(const Excluded&) = delete;

   private:
    CpuClock* clock_;
    double start_;
  };

 private:
  double origin_;
  double excluded_ = 0;
};

}  // namespace holocap
