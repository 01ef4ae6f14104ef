#include "app/options.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <functional>
#include <set>
#include <sstream>

#include "app/commands.h"
#include "core/error.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

TakeSelection TakeSelectionFlags::Parse() const {
  TakeSelection selection;
  ParseFrames(frames, &selection);
  selection.clean_plate_frames = clean_plate;
  selection.ground_truth_cameras = ground_truth_cameras;
  selection.color_only = no_depth;
  selection.Check();
  return selection;
}

void AddTakeSelectionFlags(CLI::App* command, TakeSelectionFlags* flags) {
  command->add_option("--frames", flags->frames,
                      "Frame sets after the clean plate: A:B (B excluded), A:, A, or a list such "
                      "as 0-9,15,20-29 (ranges inclusive) (default: all)");
  command->add_option("--clean-plate", flags->clean_plate,
                      "Leading frame sets without the subject (default: from the take, else 0)");
  command->add_flag(
      "--ground-truth-cameras", flags->ground_truth_cameras,
      "Use a simulated take's true cameras (gt/cameras) instead of calib/: measures a "
      "stage apart from calibration (an uncalibrated take is refused otherwise)");
  command->add_flag("--no-depth", flags->no_depth,
                    "Leave the take's depth sensors out: colour cameras only, as if the rig had "
                    "no depth sensor (no floor from depth, no depth fusion)");
}

void SceneFlags::Apply(TakeSelection* selection) const {
  if (!bounds.empty()) selection->bounds = ParseBounds(bounds);
  if (!up.empty()) selection->up = ParseUp(up);
  // "background" is the name of the clean plate's silhouettes before other sources existed.
  selection->silhouettes = silhouettes == "background" ? "plate" : silhouettes;
  selection->silhouette_threshold = silhouette_threshold;
  selection->Check();
}

void AddSceneFlags(CLI::App* command, SceneFlags* flags) {
  command->add_option("--bounds", flags->bounds,
                      "Scene box xmin,ymin,zmin,xmax,ymax,zmax in metres (default: from the "
                      "cameras, tightened to a coarse hull)");
  command->add_option(
      "--up", flags->up,
      "The world's up axis: +z, -y, ... or x,y,z (default: the cameras' median up)");
  command
      ->add_option("--silhouettes", flags->silhouettes,
                   "auto (alpha, else the clean plate, else a background model (median) on a "
                   "take of 15 frame sets or more, else a threshold chosen per image), alpha, "
                   "plate, median (each camera's per-pixel median over the take), otsu, or "
                   "threshold (--silhouette-threshold, else 0.19)")
      ->capture_default_str();
  command->add_option("--silhouette-threshold", flags->silhouette_threshold,
                      "Subject where the brightest channel exceeds this (0..1 of full scale)");
}

Eigen::Vector3d ParseUp(const std::string& text, const char* option) {
  const std::string axes = "xyz";
  std::string name = text;
  double sign = 1;
  if (!name.empty() && (name[0] == '+' || name[0] == '-')) {
    sign = name[0] == '-' ? -1 : 1;
    name = name.substr(1);
  }
  if (name.size() == 1 && axes.find(name[0]) != std::string::npos) {
    Eigen::Vector3d up = Eigen::Vector3d::Zero();
    up(static_cast<int>(axes.find(name[0]))) = sign;
    return up;
  }
  std::stringstream in(text);
  std::vector<double> v;
  std::string item;
  while (std::getline(in, item, ',')) {
    try {
      v.push_back(std::stod(item));
    } catch (const std::exception&) {
      v.clear();
      break;
    }
  }
  const Eigen::Vector3d up = v.size() == 3 ? Eigen::Vector3d(v[0], v[1], v[2]) : Eigen::Vector3d();
  if (v.size() != 3 || !up.allFinite() || !(up.norm() > 0))
    Fail(option, " must be +x, -x, +y, -y, +z, -z or a direction x,y,z, got '", text, "'");
  return up.normalized();
}

