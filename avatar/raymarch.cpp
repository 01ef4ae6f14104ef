#include "avatar/raymarch.h"

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <limits>

namespace holocap {
namespace {

// The 8 trilinear corners of a normalised coordinate on an n³ grid (voxel centres at
// (i + 0.5) / n). `clamp` keeps the corners inside the grid (border padding); otherwise
// corners outside are flagged invalid (zero padding).
struct Corners {
  int64_t index[8];  // voxel index, or -1 outside the grid
  float weight[8];
  float dweight[8][3];  // d weight / d (normalised coordinate)
};

inline void TrilinearCorners(const Eigen::Vector3f& u, int n, bool clamp, Corners* corners) {
  int base[3];
  float frac[3];
  for (int a = 0; a < 3; ++a) {
    float g = u[a] * n - 0.5f;
    if (clamp) g = std::clamp(g, 0.0f, static_cast<float>(n - 1));
    float floor_g = std::floor(g);
    base[a] = static_cast<int>(floor_g);
    if (clamp && base[a] >= n - 1) base[a] = std::max(n - 2, 0);
    frac[a] = g - base[a];
  }
  for (int c = 0; c < 8; ++c) {
    int offset[3] = {c & 1, (c >> 1) & 1, (c >> 2) & 1};
    float w[3], dw[3];
    bool inside = true;
    int idx[3];
    for (int a = 0; a < 3; ++a) {
      idx[a] = base[a] + offset[a];
      if (idx[a] < 0 || idx[a] >= n) inside = false;
      w[a] = offset[a] ? frac[a] : 1.0f - frac[a];
      dw[a] = (offset[a] ? 1.0f : -1.0f) * n;
    }
    corners->weight[c] = inside ? w[0] * w[1] * w[2] : 0.0f;
    corners->index[c] = inside ? (static_cast<int64_t>(idx[2]) * n + idx[1]) * n + idx[0] : -1;
    corners->dweight[c][0] = inside ? dw[0] * w[1] * w[2] : 0.0f;
    corners->dweight[c][1] = inside ? w[0] * dw[1] * w[2] : 0.0f;
    corners->dweight[c][2] = inside ? w[0] * w[1] * dw[2] : 0.0f;
  }
}

// Where a sample reads the template, and what it reads there.
struct Sample {
  Eigen::Vector3f u;     // normalised box coordinate
  Eigen::Vector3f y;     // template coordinate (u without a warp)
  Corners warp_corners;  // valid with a warp
  Corners corners;       // template corners at y
  float value[4];        // r, g, b, sigma
};

inline void EvaluateSample(const MarchVolume& volume, const Eigen::Vector3f& u, Sample* s) {
  s->u = u;
  if (volume.warp != nullptr) {
    TrilinearCorners(u, volume.warp_grid, /*clamp=*/true, &s->warp_corners);
    s->y.setZero();
    for (int c = 0; c < 8; ++c) {
      if (s->warp_corners.index[c] < 0) continue;
      const float* w = volume.warp + s->warp_corners.index[c] * 3;
      s->y += s->warp_corners.weight[c] * Eigen::Vector3f(w[0], w[1], w[2]);
    }
  } else {
    s->y = u;
  }
  TrilinearCorners(s->y, volume.grid, volume.rgba_clamped, &s->corners);
  for (float& v : s->value) v = 0;
  for (int c = 0; c < 8; ++c) {
    if (s->corners.index[c] < 0) continue;
    const float* v = volume.rgba + s->corners.index[c] * 4;
    for (int ch = 0; ch < 4; ++ch) s->value[ch] += s->corners.weight[c] * v[ch];
  }
  // Trilinear interpolation of non-negative densities is non-negative; guard against rounding.
  s->value[3] = std::max(s->value[3], 0.0f);
}

// The trilinear value alone (the forward pass needs no weight derivatives) of a channels-last
// n³ grid: the same corners and weights as TrilinearCorners, with one bounds test for the
// common case of a sample whose 8 corners all lie inside.
template <int kChannels>
inline void Interpolate(const float* grid, int n, bool clamp, const Eigen::Vector3f& u,
                        float* out) {
  int base[3];
  float frac[3];
  for (int a = 0; a < 3; ++a) {
    float g = u[a] * n - 0.5f;
    if (clamp) g = std::clamp(g, 0.0f, static_cast<float>(n - 1));
    base[a] = static_cast<int>(std::floor(g));
    if (clamp && base[a] >= n - 1) base[a] = std::max(n - 2, 0);
    frac[a] = g - base[a];
  }
  for (int ch = 0; ch < kChannels; ++ch) out[ch] = 0.0f;
  const int64_t sy = static_cast<int64_t>(n) * kChannels, sz = sy * n;
  const bool inside = base[0] >= 0 && base[1] >= 0 && base[2] >= 0 && base[0] + 1 < n &&
                      base[1] + 1 < n && base[2] + 1 < n;
  for (int c = 0; c < 8; ++c) {
    const int ox = c & 1, oy = (c >> 1) & 1, oz = (c >> 2) & 1;
    const int x = base[0] + ox, y = base[1] + oy, z = base[2] + oz;
    if (!inside && (x < 0 || y < 0 || z < 0 || x >= n || y >= n || z >= n)) continue;
    const float w = (ox ? frac[0] : 1.0f - frac[0]) * (oy ? frac[1] : 1.0f - frac[1]) *
                    (oz ? frac[2] : 1.0f - frac[2]);
    const float* v = grid + z * sz + y * sy + static_cast<int64_t>(x) * kChannels;
    for (int ch = 0; ch < kChannels; ++ch) out[ch] += w * v[ch];
  }
}

// r, g, b, sigma of a sample, as EvaluateSample computes them.
inline void EvaluateValue(const MarchVolume& volume, const Eigen::Vector3f& u, float value[4]) {
  Eigen::Vector3f y = u;
  if (volume.warp != nullptr)
    Interpolate<3>(volume.warp, volume.warp_grid, /*clamp=*/true, u, y.data());
  Interpolate<4>(volume.rgba, volume.grid, volume.rgba_clamped, y, value);
  value[3] = std::max(value[3], 0.0f);
}

// Interpolate<4> without a border test where all 8 corners lie inside, as 4-wide lerps of
// the interleaved RGBA voxels (playback: a sample is this one lookup).
inline void InterpolateRgba(const float* grid, int n, bool clamp, const Eigen::Vector3f& u,
                            float out[4]) {
  const float gx = u[0] * n - 0.5f, gy = u[1] * n - 0.5f, gz = u[2] * n - 0.5f;
  const int bx = static_cast<int>(std::floor(gx)), by = static_cast<int>(std::floor(gy)),
            bz = static_cast<int>(std::floor(gz));
  if (bx < 0 || by < 0 || bz < 0 || bx + 1 >= n || by + 1 >= n || bz + 1 >= n) {
    Interpolate<4>(grid, n, clamp, u, out);
    return;
  }
  using V = Eigen::Array4f;
  const float fx = gx - bx, fy = gy - by, fz = gz - bz;
  const int64_t sy = static_cast<int64_t>(n) * 4, sz = sy * n;
  const float* p = grid + bz * sz + by * sy + static_cast<int64_t>(bx) * 4;
  auto at = [&](int64_t offset) { return Eigen::Map<const V>(p + offset); };
  const V x00 = at(0) + fx * (at(4) - at(0));
  const V x10 = at(sy) + fx * (at(sy + 4) - at(sy));
  const V x01 = at(sz) + fx * (at(sz + 4) - at(sz));
  const V x11 = at(sz + sy) + fx * (at(sz + sy + 4) - at(sz + sy));
  const V y0 = x00 + fy * (x10 - x00);
  const V y1 = x01 + fy * (x11 - x01);
  Eigen::Map<V> result(out);
  result = y0 + fz * (y1 - y0);
}

// The world box of a volume's occupied cells: every sample outside it lies in an empty cell,
// so a skipping ray is clipped to it before it walks any cell. `any` is false when no cell is
// occupied; without a grid (or when empty cells are evaluated) it is the whole box.
struct OccupiedBox {
  bool any = true;
  Eigen::Vector3f min, max;
};

OccupiedBox OccupiedBoxOf(const MarchVolume& volume, const MarchOptions& options) {
  OccupiedBox box;
  box.min = volume.box_min;
  box.max = volume.box_max;
  const OccupancyGrid* occ = volume.occupancy;
  if (occ == nullptr || occ->empty() || options.evaluate_empty_cells) return box;
  const int n = occ->size;
  int lo[3] = {n, n, n}, hi[3] = {-1, -1, -1};
  for (int z = 0; z < n; ++z) {
    for (int y = 0; y < n; ++y) {
      for (int x = 0; x < n; ++x) {
        if (!occ->occupied[(static_cast<int64_t>(z) * n + y) * n + x]) continue;
        const int cell[3] = {x, y, z};
        for (int a = 0; a < 3; ++a) {
          lo[a] = std::min(lo[a], cell[a]);
          hi[a] = std::max(hi[a], cell[a] + 1);
        }
      }
    }
  }
  if (hi[0] < 0) {
    box.any = false;
    return box;
  }
  const Eigen::Vector3f cell_size = (volume.box_max - volume.box_min) / static_cast<float>(n);
  for (int a = 0; a < 3; ++a) {
    box.min[a] = volume.box_min[a] + lo[a] * cell_size[a];
    box.max[a] = volume.box_min[a] + hi[a] * cell_size[a];
  }
  return box;
}

// Visits the samples t_k = t_near + (k + jitter) step of one ray, jumping over empty occupancy
// cells without changing where the remaining samples fall. `visit(t, u, masked)` returns false
// to stop; `masked` samples lie in empty cells (evaluate_empty_cells) and add nothing.
// Returns the number of samples visited; sets *truncated when max_samples_per_ray stopped it.
template <typename Visit>
int64_t ForEachSample(const MarchVolume& volume, const OccupiedBox& occupied, const RayBatch& rays,
                      int64_t r, const MarchOptions& options, bool* truncated, Visit&& visit) {
  *truncated = false;
  const float t_near = rays.t_near[r], t_far = rays.t_far[r];
  if (!(t_far > t_near) || !occupied.any) return 0;
  const Eigen::Vector3f o(rays.origin[3 * r], rays.origin[3 * r + 1], rays.origin[3 * r + 2]);
  const Eigen::Vector3f d(rays.direction[3 * r], rays.direction[3 * r + 1],
                          rays.direction[3 * r + 2]);
  const Eigen::Vector3f extent = volume.box_max - volume.box_min;
  const OccupancyGrid* occ =
      (volume.occupancy != nullptr && !volume.occupancy->empty()) ? volume.occupancy : nullptr;
  const double step = options.step_m;
  const double jitter = rays.jitter.empty() ? 0.0 : rays.jitter[r];
  // Samples stay on the ray's own lattice t_near + (k + jitter) step; clipping only moves the
  // first and last k, one step wide of the occupied box so that rounding at its faces cannot
  // drop a sample (those extra samples go through the cell test like any other).
  int64_t k_first = 0;
  double t_last = t_far;
  if (occ != nullptr && !options.evaluate_empty_cells) {
    float t0 = 0, t1 = 0;
    if (!ClipToBox(o, d, occupied.min, occupied.max, t_near, &t0, &t1)) return 0;
    k_first =
        std::max<int64_t>(0, static_cast<int64_t>(std::floor((t0 - t_near) / step - jitter)) - 1);
    t_last = std::min<double>(t_far, t1 + step);
  }
  int64_t visited = 0;
  for (int64_t k = k_first;;) {
    const double t = t_near + (k + jitter) * step;
    if (t >= t_last) break;
    const Eigen::Vector3f p = o + static_cast<float>(t) * d;
    const Eigen::Vector3f u = ((p - volume.box_min).array() / extent.array()).matrix();
    if (occ != nullptr) {
      const int n = occ->size;
      int cell[3];
      for (int a = 0; a < 3; ++a) {
        cell[a] = std::clamp(static_cast<int>(std::floor(u[a] * n)), 0, n - 1);
      }
      const bool empty =
          !occ->occupied[(static_cast<int64_t>(cell[2]) * n + cell[1]) * n + cell[0]];
      if (empty && options.evaluate_empty_cells) {
        if (visited >= options.max_samples_per_ray) {
          *truncated = true;
          break;
        }
        ++visited;
        if (!visit(static_cast<float>(t), u, /*masked=*/true)) break;
        ++k;
        continue;
      }
      if (empty) {
        // Leave the cell: the nearest exit plane along the ray.
        double exit = std::numeric_limits<double>::infinity();
        for (int a = 0; a < 3; ++a) {
          if (std::abs(d[a]) < 1e-12f) continue;
          const double cell_size = extent[a] / n;
          const double plane = volume.box_min[a] + (d[a] > 0 ? cell[a] + 1 : cell[a]) * cell_size;
          exit = std::min(exit, (plane - p[a]) / d[a]);
        }
        const double t_exit = t + std::max(exit, 0.0);
        const int64_t next =
            static_cast<int64_t>(std::ceil((t_exit - t_near) / step - jitter + 1e-6));
        k = std::max(k + 1, next);
        continue;
      }
    }
    if (visited >= options.max_samples_per_ray) {
      *truncated = true;
      break;
    }
    ++visited;
    if (!visit(static_cast<float>(t), u, /*masked=*/false)) break;
    ++k;
  }
  return visited;
}

}  // namespace

void RayBatch::Resize(int64_t count) {
  origin.assign(3 * count, 0.0f);
  direction.assign(3 * count, 0.0f);
  t_near.assign(count, 0.0f);
  t_far.assign(count, 0.0f);
  jitter.assign(count, 0.0f);
}

int64_t OccupancyGrid::OccupiedCount() const {
  int64_t count = 0;
  for (uint8_t o : occupied) count += o != 0;
  return count;
}

void OccupancyGrid::Dilate(int cells) {
  if (empty() || cells <= 0) return;
  const int n = size;
  for (int pass = 0; pass < cells; ++pass) {
    std::vector<uint8_t> grown = occupied;
    for (int z = 0; z < n; ++z) {
      for (int y = 0; y < n; ++y) {
        for (int x = 0; x < n; ++x) {
          if (!occupied[(static_cast<int64_t>(z) * n + y) * n + x]) continue;
          for (int dz = -1; dz <= 1; ++dz) {
            for (int dy = -1; dy <= 1; ++dy) {
              for (int dx = -1; dx <= 1; ++dx) {
                const int xx = x + dx, yy = y + dy, zz = z + dz;
                if (xx < 0 || yy < 0 || zz < 0 || xx >= n || yy >= n || zz >= n) continue;
                grown[(static_cast<int64_t>(zz) * n + yy) * n + xx] = 1;
              }
            }
          }
        }
      }
    }
    occupied.swap(grown);
  }
}

double MarchOutputs::MeanSamples() const {
  if (samples.empty()) return 0;
  double sum = 0;
  for (int32_t s : samples) sum += s;
  return sum / samples.size();
}

bool ClipToBox(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction,
               const Eigen::Vector3f& box_min, const Eigen::Vector3f& box_max, float near_m,
               float* t_near, float* t_far) {
  double lo = near_m, hi = std::numeric_limits<double>::infinity();
  for (int a = 0; a < 3; ++a) {
    if (std::abs(direction[a]) < 1e-12f) {
      if (origin[a] < box_min[a] || origin[a] > box_max[a]) return false;
      continue;
    }
    double t0 = (box_min[a] - origin[a]) / static_cast<double>(direction[a]);
    double t1 = (box_max[a] - origin[a]) / static_cast<double>(direction[a]);
    if (t0 > t1) std::swap(t0, t1);
    lo = std::max(lo, t0);
    hi = std::min(hi, t1);
  }
  *t_near = static_cast<float>(lo);
  *t_far = static_cast<float>(hi);
  return hi > lo;
}

RayBatch CameraRays(const CameraModel& camera, const Eigen::Matrix2Xd& pixels,
                    const Eigen::Vector3f& box_min, const Eigen::Vector3f& box_max, float near_m) {
  RayBatch rays;
  const int64_t count = pixels.cols();
  rays.Resize(count);
  const Pose world_from_cam = camera.world_from_cam();
  const Eigen::Vector3f center = world_from_cam.translation().cast<float>();
  const Eigen::Matrix3d rotation = world_from_cam.rotation();
  // Unprojection (iterative for most lens models) costs as much as marching a view: chunks of
  // pixels in parallel.
  Eigen::Matrix3Xd dirs_cam(3, count);
  constexpr int64_t kChunk = 4096;
#pragma omp parallel for schedule(dynamic, 1)
  for (int64_t begin = 0; begin < count; begin += kChunk) {
    const int64_t size = std::min(kChunk, count - begin);
    dirs_cam.middleCols(begin, size) = camera.UnprojectMany(pixels.middleCols(begin, size));
  }
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < count; ++i) {
    if (!dirs_cam.col(i).allFinite()) continue;
    const Eigen::Vector3f d = (rotation * dirs_cam.col(i).normalized()).cast<float>();
    for (int a = 0; a < 3; ++a) {
      rays.origin[3 * i + a] = center[a];
      rays.direction[3 * i + a] = d[a];
    }
    float t0 = 0, t1 = 0;
    if (ClipToBox(center, d, box_min, box_max, near_m, &t0, &t1)) {
      rays.t_near[i] = t0;
      rays.t_far[i] = t1;
    }
  }
  return rays;
}

