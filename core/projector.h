// Fast, distortion-aware projection for inner loops: mrcal projects each point exactly but one
// call per voxel would dominate fusion and carving, so a camera's projection is tabulated once
// over normalised coordinates (x/z, y/z) with mrcal itself and looked up bilinearly. The
// tables are dense enough that the error stays far below a hundredth of a pixel for the lenses
// holocap meets (tests compare against CameraModel::Project).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <algorithm>
#include <memory>
#include <opencv2/core.hpp>
#include <vector>

#include "core/camera.h"

namespace holocap {

// The pose-independent part: pixel positions over a grid of normalised coordinates.
struct ProjectionTable {
  int width = 0, height = 0;
  float a0 = 0, b0 = 0, inv_step_a = 0, inv_step_b = 0;
  int cells_a = 0, cells_b = 0;
  float focal = 1;
  std::vector<Eigen::Vector2f> nodes;
};

class FastProjector {
 public:
  // Tables are cached per lens (model, intrinsics, size), so building a projector for a
  // camera seen before costs nothing.
  explicit FastProjector(const CameraModel& camera);

  // World point -> camera coordinates.
  Eigen::Vector3f ToCamera(const Eigen::Vector3f& point_in_world) const {
    return rotation_ * point_in_world + translation_;
  }
  // Camera point -> pixel. False behind the camera or outside the tabulated field of view
  // (which covers the whole image with a margin).
  bool Project(const Eigen::Vector3f& point_in_cam, float* u, float* v) const {
    if (point_in_cam.z() <= 1e-6f) return false;
    float a = point_in_cam.x() / point_in_cam.z();
    float b = point_in_cam.y() / point_in_cam.z();
    const ProjectionTable& t = *table_;
    float ga = (a - t.a0) * t.inv_step_a;
    float gb = (b - t.b0) * t.inv_step_b;
    if (!(ga >= 0 && gb >= 0 && ga < t.cells_a && gb < t.cells_b)) return false;
    int ia = static_cast<int>(ga);
    int ib = static_cast<int>(gb);
    float fa = ga - ia;
    float fb = gb - ib;
    const Eigen::Vector2f* row0 = &t.nodes[ib * (t.cells_a + 1) + ia];
    const Eigen::Vector2f* row1 = row0 + (t.cells_a + 1);
    Eigen::Vector2f p =
        (1 - fb) * ((1 - fa) * row0[0] + fa * row0[1]) + fb * ((1 - fa) * row1[0] + fa * row1[1]);
    *u = p.x();
    *v = p.y();
    return true;
  }
  bool ProjectWorld(const Eigen::Vector3f& point_in_world, float* u, float* v, float* z) const {
    Eigen::Vector3f p = ToCamera(point_in_world);
    *z = p.z();
    return Project(p, u, v);
  }
  bool InImage(float u, float v, float margin = 0) const {
    return u >= -0.5f + margin && v >= -0.5f + margin && u <= width_ - 0.5f - margin &&
           v <= height_ - 0.5f - margin;
  }
  // Pixels per unit of normalised coordinate near the image centre: turns a distance in
  // pixels at depth z into metres (metres = pixels * z / focal).
  float focal() const { return table_->focal; }
  int width() const { return width_; }
  int height() const { return height_; }
  const CameraModel& camera() const { return camera_; }

 private:
  CameraModel camera_;
  Eigen::Matrix3f rotation_;
  Eigen::Vector3f translation_;
  int width_ = 0, height_ = 0;
  std::shared_ptr<const ProjectionTable> table_;
};

// The viewing ray of every pixel as normalised coordinates (x/z, y/z): CV_32FC2, NaN where
// the lens cannot unproject or the ray points backwards. Cached per lens like the tables.
cv::Mat NormalisedRays(const CameraModel& camera);

// Bilinear sample of a single-channel CV_32F image at a pixel position; false outside.
inline bool SampleBilinear(const cv::Mat& image, float u, float v, float* value) {
  if (!(u >= 0 && v >= 0 && u <= image.cols - 1 && v <= image.rows - 1)) return false;
  int x = std::min(static_cast<int>(u), image.cols - 2);
  int y = std::min(static_cast<int>(v), image.rows - 2);
  if (x < 0 || y < 0) return false;
  float fx = u - x, fy = v - y;
  const float* r0 = image.ptr<float>(y) + x;
  const float* r1 = image.ptr<float>(y + 1) + x;
  *value = (1 - fy) * ((1 - fx) * r0[0] + fx * r0[1]) + fy * ((1 - fx) * r1[0] + fx * r1[1]);
  return true;
}

}  // namespace holocap
