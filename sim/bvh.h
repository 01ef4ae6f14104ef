// A bounding-volume hierarchy over triangles for ray casting: binned SAH build, flat node
// array, front-to-back stack traversal and Moller-Trumbore tests in float (1e-7 relative is
// sub-micrometre in a metres-scale studio).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <vector>

namespace holocap::sim {

struct TriangleHit {
  float t = 0;           // distance along the (unit) ray
  int triangle = -1;     // index into the faces given to Build
  float b1 = 0, b2 = 0;  // barycentrics of vertices 1 and 2
};

class Bvh {
 public:
  void Build(const std::vector<Eigen::Vector3f>& vertices,
             const std::vector<Eigen::Vector3i>& faces);
  bool empty() const { return nodes_.empty(); }
  // Nearest hit with t in (t_min, t_max); false when none.
  bool Intersect(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction, float t_min,
                 float t_max, TriangleHit* hit) const;
  const Eigen::Vector3f& bounds_min() const { return nodes_[0].lo; }
  const Eigen::Vector3f& bounds_max() const { return nodes_[0].hi; }

 private:
  struct Node {
    Eigen::Vector3f lo;
    int first;  // leaf: first triangle in order_; inner: right child (left is this + 1)
    Eigen::Vector3f hi;
    int count;  // leaf: triangle count (> 0); inner: 0 and `axis` below
    int axis;
  };
  struct Tri {
    Eigen::Vector3f v0, e1, e2;
  };
  int BuildRange(int begin, int end, std::vector<Eigen::Vector3f>& centroids,
                 std::vector<Eigen::Vector3f>& lo, std::vector<Eigen::Vector3f>& hi);

  std::vector<Node> nodes_;
  std::vector<Tri> tris_;   // in leaf order
  std::vector<int> order_;  // leaf order -> original face index
};

}  // namespace holocap::sim