RayBatch CameraRaysAllPixels(const CameraModel& camera, const Eigen::Vector3f& box_min,
                             const Eigen::Vector3f& box_max, float near_m) {
  Eigen::Matrix2Xd pixels(2, static_cast<int64_t>(camera.width()) * camera.height());
  for (int y = 0, i = 0; y < camera.height(); ++y) {
    for (int x = 0; x < camera.width(); ++x, ++i) pixels.col(i) << x, y;
  }
  return CameraRays(camera, pixels, box_min, box_max, near_m);
}

void MarchForward(const MarchVolume& volume, const RayBatch& rays, const MarchOptions& options,
                  MarchOutputs* out) {
  const int64_t n = rays.size();
  const OccupiedBox occupied = OccupiedBoxOf(volume, options);
  out->rgb.assign(3 * n, 0.0f);
  out->alpha.assign(n, 0.0f);
  out->depth.assign(n, 0.0f);
  out->samples.assign(n, 0);
  int64_t truncated_rays = 0;
  const double step = options.step_m;
#pragma omp parallel for schedule(dynamic, 64) reduction(+ : truncated_rays)
  for (int64_t r = 0; r < n; ++r) {
    double transmittance = 1, rgb[3] = {0, 0, 0}, depth = 0;
    float value[4];
    bool truncated = false;
    out->samples[r] =
        static_cast<int32_t>(ForEachSample(volume, occupied, rays, r, options, &truncated,
                                           [&](float t, const Eigen::Vector3f& u, bool masked) {
                                             EvaluateValue(volume, u, value);
                                             if (masked) return true;
                                             // One exponential per sample; in double, 1 - decay
                                             // keeps its precision for the faintest samples and the
                                             // product underflows to 0, never to NaN.
                                             const double decay = std::exp(-value[3] * step);
                                             const double w = transmittance * (1.0 - decay);
                                             for (int c = 0; c < 3; ++c) rgb[c] += w * value[c];
                                             depth += w * t;
                                             transmittance *= decay;
                                             return !(transmittance < options.min_transmittance);
                                           }));
    truncated_rays += truncated;
    for (int c = 0; c < 3; ++c) out->rgb[3 * r + c] = static_cast<float>(rgb[c]);
    out->alpha[r] = static_cast<float>(1.0 - transmittance);
    out->depth[r] = static_cast<float>(depth);
  }
  out->truncated_rays = truncated_rays;
}

