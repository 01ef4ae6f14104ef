// The simulated rig: a studio with an animated subject, a static object or a calibration board,
// seen by colour cameras and depth sensors whose lenses, poses, clocks and noise are known
// exactly. It writes takes with ground truth (SimulateTake) and is the HAL driver `sim:`.
//
// World: z up, floor at z = 0, metres. The studio is a closed room [-5, 5] x [-5, 5] x [0, 3.5]
// with a textured floor and walls, lit by a fixed directional light plus ambient light, without
// shadows, so the background never changes and a frame without the subject is a clean plate.
//
// Rendering is ray casting through each sensor's true mrcal model (a per-pixel ray table from
// CameraModel::UnprojectMany, interpolated bilinearly for sub-pixel samples). Colour pixels
// are the average radiance over the pixel's area: pixels whose neighbours see another surface
// or another board cell are supersampled (N x N stratified jittered samples), and pixels that
// lie wholly on the board are integrated exactly over their footprint (Board::MeanReflectance).
// The colour response is linear: DN = 255 * radiance * exposure_ratio * gain, with shot noise
// (Poisson, as Gaussian) and read noise in electrons. Depth sensors report z-depth (metres,
// quantised to millimetres like Z16 devices), with noise sigma(z) = depth_noise_k * z^2 and
// no measurement (NaN) at grazing incidence, at depth edges and outside their range.
//
// Rig files. Built-in rigs are "studio8", "single-rgbd" and "sphereN" (N colour cameras, 2 to
// 1000, spread over a sphere around the object scene; see BuiltinRig); any other name is a rig file
// (RigDescription::Load, YAML or JSON) whose sensors carry their simulation settings in
// `options`:
//
//   sensors:
//     - name: cam0
//       uri: sim:myrig#cam0           # any sim: URI; the fragment names the sensor
//       role: color                   # color | depth
//       options:
//         lens: LENSMODEL_OPENCV5     # mrcal lens model name ...
//         intrinsics: [fx, fy, cx, cy, k1, k2, p1, p2, k3]
//         size: [640, 480]            # imager width, height the intrinsics are for
//         # cameramodel: lens.cameramodel   # ... or an mrcal file (relative to the rig file);
//         #                                 # its pose is used unless a position is given
//         position: [3.0, 0.0, 1.5]   # camera centre in the world, metres
//         look_at: [0.0, 0.0, 1.0]    # a point on the optical axis (image "up" is world +z)
//     - name: depth0
//       uri: sim:myrig#depth0
//       role: depth
//       paired_with: cam0
//       options:
//         lens: LENSMODEL_OPENCV4
//         intrinsics: [570, 570, 319.5, 239.5, 0, 0, 0, 0]
//         size: [640, 480]
//         depth_from_color: [0, 0, 0, -0.025, 0, 0]   # mrcal rt from the paired colour camera,
//                                                     # used instead of position/look_at
//
// Variants: the same rig and scene as a capture a user brings would record them. The
// simulation always renders its own world (z up, metres); the take's world is that one scaled
// by world_scale and turned so that its +z points along `up`. Camera poses, ground-truth meshes,
// board poses and layout, depth (metres, noise and quantisation scaled alike) are all written
// in the take's world, so images are identical and only the numbers describing them change:
// world_scale 0.05 turns the walking 1.8 m person seen from 3 m into a 9 cm object seen from
// 15 cm; up -y gives a y-down world. rig positions in take.json stay in the simulation's world
// (they describe the sim rig, not the take). color_only drops the depth sensors (a camera ring);
// subject_albedo and background_albedo darken the subject and the room (a dark object on a
// dark backdrop); alpha writes colour as BGRA with the exact silhouette in alpha.
#pragma once

#include <cstdint>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "capture/hal.h"
#include "core/board.h"
#include "core/camera.h"
#include "core/report.h"
#include "core/rig.h"

