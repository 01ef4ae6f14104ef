// An axis-aligned box in world coordinates, metres: the one box type of every stage (capture
// volumes, reconstruction bounds, an avatar's volume).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace holocap {

struct Box {
  Eigen::Vector3d min = Eigen::Vector3d(-1.5, -1.5, 0.0);
  Eigen::Vector3d max = Eigen::Vector3d(1.5, 1.5, 2.5);

  bool Contains(const Eigen::Vector3d& point) const {
    return (point.array() >= min.array()).all() && (point.array() <= max.array()).all();
  }
  bool valid() const { return (max.array() > min.array()).all(); }
  Eigen::Vector3d size() const { return max - min; }
  Eigen::Vector3d center() const { return 0.5 * (min + max); }
  static Box From(const Eigen::AlignedBox3d& box) { return {box.min(), box.max()}; }
  Eigen::AlignedBox3d aligned() const { return {min, max}; }
};

}  // namespace holocap
