#include "splat/kernels.h"

#include <omp.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <numeric>
#include <type_traits>

namespace holocap::splat {
namespace {

// Adds the seconds since the last lap (or the start) to *target, when there is a target.
class StageTimer {
 public:
  void Lap(double* target) {
    const auto now = std::chrono::steady_clock::now();
    if (target != nullptr) *target += std::chrono::duration<double>(now - last_).count();
    last_ = now;
  }

 private:
  std::chrono::steady_clock::time_point last_ = std::chrono::steady_clock::now();
};

// A number with its gradient with respect to three inputs: enough to differentiate the
// spherical-harmonic basis by the direction without writing 48 derivatives out by hand.
template <typename T>
struct Dual3 {
  T v = 0;
  std::array<T, 3> d = {0, 0, 0};
  Dual3() = default;
  Dual3(T value) : v(value) {}  // NOLINT: constants mix into expressions
  friend Dual3 operator+(const Dual3& a, const Dual3& b) {
    Dual3 r(a.v + b.v);
    for (int i = 0; i < 3; ++i) r.d[i] = a.d[i] + b.d[i];
    return r;
  }
  friend Dual3 operator-(const Dual3& a, const Dual3& b) {
    Dual3 r(a.v - b.v);
    for (int i = 0; i < 3; ++i) r.d[i] = a.d[i] - b.d[i];
    return r;
  }
  friend Dual3 operator-(const Dual3& a) { return Dual3(0) - a; }
  friend Dual3 operator*(const Dual3& a, const Dual3& b) {
    Dual3 r(a.v * b.v);
    for (int i = 0; i < 3; ++i) r.d[i] = a.d[i] * b.v + a.v * b.d[i];
    return r;
  }
};

template <typename T>
T Sigmoid(T x) {
  return T(1) / (T(1) + std::exp(-x));
}

// Rotation matrix (row-major) of a unit quaternion w, x, y, z.
template <typename T>
void QuaternionToMatrix(const T q[4], T r[9]) {
  const T w = q[0], x = q[1], y = q[2], z = q[3];
  r[0] = 1 - 2 * (y * y + z * z);
  r[1] = 2 * (x * y - w * z);
  r[2] = 2 * (x * z + w * y);
  r[3] = 2 * (x * y + w * z);
  r[4] = 1 - 2 * (x * x + z * z);
  r[5] = 2 * (y * z - w * x);
  r[6] = 2 * (x * z - w * y);
  r[7] = 2 * (y * z + w * x);
  r[8] = 1 - 2 * (x * x + y * y);
}

// The covariance's pieces every pass needs: the unit quaternion, its rotation, the scales and
// M = R S (Sigma = M M^T).
template <typename T>
struct Shape {
  T q[4], q_norm = 1, r[9], s[3], m[9];
};

template <typename T>
Shape<T> ShapeOf(const GaussianArrays<T>& g, int64_t i) {
  Shape<T> shape;
  const T* q = &g.rotation[4 * i];
  shape.q_norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  const T inv = shape.q_norm > T(0) ? T(1) / shape.q_norm : T(0);
  for (int k = 0; k < 4; ++k) shape.q[k] = q[k] * inv;
  if (!(shape.q_norm > T(0))) shape.q[0] = 1;
  QuaternionToMatrix(shape.q, shape.r);
  for (int k = 0; k < 3; ++k) shape.s[k] = std::exp(g.log_scale[3 * i + k]);
  for (int row = 0; row < 3; ++row) {
    for (int col = 0; col < 3; ++col)
      shape.m[3 * row + col] = shape.r[3 * row + col] * shape.s[col];
  }
  return shape;
}

// The camera-space pieces of one Gaussian: the point, the EWA Jacobian J (2x3, with the
// tangent clamped to 1.3 x the field of view as 3DGS does) and T = J W (2x3).
template <typename T>
struct Footprint {
  T p[3];
  T u_clamped, v_clamped;  // x/z and y/z after the clamp
  bool clamped_u, clamped_v;
  T j[6], t[6];
};

template <typename T>
Footprint<T> FootprintOf(const T* position, const PinholeCamera& camera) {
  Footprint<T> f;
  const double* w = camera.cam_from_world_rotation;
  for (size_t row = 0; row < 3; ++row) {
    f.p[row] = T(w[3 * row]) * position[0] + T(w[3 * row + 1]) * position[1] +
               T(w[3 * row + 2]) * position[2] + T(camera.cam_from_world_translation[row]);
  }
  const T z = f.p[2];
  const T limit_u = T(1.3 * 0.5 * camera.width / camera.fx);
  const T limit_v = T(1.3 * 0.5 * camera.height / camera.fy);
  const T u = f.p[0] / z, v = f.p[1] / z;
  f.clamped_u = u < -limit_u || u > limit_u;
  f.clamped_v = v < -limit_v || v > limit_v;
  f.u_clamped = std::clamp(u, -limit_u, limit_u);
  f.v_clamped = std::clamp(v, -limit_v, limit_v);
  const T fx = T(camera.fx), fy = T(camera.fy);
  f.j[0] = fx / z;
  f.j[1] = 0;
  f.j[2] = -fx * f.u_clamped / z;
  f.j[3] = 0;
  f.j[4] = fy / z;
  f.j[5] = -fy * f.v_clamped / z;
  for (int row = 0; row < 2; ++row) {
    for (int col = 0; col < 3; ++col) {
      f.t[3 * row + col] = f.j[3 * row] * T(w[col]) + f.j[3 * row + 1] * T(w[3 + col]) +
                           f.j[3 * row + 2] * T(w[6 + col]);
    }
  }
  return f;
}

// Sigma = M M^T (symmetric, row-major 3x3).
template <typename T>
void Covariance3(const Shape<T>& shape, T sigma[9]) {
  for (int a = 0; a < 3; ++a) {
    for (int b = 0; b < 3; ++b) {
      sigma[3 * a + b] = shape.m[3 * a] * shape.m[3 * b] + shape.m[3 * a + 1] * shape.m[3 * b + 1] +
                         shape.m[3 * a + 2] * shape.m[3 * b + 2];
    }
  }
}

// Sigma2 = T Sigma T^T + low_pass I, as (a, b, c).
template <typename T>
void Covariance2(const Footprint<T>& f, const T sigma[9], T low_pass, T cov[3]) {
  T ts[6];  // T Sigma (2x3)
  for (int row = 0; row < 2; ++row) {
    for (int col = 0; col < 3; ++col) {
      ts[3 * row + col] = f.t[3 * row] * sigma[col] + f.t[3 * row + 1] * sigma[3 + col] +
                          f.t[3 * row + 2] * sigma[6 + col];
    }
  }
  cov[0] = ts[0] * f.t[0] + ts[1] * f.t[1] + ts[2] * f.t[2] + low_pass;
  cov[1] = ts[0] * f.t[3] + ts[1] * f.t[4] + ts[2] * f.t[5];
  cov[2] = ts[3] * f.t[3] + ts[4] * f.t[4] + ts[5] * f.t[5] + low_pass;
}

// The unit direction from the camera's centre to a point, and the distance.
template <typename T>
T ViewDirection(const T* position, const double center[3], T direction[3]) {
  T v[3];
  for (int k = 0; k < 3; ++k) v[k] = position[k] - T(center[k]);
  const T length = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
  const T inv = length > T(0) ? T(1) / length : T(0);
  for (int k = 0; k < 3; ++k) direction[k] = v[k] * inv;
  return length;
}

}  // namespace

template <typename T>
void GaussianArrays<T>::Resize(int64_t count) {
  position.resize(3 * count, T(0));
  rotation.resize(4 * count, T(0));
  log_scale.resize(3 * count, T(0));
  opacity.resize(count, T(0));
  sh.resize(3 * coefficients() * count, T(0));
}

template <typename T>
void GaussianArrays<T>::AppendFrom(const GaussianArrays& other, int64_t i) {
  const int k = coefficients();
  position.insert(position.end(), &other.position[3 * i], &other.position[3 * i + 3]);
  rotation.insert(rotation.end(), &other.rotation[4 * i], &other.rotation[4 * i + 4]);
  log_scale.insert(log_scale.end(), &other.log_scale[3 * i], &other.log_scale[3 * i + 3]);
  opacity.push_back(other.opacity[i]);
  sh.insert(sh.end(), &other.sh[3 * static_cast<int64_t>(k) * i],
            &other.sh[3 * static_cast<int64_t>(k) * (i + 1)]);
}

void PinholeCamera::CenterInWorld(double center[3]) const {
  // center = -R^T t
  for (int k = 0; k < 3; ++k) {
    center[k] = -(cam_from_world_rotation[k] * cam_from_world_translation[0] +
                  cam_from_world_rotation[3 + k] * cam_from_world_translation[1] +
                  cam_from_world_rotation[6 + k] * cam_from_world_translation[2]);
  }
}

template <typename T>
void ProjectedGradients<T>::Resize(int64_t count) {
  mean2d.assign(2 * count, T(0));
  conic.assign(3 * count, T(0));
  color.assign(3 * count, T(0));
  opacity.assign(count, T(0));
}

template <typename S>
void ShBasis(int degree, const S& x, const S& y, const S& z, S* out) {
  out[0] = S(0.28209479177387814);
  if (degree < 1) return;
  out[1] = S(-0.4886025119029199) * y;
  out[2] = S(0.4886025119029199) * z;
  out[3] = S(-0.4886025119029199) * x;
  if (degree < 2) return;
  const S xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  out[4] = S(1.0925484305920792) * xy;
  out[5] = S(-1.0925484305920792) * yz;
  out[6] = S(0.31539156525252005) * (S(2.0) * zz - xx - yy);
  out[7] = S(-1.0925484305920792) * xz;
  out[8] = S(0.5462742152960396) * (xx - yy);
  if (degree < 3) return;
  out[9] = S(-0.5900435899266435) * y * (S(3.0) * xx - yy);
  out[10] = S(2.890611442640554) * xy * z;
  out[11] = S(-0.4570457994644658) * y * (S(4.0) * zz - xx - yy);
  out[12] = S(0.3731763325901154) * z * (S(2.0) * zz - S(3.0) * xx - S(3.0) * yy);
  out[13] = S(-0.4570457994644658) * x * (S(4.0) * zz - xx - yy);
  out[14] = S(1.445305721320277) * z * (xx - yy);
  out[15] = S(-0.5900435899266435) * x * (xx - S(3.0) * yy);
}

template <typename T>
void ProjectGaussians(const GaussianArrays<T>& g, const PinholeCamera& camera,
                      const RasterOptions& options, ProjectedArrays<T>* out) {
  const int64_t n = g.size();
  out->mean2d.assign(2 * n, T(0));
  out->conic.assign(3 * n, T(0));
  out->depth.assign(n, T(0));
  out->color.assign(3 * n, T(0));
  out->opacity.assign(n, T(0));
  out->extent.assign(2 * n, T(0));
  out->radius.assign(n, 0);
  out->clamped.assign(3 * n, 0);
  const T smallest_alpha = T(std::max(options.min_alpha, 1e-4f));
  double center[3];
  camera.CenterInWorld(center);
  const int degree = std::min(options.active_sh_degree, g.sh_degree);
  const int k_stored = g.coefficients(), k_used = ShCoefficients(degree);
  int64_t culled_near = 0, culled_degenerate = 0, culled_transparent = 0;
#pragma omp parallel for schedule(static) reduction(+ : culled_near, culled_degenerate, \
                                                    culled_transparent)
  for (int64_t i = 0; i < n; ++i) {
    const Footprint<T> f = FootprintOf(&g.position[3 * i], camera);
    if (!(f.p[2] > T(camera.near_m))) {
      ++culled_near;
      continue;
    }
    const Shape<T> shape = ShapeOf(g, i);
    T sigma[9], cov[3];
    Covariance3(shape, sigma);
    Covariance2(f, sigma, T(options.low_pass_px2), cov);
    const T det = cov[0] * cov[2] - cov[1] * cov[1];
    if (!(det > T(0)) || !std::isfinite(det)) {
      ++culled_degenerate;
      continue;
    }
    const T mean_u = T(camera.fx) * f.p[0] / f.p[2] + T(camera.cx);
    const T mean_v = T(camera.fy) * f.p[1] / f.p[2] + T(camera.cy);
    // The box where opacity x footprint reaches the smallest alpha drawn: the ellipse
    // d^T cov^-1 d = k^2 with k^2 = 2 log(opacity / min_alpha) has half-sides k sqrt(cov_xx),
    // k sqrt(cov_yy). Tighter than the paper's 3-sigma square for faint splats, and exact.
    const T o = Sigmoid(g.opacity[i]);
    const T k2 = T(2) * std::log(o / smallest_alpha);
    if (!(k2 > T(0))) {
      ++culled_transparent;
      continue;
    }
    const T k = std::sqrt(k2);
    const T extent_u = k * std::sqrt(cov[0]), extent_v = k * std::sqrt(cov[2]);
    if (!std::isfinite(mean_u) || !std::isfinite(mean_v) || mean_u + extent_u < T(-0.5) ||
        mean_v + extent_v < T(-0.5) || mean_u - extent_u > T(camera.width - 0.5) ||
        mean_v - extent_v > T(camera.height - 0.5)) {
      continue;
    }
    const T inv_det = T(1) / det;
    out->conic[3 * i] = cov[2] * inv_det;
    out->conic[3 * i + 1] = -cov[1] * inv_det;
    out->conic[3 * i + 2] = cov[0] * inv_det;
    out->mean2d[2 * i] = mean_u;
    out->mean2d[2 * i + 1] = mean_v;
    out->depth[i] = f.p[2];
    // Beyond the image's size a box covers it all: the cap keeps the tile arithmetic in
    // integers for Gaussians that grazed the near plane.
    const T cap = T(2 * (camera.width + camera.height));
    out->extent[2 * i] = std::min(extent_u, cap);
    out->extent[2 * i + 1] = std::min(extent_v, cap);
    out->radius[i] = std::max(
        1, static_cast<int32_t>(std::ceil(std::max(out->extent[2 * i], out->extent[2 * i + 1]))));
    out->opacity[i] = o;
    T direction[3], basis[ShCoefficients(kMaxShDegree)];
    ViewDirection(&g.position[3 * i], center, direction);
    ShBasis(degree, direction[0], direction[1], direction[2], basis);
    for (int c = 0; c < 3; ++c) {
      T value = T(0.5);
      for (int k = 0; k < k_used; ++k) value += basis[k] * g.sh[(i * k_stored + k) * 3 + c];
      out->clamped[3 * i + c] = value < T(0);
      out->color[3 * i + c] = std::max(value, T(0));
    }
  }
  out->culled_near = culled_near;
  out->culled_degenerate = culled_degenerate;
  out->culled_transparent = culled_transparent;
}

