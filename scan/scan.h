// Scanning with one moving RGB-D sensor: each depth frame is tracked against the model fused so
// far (frame-to-model point-to-plane ICP with projective data association against the model's
// raycast, plus a photometric term on the colour registered to depth, coarse to fine over an
// image pyramid), fused into the sparse TSDF of reconstruction.h when tracking holds, and the
// keyframes' poses are refined at the end by a pose graph (Ceres) whose loop edges come from
// ICP between keyframes that see the same surface. Tracking failures are data: a frame whose
// residual, inlier fraction or ICP conditioning says the pose cannot be trusted is reported
// with its frame set and never fused.
//
// Poses are the depth sensor's world_from_cam; the world is the take's (the first frame starts
// at the plan's model of the depth sensor: calib/, or gt/cameras on a simulated take).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "core/pose.h"
#include "core/report.h"
#include "core/take_plan.h"
#include "core/trajectory.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

struct ScanOptions {
  double voxel_m = 0.006;        // TSDF voxel edge
  double truncation_voxels = 4;  // TSDF truncation, in voxels
  // The volume scanned: `bounds` when set, else the plan's bounds when the user gave them,
  // else a cube of this side centred where the first frame's central depth meets the ground
  // below it (a subject standing before the sensor).
  std::optional<Box> bounds;
  double volume_side_m = 2.6;
  double depth_min_m = 0.3;  // measurements outside [min, max] are neither tracked nor fused
  double depth_max_m = 4.5;
  double depth_noise_k = 0.0012;  // sigma(z) = k z^2 (fusion weights and smoothing)
  // Points this close to the floor the plan found are left out of tracking and fusion when the
  // subject turns on the spot (a turntable scan: the floor does not turn with it).
  double floor_margin_m = 0.03;

  // Tracking: Gauss-Newton over the pyramid, coarsest level first (level l: every 2^l-th pixel).
  int pyramid_levels = 3;
  // Per level, finest first. Three at each level tracks the simulated orbit and hand-held
  // walks more closely than 10/5/4 (0.8 and 0.6 cm ATE against 1.5 and 1.0 cm; scan_bench)
  // at a fraction of the linearisations, the last step of each level being well under a mm.
  std::vector<int> iterations = {3, 3, 3};
  double max_correspondence_m = 0.06;  // association gate at the finest level, doubled per level
  double max_normal_angle_deg = 45;    // model and frame normals further apart: no pair
  // The model is raycast at every model_stride-th pixel along each axis (the frame's points
  // pair with the nearest ray). 2 costs a quarter of the rays but pairs points up to a pixel
  // apart: on the simulated orbit the frame-to-frame error grows fourfold (RPE 23 mm).
  int model_stride = 1;
  // The photometric term: an intensity difference of 1 (full scale) costs as much as this
  // point-to-plane distance. 0 turns it off.
  double photometric_weight_m = 0.02;
  double huber_m = 0.01;  // point-to-plane residuals beyond this weigh less (Huber)

  // Tracking failure. A frame is LOST when fewer than min_inlier_fraction of its valid points
  // find a model point, when the point-to-plane RMS exceeds max_residual_m, when it has fewer
  // than min_points valid points, or when the pose jumped more than max_step_m / max_step_deg
  // from the prediction. It is DEGENERATE when the smallest eigenvalue of the geometric 6x6
  // Hessian (rotations scaled by the median depth) is below min_condition times the largest:
  // the surface does not fix the pose along that direction (a flat wall); the pose then keeps
  // the prediction along the weak directions.
  double min_inlier_fraction = 0.25;
  double max_residual_m = 0.012;
  int min_points = 300;
  double max_step_m = 0.25;
  double max_step_deg = 20;
  double min_condition = 1e-4;
  // This many lost frames in a row end the scan with the model so far (DEGENERATE).
  int max_lost_frames = 15;
  // More than this fraction of degenerate frames makes the scan DEGENERATE.
  double max_degenerate_fraction = 0.5;
  // The scan judges its trajectory, which a user cannot check against any truth. A lost frame
  // is a gap that only the motion model bridges, and nothing checks the frames after it against
  // the frames before it; more than this fraction of lost frames makes the scan DEGENERATE.
  double max_lost_fraction = 0.1;
  // Every keyframe is aligned again, at the end, against the final model seen from its final
  // pose (the model every other frame built). Frames fused against one consistent model move
  // by millimetres (the slow drift of frame-to-model tracking around the subject: 7-25 mm over
  // 60 frames of the simulated orbit); a keyframe that the tracking tests reject there, or that
  // must move further than max_correspondence_m (beyond it the tracker pairs no point with the
  // surface at all) to fit it, does not belong to that model: DEGENERATE.
  bool check_keyframes = true;

  // Pose graph over keyframes (every keyframe_every-th tracked frame), with loop edges between
  // keyframes whose views overlap (ICP, accepted by the tracking tests above); the volume is
  // fused again with the refined poses when they moved by more than a voxel.
  bool refine_poses = true;
  int keyframe_every = 10;
  double loop_min_angle_deg = 60;  // loop candidates: keyframes this far apart along the path
  double loop_max_distance_m = 0.6;

