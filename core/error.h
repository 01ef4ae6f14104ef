// One error type for broken preconditions and bad input. The CLI prints its message as a
// single line and exits non-zero; numerical failures are reported in summaries instead.
#pragma once

#include <functional>
#include <sstream>
#include <stdexcept>
#include <string>
#include <string_view>
#include <utility>

namespace holocap {

class Error : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// Concatenates anything streamable into one string.
template <typename... Args>
std::string Cat(Args&&... args) {
  std::ostringstream out;
  (out << ... << std::forward<Args>(args));
  return out.str();
}

// Throws holocap::Error with the concatenated message.
template <typename... Args>
[[noreturn]] void Fail(Args&&... args) {
  throw Error(Cat(std::forward<Args>(args)...));
}

// `text` made safe to print as one line of a message: valid UTF-8 is kept, newlines, tabs and
// carriage returns become \n, \t, \r, and every other control byte or byte that is not part of
// valid UTF-8 becomes \xNN. The CLI prints every error message through it, so a message that
// quotes a binary file never sends raw bytes to a terminal.
std::string Printable(std::string_view text);

// Runs `call` with the process's stderr (file descriptor 2) sent to a temporary file, restores
// it, and returns what was written there, its lines joined by "; ". For third-party libraries
// (libmrcal, libpng) that print their own diagnostics: the caller folds the text into its one
// error line. Output of other threads in that window is captured too. Exceptions of `call`
// propagate after stderr is restored.
std::string CaptureStderr(const std::function<void()>& call);

}  // namespace holocap
