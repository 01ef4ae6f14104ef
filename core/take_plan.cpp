#include "core/take_plan.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "core/check_option.h"
#include "core/error.h"

namespace holocap {

const char* ToString(SilhouetteSource source) {
  switch (source) {
    case SilhouetteSource::kNone:
      return "none";
    case SilhouetteSource::kAlpha:
      return "alpha";
    case SilhouetteSource::kCleanPlate:
      return "clean plate";
    case SilhouetteSource::kBackgroundModel:
      return "background model";
    case SilhouetteSource::kOtsu:
      return "otsu";
    case SilhouetteSource::kThreshold:
      return "threshold";
  }
  return "?";
}

void TakeSelection::Check() const {
  HOLOCAP_CHECK_OPTION_GE(first_frame, 0);
  HOLOCAP_CHECK_OPTION(last_frame < 0 || last_frame > first_frame, last_frame,
                       Cat("the range ", first_frame, ":", last_frame, " is empty"));
  for (size_t i = 0; i < frame_list.size(); ++i) {
    HOLOCAP_CHECK_OPTION(frame_list[i] >= 0, frame_list, "frame sets are 0 or more");
    HOLOCAP_CHECK_OPTION(i == 0 || frame_list[i] > frame_list[i - 1], frame_list,
                         "the listed frame sets must increase");
  }
  HOLOCAP_CHECK_OPTION(frame_list.empty() || (first_frame == 0 && last_frame == -1), frame_list,
                       "a list of frame sets and a range A:B are one or the other");
  HOLOCAP_CHECK_OPTION_GE(clean_plate_frames, -1, "-1: from the take");
  HOLOCAP_CHECK_OPTION(!bounds || bounds->valid(), bounds, "max must exceed min on every axis");
  HOLOCAP_CHECK_OPTION(!up || (up->norm() > 0 && up->allFinite()), up, "a non-zero direction");
  HOLOCAP_CHECK_OPTION(
      IsOneOf(silhouettes, {"auto", "alpha", "plate", "median", "otsu", "threshold"}), silhouettes);
  HOLOCAP_CHECK_OPTION_GE(silhouette_threshold, 0, "of full scale; 0: none");
  HOLOCAP_CHECK_OPTION_LT(silhouette_threshold, 1, "of full scale; 0: none");
  HOLOCAP_CHECK_OPTION(silhouette_threshold == 0 || !IsOneOf(silhouettes, {"alpha", "median"}),
                       silhouette_threshold,
                       Cat("silhouettes ", silhouettes, " take no threshold"));
}

nlohmann::json TakeSelection::ToJson() const {
  nlohmann::json json = {{"first_frame", first_frame},
                         {"last_frame", last_frame},
                         {"clean_plate_frames", clean_plate_frames},
                         {"ground_truth_cameras", ground_truth_cameras},
                         {"color_only", color_only},
                         {"heldout", heldout},
                         {"silhouettes", silhouettes},
                         {"silhouette_threshold", silhouette_threshold}};
  if (!frame_list.empty()) json["frames"] = frame_list;
  return json;
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
  out.reserve(names.size());
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

std::vector<std::string> TakePlan::ReconstructionSensors() const {
  std::vector<std::string> out;
  for (const auto& name : color_sensors) {
    if (std::find(heldout.begin(), heldout.end(), name) == heldout.end()) out.push_back(name);
  }
  return out;
}

void TakePlan::SetBounds(const Box& box, std::string why, bool cut_at_floor) {
  bounds = cut_at_floor ? AboveFloor(box) : box;
  bounds_source = std::move(why);
  if (!(bounds == box)) bounds_source += Cat("; cut at the floor (", floor_m, " m along up)");
  voxel_m = ImpliedVoxel(bounds, Cameras(color_sensors.empty() ? depth_sensors : color_sensors),
                         &voxel_source);
}

Box TakePlan::AboveFloor(Box box) const {
  if (!std::isfinite(floor_m)) return box;
  for (int axis = 0; axis < 3; ++axis) {
    if (up(axis) == 1 && box.max(axis) > floor_m) box.min(axis) = std::max(box.min(axis), floor_m);
    if (up(axis) == -1 && box.min(axis) < -floor_m)
      box.max(axis) = std::min(box.max(axis), -floor_m);
  }
  return box;
}

nlohmann::json TakePlan::ToJson() const {
  auto box = [](const Box& b) {
    return nlohmann::json{{"min", {b.min.x(), b.min.y(), b.min.z()}},
                          {"max", {b.max.x(), b.max.y(), b.max.z()}}};
  };
  nlohmann::json silhouette = {{"source", ToString(silhouettes)}, {"why", silhouette_reason}};
  if (silhouettes == SilhouetteSource::kThreshold) silhouette["threshold"] = silhouette_threshold;
  if (silhouettes == SilhouetteSource::kBackgroundModel) silhouette["sets"] = background_sets;
  return {{"cameras", cameras_source},
          {"color_sensors", color_sensors},
          {"depth_sensors", depth_sensors},
          {"clean_plate_frames", clean_plate_frames},
          {"frame_sets", sets},
          {"heldout", heldout},
          {"witness", witness},
          {"left_out", left_out},
          {"bounds", {{"box", box(bounds)}, {"source", bounds_source}}},
          {"view_bounds", box(view_bounds)},
          {"up", {{"axis", {up.x(), up.y(), up.z()}}, {"source", up_source}}},
          {"floor_m", std::isfinite(floor_m) ? nlohmann::json(floor_m) : nlohmann::json(nullptr)},
          {"floor_tolerance_m", floor_tolerance_m},
          {"voxel", {{"m", voxel_m}, {"source", voxel_source}}},
          {"silhouettes", silhouette}};
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
  } else {
    // A simulated take is uncalibrated like any other: its truth only measures, unless asked.
    Fail("take '", take.dir().string(),
         "' is not calibrated (no calib/<sensor>.cameramodel for every sensor): run holocap "
         "calibrate first",
         has_truth ? " (or holocap calibrate TAKE --from BOARD_TAKE; --ground-truth-cameras uses "
                     "the simulation's true cameras)"
                   : "");
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
  if (!selection.frame_list.empty()) {
    for (int64_t f : selection.frame_list) {
      if (f >= available) {
        Fail("--frames lists frame set ", f, "; the take has ", available,
             " frame sets after its clean plate (0 to ", available - 1, ")");
      }
      plan.sets.push_back(plan.clean_plate_frames + f);
    }
    return;
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

// The floor seen by the depth sensors (the clean plate, else the first set), along `plan.up`:
// the up axis becomes its normal unless the user gave one.
void FindFloor(const Take& take, const TakeSelection& selection, TakePlan& plan) {
  if (plan.depth_sensors.empty()) return;
  const size_t set = static_cast<size_t>(plan.has_clean_plate() ? plan.plate_set() : plan.sets[0]);
  std::vector<std::pair<CameraModel, cv::Mat>> maps;
  for (const auto& name : plan.depth_sensors) {
    if (take.entry(set).Find(name) == nullptr) continue;
    maps.emplace_back(plan.cameras.at(name), take.ReadFrame(set, name));
  }
  Eigen::Vector3d normal;
  double offset = 0, tolerance = 0;
  std::string why;
  if (!FloorFromDepth(maps, plan.up, &normal, &offset, &tolerance, &why)) {
    plan.up_source += "; no floor in depth: " + why;
    return;
  }
  if (!selection.up) {
    why = "floor plane (" + why + ")";
    plan.up = SnapToAxis(normal, 5, &why);
    plan.up_source = why;
  }
  if ((plan.up.array() != 0).count() == 1) {
    plan.floor_m = plan.up.dot(normal) * offset - tolerance;
    plan.floor_tolerance_m = tolerance;
  }
}

// Bounds, the box the cameras share and the up axis: the user's, else the rig's own.
void ChooseScene(const Take& take, const TakeSelection& selection, TakePlan& plan) {
  const std::vector<CameraModel> cameras =
      plan.Cameras(plan.color_sensors.size() >= 2 ? plan.color_sensors : plan.depth_sensors);
  const RigView view = ViewOfRig(cameras);
  if (selection.up) {
    plan.up = selection.up->normalized();
    plan.up_source = "user (--up)";
  } else {
    plan.up = UpFromCameras(cameras, &plan.up_source);
  }
  FindFloor(take, selection, plan);
  if (selection.bounds) {
    plan.view_bounds = view.converges ? view.shared : *selection.bounds;
    plan.SetBounds(*selection.bounds, "user (--bounds)", false);
    return;
  }
  if (!view.converges) {
    // No convergent rig (one sensor, parallel axes): the stage volume of a metre-scale studio.
    const Box stage{Eigen::Vector3d(-1.5, -1.5, 0), Eigen::Vector3d(1.5, 1.5, 2.5)};
    plan.view_bounds = stage;
    plan.SetBounds(stage, "default stage box: " + view.why + "; give --bounds for another scene",
                   false);
    return;
  }
  plan.view_bounds = view.shared;
  plan.SetBounds(view.shared, "cameras: " + view.why);
}

// The first silhouette source the take has, or the one asked for.
// The frame sets of the background model: up to kMaxBackgroundSets spread evenly over the
// take after its clean plate (the whole take, not only the sets worked on).
void ChooseBackgroundSets(const Take& take, TakePlan& plan) {
  const int64_t first = plan.clean_plate_frames;
  const int64_t available = static_cast<int64_t>(take.size()) - first;
  if (available < 3) {
    Fail("silhouettes from a background model: take '", take.dir().string(), "' has ", available,
         " frame set(s) after its clean plate; a per-pixel median needs 3 or more "
         "(and a subject that moves)");
  }
  const int64_t count = std::min(available, kMaxBackgroundSets);
  for (int64_t i = 0; i < count; ++i)
    plan.background_sets.push_back(first + (count > 1 ? i * (available - 1) / (count - 1) : 0));
}

void ChooseSilhouettes(const Take& take, const TakeSelection& selection, TakePlan& plan) {
  if (plan.color_sensors.empty()) {
    plan.silhouettes = SilhouetteSource::kNone;
    plan.silhouette_reason = "no colour camera";
    return;
  }
  const std::string& asked = selection.silhouettes;
  const bool alpha = std::all_of(
      plan.color_sensors.begin(), plan.color_sensors.end(),
      [&](const std::string& name) { return take.stream(name).pixel_format == "bgra8"; });
  if (asked == "alpha" && !alpha) {
    std::string without;
    for (const auto& name : plan.color_sensors) {
      if (take.stream(name).pixel_format != "bgra8")
        without +=
            Cat(without.empty() ? "" : ", ", name, " (", take.stream(name).pixel_format, ")");
    }
    Fail("silhouettes from alpha: take '", take.dir().string(),
         "' has colour streams without alpha: ", without,
         "; alpha comes from bgra8 streams (an RGBA import, sim --alpha); else --silhouettes "
         "plate, otsu or threshold");
  }
  if ((asked == "auto" || asked == "alpha") && alpha && selection.silhouette_threshold == 0) {
    plan.silhouettes = SilhouetteSource::kAlpha;
    plan.silhouette_reason =
        Cat("the colour frames' own alpha channel (every colour stream is bgra8)",
            asked == "alpha" ? ", asked for" : "");
  } else if (asked == "plate" ||
             (asked == "auto" && plan.has_clean_plate() && selection.silhouette_threshold == 0)) {
    if (!plan.has_clean_plate()) {
      Fail("silhouettes from a clean plate: take '", take.dir().string(),
           "' has none. Silhouettes can come from: a clean plate (record leading frame sets "
           "without the subject and pass --clean-plate N), a threshold chosen per image "
           "(--silhouettes otsu, or auto), or a given threshold on a dark background "
           "(--silhouette-threshold T, 0..1 of full scale), a background model of a moving "
           "subject over the take's frame sets (--silhouettes median), or the alpha channel of "
           "bgra8 colour streams (--silhouettes alpha, auto's first choice)");
    }
    plan.silhouettes = SilhouetteSource::kCleanPlate;
    plan.silhouette_reason = Cat("background subtraction against the clean plate (frame set ",
                                 plan.plate_set(), ")", asked == "plate" ? ", asked for" : "");
  } else if (asked == "median" ||
             (asked == "auto" && selection.silhouette_threshold == 0 &&
              static_cast<int64_t>(take.size()) - plan.clean_plate_frames >= kMinBackgroundSets)) {
    ChooseBackgroundSets(take, plan);
    plan.silhouettes = SilhouetteSource::kBackgroundModel;
    plan.silhouette_reason =
        Cat(asked == "median" ? "" : "no clean plate: ",
            "background subtraction against each camera's per-pixel median over ",
            plan.background_sets.size(), " frame sets spread over the take (a moving subject",
            " leaves each pixel to the background most of the time)",
            asked == "median" ? ", asked for" : "");
  } else if (asked == "threshold" || selection.silhouette_threshold > 0) {
    plan.silhouettes = SilhouetteSource::kThreshold;
    plan.silhouette_threshold =
        selection.silhouette_threshold > 0 ? selection.silhouette_threshold : 0.19;
    plan.silhouette_reason =
        Cat("brightest channel above ", plan.silhouette_threshold, " of full scale, asked for");
  } else {
    plan.silhouettes = SilhouetteSource::kOtsu;
    plan.silhouette_reason =
        asked == "otsu" ? "brightest channel above a threshold chosen per image (Otsu), asked for"
                        : "no clean plate: brightest channel above a threshold chosen per image "
                          "(Otsu), for a subject brighter than its background";
  }
}

void ChooseHeldout(const TakeSelection& selection, TakePlan& plan) {
  for (const auto& name : selection.heldout) {
    plan.ColorIndex(name, "held-out");
    plan.heldout.push_back(name);
  }
}

}  // namespace

TakePlan PlanTake(const Take& take, const TakeSelection& selection) {
  selection.Check();
  TakePlan plan;
  plan.take_dir = take.dir();
  for (const StreamInfo& stream : take.streams()) {
    if (stream.role == SensorRole::kColor) plan.color_sensors.push_back(stream.name);
    if (stream.role != SensorRole::kDepth) continue;
    if (selection.color_only) {
      plan.LeaveOut("depth sensors", "colour cameras only, asked for (--no-depth)");
      continue;
    }
    plan.depth_sensors.push_back(stream.name);
    if (!stream.paired_with.empty()) plan.paired_color.insert(stream.paired_with);
  }
  if (plan.color_sensors.empty() && plan.depth_sensors.empty()) {
    Fail("take '", take.dir().string(), "' has no colour ",
         selection.color_only ? "camera (--no-depth leaves its depth sensors out)"
                              : "or depth sensor");
  }
  ChooseCameraSource(take, selection, plan);
  for (const auto& name : plan.color_sensors)
    plan.cameras.emplace(name, take.Camera(name, plan.ground_truth_cameras));
  for (const auto& name : plan.depth_sensors)
    plan.cameras.emplace(name, take.Camera(name, plan.ground_truth_cameras));
  ChooseFrameSets(take, selection, plan);
  ChooseHeldout(selection, plan);
  ChooseScene(take, selection, plan);
  ChooseSilhouettes(take, selection, plan);
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
