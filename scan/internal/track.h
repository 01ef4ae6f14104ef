// The pieces of the scanner that its tracker and its driver share (scan/scan.cpp, scan/track.cpp).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/camera.h"
#include "core/pose.h"
#include "core/projector.h"
#include "scan/scan.h"

namespace holocap::scan {

// One level of a depth frame's pyramid: level l holds the means of 2^l x 2^l blocks of the
// finest level's points (those within 3 cm of the block's nearest), camera coordinates.
struct Level {
  int width = 0, height = 0;
  std::vector<Eigen::Vector3f> points;   // NaN: no measurement
  std::vector<Eigen::Vector3f> normals;  // NaN: none (too few neighbours)
  std::vector<float> intensity;          // registered colour intensity in [0, 1]; NaN: none
};

struct TrackFrame {
  std::vector<Level> levels;  // finest first
  int64_t valid = 0;          // valid points at the finest level
  float median_depth_m = 0;
};

// `depth_m`: the depth sensor's z-depth (NaN or out of [min, max]: none); `rays`: its
// NormalisedRays; `gray`: intensity registered to the depth pixels (CV_32F, NaN: none) or empty.
TrackFrame PrepareFrame(const cv::Mat& depth_m, const cv::Mat& rays, const cv::Mat& gray,
                        int levels, double depth_min_m, double depth_max_m);

// The colour image's intensity at each depth pixel's point (CV_32F in [0, 1], NaN where the
// depth or the colour has nothing). `color_from_depth` maps the depth camera's frame to the
// colour camera's.
cv::Mat RegisterIntensity(const cv::Mat& depth_m, const cv::Mat& rays, const cv::Mat& color_bgr,
                          const CameraModel& color_lens, const Pose& color_from_depth, int threads);

// What a reference (the model, or a keyframe) looks like from a pose: world points and
// normals per pixel of the depth camera, and their intensity.
struct ModelView {
  int width = 0, height = 0;
  int stride = 1;  // pixel (x, y) of the view is pixel (stride x, stride y) of the depth camera
  Pose world_from_cam = Pose::Identity();
  std::vector<Eigen::Vector3f> points;   // world; NaN: nothing
  std::vector<Eigen::Vector3f> normals;  // world, unit
  cv::Mat intensity;                     // CV_32F; NaN: none
  int64_t hits = 0;
};

// Raycasts the TSDF's zero crossing from `world_from_cam` through every stride-th pixel of the
// depth camera along each axis, searching each ray within `window_m` of `hint_depth_m` (the
// frame being tracked; pixels without a hint are skipped). Colour from the voxels.
ModelView RaycastModel(const SparseVolume& volume, const cv::Mat& rays, const Pose& world_from_cam,
                       const cv::Mat& hint_depth_m, double window_m, int stride, int threads);
// A keyframe's own finest level as a reference, posed at `world_from_cam`.
ModelView ViewOfFrame(const TrackFrame& frame, const Pose& world_from_cam);

struct AlignResult {
  Pose world_from_cam = Pose::Identity();
  int64_t points = 0;   // valid points at the finest level
  int64_t inliers = 0;  // of them paired at the last iteration
  double inlier_fraction = 0;
  double residual_m = 0;           // point-to-plane RMS of the pairs
  double condition = 0;            // smallest / largest eigenvalue of the scaled Hessian
  double geometric_condition = 0;  // the same without the photometric term
  Eigen::Vector3d weak_direction = Eigen::Vector3d::Zero();
  int iterations = 0;
};

// Gauss-Newton over the pyramid from `initial` (world_from_cam of `frame`), pairing each point
// with the reference pixel it projects to (`lens`: the depth camera's lens). Directions whose
// Hessian eigenvalue falls below min_condition of the largest keep the initial pose.
AlignResult AlignToReference(const TrackFrame& frame, const ModelView& reference,
                             const CameraModel& lens, const Pose& initial,
                             const ScanOptions& options, int threads);

// A small rigid motion from a twist (translation, then rotation vector), applied on the left.
Pose ExpTwist(const Eigen::Matrix<double, 6, 1>& twist);

}  // namespace holocap::scan