namespace {

// The tiles a drawn Gaussian's square of half-side `radius` touches, [x0, x1) x [y0, y1).
template <typename T>
bool TileRect(const ProjectedArrays<T>& p, int64_t i, const PinholeCamera& camera,
              int32_t rect[4]) {
  if (p.radius[i] <= 0) return false;
  const double u = static_cast<double>(p.mean2d[2 * i]),
               v = static_cast<double>(p.mean2d[2 * i + 1]);
  const double ru = static_cast<double>(p.extent[2 * i]),
               rv = static_cast<double>(p.extent[2 * i + 1]);
  // Clamped as doubles first: a point far off the image must not overflow the int.
  auto tile = [](double coordinate, int tiles) {
    return static_cast<int>(std::clamp(std::floor(coordinate / kTileSide), -1.0, double(tiles)));
  };
  rect[0] = std::max(0, tile(u - ru + 0.5, camera.tiles_x()));
  rect[1] = std::min(camera.tiles_x(), tile(u + ru + 0.5, camera.tiles_x()) + 1);
  rect[2] = std::max(0, tile(v - rv + 0.5, camera.tiles_y()));
  rect[3] = std::min(camera.tiles_y(), tile(v + rv + 0.5, camera.tiles_y()) + 1);
  return rect[1] > rect[0] && rect[3] > rect[2];
}

// A float's bits as an unsigned key that sorts as the float does (negative values flipped).
inline uint32_t SortKey(float value) {
  uint32_t bits;
  std::memcpy(&bits, &value, sizeof(bits));
  return (bits & 0x80000000u) != 0 ? ~bits : bits | 0x80000000u;
}

// Sorts `order` (ascending indices) by keys[order], stably: least-significant-digit radix sort
// in four passes of 8 bits, so equal depths keep index order (what a comparison sort on
// (depth, index) gives), in linear time.
void RadixSortByKey(std::vector<uint32_t>* keys, std::vector<int32_t>* order,
                    std::vector<uint32_t>* key_scratch, std::vector<int32_t>* order_scratch) {
  const size_t n = order->size();
  key_scratch->resize(n);
  order_scratch->resize(n);
  for (int shift = 0; shift < 32; shift += 8) {
    std::array<size_t, 257> offset{};
    for (size_t k = 0; k < n; ++k) ++offset[(((*keys)[k] >> shift) & 0xff) + 1];
    if (offset[((*keys)[0] >> shift & 0xff) + 1] == n) continue;  // one digit: nothing moves
    std::partial_sum(offset.begin(), offset.end(), offset.begin());
    for (size_t k = 0; k < n; ++k) {
      const size_t to = offset[((*keys)[k] >> shift) & 0xff]++;
      (*key_scratch)[to] = (*keys)[k];
      (*order_scratch)[to] = (*order)[k];
    }
    keys->swap(*key_scratch);
    order->swap(*order_scratch);
  }
}

// Per-tile lists, front to back: Gaussians sorted once by depth, then binned in that order, so
// each tile's list is already sorted.
template <typename T>
void BinTiles(const ProjectedArrays<T>& p, const PinholeCamera& camera, RasterState* state,
              KernelTimes* times) {
  StageTimer timer;
  const int64_t n = static_cast<int64_t>(p.radius.size());
  std::vector<int32_t>& order = state->depth_order;
  std::vector<uint32_t>& keys = state->depth_keys;
  order.clear();
  keys.clear();
  for (int64_t i = 0; i < n; ++i) {
    if (p.radius[i] <= 0) continue;
    order.push_back(static_cast<int32_t>(i));
    keys.push_back(SortKey(static_cast<float>(p.depth[i])));
  }
  if (!order.empty()) RadixSortByKey(&keys, &order, &state->key_scratch, &state->order_scratch);
  timer.Lap(times != nullptr ? &times->sort : nullptr);
  // Each Gaussian's tiles once, in parallel; the two passes below only read them.
  const int64_t drawn = static_cast<int64_t>(order.size());
  std::vector<int32_t>& rects = state->tile_rects;
  rects.resize(4 * drawn);
#pragma omp parallel for schedule(static)
  for (int64_t k = 0; k < drawn; ++k) {
    int32_t* rect = &rects[4 * k];
    if (!TileRect(p, order[k], camera, rect)) rect[0] = rect[1] = rect[2] = rect[3] = 0;
  }
  const int tiles = camera.tiles_x() * camera.tiles_y();
  std::vector<int32_t>& count = state->order_scratch;
  count.assign(tiles + 1, 0);
  for (int64_t k = 0; k < drawn; ++k) {
    const int32_t* rect = &rects[4 * k];
    for (int ty = rect[2]; ty < rect[3]; ++ty)
      for (int tx = rect[0]; tx < rect[1]; ++tx) ++count[ty * camera.tiles_x() + tx + 1];
  }
  std::partial_sum(count.begin(), count.end(), count.begin());
  state->tile_start.assign(count.begin(), count.end() - 1);
  state->tile_end.assign(count.begin(), count.end() - 1);
  state->entries.resize(count.back());
  for (int64_t k = 0; k < drawn; ++k) {
    const int32_t* rect = &rects[4 * k];
    for (int ty = rect[2]; ty < rect[3]; ++ty) {
      for (int tx = rect[0]; tx < rect[1]; ++tx)
        state->entries[state->tile_end[ty * camera.tiles_x() + tx]++] = order[k];
    }
  }
  timer.Lap(times != nullptr ? &times->binning : nullptr);
}

// The exponent of Gaussian i's footprint at (dx, dy) from its mean.
template <typename T>
inline T Power(const T* conic, T dx, T dy) {
  return T(-0.5) * (conic[0] * dx * dx + conic[2] * dy * dy) - conic[1] * dx * dy;
}

// The pixels of a tile (local coordinates, inclusive) inside Gaussian i's box; false if none.
template <typename T>
inline bool PixelRange(const ProjectedArrays<T>& p, int32_t i, int x0, int y0, int w, int h,
                       int range[4]) {
  auto local = [](double coordinate, int origin, int size) {
    return static_cast<int>(std::clamp(coordinate - origin, -1.0, static_cast<double>(size)));
  };
  const double mx = static_cast<double>(p.mean2d[2 * i]),
               my = static_cast<double>(p.mean2d[2 * i + 1]);
  const double ex = static_cast<double>(p.extent[2 * i]),
               ey = static_cast<double>(p.extent[2 * i + 1]);
  range[0] = std::max(0, local(std::ceil(mx - ex), x0, w));
  range[1] = std::min(w - 1, local(std::floor(mx + ex), x0, w));
  range[2] = std::max(0, local(std::ceil(my - ey), y0, h));
  range[3] = std::min(h - 1, local(std::floor(my + ey), y0, h));
  return range[1] >= range[0] && range[3] >= range[2];
}

// Below this exponent, opacity x exp(power) < min_alpha: the pixel is skipped without an exp.
template <typename T>
inline T PowerCutoff(T opacity, float min_alpha) {
  return min_alpha > 0 ? std::log(T(min_alpha) / opacity) : -std::numeric_limits<T>::infinity();
}

// Where RasterizeForward writes, shared by its tile loops.
template <typename T>
struct ForwardOutput {
  const PinholeCamera& camera;
  const T* background;
  T *color, *alpha, *depth;
  RasterState* state;

