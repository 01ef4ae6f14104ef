// A simulated rig in motion: its sensors (true models, ray tables, clocks) and its scene,
// shared by SimulateTake and the sim: driver so that both render identical frames.
#pragma once

#include <array>
#include <cstdint>
#include <deque>
#include <memory>
#include <mutex>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/take.h"
#include "sim/render.h"
#include "sim/scene.h"
#include "sim/sim.h"

namespace holocap::sim {

// The take's world from the simulation's own (z up, metres): scaled by SimOptions::world_scale
// and turned so that the simulation's +z becomes SimOptions::up. A camera's own frame scales
// with the world, so it sees the same image.
class WorldFrame {
 public:
  explicit WorldFrame(const SimOptions& options);
  double scale() const { return scale_; }
  const Eigen::Matrix3d& rotation() const { return rotation_; }
  Eigen::Vector3d Point(const Eigen::Vector3d& point_in_sim) const {
    return scale_ * (rotation_ * point_in_sim);
  }
  // world_from_x from sim_from_x, for any rigid x (a camera, the board) that scales alike.
  Pose FromSim(const Pose& sim_from_x) const;
  CameraModel Camera(const CameraModel& in_sim) const;  // the same lens, posed in the world
  Mesh Transformed(const Mesh& in_sim) const;

 private:
  double scale_ = 1;
  Eigen::Matrix3d rotation_ = Eigen::Matrix3d::Identity();
};

// How the sensors (or the subject) move during a take (SimOptions::trajectory). Every motion
// is the identity at t = 0, so the rig's poses are the poses of the first frame set.
enum class TrajectoryKind { kFixed, kOrbit, kHandheld, kTurn };
TrajectoryKind TrajectoryKindFromString(const std::string& text);  // throws Error
const char* ToString(TrajectoryKind kind);

class Trajectory {
 public:
  // `center`: a point on the vertical axis that orbits and turns go around (simulation world).
  Trajectory(TrajectoryKind kind, double deg_per_s, const Eigen::Vector3d& center, uint64_t seed);
  TrajectoryKind kind() const { return kind_; }
  bool moves_sensor() const {
    return kind_ == TrajectoryKind::kOrbit || kind_ == TrajectoryKind::kHandheld;
  }
  bool moving() const { return kind_ != TrajectoryKind::kFixed; }
  // A sensor's pose at `t_s` from its pose at t = 0 (simulation world). Orbit: turned about
  // the axis, bobbing 3 cm; handheld: an uneven arc around the axis whose distance and height
  // wander by 15 and 10 cm while the aim drifts by 2 degrees, plus hand tremor (0.3 degrees
  // and 1.5 mm at 4-11 Hz).
  Pose WorldFromCam(const Pose& world_from_cam_at_0, double t_s) const;
  // The subject's rigid motion (turn: about the axis; otherwise the identity): where a point of
  // the subject at t = 0 is at `t_s`.
  Pose WorldFromSubject(double t_s) const;

 private:
  Pose TurnAbout(double angle_rad) const;
  TrajectoryKind kind_;
  double rad_per_s_;
  Eigen::Vector3d center_;
  std::array<double, 8> phase_{};
};

struct SimSensorState {
  SensorSpec spec;
  CameraModel model;      // the true model in the take's world (written to gt/, known_model())
  CameraModel sim_model;  // the same lens in the simulation's world (rendering)
  StreamInfo stream;
  std::shared_ptr<const RayTable> rays;  // built on first use
  double clock_offset_ns = 0;            // this sensor's clock minus true time
  double exposure_offset_s = 0;          // true exposure time minus the set's nominal time
  double exposure_us = 0;                // exposure time
  double gain_db = 0;
};

struct SensorFrame {
  cv::Mat image;       // bgr8, bgra8 or depth_m (take's metres), as the stream says
  cv::Mat mask;        // subject silhouette at pixel centres, 0/255
  cv::Mat true_depth;  // depth sensors: exact z-depth, metres of the take's world
  double time_s = 0;   // true mid-exposure time
  int64_t timestamp_ns = 0;
};

class SimWorld {
 public:
  // Loads the rig, builds the sensors' true models and the scene. Throws Error.
  explicit SimWorld(const SimOptions& options);

  const SimOptions& options() const { return options_; }
  const RigDescription& rig() const { return rig_; }
  double fps() const { return fps_; }
  const Scene& scene() const { return *scene_; }
  const WorldFrame& frame() const { return frame_; }
  int size() const { return static_cast<int>(sensors_.size()); }
  const SimSensorState& sensor(int index) const { return sensors_[index]; }
  int IndexOf(const std::string& name) const;  // -1 if absent
  std::vector<StreamInfo> streams() const;

  // Builds every ray table now (in parallel inside each), so later renders do not wait.
  void PrepareRayTables(int threads);
  // The world at an instant, shared between sensors that render the same instant.
  std::shared_ptr<const Snapshot> SnapshotAt(double t_s, int64_t set) const;
  // Whether sensor `index` loses frame `set` (drop_probability, fixed by the seed).
  bool Dropped(int index, int64_t set) const;
  // Renders frame `set` of sensor `index` at its own exposure time; thread-safe.
  SensorFrame Render(int index, int64_t set, int threads) const;
  // Exact noise-free timestamp part: nominal time + exposure offset + clock offset.
  double TrueTime(int index, int64_t set) const;
  const Trajectory& trajectory() const { return *trajectory_; }
  // Sensor `index` at `t_s` along the trajectory: in the simulation's world (rendering) and
  // as ground truth in the take's world. For a turning subject the ground truth is relative to
  // the subject (the take's world as the subject is at t = 0), which is what a scan recovers.
  CameraModel SimModelAt(int index, double t_s) const;
  CameraModel TrueModelAt(int index, double t_s) const;

 private:
  const RayTable& Rays(int index) const;

  SimOptions options_;
  RigDescription rig_;
  double fps_ = 30;
  WorldFrame frame_;
  std::vector<SimSensorState> sensors_;
  std::unique_ptr<Scene> scene_;
  std::unique_ptr<Trajectory> trajectory_;
  mutable std::mutex mutex_;
  mutable std::vector<std::shared_ptr<const RayTable>> rays_;
  mutable std::deque<std::pair<std::pair<double, int64_t>, std::shared_ptr<const Snapshot>>>
      snapshots_;
};

// Timestamps start here so that clock offsets never make them negative.
inline constexpr int64_t kSimClockStartNs = 1000000000;

}  // namespace holocap::sim
