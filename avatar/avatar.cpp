#include "avatar/avatar.h"

#include "core/error.h"
#include "core/fs.h"

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

}  // namespace holocap