namespace holocap {

struct SimOptions {
  std::string rig = "studio8";     // "studio8", "single-rgbd", or a rig file (see above)
  int64_t frames = 30;             // frame sets to simulate
  std::string scene = "subject";   // "subject" (walking humanoid), "object" (static knot on a
                                   // pedestal) or "board" (calibration board sequence)
  uint64_t seed = 1;               // seeds the board poses, clocks, noise and drops
  int image_width = 0;             // > 0: render every sensor at this width (lens rescaled)
  int image_height = 0;            // > 0 with image_width: this height (centred crop/pad);
                                   // 0: the sensor's own aspect ratio
  double fps = 0;                  // frame sets per second; 0: the rig's fps
  int64_t clean_plate_frames = 0;  // leading frame sets rendered without the subject/object
  BoardLayout board = DefaultSimBoard();  // the board of the "board" scene
  // The board scene's board stays where the first pose two cameras share puts it (cam0 and
  // cam1 of a ring) in every frame set: a take from which no lens can be calibrated.
  bool board_still = false;
  // The share (0..1) of the board scene's single-camera views whose board reaches past the
  // image's edge: 35-85 % of its grid points in view, the rest outside (partial views, as a
  // hand-held board gives). Shared views keep the whole board in both cameras.
  double board_partial = 0;
  // Sensors mounted upside down: turned 180 degrees about their optical axes, so that they see
  // the board (and everything) rotated by 180 degrees against the other cameras.
  std::vector<std::string> upside_down;
  // How the sensors move (scan takes): "fixed"; "orbit" (every sensor circles the vertical
  // axis through the subject's centre, bobbing 3 cm); "handheld" (an uneven walk around the
  // subject: distance and height wander by 15 and 10 cm, the aim drifts, the hand trembles,
  // and colour frames integrate the motion over their exposure); "turn" (the sensors stay,
  // the subject turns on the spot about that axis). With any of these the subject holds its
  // first pose (it does not walk). The true pose of every frame is in gt/ (see SimulateTake).
  std::string trajectory = "fixed";
  double trajectory_deg_per_s = 30;  // angular speed around the axis (orbit, handheld, turn)

  // The take's world (see "Variants" above). Rendering is the same for every choice.
  double world_scale = 1;                         // everything scaled by this, > 0
  Eigen::Vector3d up = Eigen::Vector3d::UnitZ();  // the take's up axis (any direction)
  bool color_only = false;                        // leave the rig's depth sensors out
  double subject_albedo = 1;                      // multiplies the subject's albedo, (0, 1]
  double background_albedo = 1;                   // multiplies the room's albedo, (0, 1]
  bool alpha = false;  // colour streams "bgra8", the true silhouette (0/255) in alpha

  // Colour sensor response.
  bool noise = true;                    // shot and read noise (false: exact, deterministic)
  double full_well_electrons = 8000;    // electrons at DN 255 with unit gain
  double read_noise_electrons = 4;      // Gaussian read noise, electrons
  double exposure_us = 8000;            // exposure of sensors whose rig entry leaves it at 0
  double exposure_scale = 1;            // multiplies every exposure (brightness), > 0
  double gain_db = 0;                   // added to every sensor's own gain
  double reference_exposure_us = 8000;  // the exposure at which a white wall reads ~230 DN
  int antialias = 4;                    // N: edge pixels get N x N samples; 1 = centre only
  bool motion_blur = false;             // integrate the scene over each exposure
  int motion_blur_samples = 5;          // time samples per exposure when motion_blur is on

  // Depth sensors.
  double depth_noise_k = 0.0012;         // sigma(z) = k * z^2, 1/m (0.0012: 4.8 mm at 2 m)
  double depth_max_incidence_deg = 75;   // no measurement beyond this angle to the normal
  double depth_edge_threshold_m = 0.05;  // no measurement next to a jump in depth of more
  double depth_min_m = 0.3;              // nearest measurable z-depth
  double depth_max_m = 6.0;              // farthest measurable z-depth
  double depth_dropout_probability = 0;  // extra random missing pixels

  // Timing and delivery.
  double timestamp_jitter_ns = 50000;    // sigma of Gaussian timestamp jitter per frame
  double clock_offset_max_ns = 2000000;  // each sensor's clock offset ~ U(-max, max)
  double drop_probability = 0;           // chance that a sensor loses a given frame
  int threads = 0;                       // render threads; 0: all cores
  bool overwrite = false;                // replace an existing take directory

