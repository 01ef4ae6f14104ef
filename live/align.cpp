// The scan against a live frame: the live surface, projective point-to-plane pairs, the rigid
// ICP and the embedded deformation graph.
#include <Eigen/Sparse>
#include <algorithm>
#include <array>
#include <cmath>
#include <functional>
#include <unordered_map>

#include "core/box.h"
#include "core/error.h"
#include "core/point_tree.h"
#include "core/projector.h"
#include "live/internal/live.h"
#include "live/live.h"

namespace holocap {

namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
// How far along the surface, in node spacings, a node's reach is searched.
constexpr double kGeodesicReach = 2;

}  // namespace

namespace live {

std::vector<int> ThinnedVertices(size_t vertices, int samples) {
  std::vector<int> indices;
  const size_t stride = std::max<size_t>(1, vertices / static_cast<size_t>(std::max(1, samples)));
  for (size_t i = 0; i < vertices; i += stride) indices.push_back(static_cast<int>(i));
  return indices;
}

FitStats Associate(const std::vector<Eigen::Vector3f>& points,
                   const std::vector<Eigen::Vector3f>& normals, const LiveSurface& live,
                   double gate_m, double max_normal_angle_deg, std::vector<Pair>* pairs) {
  const FastProjector projector(live.camera);
  const Eigen::Vector3f center = live.camera.center_in_world().cast<float>();
  const float cos_max = static_cast<float>(std::cos(max_normal_angle_deg * M_PI / 180));
  const float gate = static_cast<float>(gate_m);
  FitStats fit;
  double squared = 0;
  if (pairs != nullptr) pairs->clear();
  for (size_t i = 0; i < points.size(); ++i) {
    const Eigen::Vector3f& p = points[i];
    const Eigen::Vector3f& n = normals[i];
    if (!p.allFinite() || !n.allFinite() || n.dot(center - p) <= 0) continue;
    float u, v, z;
    if (!projector.ProjectWorld(p, &u, &v, &z)) continue;
    const int x = static_cast<int>(std::lround(u));
    const int y = static_cast<int>(std::lround(v));
    if (x < 0 || y < 0 || x >= live.width || y >= live.height) continue;
    const size_t pixel = static_cast<size_t>(y) * live.width + x;
    const float depth = live.depth[pixel];
    if (std::isnan(depth) || z > depth + gate) continue;  // no measurement, or hidden behind it
    ++fit.expected;
    const Eigen::Vector3f& q = live.points[pixel];
    const Eigen::Vector3f& nq = live.normals[pixel];
    if (!nq.allFinite() || (p - q).norm() > gate || n.dot(nq) < cos_max) continue;
    ++fit.inliers;
    const double r = nq.dot(p - q);
    squared += r * r;
    if (pairs != nullptr)
      pairs->push_back({static_cast<int>(i), q.cast<double>(), nq.cast<double>()});
  }
  if (fit.expected > 0) fit.inlier_fraction = static_cast<double>(fit.inliers) / fit.expected;
  if (fit.inliers > 0) fit.residual_m = std::sqrt(squared / fit.inliers);
  return fit;
}

void AddNearestPairs(const std::vector<Eigen::Vector3f>& points,
                     const std::vector<Eigen::Vector3f>& normals, const LiveSurface& live,
                     double gate_m, double max_normal_angle_deg, int live_samples,
                     std::vector<Pair>* pairs) {
  const Eigen::Vector3f center = live.camera.center_in_world().cast<float>();
  std::vector<Eigen::Vector3d> facing;
  std::vector<int> index;
  for (size_t i = 0; i < points.size(); ++i) {
    if (!points[i].allFinite() || !normals[i].allFinite() ||
        normals[i].dot(center - points[i]) <= 0)
      continue;
    facing.push_back(points[i].cast<double>());
    index.push_back(static_cast<int>(i));
  }
  if (facing.empty()) return;
  const PointTree tree(facing);
  // A live point outside the facing points' box grown by the gate pairs with none of them.
  Box reach = Box::Empty();
  for (const Eigen::Vector3d& p : facing) reach.Extend(p);
  reach = reach.Grown(gate_m);
  const float cos_max = static_cast<float>(std::cos(max_normal_angle_deg * M_PI / 180));
  const size_t stride =
      std::max<size_t>(1, static_cast<size_t>(live.valid / std::max(1, live_samples)));
  size_t seen = 0;
  for (size_t pixel = 0; pixel < live.points.size(); ++pixel) {
    if (!live.normals[pixel].allFinite() || seen++ % stride != 0) continue;
    const Eigen::Vector3d q = live.points[pixel].cast<double>();
    if (!reach.Contains(q)) continue;
    int nearest = -1;
    double best = std::numeric_limits<double>::infinity();
    // Only a point within the gate can pair: the distances are clamped to it, so the tree
    // prunes every branch farther than the gate (most live pixels are the room, far from the
    // scan).
    tree.Nearest(q, 0, [&](int i) {
      const double d = (facing[i] - q).norm();
      if (d < best) {
        best = d;
        nearest = i;
      }
      return std::min(d, gate_m);
    });
    if (nearest < 0 || best > gate_m) continue;
    const int sample = index[nearest];
    if (normals[sample].dot(live.normals[pixel]) < cos_max) continue;
    pairs->push_back({sample, q, live.normals[pixel].cast<double>()});
  }
}

}  // namespace live

