// Progress for long work, on stderr: a single updating line on a terminal; where stderr is not
// a terminal (a pipe, a log file, a batch job), one plain line every kLineEverySeconds (or every
// HOLOCAP_PROGRESS_SECONDS seconds where that is set; 0: at every step) and a last one when the
// work printed a line before; nothing with HOLOCAP_NO_PROGRESS set.
#pragma once

#include <chrono>
#include <cstdint>
#include <mutex>
#include <string>

namespace holocap {

class Progress {
 public:
  Progress(std::string label, int64_t total);
  ~Progress();
  // Sets the amount done and an optional status text ("12.3 dB", "4 fps"). Thread-safe.
  void Update(int64_t done, const std::string& status = "");
  void Increment(const std::string& status = "");
  void Finish();

  static bool IsTerminal();  // stderr is a TTY and HOLOCAP_NO_PROGRESS is unset
  static constexpr double kLineEverySeconds = 10;

 private:
  enum class Mode { kOff, kTerminal, kLines };
  void Draw();
  void PrintLine(double elapsed);
  std::string label_;
  int64_t total_;
  int64_t done_ = 0;
  std::string status_;
  Mode mode_;
  bool finished_ = false;
  bool printed_line_ = false;
  std::chrono::steady_clock::time_point start_;
  std::chrono::steady_clock::time_point last_draw_;
  std::mutex mutex_;
};

}  // namespace holocap