  // Stores one composited pixel (x, y) of the image.
  void Store(int x, int y, T transmittance, T red, T green, T blue, T z, int32_t last) const {
    const size_t pixel = static_cast<size_t>(y) * camera.width + x;
    const T composited[3] = {red, green, blue};
    for (int c = 0; c < 3; ++c) {
      color[3 * pixel + c] =
          composited[c] + transmittance * (background ? background[3 * pixel + c] : T(0));
    }
    if (alpha != nullptr) alpha[pixel] = T(1) - transmittance;
    if (depth != nullptr) {
      const T covered = T(1) - transmittance;
      depth[pixel] = covered > T(0) ? z / covered : T(0);
    }
    state->final_transmittance[pixel] = static_cast<float>(transmittance);
    state->last_contributor[pixel] = last;
  }
};

// One tile, one pixel at a time: the reference loop (and the one double runs).
template <typename T>
void ForwardTileScalar(const ProjectedArrays<T>& p, const RasterOptions& options, int tile,
                       const ForwardOutput<T>& out) {
  const PinholeCamera& camera = out.camera;
  const RasterState& state = *out.state;
  const int tiles_x = camera.tiles_x();
  const T min_alpha = T(options.min_alpha), max_alpha = T(options.max_alpha);
  const T min_transmittance = T(options.min_transmittance);
  const int x0 = (tile % tiles_x) * kTileSide, y0 = (tile / tiles_x) * kTileSide;
  const int w = std::min(kTileSide, camera.width - x0), h = std::min(kTileSide, camera.height - y0);
  constexpr int kPixels = kTileSide * kTileSide;
  T transmittance[kPixels], rgb[kPixels * 3], z[kPixels];
  int32_t last[kPixels];
  bool done[kPixels];
  for (int q = 0; q < kPixels; ++q) {
    transmittance[q] = 1;
    rgb[3 * q] = rgb[3 * q + 1] = rgb[3 * q + 2] = z[q] = 0;
    last[q] = 0;
    done[q] = (q % kTileSide) >= w || (q / kTileSide) >= h;
  }
  int remaining = w * h;
  const int32_t begin = state.tile_start[tile], end = state.tile_end[tile];
  for (int32_t e = begin; e < end && remaining > 0; ++e) {
    const int32_t i = state.entries[e];
    const T* conic = &p.conic[3 * i];
    const T mx = p.mean2d[2 * i], my = p.mean2d[2 * i + 1], o = p.opacity[i];
    const T cr = p.color[3 * i], cg = p.color[3 * i + 1], cb = p.color[3 * i + 2];
    const T depth_i = p.depth[i];
    int range[4];
    if (!PixelRange(p, i, x0, y0, w, h, range)) continue;
    const T cutoff = PowerCutoff(o, options.min_alpha);
    for (int ly = range[2]; ly <= range[3]; ++ly) {
      for (int q = ly * kTileSide + range[0]; q <= ly * kTileSide + range[1]; ++q) {
        if (done[q]) continue;
        const T dx = T(x0 + q % kTileSide) - mx, dy = T(y0 + ly) - my;
        const T power = Power(conic, dx, dy);
        if (power > T(0) || power < cutoff) continue;
        const T a = std::min(max_alpha, o * std::exp(power));
        if (a < min_alpha) continue;
        const T next = transmittance[q] * (T(1) - a);
        if (next < min_transmittance) {
          done[q] = true;
          --remaining;
          continue;
        }
        const T weight = a * transmittance[q];
        rgb[3 * q] += weight * cr;
        rgb[3 * q + 1] += weight * cg;
        rgb[3 * q + 2] += weight * cb;
        z[q] += weight * depth_i;
        transmittance[q] = next;
        last[q] = e - begin + 1;
      }
    }
  }
  for (int q = 0; q < kPixels; ++q) {
    if ((q % kTileSide) >= w || (q / kTileSide) >= h) continue;
    out.Store(x0 + q % kTileSide, y0 + q / kTileSide, transmittance[q], rgb[3 * q], rgb[3 * q + 1],
              rgb[3 * q + 2], z[q], last[q]);
  }
}

// Lanes of floats and the masks their comparisons give (all bits set: true), GCC vector
// extensions: four (SSE2, every x86-64) or eight (AVX2).
template <int kWidth>
struct LaneTypes;
template <>
struct LaneTypes<4> {
  using Lanes = float __attribute__((vector_size(16)));
  using Mask = int32_t __attribute__((vector_size(16)));
};
template <>
struct LaneTypes<8> {
  using Lanes = float __attribute__((vector_size(32)));
  using Mask = int32_t __attribute__((vector_size(32)));
};

template <typename Mask>
inline bool AnyLane(const Mask& mask) {
  uint64_t words[sizeof(Mask) / sizeof(uint64_t)];
  std::memcpy(words, &mask, sizeof(words));
  uint64_t any = 0;
  for (uint64_t word : words) any |= word;
  return any != 0;
}

template <typename Mask>
inline int CountLanes(const Mask& mask) {
  int count = 0;
  for (size_t k = 0; k < sizeof(Mask) / sizeof(int32_t); ++k) count += mask[k] != 0;
  return count;
}

// e^x for x <= 0 (clamped to [-87, 0]): x = n ln 2 + r with |r| <= ln 2 / 2 (ln 2 split in two
// so that n ln 2 is exact), e^r by its Taylor series to degree 7 (truncation below 6e-9
// relative, under float's rounding of 6e-8), 2^n written into the exponent bits. A few ulp
// from std::exp; no table, no branch, so it vectorises. Written through `out`, as vectors
// passed by value would change the ABI between the SSE2 and AVX2 builds.
template <typename Lanes, typename Mask>
inline void ExpNonPositive(const Lanes& power, Lanes* out) {
  Lanes x = power < -87.0f ? Lanes{} - 87.0f : power;
  x = x > 0.0f ? Lanes{} : x;
  const float kShifter = 12582912.0f;  // 1.5 x 2^23: adding it rounds to an integer
  const Lanes n = (x * 1.44269504088896341f + kShifter) - kShifter;
  const Lanes r = (x - n * 0.693359375f) - n * -2.12194440e-4f;
  Lanes e = r * (1.0f / 5040) + (1.0f / 720);
  e = e * r + (1.0f / 120);
  e = e * r + (1.0f / 24);
  e = e * r + (1.0f / 6);
  e = e * r + 0.5f;
  e = e * r + 1.0f;
  e = e * r + 1.0f;
  const Mask bits = (__builtin_convertvector(n, Mask) + 127) << 23;
  Lanes scale;
  std::memcpy(&scale, &bits, sizeof(scale));
  *out = e * scale;
}

// One tile, kWidth pixels of a row at once: the same decisions as ForwardTileScalar per pixel
// (a lane composites exactly when the scalar loop would), with ExpNonPositive for std::exp.
template <int kWidth>
__attribute__((always_inline)) inline void ForwardTileLanes(const ProjectedArrays<float>& p,
                                                            const RasterOptions& options, int tile,
                                                            const ForwardOutput<float>& out) {
  using Lanes = typename LaneTypes<kWidth>::Lanes;
  using Mask = typename LaneTypes<kWidth>::Mask;
  static_assert(kTileSide % kWidth == 0, "a tile row is whole lane groups");
  const PinholeCamera& camera = out.camera;
  const RasterState& state = *out.state;
  const int tiles_x = camera.tiles_x();
  const int x0 = (tile % tiles_x) * kTileSide, y0 = (tile / tiles_x) * kTileSide;
  const int w = std::min(kTileSide, camera.width - x0), h = std::min(kTileSide, camera.height - y0);
  constexpr int kGroupsPerRow = kTileSide / kWidth, kGroups = kTileSide * kGroupsPerRow;
  Lanes transmittance[kGroups], red[kGroups], green[kGroups], blue[kGroups], z[kGroups];
  Mask last[kGroups], live[kGroups];
  Mask lane_x;  // a lane's column within its group
  for (int k = 0; k < kWidth; ++k) lane_x[k] = k;
  for (int g = 0; g < kGroups; ++g) {
    transmittance[g] = Lanes{} + 1.0f;
    red[g] = green[g] = blue[g] = z[g] = Lanes{};
    last[g] = Mask{};
    live[g] = (lane_x + (g % kGroupsPerRow) * kWidth < w) & (Mask{} + g / kGroupsPerRow < h);
  }
  const float min_alpha = options.min_alpha, max_alpha = options.max_alpha;
  const float min_transmittance = options.min_transmittance;
  int remaining = w * h;
  const int32_t begin = state.tile_start[tile], end = state.tile_end[tile];
  for (int32_t e = begin; e < end && remaining > 0; ++e) {
    const int32_t i = state.entries[e];
    const size_t at = static_cast<size_t>(i);
    int range[4];
    if (!PixelRange(p, i, x0, y0, w, h, range)) continue;
    const float a = p.conic[3 * at], b = p.conic[3 * at + 1], c = p.conic[3 * at + 2];
    const float mx = p.mean2d[2 * at], my = p.mean2d[2 * at + 1], o = p.opacity[at];
    const float cr = p.color[3 * at], cg = p.color[3 * at + 1], cb = p.color[3 * at + 2];
    const float depth_i = p.depth[i], cutoff = PowerCutoff(o, options.min_alpha);
    const int first_group = range[0] / kWidth, last_group = range[1] / kWidth;
    Lanes dx[kGroupsPerRow];
    Mask in_range[kGroupsPerRow];
    for (int g = first_group; g <= last_group; ++g) {
      const Mask column = lane_x + g * kWidth;
      dx[g] = __builtin_convertvector(column + x0, Lanes) - mx;
      in_range[g] = (column >= range[0]) & (column <= range[1]);
    }
    const Mask entry = Mask{} + (e - begin + 1);
    for (int ly = range[2]; ly <= range[3]; ++ly) {
      const float dy = float(y0 + ly) - my, c_dy_dy = c * dy * dy;
      for (int g = first_group; g <= last_group; ++g) {
        const int k = ly * kGroupsPerRow + g;
        // Power() of the scalar loop, in its order of operations.
        const Lanes power = -0.5f * (a * dx[g] * dx[g] + c_dy_dy) - b * dx[g] * dy;
        Mask draw = live[k] & in_range[g] & (power <= 0.0f) & (power >= cutoff);
        if (!AnyLane(draw)) continue;
        Lanes alpha;
        ExpNonPositive<Lanes, Mask>(power, &alpha);
        alpha *= o;
        alpha = alpha < max_alpha ? alpha : Lanes{} + max_alpha;
        draw &= alpha >= min_alpha;
        const Lanes next = transmittance[k] * (1.0f - alpha);
        const Mask stop = draw & (next < min_transmittance);
        if (AnyLane(stop)) {
          live[k] &= ~stop;
          draw &= ~stop;
          remaining -= CountLanes(stop);
        }
        const Lanes weight = draw ? alpha * transmittance[k] : Lanes{};
        red[k] += weight * cr;
        green[k] += weight * cg;
        blue[k] += weight * cb;
        z[k] += weight * depth_i;
        transmittance[k] = draw ? next : transmittance[k];
        last[k] = draw ? entry : last[k];
      }
    }
  }
  for (int ly = 0; ly < h; ++ly) {
    for (int lx = 0; lx < w; ++lx) {
      const int k = ly * kGroupsPerRow + lx / kWidth, lane = lx % kWidth;
      out.Store(x0 + lx, y0 + ly, transmittance[k][lane], red[k][lane], green[k][lane],
                blue[k][lane], z[k][lane], last[k][lane]);
    }
  }
}

// Four lanes: SSE2, on every x86-64 (and any other target GCC vectorises).
void ForwardTileVector4(const ProjectedArrays<float>& p, const RasterOptions& options, int tile,
                        const ForwardOutput<float>& out) {
  ForwardTileLanes<4>(p, options, tile, out);
}

#if defined(__x86_64__) && defined(__GNUC__)
#define HOLOCAP_SPLAT_AVX2 1
// Eight lanes, for CPUs that have AVX2 (chosen at run time: the build assumes only x86-64). No
// FMA: the footprint's exponent is then rounded exactly as the scalar loop rounds it, which
// matters for needle-thin splats whose exponent is a difference of large terms.
__attribute__((target("avx2"))) void ForwardTileVector8(const ProjectedArrays<float>& p,
                                                        const RasterOptions& options, int tile,
                                                        const ForwardOutput<float>& out) {
  ForwardTileLanes<8>(p, options, tile, out);
}
#endif

// The vector tile loop of `lanes` (0: the widest) this CPU runs.
using ForwardTileFunction = void (*)(const ProjectedArrays<float>&, const RasterOptions&, int,
                                     const ForwardOutput<float>&);
ForwardTileFunction VectorForwardTile(int lanes) {
#ifdef HOLOCAP_SPLAT_AVX2
  static const bool avx2 = [] {
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx2") != 0;
  }();
  if (avx2 && lanes != 4) return ForwardTileVector8;
#endif
  return ForwardTileVector4;
}

}  // namespace

