// The subject's meshes are closed: every edge is shared by exactly two faces that traverse it
// in opposite directions (consistent outward orientation), and each part encloses a positive
// volume.
#include <gtest/gtest.h>

#include <map>

#include "sim/scene.h"
#include "sim/sim.h"

namespace holocap::sim {
namespace {

void ExpectClosed(const Mesh& mesh, const std::string& what) {
  std::map<std::pair<int, int>, int> directed;
  for (const Eigen::Vector3i& f : mesh.faces) {
    for (int k = 0; k < 3; ++k) ++directed[{f[k], f[(k + 1) % 3]}];
  }
  int bad = 0;
  for (const auto& [edge, count] : directed) {
    const auto reverse = directed.find({edge.second, edge.first});
    if (count != 1 || reverse == directed.end() || reverse->second != 1) ++bad;
  }
  EXPECT_EQ(bad, 0) << what << ": edges not shared by exactly two opposite faces";
  double volume = 0;
  for (const Eigen::Vector3i& f : mesh.faces) {
    volume += mesh.vertices[f[0]].cast<double>().dot(
                  mesh.vertices[f[1]].cast<double>().cross(mesh.vertices[f[2]].cast<double>())) /
              6;
  }
  EXPECT_GT(volume, 1e-5) << what << ": faces must wind counter-clockwise seen from outside";
}

TEST(SceneMeshTest, HumanoidAndObjectPartsAreClosed) {
  for (const Part& part : MakeHumanoid()) ExpectClosed(part.mesh, part.name);
  for (const Part& part : MakeObject()) ExpectClosed(part.mesh, part.name);
}

TEST(SceneMeshTest, WorldMeshPerFrameIsClosedMovesAndStandsOnTheFloor) {
  const Scene scene(SceneKind::kSubject, SimOptions::DefaultSimBoard(), {}, 1, 1);
  EXPECT_FALSE(scene.At(0, 0)->has_subject());  // the clean plate
  const auto a = scene.At(0.5, 1);
  const auto b = scene.At(0.8, 2);
  ExpectClosed(a->subject_mesh(), "humanoid at 0.5 s");
  ASSERT_EQ(a->subject_mesh().vertices.size(), b->subject_mesh().vertices.size());
  double moved = 0, lowest = 1e9, highest = -1e9;
  for (size_t v = 0; v < a->subject_mesh().vertices.size(); ++v) {
    moved = std::max(moved,
                     static_cast<double>(
                         (a->subject_mesh().vertices[v] - b->subject_mesh().vertices[v]).norm()));
    lowest = std::min(lowest, static_cast<double>(a->subject_mesh().vertices[v].z()));
    highest = std::max(highest, static_cast<double>(a->subject_mesh().vertices[v].z()));
  }
  EXPECT_GT(moved, 0.05);  // limbs and body move over 0.3 s
  EXPECT_NEAR(lowest, 0.001, 1e-4);
  EXPECT_GT(highest, 1.6);
  EXPECT_LT(highest, 1.95);
}

}  // namespace
}  // namespace holocap::sim
