// The kernels of 3D Gaussian splatting (Kerbl et al. 2023) on the CPU: projection of anisotropic
// 3D Gaussians to 2D (EWA splatting through a pinhole camera), tile-based rasterisation with
// front-to-back alpha compositing, and the hand-written backward pass of both.
//
// The boundary is plain arrays in and out (structures of arrays, no OpenCV, no Eigen types), so
// that a GPU build can replace each kernel one for one and be compared against this one. Every
// kernel is a template on the scalar: float is what training and playback run, double is what
// the gradient checks of tests/splat run against finite differences.
//
// Colours are in the images' channel order (BGR in holocap), in [0, 1]. Pixel centres sit at
// integer coordinates (mrcal's and OpenCV's convention).
#pragma once

#include <cstdint>
#include <vector>

namespace holocap::splat {

constexpr int kTileSide = 16;
constexpr int kMaxShDegree = 3;
constexpr int ShCoefficients(int degree) { return (degree + 1) * (degree + 1); }

// The raw (unactivated) parameters Adam optimises, N Gaussians as a structure of arrays.
//   position    [N*3] world, metres
//   rotation    [N*4] quaternion w, x, y, z (normalised by the kernels)
//   log_scale   [N*3] scale = exp(log_scale) along the rotated axes, metres
//   opacity     [N]   logit: opacity = sigmoid(opacity)
//   sh          [N*K*3] spherical-harmonic colour, K = ShCoefficients(sh_degree), index
//               (n*K + k)*3 + channel; colour = max(0, sum_k sh_k Y_k(direction) + 0.5)
template <typename T>
struct GaussianArrays {
  int sh_degree = 0;  // the degree stored (coefficients per channel)
  std::vector<T> position, rotation, log_scale, opacity, sh;

  int64_t size() const { return static_cast<int64_t>(opacity.size()); }
  int coefficients() const { return ShCoefficients(sh_degree); }
  void Resize(int64_t count);  // new entries zero
  // Appends Gaussian `index` of `other` (same degree).
  void AppendFrom(const GaussianArrays& other, int64_t index);
};
using Gaussians = GaussianArrays<float>;

// A pinhole camera in the kernels' terms.
struct PinholeCamera {
  double fx = 1, fy = 1, cx = 0, cy = 0;
  int width = 0, height = 0;
  double cam_from_world_rotation[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};  // row-major
  double cam_from_world_translation[3] = {0, 0, 0};
  double near_m = 0.01;  // Gaussians nearer than this (z in the camera) are not drawn