template <typename T>
void RasterizeForward(const ProjectedArrays<T>& p, const PinholeCamera& camera,
                      const RasterOptions& options, const T* background, T* color, T* alpha,
                      T* depth, RasterState* state) {
  BinTiles(p, camera, state, options.times);
  StageTimer timer;
  const size_t pixels = static_cast<size_t>(camera.width) * camera.height;
  state->final_transmittance.resize(pixels);
  state->last_contributor.resize(pixels);
  const ForwardOutput<T> out{camera, background, color, alpha, depth, state};
  const int tiles = camera.tiles_x() * camera.tiles_y();
  ForwardTileFunction vector_tile = nullptr;
  if constexpr (std::is_same_v<T, float>) {
    if (options.vectorized) vector_tile = VectorForwardTile(options.lanes);
  }
  // Chunks of a few tiles: fewer trips to the shared counter, still balanced (tiles differ
  // tenfold in work between the figure and the empty background).
#pragma omp parallel for schedule(dynamic, 4)
  for (int tile = 0; tile < tiles; ++tile) {
    if constexpr (std::is_same_v<T, float>) {
      if (vector_tile != nullptr) {
        vector_tile(p, options, tile, out);
        continue;
      }
    }
    ForwardTileScalar(p, options, tile, out);
  }
  timer.Lap(options.times != nullptr ? &options.times->forward : nullptr);
}

