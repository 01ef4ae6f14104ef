#include "avatar/avatar.h"

#include "avatar/model_training.h"
#include "core/error.h"
#include "core/frame_tasks.h"
#include "core/fs.h"
#include "core/report.h"

namespace holocap {

AvatarKindRegistry& AvatarKindRegistry::Global() {
  static AvatarKindRegistry registry;
  return registry;
}

void AvatarKindRegistry::Register(AvatarKind kind) {
  if (kind.method.empty() || !kind.open) Fail("an avatar kind needs a method name and an opener");
  std::lock_guard lock(mutex_);
  kinds_[kind.method] = std::move(kind);
}

bool AvatarKindRegistry::has(const std::string& method) const {
  std::lock_guard lock(mutex_);
  return kinds_.count(method) > 0;
}

std::vector<std::string> AvatarKindRegistry::methods() const {
  std::lock_guard lock(mutex_);
  std::vector<std::string> methods;
  for (const auto& [method, kind] : kinds_) methods.push_back(method);
  return methods;
}

std::unique_ptr<AvatarModel> AvatarKindRegistry::Open(const std::filesystem::path& dir) const {
  const auto file = dir / "model.json";
  if (!std::filesystem::exists(file)) Fail("no model in ", dir.string(), ": model.json is missing");
  nlohmann::json json;
  try {
    json = nlohmann::json::parse(ReadFileToString(file));
  } catch (const nlohmann::json::exception& e) {
    Fail(file.string(), " is not valid JSON: ", e.what());
  }
  if (!json.contains("method") || !json["method"].is_string())
    Fail(file.string(), " names no \"method\"");
  const std::string method = json["method"].get<std::string>();
  ModelOpener open;
  {
    std::lock_guard lock(mutex_);
    auto it = kinds_.find(method);
    if (it != kinds_.end()) open = it->second.open;
  }
  if (!open) {
    std::string known;
    for (const auto& kind : methods()) known += (known.empty() ? "" : ", ") + kind;
    Fail(file.string(), ": unknown model method '", method, "' (known: ", known, ")");
  }
  return open(dir, json);
}

std::unique_ptr<AvatarModel> OpenModel(const std::filesystem::path& dir) {
  return AvatarKindRegistry::Global().Open(dir);
}

std::string ModelTraining::Describe() const {
  if (!reported) return "no report.json";
  return Cat(ToString(termination), ": ", message);
}

ModelTraining ReadModelTraining(const std::filesystem::path& dir) {
  ModelTraining training;
  // A per-frame run (train splat --segment-frames) is finished once every frame's record is:
  // its report.json is merged only then, and one from an earlier run may stand beside it.
  if (std::filesystem::is_regular_file(dir / "run.json")) {
    const RunState run = ReadRunState(dir);
    if (!run.done()) {
      training.reported = true;
      training.termination = Termination::kFailure;
      training.message = "the run is incomplete: " + run.Describe();
      return training;
    }
  }
  const std::filesystem::path file = dir / "report.json";
  if (!std::filesystem::is_regular_file(file)) return training;
  const nlohmann::json report = ParseReport(ReadFileToString(file), file.string());
  training.reported = true;
  training.message = report["summary"]["message"].get<std::string>();
  const std::string state = report["summary"]["termination"].get<std::string>();
  for (Termination t : {Termination::kSuccess, Termination::kConvergence,
                        Termination::kNoConvergence, Termination::kDegenerate}) {
    if (state == ToString(t)) training.termination = t;
  }
  // A later run into the same folder that did not end usable leaves the good report.json and
  // writes its own beside it (report.failed.json); once it rewrote the model, the report no
  // longer describes the model.json that is there.
  const std::filesystem::path model = dir / "model.json";
  std::error_code ec;
  if (IsUsable(training.termination) && std::filesystem::is_regular_file(model, ec) &&
      std::filesystem::last_write_time(model, ec) > std::filesystem::last_write_time(file, ec)) {
    const std::filesystem::path failed = dir / "report.failed.json";
    std::string later = "which left no report";
    if (std::filesystem::is_regular_file(failed, ec)) {
      const nlohmann::json newer = ParseReport(ReadFileToString(failed), failed.string());
      later = Cat("whose report.failed.json says ", newer["summary"].value("termination", "?"),
                  ": ", newer["summary"].value("message", ""));
    }
    training.termination = Termination::kFailure;
    training.message = Cat("its model.json was written after report.json, by a later run ", later);
  }
  return training;
}

std::string RequireFinishedModel(const std::filesystem::path& dir, bool allow_partial,
                                 const std::string& flag) {
  const ModelTraining training = ReadModelTraining(dir);
  if (training.finished()) return "";
  if (!allow_partial) {
    Fail("the model in ", dir.string(),
         " is not a finished training: ", training.reported ? "its report.json says " : "",
         training.Describe(), " (", flag, " uses it as it is)");
  }
  return Cat("the model in ", dir.string(), " is used as it is (", flag,
             "): ", training.reported ? "its training ended " : "", training.Describe());
}

}  // namespace holocap
