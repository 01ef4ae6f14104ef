#include "sim/render.h"

#include <gtest/gtest.h>

#include <chrono>
#include <cstdio>
#include <random>

#include "sim/bvh.h"
#include "sim/scene.h"
#include "sim/sim.h"

namespace holocap::sim {
namespace {

// Every lens of the built-in rigs: sub-pixel rays from the table project back where they were
// asked for. Small images keep it quick; the interpolation error scales as 1/focal length, so
// these are the hardest case.
TEST(RayTableTest, InterpolatedRaysProjectBackToTheirPixels) {
  for (const std::string rig_name : BuiltinRigNames()) {
    const RigDescription rig = BuiltinRig(rig_name);
    for (const SensorSpec& sensor : rig.sensors) {
      const CameraModel camera = SimSensorModel(rig, sensor, 160);
      const RayTable table(camera);
      std::mt19937 rng(5);
      std::uniform_real_distribution<double> ux(-0.5, camera.width() - 0.5),
          uy(-0.5, camera.height() - 0.5);
      double worst = 0, worst_centre = 0;
      for (int k = 0; k < 2000; ++k) {
        const Eigen::Vector2d pixel(ux(rng), uy(rng));
        Eigen::Vector2d back;
        ASSERT_TRUE(camera.Project(table.At(pixel.x(), pixel.y()), &back));
        worst = std::max(worst, (back - pixel).norm());
        const int cx = static_cast<int>(std::lround(pixel.x()));
        const int cy = static_cast<int>(std::lround(pixel.y()));
        if (cx < 0 || cy < 0 || cx >= camera.width() || cy >= camera.height()) continue;
        ASSERT_TRUE(camera.Project(table.Center(cx, cy), &back));
        worst_centre = std::max(worst_centre, (back - Eigen::Vector2d(cx, cy)).norm());
      }
      std::printf("%s %s (%s, %dx%d): max round-trip error %.2e px (centres %.2e px)\n",
                  rig_name.c_str(), sensor.name.c_str(), camera.lensmodel().c_str(), camera.width(),
                  camera.height(), worst, worst_centre);
      EXPECT_LT(worst, 0.005) << sensor.name;
      EXPECT_LT(worst_centre, 1e-4) << sensor.name;
    }
  }
}

TEST(BvhTest, MatchesBruteForceIntersection) {
  const std::vector<Part> parts = MakeHumanoid();
  Mesh mesh;
  for (const Part& part : parts) mesh.Append(part.mesh);
  Bvh bvh;
  bvh.Build(mesh.vertices, mesh.faces);
  std::mt19937 rng(9);
  std::uniform_real_distribution<float> u(-1, 1);
  int hits = 0;
  for (int k = 0; k < 3000; ++k) {
    const Eigen::Vector3f origin(2 * u(rng), 2 * u(rng), 0.5f + u(rng));
    const Eigen::Vector3f target(0.2f * u(rng), 0.2f * u(rng), 0.3f * u(rng));
    const Eigen::Vector3f direction = (target - origin).normalized();
    float best = std::numeric_limits<float>::infinity();
    int best_face = -1;
    for (size_t f = 0; f < mesh.faces.size(); ++f) {
      const Eigen::Vector3f a = mesh.vertices[mesh.faces[f][0]];
      const Eigen::Vector3f e1 = mesh.vertices[mesh.faces[f][1]] - a;
      const Eigen::Vector3f e2 = mesh.vertices[mesh.faces[f][2]] - a;
      const Eigen::Vector3f p = direction.cross(e2);
      const float det = e1.dot(p);
      if (std::abs(det) < 1e-12f) continue;
      const Eigen::Vector3f s = origin - a;
      const float b1 = s.dot(p) / det;
      const Eigen::Vector3f q = s.cross(e1);
      const float b2 = direction.dot(q) / det;
      const float t = e2.dot(q) / det;
      if (b1 >= 0 && b2 >= 0 && b1 + b2 <= 1 && t > 0 && t < best) {
        best = t;
        best_face = static_cast<int>(f);
      }
    }
    TriangleHit hit;
    const bool found = bvh.Intersect(origin, direction, 0, 100, &hit);
    ASSERT_EQ(found, best_face >= 0);
    if (found) {
      ++hits;
      EXPECT_NEAR(hit.t, best, 1e-5f);
    }
  }
  EXPECT_GT(hits, 500);
}

TEST(RenderTest, ColorIsDeterministicAndAntialiasingTouchesOnlyEdges) {
  const RigDescription rig = BuiltinRig("single-rgbd");
  const CameraModel camera = SimSensorModel(rig, rig.sensor("cam0"), 160);
  const RayTable table(camera);
  const Scene scene(SceneKind::kSubject, SimOptions::DefaultSimBoard(), {camera}, 0, 1);
  const auto snapshot = scene.At(0.3, 9);
  const ColorRender a = RenderColor(*snapshot, camera, table, 4, 7);
  const ColorRender b = RenderColor(*snapshot, camera, table, 4, 7);
  const ColorRender plain = RenderColor(*snapshot, camera, table, 1, 7);
  EXPECT_EQ(cv::norm(a.radiance, b.radiance, cv::NORM_INF), 0.0);
  EXPECT_GT(a.antialiased_pixels, 50);
  EXPECT_LT(a.antialiased_pixels, camera.width() * camera.height() / 4);
  int changed = 0;
  for (int y = 0; y < camera.height(); ++y) {
    for (int x = 0; x < camera.width(); ++x) {
      changed += cv::norm(a.radiance.at<cv::Vec3f>(y, x) - plain.radiance.at<cv::Vec3f>(y, x)) > 0;
    }
  }
  EXPECT_GT(changed, 0);
  EXPECT_LE(changed, a.antialiased_pixels);
  EXPECT_GT(cv::countNonZero(a.mask), 200);  // the subject is in view
}

}  // namespace
}  // namespace holocap::sim
