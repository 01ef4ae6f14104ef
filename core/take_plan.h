// The take plan: what a stage works on, chosen once from a take and the user's options.
//
// Every stage that reads a take (reconstruction, Neural Volumes, rerendering, playback) starts
// from a TakePlan: which camera models (calib/ or the simulation's gt/), which colour and depth
// sensors, how many leading clean-plate sets, which frame sets, which cameras are held out or
// serve as witnesses, the scene's bounds, up axis and voxel size, where silhouettes come from,
// and what the stage leaves out and why. The plan is written into every
// report's "plan" (TakePlan::ToJson, to which a stage adds its own keys), so a reader sees what
// a run was given, and no stage interprets the take on its own.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <filesystem>
#include <limits>
#include <map>
#include <nlohmann/json.hpp>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include <opencv2/core.hpp>
#include <utility>

#include "core/box.h"
#include "core/camera.h"
#include "core/take.h"

namespace holocap {

// Where a take's silhouettes come from, in the order a plan prefers them.
enum class SilhouetteSource {
  kNone,             // nothing to separate the subject from (no colour camera)
  kAlpha,            // the frames' own alpha channel (every colour stream bgra8)
  kCleanPlate,       // background subtraction against the clean plate
  kBackgroundModel,  // a per-pixel temporal median over a dynamic take's frame sets
  kOtsu,             // a threshold chosen per image (Otsu) on the brightest channel
  kThreshold,        // a threshold the user gave (--silhouette-threshold)
};
const char* ToString(SilhouetteSource source);

// A take this long (frame sets after its clean plate) gets a background model when it has no
// clean plate or alpha; the model takes the median of at most kMaxBackgroundSets of them.
constexpr int64_t kMinBackgroundSets = 15;
constexpr int64_t kMaxBackgroundSets = 31;

// What the user asks of a take. The flags of every command that reads a take map onto these.
struct TakeSelection {
  int64_t first_frame = 0;  // frame sets [first, last) after the clean plate
  int64_t last_frame = -1;  // -1: to the end
  // Or these frame sets after the clean plate, in increasing order (--frames 0-9,15,20-29);
  // empty: the range above.
  std::vector<int64_t> frame_list;
  int64_t clean_plate_frames = -1;    // leading sets without the subject; -1: the take's own
                                      // metadata (the simulator writes it), else 0
  bool ground_truth_cameras = false;  // gt/cameras even when calib/ exists (simulated takes)
  bool color_only = false;  // the take's depth sensors left out (--no-depth): nothing of the
                            // stage reads them (no floor, no fusion), as if the rig had none
  std::vector<std::string> heldout;   // colour cameras never reconstructed from (--heldout-names)
  std::optional<Box> bounds;          // the scene's box (--bounds); else from the rig
  std::optional<Eigen::Vector3d> up;  // the world's up axis (--up); else from the rig
  // Silhouettes: "auto" (the first of the take's sources that can run: alpha, clean plate,
  // a background model of a take of kMinBackgroundSets frame sets or more, Otsu), "alpha",
  // "plate", "median" (the background model), "otsu" or "threshold" (silhouette_threshold,
  // else 0.19 of full scale).
  std::string silhouettes = "auto";
  double silhouette_threshold = 0;  // (0, 1) of full scale; 0: none given

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
  // The scene: the box every stage works in, the box the cameras share (what a result may
  // fill at most), the up axis and the voxel size the bounds imply, each with its reason.
  Box bounds = Box::Empty();
  std::string bounds_source;  // "user (--bounds)", "cameras (...)", "cameras + coarse hull ..."
  Box view_bounds = Box::Empty();  // seen by most colour cameras (the user's box if none)
  Eigen::Vector3d up = Eigen::Vector3d::UnitZ();
  std::string up_source;
  // The floor's height along `up` when depth saw one and `up` is a world axis, less the fit's
  // tolerance (a floor seen a little high must not cut the subject's feet); NaN: none. Nothing
  // below it is part of the scene.
  double floor_m = std::numeric_limits<double>::quiet_NaN();
  // That tolerance: the floor plane itself lies at floor_m + floor_tolerance_m (0 with no floor).
  double floor_tolerance_m = 0;
  double voxel_m = 0;
  std::string voxel_source;
  SilhouetteSource silhouettes = SilhouetteSource::kNone;
  std::string silhouette_reason;
  double silhouette_threshold = 0;  // kThreshold: the level, (0, 1) of full scale
  // kBackgroundModel: the frame sets (spread over the whole take after its clean plate) whose
  // per-pixel median is each camera's background.
  std::vector<int64_t> background_sets;

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
  // The colour sensors that are not held out (the ones a reconstruction reads).
  std::vector<std::string> ReconstructionSensors() const;
  // Sets bounds (cut at the floor, if any) and the voxel size they imply (ImpliedVoxel), with
  // the reason for both.
  void SetBounds(const Box& box, std::string why, bool cut_at_floor = true);
  // `box` without what lies below the floor (unchanged when there is none).
  Box AboveFloor(Box box) const;
  // The plan's keys of every report: cameras, color_sensors, depth_sensors, clean_plate_frames,
  // frame_sets, heldout, witness, left_out, bounds, up, voxel, silhouettes.
  nlohmann::json ToJson() const;
};

// The scene as the rig sees it, for takes whose user gave no bounds.
struct RigView {
  Eigen::Vector3d center = Eigen::Vector3d::Zero();  // least squares nearest the optical axes
  double median_distance_m = 0;                      // from the cameras to `center`
  Box shared = Box::Empty();  // points seen by at least `min_cameras` (in front, in image)
  int min_cameras = 0;
  bool converges = false;  // optical axes meet (else `shared` is empty)
  std::string why;         // one line for the plan
};
// Where the cameras' optical axes pass closest (least squares) and the box, within a cube of
// 1.5 median camera distances around it, that at least half the cameras (two at least) see.
RigView ViewOfRig(const std::vector<CameraModel>& cameras);
// The median of the cameras' "up" (their -y axis in the world), normalised; snapped to the
// nearest world axis within 10 degrees. `why` says which.
Eigen::Vector3d UpFromCameras(const std::vector<CameraModel>& cameras, std::string* why);
// The floor: the plane most depth points lie on (RANSAC, within 1% of the sensors' distance to
// it) whose normal is within 30 degrees of `up`, among points back-projected from `depth_maps`
// (CV_32F z-depth, metres) of their sensors; false when no plane holds a fifth of the points.
// `normal` points to the sensors' side; the plane is {x : normal . x = offset}; `tolerance`
// is the inlier distance used.
bool FloorFromDepth(const std::vector<std::pair<CameraModel, cv::Mat>>& depth_maps,
                    const Eigen::Vector3d& up, Eigen::Vector3d* normal, double* offset,
                    double* tolerance, std::string* why);
// `up` snapped to the nearest world axis when within `degrees` of it; `why` gains which.
Eigen::Vector3d SnapToAxis(const Eigen::Vector3d& up, double degrees, std::string* why);
// The voxel a box and its cameras imply: 2/3 of a pixel's footprint at the cameras' median
// distance to the box's centre (finer adds no detail), no finer than 1/512 of the box's largest
// side (memory), rounded to a power of two in millimetres. `why` says which bound chose it.
double ImpliedVoxel(const Box& box, const std::vector<CameraModel>& cameras, std::string* why);
// How many of the cameras see a point (in front, inside the image).
int CamerasSeeing(const std::vector<CameraModel>& cameras, const Eigen::Vector3d& point_in_world);

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