void MarchBackward(const MarchVolume& volume, const RayBatch& rays, const MarchOptions& options,
                   const float* grad_rgb, const float* grad_alpha, float* grad_rgba,
                   float* grad_warp) {
  const int64_t n = rays.size();
  const OccupiedBox occupied = OccupiedBoxOf(volume, options);
  const int64_t rgba_size = static_cast<int64_t>(volume.grid) * volume.grid * volume.grid * 4;
  const bool has_warp = volume.warp != nullptr;
  const int64_t warp_size =
      has_warp ? static_cast<int64_t>(volume.warp_grid) * volume.warp_grid * volume.warp_grid * 3
               : 0;
  const int threads = omp_get_max_threads();
  // Per-thread gradient buffers (thread 0 writes the caller's directly): no atomics in the
  // inner loop, one reduction at the end.
  std::vector<std::vector<float>> rgba_parts(threads > 1 ? threads - 1 : 0);
  std::vector<std::vector<float>> warp_parts(threads > 1 ? threads - 1 : 0);
  const double step = options.step_m;
#pragma omp parallel num_threads(threads)
  {
    const int id = omp_get_thread_num();
    float* my_rgba = grad_rgba;
    float* my_warp = grad_warp;
    if (id > 0) {
      rgba_parts[id - 1].assign(rgba_size, 0.0f);
      my_rgba = rgba_parts[id - 1].data();
      if (has_warp && grad_warp != nullptr) {
        warp_parts[id - 1].assign(warp_size, 0.0f);
        my_warp = warp_parts[id - 1].data();
      }
    }
#pragma omp for schedule(dynamic, 64)
    for (int64_t r = 0; r < n; ++r) {
      const double g_rgb[3] = {grad_rgb[3 * r], grad_rgb[3 * r + 1], grad_rgb[3 * r + 2]};
      const double g_alpha = grad_alpha != nullptr ? grad_alpha[r] : 0.0;
      if (g_rgb[0] == 0 && g_rgb[1] == 0 && g_rgb[2] == 0 && g_alpha == 0) continue;
      // First pass: the ray's total colour and exit transmittance.
      double tau = 0, transmittance = 1, total[3] = {0, 0, 0};
      Sample s;
      bool truncated = false;
      ForEachSample(volume, occupied, rays, r, options, &truncated,
                    [&](float, const Eigen::Vector3f& u, bool masked) {
                      if (masked) return true;
                      float value[4];
                      EvaluateValue(volume, u, value);
                      const double optical = value[3] * step;
                      const double w = transmittance * -std::expm1(-optical);
                      for (int c = 0; c < 3; ++c) total[c] += w * value[c];
                      tau += optical;
                      transmittance = std::exp(-tau);
                      return !(transmittance < options.min_transmittance);
                    });
      const double t_end = transmittance;
      // Second pass: d/dc_k = g w_k; d/dsigma_k = step (T_{k+1} g.c_k - g.(C - P_k)) +
      // g_alpha step T_end, with P_k the colour accumulated up to and including sample k.
      tau = 0;
      transmittance = 1;
      double prefix[3] = {0, 0, 0};
      ForEachSample(volume, occupied, rays, r, options, &truncated,
                    [&](float, const Eigen::Vector3f& u, bool masked) {
                      if (masked) return true;
                      EvaluateSample(volume, u, &s);
                      const double optical = s.value[3] * step;
                      const double w = transmittance * -std::expm1(-optical);
                      for (int c = 0; c < 3; ++c) prefix[c] += w * s.value[c];
                      tau += optical;
                      const double t_next = std::exp(-tau);
                      double g_dot_c = 0, g_dot_rest = 0;
                      for (int c = 0; c < 3; ++c) {
                        g_dot_c += g_rgb[c] * s.value[c];
                        g_dot_rest += g_rgb[c] * (total[c] - prefix[c]);
                      }
                      float g_value[4];
                      for (int c = 0; c < 3; ++c) g_value[c] = static_cast<float>(g_rgb[c] * w);
                      // The clamp of a rounding-negative density has zero gradient there.
                      g_value[3] = static_cast<float>(step * (t_next * g_dot_c - g_dot_rest) +
                                                      g_alpha * step * t_end);
                      transmittance = t_next;
                      Eigen::Vector3f g_y = Eigen::Vector3f::Zero();
                      for (int c = 0; c < 8; ++c) {
                        const int64_t index = s.corners.index[c];
                        if (index < 0) continue;
                        float* g = my_rgba + index * 4;
                        const float* v = volume.rgba + index * 4;
                        for (int ch = 0; ch < 4; ++ch) {
                          g[ch] += s.corners.weight[c] * g_value[ch];
                          if (has_warp) {
                            for (int a = 0; a < 3; ++a)
                              g_y[a] += g_value[ch] * s.corners.dweight[c][a] * v[ch];
                          }
                        }
                      }
                      if (has_warp && my_warp != nullptr) {
                        for (int c = 0; c < 8; ++c) {
                          const int64_t index = s.warp_corners.index[c];
                          if (index < 0) continue;
                          for (int a = 0; a < 3; ++a)
                            my_warp[index * 3 + a] += s.warp_corners.weight[c] * g_y[a];
                        }
                      }
                      return !(transmittance < options.min_transmittance);
                    });
    }
  }
  for (const auto& part : rgba_parts) {
    if (part.empty()) continue;
    for (int64_t i = 0; i < rgba_size; ++i) grad_rgba[i] += part[i];
  }
  for (const auto& part : warp_parts) {
    if (part.empty()) continue;
    for (int64_t i = 0; i < warp_size; ++i) grad_warp[i] += part[i];
  }
}

