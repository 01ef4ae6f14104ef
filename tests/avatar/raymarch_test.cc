// The ray marcher: its hand-written backward pass against central finite differences (grid
// and warp field), and the stiff cases (density 1e6, empty volume, camera inside the volume,
// far-away camera, very small step, transmittance underflow), plus skipping that changes no
// pixel.
#include <gtest/gtest.h>

#include <array>
#include <cmath>
#include <random>

#include "avatar/raymarch.h"
#include "core/camera.h"
#include "core/pose.h"

namespace holocap::neural {
namespace {

const Eigen::Vector3f kBoxMin(-0.5f, -0.5f, 0.0f);
const Eigen::Vector3f kBoxMax(0.5f, 0.5f, 1.0f);

// A smooth blob of density with varying colour on a d³ grid, plus voxel noise up to `amount`.
std::vector<float> BlobGrid(int d, float peak_density, uint64_t seed, float amount = 0.2f) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> noise(0.0f, amount);
  std::vector<float> grid(static_cast<size_t>(d) * d * d * 4);
  for (int z = 0; z < d; ++z) {
    for (int y = 0; y < d; ++y) {
      for (int x = 0; x < d; ++x) {
        const float u = (x + 0.5f) / d - 0.5f, v = (y + 0.5f) / d - 0.5f, w = (z + 0.5f) / d - 0.5f;
        float* c = &grid[((static_cast<size_t>(z) * d + y) * d + x) * 4];
        c[0] = 0.2f + 0.6f * (x + 0.5f) / d + noise(rng);
        c[1] = 0.3f + 0.5f * (y + 0.5f) / d + noise(rng);
        c[2] = 0.8f - 0.6f * (z + 0.5f) / d + noise(rng);
        c[3] = peak_density * std::exp(-(u * u + v * v + w * w) / 0.06f) + noise(rng);
      }
    }
  }
  return grid;
}

// Colour and density affine in position: trilinear interpolation of it is affine too, so the
// value has no kinks at voxel faces and finite differences of the warp are smooth.
std::vector<float> AffineGrid(int d) {
  std::vector<float> grid(static_cast<size_t>(d) * d * d * 4);
  for (int z = 0; z < d; ++z) {
    for (int y = 0; y < d; ++y) {
      for (int x = 0; x < d; ++x) {
        const float u = (x + 0.5f) / d, v = (y + 0.5f) / d, w = (z + 0.5f) / d;
        float* c = &grid[((static_cast<size_t>(z) * d + y) * d + x) * 4];
        c[0] = 0.2f + 0.6f * u;
        c[1] = 0.3f + 0.5f * v - 0.2f * w;
        c[2] = 0.8f - 0.6f * w + 0.1f * u;
        c[3] = 2.0f + 4.0f * u + 3.0f * v - 2.0f * w;
      }
    }
  }
  return grid;
}

// A gently non-identity warp field into the template's interior (away from its zero-padded
// border half voxel): template coordinates a little rotated and scaled.
std::vector<float> WarpField(int w) {
  std::vector<float> field(static_cast<size_t>(w) * w * w * 3);
  for (int z = 0; z < w; ++z) {
    for (int y = 0; y < w; ++y) {
      for (int x = 0; x < w; ++x) {
        const float u = (x + 0.5f) / w, v = (y + 0.5f) / w, s = (z + 0.5f) / w;
        float* f = &field[((static_cast<size_t>(z) * w + y) * w + x) * 3];
        f[0] = 0.5f + 0.7f * (u - 0.5f) + 0.1f * (v - 0.5f);
        f[1] = 0.5f - 0.1f * (u - 0.5f) + 0.7f * (v - 0.5f) + 0.05f * std::sin(3 * s);
        f[2] = 0.5f + 0.8f * (s - 0.5f);
      }
    }
  }
  return field;
}

CameraModel LookingAtBox(const Eigen::Vector3d& eye, int size = 24, double focal = 30) {
  return CameraModel::Pinhole(focal, size, size,
                              CamFromWorldLookAt(eye, Eigen::Vector3d(0, 0, 0.5)));
}

RayBatch SomeRays(const CameraModel& camera, float near_m = 0.0f) {
  RayBatch rays = CameraRaysAllPixels(camera, kBoxMin, kBoxMax, near_m);
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<float> unit(0.0f, 1.0f);
  for (auto& j : rays.jitter) j = unit(rng);
  return rays;
}

// A fixed random linear functional of the outputs, so that every output is checked.
struct Functional {
  std::vector<float> g_rgb, g_alpha;
  Functional(int64_t n, uint64_t seed) : g_rgb(3 * n), g_alpha(n) {
    std::mt19937_64 rng(seed);
    std::normal_distribution<float> normal;
    for (auto& g : g_rgb) g = normal(rng);
    for (auto& g : g_alpha) g = normal(rng);
  }
  double operator()(const MarchOutputs& out) const {
    double sum = 0;
    for (size_t i = 0; i < g_rgb.size(); ++i) sum += static_cast<double>(g_rgb[i]) * out.rgb[i];
    for (size_t i = 0; i < g_alpha.size(); ++i)
      sum += static_cast<double>(g_alpha[i]) * out.alpha[i];
    return sum;
  }
};

double Evaluate(const MarchVolume& volume, const RayBatch& rays, const MarchOptions& options,
                const Functional& f) {
  MarchOutputs out;
  MarchForward(volume, rays, options, &out);
  return f(out);
}

// Relative error of analytic against central differences on `count` random entries.
double WorstRelativeError(std::vector<float>& values, const std::vector<float>& analytic,
                          const MarchVolume& volume, const RayBatch& rays,
                          const MarchOptions& options, const Functional& f, int count, float h,
                          uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::vector<size_t> candidates;
  for (size_t i = 0; i < analytic.size(); ++i) {
    if (std::abs(analytic[i]) > 1e-3f) candidates.push_back(i);
  }
  EXPECT_GT(candidates.size(), static_cast<size_t>(count)) << "too few entries carry gradient";
  double worst = 0;
  for (int k = 0; k < count && !candidates.empty(); ++k) {
    const size_t i =
        candidates[std::uniform_int_distribution<size_t>(0, candidates.size() - 1)(rng)];
    const float saved = values[i];
    values[i] = saved + h;
    const double plus = Evaluate(volume, rays, options, f);
    values[i] = saved - h;
    const double minus = Evaluate(volume, rays, options, f);
    values[i] = saved;
    const double numeric = (plus - minus) / (2 * h);
    const double error = std::abs(numeric - analytic[i]) / std::max(std::abs(numeric), 1e-2);
    worst = std::max(worst, error);
  }
  return worst;
}

TEST(RayMarchTest, GridGradientMatchesFiniteDifferences) {
  const int d = 8;
  std::vector<float> grid = BlobGrid(d, 6.0f, 1);
  MarchVolume volume{kBoxMin, kBoxMax, grid.data(), d};
  const RayBatch rays = SomeRays(LookingAtBox({2.0, 0.7, 1.2}));
  MarchOptions options;
  options.step_m = 0.05f;
  const Functional f(rays.size(), 3);
  std::vector<float> grad(grid.size(), 0.0f);
  MarchBackward(volume, rays, options, f.g_rgb.data(), f.g_alpha.data(), grad.data(), nullptr);
  const double worst = WorstRelativeError(grid, grad, volume, rays, options, f, 40, 1e-2f, 5);
  EXPECT_LT(worst, 2e-2) << "analytic grid gradient disagrees with central differences";
}

TEST(RayMarchTest, WarpGradientMatchesFiniteDifferences) {
  const int d = 8, w = 4;
  std::vector<float> grid = AffineGrid(d);
  std::vector<float> warp = WarpField(w);
  MarchVolume volume{kBoxMin, kBoxMax, grid.data(), d, warp.data(), w};
  // Few rays: the sums of float outputs that the differences see stay precise.
  const RayBatch rays = SomeRays(LookingAtBox({-1.5, 1.6, 0.9}, 10, 12));
  MarchOptions options;
  options.step_m = 0.05f;
  const Functional f(rays.size(), 4);
  std::vector<float> grad_grid(grid.size(), 0.0f), grad_warp(warp.size(), 0.0f);
  MarchBackward(volume, rays, options, f.g_rgb.data(), f.g_alpha.data(), grad_grid.data(),
                grad_warp.data());
  EXPECT_LT(WorstRelativeError(grid, grad_grid, volume, rays, options, f, 30, 1e-2f, 6), 2e-2);
  EXPECT_LT(WorstRelativeError(warp, grad_warp, volume, rays, options, f, 30, 1e-3f, 7), 2e-2)
      << "analytic warp gradient disagrees with central differences";
}

TEST(RayMarchTest, EarlyTerminationKeepsGradientsConsistent) {
  const int d = 8;
  std::vector<float> grid = BlobGrid(d, 60.0f, 3);
  MarchVolume volume{kBoxMin, kBoxMax, grid.data(), d};
  const RayBatch rays = SomeRays(LookingAtBox({0.3, -2.0, 0.6}));
  MarchOptions options;
  options.step_m = 0.03f;
  options.min_transmittance = 1e-2f;
  const Functional f(rays.size(), 8);
  std::vector<float> grad(grid.size(), 0.0f);
  MarchBackward(volume, rays, options, f.g_rgb.data(), f.g_alpha.data(), grad.data(), nullptr);
  EXPECT_LT(WorstRelativeError(grid, grad, volume, rays, options, f, 30, 1e-3f, 9), 5e-2);
}

TEST(RayMarchTest, DensityOfAMillionStaysFiniteAndOpaque) {
  const int d = 8;
  std::vector<float> grid(static_cast<size_t>(d) * d * d * 4);
  for (size_t i = 0; i < grid.size(); i += 4) {
    grid[i] = 0.25f;
    grid[i + 1] = 0.5f;
    grid[i + 2] = 0.75f;
    grid[i + 3] = 1e6f;
  }
  MarchVolume volume{kBoxMin, kBoxMax, grid.data(), d};
  const RayBatch rays = SomeRays(LookingAtBox({2.0, 0.0, 0.5}));
  MarchOptions options;
  options.step_m = 0.02f;
  MarchOutputs out;
  MarchForward(volume, rays, options, &out);
  const Functional f(rays.size(), 11);
  std::vector<float> grad(grid.size(), 0.0f);
  MarchBackward(volume, rays, options, f.g_rgb.data(), f.g_alpha.data(), grad.data(), nullptr);
  int64_t hits = 0;
  for (int64_t r = 0; r < rays.size(); ++r) {
    ASSERT_TRUE(std::isfinite(out.alpha[r]) && std::isfinite(out.rgb[3 * r]) &&
                std::isfinite(out.depth[r]));
    if (rays.t_far[r] <= rays.t_near[r]) continue;
    // The first sample inside already absorbs everything. The grid is zero-padded, so that
    // sample's colour is the voxels' scaled by its interpolation weight: the ratios hold.
    if (out.alpha[r] > 0.999f) {
      ++hits;
      EXPECT_GT(out.rgb[3 * r], 0.01f);
      EXPECT_NEAR(out.rgb[3 * r + 1], 2 * out.rgb[3 * r], 1e-4f);
      EXPECT_NEAR(out.rgb[3 * r + 2], 3 * out.rgb[3 * r], 1e-4f);
    }
  }
  EXPECT_GT(hits, rays.size() / 4);
  for (float g : grad) ASSERT_TRUE(std::isfinite(g));
}

TEST(RayMarchTest, EmptyVolumeIsTransparentWithZeroGradientOnColour) {
  const int d = 8;
  std::vector<float> grid(static_cast<size_t>(d) * d * d * 4, 0.0f);
  for (size_t i = 0; i < grid.size(); i += 4) grid[i] = grid[i + 1] = grid[i + 2] = 0.7f;
  MarchVolume volume{kBoxMin, kBoxMax, grid.data(), d};
  const RayBatch rays = SomeRays(LookingAtBox({2.0, 1.0, 1.0}));
  MarchOptions options;
  options.step_m = 0.02f;
  MarchOutputs out;
  MarchForward(volume, rays, options, &out);
  for (int64_t r = 0; r < rays.size(); ++r) {
    EXPECT_EQ(out.alpha[r], 0.0f);
    EXPECT_EQ(out.rgb[3 * r], 0.0f);
  }
  const Functional f(rays.size(), 12);
  std::vector<float> grad(grid.size(), 0.0f);
  MarchBackward(volume, rays, options, f.g_rgb.data(), f.g_alpha.data(), grad.data(), nullptr);
  double colour = 0, density = 0;
  for (size_t i = 0; i < grad.size(); ++i) (i % 4 == 3 ? density : colour) += std::abs(grad[i]);
  EXPECT_EQ(colour, 0.0);   // no light is absorbed, so colour cannot matter
  EXPECT_GT(density, 0.0);  // but adding density would change the image
}

TEST(RayMarchTest, CameraInsideTheVolumeStartsAtItsCentre) {
  const int d = 8;
  std::vector<float> grid = BlobGrid(d, 4.0f, 13);
  MarchVolume volume{kBoxMin, kBoxMax, grid.data(), d};
  const CameraModel camera =
      CameraModel::Pinhole(10, 16, 16, CamFromWorldLookAt({0.1, 0.1, 0.5}, {1, 0.2, 0.5}));
  const RayBatch rays = SomeRays(camera);
  for (int64_t r = 0; r < rays.size(); ++r) {
    EXPECT_FLOAT_EQ(rays.t_near[r], 0.0f);  // clipped to the camera centre, not behind it
    EXPECT_GT(rays.t_far[r], 0.0f);
  }
  MarchOptions options;
  options.step_m = 0.02f;
  MarchOutputs out;
  MarchForward(volume, rays, options, &out);
  for (int64_t r = 0; r < rays.size(); ++r) {
    EXPECT_GT(out.alpha[r], 0.0f);
    EXPECT_LE(out.alpha[r], 1.0f);
    EXPECT_GT(out.samples[r], 0);
  }
}

TEST(RayMarchTest, FarAwayCameraSeesTheVolumeAsFromNearby) {
  const int d = 8;
  std::vector<float> grid = BlobGrid(d, 8.0f, 14);
  MarchVolume volume{kBoxMin, kBoxMax, grid.data(), d};
  MarchOptions options;
  options.step_m = 0.02f;
  // The same centre ray from 3 m and from 3 km: same colour and alpha, depth 1000x larger.
  const Eigen::Vector3d direction = Eigen::Vector3d(1, 0.2, 0.1).normalized();
  MarchOutputs near_out, far_out;
  for (double distance : {3.0, 3000.0}) {
    const CameraModel camera =
        LookingAtBox(Eigen::Vector3d(0, 0, 0.5) + distance * direction, 2, 1e3 * distance);
    Eigen::Matrix2Xd pixel(2, 1);
    pixel << 0.5, 0.5;
    RayBatch rays = CameraRays(camera, pixel, kBoxMin, kBoxMax);
    ASSERT_GT(rays.t_far[0], rays.t_near[0]);
    MarchForward(volume, rays, options, distance < 10 ? &near_out : &far_out);
  }
  EXPECT_NEAR(far_out.alpha[0], near_out.alpha[0], 5e-3);
  EXPECT_NEAR(far_out.rgb[0], near_out.rgb[0], 5e-3);
  EXPECT_TRUE(std::isfinite(far_out.depth[0]));
  EXPECT_GT(far_out.samples[0], 0);
}

TEST(RayMarchTest, VerySmallStepConvergesAndIsCounted) {
  const int d = 8;
  std::vector<float> grid = BlobGrid(d, 5.0f, 15);
  MarchVolume volume{kBoxMin, kBoxMax, grid.data(), d};
  Eigen::Matrix2Xd pixel(2, 1);
  pixel << 11.5, 12.0;
  const RayBatch rays = CameraRays(LookingAtBox({2.0, 0.5, 0.8}), pixel, kBoxMin, kBoxMax);
  MarchOptions fine, tiny, capped;
  fine.step_m = 1e-3f;
  tiny.step_m = 1e-5f;  // 1/12500 of a voxel: 10^5 samples on this ray
  capped.step_m = 1e-5f;
  capped.max_samples_per_ray = 1000;
  MarchOutputs a, b, c;
  MarchForward(volume, rays, fine, &a);
  MarchForward(volume, rays, tiny, &b);
  MarchForward(volume, rays, capped, &c);
  EXPECT_NEAR(a.alpha[0], b.alpha[0], 2e-3);
  EXPECT_NEAR(a.rgb[1], b.rgb[1], 2e-3);
  EXPECT_GT(b.samples[0], 50000);
  EXPECT_EQ(b.truncated_rays, 0);
  EXPECT_EQ(c.samples[0], 1000);
  EXPECT_EQ(c.truncated_rays, 1);
}

TEST(RayMarchTest, SkippingChangesNoPixelAndSavesSamples) {
  const int d = 16;
  std::vector<float> grid = BlobGrid(d, 30.0f, 16);
  // Empty outside a ball: the noise floor removed where the blob is faint.
  for (size_t i = 3; i < grid.size(); i += 4)
    if (grid[i] < 15.0f) grid[i] = 0.0f;
  MarchVolume volume{kBoxMin, kBoxMax, grid.data(), d};
  OccupancyGrid occupancy = OccupancyFromVolume(volume, 8, 0.0f);
  occupancy.Dilate(1);
  EXPECT_LT(occupancy.OccupiedCount(), 8 * 8 * 8);
  const RayBatch rays = SomeRays(LookingAtBox({2.0, -1.0, 1.3}, 32));
  MarchOptions options;
  options.step_m = 1.0f / d;
  MarchOutputs all, skipped;
  MarchForward(volume, rays, options, &all);
  volume.occupancy = &occupancy;
  MarchForward(volume, rays, options, &skipped);
  for (int64_t r = 0; r < rays.size(); ++r) {
    EXPECT_NEAR(skipped.alpha[r], all.alpha[r], 1e-6);
    EXPECT_NEAR(skipped.rgb[3 * r], all.rgb[3 * r], 1e-6);
  }
  EXPECT_LT(skipped.MeanSamples(), 0.8 * all.MeanSamples());
  // Evaluating the empty cells too costs the samples back and still changes no pixel.
  options.evaluate_empty_cells = true;
  MarchOutputs evaluated;
  MarchForward(volume, rays, options, &evaluated);
  EXPECT_NEAR(evaluated.MeanSamples(), all.MeanSamples(), 1e-9);
  for (int64_t r = 0; r < rays.size(); ++r) EXPECT_NEAR(evaluated.alpha[r], all.alpha[r], 1e-6);
}

// Playback's marcher against the training one: the same samples and the same image (to float
// rounding), with and without a warp, skipping or not.
TEST(RayMarchTest, PlaybackMarchMatchesTheTrainingMarcher) {
  const int d = 16;
  std::vector<float> grid = BlobGrid(d, 30.0f, 21);
  for (size_t i = 3; i < grid.size(); i += 4)
    if (grid[i] < 12.0f) grid[i] = 0.0f;
  std::vector<float> warp = WarpField(8);
  for (bool with_warp : {false, true}) {
    MarchVolume volume{kBoxMin, kBoxMax, grid.data(), d};
    if (with_warp) {
      volume.warp = warp.data();
      volume.warp_grid = 8;
    }
    // 16 cells: the 4x coarser level has 4 cells per axis, some of them wholly empty.
    OccupancyGrid occupancy = OccupancyFromVolume(volume, 16, 0.0f);
    occupancy.Dilate(1);
    ASSERT_LT(occupancy.OccupiedCount(), 16 * 16 * 16 / 2);
    volume.occupancy = &occupancy;
    const RayBatch rays = SomeRays(LookingAtBox({2.0, -1.0, 1.3}, 40, 45));
    for (bool evaluate_empty : {false, true}) {
      for (float min_transmittance : {0.0f, 1e-3f}) {
        SCOPED_TRACE(testing::Message() << "warp " << with_warp << ", evaluate empty "
                                        << evaluate_empty << ", min T " << min_transmittance);
        MarchOptions options;
        options.step_m = 0.7f / d;
        options.evaluate_empty_cells = evaluate_empty;
        options.min_transmittance = min_transmittance;
        MarchOutputs training, playback;
        MarchForward(volume, rays, options, &training);
        MarchPlayback(volume, rays, options, &playback);
        int64_t differing_counts = 0;
        double worst = 0;
        for (int64_t r = 0; r < rays.size(); ++r) {
          differing_counts += training.samples[r] != playback.samples[r];
          worst = std::max<double>(worst, std::abs(training.alpha[r] - playback.alpha[r]));
          for (int c = 0; c < 3; ++c)
            worst = std::max<double>(worst,
                                     std::abs(training.rgb[3 * r + c] - playback.rgb[3 * r + c]));
          worst = std::max<double>(worst, std::abs(training.depth[r] - playback.depth[r]));
        }
        EXPECT_EQ(differing_counts, 0);
        EXPECT_LT(worst, 2e-5);
        EXPECT_GT(training.MeanSamples() * rays.size(), 1000.0);
      }
    }
  }
}

// Baking the warped template onto one world grid: exact at the baked voxel centres; a render
// of the baked grid (border-padded, so that its outermost half voxel continues the warped
// template) within 45 dB PSNR of the warp + template render for a smooth volume at the
// template's resolution, closer at 1.5x; voxel-sized noise (the worst case for resampling)
// within 40 dB.
TEST(RayMarchTest, BakedVolumeRendersLikeTheWarpedTemplate) {
  const int d = 24;
  std::vector<float> smooth = BlobGrid(d, 20.0f, 5, 0.0f);
  std::vector<float> noisy = BlobGrid(d, 20.0f, 5);
  std::vector<float> warp = WarpField(12);
  MarchVolume volume{kBoxMin, kBoxMax, smooth.data(), d};
  volume.warp = warp.data();
  volume.warp_grid = 12;
  const BakedVolume baked = BakeVolume(volume, d);
  ASSERT_EQ(baked.grid, d);
  ASSERT_EQ(baked.rgba.size(), smooth.size());
  // At a baked voxel centre the baked value is the warped template's.
  for (const auto& [x, y, z] : {std::array<int, 3>{3, 7, 11}, std::array<int, 3>{12, 12, 12},
                                std::array<int, 3>{20, 1, 17}}) {
    RayBatch ray;
    ray.Resize(1);
    const Eigen::Vector3f u((x + 0.5f) / d, (y + 0.5f) / d, (z + 0.5f) / d);
    const Eigen::Vector3f p = kBoxMin + ((kBoxMax - kBoxMin).array() * u.array()).matrix();
    // A ray of one sample exactly at p, of step 1 m: alpha = 1 - exp(-sigma).
    ray.origin = {p.x() - 1.0f, p.y(), p.z()};
    ray.direction = {1.0f, 0.0f, 0.0f};
    ray.t_near = {1.0f};
    ray.t_far = {1.5f};
    MarchOptions options;
    options.step_m = 1.0f;
    MarchOutputs direct, from_baked;
    MarchPlayback(volume, ray, options, &direct);
    MarchPlayback(baked.View(), ray, options, &from_baked);
    ASSERT_EQ(direct.samples[0], 1);
    const float sigma = baked.rgba[4 * ((static_cast<size_t>(z) * d + y) * d + x) + 3];
    EXPECT_GT(sigma, 0.0f);
    EXPECT_NEAR(from_baked.alpha[0], 1.0f - std::exp(-sigma), 1e-5);
    EXPECT_NEAR(direct.alpha[0], from_baked.alpha[0], 1e-5);
  }
  const RayBatch rays =
      CameraRaysAllPixels(LookingAtBox({1.8, -1.2, 1.2}, 64, 70), kBoxMin, kBoxMax);
  MarchOptions options;
  options.step_m = 1.0f / d;
  options.min_transmittance = 1e-3f;
  // PSNR of colour and alpha over the rays either render covers.
  auto psnr_db = [&](const MarchVolume& warped, int bake_grid) {
    MarchOutputs direct, from_baked;
    const BakedVolume b = BakeVolume(warped, bake_grid);
    MarchPlayback(warped, rays, options, &direct);
    MarchPlayback(b.View(), rays, options, &from_baked);
    double squared = 0;
    int64_t covered = 0;
    for (int64_t r = 0; r < rays.size(); ++r) {
      if (direct.alpha[r] < 1.0f / 255 && from_baked.alpha[r] < 1.0f / 255) continue;
      ++covered;
      for (int c = 0; c < 3; ++c)
        squared += std::pow(direct.rgb[3 * r + c] - from_baked.rgb[3 * r + c], 2);
      squared += std::pow(direct.alpha[r] - from_baked.alpha[r], 2);
    }
    EXPECT_GT(covered, rays.size() / 5);  // the blob fills a good part of the view
    return 10 * std::log10(1.0 / (squared / (4.0 * covered)));
  };
  const double at_grid = psnr_db(volume, d);
  const double finer = psnr_db(volume, d * 3 / 2);
  EXPECT_GT(at_grid, 45.0);
  EXPECT_GT(finer, at_grid);
  MarchVolume rough = volume;
  rough.rgba = noisy.data();
  EXPECT_GT(psnr_db(rough, d), 40.0);
  std::printf(
      "baked against warp + template: smooth %.1f dB (1.5x: %.1f dB), voxel noise %.1f dB\n",
      at_grid, finer, psnr_db(rough, d));
  // Without a warp, baking at the grid's own resolution is a copy.
  MarchVolume plain{kBoxMin, kBoxMax, noisy.data(), d};
  EXPECT_EQ(BakeVolume(plain, d).rgba, noisy);
}

TEST(RayMarchTest, DistortedLensRaysReprojectToTheirPixels) {
  // Rays go through the mrcal model, distortion included: a point along each ray projects
  // back to the pixel it came from.
  const CameraModel camera("LENSMODEL_OPENCV8",
                           {300, 300, 63.5, 47.5, -0.3, 0.1, 0.001, -0.001, 0.02, 0, 0, 0}, 128, 96,
                           CamFromWorldLookAt({2.5, 0.3, 0.8}, {0, 0, 0.5}));
  Eigen::Matrix2Xd pixels(2, 4);
  pixels << 0, 127, 5, 64, 0, 95, 90, 40;
  const RayBatch rays = CameraRays(camera, pixels, kBoxMin, kBoxMax);
  for (int i = 0; i < 4; ++i) {
    const Eigen::Vector3d o(rays.origin[3 * i], rays.origin[3 * i + 1], rays.origin[3 * i + 2]);
    const Eigen::Vector3d dir(rays.direction[3 * i], rays.direction[3 * i + 1],
                              rays.direction[3 * i + 2]);
    Eigen::Vector2d back;
    ASSERT_TRUE(camera.ProjectWorld(o + 2.0 * dir, &back));
    EXPECT_LT((back - pixels.col(i)).norm(), 2e-3);
  }
}

}  // namespace
}  // namespace holocap::neural
