// The differentiable volume ray marcher of Neural Volumes, in plain C++ (no LibTorch), so that
// training (through a custom autograd function) and playback share one implementation.
//
// A volume is an RGBA grid of D³ voxels over an axis-aligned box, channels last:
// value(c; x, y, z) at ((z * D + y) * D + x) * 4 + c, colour in [0, 1] and density in 1/m.
// Voxel centres sit at normalised box coordinates (i + 0.5) / D; samples between centres are
// trilinear and the grid is zero outside the box (an empty border).
//
// An optional warp field (W³ voxels, 3 channels, same layout) maps a sample's normalised box
// coordinate u to the template coordinate warp(u) in [0, 1]³ where the RGBA grid is sampled,
// as in the paper: value(x) = template(warp(u(x))). The warp is trilinear and clamped to the
// box at its border.
//
// Accumulation uses optical depth: T_k = exp(-sum_{j<k} sigma_j delta), the sample's weight
// w_k = T_k (1 - exp(-sigma_k delta)), colour = sum w_k c_k (premultiplied), alpha = 1 - T_end,
// depth = sum w_k t_k. Every term stays in [0, 1] for any density (1e6 included): an optical
// depth that overflows only drives T to 0, never to NaN. The backward pass is the exact
// gradient of these sums (recomputed ray by ray, nothing stored), scattered into the grids.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <vector>

#include "core/camera.h"

namespace holocap {

// Rays in world coordinates, clipped to the volume's box: samples lie in [t_near, t_far].
struct RayBatch {
  std::vector<float> origin;     // 3 per ray
  std::vector<float> direction;  // 3 per ray, unit length
  std::vector<float> t_near;     // metres along the ray; t_far <= t_near: misses the box
  std::vector<float> t_far;
  std::vector<float> jitter;  // in [0, 1): offset of the first sample, in steps
  int64_t size() const { return static_cast<int64_t>(t_near.size()); }
  void Resize(int64_t count);
};

// Cells of a coarse grid over the box that may hold density; empty cells are skipped.
struct OccupancyGrid {
  int size = 0;                   // cells per axis; 0 = no grid (nothing is skipped)
  std::vector<uint8_t> occupied;  // size³, x fastest
  bool empty() const { return size == 0; }
  int64_t OccupiedCount() const;
  // Marks every cell within `cells` of an occupied cell (conservative skipping).
  void Dilate(int cells);
};

struct MarchVolume {
  Eigen::Vector3f box_min = Eigen::Vector3f::Zero();
  Eigen::Vector3f box_max = Eigen::Vector3f::Ones();
  const float* rgba = nullptr;  // D³ x 4
  int grid = 0;                 // D
  const float* warp = nullptr;  // W³ x 3, or null: no warp (the template is the volume)
  int warp_grid = 0;            // W
  const OccupancyGrid* occupancy = nullptr;  // null or empty: no skipping
  // The RGBA grid is border-padded (clamped, as the warp is) instead of zero outside its voxel
  // centres: a baked grid, whose outermost half voxel continues the warped template.
  bool rgba_clamped = false;
};

struct MarchOptions {
  float step_m = 0.01f;                   // spacing of samples along a ray
  float min_transmittance = 0.0f;         // stop a ray once T falls below this (0: never)
  int64_t max_samples_per_ray = 1 << 20;  // guard against a step far too small for the box
  // Evaluate samples in empty cells too (they still add nothing): the cost of marching
  // without skipping, with the same image.
  bool evaluate_empty_cells = false;
};

struct MarchOutputs {
  std::vector<float> rgb;        // 3 per ray, premultiplied by alpha
  std::vector<float> alpha;      // 1 - transmittance at exit
  std::vector<float> depth;      // sum of w_k t_k (metres times alpha)
  std::vector<int32_t> samples;  // samples evaluated on the ray (skipped ones not counted)
  int64_t truncated_rays = 0;    // rays that hit max_samples_per_ray
  double MeanSamples() const;
};

// Rays through pixels of a camera (distortion included, via mrcal's unprojection), clipped to
// the box; t_near is at least `near_m` so that a camera inside the box starts at its centre.
// Pixels that cannot be unprojected get an empty ray. Jitter is left at 0.
RayBatch CameraRays(const CameraModel& camera, const Eigen::Matrix2Xd& pixels,
                    const Eigen::Vector3f& box_min, const Eigen::Vector3f& box_max,
                    float near_m = 0.0f);
// Every pixel of the camera, row-major.
RayBatch CameraRaysAllPixels(const CameraModel& camera, const Eigen::Vector3f& box_min,
                             const Eigen::Vector3f& box_max, float near_m = 0.0f);
// Slab intersection of one ray with the box; false when it misses.
bool ClipToBox(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction,
               const Eigen::Vector3f& box_min, const Eigen::Vector3f& box_max, float near_m,
               float* t_near, float* t_far);

void MarchForward(const MarchVolume& volume, const RayBatch& rays, const MarchOptions& options,
                  MarchOutputs* outputs);

// Gradients of sum(grad_rgb . rgb + grad_alpha . alpha) with respect to the RGBA grid and the
// warp field, added into grad_rgba (D³ x 4) and grad_warp (W³ x 3; may be null without a warp).
// The depth output carries no gradient.
void MarchBackward(const MarchVolume& volume, const RayBatch& rays, const MarchOptions& options,
                   const float* grad_rgb, const float* grad_alpha, float* grad_rgba,
                   float* grad_warp);

// Occupancy of a volume seen through its warp: a cell is occupied when the density at any of
// the grid's sample points inside it (D per axis, through the warp) exceeds `min_density`.
OccupancyGrid OccupancyFromVolume(const MarchVolume& volume, int cells, float min_density);

// ---------------------------------------------------------------------------------------------
// Playback (forward only, no gradient).

// A volume baked for playback: the template seen through the warp, resampled at the voxel
// centres of one world-space RGBA grid over the box (channels last, as MarchVolume::rgba), so
// that a sample costs one trilinear lookup instead of a warp lookup and a template lookup.
// Trilinear interpolation of the baked voxels differs from the warped template between voxel
// centres only (exactly equal at them); a volume without a warp baked at its own resolution is
// a plain copy.
struct BakedVolume {
  Eigen::Vector3f box_min = Eigen::Vector3f::Zero();
  Eigen::Vector3f box_max = Eigen::Vector3f::Ones();
  int grid = 0;
  std::vector<float> rgba;  // grid³ x 4
  bool clamped = false;     // resampled (border-padded); a copy keeps the template's zero border
  // The baked grid as a volume without a warp (it must outlive the view).
  MarchVolume View(const OccupancyGrid* occupancy = nullptr) const;
};
BakedVolume BakeVolume(const MarchVolume& volume, int grid);

// Forward marching for playback: the samples, weights and outputs of MarchForward (same sample
// lattice, same skipping, same counts; colour, alpha and depth agree to float rounding), but
// accumulated in float, with empty space left in strides of an 4x coarser occupancy level
// where a whole coarse cell is empty, and samples of a volume without a warp read as one
// 4-channel trilinear lookup. With evaluate_empty_cells every sample in an empty cell is read
// and composited with zero density (the cost of marching without skipping, the same image).
void MarchPlayback(const MarchVolume& volume, const RayBatch& rays, const MarchOptions& options,
                   MarchOutputs* outputs);

}  // namespace holocap
