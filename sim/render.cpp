#include "sim/render.h"

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>

#include "core/error.h"
#include "core/threads.h"

namespace holocap::sim {
namespace {

// A uniform number in [0, 1) from a hash of the pixel and sample, so the jitter of one pixel
// does not depend on how rows were split between threads.
double HashUniform(uint64_t seed, uint64_t a, uint64_t b) {
  return static_cast<double>(MixSeed(seed, a, b) >> 11) * (1.0 / 9007199254740992.0);
}

struct CameraRays {
  Eigen::Vector3d origin;
  Eigen::Matrix3d world_from_cam;
};

CameraRays WorldRays(const CameraModel& camera) {
  const Pose world_from_cam = camera.world_from_cam();
  return {world_from_cam.translation(), world_from_cam.linear()};
}

// Board key for anti-aliasing: which cell colour a board-front hit sees.
int SurfaceKey(const Snapshot& scene, const SurfaceHit& hit) {
  int key = hit.surface * 2;
  if (hit.surface == kBoardFront &&
      scene.board()->Reflectance(hit.board_uv.x(), hit.board_uv.y()) < 0.5) {
    key += 1;
  }
  return key;
}

}  // namespace

uint64_t MixSeed(uint64_t seed, uint64_t a, uint64_t b, uint64_t c) {
  uint64_t h = seed ^ 0x9E3779B97F4A7C15ull;
  for (uint64_t v : {a, b, c}) {
    h ^= v + 0x9E3779B97F4A7C15ull + (h << 6) + (h >> 2);
    h ^= h >> 30;
    h *= 0xBF58476D1CE4E5B9ull;
    h ^= h >> 27;
    h *= 0x94D049BB133111EBull;
    h ^= h >> 31;
  }
  return h;
}

RayTable::RayTable(const CameraModel& camera, int threads)
    : width_(camera.width()), height_(camera.height()), stride_(camera.width() + 2) {
  const int rows = height_ + 2;
  dirs_.resize(static_cast<size_t>(stride_) * rows);
  bool failed = false;
#pragma omp parallel for schedule(dynamic, 8) num_threads(ResolveThreads(threads))
  for (int row = 0; row < rows; ++row) {
    Eigen::Matrix2Xd pixels(2, stride_);
    for (int col = 0; col < stride_; ++col) pixels.col(col) << col - 1, row - 1;
    const Eigen::Matrix3Xd directions = camera.UnprojectMany(pixels);
    for (int col = 0; col < stride_; ++col) {
      if (!directions.col(col).allFinite()) {
#pragma omp atomic write
        failed = true;
      }
      dirs_[static_cast<size_t>(row) * stride_ + col] = directions.col(col).cast<float>();
    }
  }
  if (failed) {
    Fail("mrcal cannot unproject every pixel of the ", width_, "x", height_, " ",
         camera.lensmodel(), " imager: the lens is not invertible over its imager");
  }
}

Eigen::Vector3d RayTable::At(double x, double y) const {
  const double fx = std::clamp(x, -1.0, static_cast<double>(width_)) + 1;
  const double fy = std::clamp(y, -1.0, static_cast<double>(height_)) + 1;
  const int ix = std::min(static_cast<int>(fx), stride_ - 2);
  const int iy = std::min(static_cast<int>(fy), height_);
  const double ax = fx - ix, ay = fy - iy;
  const size_t base = static_cast<size_t>(iy) * stride_ + ix;
  const Eigen::Vector3d d00 = dirs_[base].cast<double>();
  const Eigen::Vector3d d10 = dirs_[base + 1].cast<double>();
  const Eigen::Vector3d d01 = dirs_[base + stride_].cast<double>();
  const Eigen::Vector3d d11 = dirs_[base + stride_ + 1].cast<double>();
  return ((1 - ay) * ((1 - ax) * d00 + ax * d10) + ay * ((1 - ax) * d01 + ax * d11)).normalized();
}

ColorRender RenderColor(const Snapshot& scene, const CameraModel& camera, const RayTable& rays,
                        int antialias, uint64_t seed, int threads) {
  const int width = camera.width(), height = camera.height();
  if (rays.width() != width || rays.height() != height) Fail("ray table does not fit the camera");
  const CameraRays cam = WorldRays(camera);
  ColorRender out;
  out.radiance.create(height, width, CV_32FC3);
  out.mask.create(height, width, CV_8U);
  std::vector<int> keys(static_cast<size_t>(width) * height);
  const int nthreads = ResolveThreads(threads);

  // Pass 1: one ray through every pixel centre.
#pragma omp parallel for schedule(dynamic, 4) num_threads(nthreads)
  for (int y = 0; y < height; ++y) {
    auto* radiance = out.radiance.ptr<cv::Vec3f>(y);
    auto* mask = out.mask.ptr<uint8_t>(y);
    for (int x = 0; x < width; ++x) {
      const SurfaceHit hit = scene.Trace(cam.origin, cam.world_from_cam * rays.Center(x, y));
      const Eigen::Vector3d value = scene.Radiance(hit);
      radiance[x] = cv::Vec3f(value.x(), value.y(), value.z());
      mask[x] = hit.is_subject() ? 255 : 0;
      keys[static_cast<size_t>(y) * width + x] = SurfaceKey(scene, hit);
    }
  }
  out.rays = static_cast<int64_t>(width) * height;
  if (antialias <= 1) return out;

  // Pass 2: pixels at surface or board-cell boundaries get their area integrated.
  std::vector<int> edges;
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x) {
      const int key = keys[static_cast<size_t>(y) * width + x];
      bool edge = false;
      for (int dy = -1; dy <= 1 && !edge; ++dy) {
        for (int dx = -1; dx <= 1 && !edge; ++dx) {
          const int nx = x + dx, ny = y + dy;
          if (nx < 0 || ny < 0 || nx >= width || ny >= height) continue;
          edge = keys[static_cast<size_t>(ny) * width + nx] != key;
        }
      }
      if (edge) edges.push_back(y * width + x);
    }
  }
  out.antialiased_pixels = static_cast<int64_t>(edges.size());
  const int n = antialias;
  int64_t extra_rays = 0;
