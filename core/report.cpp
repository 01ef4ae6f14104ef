#include "core/report.h"

#include "core/error.h"
#include "core/fs.h"

namespace holocap {

const char* ToString(Termination termination) {
  switch (termination) {
    case Termination::kSuccess:
      return "SUCCESS";
    case Termination::kConvergence:
      return "CONVERGENCE";
    case Termination::kNoConvergence:
      return "NO_CONVERGENCE";
    case Termination::kDegenerate:
      return "DEGENERATE";
    case Termination::kFailure:
      return "FAILURE";
  }
  return "?";
}

bool IsUsable(Termination termination) {
  return termination == Termination::kSuccess || termination == Termination::kConvergence ||
         termination == Termination::kNoConvergence;
}

int ExitStatus(Termination termination) { return IsUsable(termination) ? 0 : 1; }

namespace {

struct PendingReport {
  std::filesystem::path file;
  nlohmann::json json;
};
std::mutex pending_mutex;
std::vector<PendingReport>& PendingReports() {
  static std::vector<PendingReport> pending;
  return pending;
}

}  // namespace

Report::Report(std::string command)
    : exceptions_at_start_(std::uncaught_exceptions()), start_(std::chrono::steady_clock::now()) {
  json_["command"] = std::move(command);
  json_["options"] = nlohmann::json::object();
  json_["plan"] = nlohmann::json::object();
  json_["summary"] = {{"termination", ToString(Termination::kFailure)},
                      {"message", "did not finish"}};
  json_["metrics"] = nlohmann::json::object();
  json_["series"] = nlohmann::json::array();
}

void Report::SetSummary(const Summary& summary) {
  std::lock_guard lock(mutex_);
  json_["summary"] = {{"termination", ToString(summary.termination)}, {"message", summary.message}};
}

double Report::ElapsedSeconds() const {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
}

void Report::AddPoint(const std::string& metric, double value, int64_t iter) {
  AddPointAt(metric, value, iter, ElapsedSeconds());
}

void Report::AddPointAt(const std::string& metric, double value, int64_t iter, double t) {
  std::lock_guard lock(mutex_);
  json_["series"].push_back({{"t_s", t}, {"iter", iter}, {"metric", metric}, {"value", value}});
}

nlohmann::json ParseReport(const std::string& text, const std::string& origin) {
  nlohmann::json json = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (json.is_discarded() || !json.is_object()) Fail("'", origin, "' is not valid JSON");
  if (!json.contains("command") || !json.contains("summary")) {
    Fail("'", origin, "' is not a holocap report (no command or summary)");
  }
  const auto string_or_absent = [](const nlohmann::json& object, const char* key) {
    return !object.is_object() || !object.contains(key) || object[key].is_string();
  };
  if (!json["command"].is_string() || !json["summary"].is_object() ||
      !string_or_absent(json["summary"], "termination") ||
      !string_or_absent(json["summary"], "message") ||
      (json.contains("elapsed_s") && !json["elapsed_s"].is_number())) {
    Fail("'", origin,
         "' is not a holocap report: its command, termination or message is no string, its "
         "summary no object or its elapsed_s no number");
  }
  return json;
}

std::filesystem::path ReportDestination(const std::filesystem::path& file,
                                        const nlohmann::json& report) {
  const auto usable = [](const nlohmann::json& json) {
    if (!json.is_object() || !json.contains("summary") || !json["summary"].is_object())
      return false;
    const std::string state = json["summary"].value("termination", "");
    for (Termination t :
         {Termination::kSuccess, Termination::kConvergence, Termination::kNoConvergence})
      if (state == ToString(t)) return true;
    return false;
  };
  if (usable(report)) return file;
  std::error_code ec;
  if (!std::filesystem::is_regular_file(file, ec)) return file;
  nlohmann::json previous;
  try {
    previous = nlohmann::json::parse(ReadFileToString(file), nullptr, false);
  } catch (const Error&) {
    return file;
  }
  if (!usable(previous)) return file;
  std::filesystem::path beside = file;
  beside.replace_extension(".failed.json");
  return beside;
}

std::filesystem::path Report::Write(const std::filesystem::path& file) const {
  std::string text;
  std::filesystem::path destination;
  {
    std::lock_guard lock(mutex_);
    nlohmann::json copy = json_;
    copy["elapsed_s"] = ElapsedSeconds();
    text = copy.dump(2, ' ', false, nlohmann::json::error_handler_t::replace) + "\n";
    destination = ReportDestination(file, copy);
  }
  if (destination.has_parent_path()) CreateDirectories(destination.parent_path());
  WriteFileAtomic(destination, text);
  written_ = true;
  return destination;
}

Report::~Report() {
  if (failure_file_.empty() || written_ || std::uncaught_exceptions() <= exceptions_at_start_)
    return;
  try {
    std::lock_guard lock(mutex_);
    nlohmann::json copy = json_;
    copy["elapsed_s"] = ElapsedSeconds();
    std::lock_guard pending_lock(pending_mutex);
    PendingReports().push_back({failure_file_, std::move(copy)});
  } catch (...) {
    // Out of memory while unwinding: the error line still says what happened.
  }
}

std::vector<std::filesystem::path> WritePendingFailureReports(const std::string& message) {
  std::vector<PendingReport> pending;
  {
    std::lock_guard lock(pending_mutex);
    pending.swap(PendingReports());
  }
  std::vector<std::filesystem::path> written;
  for (auto& report : pending) {
    report.json["summary"] = {{"termination", ToString(Termination::kFailure)},
                              {"message", message}};
    try {
      const std::filesystem::path destination = ReportDestination(report.file, report.json);
      WriteFileAtomic(
          destination,
          report.json.dump(2, ' ', false, nlohmann::json::error_handler_t::replace) + "\n");
      written.push_back(destination);
    } catch (...) {
      // A full disk or a vanished folder: the error line is all there is.
    }
  }
  return written;
}

}  // namespace holocap