  int tiles_x() const { return (width + kTileSide - 1) / kTileSide; }
  int tiles_y() const { return (height + kTileSide - 1) / kTileSide; }
  void CenterInWorld(double center[3]) const;
};

// Per Gaussian in one view. radius 0: not drawn (behind the near plane, degenerate 2D covariance
// or off the image).
template <typename T>
struct ProjectedArrays {
  std::vector<T> mean2d;   // [N*2] pixels
  std::vector<T> conic;    // [N*3] inverse 2D covariance (a, b, c): a dx^2 + 2 b dx dy + c dy^2
  std::vector<T> depth;    // [N] z in the camera, metres
  std::vector<T> color;    // [N*3] in [0, inf)
  std::vector<T> opacity;  // [N] in (0, 1)
  std::vector<T> extent;   // [N*2] half-width, half-height of the box outside which the splat's
                           // alpha stays below RasterOptions::min_alpha (pixels)
  std::vector<int32_t> radius;     // [N] the larger extent rounded up, 0: not drawn
  std::vector<uint8_t> clamped;    // [N*3] colour channel clamped at 0 (no gradient)
  int64_t culled_near = 0;         // behind or too near the camera
  int64_t culled_degenerate = 0;   // 2D covariance not positive definite
  int64_t culled_transparent = 0;  // opacity below min_alpha: never visible
};

// Gradients of a loss with respect to ProjectedArrays' differentiable fields.
template <typename T>
struct ProjectedGradients {
  std::vector<T> mean2d, conic, color, opacity;  // same layout as ProjectedArrays
  void Resize(int64_t count);                    // zeroed
};

// What the forward rasteriser keeps for the backward pass.
struct RasterState {
  std::vector<int32_t> tile_start, tile_end;  // [tiles] ranges into `entries`
  std::vector<int32_t> entries;               // Gaussian indices, per tile front to back
  std::vector<float> final_transmittance;     // [pixels]
  std::vector<int32_t> last_contributor;      // [pixels] one past the last entry composited
  // Scratch of the depth sort, kept so that a frame of the same size allocates nothing.
  std::vector<int32_t> depth_order, order_scratch, tile_rects;
  std::vector<uint32_t> depth_keys, key_scratch;
};

// Wall seconds the kernels spent in each stage of their own, added to (RasterOptions::times).
struct KernelTimes {
  double sort = 0;       // RasterizeForward: the drawn Gaussians ordered by depth
  double binning = 0;    // RasterizeForward: each Gaussian's tiles and the per-tile lists
  double forward = 0;    // RasterizeForward: the tiles composited
  double backward = 0;   // RasterizeBackward: the tiles' gradients per (tile, Gaussian) entry
  double reduction = 0;  // RasterizeBackward: the entries' gradients summed per Gaussian
};

struct RasterOptions {
  float min_transmittance = 1e-4f;      // a pixel stops compositing below this much light
  float min_alpha = 1.0f / 255.0f;      // smaller contributions are skipped (0: none; the box a
                                        // splat is drawn in then ends at alpha 1e-4)
  float max_alpha = 0.99f;              // a splat never blocks all light (keeps 1 / (1 - alpha))
  float low_pass_px2 = 0.3f;            // added to the 2D covariance: a splat covers a pixel
  int active_sh_degree = kMaxShDegree;  // degrees above this are not evaluated
  bool vectorized = true;  // float: pixels of a tile row in lanes with a polynomial exp (the
                           // picture within float rounding of the scalar loop); false, and
                           // always for double: the scalar loop, the reference it is tested on
  int lanes = 0;           // vectorized: 4 (SSE2), 8 (AVX2; 4 on CPUs without it), 0: the widest
                           // this CPU runs
  KernelTimes* times = nullptr;  // not nullptr: the rasteriser adds its stages' seconds here
};

// The real spherical-harmonic basis up to `degree` at a unit direction (x, y, z); out holds
// ShCoefficients(degree) values. S may be a dual number (the gradient with respect to the
// direction is taken by evaluating it on one).
template <typename S>
void ShBasis(int degree, const S& x, const S& y, const S& z, S* out);

// Projects every Gaussian through `camera`. The colour is evaluated for the direction from the
// camera's centre to the Gaussian, at min(options.active_sh_degree, gaussians.sh_degree).
template <typename T>
void ProjectGaussians(const GaussianArrays<T>& gaussians, const PinholeCamera& camera,
                      const RasterOptions& options, ProjectedArrays<T>* projected);

// Draws the projected Gaussians front to back into colour [H*W*3] over `background` [H*W*3]
// (nullptr: black), alpha [H*W] = 1 - transmittance (nullptr: not written), and depth [H*W] =
// the alpha-weighted mean depth (nullptr: not written). Tiles run in parallel (OpenMP, dynamic
// schedule). `state` keeps its buffers between calls (no allocation per frame once sized).
template <typename T>
void RasterizeForward(const ProjectedArrays<T>& projected, const PinholeCamera& camera,
                      const RasterOptions& options, const T* background, T* color, T* alpha,
                      T* depth, RasterState* state);

// The gradient of a loss with respect to the projected fields, given its gradient with respect
// to the drawn colour [H*W*3] and (optional, nullptr: none) alpha [H*W]. `gradients` is resized
// and overwritten. `mean2d_norm` (optional [N]) receives the pixel-space gradient's norm of each
// drawn Gaussian (densification's statistic).
template <typename T>
void RasterizeBackward(const ProjectedArrays<T>& projected, const PinholeCamera& camera,
                       const RasterOptions& options, const RasterState& state, const T* background,
                       const T* dloss_dcolor, const T* dloss_dalpha,
                       ProjectedGradients<T>* gradients);

// The gradient with respect to the raw parameters, accumulated (+=) into `gradients` (same
// layout as `gaussians`, sized by the caller).
template <typename T>
void ProjectBackward(const GaussianArrays<T>& gaussians, const PinholeCamera& camera,
                     const RasterOptions& options, const ProjectedArrays<T>& projected,
                     const ProjectedGradients<T>& projected_gradients,
                     GaussianArrays<T>* gradients);

// The training loss of 3DGS, (1 - lambda) L1 + lambda (1 - SSIM) (11x11 Gaussian window, sigma
// 1.5, zero padding), of image [H*W*3] against target [H*W*3]; writes its gradient with respect
// to image into dloss_dimage (nullptr: none). Means are over every pixel and channel.
template <typename T>
double PhotometricLoss(const T* image, const T* target, int width, int height, double lambda,
                       T* dloss_dimage);

}  // namespace holocap::splat
