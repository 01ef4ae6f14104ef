// File-system helpers that fail with one clear line and never leave half-written files.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>
#include <string_view>

namespace holocap {

namespace fs = std::filesystem;

// Reads a whole regular file (a link to one is followed); throws Error naming the file when it
// is missing, unreadable, not a regular file (a device, FIFO or socket: refused without waiting
// on it) or longer than `max_bytes`.
inline constexpr uint64_t kAnyFileSize = ~uint64_t{0};
std::string ReadFileToString(const fs::path& file, uint64_t max_bytes = kAnyFileSize);

// Writes `bytes` to `file` through a temporary sibling and rename(2), so a reader sees either
// the old or the new content. With `durable`, the data and the directory entry are fsync'ed.
// Throws Error on any failure (full disk included) and removes the temporary.
void WriteFileAtomic(const fs::path& file, std::string_view bytes, bool durable = false);

// Creates `dir` and its parents; throws Error when that is impossible (not writable, a file
// in the way).
void CreateDirectories(const fs::path& dir);

// Appends one line (a '\n' is added) to a file opened once; each call flushes to the kernel so
// that a killed process loses at most the line being written.
class LineAppender {
 public:
  LineAppender() = default;
  explicit LineAppender(const fs::path& file, bool durable = false);
  ~LineAppender();
  LineAppender(LineAppender&& other) noexcept;
  LineAppender& operator=(LineAppender&& other) noexcept;
  LineAppender(const LineAppender&) = delete;
  LineAppender& operator=(const LineAppender&) = delete;

  void Append(std::string_view line);
  void Close();
  bool is_open() const { return fd_ >= 0; }

 private:
  int fd_ = -1;
  bool durable_ = false;
  fs::path file_;
};

}  // namespace holocap
