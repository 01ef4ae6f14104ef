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

namespace holocap {

// How a numerical stage ended. Degenerate input is its own state, never "converged".
enum class Termination {
  kSuccess,        // a non-iterative stage did all it set out to do
  kConvergence,    // an iterative stage met its tolerance
  kNoConvergence,  // it ran out of iterations or time first
  kDegenerate,     // the input cannot support a solution (ill-conditioned, too little data)
  kFailure,        // a numerical failure (NaN, divergence) or an I/O failure mid-run
};
const char* ToString(Termination termination);
bool IsUsable(Termination termination);  // success or convergence

struct Summary {
  Termination termination = Termination::kSuccess;
  std::string message;
};

class Report {
 public:
  explicit Report(std::string command);

  nlohmann::json& options() { return json_["options"]; }
  nlohmann::json& plan() { return json_["plan"]; }
  nlohmann::json& metrics() { return json_["metrics"]; }
  const nlohmann::json& json() const { return json_; }

  void SetSummary(const Summary& summary);
  // Appends a point to the error-against-time series, timed from construction. Thread-safe.
  void AddPoint(const std::string& metric, double value, int64_t iter);
  double ElapsedSeconds() const;

  // Writes atomically (report.json stays readable if the process dies mid-write).
  void Write(const std::filesystem::path& file) const;

 private:
  std::chrono::steady_clock::time_point start_;
  mutable std::mutex mutex_;
  nlohmann::json json_;
};

}  // namespace holocap
