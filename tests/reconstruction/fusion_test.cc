// Depth fusion, marching cubes and hull on analytic spheres: exact answers, stiff inputs.
#include <gtest/gtest.h>
#include <sys/resource.h>

#include <map>
#include <random>

#include <opencv2/imgproc.hpp>

#include "core/error.h"
#include "core/projector.h"
#include "reconstruction/reconstruction.h"
#include "tests/reconstruction/synthetic.h"

namespace holocap {
namespace {

using testing::RenderSphere;
using testing::RingCameras;
using testing::Sphere;
using testing::SphereError;

// Ring cameras plus one above and one below, so every part of the sphere is seen.
std::vector<CameraModel> SurroundingCameras(const Sphere& sphere, int width = 320,
                                            int height = 240) {
  std::vector<CameraModel> cameras = RingCameras(6, sphere, 1.5, width, height);
  for (double side : {1.0, -1.0}) {
    Eigen::Vector3d eye = sphere.centre + Eigen::Vector3d(0.05, 0.02, side * 1.5);
    cameras.push_back(
        CameraModel::Pinhole(0.9 * width, width, height, CamFromWorldLookAt(eye, sphere.centre)));
  }
  return cameras;
}

// Each undirected edge: how many faces use it, and whether the two uses run opposite ways.
struct EdgeCheck {
  int64_t boundary = 0, non_manifold = 0, inconsistent = 0;
};
EdgeCheck CheckEdges(const Mesh& mesh) {
  std::map<std::pair<int, int>, std::pair<int, int>> edges;  // (min, max) -> (forward, backward)
  for (const auto& f : mesh.faces) {
    for (int k = 0; k < 3; ++k) {
      int a = f[k], b = f[(k + 1) % 3];
      auto& e = edges[{std::min(a, b), std::max(a, b)}];
      (a < b ? e.first : e.second)++;
    }
  }
  EdgeCheck check;
  for (const auto& [key, uses] : edges) {
    int total = uses.first + uses.second;
    check.boundary += total == 1;
    check.non_manifold += total > 2;
    check.inconsistent += total == 2 && uses.first != 1;
  }
  return check;
}

TEST(ProjectorTest, TableMatchesMrcalToAHundredthOfAPixel) {
  std::vector<CameraModel> lenses = {
      CameraModel(
          "LENSMODEL_OPENCV8",
          {498.6, 499.4, 321.0, 238.2, 0.35, -0.05, 0.0004, 0.0002, 0.01, 0.42, -0.02, 0.015}, 640,
          480),
      CameraModel("LENSMODEL_STEREOGRAPHIC", {300.0, 300.0, 318.2, 241.1}, 640, 480),
      CameraModel("LENSMODEL_OPENCV4", {520.3, 519.1, 322.4, 236.9, -0.082, 0.031, 0.0006, -0.0004},
                  640, 480)};
  std::mt19937 rng(3);
  for (const CameraModel& lens : lenses) {
    FastProjector projector(lens);
    double worst = 0;
    for (int i = 0; i < 2000; ++i) {
      Eigen::Vector2d pixel(std::uniform_real_distribution<>(0, 639)(rng),
                            std::uniform_real_distribution<>(0, 479)(rng));
      Eigen::Vector3d ray = lens.Unproject(pixel) * std::uniform_real_distribution<>(0.5, 5)(rng);
      float u, v;
      ASSERT_TRUE(projector.Project(ray.cast<float>(), &u, &v)) << lens.lensmodel();
      Eigen::Vector2d exact;
      ASSERT_TRUE(lens.Project(ray, &exact));
      worst = std::max(worst, (Eigen::Vector2d(u, v) - exact).norm());
    }
    EXPECT_LT(worst, 0.01) << lens.lensmodel();
  }
}

TEST(TsdfTest, SphereIsClosedSeamlessAndAccurate) {
  const Sphere sphere;
  TsdfOptions options;
  options.voxel_m = 0.01;
  options.smoothing_radius_px = 0;
  options.bounds = {Eigen::Vector3d(-1, -1, 0), Eigen::Vector3d(1, 1, 2)};
  TsdfVolume tsdf(options);
  for (const CameraModel& camera : SurroundingCameras(sphere)) {
    cv::Mat depth;
    RenderSphere(camera, sphere, &depth, nullptr);
    TsdfFrameStats stats = tsdf.Integrate(depth, camera);
    EXPECT_GT(stats.valid_pixels, 1000);
  }
  Mesh mesh = ExtractMesh(tsdf.volume());
  ASSERT_GT(mesh.faces.size(), 1000u);
  auto [mean, worst] = SphereError(mesh, sphere);
  EXPECT_LT(mean, 0.001) << "mean radial error (m)";
  EXPECT_LT(worst, 0.004);
  // Seamless across the 8^3 blocks (the sphere spans many): closed and consistently wound.
  EdgeCheck edges = CheckEdges(mesh);
  EXPECT_EQ(edges.boundary, 0);
  EXPECT_EQ(edges.non_manifold, 0);
  EXPECT_EQ(edges.inconsistent, 0);
  // Counter-clockwise seen from outside: face normals point away from the centre.
  int64_t outward = 0;
  for (const auto& f : mesh.faces) {
    Eigen::Vector3f a = mesh.vertices[f[0]], b = mesh.vertices[f[1]], c = mesh.vertices[f[2]];
    outward += (b - a).cross(c - a).dot((a + b + c) / 3 - sphere.centre.cast<float>()) > 0;
  }
  EXPECT_EQ(outward, static_cast<int64_t>(mesh.faces.size()));
  // Simplification keeps the shape with fewer triangles.
  Mesh simple = SimplifyMesh(mesh, 0.03);
  EXPECT_LT(simple.faces.size(), mesh.faces.size() / 4);
  EXPECT_LT(SphereError(simple, sphere).first, 0.004);
}

// A volume made with its blocks reserved fuses the same field as one that takes them as frames
// touch them; blocks never move as more are added, and a copy holds the same voxels.
TEST(TsdfTest, ReservedBlocksFuseTheSameFieldAndStayPut) {
  const Sphere sphere;
  TsdfOptions options;
  options.voxel_m = 0.02;
  options.smoothing_radius_px = 0;
  options.bounds = {Eigen::Vector3d(-1, -1, 0), Eigen::Vector3d(1, 1, 2)};
  TsdfVolume lazy(options);
  options.reserve_blocks = 30;  // fewer than the sphere needs: the rest as frames touch them
  TsdfVolume reserved(options);
  EXPECT_GE(reserved.volume().memory_bytes(), 30 * sizeof(VoxelBlock));
  EXPECT_EQ(reserved.volume().block_count(), 0u);
  const VoxelBlock* first = nullptr;
  Eigen::Vector3i first_coordinates;
  for (const CameraModel& camera : SurroundingCameras(sphere)) {
    cv::Mat depth;
    RenderSphere(camera, sphere, &depth, nullptr);
    lazy.Integrate(depth, camera);
    reserved.Integrate(depth, camera);
    if (first == nullptr) {
      first_coordinates = reserved.volume().BlockCoordinates().front();
      first = reserved.volume().Find(first_coordinates);
    }
  }
  ASSERT_GT(reserved.volume().block_count(), BlockStore::kChunk);  // past the first chunk
  EXPECT_EQ(reserved.volume().Find(first_coordinates), first);
  const SparseVolume copy = reserved.volume();
  size_t same = 0;
  lazy.volume().ForEachBlock([&](const Eigen::Vector3i& coordinates, const VoxelBlock& block) {
    const VoxelBlock* other = reserved.volume().Find(coordinates);
    const VoxelBlock* copied = copy.Find(coordinates);
    ASSERT_NE(other, nullptr);
    ASSERT_NE(copied, nullptr);
    ASSERT_NE(copied, other);
    for (int v = 0; v < kBlockVoxels; ++v) {
      EXPECT_EQ(block.voxels[v].sdf, other->voxels[v].sdf);
      EXPECT_EQ(block.voxels[v].weight, other->voxels[v].weight);
      EXPECT_EQ(copied->voxels[v].weight, other->voxels[v].weight);
    }
    ++same;
  });
  EXPECT_EQ(same, reserved.volume().block_count());
}

TEST(TsdfTest, InvalidDepthPixelsAreRejectedNotFused) {
  const Sphere sphere;
  TsdfOptions options;
  options.voxel_m = 0.01;
  options.max_incidence_deg = 90;  // only invalid values are rejected here
  options.bounds = {Eigen::Vector3d(-1, -1, 0), Eigen::Vector3d(1, 1, 2)};
  TsdfVolume tsdf(options);
  std::mt19937 rng(5);
  int64_t error_codes = 0, rejected = 0;
  const float bad[] = {
      std::numeric_limits<float>::quiet_NaN(), 0.0f,  std::numeric_limits<float>::infinity(),
      -std::numeric_limits<float>::infinity(), -1.0f, 100.0f};
  for (const CameraModel& camera : SurroundingCameras(sphere)) {
    cv::Mat depth;
    RenderSphere(camera, sphere, &depth, nullptr);
    for (int y = 0; y < depth.rows; ++y) {
      for (int x = 0; x < depth.cols; ++x) {
        if (!std::isfinite(depth.at<float>(y, x)) || rng() % 4 != 0) continue;
        float value = bad[rng() % 6];
        depth.at<float>(y, x) = value;
        error_codes += !std::isnan(value);
      }
    }
    rejected += tsdf.Integrate(depth, camera).rejected_pixels;
  }
  // NaN is "no measurement"; 0, +-inf, negative and out-of-range values are each rejected.
  EXPECT_EQ(rejected, error_codes);
  Mesh mesh = ExtractMesh(tsdf.volume());
  ASSERT_GT(mesh.faces.size(), 1000u);
  for (const auto& v : mesh.vertices) ASSERT_TRUE(v.allFinite());
  EXPECT_LT(SphereError(mesh, sphere).first, 0.0015);
}

// Two opposite depth cameras see a sphere before a wall 1.5 m behind it. With the foreground
// mask, what lies outside the silhouette and in front of the wall is free space: the surface
// closes at the silhouette, nothing inside the sphere is carved, and a background measured in
// front of the sphere (an occluder) carves nothing.
TEST(TsdfTest, BackgroundBeforeTheWallIsFreeSpaceAndClosesTheSurface) {
  const Sphere sphere;
  const std::vector<CameraModel> cameras = RingCameras(2, sphere, 1.5);  // pinhole, OPENCV4
  auto frame = [&](const CameraModel& camera, float background_z, cv::Mat* depth, cv::Mat* mask) {
    RenderSphere(camera, sphere, depth, mask);
    depth->setTo(background_z, *mask == 0);
  };
  TsdfOptions options;
  options.voxel_m = 0.01;
  options.smoothing_radius_px = 0;
  options.max_incidence_deg = 90;
  options.bounds = {Eigen::Vector3d(-1, -1, 0), Eigen::Vector3d(1, 1, 2)};
  TsdfOptions open = options;
  open.carve_background = false;
  TsdfVolume carved(options), plain(open);
  int64_t carved_voxels = 0;
  for (const CameraModel& camera : cameras) {
    cv::Mat depth, mask;
    frame(camera, 3.0f, &depth, &mask);
    TsdfFrameStats stats = carved.Integrate(depth, camera, mask);
    carved_voxels += stats.voxels_carved;
    EXPECT_EQ(stats.valid_pixels, cv::countNonZero(mask));
    EXPECT_EQ(plain.Integrate(depth, camera, mask).voxels_carved, 0);
  }
  EXPECT_GT(carved_voxels, 10000);
  // Carving never reaches into the subject: every observed voxel a voxel inside it is negative.
  const float truncation = static_cast<float>(carved.volume().truncation_m());
  int64_t inside = 0, free_outside = 0;
  carved.volume().ForEachBlock([&](const Eigen::Vector3i& block, const VoxelBlock& data) {
    for (int z = 0; z < kBlockSide; ++z) {
      for (int y = 0; y < kBlockSide; ++y) {
        for (int x = 0; x < kBlockSide; ++x) {
          const Voxel& v = data.at(x, y, z);
          if (v.weight <= 0) continue;
          const Eigen::Vector3d centre =
              carved.volume().CenterOf(block * kBlockSide + Eigen::Vector3i(x, y, z));
          const double distance = (centre - sphere.centre).norm() - sphere.radius;
          if (distance < -options.voxel_m) {
            ++inside;
            EXPECT_LT(v.sdf, 0) << "carved inside the sphere at " << centre.transpose();
          }
          free_outside += distance > 2 * options.voxel_m && v.sdf >= 0.999f * truncation;
        }
      }
    }
  });
  EXPECT_GT(inside, 1000);
  EXPECT_GT(free_outside, 10000);
  // The two caps end at the silhouettes without carving; with it they close up: as accurate,
  // more complete.
  const Mesh truth = testing::SphereMesh(sphere);
  const SurfaceErrors with = CompareSurfaces(ExtractMesh(carved.volume()), truth, 0.005, 20000);
  const SurfaceErrors without = CompareSurfaces(ExtractMesh(plain.volume()), truth, 0.005, 20000);
  std::printf("background carved: completeness %.2f -> %.2f mm, accuracy %.2f -> %.2f mm\n",
              without.completeness_mm, with.completeness_mm, without.accuracy_mm, with.accuracy_mm);
  EXPECT_LT(with.accuracy_mm, 1.5);
  EXPECT_LT(with.accuracy_mm, without.accuracy_mm + 0.2);
  EXPECT_LT(with.completeness_mm, without.completeness_mm - 1.0);

  // A background measured in front of the voxels (an occluder) is no evidence about them; one
  // that measured nothing leaves the mask's word: free all along the ray.
  for (auto [background_z, expect_carving] : {std::pair{0.5f, false}, std::pair{NAN, true}}) {
    TsdfVolume one(options);
    cv::Mat depth, mask;
    frame(cameras[0], background_z, &depth, &mask);
    const int64_t count = one.Integrate(depth, cameras[0], mask).voxels_carved;
    EXPECT_EQ(count > 0, expect_carving) << "background at " << background_z << " m: " << count;
  }
}

TEST(TsdfTest, GrazingMeasurementsAreDroppedAndLeaveNoSmear) {
  // A floor seen from 0.3 m height: incidence runs from ~60 to ~89 degrees across the image.
  const CameraModel camera = CameraModel::Pinhole(
      300, 320, 240, CamFromWorldLookAt(Eigen::Vector3d(0, 0, 0.3), Eigen::Vector3d(0, 0.6, 0)));
  cv::Mat depth(240, 320, CV_32F, cv::Scalar(std::numeric_limits<float>::quiet_NaN()));
  const Eigen::Matrix3d world_from_cam = camera.world_from_cam().rotation();
  for (int y = 0; y < 240; ++y) {
    for (int x = 0; x < 320; ++x) {
      Eigen::Vector3d ray = camera.Unproject(Eigen::Vector2d(x, y));
      Eigen::Vector3d dir = world_from_cam * ray;
      if (dir.z() >= -1e-6) continue;
      double t = -0.3 / dir.z();
      if (t < 8) depth.at<float>(y, x) = static_cast<float>(t * ray.z());
    }
  }
  TsdfOptions options;
  options.voxel_m = 0.01;
  options.max_incidence_deg = 80;
  options.bounds = {Eigen::Vector3d(-2, -1, -0.2), Eigen::Vector3d(2, 8, 1)};
  TsdfVolume tsdf(options);
  TsdfFrameStats stats = tsdf.Integrate(depth, camera);
  EXPECT_GT(stats.rejected_pixels, 1000) << "beyond 80 degrees of incidence";
  Mesh mesh = ExtractMesh(tsdf.volume());
  ASSERT_GT(mesh.faces.size(), 500u);
  double worst = 0;
  for (const auto& v : mesh.vertices) worst = std::max(worst, std::abs(static_cast<double>(v.z())));
  EXPECT_LT(worst, 0.01) << "the floor stays flat where it is kept";
}

TEST(TsdfTest, MillimetreVoxelsOnATwoMetreStageStayBoundedBySurface) {
  const Sphere sphere{Eigen::Vector3d(0, 0, 1), 0.2};
  TsdfOptions options;
  options.voxel_m = 0.001;
  options.smoothing_radius_px = 0;
  options.bounds = {Eigen::Vector3d(-1, -1, 0), Eigen::Vector3d(1, 1, 2)};
  TsdfVolume tsdf(options);
  std::vector<CameraModel> cameras = RingCameras(3, sphere, 1.2, 640, 480, false);
  for (const CameraModel& camera : cameras) {
    cv::Mat depth;
    RenderSphere(camera, sphere, &depth, nullptr);
    tsdf.Integrate(depth, camera);
  }
  // Dense 1 mm voxels over the stage would be 8e9 voxels (~96 GB); sparse blocks hold only
  // the truncation band around the seen surface.
  const double surface_m2 = 4 * M_PI * sphere.radius * sphere.radius;
  const double band_blocks = surface_m2 / std::pow(kBlockSide * options.voxel_m, 2) * 3;
  EXPECT_LT(static_cast<double>(tsdf.volume().block_count()), band_blocks);
  EXPECT_LT(tsdf.volume().memory_bytes(), size_t{400} << 20);
  Mesh mesh = ExtractMesh(tsdf.volume());
  EXPECT_LT(SphereError(mesh, sphere).first, 0.0003);
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  std::printf("1 mm voxels: %zu blocks, %.1f MB volume, peak RSS %.1f MB, %zu triangles\n",
              tsdf.volume().block_count(), tsdf.volume().memory_bytes() / 1048576.0,
              usage.ru_maxrss / 1024.0, mesh.faces.size());
  EXPECT_LT(usage.ru_maxrss / 1024.0, 1024.0) << "peak RSS, MB";
}

TEST(TsdfTest, SubjectTouchingTheBoundsIsCutThere) {
  // The sphere pokes 10 cm through the floor of the volume.
  const Sphere sphere{Eigen::Vector3d(0, 0, 0.1), 0.2};
  TsdfOptions options;
  options.voxel_m = 0.01;
  options.bounds = {Eigen::Vector3d(-1, -1, 0), Eigen::Vector3d(1, 1, 2)};
  TsdfVolume tsdf(options);
  for (const CameraModel& camera : SurroundingCameras(sphere)) {
    cv::Mat depth;
    RenderSphere(camera, sphere, &depth, nullptr);
    tsdf.Integrate(depth, camera);
  }
  Mesh mesh = ExtractMesh(tsdf.volume());
  ASSERT_GT(mesh.faces.size(), 500u);
  float lowest = 1e9f;
  for (const auto& v : mesh.vertices) lowest = std::min(lowest, v.z());
  EXPECT_GE(lowest, -1e-6f) << "nothing below the volume";
  EXPECT_LT(lowest, 0.011f) << "the surface reaches the boundary";
  EXPECT_LT(SphereError(mesh, sphere).first, 0.0015);
}

// One depth sensor sees the front of a sphere; eight silhouettes close the rest. Completion
// fills what the sensor did not see from the hull, carved where the sensor saw free space, and
// leaves what it saw untouched.
TEST(TsdfTest, HullCompletionClosesWhatTheDepthSensorDidNotSee) {
  const Sphere sphere;
  std::vector<View> views;
  for (const CameraModel& camera : RingCameras(8, sphere, 1.5, 320, 240)) {
    View view{"cam" + std::to_string(views.size()), camera, {}, {}};
    RenderSphere(camera, sphere, nullptr, &view.mask);
    views.push_back(view);
  }
  // The sensor sits between two ring cameras, so the hull's facets facing it are its to carve.
  const CameraModel sensor = CameraModel::Pinhole(
      300, 320, 240,
      CamFromWorldLookAt(sphere.centre + Eigen::Vector3d(1.2, 0.5, 0.1), sphere.centre));
  cv::Mat depth;
  RenderSphere(sensor, sphere, &depth, nullptr);
  TsdfOptions options;
  options.voxel_m = 0.01;
  options.smoothing_radius_px = 0;
  options.bounds = {Eigen::Vector3d(-1, -1, 0), Eigen::Vector3d(1, 1, 2)};
  TsdfVolume tsdf(options);
  tsdf.Integrate(depth, sensor);
  const Mesh seen_only = ExtractMesh(tsdf.volume());
  HullOptions hull_options;
  hull_options.voxel_m = options.voxel_m;
  hull_options.bounds = options.bounds;
  hull_options.margin_px = 0;
  VisualHull hull = ComputeVisualHull(views, hull_options);
  CompletionStats stats = tsdf.CompleteFromHull(hull, {{sensor, depth}});
  EXPECT_GT(stats.blocks_added, 0);
  EXPECT_GT(stats.voxels_carved, 0) << "the sensor's free space cuts into the hull";
  const Mesh completed = ExtractMesh(tsdf.volume());
  EXPECT_GT(CheckEdges(seen_only).boundary, 0) << "one sensor sees only a cap";
  EXPECT_EQ(CheckEdges(completed).boundary, 0) << "completed into a closed surface";
  const Mesh truth = testing::SphereMesh(sphere);
  SurfaceErrors before = CompareSurfaces(seen_only, truth, 0.005, 20000);
  SurfaceErrors after = CompareSurfaces(completed, truth, 0.005, 20000);
  std::printf(
      "sensor only: completeness %.1f mm; completed: completeness %.2f mm, accuracy %.2f mm\n",
      before.completeness_mm, after.completeness_mm, after.accuracy_mm);
  EXPECT_LT(after.completeness_mm, 3.0);
  EXPECT_GT(before.completeness_mm, 50.0);
  // Where the sensor saw the sphere the surface is the sensor's: vertices facing it are as
  // accurate as before, not pulled out to the hull.
  const Eigen::Vector3d towards = (sensor.center_in_world() - sphere.centre).normalized();
  auto facing_error = [&](const Mesh& mesh) {
    double sum = 0;
    int count = 0;
    for (const auto& v : mesh.vertices) {
      Eigen::Vector3d d = v.cast<double>() - sphere.centre;
      if (d.normalized().dot(towards) < 0.7) continue;
      sum += std::abs(d.norm() - sphere.radius);
      ++count;
    }
    return sum / std::max(count, 1);
  };
  EXPECT_LT(facing_error(completed), 0.001);
  EXPECT_NEAR(facing_error(completed), facing_error(seen_only), 1e-4);
  // Every completed vertex lies in the hull (the fill only ever removes from it).
  int64_t outside = 0;
  for (const auto& v : completed.vertices)
    outside += !hull.Contains(v.cast<double>(), options.voxel_m);
  EXPECT_EQ(outside, 0);
}

class HullTest : public ::testing::Test {
 protected:
  void SetUp() override {
    cameras_ = RingCameras(8, sphere_, 1.5, 320, 240);
    for (size_t i = 0; i < cameras_.size(); ++i) {
      View view{"cam" + std::to_string(i), cameras_[i], {}, {}};
      RenderSphere(cameras_[i], sphere_, nullptr, &view.mask);
      views_.push_back(view);
    }
    options_.voxel_m = 0.01;
    options_.bounds = {Eigen::Vector3d(-1, -1, 0), Eigen::Vector3d(1, 1, 2)};
  }
  double ContainedFraction(const VisualHull& hull, double tolerance) const {
    auto points = testing::SphereMesh(sphere_).SampleSurface(5000, 1);
    int64_t inside = 0;
    for (const auto& p : points) inside += hull.Contains(p, tolerance);
    return static_cast<double>(inside) / points.size();
  }
  Sphere sphere_;
  std::vector<CameraModel> cameras_;
  std::vector<View> views_;
  HullOptions options_;
};

TEST_F(HullTest, ContainsTheSphereAndIsTight) {
  HullSummary summary;
  VisualHull hull = ComputeVisualHull(views_, options_, &summary);
  ASSERT_EQ(summary.termination, Termination::kSuccess) << summary.message;
  EXPECT_GE(ContainedFraction(hull, 0), 0.999);
  const double sphere_volume = 4.0 / 3 * M_PI * std::pow(sphere_.radius, 3);
  EXPECT_GT(summary.volume_m3, sphere_volume);
  EXPECT_LT(summary.volume_m3, 1.15 * sphere_volume);
  // The octree decided most of the stage without touching voxels.
  const double stage_blocks = 2.0 * 2 * 2 / std::pow(kBlockSide * options_.voxel_m, 3);
  EXPECT_LT(summary.surface_blocks, 0.15 * stage_blocks);
  Mesh mesh = ExtractMesh(*hull.volume);
  EXPECT_EQ(CheckEdges(mesh).boundary, 0);
  // Every hull vertex is outside or on the sphere, and not far from it for 8 views.
  double below = 0, above = 0;
  for (const auto& v : mesh.vertices) {
    double r = (v.cast<double>() - sphere_.centre).norm() - sphere_.radius;
    below = std::min(below, r);
    above = std::max(above, r);
  }
  EXPECT_GT(below, -0.006);
  EXPECT_LT(above, 0.08);
}

TEST_F(HullTest, EmptySilhouetteEmptiesTheStrictHullButNotTheConservativeOne) {
  views_[3].mask.setTo(0);
  HullSummary strict;
  ComputeVisualHull(views_, options_, &strict);
  EXPECT_EQ(strict.termination, Termination::kDegenerate) << strict.message;
  options_.tolerated_bad_views = 1;
  HullSummary conservative;
  VisualHull hull = ComputeVisualHull(views_, options_, &conservative);
  ASSERT_EQ(conservative.termination, Termination::kSuccess);
  EXPECT_GE(ContainedFraction(hull, 0), 0.99);
}

// A hull is a subject only when a ball of its volume spans min_subject_px (8) pixels in the
// views: silhouettes of a sphere 2 cm across (3.8 px at 1.5 m with a 288 px focal length) give
// a hull that is not empty but DEGENERATE; a sphere 8 cm across (15 px) gives a SUCCESS.
TEST_F(HullTest, AHullTooSmallToBeASubjectIsDegenerate) {
  options_.voxel_m = 0.002;
  options_.bounds = {sphere_.centre - Eigen::Vector3d::Constant(0.1),
                     sphere_.centre + Eigen::Vector3d::Constant(0.1)};
  auto hull_of = [&](double radius) {
    const Sphere small{sphere_.centre, radius};
    std::vector<View> views;
    for (size_t i = 0; i < cameras_.size(); ++i) {
      View view{"cam" + std::to_string(i), cameras_[i], {}, {}};
      RenderSphere(cameras_[i], small, nullptr, &view.mask);
      views.push_back(view);
    }
    HullSummary summary;
    ComputeVisualHull(views, options_, &summary);
    return summary;
  };
  const HullSummary speck = hull_of(0.01);
  EXPECT_GT(speck.volume_m3, 0);
  EXPECT_LT(speck.subject_px, options_.min_subject_px);
  EXPECT_EQ(speck.termination, Termination::kDegenerate) << speck.message;
  EXPECT_NE(speck.message.find("too small to be a subject"), std::string::npos) << speck.message;
  const HullSummary ball = hull_of(0.04);
  EXPECT_EQ(ball.termination, Termination::kSuccess) << ball.message;
  EXPECT_GT(ball.subject_px, 12);
  EXPECT_LT(ball.subject_px, 20);
}

TEST_F(HullTest, SilhouetteOfTheWrongSizeIsAnError) {
  views_[1].mask = cv::Mat::zeros(10, 10, CV_8U);
  EXPECT_THROW(ComputeVisualHull(views_, options_), Error);
  views_[1].mask = cv::Mat();
  EXPECT_THROW(ComputeVisualHull(views_, options_), Error);
}

// Thresholded silhouettes take the closing their own boundaries ask for. Exact silhouettes of a
// sphere are clean: no closing. The same silhouettes with holes and a crack cut into each (what
// a threshold does to a subject's dark patches) gain a jump at the closing that spans them: it
// is chosen, and the hull carved from the closed silhouettes holds the sphere again where the
// unclosed ones tunnel through it.
TEST_F(HullTest, ClosingFillsHolesAndCracksAndLeavesACleanBoundaryOpen) {
  std::vector<cv::Mat> clean, ragged;
  std::vector<View> ragged_views = views_;
  for (View& view : ragged_views) {
    clean.push_back(view.mask.clone());
    cv::Rect box = cv::boundingRect(view.mask);
    const cv::Point centre(box.x + box.width / 2, box.y + box.height / 2);
    // A crack 2 px wide across most of the disk, and holes of 1 and 2 px radius.
    cv::line(view.mask, centre - cv::Point(box.width / 3, box.height / 4),
             centre + cv::Point(box.width / 3, box.height / 5), cv::Scalar(0), 2);
    for (int i = 0; i < 6; ++i) {
      const cv::Point at(box.x + box.width * (2 + i % 3) / 6, box.y + box.height * (2 + i / 3) / 5);
      cv::circle(view.mask, at, 1 + i % 2, cv::Scalar(0), -1);
    }
    ragged.push_back(view.mask.clone());
  }
  const ClosingChoice open = ChooseClosing(clean, 10, 0.05);
  EXPECT_EQ(open.close_px, 0) << open.why;
  EXPECT_EQ(open.holes, 0) << open.why;
  EXPECT_NE(open.why.find("the boundary is clean"), std::string::npos) << open.why;
  const ClosingChoice closing = ChooseClosing(ragged, 10, 0.05);
  EXPECT_GE(closing.close_px, 2) << closing.why;  // a 2 px crack needs a disk 5 px across
  EXPECT_LE(closing.close_px, 3) << closing.why;
  std::printf("clean: %s\nragged: %s\n", open.why.c_str(), closing.why.c_str());
  EXPECT_GE(closing.holes, 8 * 6) << closing.why;
  EXPECT_EQ(ChooseClosing(ragged, 10, 0.05).ToJson(), closing.ToJson());
  EXPECT_EQ(ClosingChoice::FromJson(closing.ToJson()).ToJson(), closing.ToJson());

  options_.voxel_m = 0.005;
  const auto contained = [&](int radius) {
    std::vector<View> views = ragged_views;
    const cv::Mat disk =
        cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * radius + 1, 2 * radius + 1));
    for (View& view : views) {
      if (radius > 0) cv::morphologyEx(view.mask, view.mask, cv::MORPH_CLOSE, disk);
    }
    return ContainedFraction(ComputeVisualHull(views, options_), 0);
  };
  const double unclosed = contained(0), closed = contained(closing.close_px);
  std::printf("sphere surface inside the hull: %.4f unclosed, %.4f closed\n", unclosed, closed);
  EXPECT_LT(unclosed, 0.99);
  EXPECT_GE(closed, 0.999);

