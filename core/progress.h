// Progress for long work: a single updating line on a terminal, nothing when stderr is not a
// TTY (CI, pipes, files), so logs stay clean.
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

 private:
  void Draw();
  std::string label_;
  int64_t total_;
  int64_t done_ = 0;
  std::string status_;
  bool enabled_;
  bool finished_ = false;
  std::chrono::steady_clock::time_point start_;
  std::chrono::steady_clock::time_point last_draw_;
  std::mutex mutex_;
};

}  // namespace holocap
