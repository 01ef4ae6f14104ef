// Where a command may write. Every writing command claims its output before it writes anything:
// a take's recorded data (frames/, gt/, calib/, take.json, index.jsonl) is never an output, an
// input of the same command is never under its output, a non-empty directory another command
// made is written into only with --overwrite (which removes nothing), and a take is written by
// one command at a time (an advisory lock naming its holder).
#pragma once

#include <filesystem>
#include <optional>
#include <string>
#include <vector>

namespace holocap {

struct OutputRequest {
  std::string command;                        // "render": named in messages and the lock
  bool overwrite = false;                     // --overwrite was given
  std::vector<std::filesystem::path> inputs;  // what the command reads (files or folders)
  // One task of a sharded run (--shard K/N): the take's lock is shared with the run's other
  // tasks, which write other frames into the same output; any other writer is still refused.
  bool shared = false;
  // What the output is made from (a take, a model): kept in the output's marker. An output made
  // by the same command from another source is written into only with --overwrite (a second
  // take's results never mix into the first's unasked).
  std::filesystem::path source;
};

// The take directory at or above `path` (the nearest one holding take.json), if any.
std::optional<std::filesystem::path> EnclosingTake(const std::filesystem::path& path);

// An advisory lock on TAKE/.holocap.lock (flock(2), released when the process ends however it
// ends), the file holding the holder's pid and command. Move-only; unlocks on destruction.
class TakeLock {
 public:
  TakeLock() = default;
  // Throws Error naming the holder when another process holds the take's lock. `shared`: held
  // beside other shared holders (the tasks of one sharded run), never beside an exclusive one.
  static TakeLock Acquire(const std::filesystem::path& take, const std::string& command,
                          bool shared = false);
  ~TakeLock();
  TakeLock(TakeLock&& other) noexcept;
  TakeLock& operator=(TakeLock&& other) noexcept;
  TakeLock(const TakeLock&) = delete;
  TakeLock& operator=(const TakeLock&) = delete;

  bool held() const { return handle_ >= 0; }

 private:
  int handle_ = -1;  // this process's count of the take's one lock
};

// The lock file's name inside a take.
inline constexpr const char* kTakeLockFile = ".holocap.lock";
// The file an output directory's creator leaves in it (its command's name).
inline constexpr const char* kOutputMarkerFile = ".holocap-output";

// A directory of results (reconstruct's meshes, a model, rendered frames, an export): checked
// as above, created, marked as this command's (and its source's), and locked while this object
// lives: the take holding it, or, outside a take, the directory itself (its own lock file), so
// two commands never write one output at once. A path that a symbolic link leads out of the take
// it names is refused. Throws Error with one line saying what was refused and why.
class OutputDirectory {
 public:
  static OutputDirectory Claim(const std::filesystem::path& dir, const OutputRequest& request);
  const std::filesystem::path& path() const { return dir_; }

 private:
  std::filesystem::path dir_;
  TakeLock lock_;
};

// One output file (an MP4, a board image, a report page): the same checks on the file and
// its folder; an existing file is replaced only with --overwrite. The returned lock (held when
// the file lies inside a take) must live until the file is written.
TakeLock ClaimOutputFile(const std::filesystem::path& file, const OutputRequest& request);

// A take directory about to be written (import, simulate, capture): refused inside another
// take's recorded data or where it would hold an input; an existing non-empty directory is
// replaced only with --overwrite, only when it is a take this same command made (take.json's
// made_by, or for older takes its metadata), holding nothing but what a take writer makes (no
// results of other commands, no files of the user's), and never when it is a recording made by
// `holocap capture`; what is replaced is said on stderr. Returns the lock of the take being
// replaced (if any).
TakeLock ClaimTakeDirectory(const std::filesystem::path& dir, const OutputRequest& request);

}  // namespace holocap
