// The take plan: what a stage works on, chosen once from a take and the user's options.
//
// Every stage that reads a take (reconstruction, Neural Volumes, rerendering, playback) starts
// from a TakePlan: which camera models (calib/ or the simulation's gt/), which colour and depth
// sensors, how many leading clean-plate sets, which frame sets, which cameras are held out or
// serve as witnesses, and what the stage leaves out and why. The plan is written into every
// report's "plan" (TakePlan::ToJson, to which a stage adds its own keys), so a reader sees what
// a run was given, and no stage interprets the take on its own.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>
#include <set>
#include <string>
#include <vector>

#include "core/camera.h"
#include "core/take.h"

namespace holocap {

// What the user asks of a take. The flags of every command that reads a take map onto these.
struct TakeSelection {
  int64_t first_frame = 0;            // frame sets [first, last) after the clean plate
  int64_t last_frame = -1;            // -1: to the end
  int64_t clean_plate_frames = -1;    // leading sets without the subject; -1: the take's own
                                      // metadata (the simulator writes it), else 0
  bool ground_truth_cameras = false;  // gt/cameras even when calib/ exists (simulated takes)

  void Check() const;  // throws Error naming the flag
  nlohmann::json ToJson() const;
};

struct TakePlan {
  std::filesystem::path take_dir;
  bool ground_truth_cameras = false;       // gt/cameras (true models) rather than calib/
  std::string cameras_source;              // "calib/" or "gt/cameras (...why...)"
  std::vector<std::string> color_sensors;  // in the take's order
  std::vector<std::string> depth_sensors;
  std::set<std::string> paired_color;          // colour sensors a depth sensor is paired with
  std::map<std::string, CameraModel> cameras;  // every colour and depth sensor's model
  int64_t clean_plate_frames = 0;              // the plate is the last of these sets
  std::vector<int64_t> sets;                   // frame sets to work on (indices into the take)
  std::vector<std::string> heldout;            // never trained on nor reconstructed from
  std::vector<std::string> witness;            // trained on, never reconstructed from
  nlohmann::json left_out = nlohmann::json::object();  // {what: why} for skipped work

  bool has_clean_plate() const { return clean_plate_frames > 0; }
  int64_t plate_set() const { return clean_plate_frames - 1; }  // the set holding the plate
  std::vector<CameraModel> Cameras(const std::vector<std::string>& names) const;
  // Index of a colour sensor; throws Error naming `what` ("held-out", "witness") if absent.
  int ColorIndex(const std::string& name, const char* what) const;
  std::vector<int> ColorIndices(const std::vector<std::string>& names, const char* what) const;
  // Records work the stage skips, with the reason (stored under "left_out").
  void LeaveOut(const std::string& what, const std::string& why) { left_out[what] = why; }
  // Throws Error naming the first set and sensor of `names` that the take lacks.
  void RequireFrames(const Take& take, const std::vector<std::string>& names) const;
  // The plan's keys of every report: cameras, color_sensors, depth_sensors, clean_plate_frames,
  // frame_sets, heldout, witness, left_out.
  nlohmann::json ToJson() const;
};

// Chooses camera models, sensors, the clean plate and the frame sets. Throws Error for a take
// without colour or depth sensors, without camera models (calib/ or gt/cameras), or a frame
// range that selects nothing.
TakePlan PlanTake(const Take& take, const TakeSelection& selection);

// The colour cameras a stage works on: `names`, each checked to be a colour sensor of the take,
// or, when none are named, every colour sensor in the take's order. Throws Error naming the
// camera (or the take, when it has no colour camera).
std::vector<std::string> ChooseColorSensors(const Take& take,
                                            const std::vector<std::string>& names);

// `count` indices out of `candidates` whose directions seen from `center` are spread as far
// apart as possible (farthest-point sampling, whatever the world's up axis), sorted.
std::vector<int> SpreadAround(const std::vector<CameraModel>& cameras,
                              const std::vector<int>& candidates, int count,
                              const Eigen::Vector3d& center);

}  // namespace holocap