#pragma omp parallel for schedule(dynamic, 64) num_threads(nthreads) reduction(+ : extra_rays)
  for (size_t e = 0; e < edges.size(); ++e) {
    const int x = edges[e] % width, y = edges[e] / width;
    // Wholly on the board: integrate the printed pattern exactly over the pixel's footprint.
    if (keys[edges[e]] / 2 == kBoardFront) {
      const double corners[4][2] = {{-0.5, -0.5}, {0.5, -0.5}, {0.5, 0.5}, {-0.5, 0.5}};
      std::vector<Eigen::Vector2d> footprint;
      SurfaceHit hit;
      for (const auto& c : corners) {
        hit = scene.Trace(cam.origin, cam.world_from_cam * rays.At(x + c[0], y + c[1]));
        if (hit.surface != kBoardFront) break;
        footprint.push_back(hit.board_uv);
      }
      extra_rays += static_cast<int64_t>(footprint.size()) + 1;
      if (footprint.size() == 4) {
        const SurfaceHit centre = scene.Trace(cam.origin, cam.world_from_cam * rays.Center(x, y));
        const double value = Snapshot::BoardAlbedo(scene.board()->MeanReflectance(footprint)) *
                             Snapshot::Irradiance(centre.normal);
        out.radiance.at<cv::Vec3f>(y, x) = cv::Vec3f(value, value, value);
        continue;
      }
    }
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    for (int sy = 0; sy < n; ++sy) {
      for (int sx = 0; sx < n; ++sx) {
        const uint64_t sample = static_cast<uint64_t>(sy) * n + sx;
        const double jx = (sx + HashUniform(seed, edges[e], 2 * sample)) / n - 0.5;
        const double jy = (sy + HashUniform(seed, edges[e], 2 * sample + 1)) / n - 0.5;
        const SurfaceHit hit =
            scene.Trace(cam.origin, cam.world_from_cam * rays.At(x + jx, y + jy));
        sum += scene.Radiance(hit);
      }
    }
    sum /= n * n;
    extra_rays += n * n;
    out.radiance.at<cv::Vec3f>(y, x) = cv::Vec3f(sum.x(), sum.y(), sum.z());
  }
  out.rays += extra_rays;
  return out;
}