  // A clean boundary with the subject's own gaps (a comb of teeth 16 px apart, the width of
  // closing 8 px) and corners: the gaps fill only past half the radii measured, so none.
  cv::Mat comb = cv::Mat::zeros(240, 320, CV_8U);
  cv::rectangle(comb, cv::Rect(60, 150, 200, 40), cv::Scalar(255), -1);
  for (int x = 60; x < 250; x += 28)
    cv::rectangle(comb, cv::Rect(x, 60, 12, 100), cv::Scalar(255), -1);
  const ClosingChoice teeth = ChooseClosing({comb}, 10, 0.05);
  EXPECT_EQ(teeth.close_px, 0) << teeth.why;
  EXPECT_GT(teeth.fill_px.back(), 1.0) << teeth.why;  // the gaps did fill at the largest radius

  EXPECT_THROW(ChooseClosing({}, 10, 0.05), Error);
  EXPECT_THROW(ChooseClosing(clean, 1, 0.05), Error);
  EXPECT_THROW(ChooseClosing(clean, 10, -1), Error);
}

TEST(SilhouetteTest, BackgroundSubtractionRecoversANoisyDisk) {
  std::mt19937 rng(9);
  std::normal_distribution<double> noise(0, 2.0);
  cv::Mat plate(240, 320, CV_8UC3), image, truth = cv::Mat::zeros(240, 320, CV_8U);
  cv::randu(plate, 40, 200);
  cv::circle(truth, {160, 120}, 60, 255, -1);
  image = plate.clone();
  for (int y = 0; y < 240; ++y) {
    for (int x = 0; x < 320; ++x) {
      cv::Vec3b& p = image.at<cv::Vec3b>(y, x);
      if (truth.at<uint8_t>(y, x)) p = cv::Vec3b((x * 7) % 255, 90, (y * 5) % 255);
      for (int c = 0; c < 3; ++c) p[c] = cv::saturate_cast<uint8_t>(p[c] + noise(rng));
    }
  }
  // Pixels of the subject that happen to match the background are holes the closing fills.
  cv::Mat mask = ExtractSilhouette(image, plate, SilhouetteOptions{});
  EXPECT_GT(MaskIoU(mask, truth), 0.97);
  EXPECT_THROW(ExtractSilhouette(image, cv::Mat(), SilhouetteOptions{}), Error);
  SilhouetteOptions bad;
  bad.threshold = 2;
  EXPECT_THROW(bad.Check(), Error);
}

