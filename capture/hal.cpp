#include "capture/hal.h"

#include "core/error.h"

namespace holocap {

DriverRegistry& DriverRegistry::Global() {
  static DriverRegistry registry;
  return registry;
}

void DriverRegistry::Register(std::unique_ptr<Driver> driver) {
  std::string scheme = driver->scheme();
  drivers_[scheme] = std::move(driver);
}

Driver& DriverRegistry::ForUri(const std::string& uri) {
  ParsedUri parsed = ParseSensorUri(uri);
  auto it = drivers_.find(parsed.scheme);
  if (it == drivers_.end()) {
    std::string known;
    for (const auto& [scheme, driver] : drivers_) known += (known.empty() ? "" : ", ") + scheme;
    Fail("unknown URI scheme '", parsed.scheme, "' in '", uri, "' (known: ", known, ")");
  }
  return *it->second;
}

std::unique_ptr<Sensor> DriverRegistry::Open(const SensorSpec& spec) {
  return ForUri(spec.uri).Open(spec);
}

std::vector<Driver*> DriverRegistry::drivers() const {
  std::vector<Driver*> list;
  for (const auto& [scheme, driver] : drivers_) list.push_back(driver.get());
  return list;
}

bool DriverRegistry::has(const std::string& scheme) const { return drivers_.count(scheme) > 0; }

ParsedUri ParseSensorUri(const std::string& uri) {
  size_t colon = uri.find(':');
  if (colon == std::string::npos || colon == 0) {
    Fail("malformed sensor URI '", uri, "' (expected scheme:device, like sim:studio8#cam0)");
  }
  for (size_t i = 0; i < colon; ++i) {
    char c = uri[i];
    if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '-' || c == '_')) {
      Fail("malformed sensor URI '", uri, "': bad character in its scheme");
    }
  }
  ParsedUri parsed;
  parsed.scheme = uri.substr(0, colon);
  std::string rest = uri.substr(colon + 1);
  size_t hash = rest.rfind('#');
  if (hash != std::string::npos) {
    parsed.fragment = rest.substr(hash + 1);
    rest = rest.substr(0, hash);
  }
  parsed.path = rest;
  return parsed;
}

}  // namespace holocap
