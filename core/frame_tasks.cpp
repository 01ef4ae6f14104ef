#include "core/frame_tasks.h"

#include <fcntl.h>
#include <sys/file.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>

#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"

namespace holocap {
namespace {

constexpr const char* kRunFile = "run.json";
constexpr const char* kRunFormat = "holocap per-frame run 1";

// Parses `text` as JSON; nothing when it is not a JSON object.
std::optional<nlohmann::json> ParseObject(const std::string& text) {
  nlohmann::json json = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (json.is_discarded() || !json.is_object()) return std::nullopt;
  return json;
}

std::string Dump(const nlohmann::json& json) {
  return json.dump(2, ' ', false, nlohmann::json::error_handler_t::replace) + "\n";
}

// Each of `names` (relative to `dir`) with its size and hash, as records and plans list them.
nlohmann::json DescribeFiles(const std::filesystem::path& dir,
                             const std::vector<std::string>& names) {
  nlohmann::json files = nlohmann::json::array();
  for (const std::string& name : names) {
    const std::string bytes = ReadFileToString(dir / name);
    files.push_back({{"file", name}, {"bytes", bytes.size()}, {"fnv1a64", HashBytes(bytes)}});
  }
  return files;
}

// Whether every file DescribeFiles listed in `files` is in `dir` with its size and hash; else
// `why` says which is not ("'NAME' is missing", "... has another size/hash than recorded").
bool FilesIntact(const std::filesystem::path& dir, const nlohmann::json& files, std::string* why) {
  std::error_code ec;
  for (const auto& file : files) {
    const std::string name = file.value("file", "");
    const std::filesystem::path path = dir / name;
    if (name.empty() || !std::filesystem::is_regular_file(path, ec)) {
      *why = Cat("'", name, "' is missing");
      return false;
    }
    if (std::filesystem::file_size(path, ec) != file.value("bytes", uint64_t{0})) {
      *why = Cat("'", name, "' has another size than recorded");
      return false;
    }
    if (HashBytes(ReadFileToString(path)) != file.value("fnv1a64", "")) {
      *why = Cat("'", name, "' has another hash than recorded");
      return false;
    }
  }
  return true;
}

bool ParseInt(const std::string& text, int* value) {
  if (text.empty() || text.size() > 9) return false;
  for (char c : text) {
    if (c < '0' || c > '9') return false;
  }
  *value = std::stoi(text);
  return true;
}

}  // namespace

Shard Shard::Parse(const std::string& text, const std::string& flag) {
  const size_t slash = text.find('/');
  Shard shard;
  if (slash == std::string::npos || !ParseInt(text.substr(0, slash), &shard.index) ||
      !ParseInt(text.substr(slash + 1), &shard.count)) {
    Fail(flag, " must be K/N (task K of N, K from 0), got '", text, "'");
  }
  shard.Check();
  return shard;
}

void Shard::Check() const {
  HOLOCAP_CHECK_OPTION_GE(count, 1, "K/N needs N >= 1");
  HOLOCAP_CHECK_OPTION_GE(index, 0, "K/N needs 0 <= K < N");
  HOLOCAP_CHECK_OPTION_LT(index, count, "K/N needs 0 <= K < N");
}

std::string Shard::ToString() const { return Cat(index, "/", count); }

std::vector<int64_t> Shard::Of(const std::vector<int64_t>& sets) const {
  const size_t n = sets.size();
  const size_t begin = n * static_cast<size_t>(index) / static_cast<size_t>(count);
  const size_t end = n * static_cast<size_t>(index + 1) / static_cast<size_t>(count);
  return {sets.begin() + static_cast<std::ptrdiff_t>(begin),
          sets.begin() + static_cast<std::ptrdiff_t>(end)};
}

void FrameTaskOptions::Check() const { shard.Check(); }

nlohmann::json FrameTaskOptions::ToJson() const {
  return {{"shard", shard.ToString()}, {"redo", redo}};
}

std::string HashBytes(std::string_view bytes) {
  uint64_t hash = 14695981039346656037ull;
  for (unsigned char c : bytes) {
    hash ^= c;
    hash *= 1099511628211ull;
  }
  char text[17];
  std::snprintf(text, sizeof(text), "%016llx", static_cast<unsigned long long>(hash));
  return text;
}

std::filesystem::path FrameRecordPath(const std::filesystem::path& out, int64_t set) {
  char name[32];
  std::snprintf(name, sizeof(name), "%06lld.json", static_cast<long long>(set));
  return out / kFrameReportsDir / name;
}

FrameRecords::FrameRecords(std::filesystem::path out, std::string command,
                           const nlohmann::json& identity, std::vector<int64_t> sets)
    : out_(std::move(out)), command_(std::move(command)), sets_(std::move(sets)) {
  fingerprint_ = HashBytes(nlohmann::json{{"command", command_}, {"identity", identity}}.dump());
}

FrameRecords FrameRecords::OfRun(std::filesystem::path out, std::string command,
                                 std::string fingerprint, std::vector<int64_t> sets) {
  FrameRecords records(std::move(out), std::move(command), nullptr, std::move(sets));
  records.fingerprint_ = std::move(fingerprint);
  return records;
}

void FrameRecords::WriteRun(const nlohmann::json& header) const {
  CreateDirectories(out_ / kFrameReportsDir);
  const nlohmann::json run = {{"format", kRunFormat},
                              {"command", command_},
                              {"fingerprint", fingerprint_},
                              {"sets", sets_},
                              {"header", header}};
  const std::filesystem::path file = out_ / kRunFile;
  std::error_code ec;
  if (std::filesystem::is_regular_file(file, ec) && ReadFileToString(file) == Dump(run)) return;
  WriteFileAtomic(file, Dump(run), /*durable=*/true);
}

std::optional<nlohmann::json> FrameRecords::Complete(int64_t set, std::string* why) const {
  auto fail = [why](std::string reason) -> std::optional<nlohmann::json> {
    if (why != nullptr) *why = std::move(reason);
    return std::nullopt;
  };
  const std::filesystem::path file = FrameRecordPath(out_, set);
  std::error_code ec;
  if (!std::filesystem::is_regular_file(file, ec)) return fail("no record");
  const auto record = ParseObject(ReadFileToString(file));
  if (!record || !record->contains("fingerprint") || !record->contains("outputs") ||
      !record->contains("result") || !(*record)["outputs"].is_array()) {
    return fail("its record is not a frame record");
  }
  if ((*record)["fingerprint"] != fingerprint_) return fail("its record is another run's");
  std::string changed;
  if (!FilesIntact(out_, (*record)["outputs"], &changed)) return fail(Cat("output ", changed));
  return record;
}

void FrameRecords::Record(int64_t set, const nlohmann::json& result,
                          const std::vector<std::string>& outputs, double started_unix_s,
                          const std::string& task) const {
  const nlohmann::json files = DescribeFiles(out_, outputs);
  const nlohmann::json record = {{"format", kRunFormat},
                                 {"command", command_},
                                 {"fingerprint", fingerprint_},
                                 {"set", set},
                                 {"result", result},
                                 {"outputs", files},
                                 {"started_unix_s", started_unix_s},
                                 {"finished_unix_s", UnixSeconds()},
                                 {"peak_rss_mb", PeakRssMb()},
                                 {"task_cpu_s", CpuSeconds()},
                                 {"task", task}};
  CreateDirectories(out_ / kFrameReportsDir);
  WriteFileAtomic(FrameRecordPath(out_, set), Dump(record), /*durable=*/true);
}

namespace {

constexpr const char* kPlanFile = "plan.json";
constexpr const char* kPlanFormat = "holocap run plan 1";

// OUT/plan/plan.json's plan (and who made it) when it is `fingerprint`'s and its files are
// intact; else nothing, and `why` says what is missing.
std::optional<nlohmann::json> ReadPlan(const std::filesystem::path& dir, const std::string& command,
                                       const std::string& fingerprint, std::string* why,
                                       std::string* made_by) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(dir / kPlanFile, ec)) {
    *why = "no plan yet";
    return std::nullopt;
  }
  const auto stored = ParseObject(ReadFileToString(dir / kPlanFile));
  if (!stored || stored->value("format", "") != kPlanFormat || !stored->contains("plan") ||
      !(*stored)["files"].is_array()) {
    *why = "plan.json is not a run plan";
    return std::nullopt;
  }
  if (stored->value("command", "") != command || stored->value("fingerprint", "") != fingerprint) {
    *why = "the plan is another run's";
    return std::nullopt;
  }
  std::string changed;
  if (!FilesIntact(dir, (*stored)["files"], &changed)) {
    *why = Cat("the plan's file ", changed);
    return std::nullopt;
  }
  *made_by = stored->value("made_by", "");
  return (*stored)["plan"];
}

