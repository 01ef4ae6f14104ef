#include "core/trajectory.h"

#include <cmath>
#include <cstdio>
#include <sstream>

#include "core/error.h"

namespace holocap {

std::string TumLine(double time_s, const Pose& world_from_cam) {
  const Eigen::Quaterniond q(world_from_cam.linear());
  const Eigen::Vector3d& t = world_from_cam.translation();
  char line[256];
  std::snprintf(line, sizeof(line), "%.6f %.9f %.9f %.9f %.9f %.9f %.9f %.9f\n", time_s, t.x(),
                t.y(), t.z(), q.x(), q.y(), q.z(), q.w());
  return line;
}

std::vector<StampedPose> ParseTum(const std::string& text, const std::string& where) {
  std::vector<StampedPose> poses;
  std::istringstream lines(text);
  std::string line;
  for (int number = 1; std::getline(lines, line); ++number) {
    const size_t start = line.find_first_not_of(" \t\r");
    if (start == std::string::npos || line[start] == '#') continue;
    std::istringstream fields(line);
    double v[8];
    for (double& value : v) {
      if (!(fields >> value) || !std::isfinite(value)) {
        Fail(where, " line ", number, ": expected 'time tx ty tz qx qy qz qw', got '", line, "'");
      }
    }
    const Eigen::Quaterniond q(v[7], v[4], v[5], v[6]);
    if (std::abs(q.norm() - 1) > 1e-3) Fail(where, " line ", number, ": quaternion not unit");
    StampedPose pose;
    pose.time_s = v[0];
    pose.world_from_cam.linear() = q.normalized().toRotationMatrix();
    pose.world_from_cam.translation() = Eigen::Vector3d(v[1], v[2], v[3]);
    poses.push_back(pose);
  }
  return poses;
}

}  // namespace holocap
