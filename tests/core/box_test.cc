#include "core/box.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>

namespace holocap {
namespace {

// The empty box holds nothing; extending it by points gives their box, as Eigen's does.
TEST(Box, EmptyExtendsToThePointsBoxLikeEigens) {
  Box box = Box::Empty();
  Eigen::AlignedBox3d eigen;
  EXPECT_TRUE(box.empty());
  EXPECT_FALSE(box.valid());
  EXPECT_FALSE(box.Contains(Eigen::Vector3d::Zero()));
  EXPECT_EQ(box.Volume(), 0.0);
  const Eigen::Vector3d points[] = {{0.5, -1, 2}, {-0.25, 3, 1}, {0.1, 0.2, -4}};
  for (const auto& p : points) {
    box.Extend(p);
    eigen.extend(p);
  }
  EXPECT_EQ(box.min, eigen.min());
  EXPECT_EQ(box.max, eigen.max());
  EXPECT_EQ(box.center(), eigen.center());
  EXPECT_EQ(box.size(), eigen.sizes());
  EXPECT_DOUBLE_EQ(box.Volume(), eigen.volume());
  for (const auto& p : points) EXPECT_TRUE(box.Contains(p));
  EXPECT_FALSE(box.Contains({0.6, 0, 0}));
  // A single point is a flat box: not empty, without volume.
  Box point = Box::Empty();
  point.Extend(Eigen::Vector3d(1, 2, 3));
  EXPECT_FALSE(point.empty());
  EXPECT_FALSE(point.valid());
}

TEST(Box, CornersIntersectionAndGrowthFollowEigensBox) {
  const Box a{Eigen::Vector3d(-1, -2, 0), Eigen::Vector3d(1, 2, 3)};
  const Eigen::AlignedBox3d ea(a.min, a.max);
  for (int k = 0; k < 8; ++k)
    EXPECT_EQ(a.Corner(k), ea.corner(static_cast<Eigen::AlignedBox3d::CornerType>(k))) << k;
  const Box b{Eigen::Vector3d(0, 1, -1), Eigen::Vector3d(4, 5, 1)};
  const Box both = a.Intersection(b);
  EXPECT_EQ(both.min, Eigen::Vector3d(0, 1, 0));
  EXPECT_EQ(both.max, Eigen::Vector3d(1, 2, 1));
  // Boxes that do not meet intersect in an empty box.
  const Box far{Eigen::Vector3d(5, 5, 5), Eigen::Vector3d(6, 6, 6)};
  EXPECT_TRUE(a.Intersection(far).empty());
  const Box grown = a.Grown(0.5);
  EXPECT_EQ(grown.min, Eigen::Vector3d(-1.5, -2.5, -0.5));
  EXPECT_EQ(grown.max, Eigen::Vector3d(1.5, 2.5, 3.5));
  Box joined = a;
  joined.Extend(far);
  EXPECT_EQ(joined.min, a.min);
  EXPECT_EQ(joined.max, far.max);
}

}  // namespace
}  // namespace holocap
