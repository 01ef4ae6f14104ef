// An axis-aligned box in world coordinates, metres: the one box type of every stage (capture
// volumes, reconstruction bounds, a take plan's bounds, an avatar's volume, a splat scene).
#pragma once

#include <limits>

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace holocap {

struct Box {
  Eigen::Vector3d min = Eigen::Vector3d(-1.5, -1.5, 0.0);
  Eigen::Vector3d max = Eigen::Vector3d(1.5, 1.5, 2.5);

  // The box that holds nothing: min above max on every axis, so that Extend() by a point makes
  // the point's own box and Intersection() with it stays empty.
  static Box Empty() {
    return {Eigen::Vector3d::Constant(std::numeric_limits<double>::max()),
            Eigen::Vector3d::Constant(std::numeric_limits<double>::lowest())};
  }

  bool Contains(const Eigen::Vector3d& point) const {
    return (point.array() >= min.array()).all() && (point.array() <= max.array()).all();
  }
  // Holds a point (min <= max on every axis; a flat box is not empty).
  bool empty() const { return (min.array() > max.array()).any(); }
  // Has a volume (max > min on every axis).
  bool valid() const { return (max.array() > min.array()).all(); }
  Eigen::Vector3d size() const { return max - min; }
  Eigen::Vector3d center() const { return 0.5 * (min + max); }
  double Volume() const { return empty() ? 0.0 : size().prod(); }
  // Corner k (0-7): bit d of k picks max over min on axis d.
  Eigen::Vector3d Corner(int k) const {
    return {(k & 1) ? max.x() : min.x(), (k & 2) ? max.y() : min.y(), (k & 4) ? max.z() : min.z()};
  }
  Box& Extend(const Eigen::Vector3d& point) {
    min = min.cwiseMin(point);
    max = max.cwiseMax(point);
    return *this;
  }
  Box& Extend(const Box& other) {
    min = min.cwiseMin(other.min);
    max = max.cwiseMax(other.max);
    return *this;
  }
  Box Intersection(const Box& other) const {
    return {min.cwiseMax(other.min), max.cwiseMin(other.max)};
  }
  // Grown by `margin` on every side (shrunk if negative).
  Box Grown(double margin) const { return {min.array() - margin, max.array() + margin}; }
  bool operator==(const Box& other) const { return min == other.min && max == other.max; }
};

}  // namespace holocap