namespace {

// Values of one (tile, Gaussian) entry's gradient: mean2d (2), conic (3), colour (3), opacity.
constexpr int kEntryGradient = 9;

// Gradients of one tile's pixels with respect to its Gaussians, back to front, each entry's
// into its own kEntryGradient values of `entry_gradient` (indexed as state.entries): no two
// tiles write the same values, so the sum over tiles can be taken in a fixed order.
template <typename T>
void BackwardTile(const ProjectedArrays<T>& p, const PinholeCamera& camera,
                  const RasterOptions& options, const RasterState& state, int tile,
                  const T* background, const T* dloss_dcolor, const T* dloss_dalpha,
                  T* entry_gradient) {
  const int tiles_x = camera.tiles_x();
  const int x0 = (tile % tiles_x) * kTileSide, y0 = (tile / tiles_x) * kTileSide;
  const int w = std::min(kTileSide, camera.width - x0), h = std::min(kTileSide, camera.height - y0);
  constexpr int kPixels = kTileSide * kTileSide;
  T transmittance[kPixels], behind[kPixels * 3], g_color[kPixels * 3], g_alpha[kPixels],
      final_t[kPixels];
  int32_t last[kPixels];
  int32_t max_last = 0;
  for (int q = 0; q < kPixels; ++q) {
    last[q] = 0;
    if ((q % kTileSide) >= w || (q / kTileSide) >= h) continue;
    const size_t pixel =
        static_cast<size_t>(y0 + q / kTileSide) * camera.width + x0 + q % kTileSide;
    transmittance[q] = final_t[q] = T(state.final_transmittance[pixel]);
    for (int c = 0; c < 3; ++c) {
      g_color[3 * q + c] = dloss_dcolor[3 * pixel + c];
      behind[3 * q + c] = background ? final_t[q] * background[3 * pixel + c] : T(0);
    }
    g_alpha[q] = dloss_dalpha ? dloss_dalpha[pixel] : T(0);
    last[q] = state.last_contributor[pixel];
    max_last = std::max(max_last, last[q]);
  }
  const int32_t begin = state.tile_start[tile];
  const T min_alpha = T(options.min_alpha), max_alpha = T(options.max_alpha);
  // Every entry's slot is written: those no pixel reached hold zeros.
  T* const slots = entry_gradient + kEntryGradient * static_cast<size_t>(begin);
  std::fill(slots + kEntryGradient * static_cast<size_t>(max_last),
            slots + kEntryGradient * static_cast<size_t>(state.tile_end[tile] - begin), T(0));
  for (int32_t local = max_last - 1; local >= 0; --local) {
    const int32_t i = state.entries[begin + local];
    const T* conic = &p.conic[3 * i];
    const T mx = p.mean2d[2 * i], my = p.mean2d[2 * i + 1], o = p.opacity[i];
    const T col[3] = {p.color[3 * i], p.color[3 * i + 1], p.color[3 * i + 2]};
    T d_mean[2] = {0, 0}, d_conic[3] = {0, 0, 0}, d_col[3] = {0, 0, 0}, d_opacity = 0;
    int range[4];
    T* out = slots + kEntryGradient * static_cast<size_t>(local);
    if (!PixelRange(p, i, x0, y0, w, h, range)) {
      std::fill(out, out + kEntryGradient, T(0));
      continue;
    }
    const T cutoff = PowerCutoff(o, options.min_alpha);
    for (int ly = range[2]; ly <= range[3]; ++ly) {
      for (int q = ly * kTileSide + range[0]; q <= ly * kTileSide + range[1]; ++q) {
        if (local >= last[q]) continue;
        const T dx = T(x0 + q % kTileSide) - mx, dy = T(y0 + ly) - my;
        const T power = Power(conic, dx, dy);
        if (power > T(0) || power < cutoff) continue;
        const T gauss = std::exp(power);
        const T raw = o * gauss;
        const T a = std::min(max_alpha, raw);
        if (a < min_alpha) continue;
        const T one_minus = T(1) - a;
        transmittance[q] /= one_minus;
        const T weight = a * transmittance[q];
        T d_a = 0;
        for (int c = 0; c < 3; ++c) {
          d_col[c] += weight * g_color[3 * q + c];
          d_a += g_color[3 * q + c] * (transmittance[q] * col[c] - behind[3 * q + c] / one_minus);
          behind[3 * q + c] += weight * col[c];
        }
        d_a += g_alpha[q] * final_t[q] / one_minus;
        if (raw > max_alpha) continue;  // clamped: no gradient through the footprint
        d_opacity += d_a * gauss;
        const T d_power = d_a * raw;
        d_mean[0] += d_power * (conic[0] * dx + conic[1] * dy);
        d_mean[1] += d_power * (conic[2] * dy + conic[1] * dx);
        d_conic[0] += d_power * T(-0.5) * dx * dx;
        d_conic[1] += d_power * -(dx * dy);
        d_conic[2] += d_power * T(-0.5) * dy * dy;
      }
    }
    out[0] = d_mean[0];
    out[1] = d_mean[1];
    for (int c = 0; c < 3; ++c) {
      out[2 + c] = d_conic[c];
      out[5 + c] = d_col[c];
    }
    out[8] = d_opacity;
  }
}

// The sum of a vector's lanes, lane 0 first (a fixed order: the same bytes on every run).
template <typename Lanes>
inline float SumLanes(const Lanes& lanes) {
  float sum = 0;
  for (size_t k = 0; k < sizeof(Lanes) / sizeof(float); ++k) sum += lanes[k];
  return sum;
}

// BackwardTile with kWidth pixels of a row at once: the same pixels and entries as the scalar
// loop (ForwardTileLanes' footprint and ExpNonPositive, so that the alphas are the forward's
// own), each entry's gradient summed over its lanes at the end. Within float rounding of the
// scalar loop (1 / (1 - alpha) is multiplied, not divided; the sums run in another order).
template <int kWidth>
__attribute__((always_inline)) inline void BackwardTileLanes(
    const ProjectedArrays<float>& p, const PinholeCamera& camera, const RasterOptions& options,
    const RasterState& state, int tile, const float* background, const float* dloss_dcolor,
    const float* dloss_dalpha, float* entry_gradient) {
  using Lanes = typename LaneTypes<kWidth>::Lanes;
  using Mask = typename LaneTypes<kWidth>::Mask;
  static_assert(kTileSide % kWidth == 0, "a tile row is whole lane groups");
  const int tiles_x = camera.tiles_x();
  const int x0 = (tile % tiles_x) * kTileSide, y0 = (tile / tiles_x) * kTileSide;
  const int w = std::min(kTileSide, camera.width - x0), h = std::min(kTileSide, camera.height - y0);
  constexpr int kGroupsPerRow = kTileSide / kWidth, kGroups = kTileSide * kGroupsPerRow;
  Lanes transmittance[kGroups], behind_r[kGroups], behind_g[kGroups], behind_b[kGroups],
      grad_r[kGroups], grad_g[kGroups], grad_b[kGroups], grad_alpha[kGroups];
  Mask last[kGroups];
  int32_t max_last = 0;
  for (int k = 0; k < kGroups; ++k) {
    transmittance[k] = Lanes{} + 1.0f;
    behind_r[k] = behind_g[k] = behind_b[k] = grad_r[k] = grad_g[k] = grad_b[k] = grad_alpha[k] =
        Lanes{};
    last[k] = Mask{};
  }
  for (int ly = 0; ly < h; ++ly) {
    for (int lx = 0; lx < w; ++lx) {
      const int k = ly * kGroupsPerRow + lx / kWidth, lane = lx % kWidth;
      const size_t pixel = static_cast<size_t>(y0 + ly) * camera.width + x0 + lx;
      const float final_t = state.final_transmittance[pixel];
      transmittance[k][lane] = final_t;
      grad_r[k][lane] = dloss_dcolor[3 * pixel];
      grad_g[k][lane] = dloss_dcolor[3 * pixel + 1];
      grad_b[k][lane] = dloss_dcolor[3 * pixel + 2];
      if (background != nullptr) {
        behind_r[k][lane] = final_t * background[3 * pixel];
        behind_g[k][lane] = final_t * background[3 * pixel + 1];
        behind_b[k][lane] = final_t * background[3 * pixel + 2];
      }
      grad_alpha[k][lane] = dloss_dalpha != nullptr ? dloss_dalpha[pixel] * final_t : 0.0f;
      last[k][lane] = state.last_contributor[pixel];
      max_last = std::max(max_last, state.last_contributor[pixel]);
    }
  }
  const int32_t begin = state.tile_start[tile];
  const float min_alpha = options.min_alpha, max_alpha = options.max_alpha;
  float* const slots = entry_gradient + kEntryGradient * static_cast<size_t>(begin);
  std::fill(slots + kEntryGradient * static_cast<size_t>(max_last),
            slots + kEntryGradient * static_cast<size_t>(state.tile_end[tile] - begin), 0.0f);
  Mask lane_x;
  for (int k = 0; k < kWidth; ++k) lane_x[k] = k;
  for (int32_t local = max_last - 1; local >= 0; --local) {
    const int32_t i = state.entries[begin + local];
    const size_t at = static_cast<size_t>(i);
    float* out = slots + kEntryGradient * static_cast<size_t>(local);
    int range[4];
    if (!PixelRange(p, i, x0, y0, w, h, range)) {
      std::fill(out, out + kEntryGradient, 0.0f);
      continue;
    }
    const float a = p.conic[3 * at], b = p.conic[3 * at + 1], c = p.conic[3 * at + 2];
    const float mx = p.mean2d[2 * at], my = p.mean2d[2 * at + 1], o = p.opacity[at];
    const float cr = p.color[3 * at], cg = p.color[3 * at + 1], cb = p.color[3 * at + 2];
    const float cutoff = PowerCutoff(o, options.min_alpha);
    const int first_group = range[0] / kWidth, last_group = range[1] / kWidth;
    Lanes dx[kGroupsPerRow];
    Mask in_range[kGroupsPerRow];
    for (int g = first_group; g <= last_group; ++g) {
      const Mask column = lane_x + g * kWidth;
      dx[g] = __builtin_convertvector(column + x0, Lanes) - mx;
      in_range[g] = (column >= range[0]) & (column <= range[1]);
    }
    const Mask entry = Mask{} + local;
    Lanes d_mx{}, d_my{}, d_a_conic{}, d_b_conic{}, d_c_conic{}, d_r{}, d_g{}, d_b{}, d_o{};
    for (int ly = range[2]; ly <= range[3]; ++ly) {
      const float dy = float(y0 + ly) - my, c_dy_dy = c * dy * dy;
      for (int g = first_group; g <= last_group; ++g) {
        const int k = ly * kGroupsPerRow + g;
        const Lanes power = -0.5f * (a * dx[g] * dx[g] + c_dy_dy) - b * dx[g] * dy;
        Mask draw = in_range[g] & (entry < last[k]) & (power <= 0.0f) & (power >= cutoff);
        if (!AnyLane(draw)) continue;
        Lanes gauss;
        ExpNonPositive<Lanes, Mask>(power, &gauss);
        const Lanes raw = o * gauss;
        const Lanes alpha = raw < max_alpha ? raw : Lanes{} + max_alpha;
        draw &= alpha >= min_alpha;
        if (!AnyLane(draw)) continue;
        const Lanes inverse = 1.0f / (1.0f - alpha);
        const Lanes t = draw ? transmittance[k] * inverse : transmittance[k];
        transmittance[k] = t;
        const Lanes weight = draw ? alpha * t : Lanes{};
        d_r += weight * grad_r[k];
        d_g += weight * grad_g[k];
        d_b += weight * grad_b[k];
        Lanes d_alpha = grad_r[k] * (t * cr - behind_r[k] * inverse) +
                        grad_g[k] * (t * cg - behind_g[k] * inverse) +
                        grad_b[k] * (t * cb - behind_b[k] * inverse) + grad_alpha[k] * inverse;
        behind_r[k] += weight * cr;
        behind_g[k] += weight * cg;
        behind_b[k] += weight * cb;
        // Clamped at max_alpha: no gradient through the footprint.
        d_alpha = draw & (raw <= max_alpha) ? d_alpha : Lanes{};
        d_o += d_alpha * gauss;
        const Lanes d_power = d_alpha * raw;
        d_mx += d_power * (a * dx[g] + b * dy);
        d_my += d_power * (c * dy + b * dx[g]);
        d_a_conic += d_power * -0.5f * dx[g] * dx[g];
        d_b_conic += d_power * -(dx[g] * dy);
        d_c_conic += d_power * (-0.5f * dy * dy);
      }
    }
    out[0] = SumLanes(d_mx);
    out[1] = SumLanes(d_my);
    out[2] = SumLanes(d_a_conic);
    out[3] = SumLanes(d_b_conic);
    out[4] = SumLanes(d_c_conic);
    out[5] = SumLanes(d_r);
    out[6] = SumLanes(d_g);
    out[7] = SumLanes(d_b);
    out[8] = SumLanes(d_o);
  }
}

using BackwardTileFunction = void (*)(const ProjectedArrays<float>&, const PinholeCamera&,
                                      const RasterOptions&, const RasterState&, int, const float*,
                                      const float*, const float*, float*);

void BackwardTileVector4(const ProjectedArrays<float>& p, const PinholeCamera& camera,
                         const RasterOptions& options, const RasterState& state, int tile,
                         const float* background, const float* dloss_dcolor,
                         const float* dloss_dalpha, float* entry_gradient) {
  BackwardTileLanes<4>(p, camera, options, state, tile, background, dloss_dcolor, dloss_dalpha,
                       entry_gradient);
}

#ifdef HOLOCAP_SPLAT_AVX2
__attribute__((target("avx2"))) void BackwardTileVector8(
    const ProjectedArrays<float>& p, const PinholeCamera& camera, const RasterOptions& options,
    const RasterState& state, int tile, const float* background, const float* dloss_dcolor,
    const float* dloss_dalpha, float* entry_gradient) {
  BackwardTileLanes<8>(p, camera, options, state, tile, background, dloss_dcolor, dloss_dalpha,
                       entry_gradient);
}
#endif

// The vector backward tile loop of `lanes` (0: the widest) this CPU runs.
BackwardTileFunction VectorBackwardTile(int lanes) {
#ifdef HOLOCAP_SPLAT_AVX2
  if (VectorForwardTile(lanes) == ForwardTileVector8) return BackwardTileVector8;
#endif
  return BackwardTileVector4;
}

}  // namespace

