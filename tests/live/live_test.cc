// live/: the scan aligned rigidly and non-rigidly to a live depth frame, the refused mismatching
// scan, the depthless frame, and the CLI's error lines. Synthetic tubes seen by a 160x120
// pinhole camera, their depth rendered exactly.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>

#include "core/camera.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/image.h"
#include "core/mesh.h"
#include "core/pose.h"
#include "core/take.h"
#include "live/live.h"
#include "reconstruction/reconstruction.h"
#include "tests/reconstruction/synthetic.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

// A tube of `radius` along a centreline that runs up +z for `length` and bends by `bend_rad`
// about +y at its middle. The same ring and segment of every tube is the same vertex, so a bent
// tube is the straight one's vertices moved.
Mesh Tube(double length, double radius, double bend_rad, const Eigen::Vector3d& base) {
  constexpr int kRings = 61, kSegments = 24;
  Mesh mesh;
  const Eigen::Matrix3d turn =
      Eigen::AngleAxisd(bend_rad, Eigen::Vector3d::UnitY()).toRotationMatrix();
  for (int r = 0; r < kRings; ++r) {
    const double s = length * r / (kRings - 1);
    Eigen::Matrix3d frame = Eigen::Matrix3d::Identity();
    Eigen::Vector3d centre = base + Eigen::Vector3d(0, 0, std::min(s, length / 2));
    if (s > length / 2) {
      frame = turn;
      centre += turn * Eigen::Vector3d(0, 0, s - length / 2);
    }
    for (int k = 0; k < kSegments; ++k) {
      const double a = 2 * M_PI * k / kSegments;
      mesh.vertices.push_back(
          (centre + frame * Eigen::Vector3d(radius * std::cos(a), radius * std::sin(a), 0))
              .cast<float>());
    }
  }
  for (int r = 0; r + 1 < kRings; ++r) {
    for (int k = 0; k < kSegments; ++k) {
      const int a = r * kSegments + k, b = r * kSegments + (k + 1) % kSegments;
      mesh.faces.emplace_back(a, b, b + kSegments);
      mesh.faces.emplace_back(a, b + kSegments, a + kSegments);
    }
  }
  mesh.ComputeNormals();
  mesh.colors.assign(mesh.vertices.size(), Eigen::Matrix<uint8_t, 3, 1>(200, 150, 100));
  return mesh;
}

// A 160x120 pinhole camera 1.1 m in front of the tube (along -y), looking at its middle.
CameraModel SideCamera() {
  const Eigen::Vector3d target(0, 0, 1.0);
  return CameraModel("LENSMODEL_PINHOLE", {150, 150, 79.5, 59.5}, 160, 120,
                     CamFromWorldLookAt(target + Eigen::Vector3d(0.15, -1.1, 0.05), target));
}

// What the sensor measures: the subject before a wall 0.7 m behind it.
cv::Mat SensorDepth(const Mesh& subject, const CameraModel& camera) {
  Mesh scene = subject;
  Mesh wall;
  wall.vertices = {{-3, 0.7f, -2}, {3, 0.7f, -2}, {3, 0.7f, 4}, {-3, 0.7f, 4}};
  wall.faces = {{0, 1, 2}, {0, 2, 3}};
  scene.normals.clear();
  scene.colors.clear();
  scene.Append(wall);
  return RenderDepth(scene, camera);
}

Mesh Moved(const Mesh& mesh, const Pose& pose) {
  Mesh moved = mesh;
  for (Eigen::Vector3f& v : moved.vertices) v = (pose * v.cast<double>()).cast<float>();
  moved.ComputeNormals();
  return moved;
}

LiveSurface SurfaceOf(const Mesh& mesh, const CameraModel& camera) {
  const LiveOptions options;
  return MakeLiveSurface(SensorDepth(mesh, camera), camera, options.depth_min_m,
                         options.depth_max_m);
}

TEST(LiveAlign, RecoversAKnownRigidMotion) {
  const Mesh scan = Tube(0.6, 0.08, 1.0, Eigen::Vector3d(0, 0, 0.7));
  Pose truth = Pose::Identity();
  truth.linear() =
      Eigen::AngleAxisd(0.12, Eigen::Vector3d(0.3, 0.2, 1).normalized()).toRotationMatrix();
  truth.translation() = Eigen::Vector3d(0.05, -0.03, 0.04) +
                        (Eigen::Matrix3d::Identity() - truth.linear()) * Eigen::Vector3d(0, 0, 1.0);
  const CameraModel camera = SideCamera();
  const LiveSurface live = SurfaceOf(Moved(scan, truth), camera);
  ASSERT_GT(live.valid, 1000);
  const RigidAlignment aligned = AlignRigid(scan, live, Pose::Identity(), LiveOptions());
  const Pose error = truth.inverse() * aligned.world_from_scan;
  // Points of the tube (within 0.5 m of the rotation's centre) move by at most this much.
  EXPECT_LT(error.translation().norm(), 0.004);
  EXPECT_LT(RotationAngleDeg(error.linear()), 0.4);
  // Edge pixels at 160x120 (7 mm across) pair with the wall behind or carry slanted normals.
  EXPECT_GT(aligned.fit.inlier_fraction, 0.85);
  EXPECT_LT(aligned.fit.residual_m, 0.004);
}