namespace {

// The frame sets a list "a-b,c,d-e" names (ranges inclusive), in increasing order, each once.
std::vector<int64_t> ParseFrameList(const std::string& text,
                                    const std::function<int64_t(const std::string&)>& number) {
  constexpr int64_t kMaxListed = 10'000'000;  // more than any take's frame sets
  std::set<int64_t> sets;
  std::stringstream items(text);
  std::string item;
  while (std::getline(items, item, ',')) {
    const size_t dash = item.find('-', 1);
    const int64_t a = number(item.substr(0, dash));
    const int64_t b = dash == std::string::npos ? a : number(item.substr(dash + 1));
    if (a < 0 || b < a) Fail("--frames: '", item, "' is not a range A-B with 0 <= A <= B");
    if (b - a >= kMaxListed) Fail("--frames: '", item, "' lists more than ", kMaxListed, " sets");
    for (int64_t f = a; f <= b; ++f) sets.insert(f);
  }
  if (sets.empty() || text.back() == ',') throw std::invalid_argument(text);
  return {sets.begin(), sets.end()};
}

}  // namespace

void ParseFrames(const std::string& text, TakeSelection* selection) {
  if (text.empty()) return;
  auto colon = text.find(':');
  try {
    size_t used = 0;
    auto number = [&](const std::string& part) {
      const long long value = std::stoll(part, &used);
      if (used != part.size()) throw std::invalid_argument(part);
      return static_cast<int64_t>(value);
    };
    if (colon == std::string::npos &&
        (text.find(',') != std::string::npos || text.find('-', 1) != std::string::npos)) {
      selection->frame_list = ParseFrameList(text, number);
      return;
    }
    if (colon == std::string::npos) {
      selection->first_frame = number(text);
      selection->last_frame = selection->first_frame + 1;
      return;
    }
    std::string a = text.substr(0, colon), b = text.substr(colon + 1);
    selection->first_frame = a.empty() ? 0 : number(a);
    selection->last_frame = b.empty() ? -1 : number(b);
  } catch (const std::invalid_argument&) {
    Fail("--frames must be A:B, A:, A or a list like 0-9,15,20-29, got '", text, "'");
  } catch (const std::out_of_range&) {
    Fail("--frames must be A:B, A:, A or a list like 0-9,15,20-29, got '", text, "'");
  }
}

double ParseLength(const std::string& text, const char* what) {
  size_t used = 0;
  double value = 0;
  try {
    value = std::stod(text, &used);
  } catch (const std::exception&) {
    Fail(what, " must be a length such as 4mm or 0.004, got '", text, "'");
  }
  std::string unit = text.substr(used);
  unit.erase(0, unit.find_first_not_of(' '));
  double scale = unit.empty() || unit == "m" ? 1 : unit == "cm" ? 1e-2 : unit == "mm" ? 1e-3 : -1;
  if (scale < 0) Fail(what, ": unknown unit '", unit, "' in '", text, "' (use m, cm or mm)");
  if (!(value > 0) || !std::isfinite(value)) Fail(what, " must be > 0, got '", text, "'");
  return value * scale;
}

void ApplyBoardPrint(const std::string& print, const char* option, BoardLayout* layout) {
  if (print.empty()) return;
  if (print != "holocap" && print != "kalibr")
    Fail(option, " must be holocap or kalibr, got '", print, "'");
  if (layout->type != BoardType::kAprilGrid || layout->family != "tag36h11") {
    Fail(option, " ", print, " prints tag36h11 AprilTag boards, not a ",
         layout->type == BoardType::kAprilGrid ? layout->family : ToString(layout->type));
  }
  layout->border_bits = print == "kalibr" ? 2 : 1;
  try {
    layout->Check();
  } catch (const Error& e) {
    Fail(option, " ", print, ": ", e.what());
  }
}

Box ParseBounds(const std::string& text, const char* option) {
  std::stringstream in(text);
  std::vector<double> v;
  std::string item;
  while (std::getline(in, item, ',')) {
    try {
      v.push_back(std::stod(item));
    } catch (const std::exception&) {
      Fail(option, " must be six numbers xmin,ymin,zmin,xmax,ymax,zmax (metres), got '", text, "'");
    }
  }
  if (v.size() != 6)
    Fail(option, " must be six numbers xmin,ymin,zmin,xmax,ymax,zmax (metres), got '", text, "'");
  Box box;
  box.min = Eigen::Vector3d(v[0], v[1], v[2]);
  box.max = Eigen::Vector3d(v[3], v[4], v[5]);
  if (!box.valid()) Fail(option, ": max must exceed min on every axis");
  return box;
}

