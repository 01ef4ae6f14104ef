// Rig description: which sensors (by driver URI), their roles, how they are synchronised.
// Read from YAML (rig.yaml) or JSON; bad files give one clear error naming file and field.
#pragma once

#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

namespace holocap {

enum class SensorRole { kColor, kDepth, kWitness };
enum class SyncMode { kHardwareTrigger, kSoftwareTrigger, kFreeRun };

const char* ToString(SensorRole role);                     // "color", "depth", "witness"
const char* ToString(SyncMode mode);                       // "hardware", "software", "free-run"
SensorRole SensorRoleFromString(const std::string& text);  // throws Error
SyncMode SyncModeFromString(const std::string& text);      // throws Error

struct SensorSpec {
  std::string name;  // unique within the rig, e.g. "cam3"
  std::string uri;   // "sim:studio8#cam3", "aravis:Fake_1", "v4l2:/dev/video0"
  SensorRole role = SensorRole::kColor;
  double exposure_us = 0;  // 0: the driver's default or automatic exposure
  double gain_db = 0;
  std::string paired_with;  // a depth sensor's colour sensor (depth_from_color)
  nlohmann::json options = nlohmann::json::object();  // driver-specific settings
  // The capture host that records it (a key of RigDescription::hosts); "": this machine.
  std::string host;

  // The part of the URI before the first ':' ("sim", "aravis", ...).
  std::string scheme() const;
};

struct RigDescription {
  std::string name = "rig";
  SyncMode sync = SyncMode::kSoftwareTrigger;
  double fps = 30;  // frame sets per second asked of the sensors
  std::vector<SensorSpec> sensors;
  nlohmann::json options = nlohmann::json::object();  // rig-wide driver settings (e.g. sim)
  // Capture hosts by name: the control address of each `holocap capture-node`
  // ("tcp://10.0.0.2:5601"). Empty: one machine records every sensor. Otherwise every sensor
  // names its host.
  std::map<std::string, std::string> hosts;

  // Throws Error (file, field and reason) for a malformed or inconsistent description.
  static RigDescription Load(const std::filesystem::path& file);
  // Load's parsers on text; `origin` names the text in errors (Load gives the file's path).
  static RigDescription ParseYaml(const std::string& text, const std::string& origin);
  static RigDescription ParseJson(const std::string& text, const std::string& origin);
  static RigDescription FromJson(const nlohmann::json& json, const std::string& origin = "rig");
  nlohmann::json ToJson() const;
  void Check() const;  // unique names, known roles, pairings that exist, fps > 0

  const SensorSpec& sensor(const std::string& name) const;  // throws Error if absent
  int IndexOf(const std::string& name) const;               // -1 if absent
  bool HasRole(SensorRole role) const;
};

}  // namespace holocap
