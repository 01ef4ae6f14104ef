// Run reports: every long command writes report.json with its options, the plan it chose, a
// summary (termination state and message), final metrics and an error-against-time series
// [{t_s, iter, metric, value}].
#pragma once

#include <chrono>
#include <cstdint>
#include <filesystem>
#include <mutex>
#include <nlohmann/json.hpp>
#include <string>
#include <utility>
#include <vector>

namespace holocap {

// How a stage ended: one contract for every stage and every command.
//
// clang-format off
// | state          | means                                                          | usable | exit |
// |----------------|----------------------------------------------------------------|--------|------|
// | SUCCESS        | the stage reached its goal (did all it set out to do)          | yes    | 0    |
// | CONVERGENCE    | an iterative stage stopped because its error stopped falling   | yes    | 0    |
// | NO_CONVERGENCE | the budget (iterations, time) ran out while the error fell     | yes    | 0    |
// | DEGENERATE     | the input cannot support the result; the reason is the message | no     | 1    |
// | FAILURE        | the stage could not run (I/O, NaN, divergence), or never ran   | no     | 1    |
// clang-format on
//
// A usable result is written and may be used by the next stage; NO_CONVERGENCE says a larger
// budget would still improve it. Every stage's summary derives from Summary, which starts as
// FAILURE "not run" (as Ceres' Solver::Summary does): a stage that returns early can never
// report success by accident.
enum class Termination {
  kSuccess,
  kConvergence,
  kNoConvergence,
  kDegenerate,
  kFailure,
};
const char* ToString(Termination termination);
bool IsUsable(Termination termination);   // success, convergence or no convergence
int ExitStatus(Termination termination);  // 0 when usable, else 1: the CLI's one rule

struct Summary {
  Termination termination = Termination::kFailure;
  std::string message = "not run";

  bool IsUsable() const { return holocap::IsUsable(termination); }
  // Sets both fields at once (the one place a stage states how it ended).
  void End(Termination state, std::string why) {
    termination = state;
    message = std::move(why);
  }
};

class Report {
 public:
  explicit Report(std::string command);
  // A report that has a failure destination, was never written, and dies while an exception
  // unwinds (the command ended by an error first) is kept for WritePendingFailureReports.
  ~Report();
  Report(const Report&) = delete;
  Report& operator=(const Report&) = delete;

  nlohmann::json& options() { return json_["options"]; }
  nlohmann::json& plan() { return json_["plan"]; }
  nlohmann::json& metrics() { return json_["metrics"]; }
  const nlohmann::json& json() const { return json_; }

  void SetSummary(const Summary& summary);
  // Appends a point to the error-against-time series, timed from construction. Thread-safe.
  void AddPoint(const std::string& metric, double value, int64_t iter);
  // The same at a given time (a series rebuilt from what earlier runs recorded).
  void AddPointAt(const std::string& metric, double value, int64_t iter, double t_s);
  double ElapsedSeconds() const;

  // Writes atomically (report.json stays readable if the process dies mid-write) and returns
  // where: a report of a run that is not usable never replaces a usable one (a previous good
  // result's), it goes beside it instead (report.failed.json; see ReportDestination).
  std::filesystem::path Write(const std::filesystem::path& file) const;
  // Where this report goes if the command ends by an error first: set once the command has
  // claimed its output (core/output.h), so a refused output never receives a report.
  void SetFailureDestination(const std::filesystem::path& file) { failure_file_ = file; }

 private:
  std::filesystem::path failure_file_;
  mutable bool written_ = false;  // a written report stands (its own summary, e.g. DEGENERATE)
  int exceptions_at_start_ = 0;
  std::chrono::steady_clock::time_point start_;
  mutable std::mutex mutex_;
  nlohmann::json json_;
};

// Writes each report that died with an exception (see ~Report) to its failure destination with
// FAILURE and `message` (the error line's text): options, plan, metrics and series so far are
// kept. Returns the files written; errors while writing are swallowed (the error line stands).
std::vector<std::filesystem::path> WritePendingFailureReports(const std::string& message);

// A report.json's text, checked to be a report (`origin` names it in errors): an object with a
// string command, a summary object whose termination and message are strings, a numeric
// elapsed_s. Throws Error.
nlohmann::json ParseReport(const std::string& text, const std::string& origin);

// Where `report` (a report's JSON) goes when asked to go to `file`: `file`, unless `report` is
// not usable (DEGENERATE, FAILURE) and `file` holds a usable report; then beside it, the same
// name with ".failed.json" (report.json -> report.failed.json).
std::filesystem::path ReportDestination(const std::filesystem::path& file,
                                        const nlohmann::json& report);

}  // namespace holocap
