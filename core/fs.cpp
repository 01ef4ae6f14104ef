#include "core/fs.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <random>

#include "core/error.h"

namespace holocap {
namespace {

std::string ErrnoText(int err) { return std::strerror(err); }

void WriteAll(int fd, std::string_view bytes, const fs::path& file) {
  const char* data = bytes.data();
  size_t left = bytes.size();
  while (left > 0) {
    ssize_t n = ::write(fd, data, left);
    if (n < 0) {
      if (errno == EINTR) continue;
      Fail("cannot write '", file.string(), "': ", ErrnoText(errno));
    }
    data += n;
    left -= static_cast<size_t>(n);
  }
}

void SyncDirectory(const fs::path& dir) {
  int fd = ::open(dir.empty() ? "." : dir.c_str(), O_RDONLY | O_DIRECTORY);
  if (fd >= 0) {
    ::fsync(fd);
    ::close(fd);
  }
}

}  // namespace

std::string ReadFileToString(const fs::path& file, uint64_t max_bytes) {
  // O_NONBLOCK: opening a FIFO must not wait for a writer; it is refused below like a device.
  const int fd = ::open(file.c_str(), O_RDONLY | O_CLOEXEC | O_NOCTTY | O_NONBLOCK);
  if (fd < 0) {
    const int err = errno;
    if (err == ENOENT) Fail("'", file.string(), "' does not exist");
    Fail("cannot read '", file.string(), "': ", ErrnoText(err));
  }
  struct FdCloser {
    int fd;
    ~FdCloser() { ::close(fd); }
  } closer{fd};
  struct stat status {};
  if (::fstat(fd, &status) != 0) Fail("cannot read '", file.string(), "': ", ErrnoText(errno));
  if (S_ISDIR(status.st_mode)) Fail("'", file.string(), "' is a folder, not a file");
  if (!S_ISREG(status.st_mode)) {
    Fail("'", file.string(), "' is not a regular file (a device, FIFO or socket); holocap reads ",
         "regular files only");
  }
  const auto declared = static_cast<uint64_t>(status.st_size);
  if (declared > max_bytes) {
    Fail("'", file.string(), "' holds ", declared, " bytes, more than the ", max_bytes,
         " such a file may have");
  }
  std::string bytes;
  bytes.reserve(declared);
  // Read to the end, not to the size stat gave: /proc files say 0, a file may grow meanwhile.
  char buffer[1 << 16];
  while (true) {
    const ssize_t n = ::read(fd, buffer, sizeof(buffer));
    if (n < 0) {
      if (errno == EINTR) continue;
      Fail("error reading '", file.string(), "': ", ErrnoText(errno));
    }
    if (n == 0) break;
    if (bytes.size() + static_cast<uint64_t>(n) > max_bytes) {
      Fail("'", file.string(), "' holds more than the ", max_bytes, " bytes such a file may have");
    }
    bytes.append(buffer, static_cast<size_t>(n));
  }
  return bytes;
}

void WriteFileAtomic(const fs::path& file, std::string_view bytes, bool durable) {
  thread_local std::mt19937_64 random{std::random_device{}()};
  fs::path temp = file;
  temp += ".tmp" + std::to_string(::getpid()) + "_" + std::to_string(random() % 1000000007);
  int fd = ::open(temp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) Fail("cannot create '", file.string(), "': ", ErrnoText(errno));
  try {
    WriteAll(fd, bytes, file);
    if (durable && ::fsync(fd) != 0) Fail("cannot sync '", file.string(), "': ", ErrnoText(errno));
  } catch (...) {
    ::close(fd);
    ::unlink(temp.c_str());
    throw;
  }
  if (::close(fd) != 0) {
    int err = errno;
    ::unlink(temp.c_str());
    Fail("cannot write '", file.string(), "': ", ErrnoText(err));
  }
  if (::rename(temp.c_str(), file.c_str()) != 0) {
    int err = errno;
    ::unlink(temp.c_str());
    Fail("cannot replace '", file.string(), "': ", ErrnoText(err));
  }
  if (durable) SyncDirectory(file.parent_path());
}

void CreateDirectories(const fs::path& dir) {
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec || !fs::is_directory(dir)) {
    Fail("cannot create directory '", dir.string(),
         "': ", ec ? ec.message() : std::string("a file is in the way"));
  }
  if (::access(dir.c_str(), W_OK) != 0) Fail("directory '", dir.string(), "' is not writable");
}

LineAppender::LineAppender(const fs::path& file, bool durable) : durable_(durable), file_(file) {
  fd_ = ::open(file.c_str(), O_WRONLY | O_CREAT | O_APPEND | O_CLOEXEC, 0644);
  if (fd_ < 0) Fail("cannot open '", file.string(), "' for appending: ", ErrnoText(errno));
}

LineAppender::~LineAppender() { Close(); }

LineAppender::LineAppender(LineAppender&& other) noexcept
    : fd_(other.fd_), durable_(other.durable_), file_(std::move(other.file_)) {
  other.fd_ = -1;
}

LineAppender& LineAppender::operator=(LineAppender&& other) noexcept {
  if (this != &other) {
    Close();
    fd_ = other.fd_;
    durable_ = other.durable_;
    file_ = std::move(other.file_);
    other.fd_ = -1;
  }
  return *this;
}

void LineAppender::Append(std::string_view line) {
  if (fd_ < 0) Fail("'", file_.string(), "' is closed");
  std::string buffer;
  buffer.reserve(line.size() + 1);
  buffer.append(line);
  buffer.push_back('\n');
  // One write(2) per line: with O_APPEND a killed process leaves whole lines or one torn tail.
  WriteAll(fd_, buffer, file_);
  if (durable_ && ::fdatasync(fd_) != 0) {
    Fail("cannot sync '", file_.string(), "': ", ErrnoText(errno));
  }
}

void LineAppender::Close() {
  if (fd_ >= 0) {
    ::close(fd_);
    fd_ = -1;
  }
}

}  // namespace holocap
