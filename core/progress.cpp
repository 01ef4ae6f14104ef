#include "core/progress.h"

#include <unistd.h>

#include <cstdio>
#include <cstdlib>

namespace holocap {

namespace {

// Seconds between plain lines: HOLOCAP_PROGRESS_SECONDS where it is a number >= 0 (0: a line
// at every step, as tests that look for the lines want), else kLineEverySeconds. Read once.
double LineEverySeconds() {
  static const double seconds = [] {
    const char* text = std::getenv("HOLOCAP_PROGRESS_SECONDS");
    if (text == nullptr) return Progress::kLineEverySeconds;
    char* end = nullptr;
    const double value = std::strtod(text, &end);
    return end != text && value >= 0 ? value : Progress::kLineEverySeconds;
  }();
  return seconds;
}

}  // namespace

bool Progress::IsTerminal() {
  return ::isatty(STDERR_FILENO) == 1 && std::getenv("HOLOCAP_NO_PROGRESS") == nullptr;
}

Progress::Progress(std::string label, int64_t total)
    : label_(std::move(label)),
      total_(total),
      mode_(std::getenv("HOLOCAP_NO_PROGRESS") != nullptr ? Mode::kOff
            : IsTerminal()                                ? Mode::kTerminal
                                                          : Mode::kLines),
      start_(std::chrono::steady_clock::now()),
      last_draw_(start_) {}

Progress::~Progress() { Finish(); }

void Progress::Update(int64_t done, const std::string& status) {
  std::lock_guard lock(mutex_);
  done_ = done;
  status_ = status;
  auto now = std::chrono::steady_clock::now();
  if (mode_ == Mode::kLines) {
    const double elapsed = std::chrono::duration<double>(now - start_).count();
    if (!finished_ && now - last_draw_ >= std::chrono::duration<double>(LineEverySeconds())) {
      last_draw_ = now;
      PrintLine(elapsed);
    }
    return;
  }
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

// One self-contained line, for logs: "reconstruct: 12/60 frame sets, 34 s (20 s left) status".
void Progress::PrintLine(double elapsed) {
  const double eta = (done_ > 0 && total_ > done_) ? elapsed / done_ * (total_ - done_) : 0;
  std::fprintf(stderr, "%s: %lld/%lld, %.0f s", label_.c_str(), static_cast<long long>(done_),
               static_cast<long long>(total_), elapsed);
  if (eta > 0) std::fprintf(stderr, " (%.0f s left)", eta);
  if (!status_.empty()) std::fprintf(stderr, "  %s", status_.c_str());
  std::fprintf(stderr, "\n");
  std::fflush(stderr);
  printed_line_ = true;
}

void Progress::Draw() {
  if (mode_ != Mode::kTerminal || finished_) return;
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
  if (mode_ == Mode::kTerminal) {
    Draw();
    std::fprintf(stderr, "\n");
  } else if (mode_ == Mode::kLines && printed_line_) {
    PrintLine(std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count());
  }
  finished_ = true;
}

}  // namespace holocap