template <typename T>
void RasterizeBackward(const ProjectedArrays<T>& p, const PinholeCamera& camera,
                       const RasterOptions& options, const RasterState& state, const T* background,
                       const T* dloss_dcolor, const T* dloss_dalpha,
                       ProjectedGradients<T>* gradients) {
  const int64_t n = static_cast<int64_t>(p.radius.size());
  const int tiles = camera.tiles_x() * camera.tiles_y();
  // Each (tile, Gaussian) entry's gradient in its own slot, then summed per Gaussian in tile
  // order: the same bytes whatever the threads and however the tiles were shared out among
  // them (per-thread sums would add in the order the tiles happened to run).
  // Reused between calls by the calling thread (each tile writes all of its slots): a view
  // allocates nothing. The workers write through `slots`, never through their own copy.
  StageTimer timer;
  static thread_local std::vector<T> entry_gradient;
  entry_gradient.resize(kEntryGradient * state.entries.size());
  T* const slots = entry_gradient.data();
  BackwardTileFunction vector_tile = nullptr;
  if constexpr (std::is_same_v<T, float>) {
    if (options.vectorized) vector_tile = VectorBackwardTile(options.lanes);
  }
#pragma omp parallel for schedule(dynamic, 1)
  for (int tile = 0; tile < tiles; ++tile) {
    if constexpr (std::is_same_v<T, float>) {
      if (vector_tile != nullptr) {
        vector_tile(p, camera, options, state, tile, background, dloss_dcolor, dloss_dalpha, slots);
        continue;
      }
    }
    BackwardTile(p, camera, options, state, tile, background, dloss_dcolor, dloss_dalpha, slots);
  }
  timer.Lap(options.times != nullptr ? &options.times->backward : nullptr);
  gradients->Resize(n);
  for (int tile = 0; tile < tiles; ++tile) {
    for (int32_t e = state.tile_start[tile]; e < state.tile_end[tile]; ++e) {
      const int32_t i = state.entries[e];
      const T* g = slots + kEntryGradient * static_cast<size_t>(e);
      gradients->mean2d[2 * i] += g[0];
      gradients->mean2d[2 * i + 1] += g[1];
      for (int c = 0; c < 3; ++c) {
        gradients->conic[3 * i + c] += g[2 + c];
        gradients->color[3 * i + c] += g[5 + c];
      }
      gradients->opacity[i] += g[8];
    }
  }
  timer.Lap(options.times != nullptr ? &options.times->reduction : nullptr);
}

