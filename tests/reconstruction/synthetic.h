// Synthetic scenes with exact answers for the reconstruction tests: spheres seen by pinhole
// and distorted cameras, their depth maps and silhouettes rendered analytically.
#pragma once

#include <Eigen/Core>
#include <cmath>
#include <limits>
#include <opencv2/core.hpp>
#include <vector>

#include "core/camera.h"
#include "core/mesh.h"
#include "core/pose.h"
#include "reconstruction/reconstruction.h"

namespace holocap::testing {

struct Sphere {
  Eigen::Vector3d centre = Eigen::Vector3d(0, 0, 1);
  double radius = 0.3;
};

// Cameras on a ring of `radius` around the sphere's centre, at heights alternating around it.
inline std::vector<CameraModel> RingCameras(int count, const Sphere& sphere, double radius,
                                            int width = 320, int height = 240,
                                            bool distorted = true) {
  std::vector<CameraModel> cameras;
  for (int i = 0; i < count; ++i) {
    double azimuth = 2 * M_PI * i / count;
    Eigen::Vector3d eye =
        sphere.centre + Eigen::Vector3d(radius * std::cos(azimuth), radius * std::sin(azimuth),
                                        (i % 2 ? 0.4 : -0.2) * radius);
    Pose pose = CamFromWorldLookAt(eye, sphere.centre);
    double f = 0.9 * width;
    if (distorted && i % 2 == 1) {
      cameras.emplace_back("LENSMODEL_OPENCV4",
                           std::vector<double>{f, f, 0.5 * (width - 1) + 3, 0.5 * (height - 1) - 2,
                                               -0.12, 0.04, 0.001, -0.0005},
                           width, height, pose);
    } else {
      cameras.push_back(CameraModel::Pinhole(f, width, height, pose));
    }
  }
  return cameras;
}

// Distance along a unit ray to the sphere (infinity when missed).
inline double RaySphere(const Eigen::Vector3d& origin, const Eigen::Vector3d& direction,
                        const Sphere& s) {
  Eigen::Vector3d oc = origin - s.centre;
  double b = oc.dot(direction);
  double c = oc.squaredNorm() - s.radius * s.radius;
  double disc = b * b - c;
  if (disc < 0) return std::numeric_limits<double>::infinity();
  double t = -b - std::sqrt(disc);
  return t > 0 ? t : std::numeric_limits<double>::infinity();
}

// z-depth (metres, NaN off the sphere) and silhouette of a sphere through a camera.
inline void RenderSphere(const CameraModel& camera, const Sphere& sphere, cv::Mat* depth,
                         cv::Mat* mask) {
  const int w = camera.width(), h = camera.height();
  Eigen::Matrix2Xd pixels(2, w * h);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) pixels.col(y * w + x) << x, y;
  Eigen::Matrix3Xd rays = camera.UnprojectMany(pixels);
  const Eigen::Vector3d origin = camera.center_in_world();
  const Eigen::Matrix3d world_from_cam = camera.world_from_cam().rotation();
  if (depth) *depth = cv::Mat(h, w, CV_32F, cv::Scalar(std::numeric_limits<float>::quiet_NaN()));
  if (mask) *mask = cv::Mat::zeros(h, w, CV_8U);
  for (int i = 0; i < w * h; ++i) {
    Eigen::Vector3d ray = rays.col(i).normalized();
    double t = RaySphere(origin, world_from_cam * ray, sphere);
    if (!std::isfinite(t)) continue;
    if (depth) depth->at<float>(i / w, i % w) = static_cast<float>(t * ray.z());
    if (mask) mask->at<uint8_t>(i / w, i % w) = 255;
  }
}

// A finely tessellated sphere mesh (for surface comparisons).
inline Mesh SphereMesh(const Sphere& s, int rings = 96, int segments = 192) {
  Mesh mesh;
  for (int r = 0; r <= rings; ++r) {
    double theta = M_PI * r / rings;
    for (int k = 0; k < segments; ++k) {
      double phi = 2 * M_PI * k / segments;
      mesh.vertices.push_back(
          (s.centre + s.radius * Eigen::Vector3d(std::sin(theta) * std::cos(phi),
                                                 std::sin(theta) * std::sin(phi), std::cos(theta)))
              .cast<float>());
    }
  }
  for (int r = 0; r < rings; ++r) {
    for (int k = 0; k < segments; ++k) {
      int a = r * segments + k, b = r * segments + (k + 1) % segments;
      int c = (r + 1) * segments + k, d = (r + 1) * segments + (k + 1) % segments;
      mesh.faces.emplace_back(a, c, b);
      mesh.faces.emplace_back(b, c, d);
    }
  }
  return mesh;
}

// Mean and max of | |v - centre| - radius | over a mesh's vertices.
inline std::pair<double, double> SphereError(const Mesh& mesh, const Sphere& s) {
  double sum = 0, worst = 0;
  for (const auto& v : mesh.vertices) {
    double e = std::abs((v.cast<double>() - s.centre).norm() - s.radius);
    sum += e;
    worst = std::max(worst, e);
  }
  return {mesh.vertices.empty() ? 0 : sum / mesh.vertices.size(), worst};
}

}  // namespace holocap::testing
