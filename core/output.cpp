#include "core/output.h"

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <map>
#include <mutex>
#include <nlohmann/json.hpp>

#include "core/error.h"
#include "core/fs.h"

namespace holocap {
namespace {

// Absolute, with symbolic links and ".." resolved as far as the path exists.
fs::path Canonical(const fs::path& path) {
  std::error_code ec;
  fs::path absolute = fs::absolute(path, ec);
  if (ec) Fail("cannot resolve '", path.string(), "': ", ec.message());
  fs::path canonical = fs::weakly_canonical(absolute, ec);
  return ec ? absolute.lexically_normal() : canonical;
}

// Whether `path` is `root` or lies below it (both canonical).
bool IsAtOrUnder(const fs::path& path, const fs::path& root) {
  auto p = path.begin();
  for (auto r = root.begin(); r != root.end(); ++r, ++p) {
    if (r->empty()) continue;  // a trailing separator
    if (p == path.end() || *p != *r) return false;
  }
  return true;
}

bool IsTakeDirectory(const fs::path& dir) {
  std::error_code ec;
  return fs::is_regular_file(dir / "take.json", ec);
}

// The part of take `take` that `path` lies in when it is recorded data ("" otherwise): the
// frames, ground truth, calibration, manifest, index and the take's own report.
std::string RecordedPart(const fs::path& path, const fs::path& take) {
  const fs::path relative = path.lexically_relative(take);
  if (relative.empty() || *relative.begin() == "." || *relative.begin() == "..") return "";
  const std::string first = relative.begin()->string();
  for (const char* part : {"frames", "gt", "calib", "take.json", "index.jsonl", "report.json"}) {
    if (first == part) return first;
  }
  return "";
}

void RefuseRecordedData(const fs::path& shown, const fs::path& canonical) {
  const auto take = EnclosingTake(canonical);
  if (!take) return;
  const std::string part = RecordedPart(canonical, *take);
  if (!part.empty()) {
    Fail("'", shown.string(), "' is part of the recorded take '", take->string(), "' (", part,
         "); no command writes there: give an output outside the take's recording, e.g. '",
         (*take / "renders").string(), "'");
  }
}

void RefuseInputsUnder(const fs::path& shown, const fs::path& canonical,
                       const OutputRequest& request) {
  for (const auto& input : request.inputs) {
    if (input.empty()) continue;
    if (IsAtOrUnder(Canonical(input), canonical)) {
      Fail("'", shown.string(), "' holds the input '", input.string(), "' of holocap ",
           request.command,
           "; choose an output apart from it (--overwrite never removes an input)");
    }
  }
}

// Empty, or holding nothing but another process's marker still being written (its temporary
// file, renamed into place in a moment): the tasks of a sharded run claim the same new folder
// at the same time.
bool EmptyButForMarkerBeingWritten(const fs::path& dir) {
  const std::string temporary = std::string(kOutputMarkerFile) + ".tmp";
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(dir, ec)) {
    const std::string name = entry.path().filename().string();
    if (name.rfind(temporary, 0) != 0 && name != kTakeLockFile) return false;
  }
  return !ec;
}

// An output's marker: the command that made it, then (since markers name it) "source PATH".
struct Marker {
  std::string command;
  std::string source;  // "" in a marker that names none
};

Marker ReadMarker(const fs::path& dir) {
  std::error_code ec;
  if (!fs::is_regular_file(dir / kOutputMarkerFile, ec)) return {};
  const std::string text = ReadFileToString(dir / kOutputMarkerFile, 1 << 16);
  Marker marker;
  size_t start = 0;
  for (int line = 0; start < text.size(); ++line) {
    size_t end = text.find('\n', start);
    if (end == std::string::npos) end = text.size();
    std::string content = text.substr(start, end - start);
    while (!content.empty() && content.back() == ' ') content.pop_back();
    if (line == 0) {
      marker.command = content;
    } else if (content.rfind("source ", 0) == 0) {
      marker.source = content.substr(7);
    }
    start = end + 1;
  }
  return marker;
}

std::string MarkerText(const OutputRequest& request) {
  std::string text = request.command + "\n";
  if (!request.source.empty()) text += "source " + Canonical(request.source).string() + "\n";
  return text;
}

// Refuses a path that names a place inside a take but leads, through a symbolic link, out of it
// (into another take or anywhere else): the claim is made where the path leads.
void RefuseLinkOutOfItsTake(const fs::path& shown, const fs::path& canonical) {
  std::error_code ec;
  const fs::path lexical = fs::absolute(shown, ec).lexically_normal();
  if (ec) return;
  // The nearest take above the path as written, found without following the final parts.
  fs::path dir = lexical.parent_path();
  while (true) {
    if (IsTakeDirectory(dir)) break;
    if (!dir.has_parent_path() || dir.parent_path() == dir) return;
    dir = dir.parent_path();
  }
  const fs::path take = Canonical(dir);
  if (!IsAtOrUnder(canonical, take)) {
    Fail("'", shown.string(), "' lies in the take '", dir.string(),
         "' but a symbolic link leads it to '", canonical.string(),
         "', outside that take; give the folder it leads to, or a folder that is no link");
  }
}

// This process's command line, as one printable line.
std::string OwnCommandLine() {
  std::string text;
  try {
    text = ReadFileToString("/proc/self/cmdline");
  } catch (const Error&) {
    return "";
  }
  while (!text.empty() && text.back() == '\0') text.pop_back();
  for (char& c : text) {
    if (c == '\0') c = ' ';
    if (static_cast<unsigned char>(c) < 0x20 || c == 0x7f) c = '?';
  }
  return text.size() > 300 ? text.substr(0, 300) + "..." : text;
}

// flock(2) locks belong to an open file: the takes this process holds are counted here, so that
// a command that claims two outputs in one take (the demo) does not lock itself out.
struct HeldLock {
  int fd = -1;
  int count = 0;
};
std::mutex held_mutex;
std::map<int, std::string>& LockKeys() {
  static std::map<int, std::string> keys;  // handle -> take
  return keys;
}
std::map<std::string, HeldLock>& HeldLocks() {
  static std::map<std::string, HeldLock> held;
  return held;
}
int next_handle = 0;

}  // namespace

