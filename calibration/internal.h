// Helpers shared by the calibration sources (not part of the public interface).
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <opencv2/core.hpp>
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

// libapriltag's detection-square width and total width of a family, in bits, and whether its
// border is light inside and dark outside.
void FamilyGeometry(const std::string& family, int* width_at_border, int* total_width,
                    bool* reversed_border = nullptr);

// Throws Error unless mrcal knows the (configured) lens model name.
void CheckLensmodelName(const std::string& name);

// Refines `corner` in an 8-bit grey image from the straight edges that leave it along `rays`:
// 2 rays for the L corner of a dark or light square (a tag's), 4 for a chessboard's X
// junction (rays k and k + 2 opposite). Each edge is measured up to `reach_in_px` to its side
// facing the first two rays' wedge and `reach_out_px` to the other, where the image must be
// uniform, and up to `length_px` along it, where it must be straight and alone. False (corner
// unchanged) when the edges cannot be measured or the result moves beyond the reach.
bool RefineEdgeCorner(const cv::Mat& grey, const std::vector<Eigen::Vector2d>& rays,
                      double reach_in_px, double reach_out_px, double length_px,
                      Eigen::Vector2d* corner);

// Mean of rotations (chordal L2 on quaternions) and translations.
Pose AveragePoses(const std::vector<Pose>& poses);

}  // namespace holocap::calibration_internal

namespace holocap {
using calibration_internal::ResolveThreads;
}
