#include "app/options.h"

#include <cmath>
#include <cstdio>
#include <sstream>

#include "core/error.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

TakeSelection TakeSelectionFlags::Parse() const {
  TakeSelection selection;
  ParseFrames(frames, &selection.first_frame, &selection.last_frame);
  selection.clean_plate_frames = clean_plate;
  selection.ground_truth_cameras = ground_truth_cameras;
  selection.Check();
  return selection;
}

void AddTakeSelectionFlags(CLI::App* command, TakeSelectionFlags* flags) {
  command->add_option("--frames", flags->frames,
                      "Frame sets A:B (or A:, or A alone) after the clean plate (default: all)");
  command->add_option("--clean-plate", flags->clean_plate,
                      "Leading frame sets without the subject (default: from the take, else 0)");
  command->add_flag("--ground-truth-cameras", flags->ground_truth_cameras,
                    "Use the simulation's true cameras (gt/cameras) even when calib/ exists");
}

void ParseFrames(const std::string& text, int64_t* first, int64_t* last) {
  if (text.empty()) return;
  auto colon = text.find(':');
  try {
    size_t used = 0;
    auto number = [&](const std::string& part) {
      const long long value = std::stoll(part, &used);
      if (used != part.size()) throw std::invalid_argument(part);
      return static_cast<int64_t>(value);
    };
    if (colon == std::string::npos) {
      *first = number(text);
      *last = *first + 1;
      return;
    }
    std::string a = text.substr(0, colon), b = text.substr(colon + 1);
    *first = a.empty() ? 0 : number(a);
    *last = b.empty() ? -1 : number(b);
  } catch (const std::exception&) {
    Fail("--frames must be A:B, A: or A, got '", text, "'");
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

void CheckNamingFlags(const std::function<void()>& check,
                      const std::map<std::string, std::string>& flag_of_field) {
  try {
    check();
  } catch (const Error& e) {
    const std::string message = e.what();
    for (const auto& [field, flag] : flag_of_field) {
      if (message.rfind(field + " ", 0) == 0) throw Error(flag + message.substr(field.size()));
    }
    throw;
  }
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

}  // namespace holocap
