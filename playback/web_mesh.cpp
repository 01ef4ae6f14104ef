// The reconstruction's textured meshes read back from binary glTF and drawn natively the way the
// web player's mesh stream draws them.
#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "core/error.h"
#include "core/fs.h"
#include "playback/internal/web_stream.h"
#include "playback/playback.h"

namespace holocap {
cv::Vec3f web::SampleAtlas(const cv::Mat& atlas, float u, float v) {
  const float x = u * atlas.cols - 0.5f, y = v * atlas.rows - 0.5f;
  const int x0 = static_cast<int>(std::floor(x)), y0 = static_cast<int>(std::floor(y));
  const float fx = x - x0, fy = y - y0;
  auto at = [&](int xi, int yi) {
    const cv::Vec3b& t =
        atlas.at<cv::Vec3b>(std::clamp(yi, 0, atlas.rows - 1), std::clamp(xi, 0, atlas.cols - 1));
    return cv::Vec3f(t[0], t[1], t[2]) * (1.0f / 255);
  };
  return (at(x0, y0) * (1 - fx) + at(x0 + 1, y0) * fx) * (1 - fy) +
         (at(x0, y0 + 1) * (1 - fx) + at(x0 + 1, y0 + 1) * fx) * fy;
}

RenderedView RenderTexturedMesh(const TexturedMeshFrame& mesh, const CameraModel& camera) {
  if (!camera.has_core()) Fail("camera lens ", camera.lensmodel(), " has no pinhole core");
  const double fx = camera.intrinsics()[0], fy = camera.intrinsics()[1];
  const double cx = camera.intrinsics()[2], cy = camera.intrinsics()[3];
  const int w = camera.width(), h = camera.height();
  RenderedView view;
  view.color = cv::Mat::zeros(h, w, CV_32FC3);
  view.alpha = cv::Mat::zeros(h, w, CV_32FC1);
  view.depth = cv::Mat(h, w, CV_32FC1, cv::Scalar(std::numeric_limits<float>::infinity()));
  const bool textured = !mesh.atlas.empty();
  constexpr double kNear = 1e-3;
  for (size_t f = 0; f < mesh.faces(); ++f) {
    Eigen::Vector3d p[3];
    double x[3], y[3], inv_z[3];
    bool behind = false;
    for (int k = 0; k < 3; ++k) {
      p[k] = camera.cam_from_world() * mesh.positions[3 * f + k].cast<double>();
      behind = behind || p[k].z() < kNear;
      inv_z[k] = 1.0 / p[k].z();
      x[k] = fx * p[k].x() * inv_z[k] + cx;
      y[k] = fy * p[k].y() * inv_z[k] + cy;
    }
    if (behind) continue;
    const double area = (x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0]);
    if (std::abs(area) < 1e-12) continue;
    const int x_lo = std::max(0, static_cast<int>(std::ceil(std::min({x[0], x[1], x[2]}))));
    const int x_hi = std::min(w - 1, static_cast<int>(std::floor(std::max({x[0], x[1], x[2]}))));
    const int y_lo = std::max(0, static_cast<int>(std::ceil(std::min({y[0], y[1], y[2]}))));
    const int y_hi = std::min(h - 1, static_cast<int>(std::floor(std::max({y[0], y[1], y[2]}))));
    for (int py = y_lo; py <= y_hi; ++py) {
      for (int px = x_lo; px <= x_hi; ++px) {
        double b[3];
        for (int k = 0; k < 3; ++k) {
          const int i = (k + 1) % 3, j = (k + 2) % 3;
          b[k] = ((x[j] - x[i]) * (py - y[i]) - (y[j] - y[i]) * (px - x[i])) / area;
        }
        if (b[0] < 0 || b[1] < 0 || b[2] < 0) continue;
        // Perspective-correct weights: screen barycentrics over depth, renormalised.
        const double q0 = b[0] * inv_z[0], q1 = b[1] * inv_z[1], q2 = b[2] * inv_z[2];
        const double inv = q0 + q1 + q2;
        const float z = static_cast<float>(1.0 / inv);
        float& depth = view.depth.at<float>(py, px);
        if (z >= depth) continue;
        depth = z;
        const float w0 = static_cast<float>(q0 / inv), w1 = static_cast<float>(q1 / inv),
                    w2 = 1.0f - w0 - w1;
        cv::Vec3f color;
        if (textured) {
          const Eigen::Vector2f uv =
              w0 * mesh.uvs[3 * f] + w1 * mesh.uvs[3 * f + 1] + w2 * mesh.uvs[3 * f + 2];
          color = web::SampleAtlas(mesh.atlas, uv.x(), uv.y());
        } else if (!mesh.colors.empty()) {
          const Eigen::Vector3f rgb =
              (w0 * mesh.colors[3 * f].cast<float>() + w1 * mesh.colors[3 * f + 1].cast<float>() +
               w2 * mesh.colors[3 * f + 2].cast<float>()) /
              255.0f;
          color = cv::Vec3f(rgb.z(), rgb.y(), rgb.x());
        } else {
          color = cv::Vec3f(0.5f, 0.5f, 0.5f);
        }
        view.color.at<cv::Vec3f>(py, px) = color;
        view.alpha.at<float>(py, px) = 1.0f;
      }
    }
  }
  view.depth.setTo(std::numeric_limits<float>::quiet_NaN(),
                   view.depth == std::numeric_limits<float>::infinity());
  return view;
}

}  // namespace holocap