  // Throws Error with the reason when a field is out of range.
  void Check() const;
  nlohmann::json ToJson() const;

  static BoardLayout DefaultSimBoard();  // tag36h11, 5 x 4 tags, 10 cm spacing
};

// Ends SUCCESS when every frame set was written, FAILURE when writing stopped it (the take keeps
// the sets written before).
struct SimSummary : Summary {
  int64_t frame_sets = 0;      // frame sets written
  int64_t frames_written = 0;  // sensor frames written
  int64_t frames_dropped = 0;  // sensor frames dropped on purpose (drop_probability)
  double seconds = 0;          // wall time of the whole simulation
  double frame_sets_per_minute = 0;
  double render_seconds = 0;  // of which rendering (the rest: setup, encoding, writing)
};

// Simulates a take into `out` (a new directory): frames through TakeWriter (colour "bgr8" PNG,
// or "bgra8" with the silhouette in alpha when options.alpha; depth "depth_m" EXR in metres,
// NaN = no measurement; clock "sim") and ground truth, all in the take's world (see Variants):
//   gt/cameras/<sensor>.cameramodel   true lens and cam_from_world of every sensor
//   gt/meshes/<set:06d>.ply           the subject in world coordinates at the set's nominal
//                                     time set / fps (clean plates have none)
//   gt/meshes/static.ply              the static object (object scene), world coordinates
//   gt/masks/<sensor>/<set:06d>.png   the subject's silhouette (255) per delivered frame
//   gt/depth/<sensor>/<set:06d>.exr   true z-depth (metres) for depth sensors
//   gt/board.json                     board layout and per-set world_from_board (board scene)
//   gt/trajectory/<sensor>.tum        moving takes: every delivered frame's true world_from_cam
//                                     as TUM lines "time_s tx ty tz qx qy qz qw" (time_s: the
//                                     frame's true mid-exposure time); a turning subject's are
//                                     relative to the subject (the world as it is at t = 0)
//   gt/sim.json                       options, per-sensor clock offsets, exposure times,
//                                     every frame's true time and timestamp, dropped frames,
//                                     noise parameters, depth_from_color of paired sensors,
//                                     and each frame's true cam_from_world when sensors move
// `report` (optional) gets the options, metrics and a frame-sets-per-minute series.
// Throws Error for bad options or an unwritable directory.
SimSummary SimulateTake(const SimOptions& options, const std::filesystem::path& out,
                        Report* report = nullptr);

// Built-in rigs. "studio8": eight 640x480-class colour cameras on a 3 m ring around a 2 m
// stage (one of them the real OPENCV8 wide lens rescaled, one stereographic 112-degree lens,
// the rest OPENCV4/5/8 with modest distortion) and two 640x480 depth sensors paired with cam2
// and cam6. "single-rgbd": one colour camera cam0 and one depth sensor depth0.
std::vector<std::string> BuiltinRigNames();
// studio8, single-rgbd or sphereN; throws Error for an unknown name.
RigDescription BuiltinRig(const std::string& name);
// A built-in rig by name, otherwise the rig file at `name_or_path`.
RigDescription LoadSimRig(const std::string& name_or_path);

// The true model (lens, imager size and cam_from_world) of a sensor of a sim rig, optionally
// re-rendered at another size (width > 0; height 0 keeps the aspect ratio). `base_dir`
// resolves relative .cameramodel paths. Throws Error naming the sensor and field.
CameraModel SimSensorModel(const RigDescription& rig, const SensorSpec& sensor, int width = 0,
                           int height = 0, const std::filesystem::path& base_dir = {});

// Registers the `sim:` driver. URIs: "sim:<rig>#<sensor>", e.g. "sim:studio8#cam3",
// "sim:single-rgbd#depth0", or a rig file path as <rig>. Sensor options (SensorSpec.options,
// all optional): scene, seed, frames (0 = endless), width, height, noise, antialias. Sensors
// of one rig with the same scene and seed share one world; each Grab renders the sensor's
// next frame at its own time. known_model() is the true model.
void RegisterSimDriver(DriverRegistry& registry);

}  // namespace holocap
