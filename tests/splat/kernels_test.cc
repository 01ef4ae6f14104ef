// The splatting kernels' backward passes against central finite differences, in double, on
// small scenes whose every Gaussian lies well inside the smooth part of the functions (no
// alpha clamp, no threshold, no tile edge crossing within a step).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <functional>
#include <random>
#include <vector>

#include "splat/kernels.h"

namespace holocap::splat {
namespace {

// A camera 2.5 m in front of the origin, looking at it along +z, slightly rotated.
PinholeCamera TestCamera(int width = 36, int height = 30) {
  PinholeCamera camera;
  camera.fx = 45;
  camera.fy = 43;
  camera.cx = 0.5 * (width - 1) + 1.3;
  camera.cy = 0.5 * (height - 1) - 0.7;
  camera.width = width;
  camera.height = height;
  const double angle = 0.2;
  const double r[9] = {std::cos(angle),  0, std::sin(angle), 0, 1, 0,
                       -std::sin(angle), 0, std::cos(angle)};
  for (int k = 0; k < 9; ++k) camera.cam_from_world_rotation[k] = r[k];
  camera.cam_from_world_translation[0] = 0.05;
  camera.cam_from_world_translation[1] = -0.03;
  camera.cam_from_world_translation[2] = 2.5;
  return camera;
}

GaussianArrays<double> RandomGaussians(int count, int degree, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> unit(-1, 1);
  GaussianArrays<double> g;
  g.sh_degree = degree;
  g.Resize(count);
  for (int i = 0; i < count; ++i) {
    for (int k = 0; k < 3; ++k) g.position[3 * i + k] = 0.35 * unit(rng);
    for (int k = 0; k < 4; ++k) g.rotation[4 * i + k] = unit(rng) + (k == 0 ? 1.5 : 0);
    for (int k = 0; k < 3; ++k) g.log_scale[3 * i + k] = std::log(0.06) + 0.4 * unit(rng);
    g.opacity[i] = 0.8 * unit(rng) - 0.3;
    for (int k = 0; k < g.coefficients(); ++k)
      for (int c = 0; c < 3; ++c) g.sh[(i * g.coefficients() + k) * 3 + c] = 0.3 * unit(rng);
  }
  return g;
}

// sum(weights . image) + sum(alpha_weights . alpha): a loss whose gradient is the weights.
struct LinearLoss {
  std::vector<double> color_weights, alpha_weights, background;
};

LinearLoss MakeLoss(const PinholeCamera& camera, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> unit(-1, 1);
  const size_t pixels = static_cast<size_t>(camera.width) * camera.height;
  LinearLoss loss;
  for (size_t k = 0; k < 3 * pixels; ++k) loss.color_weights.push_back(unit(rng));
  for (size_t k = 0; k < pixels; ++k) loss.alpha_weights.push_back(unit(rng));
  for (size_t k = 0; k < 3 * pixels; ++k) loss.background.push_back(0.5 + 0.4 * unit(rng));
  return loss;
}

// The forward pass of the whole chain over the loss's background.
struct Forward {
  ProjectedArrays<double> projected;
  std::vector<double> color, alpha;
  RasterState state;
};

Forward RunForward(const GaussianArrays<double>& g, const PinholeCamera& camera,
                   const RasterOptions& options, const LinearLoss& loss) {
  Forward forward;
  ProjectGaussians(g, camera, options, &forward.projected);
  const size_t pixels = static_cast<size_t>(camera.width) * camera.height;
  forward.color.resize(3 * pixels);
  forward.alpha.resize(pixels);
  RasterizeForward(forward.projected, camera, options, loss.background.data(), forward.color.data(),
                   forward.alpha.data(), static_cast<double*>(nullptr), &forward.state);
  return forward;
}

double Evaluate(const GaussianArrays<double>& g, const PinholeCamera& camera,
                const RasterOptions& options, const LinearLoss& loss) {
  const Forward forward = RunForward(g, camera, options, loss);
  double sum = 0;
  for (size_t k = 0; k < forward.color.size(); ++k) sum += loss.color_weights[k] * forward.color[k];
  for (size_t k = 0; k < forward.alpha.size(); ++k) sum += loss.alpha_weights[k] * forward.alpha[k];
  return sum;
}

// The analytic gradient of the whole chain, raw parameters.
GaussianArrays<double> Analytic(const GaussianArrays<double>& g, const PinholeCamera& camera,
                                const RasterOptions& options, const LinearLoss& loss) {
  const Forward forward = RunForward(g, camera, options, loss);
  const ProjectedArrays<double>& projected = forward.projected;
  const RasterState& state = forward.state;
  ProjectedGradients<double> pg;
  RasterizeBackward(projected, camera, options, state, loss.background.data(),
                    loss.color_weights.data(), loss.alpha_weights.data(), &pg);
  GaussianArrays<double> gradient;
  gradient.sh_degree = g.sh_degree;
  gradient.Resize(g.size());
  ProjectBackward(g, camera, options, projected, pg, &gradient);
  return gradient;
}

// Compares every parameter's analytic derivative with a central difference; returns the worst
// error relative to max(1, |derivative|) scale of the field.
// NOLINTNEXTLINE(performance-unnecessary-value-param): g is a copy, perturbed in place
void ExpectMatches(GaussianArrays<double> g, const PinholeCamera& camera,
                   const RasterOptions& options, const LinearLoss& loss) {
  const GaussianArrays<double> analytic = Analytic(g, camera, options, loss);
  struct Field {
    const char* name;
    std::vector<double> GaussianArrays<double>::*member;
  };
  const Field fields[] = {{"position", &GaussianArrays<double>::position},
                          {"rotation", &GaussianArrays<double>::rotation},
                          {"log_scale", &GaussianArrays<double>::log_scale},
                          {"opacity", &GaussianArrays<double>::opacity},
                          {"sh", &GaussianArrays<double>::sh}};
  const double h = 1e-6;
  for (const Field& field : fields) {
    std::vector<double>& values = g.*field.member;
    const std::vector<double>& derivative = analytic.*field.member;
    double scale = 1e-3;
    for (double d : derivative) scale = std::max(scale, std::abs(d));
    // A check of Gaussians that draw nothing would compare zeros with zeros.
    EXPECT_GT(scale, 1e-2) << field.name << ": no gradient at all";
    int checked = 0;
    for (size_t k = 0; k < values.size(); ++k) {
      const double saved = values[k];
      values[k] = saved + h;
      const double plus = Evaluate(g, camera, options, loss);
      values[k] = saved - h;
      const double minus = Evaluate(g, camera, options, loss);
      values[k] = saved;
      const double numeric = (plus - minus) / (2 * h);
      EXPECT_NEAR(derivative[k], numeric, 2e-5 * scale + 1e-7)
          << field.name << "[" << k << "] analytic " << derivative[k] << " numeric " << numeric;
      ++checked;
    }
    EXPECT_GT(checked, 0) << field.name;
  }
}

// The thresholds (alpha clamp, skip, early stop) are where the composite is not smooth; the
// checks keep every Gaussian clear of them.
RasterOptions SmoothOptions(int degree) {
  RasterOptions options;
  options.min_alpha = 0;
  options.max_alpha = 0.999f;
  options.min_transmittance = 0;
  options.active_sh_degree = degree;
  return options;
}

TEST(SplatGradient, WholeChainDegree0) {
  const PinholeCamera camera = TestCamera();
  ExpectMatches(RandomGaussians(6, 0, 1), camera, SmoothOptions(0), MakeLoss(camera, 2));
}

TEST(SplatGradient, WholeChainDegree3ViewDependentColour) {
  const PinholeCamera camera = TestCamera();
  ExpectMatches(RandomGaussians(5, 3, 3), camera, SmoothOptions(3), MakeLoss(camera, 4));
}

TEST(SplatGradient, DegreeBelowStorage) {
  const PinholeCamera camera = TestCamera();
  ExpectMatches(RandomGaussians(5, 3, 5), camera, SmoothOptions(1), MakeLoss(camera, 6));
}

TEST(SplatGradient, ClampedTangentOutsideTheView) {
  // A Gaussian beyond 1.3 x the half field of view: its Jacobian uses the clamped tangent.
  PinholeCamera camera = TestCamera();
  GaussianArrays<double> g = RandomGaussians(3, 1, 7);
  g.position[0] = 2.6;  // x/z ~ 1.0, limit 1.3 * 18 / 45 = 0.52
  g.log_scale[0] = g.log_scale[1] = g.log_scale[2] = std::log(0.9);
  ProjectedArrays<double> projected;
  ProjectGaussians(g, camera, SmoothOptions(1), &projected);
  ASSERT_GT(projected.radius[0], 0) << "the wide Gaussian must still reach the image";
  ExpectMatches(g, camera, SmoothOptions(1), MakeLoss(camera, 8));
}

TEST(SplatGradient, DefaultThresholdsAwayFromTheirEdges) {
  // With the thresholds on, the gradient still matches where no Gaussian sits on one.
  const PinholeCamera camera = TestCamera();
  RasterOptions options;
  options.active_sh_degree = 1;
  ExpectMatches(RandomGaussians(4, 1, 9), camera, options, MakeLoss(camera, 10));
}

TEST(SplatGradient, PhotometricLossL1AndSsim) {
  const int width = 23, height = 17;
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<double> unit(0, 1);
  std::vector<double> image(size_t{3} * width * height), target(image.size()),
      gradient(image.size());
  for (size_t k = 0; k < image.size(); ++k) {
    target[k] = unit(rng);
    image[k] = target[k] + (unit(rng) < 0.5 ? -1 : 1) * (0.05 + 0.2 * unit(rng));
  }
  PhotometricLoss(image.data(), target.data(), width, height, 0.2, gradient.data());
  const double h = 1e-6;
  for (size_t k = 0; k < image.size(); k += 7) {
    const double saved = image[k];
    image[k] = saved + h;
    const double plus = PhotometricLoss(image.data(), target.data(), width, height, 0.2,
                                        static_cast<double*>(nullptr));
    image[k] = saved - h;
    const double minus = PhotometricLoss(image.data(), target.data(), width, height, 0.2,
                                         static_cast<double*>(nullptr));
    image[k] = saved;
    EXPECT_NEAR(gradient[k], (plus - minus) / (2 * h), 1e-8) << "pixel value " << k;
  }
  // SSIM of an image with itself is 1 and L1 0: the loss is 0.
  EXPECT_NEAR(PhotometricLoss(target.data(), target.data(), width, height, 0.2,
                              static_cast<double*>(nullptr)),
              0.0, 1e-12);
}

TEST(SplatGradient, ForwardComposite) {
  // One opaque, flat-coloured Gaussian in front of another: the pixel under both is the front
  // one's colour times its alpha, plus what the back one and the background add behind it.
  PinholeCamera camera = TestCamera(32, 32);
  for (int k = 0; k < 9; ++k) camera.cam_from_world_rotation[k] = k % 4 == 0 ? 1 : 0;
  camera.cx = camera.cy = 15.5;
  camera.cam_from_world_translation[0] = camera.cam_from_world_translation[1] = 0;
  GaussianArrays<double> g;
  g.sh_degree = 0;
  g.Resize(2);
  for (int i = 0; i < 2; ++i) {
    g.rotation[4 * static_cast<size_t>(i)] = 1;
    for (int k = 0; k < 3; ++k) g.log_scale[3 * i + k] = std::log(0.2);
    g.position[3 * i + 2] = i == 0 ? -0.5 : 0.5;  // i = 0 nearer
  }
  g.opacity[0] = std::log(0.6 / 0.4);  // 0.6 at the centre
  g.opacity[1] = std::log(0.5 / 0.5);
  // Colour = 0.28209 sh + 0.5: front red 1 (BGR index 2), back blue 1 (index 0), the rest 0.5.
  g.sh[2] = 0.5 / 0.28209479177387814;
  g.sh[3 + 0] = 0.5 / 0.28209479177387814;
  RasterOptions options;
  options.active_sh_degree = 0;
  ProjectedArrays<double> projected;
  ProjectGaussians(g, camera, options, &projected);
  std::vector<double> color(size_t{3} * 32 * 32), alpha(size_t{32} * 32),
      background(size_t{3} * 32 * 32, 0.25);
  RasterState state;
  RasterizeForward(projected, camera, options, background.data(), color.data(), alpha.data(),
                   static_cast<double*>(nullptr), &state);
  // Both centres project near pixel (15.5, 15.5); sample (15, 15), 0.5 px off in each axis.
  const size_t p = 15 * 32 + 15;
  auto footprint = [&](int i) {
    const double* c = &projected.conic[3 * static_cast<size_t>(i)];
    const double dx = 15 - projected.mean2d[2 * static_cast<size_t>(i)],
                 dy = 15 - projected.mean2d[2 * static_cast<size_t>(i) + 1];
    return std::exp(-0.5 * (c[0] * dx * dx + c[2] * dy * dy) - c[1] * dx * dy);
  };
  const double a0 = 0.6 * footprint(0), a1 = 0.5 * footprint(1);
  EXPECT_NEAR(color[3 * p + 2], a0 * 1.0 + (1 - a0) * a1 * 0.5 + (1 - a0) * (1 - a1) * 0.25, 1e-9);
  EXPECT_NEAR(color[3 * p + 0], a0 * 0.5 + (1 - a0) * a1 * 1.0 + (1 - a0) * (1 - a1) * 0.25, 1e-9);
  EXPECT_NEAR(alpha[p], 1 - (1 - a0) * (1 - a1), 1e-9);
}

// The rasteriser playback runs (four or eight pixels at a time, a polynomial exp) against the
// scalar reference loop on a dense float scene that reaches every threshold (alpha skip, clamp,
// early stop) and partial tiles. Both round the footprint's exponent alike (no FMA); only exp
// differs, by a few ulp, so each alpha is within ~3e-7 relative and a pixel's colour or alpha,
// a sum over its layers of weights in [0, 1], within 1e-5 where both composite the same layers
// (depth, ~2.5 m and divided by the coverage, within 5e-5 m). A layer sitting within that
// rounding of a threshold may be taken by one loop and not the other (at most min_alpha = 0.004
// of change): such pixels, seen in last_contributor, must stay rare.
void ExpectVectorMatchesScalar(int lanes) {
  const PinholeCamera camera = TestCamera(83, 61);
  const GaussianArrays<double> source = RandomGaussians(2000, 3, 11);
  GaussianArrays<float> g;
  g.sh_degree = source.sh_degree;
  auto to_float = [](const std::vector<double>& from, std::vector<float>* to) {
    to->assign(from.begin(), from.end());
  };
  to_float(source.position, &g.position);
  to_float(source.rotation, &g.rotation);
  to_float(source.log_scale, &g.log_scale);
  to_float(source.opacity, &g.opacity);
  to_float(source.sh, &g.sh);
  for (float& opacity : g.opacity) opacity += 2.5f;        // 0.8 to 0.95: early stops happen
  for (float& log_scale : g.log_scale) log_scale += 0.7f;  // twice as large: they overlap
  const size_t pixels = static_cast<size_t>(camera.width) * camera.height;
  std::vector<float> background(3 * pixels, 0.3f);
  struct Render {
    std::vector<float> color, alpha, depth;
    RasterState state;
  };
  auto render = [&](bool vectorized) {
    RasterOptions options;
    options.vectorized = vectorized;
    options.lanes = lanes;
    ProjectedArrays<float> projected;
    ProjectGaussians(g, camera, options, &projected);
    Render r;
    r.color.resize(3 * pixels);
    r.alpha.resize(pixels);
    r.depth.resize(pixels);
    RasterizeForward(projected, camera, options, background.data(), r.color.data(), r.alpha.data(),
                     r.depth.data(), &r.state);
    return r;
  };
  const Render reference = render(false), vectorized = render(true);
  int stopped = 0, flipped = 0;
  double color_error = 0, alpha_error = 0, depth_error = 0;
  for (size_t q = 0; q < pixels; ++q) {
    stopped += reference.state.final_transmittance[q] < 1e-3f;
    if (reference.state.last_contributor[q] != vectorized.state.last_contributor[q]) {
      ++flipped;
      continue;
    }
    for (int c = 0; c < 3; ++c)
      color_error = std::max(
          color_error, double(std::abs(reference.color[3 * q + c] - vectorized.color[3 * q + c])));
    alpha_error = std::max(alpha_error, double(std::abs(reference.alpha[q] - vectorized.alpha[q])));
    depth_error = std::max(depth_error, double(std::abs(reference.depth[q] - vectorized.depth[q])));
  }
  EXPECT_GT(stopped, int(pixels / 20)) << "the scene must reach the early stop";
  EXPECT_LT(color_error, 1e-5);
  EXPECT_LT(alpha_error, 1e-5);
  // Depth (~2.5 m) is divided by the coverage: where a pixel is barely covered, its rounding grows.
  EXPECT_LT(depth_error, 5e-5);
  EXPECT_LE(flipped, int(pixels / 1000)) << "pixels whose layers differ";
  std::printf(
      "%d lanes against scalar: colour %.3g, alpha %.3g, depth %.3g m; %d of %zu pixels "
      "stopped early, %d composited other layers\n",
      lanes, color_error, alpha_error, depth_error, stopped, pixels, flipped);
  EXPECT_EQ(reference.state.entries, vectorized.state.entries);
}

TEST(SplatRaster, VectorMatchesScalarReference4Lanes) { ExpectVectorMatchesScalar(4); }

TEST(SplatRaster, VectorMatchesScalarReference8Lanes) {
#if defined(__x86_64__)
  if (!__builtin_cpu_supports("avx2")) GTEST_SKIP() << "this CPU has no AVX2: 4 lanes run";
#endif
  ExpectVectorMatchesScalar(8);
}

// The backward pass playback's training runs (lanes, ExpNonPositive, 1 / (1 - alpha) multiplied)
// against the scalar reference loop, on the dense scene above drawn by the vector forward pass,
// with a random gradient of colour and alpha. Both walk the same entries and pixels; each
// Gaussian's gradient is a sum of terms that differ by float rounding (a few ulp of exp, the
// reciprocal) added in another order, so every field agrees within 1e-4 of its largest value,
// and on the whole (the sum of differences against the sum of values) within 1e-5. A layer at a
// threshold (min_alpha, the clamp) within that rounding may count in one loop and not the
// other: the per-value bound has room for it.
void ExpectVectorBackwardMatchesScalar(int lanes) {
  const PinholeCamera camera = TestCamera(83, 61);
  const GaussianArrays<double> source = RandomGaussians(2000, 3, 12);
  GaussianArrays<float> g;
  g.sh_degree = source.sh_degree;
  g.position.assign(source.position.begin(), source.position.end());
  g.rotation.assign(source.rotation.begin(), source.rotation.end());
  g.log_scale.assign(source.log_scale.begin(), source.log_scale.end());
  g.opacity.assign(source.opacity.begin(), source.opacity.end());
  g.sh.assign(source.sh.begin(), source.sh.end());
  for (float& opacity : g.opacity) opacity += 2.5f;
  for (float& log_scale : g.log_scale) log_scale += 0.7f;
  const size_t pixels = static_cast<size_t>(camera.width) * camera.height;
  std::vector<float> background(3 * pixels, 0.3f), color(3 * pixels), alpha(pixels);
  std::vector<float> d_color(3 * pixels), d_alpha(pixels);
  std::mt19937_64 rng(13);
  std::uniform_real_distribution<float> unit(-1, 1);
  for (float& v : d_color) v = unit(rng);
  for (float& v : d_alpha) v = unit(rng);
  RasterOptions options;
  options.lanes = lanes;
  ProjectedArrays<float> projected;
  ProjectGaussians(g, camera, options, &projected);
  RasterState state;
  RasterizeForward(projected, camera, options, background.data(), color.data(), alpha.data(),
                   static_cast<float*>(nullptr), &state);
  ProjectedGradients<float> reference, vectorized;
  options.vectorized = false;
  RasterizeBackward(projected, camera, options, state, background.data(), d_color.data(),
                    d_alpha.data(), &reference);
  options.vectorized = true;
  RasterizeBackward(projected, camera, options, state, background.data(), d_color.data(),
                    d_alpha.data(), &vectorized);
  auto compare = [](const char* name, const std::vector<float>& a, const std::vector<float>& b) {
    ASSERT_EQ(a.size(), b.size());
    double largest = 0, worst = 0, total = 0, differences = 0;
    for (size_t k = 0; k < a.size(); ++k) {
      largest = std::max(largest, double(std::abs(a[k])));
      worst = std::max(worst, double(std::abs(a[k] - b[k])));
      total += std::abs(a[k]);
      differences += std::abs(a[k] - b[k]);
    }
    EXPECT_GT(largest, 0) << name;
    EXPECT_LT(worst, 1e-4 * largest) << name;
    EXPECT_LT(differences, 1e-5 * total) << name;
    std::printf("%s: largest %.3g, worst difference %.3g, on the whole %.3g\n", name, largest,
                worst, differences / total);
  };
  compare("mean2d", reference.mean2d, vectorized.mean2d);
  compare("conic", reference.conic, vectorized.conic);
  compare("color", reference.color, vectorized.color);
  compare("opacity", reference.opacity, vectorized.opacity);
}

TEST(SplatRaster, VectorBackwardMatchesScalarReference4Lanes) {
  ExpectVectorBackwardMatchesScalar(4);
}

TEST(SplatRaster, VectorBackwardMatchesScalarReference8Lanes) {
#if defined(__x86_64__)
  if (!__builtin_cpu_supports("avx2")) GTEST_SKIP() << "this CPU has no AVX2: 4 lanes run";
#endif
  ExpectVectorBackwardMatchesScalar(8);
}

// The loss in float (its blur's AVX2 clone where the CPU has AVX2) against the same in double,
// on an image whose size is no multiple of any vector width: the loss within 1e-6 and every
// gradient value within 1e-4 of the largest (float rounding of sums of 121 products).
TEST(SplatGradient, PhotometricLossFloatMatchesDouble) {
  const int width = 61, height = 37;
  std::mt19937_64 rng(17);
  std::uniform_real_distribution<double> unit(0, 1);
  std::vector<double> image(size_t{3} * width * height), target(image.size()),
      gradient(image.size());
  for (size_t k = 0; k < image.size(); ++k) {
    target[k] = unit(rng);
    image[k] = std::clamp(target[k] + 0.3 * (unit(rng) - 0.5), 0.0, 1.0);
  }
  const std::vector<float> image_f(image.begin(), image.end()),
      target_f(target.begin(), target.end());
  std::vector<float> gradient_f(image.size());
  const double loss =
      PhotometricLoss(image.data(), target.data(), width, height, 0.2, gradient.data());
  const double loss_f =
      PhotometricLoss(image_f.data(), target_f.data(), width, height, 0.2, gradient_f.data());
  EXPECT_NEAR(loss_f, loss, 1e-6);
  double largest = 0, worst = 0;
  for (size_t k = 0; k < image.size(); ++k) {
    largest = std::max(largest, std::abs(gradient[k]));
    worst = std::max(worst, std::abs(gradient[k] - gradient_f[k]));
  }
  EXPECT_GT(largest, 0);
  EXPECT_LT(worst, 1e-4 * largest);
}

// The depth sort: every tile's list runs front to back, equal depths in index order.
TEST(SplatRaster, TileListsFrontToBack) {
  const PinholeCamera camera = TestCamera(64, 48);
  GaussianArrays<double> g = RandomGaussians(600, 0, 5);
  for (int i = 0; i < 40; ++i)  // the same place: the same depth
    for (int k = 0; k < 3; ++k) g.position[3 * (i + 40) + k] = g.position[3 * i + k];
  RasterOptions options;
  ProjectedArrays<double> projected;
  ProjectGaussians(g, camera, options, &projected);
  RasterState state;
  std::vector<double> color(size_t{3} * 64 * 48);
  RasterizeForward(projected, camera, options, static_cast<const double*>(nullptr), color.data(),
                   static_cast<double*>(nullptr), static_cast<double*>(nullptr), &state);
  int64_t pairs = 0;
  for (size_t tile = 0; tile < state.tile_start.size(); ++tile) {
    for (int32_t e = state.tile_start[tile] + 1; e < state.tile_end[tile]; ++e) {
      const int32_t a = state.entries[e - 1], b = state.entries[e];
      const float da = float(projected.depth[a]), db = float(projected.depth[b]);
      EXPECT_TRUE(da < db || (da == db && a < b)) << "tile " << tile << " entry " << e;
      ++pairs;
    }
  }
  EXPECT_GT(pairs, 1000);
}

}  // namespace
}  // namespace holocap::splat
