#include "core/rig.h"

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <set>

#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"

namespace holocap {
namespace {

// Whether `text` is UTF-8 as RFC 3629 defines it (no overlong forms, no surrogates).
bool IsUtf8(const std::string& text) {
  for (size_t i = 0; i < text.size();) {
    const auto byte = [&](size_t k) { return static_cast<unsigned char>(text[k]); };
    unsigned char lead = byte(i);
    size_t length = lead < 0x80   ? 1
                    : lead < 0xC2 ? 0
                    : lead < 0xE0 ? 2
                    : lead < 0xF0 ? 3
                    : lead < 0xF5 ? 4
                                  : 0;
    if (length == 0 || i + length > text.size()) return false;
    unsigned char low = 0x80, high = 0xBF;  // the second byte's range
    if (lead == 0xE0) low = 0xA0;
    if (lead == 0xED) high = 0x9F;
    if (lead == 0xF0) low = 0x90;
    if (lead == 0xF4) high = 0x8F;
    if (length > 1 && (byte(i + 1) < low || byte(i + 1) > high)) return false;
    for (size_t k = 2; k < length; ++k) {
      if (byte(i + k) < 0x80 || byte(i + k) > 0xBF) return false;
    }
    i += length;
  }
  return true;
}

// yaml-cpp passes any bytes through, but a rig's strings go into take.json, which is UTF-8.
const std::string& Utf8Scalar(const YAML::Node& node) {
  if (!IsUtf8(node.Scalar()))
    throw YAML::ParserException(node.Mark(), "a string that is not UTF-8 (take.json needs UTF-8)");
  return node.Scalar();
}

// The most values a rig's YAML may expand to. yaml-cpp keeps an alias as one shared node, but
// copying it into JSON expands it: nested aliases ("billion laughs") would take gigabytes. A
// rig of a thousand sensors is some ten thousand values.
constexpr int64_t kMaxRigYamlValues = 200'000;

nlohmann::json JsonFromYaml(const YAML::Node& node, int64_t* budget) {
  if (--*budget < 0) {
    throw YAML::ParserException(node.Mark(), Cat("it expands to more than ", kMaxRigYamlValues,
                                                 " values (aliases nested in aliases?)"));
  }
  switch (node.Type()) {
    case YAML::NodeType::Null:
    case YAML::NodeType::Undefined:
      return nullptr;
    case YAML::NodeType::Sequence: {
      nlohmann::json array = nlohmann::json::array();
      for (const auto& item : node) array.push_back(JsonFromYaml(item, budget));
      return array;
    }
    case YAML::NodeType::Map: {
      nlohmann::json object = nlohmann::json::object();
      for (const auto& item : node)
        object[item.first.IsScalar() ? Utf8Scalar(item.first) : item.first.as<std::string>()] =
            JsonFromYaml(item.second, budget);
      return object;
    }
    case YAML::NodeType::Scalar: {
      const std::string& text = Utf8Scalar(node);
      if (node.Tag() == "!") return text;  // quoted in the file: keep as a string
      bool boolean;
      if (YAML::convert<bool>::decode(node, boolean) &&
          (text == "true" || text == "false" || text == "True" || text == "False")) {
        return boolean;
      }
      try {
        size_t used = 0;
        long long integer = std::stoll(text, &used);
        if (used == text.size()) return integer;
      } catch (...) {
      }
      try {
        size_t used = 0;
        double number = std::stod(text, &used);
        if (used == text.size()) return number;
      } catch (...) {
      }
      return text;
    }
  }
  return nullptr;
}

template <typename T>
T Field(const nlohmann::json& object, const char* key, const T& fallback,
        const std::string& where) {
  if (!object.contains(key) || object[key].is_null()) return fallback;
  try {
    return object[key].get<T>();
  } catch (const nlohmann::json::exception&) {
    Fail(where, ": field '", key, "' has the wrong type (", object[key].dump(), ")");
  }
}

}  // namespace

const char* ToString(SensorRole role) {
  switch (role) {
    case SensorRole::kColor:
      return "color";
    case SensorRole::kDepth:
      return "depth";
    case SensorRole::kWitness:
      return "witness";
  }
  return "?";
}

const char* ToString(SyncMode mode) {
  switch (mode) {
    case SyncMode::kHardwareTrigger:
      return "hardware";
    case SyncMode::kSoftwareTrigger:
      return "software";
    case SyncMode::kFreeRun:
      return "free-run";
  }
  return "?";
}

SensorRole SensorRoleFromString(const std::string& text) {
  if (text == "color" || text == "colour") return SensorRole::kColor;
  if (text == "depth") return SensorRole::kDepth;
  if (text == "witness") return SensorRole::kWitness;
  Fail("unknown sensor role '", text, "' (color, depth or witness)");
}

SyncMode SyncModeFromString(const std::string& text) {
  if (text == "hardware" || text == "hardware-trigger") return SyncMode::kHardwareTrigger;
  if (text == "software" || text == "software-trigger") return SyncMode::kSoftwareTrigger;
  if (text == "free-run" || text == "freerun") return SyncMode::kFreeRun;
  Fail("unknown sync mode '", text, "' (hardware, software or free-run)");
}

std::string SensorSpec::scheme() const {
  size_t colon = uri.find(':');
  return colon == std::string::npos ? std::string() : uri.substr(0, colon);
}

RigDescription RigDescription::FromJson(const nlohmann::json& json, const std::string& origin) {
  if (!json.is_object()) Fail(origin, ": a rig description must be a mapping");
  RigDescription rig;
  rig.name = Field<std::string>(json, "name", rig.name, origin);
  try {
    rig.sync = SyncModeFromString(Field<std::string>(json, "sync", ToString(rig.sync), origin));
  } catch (const Error& e) {
    Fail(origin, ": ", e.what());
  }
  rig.fps = Field<double>(json, "fps", rig.fps, origin);
  if (json.contains("options") && json["options"].is_object()) rig.options = json["options"];
  if (json.contains("hosts")) {
    if (!json["hosts"].is_object()) Fail(origin, ": 'hosts' must map host names to addresses");
    for (const auto& [host, address] : json["hosts"].items()) {
      if (!address.is_string()) Fail(origin, ": hosts: '", host, "' must be an address string");
      rig.hosts[host] = address.get<std::string>();
    }
  }
  if (!json.contains("sensors") || !json["sensors"].is_array()) {
    Fail(origin, ": 'sensors' must be a list of sensors");
  }
  int index = 0;
  for (const auto& item : json["sensors"]) {
    std::string where = origin + ": sensors[" + std::to_string(index++) + "]";
    if (!item.is_object()) Fail(where, " must be a mapping");
    SensorSpec spec;
    spec.name = Field<std::string>(item, "name", "", where);
    spec.uri = Field<std::string>(item, "uri", "", where);
    if (spec.name.empty()) Fail(where, ": 'name' is missing");
    if (spec.uri.empty()) Fail(where, " (", spec.name, "): 'uri' is missing");
    try {
      spec.role = SensorRoleFromString(Field<std::string>(item, "role", "color", where));
    } catch (const Error& e) {
      Fail(where, " (", spec.name, "): ", e.what());
    }
    spec.exposure_us = Field<double>(item, "exposure_us", 0.0, where);
    spec.gain_db = Field<double>(item, "gain_db", 0.0, where);
    spec.paired_with = Field<std::string>(item, "paired_with", "", where);
    spec.host = Field<std::string>(item, "host", "", where);
    if (item.contains("options")) {
      if (!item["options"].is_object()) Fail(where, ": 'options' must be a mapping");
      spec.options = item["options"];
    }
    rig.sensors.push_back(std::move(spec));
  }
  try {
    rig.Check();
  } catch (const Error& e) {
    Fail(origin, ": ", e.what());
  }
  return rig;
}

RigDescription RigDescription::Load(const std::filesystem::path& file) {
  std::string text = ReadFileToString(file);
  if (file.extension() == ".json") return ParseJson(text, file.string());
  return ParseYaml(text, file.string());
}

RigDescription RigDescription::ParseYaml(const std::string& text, const std::string& origin) {
  nlohmann::json json;
  try {
    int64_t budget = kMaxRigYamlValues;
    json = JsonFromYaml(YAML::Load(text), &budget);
  } catch (const YAML::Exception& e) {
    Fail("'", origin, "' is not valid YAML: line ", e.mark.line + 1, ": ", e.msg);
  }
  return FromJson(json, origin);
}

RigDescription RigDescription::ParseJson(const std::string& text, const std::string& origin) {
  nlohmann::json json;
  try {
    json = nlohmann::json::parse(text);
  } catch (const nlohmann::json::exception& e) {
    Fail("'", origin, "' is not valid JSON: ", e.what());
  }
  return FromJson(json, origin);
}

nlohmann::json RigDescription::ToJson() const {
  nlohmann::json json;
  json["name"] = name;
  json["sync"] = ToString(sync);
  json["fps"] = fps;
  if (!options.empty()) json["options"] = options;
  if (!hosts.empty()) json["hosts"] = hosts;
  json["sensors"] = nlohmann::json::array();
  for (const auto& spec : sensors) {
    nlohmann::json item;
    item["name"] = spec.name;
    item["uri"] = spec.uri;
    item["role"] = ToString(spec.role);
    if (spec.exposure_us != 0) item["exposure_us"] = spec.exposure_us;
    if (spec.gain_db != 0) item["gain_db"] = spec.gain_db;
    if (!spec.paired_with.empty()) item["paired_with"] = spec.paired_with;
    if (!spec.options.empty()) item["options"] = spec.options;
    if (!spec.host.empty()) item["host"] = spec.host;
    json["sensors"].push_back(item);
  }
  return json;
}

namespace {
std::string HostList(const std::map<std::string, std::string>& hosts) {
  std::string list;
  for (const auto& [host, address] : hosts) list += (list.empty() ? "" : ", ") + host;
  return list.empty() ? "none" : list;
}
}  // namespace

void RigDescription::Check() const {
  HOLOCAP_CHECK_OPTION_GT(fps, 0);
  HOLOCAP_CHECK_OPTION_LE(fps, 10000);
  HOLOCAP_CHECK_OPTION(!sensors.empty(), sensors, "the rig has no sensors");
  // A sensor's name is a folder of the take (frames/NAME): no separator, no "." or "..", no
  // control character.
  const auto is_plain_name = [](const std::string& name) {
    return name.find_first_of("/\\ \t#") == std::string::npos && name != "." && name != ".." &&
           std::none_of(name.begin(), name.end(),
                        [](char c) { return static_cast<unsigned char>(c) < 0x20 || c == 0x7f; });
  };
  std::set<std::string> names;
  for (const auto& spec : sensors) {
    HOLOCAP_CHECK_OPTION(
        is_plain_name(spec.name), sensors,
        Cat("sensor name '", spec.name,
            "' may not be '.' or '..' or contain '/', '\\', '#', spaces or control characters"));
    HOLOCAP_CHECK_OPTION(names.count(spec.name) == 0, sensors,
                         Cat("sensor name '", spec.name, "' appears twice"));
    names.insert(spec.name);
    HOLOCAP_CHECK_OPTION(
        !spec.scheme().empty(), sensors,
        Cat("sensor '", spec.name, "': URI '", spec.uri, "' has no scheme (like sim: or aravis:)"));
  }
  for (const auto& spec : sensors) {
    HOLOCAP_CHECK_OPTION(spec.paired_with.empty() || names.count(spec.paired_with) > 0, sensors,
                         Cat("sensor '", spec.name, "' is paired with '", spec.paired_with,
                             "', which is not in the rig"));
    HOLOCAP_CHECK_OPTION(
        hosts.empty() || !spec.host.empty(), sensors,
        Cat("sensor '", spec.name, "' names no host (the rig's hosts: ", HostList(hosts), ")"));
    HOLOCAP_CHECK_OPTION(spec.host.empty() || hosts.count(spec.host) > 0, hosts,
                         Cat("sensor '", spec.name, "': host '", spec.host,
                             "' is not in the rig's hosts (", HostList(hosts), ")"));
  }
  for (const auto& [host, address] : hosts) {
    HOLOCAP_CHECK_OPTION(
        !host.empty() && is_plain_name(host), hosts,
        Cat("host name '", host,
            "' may not be empty, '.' or '..' or contain '/', '\\', '#', spaces or control "
            "characters"));
  }
}

const SensorSpec& RigDescription::sensor(const std::string& sensor_name) const {
  int i = IndexOf(sensor_name);
  if (i < 0) Fail("the rig has no sensor named '", sensor_name, "'");
  return sensors[i];
}

int RigDescription::IndexOf(const std::string& sensor_name) const {
  for (size_t i = 0; i < sensors.size(); ++i) {
    if (sensors[i].name == sensor_name) return static_cast<int>(i);
  }
  return -1;
}

bool RigDescription::HasRole(SensorRole role) const {
  for (const auto& spec : sensors) {
    if (spec.role == role) return true;
  }
  return false;
}

}  // namespace holocap