// A lit subject on a dark background whose shaded side is darker than Otsu's level: the
// level alone loses the shaded side, the hysteresis (half the level, where connected) keeps it
// and leaves a dim patch of background that touches nothing bright.
TEST(SilhouetteTest, OtsuWithHysteresisKeepsTheShadedSide) {
  cv::Mat image(240, 320, CV_8UC3, cv::Scalar::all(6)), truth = cv::Mat::zeros(240, 320, CV_8U);
  cv::circle(truth, {160, 120}, 60, 255, -1);
  image.setTo(cv::Scalar::all(200), truth);
  cv::Mat shaded = truth.clone();
  shaded(cv::Rect(0, 0, 160, 240)).setTo(0);
  image.setTo(cv::Scalar::all(70), shaded);
  cv::rectangle(image, {10, 10}, {40, 40}, cv::Scalar::all(60), -1);  // dim, apart
  SilhouetteOptions otsu;
  otsu.mode = SilhouetteMode::kOtsu;
  const double with_hysteresis = MaskIoU(ExtractSilhouette(image, cv::Mat(), otsu), truth);
  otsu.hysteresis_sigmas = 0;
  const double level_alone = MaskIoU(ExtractSilhouette(image, cv::Mat(), otsu), truth);
  EXPECT_GT(with_hysteresis, 0.98);
  EXPECT_LT(level_alone, 0.6);
}