std::optional<fs::path> EnclosingTake(const fs::path& path) {
  fs::path dir = Canonical(path);
  while (true) {
    if (IsTakeDirectory(dir)) return dir;
    if (!dir.has_parent_path() || dir.parent_path() == dir) return std::nullopt;
    dir = dir.parent_path();
  }
}

TakeLock TakeLock::Acquire(const fs::path& take, const std::string& command, bool shared) {
  const std::string key = Canonical(take).string();
  std::error_code ec;
  if (!fs::is_directory(key, ec)) Fail("take '", take.string(), "' does not exist");
  std::lock_guard guard(held_mutex);
  HeldLock& held = HeldLocks()[key];
  if (held.count == 0) {
    const fs::path file = fs::path(key) / kTakeLockFile;
    const int fd = ::open(file.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
    if (fd < 0) {
      HeldLocks().erase(key);
      Fail("cannot lock take '", take.string(), "' (", file.string(), "): ", std::strerror(errno));
    }
    if (::flock(fd, (shared ? LOCK_SH : LOCK_EX) | LOCK_NB) != 0) {
      const int err = errno;
      std::string holder;
      try {
        holder = ReadFileToString(file);
      } catch (const Error&) {
      }
      while (!holder.empty() && holder.back() == '\n') holder.pop_back();
      ::close(fd);
      HeldLocks().erase(key);
      if (err != EWOULDBLOCK) {
        Fail("cannot lock take '", take.string(), "' (", file.string(), "): ", std::strerror(err));
      }
      const bool is_take = IsTakeDirectory(key);
      Fail(is_take ? "take '" : "'", take.string(), "' is being written by ",
           holder.empty() ? std::string("another process") : holder, "; one command writes into ",
           is_take ? "a take" : "an output", " at a time (run ", command,
           " again when it has ended)");
    }
    const std::string line = "pid " + std::to_string(::getpid()) + " (" + OwnCommandLine() + ")\n";
    if (::ftruncate(fd, 0) != 0 || ::pwrite(fd, line.data(), line.size(), 0) < 0) {
      // The lock holds without the note; the message of a second writer is the poorer for it.
    }
    held.fd = fd;
  }
  ++held.count;
  TakeLock lock;
  lock.handle_ = next_handle++;
  LockKeys()[lock.handle_] = key;
  return lock;
}

TakeLock::~TakeLock() {
  if (handle_ < 0) return;
  std::lock_guard guard(held_mutex);
  const std::string key = LockKeys()[handle_];
  LockKeys().erase(handle_);
  HeldLock& held = HeldLocks()[key];
  if (--held.count <= 0) {
    if (::ftruncate(held.fd, 0) != 0) {
      // An old note in an unlocked file names no holder: flock decides, not the note.
    }
    ::close(held.fd);  // releases the flock
    HeldLocks().erase(key);
  }
}

TakeLock::TakeLock(TakeLock&& other) noexcept : handle_(other.handle_) { other.handle_ = -1; }

TakeLock& TakeLock::operator=(TakeLock&& other) noexcept {
  if (this != &other) {
    TakeLock old(std::move(*this));
    handle_ = other.handle_;
    other.handle_ = -1;
  }
  return *this;
}

OutputDirectory OutputDirectory::Claim(const fs::path& dir, const OutputRequest& request) {
  const fs::path canonical = Canonical(dir);
  RefuseLinkOutOfItsTake(dir, canonical);
  if (IsTakeDirectory(canonical)) {
    Fail("'", dir.string(), "' is a take's directory; holocap ", request.command,
         " writes its results into a folder of their own, e.g. '", (dir / request.command).string(),
         "'");
  }
  RefuseRecordedData(dir, canonical);
  RefuseInputsUnder(dir, canonical, request);
  std::error_code ec;
  bool fresh = true, rewrite_marker = false;
  if (fs::exists(canonical, ec)) {
    if (!fs::is_directory(canonical, ec)) Fail("'", dir.string(), "' exists and is not a folder");
    if (!EmptyButForMarkerBeingWritten(canonical)) {
      fresh = false;
      const Marker marker = ReadMarker(canonical);
      if (marker.command != request.command && !request.overwrite) {
        Fail("'", dir.string(), "' is not empty and holocap ", request.command,
             " did not make it (",
             marker.command.empty() ? "no holocap output" : "holocap " + marker.command,
             "); pass --overwrite to write into it (nothing there is removed)");
      }
      const std::string source =
          request.source.empty() ? std::string() : Canonical(request.source).string();
      if (marker.command == request.command && !marker.source.empty() && !source.empty() &&
          marker.source != source) {
        if (!request.overwrite) {
          Fail("'", dir.string(), "' holds holocap ", request.command, "'s results of '",
               marker.source, "', not of '", source,
               "'; choose another folder, or pass --overwrite to write into it (its files of "
               "the same names are replaced, nothing else is removed)");
        }
        std::fprintf(stderr,
                     "holocap %s: writing into '%s', which holds results of '%s' (--overwrite: "
                     "its files of the same names are replaced)\n",
                     request.command.c_str(), dir.c_str(), marker.source.c_str());
        rewrite_marker = true;
      }
    }
  }
  OutputDirectory output;
  output.dir_ = dir;
  const auto take = EnclosingTake(canonical);
  if (take) output.lock_ = TakeLock::Acquire(*take, request.command, request.shared);
  CreateDirectories(dir);
  // Outside a take the output is its own lock's home: one writer at a time all the same.
  if (!take) output.lock_ = TakeLock::Acquire(dir, request.command, request.shared);
  if (fresh || rewrite_marker) WriteFileAtomic(dir / kOutputMarkerFile, MarkerText(request));
  return output;
}

TakeLock ClaimOutputFile(const fs::path& file, const OutputRequest& request) {
  const fs::path canonical = Canonical(file);
  RefuseRecordedData(file, canonical);
  RefuseInputsUnder(file, canonical, request);
  std::error_code ec;
  if (fs::is_directory(canonical, ec)) Fail("'", file.string(), "' is a folder, not a file");
  if (fs::exists(canonical, ec) && !request.overwrite) {
    Fail("'", file.string(), "' exists; pass --overwrite to replace it");
  }
  if (const auto take = EnclosingTake(canonical.parent_path())) {
    return TakeLock::Acquire(*take, request.command);
  }
  return {};
}

TakeLock ClaimTakeDirectory(const fs::path& dir, const OutputRequest& request) {
  const fs::path canonical = Canonical(dir);
  if (canonical.has_parent_path()) RefuseRecordedData(dir, canonical);
  RefuseInputsUnder(dir, canonical, request);
  std::error_code ec;
  if (!fs::exists(canonical, ec)) return {};
  if (!fs::is_directory(canonical, ec)) Fail("'", dir.string(), "' exists and is not a folder");
  if (fs::is_empty(canonical, ec)) return {};
  if (!request.overwrite) {
    Fail("'", dir.string(), "' is not empty (refusing to overwrite a take; --overwrite replaces ",
         "a take made by import or sim)");
  }
  if (!IsTakeDirectory(canonical)) {
    Fail("'", dir.string(), "' is not empty and holds no take; --overwrite replaces only a take");
  }
  nlohmann::json manifest;
  try {
    manifest = nlohmann::json::parse(ReadFileToString(canonical / "take.json", 64 << 20));
  } catch (const nlohmann::json::exception&) {
    Fail("'", dir.string(), "' holds a take.json that is not JSON; it is not replaced");
  }
  if (!manifest.is_object() || manifest.value("format", "") != "holocap-take") {
    Fail("'", dir.string(),
         "' holds a take.json that is not a holocap take's; it is not replaced (--overwrite "
         "replaces only a take holocap made)");
  }
  const nlohmann::json metadata = manifest.value("metadata", nlohmann::json::object());
  if (metadata.is_object() && metadata.contains("capture")) {
    Fail("'", dir.string(),
         "' holds a recording made by holocap capture; no command replaces a recording (move it "
         "away first)");
  }
  // Who made it: take.json says since it has made_by; before, sim and import marked their
  // metadata.
  std::string maker = manifest.value("made_by", "");
  if (maker.empty() && metadata.is_object()) {
    if (metadata.value("simulated", false)) maker = "sim";
    if (metadata.contains("interop")) maker = "import";
  }
  if (maker != request.command) {
    Fail("'", dir.string(), "' holds a take made by ",
         maker.empty() ? std::string("another program") : "holocap " + maker, "; holocap ",
         request.command, " --overwrite replaces only a take it made (move it away first)");
  }
  // Only what a take writer makes is replaced: results of other commands (recon/, models/) and
  // files of the user's stay, so the take is not replaced while they are there.
  std::vector<std::string> foreign;
  std::error_code listing;
  for (const auto& entry : fs::directory_iterator(canonical, listing)) {
    const std::string name = entry.path().filename().string();
    bool ours = name == kTakeLockFile;
    for (const char* part : {"frames", "gt", "calib", "take.json", "index.jsonl", "report.json"})
      ours = ours || name == part;
    if (!ours) foreign.push_back(name);
  }
  if (!foreign.empty()) {
    std::sort(foreign.begin(), foreign.end());
    std::string names;
    for (size_t i = 0; i < foreign.size() && i < 4; ++i) names += (i ? ", " : "") + foreign[i];
    if (foreign.size() > 4) names += Cat(" and ", foreign.size() - 4, " more");
    Fail("'", dir.string(), "' holds ", names, ", which holocap ", request.command,
         " did not make (results of other commands, or files of yours); --overwrite replaces a "
         "take only when it holds nothing else: move them away first");
  }
  std::fprintf(stderr,
               "holocap %s: replacing the take '%s' (made by holocap %s, %lld frame sets)\n",
               request.command.c_str(), dir.c_str(), maker.c_str(),
               static_cast<long long>(manifest.contains("frame_sets") &&
                                              manifest["frame_sets"].is_number_integer()
                                          ? manifest["frame_sets"].get<int64_t>()
                                          : 0));
  return TakeLock::Acquire(canonical, request.command);
}

}  // namespace holocap
