#include "core/take_plan.h"

#include <algorithm>
#include <limits>

#include "core/error.h"

namespace holocap {

void TakeSelection::Check() const {
  if (first_frame < 0) Fail("--frames: the first frame set must be 0 or more, not ", first_frame);
  if (last_frame >= 0 && last_frame <= first_frame) {
    Fail("--frames: the range ", first_frame, ":", last_frame, " is empty");
  }
  if (clean_plate_frames < -1)
    Fail("--clean-plate must be -1 (from the take) or more, not ", clean_plate_frames);
}

nlohmann::json TakeSelection::ToJson() const {
  return {{"first_frame", first_frame},
          {"last_frame", last_frame},
          {"clean_plate_frames", clean_plate_frames},
          {"ground_truth_cameras", ground_truth_cameras}};
}

std::vector<CameraModel> TakePlan::Cameras(const std::vector<std::string>& names) const {
  std::vector<CameraModel> out;
  out.reserve(names.size());
  for (const auto& name : names) out.push_back(cameras.at(name));
  return out;
}

int TakePlan::ColorIndex(const std::string& name, const char* what) const {
  auto it = std::find(color_sensors.begin(), color_sensors.end(), name);
  if (it == color_sensors.end())
    Fail("the ", what, " camera '", name, "' is not a colour camera of the take");
  return static_cast<int>(it - color_sensors.begin());
}

std::vector<int> TakePlan::ColorIndices(const std::vector<std::string>& names,
                                        const char* what) const {
  std::vector<int> out;
  for (const auto& name : names) out.push_back(ColorIndex(name, what));
  return out;
}

void TakePlan::RequireFrames(const Take& take, const std::vector<std::string>& names) const {
  for (int64_t set : sets) {
    for (const auto& name : names) {
      if (take.entry(static_cast<size_t>(set)).Find(name) == nullptr) {
        Fail("frame set ", set, " of take '", take_dir.string(), "' has no frame from '", name,
             "' (dropped); ", "choose another range with --frames");
      }
    }
  }
  if (!has_clean_plate()) return;
  for (const auto& name : names) {
    if (take.entry(static_cast<size_t>(plate_set())).Find(name) == nullptr) {
      Fail("the clean plate (set ", plate_set(), ") has no frame from '", name, "'");
    }
  }
}

nlohmann::json TakePlan::ToJson() const {
  return {{"cameras", cameras_source},
          {"color_sensors", color_sensors},
          {"depth_sensors", depth_sensors},
          {"clean_plate_frames", clean_plate_frames},
          {"frame_sets", sets},
          {"heldout", heldout},
          {"witness", witness},
          {"left_out", left_out}};
}

namespace {

void ChooseCameraSource(const Take& take, const TakeSelection& selection, TakePlan& plan) {
  const bool has_truth =
      take.has_ground_truth() && std::filesystem::is_directory(take.gt_dir() / "cameras");
  if (selection.ground_truth_cameras) {
    if (!has_truth)
      Fail("take '", take.dir().string(), "' has no gt/cameras (only simulated takes do)");
    plan.ground_truth_cameras = true;
    plan.cameras_source = "gt/cameras (asked for)";
  } else if (take.has_calibration()) {
    plan.cameras_source = "calib/";
  } else if (has_truth) {
    plan.ground_truth_cameras = true;
    plan.cameras_source = "gt/cameras (the take has no calib/: true models of the simulation)";
  } else {
    Fail("take '", take.dir().string(),
         "' is not calibrated (no calib/<sensor>.cameramodel for every sensor): run holocap "
         "calibrate first");
  }
}

void ChooseFrameSets(const Take& take, const TakeSelection& selection, TakePlan& plan) {
  plan.clean_plate_frames = selection.clean_plate_frames >= 0
                                ? selection.clean_plate_frames
                                : take.metadata().value("clean_plate_frames", int64_t{0});
  const int64_t available = static_cast<int64_t>(take.size()) - plan.clean_plate_frames;
  if (available <= 0) {
    Fail("take '", take.dir().string(), "' has ", take.size(),
         " frame sets, all of them clean plate");
  }
  const int64_t first = selection.first_frame;
  const int64_t last =
      selection.last_frame < 0 ? available : std::min(selection.last_frame, available);
  if (first >= last) {
    Fail("frame range ", first, ":", last, " selects nothing (the take has ", available,
         " frame sets after its clean plate)");
  }
  for (int64_t f = first; f < last; ++f) plan.sets.push_back(plan.clean_plate_frames + f);
}

}  // namespace

TakePlan PlanTake(const Take& take, const TakeSelection& selection) {
  selection.Check();
  TakePlan plan;
  plan.take_dir = take.dir();
  for (const StreamInfo& stream : take.streams()) {
    if (stream.role == SensorRole::kColor) plan.color_sensors.push_back(stream.name);
    if (stream.role == SensorRole::kDepth) plan.depth_sensors.push_back(stream.name);
    if (!stream.paired_with.empty()) plan.paired_color.insert(stream.paired_with);
  }
  if (plan.color_sensors.empty() && plan.depth_sensors.empty()) {
    Fail("take '", take.dir().string(), "' has no colour or depth sensor");
  }
  ChooseCameraSource(take, selection, plan);
  for (const auto& name : plan.color_sensors)
    plan.cameras.emplace(name, take.Camera(name, plan.ground_truth_cameras));
  for (const auto& name : plan.depth_sensors)
    plan.cameras.emplace(name, take.Camera(name, plan.ground_truth_cameras));
  ChooseFrameSets(take, selection, plan);
  return plan;
}

std::vector<std::string> ChooseColorSensors(const Take& take,
                                            const std::vector<std::string>& names) {
  std::vector<std::string> sensors = names;
  if (sensors.empty()) {
    for (const StreamInfo& stream : take.streams()) {
      if (stream.role == SensorRole::kColor) sensors.push_back(stream.name);
    }
    if (sensors.empty()) Fail("take ", take.dir().string(), " has no colour camera");
  }
  for (const auto& name : sensors) {
    if (!take.has_stream(name))
      Fail("camera '", name, "' is not in the take ", take.dir().string());
    if (take.stream(name).role != SensorRole::kColor) {
      Fail("sensor '", name, "' is not a colour camera (role ", ToString(take.stream(name).role),
           ")");
    }
  }
  return sensors;
}

std::vector<int> SpreadAround(const std::vector<CameraModel>& cameras,
                              const std::vector<int>& candidates, int count,
                              const Eigen::Vector3d& center) {
  std::vector<int> picked;
  if (count <= 0 || candidates.empty()) return picked;
  auto direction = [&](int i) { return (cameras[i].center_in_world() - center).normalized(); };
  picked.push_back(candidates.front());
  while (static_cast<int>(picked.size()) < std::min<int>(count, candidates.size())) {
    int best = -1;
    double best_distance = -1;
    for (int c : candidates) {
      if (std::find(picked.begin(), picked.end(), c) != picked.end()) continue;
      double nearest = std::numeric_limits<double>::infinity();
      for (int p : picked) nearest = std::min(nearest, (direction(c) - direction(p)).norm());
      if (nearest > best_distance) {
        best_distance = nearest;
        best = c;
      }
    }
    picked.push_back(best);
  }
  std::sort(picked.begin(), picked.end());
  return picked;
}

}  // namespace holocap