LiveSurface MakeLiveSurface(const cv::Mat& depth_m, const CameraModel& camera, double depth_min_m,
                            double depth_max_m) {
  if (depth_m.type() != CV_32F || depth_m.cols != camera.width() ||
      depth_m.rows != camera.height()) {
    Fail("live: depth map of ", depth_m.cols, "x", depth_m.rows,
         " does not match its sensor's model (", camera.width(), "x", camera.height(), ")");
  }
  LiveSurface live;
  live.camera = camera;
  live.width = depth_m.cols;
  live.height = depth_m.rows;
  const size_t count = static_cast<size_t>(live.width) * live.height;
  live.points.assign(count, Eigen::Vector3f::Constant(kNaN));
  live.normals.assign(count, Eigen::Vector3f::Constant(kNaN));
  live.depth.assign(count, kNaN);
  const cv::Mat rays = NormalisedRays(camera);
  const Eigen::Isometry3f world_from_cam = camera.world_from_cam().cast<float>();
  for (int y = 0; y < live.height; ++y) {
    for (int x = 0; x < live.width; ++x) {
      const float d = depth_m.at<float>(y, x);
      const cv::Vec2f& ray = rays.at<cv::Vec2f>(y, x);
      if (!(d >= depth_min_m && d <= depth_max_m) || std::isnan(ray[0])) continue;
      const size_t i = static_cast<size_t>(y) * live.width + x;
      live.depth[i] = d;
      live.points[i] = world_from_cam * Eigen::Vector3f(ray[0] * d, ray[1] * d, d);
    }
  }
  const Eigen::Vector3f center = camera.center_in_world().cast<float>();
  for (int y = 1; y + 1 < live.height; ++y) {
    for (int x = 1; x + 1 < live.width; ++x) {
      const size_t i = static_cast<size_t>(y) * live.width + x;
      const Eigen::Vector3f& p = live.points[i];
      if (!p.allFinite()) continue;
      // Central differences, or one-sided where a neighbour has no measurement.
      auto side = [&](size_t a, size_t b) -> Eigen::Vector3f {
        if (live.points[a].allFinite() && live.points[b].allFinite())
          return live.points[b] - live.points[a];
        if (live.points[b].allFinite()) return live.points[b] - p;
        if (live.points[a].allFinite()) return p - live.points[a];
        return Eigen::Vector3f::Constant(kNaN);
      };
      const Eigen::Vector3f dx = side(i - 1, i + 1);
      const Eigen::Vector3f dy = side(i - live.width, i + live.width);
      Eigen::Vector3f n = dx.cross(dy);
      if (!n.allFinite() || n.norm() < 1e-12f) continue;
      n.normalize();
      if (n.dot(center - p) < 0) n = -n;
      live.normals[i] = n;
      ++live.valid;
    }
  }
  return live;
}