namespace {

// d loss / d (raw parameters) of Gaussian i, from the projected gradients (accumulated).
template <typename T>
void ProjectBackwardOne(const GaussianArrays<T>& g, const PinholeCamera& camera,
                        const RasterOptions& options, const ProjectedArrays<T>& p,
                        const ProjectedGradients<T>& pg, const double center[3], int64_t i,
                        GaussianArrays<T>* out) {
  const Footprint<T> f = FootprintOf(&g.position[3 * i], camera);
  const Shape<T> shape = ShapeOf(g, i);
  T sigma[9], cov[3];
  Covariance3(shape, sigma);
  Covariance2(f, sigma, T(options.low_pass_px2), cov);
  const T fx = T(camera.fx), fy = T(camera.fy), z = f.p[2];
  T d_p[3] = {0, 0, 0};  // d loss / d point in camera

  // mean2d = (fx x/z + cx, fy y/z + cy).
  const T gu = pg.mean2d[2 * i], gv = pg.mean2d[2 * i + 1];
  d_p[0] += gu * fx / z;
  d_p[1] += gv * fy / z;
  d_p[2] += -(gu * fx * f.p[0] + gv * fy * f.p[1]) / (z * z);

  // conic = inverse(Sigma2): dL/dSigma2 = -C G C, G the gradient as a symmetric matrix.
  const T* conic = &p.conic[3 * i];
  const T ga = pg.conic[3 * i], gb = T(0.5) * pg.conic[3 * i + 1], gc = pg.conic[3 * i + 2];
  const T c00 = conic[0], c01 = conic[1], c11 = conic[2];
  // H = -C G C (2x2 symmetric).
  const T cg00 = c00 * ga + c01 * gb, cg01 = c00 * gb + c01 * gc;
  const T cg10 = c01 * ga + c11 * gb, cg11 = c01 * gb + c11 * gc;
  const T h00 = -(cg00 * c00 + cg01 * c01), h01 = -(cg00 * c01 + cg01 * c11);
  const T h11 = -(cg10 * c01 + cg11 * c11);
  const T hm[4] = {h00, h01, h01, h11};

  // Sigma2 = T Sigma T^T: dL/dSigma = T^T H T, dL/dT = 2 H T Sigma.
  T ht[6];  // H T (2x3)
  for (int row = 0; row < 2; ++row)
    for (int col = 0; col < 3; ++col)
      ht[3 * row + col] = hm[2 * row] * f.t[col] + hm[2 * row + 1] * f.t[3 + col];
  T d_sigma[9];
  for (int a = 0; a < 3; ++a)
    for (int b = 0; b < 3; ++b) d_sigma[3 * a + b] = f.t[a] * ht[b] + f.t[3 + a] * ht[3 + b];
  T d_t[6];
  for (int row = 0; row < 2; ++row) {
    for (int col = 0; col < 3; ++col) {
      d_t[3 * row + col] = 2 * (ht[3 * row] * sigma[col] + ht[3 * row + 1] * sigma[3 + col] +
                                ht[3 * row + 2] * sigma[6 + col]);
    }
  }
  // T = J W: dL/dJ = dL/dT W^T.
  const double* w = camera.cam_from_world_rotation;
  T d_j[6];
  for (size_t row = 0; row < 2; ++row) {
    for (size_t col = 0; col < 3; ++col) {
      d_j[3 * row + col] = d_t[3 * row] * T(w[3 * col]) + d_t[3 * row + 1] * T(w[3 * col + 1]) +
                           d_t[3 * row + 2] * T(w[3 * col + 2]);
    }
  }
  // J00 = fx/z, J02 = -fx u/z (u = x/z unless clamped), J11 = fy/z, J12 = -fy v/z.
  d_p[2] += -d_j[0] * fx / (z * z) - d_j[4] * fy / (z * z);
  if (f.clamped_u) {
    d_p[2] += d_j[2] * fx * f.u_clamped / (z * z);
  } else {
    d_p[0] += -d_j[2] * fx / (z * z);
    d_p[2] += d_j[2] * 2 * fx * f.p[0] / (z * z * z);
  }
  if (f.clamped_v) {
    d_p[2] += d_j[5] * fy * f.v_clamped / (z * z);
  } else {
    d_p[1] += -d_j[5] * fy / (z * z);
    d_p[2] += d_j[5] * 2 * fy * f.p[1] / (z * z * z);
  }
  // p = W m + t.
  T* d_m = &out->position[3 * i];
  for (int k = 0; k < 3; ++k)
    d_m[k] += T(w[k]) * d_p[0] + T(w[3 + k]) * d_p[1] + T(w[6 + k]) * d_p[2];

  // Sigma = M M^T: dL/dM = 2 dL/dSigma M (dL/dSigma symmetric).
  T d_mm[9];
  for (int a = 0; a < 3; ++a) {
    for (int b = 0; b < 3; ++b) {
      d_mm[3 * a + b] = (d_sigma[3 * a] + d_sigma[a]) * shape.m[b] +
                        (d_sigma[3 * a + 1] + d_sigma[3 + a]) * shape.m[3 + b] +
                        (d_sigma[3 * a + 2] + d_sigma[6 + a]) * shape.m[6 + b];
    }
  }
  // M = R S: dL/ds_b = sum_a dM_ab R_ab; dL/dR_ab = dM_ab s_b.
  T d_r[9];
  for (int b = 0; b < 3; ++b) {
    T d_s = 0;
    for (int a = 0; a < 3; ++a) {
      d_s += d_mm[3 * a + b] * shape.r[3 * a + b];
      d_r[3 * a + b] = d_mm[3 * a + b] * shape.s[b];
    }
    out->log_scale[3 * i + b] += d_s * shape.s[b];
  }
  // R(q) for the unit quaternion, then through the normalisation.
  const T qw = shape.q[0], qx = shape.q[1], qy = shape.q[2], qz = shape.q[3];
  const T d_qn[4] = {
      2 * (-qz * d_r[1] + qy * d_r[2] + qz * d_r[3] - qx * d_r[5] - qy * d_r[6] + qx * d_r[7]),
      2 * (qy * d_r[1] + qz * d_r[2] + qy * d_r[3] - 2 * qx * d_r[4] - qw * d_r[5] + qz * d_r[6] +
           qw * d_r[7] - 2 * qx * d_r[8]),
      2 * (-2 * qy * d_r[0] + qx * d_r[1] + qw * d_r[2] + qx * d_r[3] + qz * d_r[5] - qw * d_r[6] +
           qz * d_r[7] - 2 * qy * d_r[8]),
      2 * (-2 * qz * d_r[0] - qw * d_r[1] + qx * d_r[2] + qw * d_r[3] - 2 * qz * d_r[4] +
           qy * d_r[5] + qx * d_r[6] + qy * d_r[7])};
  const T dot = qw * d_qn[0] + qx * d_qn[1] + qy * d_qn[2] + qz * d_qn[3];
  if (shape.q_norm > T(0)) {
    for (int k = 0; k < 4; ++k)
      out->rotation[4 * i + k] += (d_qn[k] - shape.q[k] * dot) / shape.q_norm;
  }

  // opacity = sigmoid(logit).
  const T o = p.opacity[i];
  out->opacity[i] += pg.opacity[i] * o * (T(1) - o);

  // colour = sum_k sh_k Y_k(direction) + 0.5, per channel unless clamped.
  const int degree = std::min(options.active_sh_degree, g.sh_degree);
  const int k_stored = g.coefficients(), k_used = ShCoefficients(degree);
  T direction[3];
  const T length = ViewDirection(&g.position[3 * i], center, direction);
  Dual3<T> dx(direction[0]), dy(direction[1]), dz(direction[2]);
  dx.d[0] = dy.d[1] = dz.d[2] = T(1);
  Dual3<T> basis[ShCoefficients(kMaxShDegree)];
  ShBasis(degree, dx, dy, dz, basis);
  T d_dir[3] = {0, 0, 0};
  for (int c = 0; c < 3; ++c) {
    if (p.clamped[3 * i + c]) continue;
    const T gcol = pg.color[3 * i + c];
    for (int k = 0; k < k_used; ++k) {
      const T coefficient = g.sh[(i * k_stored + k) * 3 + c];
      out->sh[(i * k_stored + k) * 3 + c] += gcol * basis[k].v;
      for (int a = 0; a < 3; ++a) d_dir[a] += gcol * coefficient * basis[k].d[a];
    }
  }
  if (length > T(0)) {
    const T along = d_dir[0] * direction[0] + d_dir[1] * direction[1] + d_dir[2] * direction[2];
    for (int a = 0; a < 3; ++a) d_m[a] += (d_dir[a] - direction[a] * along) / length;
  }
}

}  // namespace

template <typename T>
void ProjectBackward(const GaussianArrays<T>& g, const PinholeCamera& camera,
                     const RasterOptions& options, const ProjectedArrays<T>& p,
                     const ProjectedGradients<T>& pg, GaussianArrays<T>* out) {
  double center[3];
  camera.CenterInWorld(center);
  const int64_t n = g.size();
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    if (p.radius[i] <= 0) continue;
    // Drawn but reached by no pixel (hidden behind others): every term would add zero.
    bool reached = pg.opacity[i] != T(0);
    for (int k = 0; k < 3 && !reached; ++k)
      reached = pg.conic[3 * i + k] != T(0) || pg.color[3 * i + k] != T(0);
    for (int k = 0; k < 2 && !reached; ++k) reached = pg.mean2d[2 * i + k] != T(0);
    if (!reached) continue;
    ProjectBackwardOne(g, camera, options, p, pg, center, i, out);
  }
}

namespace {

// The 11-tap Gaussian window of SSIM (sigma 1.5), normalised.
template <typename T>
const std::array<T, 11>& SsimWindow() {
  static const std::array<T, 11> window = [] {
    std::array<double, 11> k{};
    double sum = 0;
    for (int i = 0; i < 11; ++i) sum += k[i] = std::exp(-(i - 5) * (i - 5) / (2 * 1.5 * 1.5));
    std::array<T, 11> out{};
    for (int i = 0; i < 11; ++i) out[i] = T(k[i] / sum);
    return out;
  }();
  return window;
}

// out[j] += weight x source[j]: the blur's one operation. The float one also in an AVX2 clone
// chosen at run time (no FMA: the same rounding as the SSE2 one).
__attribute__((target_clones("avx2", "default"))) void AddScaled(const float* source, float weight,
                                                                 int count, float* out) {
  for (int j = 0; j < count; ++j) out[j] += weight * source[j];
}
void AddScaled(const double* source, double weight, int count, double* out) {
  for (int j = 0; j < count; ++j) out[j] += weight * source[j];
}

// The horizontal pass of the separable blur on one interleaved row (`values` = 3 x width
// values, a pixel's three channels together), zero padded: `padded` holds the row at offset
// 15 with 15 zeros either side, so that every output is the same 11 products, channel by
// channel, in the same order, without a bounds test.
template <typename T>
inline void BlurRow(const T* padded, int values, T* out) {
  const std::array<T, 11>& w = SsimWindow<T>();
  std::fill(out, out + values, T(0));
  for (int k = 0; k < 11; ++k) AddScaled(padded + 3 * k, w[k], values, out);
}

// The vertical pass for row y of a map whose rows were blurred horizontally (`rows`, `values`
// a row), zero padded: out = sum over the rows inside the image, top to bottom.
template <typename T>
inline void BlurColumn(const T* rows, int values, int height, int y, T* out) {
  const std::array<T, 11>& w = SsimWindow<T>();
  std::fill(out, out + values, T(0));
  for (int k = std::max(0, 5 - y); k < 11 && y + k - 5 < height; ++k)
    AddScaled(rows + static_cast<size_t>(y + k - 5) * values, w[k], values, out);
}

// What the loss keeps between calls, so that a frame of the same size allocates nothing.
template <typename T>
struct LossScratch {
  std::vector<T> rows;                   // 5 horizontally blurred maps (x, y, xx, yy, xy)
  std::vector<T> gradient_maps;          // the SSIM map's 3 gradients (mu, xx, xy)
  std::vector<T> gradient_rows;          // those blurred horizontally
  std::vector<double> l1_row, ssim_row;  // per image row
};

}  // namespace