// Longest ratio of an edge's deformed length to its rest length, and the shortest.
std::pair<double, double> EdgeStretch(const Mesh& rest, const Mesh& deformed) {
  double most = 0, least = 1e9;
  for (const Eigen::Vector3i& face : rest.faces) {
    for (int c = 0; c < 3; ++c) {
      const int a = face[c], b = face[(c + 1) % 3];
      const double ratio = (deformed.vertices[a] - deformed.vertices[b]).norm() /
                           (rest.vertices[a] - rest.vertices[b]).norm();
      most = std::max(most, ratio);
      least = std::min(least, ratio);
    }
  }
  return {most, least};
}

TEST(LiveAlign, NonRigidFollowsABentLimbWithoutTearing) {
  const Mesh straight = Tube(0.6, 0.08, 0, Eigen::Vector3d(0, 0, 0.7));
  const Mesh bent = Tube(0.6, 0.08, 0.5, Eigen::Vector3d(0, 0, 0.7));  // ~29 degrees at the elbow
  const CameraModel camera = SideCamera();
  const LiveSurface live = SurfaceOf(bent, camera);
  LiveOptions options;
  // The scan's upper arm lies on the live one (as the rigid alignment leaves a limb attached to
  // a body); its forearm points straight on where the live one bends away.
  const Mesh& aligned = straight;
  const NonRigidFit fit = FitNonRigid(aligned, live, options);
  EXPECT_GT(fit.nodes, 5);
  // The rigid fit cannot follow the elbow; the deformation does.
  EXPECT_LT(fit.before.inlier_fraction, 0.75);
  // (A perfect scan reaches 0.94 here: edge pixels pair with the wall or carry slanted normals.)
  EXPECT_GT(fit.after.inlier_fraction, 0.8);
  EXPECT_LT(fit.after.residual_m, 0.5 * fit.before.residual_m);
  // The forearm's tip moves by the chord of the bend, 15 cm.
  EXPECT_GT(fit.deformation_max_m, 0.12);
  // No tearing: the live tube kinks at the elbow (its own edges there stretch and shrink
  // several times over); the graph spreads the bend over its nodes, every edge within half its
  // length.
  const auto [kink_most, kink_least] = EdgeStretch(aligned, bent);
  EXPECT_GT(kink_most, 3);
  const auto [most, least] = EdgeStretch(aligned, fit.deformed);
  EXPECT_LT(most, 1.5);
  EXPECT_GT(least, 0.5);
  // The regulariser is what holds it together: all but no stiffness fits the data as well but
  // stretches the mesh further.
  LiveOptions loose = options;
  loose.arap_weight = 1e-4;
  const NonRigidFit floppy = FitNonRigid(aligned, live, loose);
  EXPECT_GT(EdgeStretch(aligned, floppy.deformed).first, most);
}