FitStats MeasureFit(const std::vector<Eigen::Vector3f>& points,
                    const std::vector<Eigen::Vector3f>& normals, const LiveSurface& live,
                    double gate_m, double max_normal_angle_deg) {
  return live::Associate(points, normals, live, gate_m, max_normal_angle_deg, nullptr);
}

RigidAlignment AlignRigid(const Mesh& scan, const LiveSurface& live, const Pose& initial,
                          const LiveOptions& options) {
  if (scan.normals.size() != scan.vertices.size()) Fail("live: the scan's mesh has no normals");
  const std::vector<int> samples =
      live::ThinnedVertices(scan.vertices.size(), options.alignment_samples);
  RigidAlignment result;
  result.world_from_scan = initial;
  std::vector<Eigen::Vector3f> points(samples.size()), normals(samples.size());
  auto pose_samples = [&] {
    const Eigen::Isometry3f pose = result.world_from_scan.cast<float>();
    for (size_t s = 0; s < samples.size(); ++s) {
      points[s] = pose * scan.vertices[samples[s]];
      normals[s] = pose.linear() * scan.normals[samples[s]];
    }
  };
  std::vector<live::Pair> pairs;
  for (int iteration = 0; iteration < options.rigid_iterations; ++iteration) {
    pose_samples();
    const double gate = std::max(options.gate_m, options.coarse_gate_m * std::pow(0.5, iteration));
    live::Associate(points, normals, live, gate, options.max_normal_angle_deg, &pairs);
    live::AddNearestPairs(points, normals, live, gate, options.max_normal_angle_deg,
                          options.alignment_samples, &pairs);
    if (pairs.size() < 6) break;
    Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
    for (const live::Pair& pair : pairs) centroid += points[pair.index].cast<double>();
    centroid /= static_cast<double>(pairs.size());
    Eigen::Matrix<double, 6, 6> hessian = Eigen::Matrix<double, 6, 6>::Zero();
    Eigen::Matrix<double, 6, 1> gradient = Eigen::Matrix<double, 6, 1>::Zero();
    for (const live::Pair& pair : pairs) {
      const Eigen::Vector3d p = points[pair.index].cast<double>();
      const double r = pair.normal.dot(p - pair.point);
      Eigen::Matrix<double, 6, 1> jacobian;
      jacobian << (p - centroid).cross(pair.normal), pair.normal;
      const double weight = live::HuberWeight(r, options.huber_m);
      hessian += weight * jacobian * jacobian.transpose();
      gradient += weight * r * jacobian;
    }
    hessian.diagonal().array() += 1e-9 * (1 + hessian.diagonal().maxCoeff());
    const Eigen::Matrix<double, 6, 1> step = hessian.ldlt().solve(-gradient);
    if (!step.allFinite()) break;
    Pose delta = Pose::Identity();
    delta.linear() = live::SmallRotation(step.head<3>());
    delta.translation() = centroid + step.tail<3>() - delta.linear() * centroid;
    result.world_from_scan = delta * result.world_from_scan;
    result.world_from_scan.linear() = NearestRotation(result.world_from_scan.linear());
    result.iterations = iteration + 1;
  }
  pose_samples();
  result.fit = MeasureFit(points, normals, live, options.gate_m, options.max_normal_angle_deg);
  return result;
}