OccupancyGrid OccupancyFromVolume(const MarchVolume& volume, int cells, float min_density) {
  OccupancyGrid occupancy;
  occupancy.size = cells;
  occupancy.occupied.assign(static_cast<int64_t>(cells) * cells * cells, 0);
  const int d = volume.grid;
#pragma omp parallel for schedule(static)
  for (int z = 0; z < d; ++z) {
    float value[4];
    for (int y = 0; y < d; ++y) {
      for (int x = 0; x < d; ++x) {
        const Eigen::Vector3f u((x + 0.5f) / d, (y + 0.5f) / d, (z + 0.5f) / d);
        EvaluateValue(volume, u, value);
        if (value[3] <= min_density) continue;
        const int cx = std::min(x * cells / d, cells - 1);
        const int cy = std::min(y * cells / d, cells - 1);
        const int cz = std::min(z * cells / d, cells - 1);
        uint8_t& cell = occupancy.occupied[(static_cast<int64_t>(cz) * cells + cy) * cells + cx];
#pragma omp atomic write
        cell = 1;
      }
    }
  }
  return occupancy;
}

MarchVolume BakedVolume::View(const OccupancyGrid* occupancy) const {
  MarchVolume volume;
  volume.box_min = box_min;
  volume.box_max = box_max;
  volume.rgba = rgba.data();
  volume.grid = grid;
  volume.occupancy = occupancy;
  volume.rgba_clamped = clamped;
  return volume;
}

