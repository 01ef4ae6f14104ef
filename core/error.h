// One error type for broken preconditions and bad input. The CLI prints its message as a
// single line and exits non-zero; numerical failures are reported in summaries instead.
#pragma once

#include <sstream>
#include <stdexcept>
#include <string>
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

}  // namespace holocap
