// Helpers shared by the calibration sources (not part of the public interface).
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <string>
#include <thread>
#include <vector>

#include "core/pose.h"

namespace holocap::calibration_internal {

// 0 = every core; never more threads than jobs.
inline int ResolveThreads(int requested, int jobs) {
  int threads = requested > 0 ? requested : static_cast<int>(std::thread::hardware_concurrency());
  return std::max(1, std::min(threads, std::max(1, jobs)));
}

// The rigid transform b_from_a minimising sum |b - T a|² (Kabsch/Umeyama without scale).
Pose FitRigid(const std::vector<Eigen::Vector3d>& a, const std::vector<Eigen::Vector3d>& b);

// libapriltag's detection-square width and total width of a family, in bits.
void FamilyGeometry(const std::string& family, int* width_at_border, int* total_width);

// Throws Error unless mrcal knows the (configured) lens model name.
void CheckLensmodelName(const std::string& name);

// Mean of rotations (chordal L2 on quaternions) and translations.
Pose AveragePoses(const std::vector<Pose>& poses);

}  // namespace holocap::calibration_internal

namespace holocap {
using calibration_internal::ResolveThreads;
}
