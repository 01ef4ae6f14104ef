#include "core/point_tree.h"

#include <algorithm>
#include <utility>

namespace holocap {

namespace {
constexpr int kLeafSize = 12;
}

PointTree::PointTree(std::vector<Eigen::Vector3d> points) : points_(std::move(points)) {
  index_.resize(points_.size());
  for (size_t i = 0; i < index_.size(); ++i) index_[i] = static_cast<int>(i);
  if (!points_.empty()) Build(0, static_cast<int>(points_.size()), 0);
}

double PointTriangleDistance(const Eigen::Vector3d& p, const Eigen::Vector3d& a,
                             const Eigen::Vector3d& b, const Eigen::Vector3d& c) {
  const Eigen::Vector3d ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0 && d2 <= 0) return ap.norm();
  const Eigen::Vector3d bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0 && d4 <= d3) return bp.norm();
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) return (p - (a + d1 / (d1 - d3) * ab)).norm();
  const Eigen::Vector3d cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0 && d5 <= d6) return cp.norm();
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) return (p - (a + d2 / (d2 - d6) * ac)).norm();
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) {
    return (p - (b + (d4 - d3) / ((d4 - d3) + (d5 - d6)) * (c - b))).norm();
  }
  const double denom = 1 / (va + vb + vc);
  return (p - (a + ab * (vb * denom) + ac * (vc * denom))).norm();
}

int PointTree::Build(int begin, int end, int depth) {
  int index = static_cast<int>(nodes_.size());
  nodes_.emplace_back();
  if (end - begin <= kLeafSize) {
    nodes_[index].begin = begin;
    nodes_[index].end = end;
    return index;
  }
  Eigen::Vector3d lo = points_[begin], hi = points_[begin];
  for (int i = begin; i < end; ++i) {
    lo = lo.cwiseMin(points_[i]);
    hi = hi.cwiseMax(points_[i]);
  }
  int axis;
  (hi - lo).maxCoeff(&axis);
  int mid = (begin + end) / 2;
  std::vector<int> order(end - begin);
  for (int i = begin; i < end; ++i) order[i - begin] = i;
  std::nth_element(order.begin(), order.begin() + (mid - begin), order.end(),
                   [&](int a, int b) { return points_[a][axis] < points_[b][axis]; });
  std::vector<Eigen::Vector3d> moved_points(end - begin);
  std::vector<int> moved_index(end - begin);
  for (int i = 0; i < end - begin; ++i) {
    moved_points[i] = points_[order[i]];
    moved_index[i] = index_[order[i]];
  }
  std::copy(moved_points.begin(), moved_points.end(), points_.begin() + begin);
  std::copy(moved_index.begin(), moved_index.end(), index_.begin() + begin);
  double split = points_[mid][axis];
  int left = Build(begin, mid, depth + 1);
  int right = Build(mid, end, depth + 1);
  nodes_[index].axis = axis;
  nodes_[index].split = split;
  nodes_[index].left = left;
  nodes_[index].right = right;
  return index;
}

}  // namespace holocap
