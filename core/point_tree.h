// Exact nearest-neighbour queries over a static point set (a kd-tree), and through it exact
// point-to-surface distances (triangles indexed by their centroids).
#pragma once

#include <Eigen/Core>
#include <cmath>
#include <limits>
#include <vector>

namespace holocap {

class PointTree {
 public:
  explicit PointTree(std::vector<Eigen::Vector3d> points);
  // The smallest `distance(index)` over the points, where distance(i) >= |query - point i| -
  // `slack`: the kd-tree prunes with that bound (used for triangles by their centroids).
  template <typename Distance>
  double Nearest(const Eigen::Vector3d& query, double slack, Distance distance) const;
  size_t size() const { return points_.size(); }

 private:
  struct Node {
    int axis = -1;  // -1: leaf
    double split = 0;
    int left = -1, right = -1;
    int begin = 0, end = 0;  // leaf range in points_
  };
  int Build(int begin, int end, int depth);
  std::vector<Eigen::Vector3d> points_;
  std::vector<int> index_;  // original index of points_[i]
  std::vector<Node> nodes_;
};

template <typename Distance>
double PointTree::Nearest(const Eigen::Vector3d& query, double slack, Distance distance) const {
  double best = std::numeric_limits<double>::infinity();
  int stack[128];
  double stack_gap[128];
  int top = 0;
  if (points_.empty()) return best;
  stack[top] = 0;
  stack_gap[top++] = 0;
  while (top > 0) {
    --top;
    const int n = stack[top];
    if (stack_gap[top] - slack >= best) continue;
    const Node& node = nodes_[n];
    if (node.axis < 0) {
      for (int i = node.begin; i < node.end; ++i) {
        if ((points_[i] - query).norm() - slack < best) best = std::min(best, distance(index_[i]));
      }
      continue;
    }
    const double diff = query[node.axis] - node.split;
    stack[top] = diff < 0 ? node.right : node.left;
    stack_gap[top++] = std::abs(diff);
    stack[top] = diff < 0 ? node.left : node.right;
    stack_gap[top++] = 0;
  }
  return best;
}

// Distance from a point to a triangle (Ericson, Real-Time Collision Detection, 5.1.5).
double PointTriangleDistance(const Eigen::Vector3d& p, const Eigen::Vector3d& a,
                             const Eigen::Vector3d& b, const Eigen::Vector3d& c);

}  // namespace holocap