BakedVolume BakeVolume(const MarchVolume& volume, int grid) {
  BakedVolume baked;
  baked.box_min = volume.box_min;
  baked.box_max = volume.box_max;
  baked.grid = grid;
  const int64_t voxels = static_cast<int64_t>(grid) * grid * grid;
  if (volume.warp == nullptr && grid == volume.grid) {
    baked.rgba.assign(volume.rgba, volume.rgba + 4 * voxels);
    return baked;
  }
  baked.rgba.resize(4 * voxels);
  baked.clamped = true;
#pragma omp parallel for schedule(static)
  for (int z = 0; z < grid; ++z) {
    for (int y = 0; y < grid; ++y) {
      for (int x = 0; x < grid; ++x) {
        const Eigen::Vector3f u((x + 0.5f) / grid, (y + 0.5f) / grid, (z + 0.5f) / grid);
        EvaluateValue(volume, u,
                      &baked.rgba[4 * ((static_cast<int64_t>(z) * grid + y) * grid + x)]);
      }
    }
  }
  return baked;
}

namespace {

// The playback walk of one ray: ForEachSample's lattice, cell test and exit rule, plus a
// coarse level (kCoarse³ fine cells each) whose empty cells are left in one stride.
constexpr int kCoarse = 4;

struct CoarseOccupancy {
  int size = 0;
  std::vector<uint8_t> occupied;
};

CoarseOccupancy CoarseOf(const OccupancyGrid& occ) {
  CoarseOccupancy coarse;
  const int n = occ.size;
  coarse.size = (n + kCoarse - 1) / kCoarse;
  const int m = coarse.size;
  coarse.occupied.assign(static_cast<int64_t>(m) * m * m, 0);
  for (int z = 0; z < n; ++z) {
    for (int y = 0; y < n; ++y) {
      for (int x = 0; x < n; ++x) {
        if (!occ.occupied[(static_cast<int64_t>(z) * n + y) * n + x]) continue;
        coarse.occupied[(static_cast<int64_t>(z / kCoarse) * m + y / kCoarse) * m + x / kCoarse] =
            1;
      }
    }
  }
  return coarse;
}

template <bool kWarp>
void MarchPlaybackRays(const MarchVolume& volume, const RayBatch& rays, const MarchOptions& options,
                       MarchOutputs* out) {
  const int64_t count = rays.size();
  const OccupiedBox occupied = OccupiedBoxOf(volume, options);
  const OccupancyGrid* occ =
      (volume.occupancy != nullptr && !volume.occupancy->empty()) ? volume.occupancy : nullptr;
  const CoarseOccupancy coarse = occ != nullptr ? CoarseOf(*occ) : CoarseOccupancy{};
  const Eigen::Vector3f extent = volume.box_max - volume.box_min;
  const double step = options.step_m;
  const float step_f = options.step_m;
  int64_t truncated_rays = 0;
#pragma omp parallel for schedule(dynamic, 64) reduction(+ : truncated_rays)
  for (int64_t r = 0; r < count; ++r) {
    float transmittance = 1, rgb[3] = {0, 0, 0}, depth = 0;
    int64_t visited = 0;
    const float t_near = rays.t_near[r], t_far = rays.t_far[r];
    const Eigen::Vector3f o(rays.origin[3 * r], rays.origin[3 * r + 1], rays.origin[3 * r + 2]);
    const Eigen::Vector3f d(rays.direction[3 * r], rays.direction[3 * r + 1],
                            rays.direction[3 * r + 2]);
    const double jitter = rays.jitter.empty() ? 0.0 : rays.jitter[r];
    int64_t k_first = 0;
    double t_last = t_far;
    bool live = t_far > t_near && occupied.any;
    if (live && occ != nullptr && !options.evaluate_empty_cells) {
      float t0 = 0, t1 = 0;
      live = ClipToBox(o, d, occupied.min, occupied.max, t_near, &t0, &t1);
      k_first =
          std::max<int64_t>(0, static_cast<int64_t>(std::floor((t0 - t_near) / step - jitter)) - 1);
      t_last = std::min<double>(t_far, t1 + step);
    }
    for (int64_t k = k_first; live;) {
      const double t = t_near + (k + jitter) * step;
      if (t >= t_last) break;
      const Eigen::Vector3f p = o + static_cast<float>(t) * d;
      const Eigen::Vector3f u = ((p - volume.box_min).array() / extent.array()).matrix();
      bool masked = false;
      if (occ != nullptr) {
        const int n = occ->size;
        int cell[3];
        for (int a = 0; a < 3; ++a)
          cell[a] = std::clamp(static_cast<int>(std::floor(u[a] * n)), 0, n - 1);
        if (!occ->occupied[(static_cast<int64_t>(cell[2]) * n + cell[1]) * n + cell[0]]) {
          if (options.evaluate_empty_cells) {
            masked = true;
          } else {
            // Leave the empty coarse cell when the whole of it is empty, else the fine cell.
            const int m = coarse.size;
            const bool coarse_empty =
                !coarse.occupied[(static_cast<int64_t>(cell[2] / kCoarse) * m + cell[1] / kCoarse) *
                                     m +
                                 cell[0] / kCoarse];
            double exit = std::numeric_limits<double>::infinity();
            for (int a = 0; a < 3; ++a) {
              if (std::abs(d[a]) < 1e-12f) continue;
              const double cell_size = extent[a] / n;
              int face = d[a] > 0 ? cell[a] + 1 : cell[a];
              if (coarse_empty) {
                const int c = cell[a] / kCoarse;
                face = d[a] > 0 ? std::min(n, (c + 1) * kCoarse) : c * kCoarse;
              }
              const double plane = volume.box_min[a] + face * cell_size;
              exit = std::min(exit, (plane - p[a]) / d[a]);
            }
            const double t_exit = t + std::max(exit, 0.0);
            const int64_t next =
                static_cast<int64_t>(std::ceil((t_exit - t_near) / step - jitter + 1e-6));
            k = std::max(k + 1, next);
            continue;
          }
        }
      }
      if (visited >= options.max_samples_per_ray) {
        ++truncated_rays;
        break;
      }
      ++visited;
      float value[4];
      if constexpr (kWarp) {
        EvaluateValue(volume, u, value);
      } else {
        InterpolateRgba(volume.rgba, volume.grid, volume.rgba_clamped, u, value);
      }
      // A masked sample is read but composited with zero density: it adds nothing.
      const float sigma = masked ? 0.0f : std::max(value[3], 0.0f);
      const float decay = std::exp(-sigma * step_f);
      const float w = transmittance * (1.0f - decay);
      for (int c = 0; c < 3; ++c) rgb[c] += w * value[c];
      depth += w * static_cast<float>(t);
      transmittance *= decay;
      if (transmittance < options.min_transmittance) break;
      ++k;
    }
    out->samples[r] = static_cast<int32_t>(visited);
    for (int c = 0; c < 3; ++c) out->rgb[3 * r + c] = rgb[c];
    out->alpha[r] = 1.0f - transmittance;
    out->depth[r] = depth;
  }
  out->truncated_rays = truncated_rays;
}

}  // namespace

void MarchPlayback(const MarchVolume& volume, const RayBatch& rays, const MarchOptions& options,
                   MarchOutputs* out) {
  const int64_t n = rays.size();
  out->rgb.assign(3 * n, 0.0f);
  out->alpha.assign(n, 0.0f);
  out->depth.assign(n, 0.0f);
  out->samples.assign(n, 0);
  out->truncated_rays = 0;
  if (volume.warp != nullptr) {
    MarchPlaybackRays<true>(volume, rays, options, out);
  } else {
    MarchPlaybackRays<false>(volume, rays, options, out);
  }
}

}  // namespace holocap