namespace {

// Up to `count` (distance, node) pairs, nearest first.
struct NearestNodes {
  std::array<std::pair<float, int>, 5> best;
  int count = 0;
  void Offer(float distance, int node, int capacity) {
    if (count == capacity && distance >= best[count - 1].first) return;
    int at = std::min(count, capacity - 1);
    if (count < capacity) ++count;
    while (at > 0 && best[at - 1].first > distance) {
      best[at] = best[at - 1];
      --at;
    }
    best[at] = {distance, node};
  }
};

// One node per occupied cell of `spacing_m`: the vertex nearest the mean of the cell's vertices.
std::vector<int> SampleNodeVertices(const Mesh& mesh, double spacing_m) {
  struct Cell {
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    int count = 0;
    int best = -1;
    double best_distance = 0;
  };
  std::unordered_map<int64_t, Cell> cells;
  auto key_of = [&](const Eigen::Vector3f& v) {
    const Eigen::Vector3i c = (v.cast<double>() / spacing_m).array().floor().cast<int>();
    return (static_cast<int64_t>(c.x() + (1 << 20)) << 42) |
           (static_cast<int64_t>(c.y() + (1 << 20)) << 21) |
           static_cast<int64_t>(c.z() + (1 << 20));
  };
  for (const Eigen::Vector3f& v : mesh.vertices) {
    Cell& cell = cells[key_of(v)];
    cell.sum += v.cast<double>();
    ++cell.count;
  }
  for (size_t i = 0; i < mesh.vertices.size(); ++i) {
    Cell& cell = cells[key_of(mesh.vertices[i])];
    const double distance = (mesh.vertices[i].cast<double>() - cell.sum / cell.count).norm();
    if (cell.best < 0 || distance < cell.best_distance) {
      cell.best = static_cast<int>(i);
      cell.best_distance = distance;
    }
  }
  std::vector<int> chosen;
  chosen.reserve(cells.size());
  for (const auto& [key, cell] : cells) chosen.push_back(cell.best);
  std::sort(chosen.begin(), chosen.end());  // deterministic order
  return chosen;
}

// The `capacity` nearest nodes of every vertex along the mesh's edges, within `reach_m`:
// a bounded Dijkstra from each node's vertex.
std::vector<NearestNodes> GeodesicNearestNodes(const Mesh& mesh,
                                               const std::vector<int>& node_vertex, double reach_m,
                                               int capacity) {
  const size_t n = mesh.vertices.size();
  const VertexNeighbours adjacency = NeighboursOf(mesh);
  std::vector<NearestNodes> nearest(n);
  std::vector<float> distance(n, std::numeric_limits<float>::infinity());
  std::vector<int> touched;
  using Entry = std::pair<float, int>;
  std::vector<Entry> heap;
  const float reach = static_cast<float>(reach_m);
  for (size_t j = 0; j < node_vertex.size(); ++j) {
    const int source = node_vertex[j];
    distance[source] = 0;
    touched.push_back(source);
    heap.assign(1, {0.0f, source});
    while (!heap.empty()) {
      std::pop_heap(heap.begin(), heap.end(), std::greater<>());
      const auto [d, v] = heap.back();
      heap.pop_back();
      if (d > distance[v]) continue;
      nearest[v].Offer(d, static_cast<int>(j), capacity);
      for (int32_t e = adjacency.start[v]; e < adjacency.start[v + 1]; ++e) {
        const int32_t to = adjacency.neighbours[e];
        const float next = d + (mesh.vertices[v] - mesh.vertices[to]).norm();
        if (next > reach || next >= distance[to]) continue;
        if (!std::isfinite(distance[to])) touched.push_back(to);
        distance[to] = next;
        heap.emplace_back(next, to);
        std::push_heap(heap.begin(), heap.end(), std::greater<>());
      }
    }
    for (int v : touched) distance[v] = std::numeric_limits<float>::infinity();
    touched.clear();
  }
  return nearest;
}

}  // namespace