// An exclusive flock(2) on `file` while it lives, waited for; released however the process ends.
class WaitedLock {
 public:
  explicit WaitedLock(const std::filesystem::path& file)
      : fd_(::open(file.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644)) {
    if (fd_ < 0) Fail("cannot open the lock '", file.string(), "': ", std::strerror(errno));
    while (::flock(fd_, LOCK_EX) != 0) {
      if (errno == EINTR) continue;
      const int error = errno;
      ::close(fd_);
      Fail("cannot lock '", file.string(), "': ", std::strerror(error));
    }
  }
  ~WaitedLock() { ::close(fd_); }
  WaitedLock(const WaitedLock&) = delete;
  WaitedLock& operator=(const WaitedLock&) = delete;

 private:
  int fd_;
};

}  // namespace

StoredPlan PlanOnce(const std::filesystem::path& out, const std::string& command,
                    const std::string& fingerprint, const std::string& task,
                    const std::function<nlohmann::json(std::vector<std::string>* files)>& make) {
  const std::filesystem::path dir = out / kPlanDir;
  StoredPlan result;
  if (auto plan = ReadPlan(dir, command, fingerprint, &result.why, &result.made_by)) {
    result.plan = std::move(*plan);
    return result;
  }
  CreateDirectories(dir);
  const WaitedLock lock(dir / ".lock");
  // Another task may have made it while this one waited.
  if (auto plan = ReadPlan(dir, command, fingerprint, &result.why, &result.made_by)) {
    result.plan = std::move(*plan);
    return result;
  }
  std::vector<std::string> files;
  const double cpu_s = CpuSeconds();
  result.plan = make(&files);
  result.made = true;
  result.made_by = task;
  const nlohmann::json stored = {{"format", kPlanFormat},
                                 {"command", command},
                                 {"fingerprint", fingerprint},
                                 {"plan", result.plan},
                                 {"files", DescribeFiles(dir, files)},
                                 {"made_by", task},
                                 {"made_cpu_s", CpuSeconds() - cpu_s},
                                 {"made_unix_s", UnixSeconds()}};
  WriteFileAtomic(dir / kPlanFile, Dump(stored), /*durable=*/true);
  return result;
}

