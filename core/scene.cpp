// The scene as a rig sees it: where the optical axes meet, the box most cameras share, the
// cameras' common up direction and the voxel size that the box and the lenses imply.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <numbers>

#include <Eigen/Eigenvalues>

#include "core/error.h"
#include "core/take_plan.h"

namespace holocap {
namespace {

std::string Format(const char* format, double a, double b = 0, double c = 0, double d = 0) {
  char text[160];
  std::snprintf(text, sizeof(text), format, a, b, c, d);
  return text;
}

double Median(std::vector<double> values) {
  if (values.empty()) return 0;
  const size_t half = values.size() / 2;
  std::nth_element(values.begin(), values.begin() + half, values.end());
  return values[half];
}

// Counts, for every point (3xN), the cameras that see it: in front and inside the image.
std::vector<int> SeenCounts(const std::vector<CameraModel>& cameras, const Eigen::Matrix3Xd& p) {
  std::vector<int> counts(p.cols(), 0);
  for (const CameraModel& camera : cameras) {
    const Eigen::Matrix3Xd in_cam = camera.cam_from_world() * p;
    const Eigen::Matrix2Xd pixels = camera.ProjectMany(in_cam);
    for (Eigen::Index i = 0; i < p.cols(); ++i) {
      counts[i] += in_cam(2, i) > 0 && pixels.col(i).allFinite() && camera.InImage(pixels.col(i));
    }
  }
  return counts;
}

// The box of the points of a grid over `box` (n per side) that `min_cameras` cameras see; empty
// when none is.
Box SeenBox(const std::vector<CameraModel>& cameras, const Box& box, int n, int min_cameras) {
  Eigen::Matrix3Xd points(3, n * n * n);
  const Eigen::Vector3d step = box.size() / (n - 1);
  for (int i = 0, c = 0; i < n; ++i)
    for (int j = 0; j < n; ++j)
      for (int k = 0; k < n; ++k, ++c)
        points.col(c) = box.min + step.cwiseProduct(Eigen::Vector3d(i, j, k));
  const std::vector<int> counts = SeenCounts(cameras, points);
  Box seen = Box::Empty();
  for (Eigen::Index i = 0; i < points.cols(); ++i)
    if (counts[i] >= min_cameras) seen.Extend(Eigen::Vector3d(points.col(i)));
  if (seen.empty()) return seen;
  // The true edge lies within a step of the outermost seen points.
  return Box{seen.min - step, seen.max + step}.Intersection(box);
}

}  // namespace

int CamerasSeeing(const std::vector<CameraModel>& cameras, const Eigen::Vector3d& point_in_world) {
  return SeenCounts(cameras, point_in_world)[0];
}

RigView ViewOfRig(const std::vector<CameraModel>& cameras) {
  RigView view;
  const int n = static_cast<int>(cameras.size());
  if (n < 2) {
    view.why = Cat(n, " camera: no optical axes to meet");
    return view;
  }
  Eigen::Matrix3d a = Eigen::Matrix3d::Zero();
  Eigen::Vector3d b = Eigen::Vector3d::Zero();
  for (const auto& camera : cameras) {
    const Eigen::Vector3d c = camera.center_in_world();
    const Eigen::Vector3d d = camera.world_from_cam().rotation().col(2);
    const Eigen::Matrix3d p = Eigen::Matrix3d::Identity() - d * d.transpose();
    a += p;
    b += p * c;
  }
  // Parallel axes leave a direction along which no point is nearer than another.
  const double weakest = Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(a).eigenvalues()(0);
  view.center = a.ldlt().solve(b);
  std::vector<double> distances;
  int in_front = 0;
  for (const auto& camera : cameras) {
    distances.push_back((camera.center_in_world() - view.center).norm());
    in_front += (camera.cam_from_world() * view.center).z() > 0;
  }
  view.median_distance_m = Median(distances);
  if (!(weakest > 0.01 * n) || !view.center.allFinite() || in_front < 2) {
    view.why = Cat("the ", n, " cameras' optical axes do not meet in front of them");
    return view;
  }
  view.min_cameras = std::max(2, (n + 1) / 2);
  // A coarse grid, then two finer ones over what the coarser saw (a narrow lens sees a volume
  // a few grid steps wide).
  const double half = view.median_distance_m;
  Box box{view.center.array() - half, view.center.array() + half};
  for (int pass = 0; pass < 3 && !box.empty(); ++pass)
    box = SeenBox(cameras, box, 24, view.min_cameras);
  if (box.empty()) {
    view.why = Cat("no point near where the optical axes meet is seen by ", view.min_cameras,
                   " of the ", n, " cameras");
    return view;
  }
  view.shared = box;
  view.converges = true;
  view.why =
      Cat(n, " optical axes meet nearest ",
          Format("(%.3f, %.3f, %.3f)", view.center.x(), view.center.y(), view.center.z()),
          Format(", %.3f m from the cameras (median); the box that ", view.median_distance_m),
          view.min_cameras, " of them see, ",
          Format("%.3f x %.3f x %.3f m", box.size().x(), box.size().y(), box.size().z()));
  return view;
}

Eigen::Vector3d UpFromCameras(const std::vector<CameraModel>& cameras, std::string* why) {
  if (cameras.empty()) {
    *why = "no camera: +z";
    return Eigen::Vector3d::UnitZ();
  }
  std::vector<double> x, y, z;
  for (const auto& camera : cameras) {
    const Eigen::Vector3d up = -camera.world_from_cam().rotation().col(1);
    x.push_back(up.x());
    y.push_back(up.y());
    z.push_back(up.z());
  }
  Eigen::Vector3d up(Median(x), Median(y), Median(z));
  if (!(up.norm() > 1e-6)) {
    *why = "the cameras' up directions cancel: +z";
    return Eigen::Vector3d::UnitZ();
  }
  up.normalize();
  *why = Cat("cameras: the median up (-y) of ", cameras.size(), " cameras");
  return SnapToAxis(up, 10, why);
}

Eigen::Vector3d SnapToAxis(const Eigen::Vector3d& up, double degrees, std::string* why) {
  Eigen::Index axis = 0;
  up.cwiseAbs().maxCoeff(&axis);
  Eigen::Vector3d snapped = Eigen::Vector3d::Zero();
  snapped(axis) = up(axis) > 0 ? 1 : -1;
  const double off =
      std::acos(std::clamp(up.normalized().dot(snapped), -1.0, 1.0)) * 180 / std::numbers::pi;
  const std::string name = std::string(up(axis) > 0 ? "+" : "-") + "xyz"[axis];
  if (off <= degrees) {
    *why += Cat(" is ", Format("%.1f", off), " degrees from ", name);
    return snapped;
  }
  *why += Cat(" (", Format("%.1f", off), " degrees from ", name, ", no world axis)");
  return up.normalized();
}

bool FloorFromDepth(const std::vector<std::pair<CameraModel, cv::Mat>>& depth_maps,
                    const Eigen::Vector3d& up, Eigen::Vector3d* normal, double* offset,
                    double* tolerance_out, std::string* why) {
  std::vector<Eigen::Vector3d> points;
  Eigen::Vector3d sensors = Eigen::Vector3d::Zero();
  double distance = 0;
  constexpr int kStride = 6;
  for (const auto& [camera, depth] : depth_maps) {
    sensors += camera.center_in_world() / depth_maps.size();
    const Pose world_from_cam = camera.world_from_cam();
    for (int y = kStride / 2; y < depth.rows; y += kStride) {
      for (int x = kStride / 2; x < depth.cols; x += kStride) {
        const float z = depth.at<float>(y, x);
        if (!(z > 0) || !std::isfinite(z)) continue;
        const Eigen::Vector3d ray = camera.Unproject(Eigen::Vector2d(x, y));
        if (!(ray.z() > 0)) continue;
        points.push_back(world_from_cam * (ray * (z / ray.z())));
        distance += z;
      }
    }
  }
  if (points.size() < 100) {
    *why = Cat("too few depth points (", points.size(), ")");
    return false;
  }
  distance /= points.size();
  const double tolerance = 0.01 * distance;
  const double cos_limit = std::cos(30 * std::numbers::pi / 180);
  uint64_t state = 0x9e3779b97f4a7c15ULL;  // a fixed sequence: the same take, the same floor
  auto next = [&]() {
    state ^= state << 13;
    state ^= state >> 7;
    state ^= state << 17;
    return static_cast<size_t>(state % points.size());
  };
  size_t best = 0;
  Eigen::Vector3d best_normal = up;
  double best_offset = 0;
  for (int iteration = 0; iteration < 400; ++iteration) {
    const Eigen::Vector3d &a = points[next()], &b = points[next()], &c = points[next()];
    Eigen::Vector3d n = (b - a).cross(c - a);
    if (!(n.norm() > 1e-12)) continue;
    n.normalize();
    if (n.dot(up) < 0) n = -n;
    if (n.dot(up) < cos_limit) continue;
    const double d = n.dot(a);
    size_t inliers = 0;
    for (const auto& p : points) inliers += std::abs(n.dot(p) - d) < tolerance;
    if (inliers > best) best = inliers, best_normal = n, best_offset = d;
  }
  if (best < points.size() / 5) {
    *why =
        Cat("no plane within 30 degrees of up holds a fifth of ", points.size(), " depth points");
    return false;
  }
  // Least squares over the inliers.
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  std::vector<Eigen::Vector3d> inliers;
  for (const auto& p : points) {
    if (std::abs(best_normal.dot(p) - best_offset) < tolerance) inliers.push_back(p);
  }
  for (const auto& p : inliers) mean += p / inliers.size();
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  for (const auto& p : inliers) scatter += (p - mean) * (p - mean).transpose();
  Eigen::Vector3d n = Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(scatter).eigenvectors().col(0);
  if (n.dot(sensors - mean) < 0) n = -n;
  *normal = n;
  *offset = n.dot(mean);
  *tolerance_out = tolerance;
  *why = Cat("depth: a plane holds ", inliers.size(), " of ", points.size(), " points of ",
             depth_maps.size(), " sensor(s)");
  return true;
}

double ImpliedVoxel(const Box& box, const std::vector<CameraModel>& cameras, std::string* why) {
  const Eigen::Vector3d center = box.center();
  std::vector<double> footprints;
  for (const auto& camera : cameras) {
    const Eigen::Vector2d middle(0.5 * (camera.width() - 1), 0.5 * (camera.height() - 1));
    const Eigen::Vector3d a = camera.Unproject(middle);
    const Eigen::Vector3d b = camera.Unproject(middle + Eigen::Vector2d(1, 0));
    const double radians = std::acos(std::clamp(a.dot(b), -1.0, 1.0));
    footprints.push_back(radians * (camera.center_in_world() - center).norm());
  }
  const double detail = 2.0 / 3.0 * Median(footprints);
  const double memory = box.size().maxCoeff() / 512;
  const double chosen = std::max(detail, memory);
  const double voxel = 1e-3 * std::exp2(std::round(std::log2(chosen * 1e3)));
  if (why != nullptr) {
    *why = detail >= memory
               ? Format(
                     "2/3 of a pixel's footprint at the cameras' median distance (%.3f mm), "
                     "to a power of two: %.4g mm",
                     detail * 1e3, voxel * 1e3)
               : Format(
                     "1/512 of the bounds' largest side (%.3f mm; a pixel's footprint would "
                     "allow %.3f mm), to a power of two: %.4g mm",
                     memory * 1e3, detail * 1e3, voxel * 1e3);
  }
  return voxel;
}

}  // namespace holocap
