#include "core/rig_alignment.h"

#include <Eigen/Eigenvalues>
#include <algorithm>

#include "core/error.h"

namespace holocap {
namespace {

double MedianOf(std::vector<double> values) {
  std::nth_element(values.begin(), values.begin() + values.size() / 2, values.end());
  return values[values.size() / 2];
}

// The rotation whose difference lies closest to the others' (medoid), then the mean of those
// within three times the median distance from it.
Eigen::Matrix3d RobustMeanRotation(const std::vector<Pose>& rotations) {
  const size_t n = rotations.size();
  auto angle = [](const Pose& a, const Pose& b) {
    return RotationAngleDeg(a.linear().transpose() * b.linear());
  };
  size_t medoid = 0;
  double best = 1e300;
  for (size_t i = 0; i < n; ++i) {
    double sum = 0;
    for (size_t k = 0; k < n; ++k) sum += angle(rotations[i], rotations[k]);
    if (sum < best) {
      best = sum;
      medoid = i;
    }
  }
  std::vector<double> distance(n);
  for (size_t i = 0; i < n; ++i) distance[i] = angle(rotations[medoid], rotations[i]);
  const double limit = std::max(3 * MedianOf(distance), 1e-9);
  std::vector<Pose> kept;
  for (size_t i = 0; i < n; ++i) {
    if (distance[i] <= limit) kept.push_back(rotations[i]);
  }
  return AveragePoses(kept).linear();
}

// The mean of the offsets within three times the median spread of their per-axis median.
Eigen::Vector3d RobustMeanOffset(const std::vector<Eigen::Vector3d>& offsets) {
  Eigen::Vector3d median;
  for (int d = 0; d < 3; ++d) {
    std::vector<double> v;
    for (const auto& o : offsets) v.push_back(o[d]);
    median[d] = MedianOf(v);
  }
  std::vector<double> spread;
  for (const auto& o : offsets) spread.push_back((o - median).norm());
  const double limit = std::max(3 * MedianOf(spread), 1e-12);
  Eigen::Vector3d offset = Eigen::Vector3d::Zero();
  int used = 0;
  for (size_t i = 0; i < offsets.size(); ++i) {
    if (spread[i] > limit) continue;
    offset += offsets[i];
    ++used;
  }
  return offset / std::max(used, 1);
}

}  // namespace

Pose AveragePoses(const std::vector<Pose>& poses) {
  if (poses.empty()) Fail("AveragePoses of nothing");
  Eigen::Matrix4d accumulate = Eigen::Matrix4d::Zero();
  Eigen::Vector3d translation = Eigen::Vector3d::Zero();
  const Eigen::Quaterniond first(poses[0].linear());
  for (const Pose& p : poses) {
    Eigen::Quaterniond q(p.linear());
    if (q.dot(first) < 0) q.coeffs() = -q.coeffs();
    accumulate += q.coeffs() * q.coeffs().transpose();
    translation += p.translation();
  }
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix4d> eigen(accumulate);
  Eigen::Quaterniond mean(Eigen::Vector4d(eigen.eigenvectors().col(3)));
  Pose result = Pose::Identity();
  result.linear() = mean.normalized().toRotationMatrix();
  result.translation() = translation / static_cast<double>(poses.size());
  return result;
}

Pose AlignRigs(const std::map<std::string, CameraModel>& in_from,
               const std::map<std::string, CameraModel>& in_to) {
  Pose to_from_from = Pose::Identity();
  std::vector<Pose> rotations;
  for (const auto& [name, from] : in_from) {
    auto to = in_to.find(name);
    if (to == in_to.end()) continue;
    Pose r = Pose::Identity();
    r.linear() = to->second.world_from_cam().linear() * from.cam_from_world().linear();
    rotations.push_back(r);
  }
  if (rotations.empty()) return to_from_from;
  to_from_from.linear() = RobustMeanRotation(rotations);
  std::vector<Eigen::Vector3d> offsets;
  for (const auto& [name, from] : in_from) {
    auto to = in_to.find(name);
    if (to == in_to.end()) continue;
    offsets.push_back(to->second.center_in_world() -
                      to_from_from.linear() * from.center_in_world());
  }
  to_from_from.translation() = RobustMeanOffset(offsets);
  return to_from_from;
}

}  // namespace holocap