// A dim subject standing on a dim, noisy floor (a dark room): half of Otsu's level lies inside
// the floor's noise, so the hysteresis would join the floor it touches; the weak level stays
// four robust deviations above the darker class's median and keeps the floor out.
TEST(SilhouetteTest, OtsuHysteresisDoesNotJoinANoisyFloorTheSubjectTouches) {
  cv::Mat grey(240, 320, CV_8U), truth = cv::Mat::zeros(240, 320, CV_8U);
  cv::RNG rng(7);
  rng.fill(grey, cv::RNG::NORMAL, 8, 1.5);  // the room: 8 DN, noise 1.5 DN
  cv::rectangle(truth, {140, 40}, {180, 200}, 255, -1);
  grey.setTo(26, truth);  // the subject, standing on the floor's top row
  cv::Mat image;
  cv::cvtColor(grey, image, cv::COLOR_GRAY2BGR);
  SilhouetteOptions otsu;
  otsu.mode = SilhouetteMode::kOtsu;
  otsu.open_px = otsu.dilate_px = otsu.erode_px = 0;
  otsu.min_component_fraction = 0;
  const cv::Mat mask = ExtractSilhouette(image, cv::Mat(), otsu);
  EXPECT_GT(MaskIoU(mask, truth), 0.97);
  EXPECT_LT(cv::countNonZero(mask & ~truth), 0.02 * cv::countNonZero(truth));
}