  MeshingOptions meshing;
  TextureOptions texture;
  int texture_views = 12;  // keyframes (spread over the scan) that colour the mesh
  // Fused frames (spread over the scan) whose colours give the scan's light and albedo
  // (scan/light.h: lighting.json, albedo.ply).
  int light_views = 36;
  // The subject turned on the spot before a still sensor (the user says so: --turn; a take's
  // metadata never does): the floor is left out of tracking and fusion, and the light found.
  bool subject_turns = false;
  bool write_glb = true;
  int threads = 0;  // 0: all cores

  void Check() const;  // throws Error naming the field
  nlohmann::json ToJson() const;
};

enum class TrackingState { kFirst, kTracked, kDegenerate, kLost, kSkipped };
const char* ToString(TrackingState state);

struct ScanFrame {
  int64_t set = 0;
  double time_s = 0;  // the depth frame's timestamp, seconds of its clock
  TrackingState state = TrackingState::kSkipped;
  std::string why;                         // lost, degenerate or skipped: the reason
  Pose world_from_cam = Pose::Identity();  // the depth sensor (after refinement)
  bool fused = false;
  int64_t points = 0;          // valid depth points at the finest level
  double inlier_fraction = 0;  // of them, paired with the model
  double residual_m = 0;       // point-to-plane RMS of the pairs
  double condition = 0;        // smallest / largest eigenvalue of the scaled Hessian
  Eigen::Vector3d weak_direction = Eigen::Vector3d::Zero();  // degenerate: translation part
  double seconds = 0;                                        // tracking + fusion
  double cpu_seconds = 0;  // ... as CPU time of the process (every thread)
};

// Errors of an estimated trajectory against the truth, matched by time (within half a frame).
struct TrajectoryErrors {
  int64_t matched = 0;
  double ate_rmse_m = 0;  // after the rigid (Umeyama, no scale) alignment of positions
  double ate_max_m = 0;
  double rpe_trans_m = 0;  // RMSE of the relative motion's translation error, consecutive frames
  double rpe_rot_deg = 0;  // ... and of its rotation error
  nlohmann::json ToJson() const;
};
TrajectoryErrors CompareTrajectories(const std::vector<StampedPose>& estimate,
                                     const std::vector<StampedPose>& truth);
// The true trajectory of a simulated take's depth sensor (gt/sim.json), stamped with the take's
// timestamps like a scan's; empty when the take has none. Throws Error for a damaged file.
std::vector<StampedPose> TrueTrajectory(const Take& take, const std::string& sensor);

// SUCCESS: every frame tracked or re-localised, at most max_lost_fraction of them lost (lost
// frames are counted and named), and every keyframe agreeing with the final model; DEGENERATE:
// tracking lost for good (the model so far is written), too many lost or degenerate frames, a
// keyframe that the final model contradicts, no valid depth at all, or nothing fused; FAILURE:
// an output could not be written.
struct ScanSummary : Summary {
  std::vector<ScanFrame> frames;
  int64_t tracked = 0, degenerate = 0, lost = 0, fused = 0, keyframes = 0, loops = 0;
  double seconds = 0;
  double tracking_seconds = 0;   // of which tracking (pyramids, raycasts, ICP)
  double fusion_seconds = 0;     // ... and fusion
  double frames_per_second = 0;  // frames tracked and fused per second of the two
  // CPU time of tracking + fusion (every thread), per frame: what the frames cost whatever
  // else the machine runs (1 / cpu_seconds_per_frame is the rate on one idle core).
  double cpu_seconds_per_frame = 0;
  double fusion_cpu_seconds_per_frame = 0;  // ... of which fusion
  std::optional<TrajectoryErrors> errors;   // against the truth, when the take has it
  int64_t vertices = 0, faces = 0;
  nlohmann::json metrics;  // the report's metrics
};

// Scans the plan's frame sets of a take with its single depth sensor (and its paired colour
// camera, for the photometric term and the texture) into `out`: trajectory.tum (world_from_cam
// of the depth sensor, TUM format, times in seconds of the take's clock), trajectory.json
// (every frame's state and pose), mesh.ply, mesh.glb (textured), with a colour camera the light
// the scan was seen in and, when one was found, the mesh's albedo (lighting.json, albedo.ply), and
// report.json. Throws Error for bad options or a take without exactly one depth sensor.
ScanSummary ScanTake(const Take& take, const TakePlan& plan, const std::filesystem::path& out,
                     const ScanOptions& options, Report* report = nullptr);
// The same, opening and planning the take first.
ScanSummary ScanTake(const std::filesystem::path& take_dir, const TakeSelection& selection,
                     const std::filesystem::path& out, const ScanOptions& options,
                     Report* report = nullptr);

}  // namespace holocap