namespace {

// Each command's flags whose names do not follow from their fields (NameFieldFlags).
std::map<const CLI::App*, std::map<std::string, std::string>>& FieldFlagTables() {
  static std::map<const CLI::App*, std::map<std::string, std::string>> tables;
  return tables;
}

// Flags of other names than their fields, the same on every command that has them.
const std::map<std::string, std::string> kSharedFieldFlags = {
    {"TakeSelection::first_frame", "--frames"},
    {"TakeSelection::last_frame", "--frames"},
    {"TakeSelection::frame_list", "--frames"},
    {"TakeSelection::clean_plate_frames", "--clean-plate"},
    {"Shard::index", "--shard"},
    {"Shard::count", "--shard"}};

// The units of field names (core/check_option.h's fields carry them; flags do not).
constexpr const char* kUnitSuffixes[] = {"_m", "_mm", "_px", "_s", "_ms", "_db", "_deg"};

// kl_weight: --kl-weight.
std::string FlagNamed(std::string field) {
  std::replace(field.begin(), field.end(), '_', '-');
  return "--" + field;
}

// The flag that fills the field `error` names, whether the user gave it or not; "" for none.
std::string FlagFillingField(const CLI::App& command, const OptionError& error) {
  // A member of a member ("render.step_voxels") is found by its own name too.
  const std::string& written = error.field();
  const std::string name = written.substr(written.rfind('.') + 1);
  std::vector<std::string> keys;
  for (const std::string& field : {written, name}) {
    if (!error.options().empty()) keys.push_back(error.options() + "::" + field);
    keys.push_back(field);
  }
  const auto table = FieldFlagTables().find(&command);
  for (const std::string& key : keys) {
    if (table == FieldFlagTables().end()) break;
    if (const auto entry = table->second.find(key); entry != table->second.end())
      return entry->second;
  }
  for (const std::string& key : keys) {
    const auto entry = kSharedFieldFlags.find(key);
    if (entry != kSharedFieldFlags.end() && command.get_option_no_throw(entry->second) != nullptr)
      return entry->second;
  }
  if (command.get_option_no_throw(FlagNamed(name)) != nullptr) return FlagNamed(name);
  for (const std::string unit : kUnitSuffixes) {
    if (name.size() <= unit.size() || !name.ends_with(unit)) continue;
    std::string flag = FlagNamed(name.substr(0, name.size() - unit.size()));
    if (command.get_option_no_throw(flag) != nullptr) return flag;
  }
  return "";
}

}  // namespace

void NameFieldFlags(CLI::App* command, const std::map<std::string, std::string>& flag_of_field) {
  for (const auto& [field, flag] : flag_of_field) FieldFlagTables()[command][field] = flag;
}

std::string FlagOfField(const CLI::App& command, const OptionError& error) {
  const std::string flag = FlagFillingField(command, error);
  if (flag.empty()) return "";
  const CLI::Option* option = command.get_option_no_throw(flag);
  return option != nullptr && option->count() > 0 ? flag : "";
}

std::string OptionErrorMessage(const CLI::App& command, const OptionError& error) {
  const std::string flag = FlagOfField(command, error);
  if (flag.empty()) return error.what();
  // What the user typed after the flag (a length in its unit, K/N, a list), not the field's
  // value: the line quotes the command line back.
  const CLI::Option* option = command.get_option_no_throw(flag);
  std::string typed;
  for (const std::string& result : option->results())
    typed += (typed.empty() ? "" : ",") + (result.empty() ? std::string("''") : result);
  return error.NamedAs(option->get_expected_max() == 0 ? flag : flag + " " + typed);
}

void EndCommand(const Summary& summary, const std::string& what) {
  std::printf("%s: %s\n", ToString(summary.termination), summary.message.c_str());
  FailUnlessUsable(summary, what);
}

void FailUnlessUsable(const Summary& summary, const std::string& what) {
  std::fflush(stdout);
  if (ExitStatus(summary.termination) != 0) {
    Fail(what, " ended ", ToString(summary.termination), ": ", summary.message);
  }
}

std::vector<DemoStage>& DemoStageTable() {
  static std::vector<DemoStage> table;
  return table;
}

void AddOverwriteFlag(CLI::App* command, bool* overwrite) {
  command->add_flag("--overwrite", *overwrite,
                    "Write into a non-empty output another command made, or replace an output "
                    "file (nothing is removed; a take's recording is never an output)");
}

}  // namespace holocap