// The deformation carried from frame to frame: the same deformation of the scan moved rigidly,
// and back.
TEST(LiveAlign, DeformationGraphMovesWithTheScan) {
  const Mesh tube = Tube(0.6, 0.08, 0, Eigen::Vector3d(0, 0, 0.7));
  DeformationGraph graph(tube, 0.1, 4);
  for (size_t j = 0; j < graph.nodes.size(); ++j) {
    graph.rotation[j] =
        Eigen::AngleAxisd(0.05 * j, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
    graph.translation[j] = Eigen::Vector3d(0.01 * j, -0.02, 0.005 * j);
  }
  Pose world_from_rest = Pose::Identity();
  world_from_rest.linear() =
      Eigen::AngleAxisd(0.7, Eigen::Vector3d(0.2, 1, 0.4).normalized()).toRotationMatrix();
  world_from_rest.translation() = Eigen::Vector3d(0.3, -1.2, 0.5);
  const DeformationGraph posed = graph.Posed(world_from_rest);
  double worst = 0;
  for (size_t v = 0; v < tube.vertices.size(); v += 7) {
    const Eigen::Vector3d rest = tube.vertices[v].cast<double>();
    worst = std::max(
        worst,
        (posed.Apply(v, world_from_rest * rest) - world_from_rest * graph.Apply(v, rest)).norm());
  }
  EXPECT_LT(worst, 1e-9);
  DeformationGraph back(tube, 0.1, 4);
  back.TakeMotions(posed, world_from_rest);
  for (size_t j = 0; j < graph.nodes.size(); ++j) {
    EXPECT_LT((back.rotation[j] - graph.rotation[j]).norm(), 1e-9);
    EXPECT_LT((back.translation[j] - graph.translation[j]).norm(), 1e-9);
  }
}

// Two legs: tubes of radius 4 cm, the second 10 cm behind the first along `camera`'s ray
// through the first (its front surface 2 cm behind the first's back); the first bent by
// `bend_rad` at its knee.
Mesh Legs(const CameraModel& camera, double bend_rad, std::vector<int>* back_vertices) {
  const Eigen::Vector3d front(0, 0, 0.7);
  Eigen::Vector3d ray = front - camera.center_in_world();
  ray.z() = 0;
  Mesh legs = Tube(0.6, 0.04, bend_rad, front);
  const size_t first = legs.vertices.size();
  Mesh back = Tube(0.6, 0.04, 0, front + 0.1 * ray.normalized());
  legs.colors.clear();
  back.colors.clear();
  legs.Append(back);
  legs.ComputeNormals();
  back_vertices->clear();
  for (size_t v = first; v < legs.vertices.size(); ++v)
    back_vertices->push_back(static_cast<int>(v));
  return legs;
}

// Nodes and vertices are tied along the surface: two legs that pass within 2 cm of each other
// share no edge and no vertex weight (nodes every 7 cm: through the air they would).
TEST(LiveAlign, DeformationGraphTiesNodesAlongTheSurface) {
  std::vector<int> back;
  const Mesh legs = Legs(SideCamera(), 0, &back);
  const DeformationGraph graph(legs, 0.07, 4);
  const int first_back = back.front();
  Eigen::Vector2d back_axis = Eigen::Vector2d::Zero();
  for (int v : back) back_axis += legs.vertices[v].head<2>().cast<double>() / back.size();
  // Back-leg vertices lie 4 cm from its axis, front-leg ones at least 6 cm.
  auto leg_of_node = [&](int j) { return (graph.nodes[j].head<2>() - back_axis).norm() < 0.05; };
  int crossing_edges = 0, edges = 0;
  for (size_t j = 0; j < graph.nodes.size(); ++j) {
    for (int k : graph.edges[j]) {
      ++edges;
      if (leg_of_node(static_cast<int>(j)) != leg_of_node(k)) ++crossing_edges;
    }
  }
  EXPECT_GT(edges, 4 * static_cast<int>(graph.nodes.size()) / 2);
  EXPECT_EQ(crossing_edges, 0);
  int crossing_weights = 0;
  for (size_t v = 0; v < legs.vertices.size(); ++v) {
    const bool on_back = static_cast<int>(v) >= first_back;
    for (int n = 0; n < 4; ++n) {
      const int j = graph.vertex_node[v][n];
      if (j >= 0 && graph.vertex_weight[v][n] > 0 && leg_of_node(j) != on_back) ++crossing_weights;
    }
  }
  EXPECT_EQ(crossing_weights, 0);
}

// The front leg bends away; the back leg, which the front one hid from the sensor and still
// partly hides, stays where it was. Without the scan's own occlusion its samples behind the
// front leg pair with the front leg's surface (within the coarse gate) and are pulled onto it.
TEST(LiveAlign, NonRigidLeavesAHiddenLimbWhereItIs) {
  const CameraModel camera = SideCamera();
  std::vector<int> back;
  const Mesh rest = Legs(camera, 0, &back);
  const Mesh bent = Legs(camera, 0.5, &back);
  const LiveSurface live = SurfaceOf(bent, camera);
  const NonRigidFit fit = FitNonRigid(rest, live, LiveOptions());
  // The front leg follows its knee (its tip moves 15 cm; 41 % of the seen samples fit before,
  // 67 % after)...
  EXPECT_GT(fit.deformation_max_m, 0.1);
  EXPECT_GT(fit.after.inlier_fraction, fit.before.inlier_fraction + 0.2);
  // ... and the back leg stays: every vertex within 2 cm of where it was (1.1 cm: its edge as
  // the sensor now sees it). Paired through the front leg it moved 15 cm; tied to the front
  // leg's nodes through the air, 28 cm.
  double worst = 0;
  for (int v : back)
    worst =
        std::max(worst, static_cast<double>((fit.deformed.vertices[v] - rest.vertices[v]).norm()));
  EXPECT_LT(worst, 0.02);
}

TEST(LiveCompositor, ComposesTheLiveSurfaceWithTheUnseenScan) {
  const Mesh straight = Tube(0.6, 0.08, 0, Eigen::Vector3d(0, 0, 0.7));
  const Mesh bent = Tube(0.6, 0.08, 0.5, Eigen::Vector3d(0, 0, 0.7));
  const CameraModel camera = SideCamera();
  LiveCompositor compositor(straight, LiveOptions());
  const LiveResult result =
      compositor.Process(3, SensorDepth(bent, camera), camera, cv::Mat(), camera);
  ASSERT_EQ(result.frame.state, LiveState::kComposed) << result.frame.why;
  EXPECT_GT(result.frame.live_faces, 1000);
  // The back of the tube, which the sensor cannot see, comes from the scan: about half of it.
  EXPECT_GT(result.frame.scan_faces, straight.faces.size() / 3);
  EXPECT_LT(result.frame.scan_faces, straight.faces.size() * 4 / 5);
  EXPECT_EQ(result.composed.faces.size(), result.frame.live_faces + result.frame.scan_faces);
  // The composed back lies on the bent tube's surface (its axis within a few mm of the radius).
  const Eigen::Vector3d elbow(0, 0, 1.0);
  const Eigen::Vector3d upper =
      Eigen::AngleAxisd(0.5, Eigen::Vector3d::UnitY()) * Eigen::Vector3d::UnitZ();
  double worst = 0;
  for (size_t v = result.live.vertices.size(); v < result.composed.vertices.size(); ++v) {
    const Eigen::Vector3d p = result.composed.vertices[v].cast<double>();
    const Eigen::Vector3d rel = p - elbow;
    const double along = rel.dot(upper);
    const double off = along > 0.03      ? (rel - along * upper).norm()
                       : rel.z() < -0.03 ? Eigen::Vector2d(p.x(), p.y()).norm()
                                         : 0.08;
    worst = std::max(worst, std::abs(off - 0.08));
  }
  EXPECT_LT(worst, 0.02);
}

// A limb the scan was not bent onto (here: the alignment kept rigid) is still the subject's:
// the live pixels joined to the fitted body without a jump in depth are kept; the wall behind,
// across a jump, is not.
TEST(LiveCompositor, KeepsTheLiveLimbTheScanWasNotBentOnto) {
  const Mesh straight = Tube(0.6, 0.08, 0, Eigen::Vector3d(0, 0, 0.7));
  const Mesh bent = Tube(0.6, 0.08, 0.6, Eigen::Vector3d(0, 0, 0.7));
  const CameraModel camera = SideCamera();
  const int tube_pixels = cv::countNonZero(RenderSilhouette(bent, camera));
  LiveOptions options;
  options.nonrigid = false;
  options.min_inlier_fraction = 0.3;  // the rigid scan fits the lower half only
  const double reach = options.subject_reach_m;
  std::map<double, int64_t> kept;
  for (double r : {0.0, reach}) {
    options.subject_reach_m = r;
    LiveCompositor compositor(straight, options);
    const LiveResult result =
        compositor.Process(3, SensorDepth(bent, camera), camera, cv::Mat(), camera);
    ASSERT_EQ(result.frame.state, LiveState::kComposed) << result.frame.why;
    kept[r] = result.frame.subject_pixels;
  }
  // Near the scan alone: 1103 of the tube's 1885 pixels; grown: all of them, and no more.
  EXPECT_LT(kept[0.0], 0.8 * tube_pixels);
  EXPECT_GT(kept[reach], 0.97 * tube_pixels);
  EXPECT_LE(kept[reach], tube_pixels);
}

// The unseen scan in the light the scan was seen in, fixed to the sensor: each vertex's albedo
// times 1 + max(0, n . light), n its composed normal in the sensor's frame; colours as scanned
// with relight off.
TEST(LiveCompositor, RelightsTheUnseenScanInTheSensorsLight) {
  Mesh scan = Tube(0.6, 0.08, 0, Eigen::Vector3d(0, 0, 0.7));
  scan.colors.assign(scan.vertices.size(), Eigen::Matrix<uint8_t, 3, 1>(77, 77, 77));
  ScanAlbedo albedo;
  albedo.light.observed = true;
  albedo.light.light = Eigen::Vector3d(1.5, 0, 0.5);  // from the camera's right, a little behind
  albedo.colors.assign(scan.vertices.size(), Eigen::Matrix<uint8_t, 3, 1>(100, 90, 80));
  const CameraModel camera = SideCamera();
  const cv::Mat depth = SensorDepth(scan, camera);
  LiveCompositor relit(scan, LiveOptions(), Eigen::Vector3d::UnitZ(),
                       std::numeric_limits<double>::quiet_NaN(), albedo);
  const LiveResult result = relit.Process(0, depth, camera, cv::Mat(), camera);
  ASSERT_EQ(result.frame.state, LiveState::kComposed) << result.frame.why;
  ASSERT_EQ(result.composed.normals.size(), result.composed.vertices.size());
  const Eigen::Matrix3d to_sensor = camera.cam_from_world().linear();
  int lit = 0, scanned = 0;
  for (size_t v = result.live.vertices.size(); v < result.composed.vertices.size(); ++v) {
    const Eigen::Vector3d n = (to_sensor * result.composed.normals[v].cast<double>()).normalized();
    const double shading = 1 + std::max(0.0, n.dot(albedo.light.light));
    ASSERT_NEAR(result.composed.colors[v][0], std::min(255.0, 100 * shading), 0.51);
    ASSERT_NEAR(result.composed.colors[v][2], std::min(255.0, 80 * shading), 0.51);
    lit += shading > 1.2;
    ++scanned;
  }
  EXPECT_GT(scanned, 100);
  EXPECT_GT(lit, scanned / 5);  // the right side of the back is lit, the left is not
  EXPECT_LT(lit, scanned * 4 / 5);
  LiveOptions off;
  off.relight = false;
  LiveCompositor as_seen(scan, off, Eigen::Vector3d::UnitZ(),
                         std::numeric_limits<double>::quiet_NaN(), albedo);
  const LiveResult plain = as_seen.Process(0, depth, camera, cv::Mat(), camera);
  ASSERT_EQ(plain.frame.state, LiveState::kComposed) << plain.frame.why;
  for (size_t v = plain.live.vertices.size(); v < plain.composed.vertices.size(); ++v)
    ASSERT_EQ(plain.composed.colors[v][0], 77);
  // An albedo of another mesh is refused.
  albedo.colors.pop_back();
  EXPECT_THROW(LiveCompositor(scan, LiveOptions(), Eigen::Vector3d::UnitZ(),
                              std::numeric_limits<double>::quiet_NaN(), albedo),
               Error);
}

TEST(LiveCompositor, RefusesAScanOfAnotherShape) {
  const Mesh tube = Tube(0.6, 0.08, 0.5, Eigen::Vector3d(0, 0, 0.7));
  const Mesh ball = testing::SphereMesh({Eigen::Vector3d(0, 0, 1.0), 0.2}, 24, 48);
  const CameraModel camera = SideCamera();
  LiveCompositor compositor(ball, LiveOptions());
  const LiveResult result =
      compositor.Process(0, SensorDepth(tube, camera), camera, cv::Mat(), camera);
  EXPECT_EQ(result.frame.state, LiveState::kRefused);
  EXPECT_NE(result.frame.why.find("does not fit"), std::string::npos) << result.frame.why;
  EXPECT_TRUE(result.composed.empty());
}

// A scan of something smaller than the subject fits a part of it perfectly: a tube a third as
// long as the live one lies on its lower part, every visible point within the gate. The live
// surface joined to it goes on up the tube, so it explains about half of that surface and the
// frame is refused; the same frame composes when that check is off.
TEST(LiveCompositor, RefusesAScanOfAPartOfALargerSubject) {
  const Mesh live_tube = Tube(0.9, 0.08, 0, Eigen::Vector3d(0, 0, 0.6));
  const Mesh short_tube = Tube(0.3, 0.08, 0, Eigen::Vector3d(0, 0, 0.6));
  const CameraModel camera = SideCamera();
  LiveCompositor compositor(short_tube, LiveOptions());
  const LiveResult refused =
      compositor.Process(0, SensorDepth(live_tube, camera), camera, cv::Mat(), camera);
  EXPECT_EQ(refused.frame.state, LiveState::kRefused);
  EXPECT_GT(refused.frame.inlier_fraction, 0.9) << "the short tube fits where it lies";
  EXPECT_LT(refused.frame.explained_fraction, 0.6);
  EXPECT_NE(refused.frame.why.find("of the live surface joined to it"), std::string::npos)
      << refused.frame.why;
  EXPECT_TRUE(refused.composed.empty());

  LiveOptions unchecked;
  unchecked.min_explained_fraction = 0;
  LiveCompositor composes(short_tube, unchecked);
  const LiveResult composed =
      composes.Process(0, SensorDepth(live_tube, camera), camera, cv::Mat(), camera);
  EXPECT_EQ(composed.frame.state, LiveState::kComposed) << composed.frame.why;

  // The whole tube as the scan explains all of it.
  LiveCompositor whole(live_tube, LiveOptions());
  const LiveResult fits =
      whole.Process(0, SensorDepth(live_tube, camera), camera, cv::Mat(), camera);
  ASSERT_EQ(fits.frame.state, LiveState::kComposed) << fits.frame.why;
  EXPECT_GT(fits.frame.explained_fraction, 0.95);
}

TEST(LiveCompositor, ReportsADepthlessFrameWithoutComposingIt) {
  const Mesh tube = Tube(0.6, 0.08, 0, Eigen::Vector3d(0, 0, 0.7));
  const CameraModel camera = SideCamera();
  LiveCompositor compositor(tube, LiveOptions());
  const cv::Mat nan(camera.height(), camera.width(), CV_32F,
                    cv::Scalar(std::numeric_limits<float>::quiet_NaN()));
  const LiveResult none = compositor.Process(1, nan, camera, cv::Mat(), camera);
  EXPECT_EQ(none.frame.state, LiveState::kNoDepth);
  EXPECT_NE(none.frame.why.find("no usable depth"), std::string::npos);
  EXPECT_TRUE(none.composed.empty());
  // The next frame with depth is composed as usual.
  const LiveResult next =
      compositor.Process(2, SensorDepth(tube, camera), camera, cv::Mat(), camera);
  EXPECT_EQ(next.frame.state, LiveState::kComposed) << next.frame.why;
}

TEST(LiveCli, RefusesAMissingOrDamagedScan) {
  testing::TempDir dir("holocap-live");
  std::filesystem::create_directories(dir / "take");
  testing::ExpectOneLineError(
      testing::RunCli("live " + (dir / "take").string() + " --scan " + (dir / "none").string()),
      "is not a directory");
  std::filesystem::create_directories(dir / "empty");
  testing::ExpectOneLineError(
      testing::RunCli("live " + (dir / "take").string() + " --scan " + (dir / "empty").string()),
      "holds no mesh.ply");
  std::filesystem::create_directories(dir / "damaged");
  std::ofstream(dir / "damaged" / "mesh.ply")
      << "ply\nformat binary_little_endian 1.0\nelement vertex 9";
  testing::ExpectOneLineError(
      testing::RunCli("live " + (dir / "take").string() + " --scan " + (dir / "damaged").string()),
      "mesh.ply");
  std::filesystem::create_directories(dir / "failed");
  WritePly(dir / "failed" / "mesh.ply", Tube(0.6, 0.08, 0, Eigen::Vector3d::Zero()));
  std::ofstream(dir / "failed" / "report.json") << R"({"summary": {"termination": "DEGENERATE"}})";
  testing::ExpectOneLineError(
      testing::RunCli("live " + (dir / "take").string() + " --scan " + (dir / "failed").string()),
      "ended DEGENERATE");
  std::filesystem::create_directories(dir / "unlit");
  WritePly(dir / "unlit" / "mesh.ply", Tube(0.6, 0.08, 0, Eigen::Vector3d::Zero()));
  WritePly(dir / "unlit" / "albedo.ply", Tube(0.6, 0.08, 0, Eigen::Vector3d::Zero()));
  std::ofstream(dir / "unlit" / "lighting.json") << R"({"observed": true, "light": [0, 1)";
  testing::ExpectOneLineError(
      testing::RunCli("live " + (dir / "take").string() + " --scan " + (dir / "unlit").string()),
      "lighting.json' is damaged");
  EXPECT_FALSE(std::filesystem::exists(dir / "take" / "live"));
}

// A scan take and a live take calibrated apart each have a world of their own (z up, the floor
// at 0, but the origin and heading wherever each calibration put them): the scan does not lie on
// the live subject, and the first frame must find it there. The live depth's floor must not pull
// that search (nor the fit) down.
TEST(LiveCli, FindsAScanCalibratedInAnotherWorld) {
  testing::TempDir dir("holocap-live-world");
  const std::string turn = (dir / "turn").string(), walk = (dir / "walk").string();
  ASSERT_EQ(testing::RunCli("sim --rig single-rgbd --trajectory turn --fps 10 --frames 36 "
                            "--trajectory-speed 50 --size 320x240 --out " +
                            turn)
                .exit_code,
            0);
  // The scan take's calibration: its true models in a world turned 100 degrees about the
  // vertical and moved 2.9 m along the floor (what a calibration of the scan take alone gives).
  Pose other_from_sim = Pose::Identity();
  other_from_sim.linear() =
      Eigen::AngleAxisd(100 * M_PI / 180, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  other_from_sim.translation() = Eigen::Vector3d(2.7, -1.1, 0);
  std::filesystem::create_directories(dir / "turn" / "calib");
  for (const char* name : {"cam0", "depth0"}) {
    CameraModel model =
        CameraModel::Read(dir / "turn" / "gt" / "cameras" / (std::string(name) + ".cameramodel"));
    model.set_cam_from_world(model.cam_from_world() * other_from_sim.inverse());
    model.Write(dir / "turn" / "calib" / (std::string(name) + ".cameramodel"));
  }
  const testing::CommandResult scan = testing::RunCli("scan " + turn + " --turn");
  ASSERT_EQ(scan.exit_code, 0) << scan.output;
  // The same scan in the simulation's world, the live take's: where the subject lies.
  const testing::CommandResult same = testing::RunCli(
      "scan " + turn + " --turn --ground-truth-cameras --out " + (dir / "same").string());
  ASSERT_EQ(same.exit_code, 0) << same.output;
  ASSERT_EQ(
      testing::RunCli("sim --rig single-rgbd --frames 3 --size 320x240 --out " + walk).exit_code,
      0);
  auto live = [&](const std::string& scan_dir, const std::string& out) {
    const testing::CommandResult run =
        testing::RunCli("live " + walk + " --ground-truth-cameras --scan " + scan_dir + " --out " +
                        (dir / out).string());
    EXPECT_EQ(run.exit_code, 0) << run.output;
    return nlohmann::json::parse(ReadFileToString(dir / out / "report.json"));
  };
  const auto elsewhere = live(turn + "/scan", "elsewhere"),
             here = live((dir / "same").string(), "here");
  EXPECT_EQ(elsewhere["summary"]["termination"], "SUCCESS");
  const auto& frames = elsewhere["metrics"]["per_frame"];
  ASSERT_EQ(frames.size(), 3u);
  // The scans differ by the worlds' motion: where one lies on the subject, the other must.
  auto pose = [](const nlohmann::json& rows) {
    Pose p = Pose::Identity();
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 4; ++c) p.matrix()(r, c) = rows[r][c].get<double>();
    }
    return p;
  };
  for (size_t i = 0; i < frames.size(); ++i) {
    const auto& reference = here["metrics"]["per_frame"][i];
    EXPECT_EQ(frames[i]["state"], "composed") << frames[i].dump();
    const Pose expected = pose(reference["world_from_scan"]) * other_from_sim.inverse();
    const Pose found = pose(frames[i]["world_from_scan"]);
    EXPECT_LT((found.translation() - expected.translation()).norm(), 0.01) << i;
    EXPECT_LT(Eigen::AngleAxisd(found.linear() * expected.linear().transpose()).angle(), M_PI / 180)
        << i;
    EXPECT_NEAR(frames[i]["inlier_fraction"].get<double>(),
                reference["inlier_fraction"].get<double>(), 0.02)
        << frames[i].dump() << reference.dump();
  }
}

