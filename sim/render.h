// Ray casting of a Snapshot through a camera's true mrcal model, and the sensors' responses
// (colour noise and exposure, depth noise, quantisation and dropouts).
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <opencv2/core.hpp>
#include <random>
#include <vector>

#include "core/camera.h"
#include "sim/scene.h"

namespace holocap::sim {

// Unit viewing directions (camera frame) on the integer pixel lattice from -1 to width (and
// -1 to height), one border pixel beyond the imager so that every point of every pixel's area
// interpolates between four exact directions. Built with one mrcal unprojection per lattice
// point; between them, bilinear interpolation errs by ~1/(8 f) px (< 1e-3 px for f > 100 px).
class RayTable {
 public:
  RayTable() = default;
  // `threads` <= 0: all cores.
  explicit RayTable(const CameraModel& camera, int threads = 0);
  int width() const { return width_; }
  int height() const { return height_; }
  // Exact at integer pixels (pixel centres), bilinear in between; x in [-1, width].
  Eigen::Vector3d At(double x, double y) const;
  Eigen::Vector3d Center(int x, int y) const {
    return dirs_[static_cast<size_t>(y + 1) * stride_ + (x + 1)].cast<double>();
  }

 private:
  int width_ = 0, height_ = 0, stride_ = 0;
  std::vector<Eigen::Vector3f> dirs_;
};

struct ColorRender {
  cv::Mat radiance;  // CV_32FC3 linear RGB, the pixel-area average
  cv::Mat mask;      // CV_8U, 255 where the pixel centre sees the subject
  int64_t rays = 0;  // rays cast (centre, supersampling, board footprints)
  int64_t antialiased_pixels = 0;
};

// Renders colour. `antialias` N: pixels whose 8 neighbours see another surface or board cell
// get N x N jittered stratified samples, or, when wholly on the board, the exact footprint
// integral. `seed` fixes the jitter. Parallel over rows with `threads` (<= 0: all cores).
ColorRender RenderColor(const Snapshot& scene, const CameraModel& camera, const RayTable& rays,
                        int antialias, uint64_t seed, int threads = 0);

struct DepthRender {
  cv::Mat z;              // CV_32F true z-depth in metres (the camera-frame z of the hit)
  cv::Mat cos_incidence;  // CV_32F |cos| of the angle between the ray and the surface normal
  cv::Mat mask;           // CV_8U, 255 on the subject
};
// Centre-of-pixel depth (depth sensors do not average over their pixels).
DepthRender RenderDepth(const Snapshot& scene, const CameraModel& camera, const RayTable& rays,
                        int threads = 0);

struct DepthSensorModel {
  double noise_k = 0.0012;         // sigma(z) = noise_k * z^2 (1/m)
  double max_incidence_deg = 75;   // grazing surfaces give no measurement
  double edge_threshold_m = 0.05;  // pixels next to a larger depth jump give none
  double min_m = 0.3;
  double max_m = 6.0;
  double dropout_probability = 0;  // extra random holes
  bool noise = true;               // false: only quantisation and dropouts
};
// Metres in CV_32F, NaN = no measurement; values are whole millimetres (Z16).
cv::Mat MeasureDepth(const DepthRender& truth, const DepthSensorModel& model, uint64_t seed);

struct ColorSensorModel {
  bool noise = true;
  double full_well_electrons = 8000;
  double read_noise_electrons = 4;
  double exposure_ratio = 1;  // exposure / reference exposure
  double gain = 1;            // linear
};
// CV_8UC3 BGR from linear RGB radiance.
cv::Mat MeasureColor(const cv::Mat& radiance, const ColorSensorModel& model, uint64_t seed);

// A seed for one (sensor, frame, purpose) from the run's seed.
uint64_t MixSeed(uint64_t seed, uint64_t a, uint64_t b = 0, uint64_t c = 0);

}  // namespace holocap::sim
