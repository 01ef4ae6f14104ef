#include "core/frame_tasks.h"

#include <sys/resource.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>

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
  if (count < 1) Fail("--shard K/N needs N >= 1 (got ", count, ")");
  if (index < 0 || index >= count)
    Fail("--shard K/N needs 0 <= K < N (got ", index, "/", count, ")");
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
  for (const auto& output : (*record)["outputs"]) {
    const std::string name = output.value("file", "");
    const std::filesystem::path path = out_ / name;
    if (name.empty() || !std::filesystem::is_regular_file(path, ec))
      return fail(Cat("output '", name, "' is missing"));
    if (std::filesystem::file_size(path, ec) != output.value("bytes", uint64_t{0}))
      return fail(Cat("output '", name, "' has another size than recorded"));
    if (HashBytes(ReadFileToString(path)) != output.value("fnv1a64", ""))
      return fail(Cat("output '", name, "' has another hash than recorded"));
  }
  return record;
}

void FrameRecords::Record(int64_t set, const nlohmann::json& result,
                          const std::vector<std::string>& outputs, double started_unix_s,
                          const std::string& task) const {
  nlohmann::json files = nlohmann::json::array();
  for (const std::string& name : outputs) {
    const std::string bytes = ReadFileToString(out_ / name);
    files.push_back({{"file", name}, {"bytes", bytes.size()}, {"fnv1a64", HashBytes(bytes)}});
  }
  const nlohmann::json record = {{"format", kRunFormat},
                                 {"command", command_},
                                 {"fingerprint", fingerprint_},
                                 {"set", set},
                                 {"result", result},
                                 {"outputs", files},
                                 {"started_unix_s", started_unix_s},
                                 {"finished_unix_s", UnixSeconds()},
                                 {"peak_rss_mb", PeakRssMb()},
                                 {"task", task}};
  CreateDirectories(out_ / kFrameReportsDir);
  WriteFileAtomic(FrameRecordPath(out_, set), Dump(record), /*durable=*/true);
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
         ": it is not the output of a per-frame command (reconstruct)");
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
      ++state.frames_by_task[record->value("task", "?")];
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

double UnixSeconds() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

}  // namespace holocap
