// The sensor trajectories of scan takes: an orbit, a hand-held walk around the subject, and a
// fixed sensor before a subject turning on the spot.
#include <cmath>
#include <numbers>
#include <random>

#include "core/error.h"
#include "sim/world.h"

namespace holocap::sim {
namespace {

constexpr double kPi = std::numbers::pi;
constexpr double kDeg = kPi / 180;

Eigen::Matrix3d SmallRotation(const Eigen::Vector3d& angles_rad) {
  return (Eigen::AngleAxisd(angles_rad.z(), Eigen::Vector3d::UnitZ()) *
          Eigen::AngleAxisd(angles_rad.y(), Eigen::Vector3d::UnitY()) *
          Eigen::AngleAxisd(angles_rad.x(), Eigen::Vector3d::UnitX()))
      .matrix();
}

}  // namespace

TrajectoryKind TrajectoryKindFromString(const std::string& text) {
  if (text == "fixed") return TrajectoryKind::kFixed;
  if (text == "orbit") return TrajectoryKind::kOrbit;
  if (text == "handheld") return TrajectoryKind::kHandheld;
  if (text == "turn") return TrajectoryKind::kTurn;
  Fail("unknown trajectory '", text, "' (known: fixed, orbit, handheld, turn)");
}

const char* ToString(TrajectoryKind kind) {
  switch (kind) {
    case TrajectoryKind::kFixed:
      return "fixed";
    case TrajectoryKind::kOrbit:
      return "orbit";
    case TrajectoryKind::kHandheld:
      return "handheld";
    case TrajectoryKind::kTurn:
      return "turn";
  }
  return "?";
}

Trajectory::Trajectory(TrajectoryKind kind, double deg_per_s, const Eigen::Vector3d& center,
                       uint64_t seed)
    : kind_(kind), rad_per_s_(deg_per_s * kDeg), center_(center) {
  std::mt19937_64 rng(MixSeed(seed, 9));
  std::uniform_real_distribution<double> angle(0, 2 * kPi);
  for (double& phase : phase_) phase = angle(rng);
}

Pose Trajectory::TurnAbout(double angle_rad) const {
  Pose turn = Pose::Identity();
  turn.linear() = Eigen::AngleAxisd(angle_rad, Eigen::Vector3d::UnitZ()).matrix();
  turn.translation() = center_ - turn.linear() * center_;
  return turn;
}

Pose Trajectory::WorldFromSubject(double t_s) const {
  return kind_ == TrajectoryKind::kTurn ? TurnAbout(rad_per_s_ * t_s) : Pose::Identity();
}

Pose Trajectory::WorldFromCam(const Pose& world_from_cam_at_0, double t_s) const {
  if (kind_ == TrajectoryKind::kOrbit) {
    Pose moved = TurnAbout(rad_per_s_ * t_s) * world_from_cam_at_0;
    moved.translation().z() += 0.03 * std::sin(2 * kPi * 0.2 * t_s);
    return moved;
  }
  if (kind_ != TrajectoryKind::kHandheld) return world_from_cam_at_0;
  // Slow wander: each term is zero at t = 0 so that the first frame is the rig's pose.
  const auto wander = [&](double amplitude, double hz, int k) {
    return amplitude * (std::sin(2 * kPi * hz * t_s + phase_[k]) - std::sin(phase_[k]));
  };
  const double angle = rad_per_s_ * t_s + wander(0.15, 0.11, 0);
  Pose moved = TurnAbout(angle) * world_from_cam_at_0;
  Eigen::Vector3d outward = moved.translation() - center_;
  outward.z() = 0;
  if (outward.norm() > 1e-9) moved.translation() += wander(0.15, 0.07, 1) * outward.normalized();
  moved.translation().z() += wander(0.10, 0.13, 2);
  const Eigen::Vector3d drift(wander(2 * kDeg, 0.09, 3), wander(2 * kDeg, 0.06, 4), 0);
  // Tremor: a few incommensurate frequencies in the 4-11 Hz band of a held camera.
  Eigen::Vector3d tremor = Eigen::Vector3d::Zero();
  Eigen::Vector3d jolt = Eigen::Vector3d::Zero();
  const double hz[3] = {4.3, 7.1, 10.7};
  for (int axis = 0; axis < 3; ++axis) {
    for (int k = 0; k < 3; ++k) {
      const double phase = phase_[(axis + k + 5) % 8] + axis;
      const double s = std::sin(2 * kPi * hz[k] * t_s + phase) - std::sin(phase);
      tremor[axis] += 0.1 * kDeg * s;
      jolt[axis] += 0.0005 * s;
    }
  }
  Pose shake = Pose::Identity();
  shake.linear() = SmallRotation(drift + tremor);
  shake.translation() = jolt;
  return moved * shake;
}

}  // namespace holocap::sim
