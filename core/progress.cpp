#include "core/progress.h"

#include <unistd.h>

#include <cstdio>
#include <cstdlib>

namespace holocap {

bool Progress::IsTerminal() {
  return ::isatty(STDERR_FILENO) == 1 && std::getenv("HOLOCAP_NO_PROGRESS") == nullptr;
}

Progress::Progress(std::string label, int64_t total)
    : label_(std::move(label)),
      total_(total),
      enabled_(IsTerminal()),
      start_(std::chrono::steady_clock::now()) {}

Progress::~Progress() { Finish(); }

void Progress::Update(int64_t done, const std::string& status) {
  std::lock_guard lock(mutex_);
  done_ = done;
  status_ = status;
  auto now = std::chrono::steady_clock::now();
  // Redraw at most 10 times a second so progress costs nothing measurable.
  if (now - last_draw_ > std::chrono::milliseconds(100) || done_ >= total_) {
    last_draw_ = now;
    Draw();
  }
}

void Progress::Increment(const std::string& status) {
  int64_t next;
  {
    std::lock_guard lock(mutex_);
    next = done_ + 1;
  }
  Update(next, status);
}

void Progress::Draw() {
  if (!enabled_ || finished_) return;
  double elapsed = std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
  const int width = 30;
  int filled = total_ > 0 ? static_cast<int>(width * std::min<int64_t>(done_, total_) / total_) : 0;
  std::string bar(filled, '#');
  bar.resize(width, '.');
  double eta = (done_ > 0 && total_ > done_) ? elapsed / done_ * (total_ - done_) : 0;
  std::fprintf(stderr, "\r\033[K%s [%s] %lld/%lld  %.1fs", label_.c_str(), bar.c_str(),
               static_cast<long long>(done_), static_cast<long long>(total_), elapsed);
  if (eta > 0) std::fprintf(stderr, " (%.0fs left)", eta);
  if (!status_.empty()) std::fprintf(stderr, "  %s", status_.c_str());
  std::fflush(stderr);
}

void Progress::Finish() {
  std::lock_guard lock(mutex_);
  if (finished_) return;
  if (enabled_) {
    Draw();
    std::fprintf(stderr, "\n");
  }
  finished_ = true;
}

}  // namespace holocap