// The morphology's radii scale with the image's width when morphology_width is set: a recipe
// for 640-pixel images grows a 160-pixel image's silhouette by a quarter as many pixels.
TEST(SilhouetteTest, MorphologyScalesWithTheImagesWidth) {
  cv::Mat truth = cv::Mat::zeros(120, 160, CV_8U);
  cv::rectangle(truth, {70, 20}, {89, 99}, 255, -1);
  cv::Mat image;
  cv::cvtColor(truth, image, cv::COLOR_GRAY2BGR);
  SilhouetteOptions recipe;
  recipe.mode = SilhouetteMode::kThreshold;
  recipe.open_px = 0;
  recipe.dilate_px = 8;
  recipe.erode_px = 4;
  recipe.min_component_fraction = 0;
  const int fixed = cv::countNonZero(ExtractSilhouette(image, cv::Mat(), recipe));
  recipe.morphology_width = 640;
  const int scaled = cv::countNonZero(ExtractSilhouette(image, cv::Mat(), recipe));
  // 4 px of net growth on each side of a 20 x 80 px box, then 1 px.
  EXPECT_GT(fixed, 26 * 86);
  EXPECT_LT(scaled, 23 * 83);
  EXPECT_GT(scaled, cv::countNonZero(truth));
  recipe.morphology_width = -1;
  EXPECT_THROW(recipe.Check(), Error);
}

