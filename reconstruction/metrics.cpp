// Surface-to-surface distances (accuracy, completeness, Chamfer, F-score).
#include <omp.h>
#include <opencv2/imgproc.hpp>

#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <map>
#include <memory>

#include "core/box.h"
#include "core/error.h"
#include "core/point_tree.h"
#include "core/projector.h"
#include "reconstruction/reconstruction.h"

namespace holocap {
SurfaceErrors CompareSurfaces(const Mesh& reconstruction, const Mesh& truth,
                              double fscore_threshold_m, size_t samples,
                              const std::function<bool(const Eigen::Vector3d&)>& truth_filter) {
  if (truth.empty() || truth.faces.empty()) Fail("CompareSurfaces: the true mesh is empty");
  if (!(fscore_threshold_m > 0) || samples == 0)
    Fail("CompareSurfaces: bad threshold or sample count");
  SurfaceErrors errors;
  if (reconstruction.faces.empty()) {
    errors.accuracy_mm = errors.completeness_mm = errors.chamfer_mm =
        std::numeric_limits<double>::infinity();
    return errors;
  }
  std::vector<Eigen::Vector3d> recon_points = reconstruction.SampleSurface(samples, 7);
  std::vector<Eigen::Vector3d> truth_points = truth.SampleSurface(samples, 11);
  if (truth_filter) {
    std::vector<Eigen::Vector3d> kept;
    for (const auto& p : truth_points) {
      if (truth_filter(p)) kept.push_back(p);
    }
    truth_points = std::move(kept);
    if (truth_points.empty()) Fail("CompareSurfaces: the filter kept no true surface point");
  }
  // Samples of one surface against the triangles of the other (exact point-to-surface
  // distances; sample-to-sample distances would add the sampling spacing to every figure).
  struct Surface {
    const Mesh* mesh;
    std::unique_ptr<PointTree> centroids;
    double slack = 0;  // largest centroid-to-corner distance
    double Distance(const Eigen::Vector3d& q) const {
      return centroids->Nearest(q, slack, [&](int f) {
        const Eigen::Vector3i& face = mesh->faces[f];
        return PointTriangleDistance(q, mesh->vertices[face[0]].cast<double>(),
                                     mesh->vertices[face[1]].cast<double>(),
                                     mesh->vertices[face[2]].cast<double>());
      });
    }
  };
  auto surface_of = [](const Mesh& mesh) {
    Surface s{&mesh, nullptr, 0};
    std::vector<Eigen::Vector3d> centres(mesh.faces.size());
    for (size_t f = 0; f < mesh.faces.size(); ++f) {
      Eigen::Vector3d a = mesh.vertices[mesh.faces[f][0]].cast<double>();
      Eigen::Vector3d b = mesh.vertices[mesh.faces[f][1]].cast<double>();
      Eigen::Vector3d c = mesh.vertices[mesh.faces[f][2]].cast<double>();
      centres[f] = (a + b + c) / 3;
      s.slack = std::max(
          {s.slack, (a - centres[f]).norm(), (b - centres[f]).norm(), (c - centres[f]).norm()});
    }
    s.centroids = std::make_unique<PointTree>(std::move(centres));
    return s;
  };
  const Surface recon_surface = surface_of(reconstruction);
  const Surface truth_surface = surface_of(truth);
  const int64_t nr = static_cast<int64_t>(recon_points.size());
  const int64_t nt = static_cast<int64_t>(truth_points.size());
  // Distances in parallel, summed in order: the same bits whatever the threads.
  std::vector<double> to_truth(nr), to_recon(nt);
#pragma omp parallel for schedule(dynamic, 256)
  for (int64_t i = 0; i < nr; ++i) to_truth[i] = truth_surface.Distance(recon_points[i]);
#pragma omp parallel for schedule(dynamic, 256)
  for (int64_t i = 0; i < nt; ++i) to_recon[i] = recon_surface.Distance(truth_points[i]);
  double accuracy = 0, completeness = 0;
  int64_t precise = 0, recalled = 0;
  for (double d : to_truth) {
    accuracy += d;
    precise += d <= fscore_threshold_m;
  }
  for (double d : to_recon) {
    completeness += d;
    recalled += d <= fscore_threshold_m;
  }
  errors.samples = nr + nt;
  errors.accuracy_mm = 1e3 * accuracy / nr;
  errors.completeness_mm = 1e3 * completeness / nt;
  errors.chamfer_mm = 0.5 * (errors.accuracy_mm + errors.completeness_mm);
  errors.precision = static_cast<double>(precise) / nr;
  errors.recall = static_cast<double>(recalled) / nt;
  errors.fscore = (errors.precision + errors.recall) > 0
                      ? 2 * errors.precision * errors.recall / (errors.precision + errors.recall)
                      : 0;
  return errors;
}

std::function<bool(const Eigen::Vector3d&)> SeenInDepthMaps(
    const std::vector<std::pair<CameraModel, cv::Mat>>& true_depths, double tolerance_m) {
  auto maps = std::make_shared<std::vector<std::pair<FastProjector, cv::Mat>>>();
  for (const auto& [camera, depth] : true_depths) {
    if (depth.type() != CV_32FC1 || depth.cols != camera.width() || depth.rows != camera.height()) {
      Fail("SeenInDepthMaps: depth maps must be CV_32F and their camera's size");
    }
    maps->emplace_back(FastProjector(camera), depth);
  }
  const float tolerance = static_cast<float>(tolerance_m);
  return [maps, tolerance](const Eigen::Vector3d& p) {
    for (const auto& [projector, depth] : *maps) {
      float u, v, z;
      if (!projector.ProjectWorld(p.cast<float>(), &u, &v, &z)) continue;
      int x = static_cast<int>(std::lround(u)), y = static_cast<int>(std::lround(v));
      if (x < 0 || y < 0 || x >= depth.cols || y >= depth.rows) continue;
      float d = depth.at<float>(y, x);
      if (std::isfinite(d) && std::abs(d - z) < tolerance) return true;
    }
    return false;
  };
}

std::function<bool(const Eigen::Vector3d&)> OnOuterSurface(const Mesh& truth, double tolerance_m) {
  // Parts: faces connected through shared vertices, vertices within a micrometre welded (meshes
  // repeat a pole or seam vertex), faces that collapse when welded left out of the edge count.
  std::map<std::array<int64_t, 3>, int> welded;  // on a micrometre grid
  std::vector<int> id(truth.vertices.size());
  for (size_t i = 0; i < truth.vertices.size(); ++i) {
    const Eigen::Vector3d v = truth.vertices[i].cast<double>() * 1e6;
    const std::array<int64_t, 3> cell = {std::llround(v.x()), std::llround(v.y()),
                                         std::llround(v.z())};
    id[i] = welded.emplace(cell, static_cast<int>(welded.size())).first->second;
  }
  std::vector<int> parent(welded.size());
  for (size_t i = 0; i < parent.size(); ++i) parent[i] = static_cast<int>(i);
  auto find = [&](int x) {
    while (parent[x] != x) x = parent[x] = parent[parent[x]];
    return x;
  };
  for (const auto& f : truth.faces) {
    parent[find(id[f[1]])] = find(id[f[0]]);
    parent[find(id[f[2]])] = find(id[f[0]]);
  }
  struct Part {
    std::vector<std::array<Eigen::Vector3d, 3>> triangles;
    Box box = Box::Empty();
    std::map<std::pair<int, int>, int> edge_uses;
  };
  std::map<int, Part> by_root;
  for (const auto& f : truth.faces) {
    Part& part = by_root[find(id[f[0]])];
    const int w[3] = {id[f[0]], id[f[1]], id[f[2]]};
    std::array<Eigen::Vector3d, 3> t;
    for (int k = 0; k < 3; ++k) {
      t[k] = truth.vertices[f[k]].cast<double>();
      part.box.Extend(t[k]);
    }
    if (w[0] == w[1] || w[1] == w[2] || w[0] == w[2]) continue;
    for (int k = 0; k < 3; ++k)
      ++part.edge_uses[{std::min(w[k], w[(k + 1) % 3]), std::max(w[k], w[(k + 1) % 3])}];
    part.triangles.push_back(t);
  }
  // Only closed parts enclose a solid.
  auto parts = std::make_shared<std::vector<Part>>();
  for (auto& [root, part] : by_root) {
    bool closed = std::all_of(part.edge_uses.begin(), part.edge_uses.end(),
                              [](const auto& e) { return e.second == 2; });
    part.edge_uses.clear();
    if (closed) parts->push_back(std::move(part));
  }
  return [parts, tolerance_m](const Eigen::Vector3d& p) {
    for (const Part& part : *parts) {
      if (!part.box.Contains(p)) continue;
      // Ray parity along a direction no axis-aligned structure shares.
      const Eigen::Vector3d direction = Eigen::Vector3d(0.0123, 0.0371, 1.0).normalized();
      int crossings = 0;
      for (const auto& t : part.triangles) {
        const Eigen::Vector3d e1 = t[1] - t[0], e2 = t[2] - t[0], h = direction.cross(e2);
        const double det = e1.dot(h);
        if (std::abs(det) < 1e-18) continue;
        const Eigen::Vector3d s = p - t[0];
        const double u = s.dot(h) / det;
        if (u < 0 || u > 1) continue;
        const Eigen::Vector3d q = s.cross(e1);
        const double v = direction.dot(q) / det;
        if (v < 0 || u + v > 1) continue;
        crossings += e2.dot(q) / det > 0;
      }
      if (crossings % 2 == 0) continue;
      // Inside this part, and not on its surface: buried in the solid.
      double nearest = std::numeric_limits<double>::infinity();
      for (const auto& t : part.triangles)
        nearest = std::min(nearest, PointTriangleDistance(p, t[0], t[1], t[2]));
      if (nearest > tolerance_m) return false;
    }
    return true;
  };
}

cv::Mat DepthForeground(const cv::Mat& depth, const cv::Mat& plate, double noise_k) {
  if (depth.type() != CV_32FC1 || plate.type() != CV_32FC1 || depth.size() != plate.size()) {
    Fail("DepthForeground: depth map and clean plate must be CV_32F of one size");
  }
  // Single-pixel holes of the plate (noise dropouts, grazing floor, depth edges) take the
  // nearest depth around them, so that a later measurement there is not mistaken for the
  // subject; only wide holes (out of range) stay unknown.
  constexpr int kFill = 3;
  cv::Mat filled = plate.clone();
  for (int y = 0; y < plate.rows; ++y) {
    for (int x = 0; x < plate.cols; ++x) {
      if (std::isfinite(plate.at<float>(y, x))) continue;
      float nearest = std::numeric_limits<float>::infinity();
      for (int dy = -kFill; dy <= kFill; ++dy) {
        for (int dx = -kFill; dx <= kFill; ++dx) {
          int yy = y + dy, xx = x + dx;
          if (yy < 0 || xx < 0 || yy >= plate.rows || xx >= plate.cols) continue;
          float v = plate.at<float>(yy, xx);
          if (std::isfinite(v)) nearest = std::min(nearest, v);
        }
      }
      filled.at<float>(y, x) =
          std::isfinite(nearest) ? nearest : std::numeric_limits<float>::quiet_NaN();
    }
  }
  cv::Mat mask(depth.size(), CV_8U, cv::Scalar(0));
  for (int y = 0; y < depth.rows; ++y) {
    const float* d = depth.ptr<float>(y);
    const float* p = filled.ptr<float>(y);
    uint8_t* m = mask.ptr<uint8_t>(y);
    for (int x = 0; x < depth.cols; ++x) {
      if (!std::isfinite(d[x])) continue;
      float margin = std::max(0.02f, static_cast<float>(4 * noise_k * d[x] * d[x]));
      m[x] = (!std::isfinite(p[x]) || d[x] < p[x] - margin) ? 255 : 0;
    }
  }
  // Isolated pixels are noise, not a subject.
  cv::morphologyEx(mask, mask, cv::MORPH_OPEN,
                   cv::getStructuringElement(cv::MORPH_RECT, cv::Size(3, 3)));
  return mask;
}

}  // namespace holocap
