// Vertex colouring on ray-cast spheres with a known surface colour: views that see a vertex
// give its colour, occluded views do not, and vertices no view sees are filled from their
// seen neighbours over the mesh.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>

#include "core/error.h"
#include "reconstruction/reconstruction.h"
#include "tests/reconstruction/synthetic.h"

namespace holocap {
namespace {

using testing::RaySphere;
using testing::RingCameras;
using testing::Sphere;

// A smooth colour over the unit sphere of directions (RGB, 0..255).
Eigen::Vector3f SurfaceColour(const Eigen::Vector3d& direction) {
  return Eigen::Vector3f(128 + 100 * direction.x(), 128 + 100 * direction.y(),
                         128 + 100 * direction.z());
}

struct ColouredSphere {
  Sphere sphere;
  bool flat = false;  // one colour (pure red) instead of SurfaceColour
  Eigen::Vector3f ColourAt(const Eigen::Vector3d& point) const {
    return flat ? Eigen::Vector3f(255, 0, 0) : SurfaceColour((point - sphere.centre).normalized());
  }
};

// Ray-cast image (BGR) of the nearest sphere at each pixel; black where none.
cv::Mat RayCast(const CameraModel& camera, const std::vector<ColouredSphere>& spheres) {
  const int w = camera.width(), h = camera.height();
  Eigen::Matrix2Xd pixels(2, w * h);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) pixels.col(y * w + x) << x, y;
  const Eigen::Matrix3Xd rays = camera.UnprojectMany(pixels);
  const Eigen::Vector3d origin = camera.center_in_world();
  const Eigen::Matrix3d world_from_cam = camera.world_from_cam().rotation();
  cv::Mat image(h, w, CV_8UC3, cv::Scalar::all(0));
  for (int i = 0; i < w * h; ++i) {
    const Eigen::Vector3d ray = world_from_cam * rays.col(i).normalized();
    double best = std::numeric_limits<double>::infinity();
    const ColouredSphere* hit = nullptr;
    for (const auto& s : spheres) {
      const double t = RaySphere(origin, ray, s.sphere);
      if (t < best) best = t, hit = &s;
    }
    if (hit == nullptr) continue;
    const Eigen::Vector3f rgb = hit->ColourAt(origin + best * ray);
    image.at<cv::Vec3b>(i / w, i % w) =
        cv::Vec3b(cv::saturate_cast<uint8_t>(rgb.z()), cv::saturate_cast<uint8_t>(rgb.y()),
                  cv::saturate_cast<uint8_t>(rgb.x()));
  }
  return image;
}

std::vector<View> Views(const std::vector<CameraModel>& cameras,
                        const std::vector<ColouredSphere>& spheres) {
  std::vector<View> views;
  for (size_t i = 0; i < cameras.size(); ++i)
    views.push_back({"cam" + std::to_string(i), cameras[i], RayCast(cameras[i], spheres), {}});
  return views;
}

double ColourError(const Eigen::Matrix<uint8_t, 3, 1>& colour, const Eigen::Vector3f& truth) {
  return (colour.cast<float>() - truth).cwiseAbs().maxCoeff();
}

TEST(TextureTest, SeenVerticesTakeTheirColourAndThePolesAreFilledFromTheirNeighbours) {
  const Sphere sphere;
  // Six cameras around the equator see neither pole squarely: the caps are filled.
  const std::vector<CameraModel> cameras = RingCameras(6, sphere, 1.5, 320, 240);
  const std::vector<View> views = Views(cameras, {{sphere}});
  const Mesh mesh = testing::SphereMesh(sphere, 48, 96);
  TextureOptions options;
  options.atlas = false;
  options.min_cos_incidence = 0.3;
  const TexturedMesh textured = TextureMesh(mesh, views, options);
  const int64_t n = static_cast<int64_t>(mesh.vertices.size());
  EXPECT_EQ(textured.seen_vertices + textured.filled_vertices + textured.uncoloured_vertices, n);
  EXPECT_EQ(textured.uncoloured_vertices, 0);
  EXPECT_GT(textured.filled_vertices, n / 50);
  EXPECT_GT(textured.seen_vertices, n * 8 / 10);
  double seen_error = 0, filled_error = 0, filled_worst = 0;
  // The fill obeys the maximum principle: its colours lie within the range of the seen ones.
  Eigen::Vector3f low = Eigen::Vector3f::Constant(255), high = Eigen::Vector3f::Zero();
  std::vector<bool> seen(n);
  for (int64_t i = 0; i < n; ++i) {
    const Eigen::Vector3d p = mesh.vertices[i].cast<double>();
    const Eigen::Vector3f truth = SurfaceColour((p - sphere.centre).normalized());
    // A vertex is seen when some camera views it within the incidence threshold.
    for (const auto& camera : cameras) {
      const Eigen::Vector3d to_camera = (camera.center_in_world() - p).normalized();
      if (to_camera.dot((p - sphere.centre).normalized()) >= options.min_cos_incidence)
        seen[i] = true;
    }
    const double error = ColourError(textured.mesh.colors[i], truth);
    if (seen[i]) {
      seen_error += error;
      low = low.cwiseMin(textured.mesh.colors[i].cast<float>());
      high = high.cwiseMax(textured.mesh.colors[i].cast<float>());
    } else {
      filled_error += error;
      // The mesh's poles are rings of coincident vertices, each joined to its own sector only.
      const bool pole = std::abs((p - sphere.centre).z()) > 0.9999 * sphere.radius;
      if (!pole) filled_worst = std::max(filled_worst, error);
    }
  }
  const int64_t seen_count = std::count(seen.begin(), seen.end(), true);
  EXPECT_NEAR(static_cast<double>(textured.seen_vertices), static_cast<double>(seen_count),
              0.02 * n);
  EXPECT_LT(seen_error / seen_count, 4.0);  // bilinear sampling of a smooth colour
  // The caps' truth varies by ~20 DN across them; the fill comes from their rims.
  // Left grey (128), the lower cap would be ~100 DN off in blue.
  EXPECT_LT(filled_error / (n - seen_count), 20.0);
  EXPECT_LT(filled_worst, 45.0);
  for (int64_t i = 0; i < n; ++i) {
    if (seen[i]) continue;
    const Eigen::Vector3f c = textured.mesh.colors[i].cast<float>();
    EXPECT_TRUE((c.array() >= low.array() - 1).all() && (c.array() <= high.array() + 1).all()) << i;
  }
  const nlohmann::json metrics = textured.Metrics();
  EXPECT_NEAR(metrics["seen_fraction"].get<double>() + metrics["filled_fraction"].get<double>(),
              1.0, 1e-9);
}

TEST(TextureTest, OccludedViewsGiveNoColourAndUnreachablePartsStayUncoloured) {
  const Sphere sphere;
  // A red ball between the sphere and camera 0, and a small ball inside the sphere that no
  // camera sees; both are part of the mesh.
  ColouredSphere occluder{{sphere.centre + Eigen::Vector3d(0.7, 0, 0), 0.12}, true};
  const std::vector<CameraModel> cameras = RingCameras(4, sphere, 1.5, 320, 240, false);
  const std::vector<View> views = Views(cameras, {{sphere}, occluder});
  Mesh mesh = testing::SphereMesh(sphere, 48, 96);
  const int64_t main_vertices = static_cast<int64_t>(mesh.vertices.size());
  Mesh hidden = testing::SphereMesh({sphere.centre, 0.05}, 8, 16);  // inside the sphere
  mesh.Append(hidden);
  mesh.Append(testing::SphereMesh(occluder.sphere, 24, 48));
  TextureOptions options;
  options.atlas = false;
  const TexturedMesh textured = TextureMesh(mesh, views, options);
  EXPECT_EQ(textured.uncoloured_vertices, static_cast<int64_t>(hidden.vertices.size()));
  for (int64_t i = main_vertices; i < main_vertices + static_cast<int64_t>(hidden.vertices.size());
       ++i) {
    EXPECT_EQ(textured.mesh.colors[i].cast<int>(), Eigen::Vector3i(128, 128, 128));
  }
  // No vertex of the sphere may take the occluder's red (camera 0 sees it where it hides them).
  int64_t reddish = 0;
  double worst = 0;
  for (int64_t i = 0; i < main_vertices; ++i) {
    const Eigen::Vector3d p = mesh.vertices[i].cast<double>();
    const Eigen::Vector3f truth = SurfaceColour((p - sphere.centre).normalized());
    const double error = ColourError(textured.mesh.colors[i], truth);
    worst = std::max(worst, error);
    reddish += error > 40;
  }
  EXPECT_EQ(reddish, 0) << "worst error " << worst;
}

TEST(TextureTest, BadOptionsAreErrors) {
  TextureOptions options;
  options.occlusion_scale = 0;
  EXPECT_THROW(options.Check(), Error);
  options = {};
  options.fill_smoothing_iterations = -1;
  EXPECT_THROW(options.Check(), Error);
}

}  // namespace
}  // namespace holocap