// The SSIM of all three channels at once, on the interleaved images: each separable blur runs
// along rows of 3 x width values (a tap steps by a pixel, 3 values), so channels never need
// separating. Four passes over the rows in one parallel region (products and horizontal blur
// with L1; vertical blur and the SSIM map's gradient; the gradient's horizontal blur; its
// vertical blur into dloss), each a static share of rows, per-row sums added in row order: the
// same value whatever the threads.
template <typename T>
double PhotometricLoss(const T* image, const T* target, int width, int height, double lambda,
                       T* dloss_dimage) {
  const int values = 3 * width;
  const size_t pixels = static_cast<size_t>(width) * height, count = 3 * pixels;
  static thread_local LossScratch<T> scratch;
  LossScratch<T>& s = scratch;
  s.l1_row.assign(height, 0.0);
  s.ssim_row.assign(height, 0.0);
  const bool ssim = lambda > 0;
  if (ssim) {
    s.rows.resize(5 * count);
    if (dloss_dimage != nullptr) {
      s.gradient_maps.resize(3 * count);
      s.gradient_rows.resize(3 * count);
    }
  }
  const T l1_step = T((1 - lambda) / static_cast<double>(count));
  const T c1 = T(0.01 * 0.01), c2 = T(0.03 * 0.03);
  const T scale = T(-lambda / static_cast<double>(count));
  T* const rows = s.rows.data();
  T* const gradient_maps = s.gradient_maps.data();
  T* const gradient_rows = s.gradient_rows.data();
  double* const l1_row = s.l1_row.data();
  double* const ssim_row = s.ssim_row.data();
#pragma omp parallel
  {
    static thread_local std::vector<T> row;  // a padded row, then 5 vertical results
    row.assign(6 * static_cast<size_t>(values) + 30, T(0));
    T* const padded = row.data();
#pragma omp for schedule(static)
    for (int y = 0; y < height; ++y) {
      const T* x_row = image + static_cast<size_t>(y) * values;
      const T* y_row = target + static_cast<size_t>(y) * values;
      double l1 = 0;
      for (int j = 0; j < values; ++j) {
        const T d = x_row[j] - y_row[j];
        l1 += std::abs(static_cast<double>(d));
        if (dloss_dimage != nullptr) {
          dloss_dimage[static_cast<size_t>(y) * values + j] =
              d > T(0) ? l1_step : (d < T(0) ? -l1_step : T(0));
        }
      }
      l1_row[y] = l1;
      if (!ssim) continue;
      for (int map = 0; map < 5; ++map) {
        T* inner = padded + 15;
        for (int j = 0; j < values; ++j) {
          const T a = x_row[j], b = y_row[j];
          inner[j] = map == 0 ? a : map == 1 ? b : map == 2 ? a * a : map == 3 ? b * b : a * b;
        }
        BlurRow(padded, values, rows + map * count + static_cast<size_t>(y) * values);
      }
    }
    if (ssim) {
      // 5 rows of `values`: mu_x, mu_y, E[xx], E[yy], E[xy]; then the row's SSIM values.
      T* const blurred = padded;
      T* const map_row = padded + 5 * static_cast<size_t>(values);
#pragma omp for schedule(static)
      for (int y = 0; y < height; ++y) {
        for (int map = 0; map < 5; ++map)
          BlurColumn(rows + map * count, values, height, y, blurred + map * values);
        const T *mx = blurred, *my = blurred + values, *sxx = blurred + 2 * values,
                *syy = blurred + 3 * values, *sxy = blurred + 4 * values;
        const size_t at = static_cast<size_t>(y) * values;
        const bool gradient = dloss_dimage != nullptr;
        for (int j = 0; j < values; ++j) {
          const T var_x = sxx[j] - mx[j] * mx[j], var_y = syy[j] - my[j] * my[j];
          const T cov = sxy[j] - mx[j] * my[j];
          const T a1 = 2 * mx[j] * my[j] + c1, a2 = 2 * cov + c2;
          const T b1 = mx[j] * mx[j] + my[j] * my[j] + c1, b2 = var_x + var_y + c2;
          const T value = a1 * a2 / (b1 * b2);
          map_row[j] = value;
          if (!gradient) continue;
          // dS/dmu_x, dS/dvar_x, dS/dcov; var_x = E[x^2] - mu_x^2 and cov = E[xy] - mu_x mu_y.
          const T ds_dmu = 2 * my[j] * a2 / (b1 * b2) - 2 * mx[j] * value / b1;
          const T ds_dvar = -value / b2;
          const T ds_dcov = 2 * a1 / (b1 * b2);
          gradient_maps[at + j] = ds_dmu - 2 * mx[j] * ds_dvar - my[j] * ds_dcov;
          gradient_maps[count + at + j] = ds_dvar;
          gradient_maps[2 * count + at + j] = ds_dcov;
        }
        double sum = 0;
        for (int j = 0; j < values; ++j) sum += map_row[j];
        ssim_row[y] = sum;
      }
    }
    if (ssim && dloss_dimage != nullptr) {
#pragma omp for schedule(static)
      for (int y = 0; y < height; ++y) {
        const size_t at = static_cast<size_t>(y) * values;
        for (int map = 0; map < 3; ++map) {
          std::copy(gradient_maps + map * count + at, gradient_maps + map * count + at + values,
                    padded + 15);
          std::fill(padded, padded + 15, T(0));
          std::fill(padded + 15 + values, padded + 30 + values, T(0));
          BlurRow(padded, values, gradient_rows + map * count + at);
        }
      }
#pragma omp for schedule(static)
      for (int y = 0; y < height; ++y) {
        for (int map = 0; map < 3; ++map)
          BlurColumn(gradient_rows + map * count, values, height, y, padded + map * values);
        const T *b_mu = padded, *b_xx = padded + values, *b_xy = padded + 2 * values;
        const size_t at = static_cast<size_t>(y) * values;
        for (int j = 0; j < values; ++j) {
          dloss_dimage[at + j] +=
              scale * (b_mu[j] + 2 * image[at + j] * b_xx[j] + target[at + j] * b_xy[j]);
        }
      }
    }
  }
  double l1 = 0, ssim_sum = 0;
  for (int y = 0; y < height; ++y) {
    l1 += l1_row[y];
    ssim_sum += ssim_row[y];
  }
  l1 /= static_cast<double>(count);
  if (!ssim) return l1;
  return (1 - lambda) * l1 + lambda * (1 - ssim_sum / static_cast<double>(count));
}

// The two scalars every kernel is built for: float runs, double checks.
// NOLINTBEGIN(bugprone-macro-parentheses): T is a type
#define HOLOCAP_SPLAT_INSTANTIATE(T)                                                               \
  template struct GaussianArrays<T>;                                                               \
  template struct ProjectedGradients<T>;                                                           \
  template void ShBasis<T>(int, const T&, const T&, const T&, T*);                                 \
  template void ProjectGaussians<T>(const GaussianArrays<T>&, const PinholeCamera&,                \
                                    const RasterOptions&, ProjectedArrays<T>*);                    \
  template void RasterizeForward<T>(const ProjectedArrays<T>&, const PinholeCamera&,               \
                                    const RasterOptions&, const T*, T*, T*, T*, RasterState*);     \
  template void RasterizeBackward<T>(const ProjectedArrays<T>&, const PinholeCamera&,              \
                                     const RasterOptions&, const RasterState&, const T*, const T*, \
                                     const T*, ProjectedGradients<T>*);                            \
  template void ProjectBackward<T>(const GaussianArrays<T>&, const PinholeCamera&,                 \
                                   const RasterOptions&, const ProjectedArrays<T>&,                \
                                   const ProjectedGradients<T>&, GaussianArrays<T>*);              \
  template double PhotometricLoss<T>(const T*, const T*, int, int, double, T*);
HOLOCAP_SPLAT_INSTANTIATE(float)
HOLOCAP_SPLAT_INSTANTIATE(double)
#undef HOLOCAP_SPLAT_INSTANTIATE
// NOLINTEND(bugprone-macro-parentheses)

}  // namespace holocap::splat