DepthRender RenderDepth(const Snapshot& scene, const CameraModel& camera, const RayTable& rays,
                        int threads) {
  const int width = camera.width(), height = camera.height();
  if (rays.width() != width || rays.height() != height) Fail("ray table does not fit the camera");
  const CameraRays cam = WorldRays(camera);
  DepthRender out;
  out.z.create(height, width, CV_32F);
  out.cos_incidence.create(height, width, CV_32F);
  out.mask.create(height, width, CV_8U);
#pragma omp parallel for schedule(dynamic, 4) num_threads(ResolveThreads(threads))
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x) {
      const Eigen::Vector3d direction_in_cam = rays.Center(x, y);
      const Eigen::Vector3d direction = cam.world_from_cam * direction_in_cam;
      const SurfaceHit hit = scene.Trace(cam.origin, direction);
      out.z.at<float>(y, x) = static_cast<float>(hit.t * direction_in_cam.z());
      out.cos_incidence.at<float>(y, x) = static_cast<float>(std::abs(hit.normal.dot(direction)));
      out.mask.at<uint8_t>(y, x) = hit.is_subject() ? 255 : 0;
    }
  }
  return out;
}

cv::Mat MeasureDepth(const DepthRender& truth, const DepthSensorModel& model, uint64_t seed) {
  const int width = truth.z.cols, height = truth.z.rows;
  cv::Mat depth(height, width, CV_32F);
  const double min_cos = std::cos(model.max_incidence_deg * std::numbers::pi / 180);
  const float nan = std::numeric_limits<float>::quiet_NaN();
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> gauss(0, 1);
  std::uniform_real_distribution<double> unit(0, 1);
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x) {
      const double z = truth.z.at<float>(y, x);
      // Draw both numbers for every pixel so that one pixel's fate never shifts another's noise.
      const double noise = gauss(rng);
      const double drop = unit(rng);
      bool valid = std::isfinite(z) && z >= model.min_m && z <= model.max_m &&
                   truth.cos_incidence.at<float>(y, x) >= min_cos &&
                   drop >= model.dropout_probability;
      for (int k = 0; k < 4 && valid; ++k) {
        const int nx = x + (k == 0) - (k == 1), ny = y + (k == 2) - (k == 3);
        if (nx < 0 || ny < 0 || nx >= width || ny >= height) continue;
        valid = std::abs(truth.z.at<float>(ny, nx) - z) <= model.edge_threshold_m;
      }
      if (!valid) {
        depth.at<float>(y, x) = nan;
        continue;
      }
      const double measured = model.noise ? z + model.noise_k * z * z * noise : z;
      depth.at<float>(y, x) = static_cast<float>(std::round(measured * 1000) / 1000);
    }
  }
  return depth;
}

cv::Mat MeasureColor(const cv::Mat& radiance, const ColorSensorModel& model, uint64_t seed) {
  cv::Mat image(radiance.rows, radiance.cols, CV_8UC3);
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> gauss(0, 1);
  const double full_well = model.full_well_electrons;
  const double read2 = model.read_noise_electrons * model.read_noise_electrons;
  for (int y = 0; y < radiance.rows; ++y) {
    const auto* in = radiance.ptr<cv::Vec3f>(y);
    auto* out = image.ptr<cv::Vec3b>(y);
    for (int x = 0; x < radiance.cols; ++x) {
      for (int c = 0; c < 3; ++c) {
        double electrons =
            std::max(0.0, static_cast<double>(in[x][c])) * model.exposure_ratio * full_well;
        if (model.noise) electrons += std::sqrt(electrons + read2) * gauss(rng);
        electrons = std::clamp(electrons, 0.0, full_well);
        const double dn = 255.0 * electrons / full_well * model.gain;
        // BGR as OpenCV stores it, from RGB radiance.
        out[x][2 - c] = static_cast<uint8_t>(std::clamp(std::round(dn), 0.0, 255.0));
      }
    }
  }
  return image;
}

}  // namespace holocap::sim