// BGRA frames: alpha mode keeps the alpha channel exactly (no morphology: a one-pixel speck of
// alpha stays); the other modes read the colour alone, so a plate whose alpha differs from the
// image's everywhere still subtracts to the subject.
TEST(SilhouetteTest, AlphaModeReadsAlphaAndTheOthersIgnoreIt) {
  cv::Mat truth = cv::Mat::zeros(120, 160, CV_8U);
  cv::circle(truth, {80, 60}, 30, 255, -1);
  truth.at<uint8_t>(5, 5) = 255;
  cv::Mat plate(120, 160, CV_8UC4, cv::Scalar(60, 70, 80, 0)), image = plate.clone();
  image.setTo(cv::Scalar(200, 40, 90, 0), truth);
  std::vector<cv::Mat> channels;
  cv::split(image, channels);
  channels[3] = truth.clone();
  cv::merge(channels, image);
  SilhouetteOptions alpha;
  alpha.mode = SilhouetteMode::kAlpha;
  EXPECT_EQ(cv::norm(ExtractSilhouette(image, cv::Mat(), alpha), truth, cv::NORM_INF), 0);
  cv::Mat bgr;
  cv::cvtColor(image, bgr, cv::COLOR_BGRA2BGR);
  EXPECT_THROW(ExtractSilhouette(bgr, cv::Mat(), alpha), Error);
  cv::Mat opaque_plate = plate.clone();
  opaque_plate.setTo(cv::Scalar(60, 70, 80, 255));  // alpha differs from the image's everywhere
  const cv::Mat subtracted = ExtractSilhouette(image, opaque_plate, SilhouetteOptions{});
  cv::Mat disk = truth.clone();
  disk.at<uint8_t>(5, 5) = 0;
  EXPECT_GT(MaskIoU(subtracted, disk), 0.97);
}