// The README's workflow on a small simulated take: a half turn scanned, three frames of the walk
// seen by the fixed sensor beside two held-out cameras, one frame's depth lost.
TEST(LiveCli, CompletesASimulatedWalkAndReportsADepthlessFrame) {
  testing::TempDir dir("holocap-live");
  const std::string rig = R"(name: live-rig
sync: hardware
fps: 10
sensors:
  - {name: cam0, uri: "sim:live-rig#cam0", role: color, options: {lens: LENSMODEL_OPENCV5, intrinsics: [535.4, 534.8, 320.6, 238.3, 0.08, -0.18, 0.0004, -0.0002, 0.09], size: [640, 480], position: [2.4, -1.3, 1.15], look_at: [0, 0, 0.95]}}
  - {name: depth0, uri: "sim:live-rig#depth0", role: depth, paired_with: cam0, options: {lens: LENSMODEL_OPENCV4, intrinsics: [570.3, 570.9, 319.2, 241.6, 0.01, -0.02, 0.0002, -0.0001], size: [640, 480], depth_from_color: [0.0015, -0.002, 0.001, -0.045, 0.0002, 0.0008]}}
  - {name: cam90, uri: "sim:live-rig#cam90", role: color, options: {lens: LENSMODEL_PINHOLE, intrinsics: [535, 535, 319.5, 239.5], size: [640, 480], position: [1.3, 2.4, 1.15], look_at: [0, 0, 0.95]}}
)";
  std::ofstream(dir / "live-rig.yaml") << rig;
  const std::string turn = (dir / "turn").string(), walk = (dir / "walk").string();
  ASSERT_EQ(testing::RunCli("sim --rig single-rgbd --trajectory turn --fps 10 --frames 36 "
                            "--trajectory-speed 50 --size 160x120 --out " +
                            turn)
                .exit_code,
            0);
  // The truth stands in for a calibration here, and the test says so; the subject turns (--turn).
  const testing::CommandResult scan =
      testing::RunCli("scan " + turn + " --ground-truth-cameras --turn");
  ASSERT_EQ(scan.exit_code, 0) << scan.output;
  ASSERT_EQ(testing::RunCli("sim --rig " + (dir / "live-rig.yaml").string() +
                            " --frames 3 --size 160x120 --out " + walk)
                .exit_code,
            0);
  const std::filesystem::path lost = dir / "walk" / "frames" / "depth0" / "000001.exr";
  const cv::Mat depth = ReadImage(lost);
  WriteExrDepth(lost,
                cv::Mat(depth.size(), CV_32F, cv::Scalar(std::numeric_limits<float>::quiet_NaN())));
  const testing::CommandResult live =
      testing::RunCli("live " + walk + " --ground-truth-cameras --scan " + turn + "/scan");
  ASSERT_EQ(live.exit_code, 0) << live.output;
  EXPECT_NE(live.output.find("2 composed, 1 without depth, 0 refused"), std::string::npos)
      << live.output;
  const std::filesystem::path out = dir / "walk" / "live";
  const auto report = nlohmann::json::parse(ReadFileToString(out / "report.json"));
  EXPECT_EQ(report["summary"]["termination"], "SUCCESS");
  EXPECT_TRUE(report["plan"]["left_out"].contains("colour cameras cam90"));
  // The subject turned before the still sensor (--turn): the scan finds the room's light, which
  // does not turn with it, and live relights the scan's part with it.
  const auto light =
      nlohmann::json::parse(ReadFileToString(dir / "turn" / "scan" / "lighting.json"));
  const bool found = light["observed"].get<bool>();
  EXPECT_TRUE(found) << light.dump();
  EXPECT_EQ(report["metrics"]["relit"], true) << report["metrics"]["relit_why"];
  ASSERT_TRUE(std::filesystem::exists(dir / "turn" / "scan" / "albedo.ply"));
  EXPECT_EQ(ReadPly(dir / "turn" / "scan" / "albedo.ply").vertices.size(),
            ReadPly(dir / "turn" / "scan" / "mesh.ply").vertices.size());
  const auto& frames = report["metrics"]["per_frame"];
  ASSERT_EQ(frames.size(), 3u);
  EXPECT_EQ(frames[1]["state"], "no_depth");
  for (int i : {0, 2}) {
    EXPECT_EQ(frames[i]["state"], "composed");
    EXPECT_GT(frames[i]["inlier_fraction"].get<double>(), 0.6);
    EXPECT_LT(frames[i]["residual_m"].get<double>(), 0.015);
    EXPECT_GT(frames[i]["scan_faces"].get<int64_t>(), 0);
    EXPECT_GT(frames[i]["live_faces"].get<int64_t>(), 0);
  }
  EXPECT_TRUE(std::filesystem::exists(out / "recon" / "000000.glb"));
  EXPECT_TRUE(std::filesystem::exists(out / "recon" / "000002.ply"));
  EXPECT_FALSE(std::filesystem::exists(out / "recon" / "000001.ply"));

  // The same sensor live: the walk's depth0 and cam0 replayed at their recorded pace through the
  // HAL, recorded into a new take and composed as the sets arrive (the newest set first: how
  // many are skipped depends on the machine, never which set is last).
  std::ofstream(dir / "sensor.yaml") << "name: rgbd\nsync: free-run\nfps: 10\nsensors:\n"
                                     << "  - {name: cam0, uri: \"replay:" << walk
                                     << "#cam0\", role: color, options: {pace: recorded}}\n"
                                     << "  - {name: depth0, uri: \"replay:" << walk
                                     << "#depth0\", role: depth, paired_with: cam0, options: "
                                        "{pace: recorded}}\n";
  const std::string captured = (dir / "captured").string(), sensor = (dir / "sensor.yaml").string();
  // The studio's calibration of this sensor (here the simulation's models, copied by the test
  // into a folder of its own: what a user gives with --calib).
  const std::filesystem::path studio = dir / "studio-calib";
  std::filesystem::create_directories(studio);
  for (const char* name : {"cam0", "depth0"}) {
    std::filesystem::copy_file(
        dir / "walk" / "gt" / "cameras" / (std::string(name) + ".cameramodel"),
        studio / (std::string(name) + ".cameramodel"));
  }
  // The replayed take is not calibrated: its driver knows no model, and --live says so.
  testing::ExpectOneLineError(testing::RunCli("capture --rig " + sensor + " --frames 3 --out " +
                                              (dir / "c0").string() + " --live " + turn + "/scan"),
                              "knows no model of it; give --calib DIR");
  const testing::CommandResult streamed =
      testing::RunCli("capture --rig " + sensor + " --frames 3 --out " + captured + " --live " +
                      turn + "/scan --calib " + studio.string());
  ASSERT_EQ(streamed.exit_code, 0) << streamed.output;
  EXPECT_NE(streamed.output.find("3 sets offered"), std::string::npos) << streamed.output;
  EXPECT_EQ(Take::Open(captured).size(), 3u);  // every set recorded, whatever was composed
  const auto live_report =
      nlohmann::json::parse(ReadFileToString(dir / "captured" / "live" / "report.json"));
  EXPECT_EQ(live_report["summary"]["termination"], "SUCCESS");
  EXPECT_EQ(live_report["metrics"]["offered"], 3);
  EXPECT_EQ(live_report["metrics"]["relit"], found) << live_report["metrics"]["relit_why"];
  const auto& streamed_frames = live_report["metrics"]["per_frame"];
  ASSERT_EQ(streamed_frames.size(), 3u);
  EXPECT_NE(streamed_frames[1]["state"], "composed");
  EXPECT_EQ(streamed_frames[2]["state"], "composed");
  EXPECT_GT(live_report["metrics"]["latency_s"]["max"].get<double>(), 0);
  EXPECT_TRUE(std::filesystem::exists(dir / "captured" / "live" / "recon" / "000002.glb"));
  // The models it composed with are the new take's calibration: `live` composes every set later.
  EXPECT_TRUE(std::filesystem::exists(dir / "captured" / "calib" / "depth0.cameramodel"));
  const testing::CommandResult later = testing::RunCli("live " + captured + " --scan " + turn +
                                                       "/scan --out " + (dir / "later").string());
  ASSERT_EQ(later.exit_code, 0) << later.output;
  EXPECT_NE(later.output.find("2 composed, 1 without depth, 0 refused"), std::string::npos)
      << later.output;
  // The simulation's true models, asked for by the rig (cameras: truth), compose but never
  // become the new take's calibration.
  std::ofstream(dir / "truth.yaml") << "name: rgbd\nsync: free-run\nfps: 10\nsensors:\n"
                                    << "  - {name: cam0, uri: \"replay:" << walk
                                    << "#cam0\", role: color, options: {cameras: truth}}\n"
                                    << "  - {name: depth0, uri: \"replay:" << walk
                                    << "#depth0\", role: depth, paired_with: cam0, options: "
                                       "{cameras: truth}}\n";
  const testing::CommandResult truth =
      testing::RunCli("capture --rig " + (dir / "truth.yaml").string() + " --frames 3 --out " +
                      (dir / "truth").string() + " --live " + turn + "/scan");
  ASSERT_EQ(truth.exit_code, 0) << truth.output;
  EXPECT_NE(truth.output.find("the simulation's true models (never written to calib/)"),
            std::string::npos)
      << truth.output;
  EXPECT_EQ(Take::Open(dir / "truth").size(), 3u);
  EXPECT_FALSE(std::filesystem::exists(dir / "truth" / "calib"));
  testing::ExpectOneLineError(
      testing::RunCli("live " + (dir / "truth").string() + " --scan " + turn + "/scan"),
      "is not calibrated");
  // One frame of six whose depth the scan does not fit (a wall 4 m away, behind where the subject
  // stood): refused, well under the fifth that calls the scan another subject, and still not a
  // SUCCESS: the output misses that frame, and the termination says how many and why.
  const std::string six = (dir / "six").string();
  ASSERT_EQ(testing::RunCli("sim --rig " + (dir / "live-rig.yaml").string() +
                            " --frames 6 --size 160x120 --out " + six)
                .exit_code,
            0);
  const std::filesystem::path wall = dir / "six" / "frames" / "depth0" / "000003.exr";
  WriteExrDepth(wall, cv::Mat(ReadImage(wall).size(), CV_32F, cv::Scalar(4.0f)));
  const testing::CommandResult refused =
      testing::RunCli("live " + six + " --ground-truth-cameras --scan " + turn + "/scan");
  EXPECT_EQ(refused.exit_code, 1) << refused.output;
  EXPECT_NE(refused.output.find("DEGENERATE: 1 of 6 frames with depth were refused"),
            std::string::npos)
      << refused.output;
  EXPECT_NE(refused.output.find("first set 3: "), std::string::npos) << refused.output;
  const auto refused_report =
      nlohmann::json::parse(ReadFileToString(dir / "six" / "live" / "report.json"));
  EXPECT_EQ(refused_report["summary"]["termination"], "DEGENERATE");
  EXPECT_EQ(refused_report["metrics"]["per_frame"][3]["state"], "refused");
  // Bad set-ups are one error line each, before anything is recorded.
  testing::ExpectOneLineError(
      testing::RunCli("capture --rig " + sensor + " --frames 3 --out " + (dir / "c2").string() +
                      " --live " + turn + "/scan --calib " + dir.path().string()),
      "no depth0.cameramodel");
  testing::ExpectOneLineError(
      testing::RunCli("capture --rig " + sensor + " --frames 3 --out " + (dir / "c3").string() +
                      " --live " + (dir / "nothing").string() + " --calib " + studio.string()),
      "is not a directory");
  EXPECT_FALSE(std::filesystem::exists(dir / "c0"));
  EXPECT_FALSE(std::filesystem::exists(dir / "c2"));
  EXPECT_FALSE(std::filesystem::exists(dir / "c3"));
}

}  // namespace
}  // namespace holocap
