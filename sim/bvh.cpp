#include "sim/bvh.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace holocap::sim {
namespace {

constexpr int kBins = 16;
constexpr int kLeafSize = 4;

float HalfArea(const Eigen::Vector3f& lo, const Eigen::Vector3f& hi) {
  const Eigen::Vector3f d = (hi - lo).cwiseMax(0.0f);
  return d.x() * d.y() + d.y() * d.z() + d.z() * d.x();
}

}  // namespace

void Bvh::Build(const std::vector<Eigen::Vector3f>& vertices,
                const std::vector<Eigen::Vector3i>& faces) {
  nodes_.clear();
  tris_.clear();
  order_.resize(faces.size());
  if (faces.empty()) return;
  std::vector<Eigen::Vector3f> centroids(faces.size()), lo(faces.size()), hi(faces.size());
  for (size_t f = 0; f < faces.size(); ++f) {
    const Eigen::Vector3f& a = vertices[faces[f][0]];
    const Eigen::Vector3f& b = vertices[faces[f][1]];
    const Eigen::Vector3f& c = vertices[faces[f][2]];
    lo[f] = a.cwiseMin(b).cwiseMin(c);
    hi[f] = a.cwiseMax(b).cwiseMax(c);
    centroids[f] = (a + b + c) / 3.0f;
    order_[f] = static_cast<int>(f);
  }
  nodes_.reserve(2 * faces.size() / kLeafSize + 1);
  BuildRange(0, static_cast<int>(faces.size()), centroids, lo, hi);
  tris_.resize(faces.size());
  for (size_t k = 0; k < order_.size(); ++k) {
    const Eigen::Vector3i& face = faces[order_[k]];
    const Eigen::Vector3f& a = vertices[face[0]];
    tris_[k] = {a, vertices[face[1]] - a, vertices[face[2]] - a};
  }
}

int Bvh::BuildRange(int begin, int end, std::vector<Eigen::Vector3f>& centroids,
                    std::vector<Eigen::Vector3f>& lo, std::vector<Eigen::Vector3f>& hi) {
  const int index = static_cast<int>(nodes_.size());
  nodes_.push_back({Eigen::Vector3f::Zero(), 0, Eigen::Vector3f::Zero(), 0, 0});
  Eigen::Vector3f box_lo = Eigen::Vector3f::Constant(std::numeric_limits<float>::max());
  Eigen::Vector3f box_hi = -box_lo;
  Eigen::Vector3f cen_lo = box_lo, cen_hi = box_hi;
  for (int k = begin; k < end; ++k) {
    const int f = order_[k];
    box_lo = box_lo.cwiseMin(lo[f]);
    box_hi = box_hi.cwiseMax(hi[f]);
    cen_lo = cen_lo.cwiseMin(centroids[f]);
    cen_hi = cen_hi.cwiseMax(centroids[f]);
  }
  const int count = end - begin;
  auto make_leaf = [&] {
    nodes_[index] = {box_lo, begin, box_hi, count, 0};
    return index;
  };
  if (count <= kLeafSize) return make_leaf();

  // Binned surface-area heuristic over the axis of largest centroid extent.
  int axis = 0;
  const Eigen::Vector3f extent = cen_hi - cen_lo;
  if (extent.y() > extent[axis]) axis = 1;
  if (extent.z() > extent[axis]) axis = 2;
  if (!(extent[axis] > 0)) return make_leaf();
  struct Bin {
    Eigen::Vector3f lo = Eigen::Vector3f::Constant(std::numeric_limits<float>::max());
    Eigen::Vector3f hi = Eigen::Vector3f::Constant(-std::numeric_limits<float>::max());
    int count = 0;
  } bins[kBins];
  const float scale = kBins / extent[axis];
  auto bin_of = [&](int f) {
    return std::min(kBins - 1, static_cast<int>((centroids[f][axis] - cen_lo[axis]) * scale));
  };
  for (int k = begin; k < end; ++k) {
    const int f = order_[k];
    Bin& bin = bins[bin_of(f)];
    bin.lo = bin.lo.cwiseMin(lo[f]);
    bin.hi = bin.hi.cwiseMax(hi[f]);
    ++bin.count;
  }
  float right_cost[kBins];
  {
    Bin acc;
    for (int b = kBins - 1; b > 0; --b) {
      acc.lo = acc.lo.cwiseMin(bins[b].lo);
      acc.hi = acc.hi.cwiseMax(bins[b].hi);
      acc.count += bins[b].count;
      right_cost[b] = acc.count == 0 ? 0 : HalfArea(acc.lo, acc.hi) * acc.count;
    }
  }
  int best_split = -1;
  float best_cost = std::numeric_limits<float>::max();
  Bin acc;
  for (int b = 0; b < kBins - 1; ++b) {
    acc.lo = acc.lo.cwiseMin(bins[b].lo);
    acc.hi = acc.hi.cwiseMax(bins[b].hi);
    acc.count += bins[b].count;
    if (acc.count == 0 || acc.count == count) continue;
    const float cost = HalfArea(acc.lo, acc.hi) * acc.count + right_cost[b + 1];
    if (cost < best_cost) {
      best_cost = cost;
      best_split = b;
    }
  }
  int middle;
  if (best_split < 0) {
    middle = begin + count / 2;
    std::nth_element(order_.begin() + begin, order_.begin() + middle, order_.begin() + end,
                     [&](int a, int b) { return centroids[a][axis] < centroids[b][axis]; });
  } else {
    middle = static_cast<int>(std::partition(order_.begin() + begin, order_.begin() + end,
                                             [&](int f) { return bin_of(f) <= best_split; }) -
                              order_.begin());
  }
  BuildRange(begin, middle, centroids, lo, hi);
  const int right = BuildRange(middle, end, centroids, lo, hi);
  nodes_[index] = {box_lo, right, box_hi, 0, axis};
  return index;
}

