// The pieces of live/ that its alignment, deformation and composition share.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cmath>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <vector>

#include "live/live.h"

namespace holocap::live {

// A scan point paired with the live surface: the live point and its normal.
struct Pair {
  int index = 0;  // into the points associated
  Eigen::Vector3d point, normal;
};

// Huber's weight of a residual (1 inside the threshold).
inline double HuberWeight(double residual, double threshold) {
  const double magnitude = std::abs(residual);
  return magnitude <= threshold ? 1.0 : threshold / magnitude;
}

// The rotation of a rotation vector.
inline Eigen::Matrix3d SmallRotation(const Eigen::Vector3d& omega) {
  const double angle = omega.norm();
  if (angle < 1e-12) return Eigen::Matrix3d::Identity();
  return Eigen::AngleAxisd(angle, omega / angle).toRotationMatrix();
}

// About `samples` vertex indices spread evenly over a mesh's vertex list.
std::vector<int> ThinnedVertices(size_t vertices, int samples);

// Projective association: each point facing the sensor is compared with the live pixel it
// projects to (points over no measurement, or hidden behind the live surface by more than the
// gate, are not expected to be seen). The inliers (within `gate_m`, normals within the angle)
// go to `pairs` (optional).
FitStats Associate(const std::vector<Eigen::Vector3f>& points,
                   const std::vector<Eigen::Vector3f>& normals, const LiveSurface& live,
                   double gate_m, double max_normal_angle_deg, std::vector<Pair>* pairs);

// The other way round: about `live_samples` live points, each paired with the nearest point
// facing the sensor (within the gate and the normal angle). These pull a part of the scan
// towards live surface it does not yet cover (a limb bent elsewhere), which projective pairs
// never see.
void AddNearestPairs(const std::vector<Eigen::Vector3f>& points,
                     const std::vector<Eigen::Vector3f>& normals, const LiveSurface& live,
                     double gate_m, double max_normal_angle_deg, int live_samples,
                     std::vector<Pair>* pairs);

// Colour as three channels (grey and BGRA frames converted; empty stays empty).
cv::Mat ThreeChannels(const cv::Mat& frame);
// OUT_RECON/<set>.ply and, with `glb`, <set>.glb.
void WriteComposed(const std::filesystem::path& recon, int64_t set, const Mesh& mesh, bool glb);
// Counts the frames' states and ends `summary` (see LiveSummary).
void Conclude(const LiveOptions& options, LiveSummary* summary);
// A composed frame's fit in the report's series (nothing for other states or no report).
void RecordFrame(Report* report, const LiveFrame& frame);
// The report's metrics of a run: counts, sensors, every frame.
nlohmann::json SummaryMetrics(const LiveSummary& summary);
}  // namespace holocap::live
