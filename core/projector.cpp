#include "core/projector.h"

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <functional>
#include <limits>
#include <map>
#include <mutex>
#include <string>

#include "core/error.h"

namespace holocap {

namespace {

std::string LensKey(const CameraModel& camera) {
  std::string key = camera.lensmodel() + "|" + std::to_string(camera.width()) + "x" +
                    std::to_string(camera.height());
  for (double v : camera.intrinsics()) key += "|" + std::to_string(v);
  return key;
}

template <typename T>
std::shared_ptr<const T> Cached(const std::string& key, const std::function<T()>& build) {
  static std::mutex mutex;
  static std::map<std::string, std::shared_ptr<const T>> cache;
  {
    std::lock_guard lock(mutex);
    auto it = cache.find(key);
    if (it != cache.end()) return it->second;
  }
  auto value = std::make_shared<const T>(build());
  std::lock_guard lock(mutex);
  if (cache.size() > 64) cache.clear();  // bounded: a long run over many rigs stays small
  return cache.emplace(key, value).first->second;
}

ProjectionTable BuildTable(const CameraModel& lens, int table_cells) {
  ProjectionTable table;
  const int width = lens.width(), height = lens.height();
  table.width = width;
  table.height = height;
  // The field of view: every border pixel unprojected.
  std::vector<Eigen::Vector2d> samples;
  for (int x = 0; x <= width; x += 4) {
    samples.emplace_back(x - 0.5, -0.5);
    samples.emplace_back(x - 0.5, height - 0.5);
  }
  for (int y = 0; y <= height; y += 4) {
    samples.emplace_back(-0.5, y - 0.5);
    samples.emplace_back(width - 0.5, y - 0.5);
  }
  Eigen::Matrix2Xd pixels(2, samples.size());
  for (size_t i = 0; i < samples.size(); ++i) pixels.col(i) = samples[i];
  Eigen::Matrix3Xd rays = lens.UnprojectMany(pixels);
  double amin = 0, amax = 0, bmin = 0, bmax = 0;
  bool any = false;
  for (int i = 0; i < rays.cols(); ++i) {
    Eigen::Vector3d ray = rays.col(i);
    if (!ray.allFinite()) continue;
    // Rays at or beyond 90 degrees cannot be tabulated in x/z; clamp to ~84 degrees.
    double z = std::max(ray.z(), 0.1 * ray.head<2>().norm());
    double a = ray.x() / z, b = ray.y() / z;
    if (!any) {
      amin = amax = a;
      bmin = bmax = b;
      any = true;
    }
    amin = std::min(amin, a), amax = std::max(amax, a);
    bmin = std::min(bmin, b), bmax = std::max(bmax, b);
  }
  if (!any) Fail("camera model '", lens.lensmodel(), "' unprojects none of its border pixels");
  double margin_a = 0.08 * (amax - amin), margin_b = 0.08 * (bmax - bmin);
  amin -= margin_a, amax += margin_a, bmin -= margin_b, bmax += margin_b;
  double aspect = (bmax - bmin) / (amax - amin);
  table.cells_a = table_cells;
  table.cells_b = std::max(16, static_cast<int>(std::lround(table_cells * aspect)));
  double step_a = (amax - amin) / table.cells_a, step_b = (bmax - bmin) / table.cells_b;
  table.a0 = static_cast<float>(amin);
  table.b0 = static_cast<float>(bmin);
  table.inv_step_a = static_cast<float>(1 / step_a);
  table.inv_step_b = static_cast<float>(1 / step_b);

  Eigen::Matrix3Xd points(3, (table.cells_a + 1) * (table.cells_b + 1));
  for (int j = 0; j <= table.cells_b; ++j) {
    for (int i = 0; i <= table.cells_a; ++i) {
      points.col(j * (table.cells_a + 1) + i) =
          Eigen::Vector3d(amin + i * step_a, bmin + j * step_b, 1);
    }
  }
  Eigen::Matrix2Xd projected = lens.ProjectMany(points);
  table.nodes.resize(points.cols());
  for (int i = 0; i < points.cols(); ++i) {
    Eigen::Vector2d p = projected.col(i);
    // A node mrcal cannot project is pushed far outside the image, so lookups near it fail
    // the image test instead of returning garbage.
    table.nodes[i] = p.allFinite() ? p.cast<float>() : Eigen::Vector2f(-1e6f, -1e6f);
  }
  // Local focal length along the principal direction: d pixel / d (x/z).
  Eigen::Vector3d ray = lens.Unproject(Eigen::Vector2d(0.5 * (width - 1), 0.5 * (height - 1)));
  Eigen::Vector3d dir = ray / ray.z();
  const double h = 1e-4;
  Eigen::Vector2d p0, pa, pb;
  if (lens.Project(dir, &p0) && lens.Project(dir + Eigen::Vector3d(h, 0, 0), &pa) &&
      lens.Project(dir + Eigen::Vector3d(0, h, 0), &pb)) {
    table.focal = static_cast<float>(0.5 * ((pa - p0).norm() + (pb - p0).norm()) / h);
  }
  return table;
}

constexpr int kTableCells = 768;

}  // namespace

FastProjector::FastProjector(const CameraModel& camera)
    : camera_(camera), width_(camera.width()), height_(camera.height()) {
  if (width_ <= 0 || height_ <= 0) Fail("camera model without an imager size");
  rotation_ = camera.cam_from_world().rotation().cast<float>();
  translation_ = camera.cam_from_world().translation().cast<float>();
  CameraModel lens = camera;
  lens.set_cam_from_world(Pose::Identity());
  table_ = Cached<ProjectionTable>(LensKey(camera), [&] { return BuildTable(lens, kTableCells); });
}

static cv::Mat BuildRays(const CameraModel& camera) {
  const int w = camera.width(), h = camera.height();
  Eigen::Matrix2Xd pixels(2, static_cast<Eigen::Index>(w) * h);
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) pixels.col(static_cast<Eigen::Index>(y) * w + x) << x, y;
  }
  Eigen::Matrix3Xd rays = camera.UnprojectMany(pixels);
  cv::Mat out(h, w, CV_32FC2);
  const float nan = std::numeric_limits<float>::quiet_NaN();
  for (int y = 0; y < h; ++y) {
    auto* row = out.ptr<cv::Vec2f>(y);
    for (int x = 0; x < w; ++x) {
      Eigen::Vector3d ray = rays.col(static_cast<Eigen::Index>(y) * w + x);
      row[x] = (ray.allFinite() && ray.z() > 1e-6) ? cv::Vec2f(ray.x() / ray.z(), ray.y() / ray.z())
                                                   : cv::Vec2f(nan, nan);
    }
  }
  return out;
}

cv::Mat NormalisedRays(const CameraModel& camera) {
  return *Cached<cv::Mat>("rays|" + LensKey(camera), [&] { return BuildRays(camera); });
}

}  // namespace holocap