bool Bvh::Intersect(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction, float t_min,
                    float t_max, TriangleHit* hit) const {
  if (nodes_.empty()) return false;
  const Eigen::Vector3f inv = direction.cwiseInverse();
  const bool negative[3] = {direction.x() < 0, direction.y() < 0, direction.z() < 0};
  auto box_entry = [&](const Node& node, float limit) {
    const Eigen::Vector3f t0 = (node.lo - origin).cwiseProduct(inv);
    const Eigen::Vector3f t1 = (node.hi - origin).cwiseProduct(inv);
    const float enter = std::max(t0.cwiseMin(t1).maxCoeff(), t_min);
    const float leave = std::min(t0.cwiseMax(t1).minCoeff(), limit);
    return enter <= leave ? enter : std::numeric_limits<float>::infinity();
  };
  bool found = false;
  float best = t_max;
  int stack[128];
  int top = 0;
  if (box_entry(nodes_[0], best) == std::numeric_limits<float>::infinity()) return false;
  stack[top++] = 0;
  while (top > 0) {
    const Node& node = nodes_[stack[--top]];
    if (node.count > 0) {
      for (int k = node.first; k < node.first + node.count; ++k) {
        const Tri& tri = tris_[k];
        const Eigen::Vector3f p = direction.cross(tri.e2);
        const float det = tri.e1.dot(p);
        if (std::abs(det) < 1e-12f) continue;
        const float inv_det = 1.0f / det;
        const Eigen::Vector3f s = origin - tri.v0;
        const float b1 = s.dot(p) * inv_det;
        if (b1 < 0 || b1 > 1) continue;
        const Eigen::Vector3f q = s.cross(tri.e1);
        const float b2 = direction.dot(q) * inv_det;
        if (b2 < 0 || b1 + b2 > 1) continue;
        const float t = tri.e2.dot(q) * inv_det;
        if (t > t_min && t < best) {
          best = t;
          found = true;
          hit->t = t;
          hit->triangle = order_[k];
          hit->b1 = b1;
          hit->b2 = b2;
        }
      }
      continue;
    }
    const int self = static_cast<int>(&node - nodes_.data());
    int near_child = self + 1, far_child = node.first;
    if (negative[node.axis]) std::swap(near_child, far_child);
    const float t_near = box_entry(nodes_[near_child], best);
    const float t_far = box_entry(nodes_[far_child], best);
    // Push the farther child first so the nearer one is visited first.
    if (t_far != std::numeric_limits<float>::infinity()) stack[top++] = far_child;
    if (t_near != std::numeric_limits<float>::infinity()) stack[top++] = near_child;
  }
  return found;
}

}  // namespace holocap::sim