std::string RunState::Describe(size_t shown) const {
  std::string text = Cat(complete.size(), " of ", sets.size(), " frame sets complete");
  if (incomplete.empty()) return text;
  text += "; incomplete: ";
  size_t listed = 0;
  for (const auto& [set, why] : incomplete) {
    if (listed == shown) {
      text += Cat(", ... (", incomplete.size() - shown, " more)");
      break;
    }
    text += Cat(listed++ == 0 ? "" : ", ", set, " (", why, ")");
  }
  return text;
}

RunState ReadRunState(const std::filesystem::path& out) {
  const std::filesystem::path file = out / kRunFile;
  std::error_code ec;
  if (!std::filesystem::is_regular_file(file, ec)) {
    Fail("'", out.string(), "' holds no ", kRunFile,
         ": it is not the output of a per-frame command (reconstruct, train splat "
         "--segment-frames, export web)");
  }
  const auto run = ParseObject(ReadFileToString(file));
  if (!run || run->value("format", "") != kRunFormat || !(*run)["sets"].is_array())
    Fail("'", file.string(), "' is not a holocap run description");
  RunState state;
  state.out = out;
  state.command = (*run)["command"].get<std::string>();
  state.fingerprint = (*run)["fingerprint"].get<std::string>();
  state.sets = (*run)["sets"].get<std::vector<int64_t>>();
  state.header = (*run)["header"];
  const FrameRecords run_records =
      FrameRecords::OfRun(out, state.command, state.fingerprint, state.sets);
  for (int64_t set : state.sets) {
    std::string why;
    if (auto record = run_records.Complete(set, &why)) {
      const std::string task = record->value("task", "?");
      ++state.frames_by_task[task];
      state.cpu_s_by_task[task] =
          std::max(state.cpu_s_by_task[task], record->value("task_cpu_s", 0.0));
      state.complete[set] = std::move(*record);
    } else {
      state.incomplete[set] = why;
    }
  }
  return state;
}

std::string DescribeTask(const Shard& shard) {
  char host[256] = {};
  if (::gethostname(host, sizeof(host) - 1) != 0) host[0] = '\0';
  std::string text = Cat("shard ", shard.ToString(), ", host ", host, ", pid ", ::getpid());
  const char* job = std::getenv("SLURM_ARRAY_JOB_ID");
  const char* task = std::getenv("SLURM_ARRAY_TASK_ID");
  if (job != nullptr && task != nullptr) text += Cat(", Slurm job ", job, "_", task);
  return text;
}

std::filesystem::path TaskReportPath(const std::filesystem::path& out, const Shard& shard) {
  if (shard.whole()) return out / "report.json";
  return out / "tasks" / Cat("shard-", shard.index, "-of-", shard.count) / "report.json";
}

double PeakRssMb() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return usage.ru_maxrss / 1024.0;
}

double CpuSeconds() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  const auto seconds = [](const timeval& t) { return t.tv_sec + 1e-6 * t.tv_usec; };
  return seconds(usage.ru_utime) + seconds(usage.ru_stime);
}

double UnixSeconds() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

}  // namespace holocap