TEST(SurfaceErrorsTest, ScaledSphereGivesItsOffset) {
  Sphere a, b = a;
  b.radius = a.radius + 0.004;
  SurfaceErrors e = CompareSurfaces(testing::SphereMesh(a), testing::SphereMesh(b), 0.005, 20000);
  EXPECT_NEAR(e.chamfer_mm, 4.0, 0.2);
  EXPECT_NEAR(e.fscore, 1.0, 1e-9);
  SurfaceErrors far = CompareSurfaces(testing::SphereMesh(a), testing::SphereMesh(b), 0.003, 20000);
  EXPECT_LT(far.fscore, 0.01);
}

// A truth made of two overlapping closed parts: the faces of each inside the other are buried,
// not surface; a part that is not closed buries nothing.
TEST(SurfaceErrorsTest, OuterSurfaceLeavesOutFacesBuriedInOtherParts) {
  const Sphere a{Eigen::Vector3d(0, 0, 1), 0.3}, b{Eigen::Vector3d(0.4, 0, 1), 0.3};
  Mesh truth = testing::SphereMesh(a, 48, 96);
  const Mesh second = testing::SphereMesh(b, 48, 96);
  const int offset = static_cast<int>(truth.vertices.size());
  truth.vertices.insert(truth.vertices.end(), second.vertices.begin(), second.vertices.end());
  for (const auto& f : second.faces)
    truth.faces.emplace_back(f + Eigen::Vector3i::Constant(offset));
  const auto outer = OnOuterSurface(truth);
  int64_t wrong = 0, buried = 0;
  const auto points = truth.SampleSurface(4000, 2);
  for (const auto& p : points) {
    const bool inside_other =
        (p - a.centre).norm() < a.radius - 1e-3 || (p - b.centre).norm() < b.radius - 1e-3;
    buried += !outer(p);
    wrong += outer(p) == inside_other;
  }
  // Each sphere has a cap of height 0.1 m inside the other: 1/6 of its area.
  EXPECT_NEAR(static_cast<double>(buried) / points.size(), 1.0 / 6, 0.02);
  EXPECT_LT(wrong, 20) << "of " << points.size()
                       << " (the facets stand off the true spheres by < 1 mm)";
  // Open parts enclose nothing: half of the second sphere buries none of the first.
  Mesh open = testing::SphereMesh(a, 48, 96);
  const int open_offset = static_cast<int>(open.vertices.size());
  open.vertices.insert(open.vertices.end(), second.vertices.begin(), second.vertices.end());
  for (size_t f = 0; f < second.faces.size() / 2; ++f)
    open.faces.emplace_back(second.faces[f] + Eigen::Vector3i::Constant(open_offset));
  const auto open_outer = OnOuterSurface(open);
  int64_t dropped = 0;
  for (const auto& p : testing::SphereMesh(a, 48, 96).SampleSurface(2000, 3))
    dropped += !open_outer(p);
  EXPECT_EQ(dropped, 0);
}

}  // namespace
}  // namespace holocap
