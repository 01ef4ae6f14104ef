// The light a scan was seen in: a textured sphere seen by a ring of cameras, lit by ambient +
// directional light either fixed to the camera (a subject turning before a fixed sensor) or
// fixed to the sphere's world (a sensor circling a still subject), rendered analytically.
#include "scan/light.h"

#include <gtest/gtest.h>

#include <cmath>

#include "core/error.h"
#include "tests/reconstruction/synthetic.h"

namespace holocap {
namespace {

using testing::Sphere;

// A pattern of bands and patches on the sphere, RGB in [0.25, 0.75].
Eigen::Vector3d Albedo(const Eigen::Vector3d& unit) {
  const double a = 0.5 + 0.25 * std::sin(7 * std::atan2(unit.y(), unit.x()));
  const double b = 0.5 + 0.25 * std::cos(5 * unit.z());
  return Eigen::Vector3d(a, b, 0.5 * (a + b));
}

// The sphere through `camera`, each pixel's albedo times 1 + max(0, n . light) with n in the
// camera's frame (`light_in_camera`) or in the world (`light_in_world`), times 0.45.
cv::Mat RenderLit(const CameraModel& camera, const Sphere& sphere,
                  const Eigen::Vector3d& light_in_camera, const Eigen::Vector3d& light_in_world) {
  const int w = camera.width(), h = camera.height();
  cv::Mat bgr(h, w, CV_8UC3, cv::Scalar::all(0));
  const Eigen::Vector3d origin = camera.center_in_world();
  const Eigen::Matrix3d world_from_cam = camera.world_from_cam().rotation();
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const Eigen::Vector3d ray =
          world_from_cam * camera.Unproject(Eigen::Vector2d(x, y)).normalized();
      const double t = testing::RaySphere(origin, ray, sphere);
      if (!std::isfinite(t)) continue;
      const Eigen::Vector3d n = (origin + t * ray - sphere.centre).normalized();
      const double shading = 1 +
                             std::max(0.0, (world_from_cam.transpose() * n).dot(light_in_camera)) +
                             std::max(0.0, n.dot(light_in_world));
      const Eigen::Vector3d rgb = 0.45 * shading * Albedo(n);
      for (int c = 0; c < 3; ++c) {
        bgr.at<cv::Vec3b>(y, x)[2 - c] =
            static_cast<uint8_t>(std::clamp(std::lround(255 * rgb[c]), long{0}, long{255}));
      }
    }
  }
  return bgr;
}

struct Scene {
  Sphere sphere;
  Mesh mesh;
  std::vector<LitView> views;
};

// 24 cameras around the sphere, a little above it, lit as RenderLit says.
Scene Ring(const Eigen::Vector3d& light_in_camera, const Eigen::Vector3d& light_in_world) {
  Scene scene;
  scene.mesh = testing::SphereMesh(scene.sphere, 64, 128);
  scene.mesh.ComputeNormals();
  for (int i = 0; i < 24; ++i) {
    const double azimuth = 2 * M_PI * i / 24;
    const Eigen::Vector3d eye = scene.sphere.centre + Eigen::Vector3d(1.2 * std::cos(azimuth),
                                                                      1.2 * std::sin(azimuth), 0.3);
    LitView view;
    view.camera = CameraModel::Pinhole(200, 160, 120, CamFromWorldLookAt(eye, scene.sphere.centre));
    view.sensor_from_world = view.camera.cam_from_world().linear();
    view.bgr = RenderLit(view.camera, scene.sphere, light_in_camera, light_in_world);
    scene.views.push_back(view);
  }
  return scene;
}

TEST(ScanLight, ALightTurningWithTheSensorIsFoundAndDividedOut) {
  // From the upper right of the camera, a little from behind the subject; 1.2 times the ambient.
  const Eigen::Vector3d truth = 1.2 * Eigen::Vector3d(0.6, -0.6, -0.3).normalized();
  const Scene scene = Ring(truth, Eigen::Vector3d::Zero());
  Mesh albedo;
  const ScanLight light = EstimateScanLight(scene.mesh, scene.views,
                                            std::vector<bool>(scene.mesh.vertices.size(), true),
                                            ScanLightOptions{}, &albedo);
  ASSERT_TRUE(light.observed) << light.why;
  EXPECT_EQ(light.views, 24);
  EXPECT_GT(light.vertices, 1000);
  // The images are the model exactly, but for 8-bit levels and a tessellated sphere's normals.
  EXPECT_LT((light.light - truth).norm(), 0.08) << light.light.transpose();
  EXPECT_LT(light.rms_lit, 0.25 * light.rms_flat);
  // Every vertex seen holds its albedo (times the ambient's 0.45).
  ASSERT_EQ(albedo.colors.size(), scene.mesh.vertices.size());
  double error = 0;
  int64_t counted = 0;
  for (size_t v = 0; v < albedo.vertices.size(); ++v) {
    const Eigen::Vector3d n =
        (albedo.vertices[v].cast<double>() - scene.sphere.centre).normalized();
    if (std::abs(n.z()) > 0.5) continue;  // the poles, seen at grazing angles only
    error += (albedo.colors[v].cast<double>() / 255 - 0.45 * Albedo(n)).cwiseAbs().mean();
    ++counted;
  }
  ASSERT_GT(counted, 1000);
  EXPECT_LT(error / counted, 0.015);
}

TEST(ScanLight, ALightFixedToAStillSubjectIsNotObservedAndColoursStay) {
  // The sensor circles the subject: every patch is seen in one light, whatever it is.
  const Scene scene = Ring(Eigen::Vector3d::Zero(), Eigen::Vector3d(0.3, 0.2, 0.9));
  Mesh albedo;
  const ScanLight light = EstimateScanLight(scene.mesh, scene.views,
                                            std::vector<bool>(scene.mesh.vertices.size(), true),
                                            ScanLightOptions{}, &albedo);
  EXPECT_FALSE(light.observed);
  EXPECT_NE(light.why.find("no directional light"), std::string::npos) << light.why;
  EXPECT_EQ(light.light, Eigen::Vector3d::Zero());
}

TEST(ScanLight, TooFewSightingsAreSaid) {
  const Scene scene = Ring(Eigen::Vector3d(0.5, -0.5, 0), Eigen::Vector3d::Zero());
  const std::vector<LitView> one(scene.views.begin(), scene.views.begin() + 1);
  const ScanLight light =
      EstimateScanLight(scene.mesh, one, std::vector<bool>(scene.mesh.vertices.size(), true),
                        ScanLightOptions{}, nullptr);
  EXPECT_FALSE(light.observed);
  EXPECT_NE(light.why.find("seen twice"), std::string::npos) << light.why;
}

TEST(ScanLight, JsonRoundTripsAndRefusesAnImpossibleLight) {
  ScanLight light;
  light.observed = true;
  light.light = Eigen::Vector3d(0.1, -0.7, 0.2);
  const ScanLight back = ScanLight::FromJson(light.ToJson());
  EXPECT_TRUE(back.observed);
  EXPECT_TRUE(back.light.isApprox(light.light));
  nlohmann::json bad = light.ToJson();
  bad["light"] = {0, std::nan(""), 0};
  EXPECT_THROW(ScanLight::FromJson(bad), Error);
  bad["light"] = {1, 2};
  EXPECT_THROW(ScanLight::FromJson(bad), Error);
  EXPECT_DOUBLE_EQ(light.Shading(Eigen::Vector3d(0, 1, 0)), 1.0);
  EXPECT_NEAR(light.Shading(Eigen::Vector3d(0, -1, 0)), 1.7, 1e-12);
}

}  // namespace
}  // namespace holocap