DeformationGraph::DeformationGraph(const Mesh& mesh, double spacing_m, int neighbours) {
  neighbours = std::clamp(neighbours, 1, 4);
  const std::vector<int> node_vertex = SampleNodeVertices(mesh, spacing_m);
  for (int index : node_vertex) nodes.push_back(mesh.vertices[index].cast<double>());
  rotation.assign(nodes.size(), Eigen::Matrix3d::Identity());
  translation.assign(nodes.size(), Eigen::Vector3d::Zero());

  // Nodes and vertices are tied along the surface, not through the air: two legs or an arm and
  // the torso that pass close move apart without pulling each other. A piece of the mesh that
  // no node reaches along its edges falls back on the nearest nodes in space.
  const double reach_m = kGeodesicReach * spacing_m;
  const std::vector<NearestNodes> geodesic =
      GeodesicNearestNodes(mesh, node_vertex, reach_m, neighbours + 1);
  // The k + 1 nearest nodes of a point in space (the last one sets the weights' reach).
  auto nearest = [&](const Eigen::Vector3d& point, int k, int skip) {
    NearestNodes best;
    for (size_t j = 0; j < nodes.size(); ++j) {
      if (static_cast<int>(j) == skip) continue;
      best.Offer(static_cast<float>((nodes[j] - point).norm()), static_cast<int>(j), k + 1);
    }
    return best;
  };
  edges.resize(nodes.size());
  for (size_t j = 0; j < nodes.size(); ++j) {
    const NearestNodes& along = geodesic[node_vertex[j]];
    for (int n = 0; n < along.count; ++n)
      if (along.best[n].second != static_cast<int>(j) &&
          static_cast<int>(edges[j].size()) < neighbours)
        edges[j].push_back(along.best[n].second);
    if (!edges[j].empty()) continue;
    const NearestNodes best = nearest(nodes[j], neighbours, static_cast<int>(j));
    for (int n = 0; n < std::min(neighbours, best.count); ++n)
      edges[j].push_back(best.best[n].second);
  }
  vertex_node.assign(mesh.vertices.size(), {-1, -1, -1, -1});
  vertex_weight.assign(mesh.vertices.size(), Eigen::Vector4f::Zero());
  for (size_t i = 0; i < mesh.vertices.size(); ++i) {
    NearestNodes best = geodesic[i];
    // Fewer than k + 1 along the surface: the search's reach bounds the weights.
    double reach = reach_m;
    if (best.count == 0) {
      best = nearest(mesh.vertices[i].cast<double>(), neighbours, -1);
      if (best.count == 0) continue;
      reach = best.best[best.count - 1].first;
    } else if (best.count == neighbours + 1) {
      reach = best.best[neighbours].first;
    }
    reach += 1e-6;
    const int used = std::min(neighbours, best.count);
    float total = 0;
    for (int n = 0; n < used; ++n) {
      const double w = std::pow(1 - best.best[n].first / reach, 2);
      vertex_node[i][n] = best.best[n].second;
      vertex_weight[i][n] = static_cast<float>(w);
      total += static_cast<float>(w);
    }
    if (total <= 0) {
      vertex_weight[i] = Eigen::Vector4f(1, 0, 0, 0);
    } else {
      vertex_weight[i] /= total;
    }
  }
}

Eigen::Vector3d DeformationGraph::Apply(size_t vertex, const Eigen::Vector3d& rest) const {
  Eigen::Vector3d moved = Eigen::Vector3d::Zero();
  double total = 0;
  for (int n = 0; n < 4; ++n) {
    const int j = vertex_node[vertex][n];
    if (j < 0) continue;
    const double w = vertex_weight[vertex][n];
    moved += w * (rotation[j] * (rest - nodes[j]) + nodes[j] + translation[j]);
    total += w;
  }
  return total > 0 ? Eigen::Vector3d(moved / total) : rest;
}

DeformationGraph DeformationGraph::Posed(const Pose& world_from_rest) const {
  DeformationGraph posed = *this;
  const Eigen::Matrix3d r = world_from_rest.linear();
  for (size_t j = 0; j < nodes.size(); ++j) {
    posed.nodes[j] = world_from_rest * nodes[j];
    posed.rotation[j] = r * rotation[j] * r.transpose();
    posed.translation[j] = r * translation[j];
  }
  return posed;
}

void DeformationGraph::TakeMotions(const DeformationGraph& posed, const Pose& world_from_rest) {
  const Eigen::Matrix3d r = world_from_rest.linear();
  for (size_t j = 0; j < nodes.size(); ++j) {
    rotation[j] = NearestRotation(r.transpose() * posed.rotation[j] * r);
    translation[j] = r.transpose() * posed.translation[j];
  }
}

Eigen::Vector3d DeformationGraph::ApplyNormal(size_t vertex, const Eigen::Vector3d& rest) const {
  Eigen::Vector3d turned = Eigen::Vector3d::Zero();
  for (int n = 0; n < 4; ++n) {
    const int j = vertex_node[vertex][n];
    if (j >= 0) turned += vertex_weight[vertex][n] * (rotation[j] * rest);
  }
  const double norm = turned.norm();
  return norm > 1e-12 ? Eigen::Vector3d(turned / norm) : rest;
}

}  // namespace holocap
