// The splat stream's chunks: key frames and deltas encoded, serialised, parsed and decoded again,
// each value within half a quantisation step of the model's (the steps follow from the encoding),
// lossless chunks exact, unchanged Gaussians costing nothing in a delta, coarse motion steps
// whose error does not accumulate over frames, faint Gaussians pruned.
#include <gtest/gtest.h>

#include <cmath>
#include <numeric>
#include <random>

#include "core/error.h"
#include "playback/internal/web_stream.h"

namespace holocap {
namespace {

splat::Gaussians RandomGaussians(int64_t count, int degree, uint32_t seed) {
  std::mt19937 random(seed);
  std::uniform_real_distribution<float> unit(-1, 1);
  splat::Gaussians g;
  g.sh_degree = degree;
  g.Resize(count);
  for (int64_t i = 0; i < count; ++i) {
    for (int a = 0; a < 3; ++a) {
      g.position[3 * i + a] = 0.8f * unit(random) + (a == 2 ? 0.9f : 0.0f);
      g.log_scale[3 * i + a] = -5.0f + 1.5f * unit(random);
    }
    for (int c = 0; c < 4; ++c) g.rotation[4 * i + c] = unit(random);
    g.opacity[i] = 4 * unit(random);
    for (int k = 0; k < g.coefficients() * 3; ++k)
      g.sh[3 * i * g.coefficients() + k] = (k < 3 ? 1.5f : 0.3f) * unit(random);
  }
  return g;
}

web::SplatCodes RoundTrip(const web::Chunk& chunk, const web::SplatCodes* previous) {
  return web::DecodeSplats(web::ParseChunk(chunk.Serialise()), previous);
}

double Sigmoid(double x) { return 1 / (1 + std::exp(-x)); }

// The model's Gaussians in the stream's order (codes.order).
splat::Gaussians InStreamOrder(const splat::Gaussians& model, const web::SplatCodes& codes) {
  splat::Gaussians ordered;
  ordered.sh_degree = model.sh_degree;
  for (int64_t i : codes.order) ordered.AppendFrom(model, i);
  return ordered;
}

// Every decoded value against the model's, within half a step of its quantisation (the derived
// largest quaternion component: 2.5 steps, as it carries the errors of the other three).
void ExpectWithinSteps(const splat::Gaussians& model, const splat::Gaussians& decoded,
                       const web::SplatEncoding& e) {
  ASSERT_EQ(decoded.size(), model.size());
  const double levels16 = std::ldexp(1.0, e.position_bits) - 1;
  const double rotation_step = std::sqrt(2.0) / (std::ldexp(1.0, e.rotation_bits) - 1);
  const double scale_step =
      (e.log_scale_max - e.log_scale_min) / (std::ldexp(1.0, e.scale_bits) - 1);
  const double dc_step = (e.dc_max - e.dc_min) / (std::ldexp(1.0, e.dc_bits) - 1);
  const double rest_step = 2 * e.rest_max / (std::ldexp(1.0, e.rest_bits) - 1);
  const int k_model = model.coefficients(), k = decoded.coefficients();
  double worst[5] = {0, 0, 0, 0, 0};
  for (int64_t i = 0; i < model.size(); ++i) {
    for (int a = 0; a < 3; ++a) {
      const double step = (e.box_max[a] - e.box_min[a]) / levels16;
      worst[0] = std::max(worst[0],
                          std::abs(decoded.position[3 * i + a] - model.position[3 * i + a]) / step);
      worst[2] =
          std::max(worst[2], std::abs(decoded.log_scale[3 * i + a] - model.log_scale[3 * i + a]) /
                                 scale_step);
    }
    double q[4], norm = 0, dot = 0;
    for (int c = 0; c < 4; ++c)
      norm += double(model.rotation[4 * i + c]) * model.rotation[4 * i + c];
    for (int c = 0; c < 4; ++c) {
      q[c] = model.rotation[4 * i + c] / std::sqrt(norm);
      dot += q[c] * decoded.rotation[4 * i + c];
    }
    for (int c = 0; c < 4; ++c) {
      const double d = std::abs((dot < 0 ? -1 : 1) * decoded.rotation[4 * i + c] - q[c]);
      worst[1] = std::max(worst[1], d / rotation_step / 5);  // half a step is 0.5: 2.5 steps too
    }
    worst[3] =
        std::max(worst[3], std::abs(Sigmoid(decoded.opacity[i]) - Sigmoid(model.opacity[i])) * 255);
    for (int j = 0; j < 3 * k; ++j) {
      const double d = std::abs(decoded.sh[3 * i * k + j] - model.sh[3 * i * k_model + j]);
      worst[4] = std::max(worst[4], d / (j < 3 ? dc_step : rest_step));
    }
  }
  const char* names[5] = {"position", "rotation", "log-scale", "opacity", "colour"};
  for (int group = 0; group < 5; ++group) {
    std::printf("%-9s worst error %.3f of a step\n", names[group], worst[group]);
    EXPECT_LE(worst[group], 0.51) << names[group];  // and float32 rounding
  }
}

TEST(WebSplatTest, KeyFrameDecodesWithinHalfAStepOfEachAttribute) {
  const splat::Gaussians model = RandomGaussians(2000, 3, 1);
  for (const char* level : {"low", "medium", "high"}) {
    web::SplatEncoding e = web::SplatEncoding::For(web::QualityByName(level), 3);
    e.Include(model);
    web::SplatCodes codes;
    const web::Chunk chunk = web::EncodeSplats(model, 0, e, nullptr, {}, &codes);
    const web::SplatCodes decoded = RoundTrip(chunk, nullptr);
    ASSERT_EQ(decoded.records, codes.records) << level;
    const splat::Gaussians g = web::SplatsFromCodes(decoded, e);
    EXPECT_EQ(g.sh_degree, std::string(level) == "low"      ? 0
                           : std::string(level) == "medium" ? 1
                                                            : 3);
    std::printf("%s: %zu bytes for %lld Gaussians of degree %d\n", level, chunk.Serialise().size(),
                static_cast<long long>(model.size()), g.sh_degree);
    ExpectWithinSteps(InStreamOrder(model, codes), g, e);
  }
}

TEST(WebSplatTest, DeltaCarriesOnlyChangedAndAddedGaussians) {
  const splat::Gaussians first = RandomGaussians(1000, 2, 2);
  const splat::Gaussians extra = RandomGaussians(40, 2, 3);
  // The next frame: every third Gaussian removed, every fifth survivor moved 2 cm, 40 added.
  splat::Gaussians next;
  next.sh_degree = 2;
  std::vector<int64_t> origin;
  int64_t moved = 0;
  for (int64_t i = 0; i < first.size(); ++i) {
    if (i % 3 == 0) continue;
    next.AppendFrom(first, i);
    if (origin.size() % 5 == 0) {
      next.position[3 * origin.size()] += 0.02f;
      ++moved;
    }
    origin.push_back(i);
  }
  for (int64_t i = 0; i < extra.size(); ++i) {
    next.AppendFrom(extra, i);
    origin.push_back(-1);
  }
  web::SplatEncoding e = web::SplatEncoding::For(web::QualityByName("high"), 2);
  e.Include(first);
  e.Include(next);
  e.Include(extra);
  web::SplatCodes key_codes, delta_codes;
  const web::Chunk key = web::EncodeSplats(first, 0, e, nullptr, {}, &key_codes);
  const web::Chunk delta = web::EncodeSplats(next, 1, e, &key_codes, origin, &delta_codes);
  const web::SplatCodes previous = RoundTrip(key, nullptr);
  const web::SplatCodes decoded = RoundTrip(delta, &previous);
  EXPECT_EQ(decoded.records, delta_codes.records);
  EXPECT_EQ(delta.header.at("removed"), 334);
  EXPECT_EQ(delta.header.at("added"), 40);
  // Moves are position residuals, which every survivor has: only the added are stored whole.
  EXPECT_EQ(delta.header.at("stored").get<int64_t>(), 40);
  ExpectWithinSteps(InStreamOrder(next, delta_codes), web::SplatsFromCodes(decoded, e), e);
  const size_t key_bytes = key.Serialise().size(), delta_bytes = delta.Serialise().size();
  std::printf("key frame %zu bytes, delta (%lld moved, 40 added) %zu bytes\n", key_bytes,
              static_cast<long long>(moved), delta_bytes);
  EXPECT_LT(delta_bytes, key_bytes / 2);
  // The same frame again: nothing stored but the masks, zero residuals and the cells' zero motion.
  std::vector<int64_t> same(next.size());
  for (size_t i = 0; i < same.size(); ++i) same[i] = static_cast<int64_t>(i);
  web::SplatCodes again;
  const web::Chunk unchanged = web::EncodeSplats(next, 2, e, &delta_codes, same, &again);
  EXPECT_EQ(unchanged.header.at("stored"), 0);
  EXPECT_LT(unchanged.Serialise().size(), key_bytes / 20);
  EXPECT_EQ(RoundTrip(unchanged, &decoded).records, delta_codes.records);
  // A delta does not decode without the frame it follows, nor after another one.
  EXPECT_THROW(RoundTrip(delta, nullptr), Error);
  EXPECT_THROW(RoundTrip(delta, &decoded), Error);
}

// Twelve frames of Gaussians drifting a third of a motion step a frame, each its own way, coded
// with coarse motion steps: every frame's positions within the dead zone of the truth (the
// encoder codes against what the decoder holds, so the error does not grow), the frames with
// no bigger error than the first delta's, fainter Gaussians than the pruning left out.
TEST(WebSplatTest, CoarseMotionErrorStaysBoundedOverFrames) {
  splat::Gaussians frame = RandomGaussians(3000, 0, 5);
  for (int64_t i = 0; i < frame.size(); ++i) frame.opacity[i] = i % 10 == 0 ? -6.0f : 3.0f;
  web::SplatEncoding e = web::SplatEncoding::For(web::QualityByName("low"), 0);
  e.Include(frame);
  e.box_min -= Eigen::Vector3d::Constant(0.2);
  e.box_max += Eigen::Vector3d::Constant(0.2);
  e = web::SplatRung(e, 6);
  ASSERT_GT(e.motion_step, 4);
  ASSERT_GT(e.prune_opacity, Sigmoid(-6.0));
  ASSERT_LT(e.prune_opacity, Sigmoid(3.0));
  std::mt19937 random(6);
  std::uniform_real_distribution<float> unit(-1, 1);
  std::vector<float> drift(frame.position.size());
  const double code_m = (e.box_max.x() - e.box_min.x()) / (std::ldexp(1.0, e.position_bits) - 1);
  for (float& d : drift) d = static_cast<float>(unit(random) * e.motion_step * code_m / 3);
  std::vector<int64_t> same(frame.size());
  std::iota(same.begin(), same.end(), int64_t{0});
  web::SplatCodes held, codes;
  double first_delta_worst = 0;
  for (int f = 0; f < 12; ++f) {
    if (f > 0)
      for (size_t j = 0; j < drift.size(); ++j) frame.position[j] += drift[j];
    const web::Chunk chunk = web::EncodeSplats(frame, f, e, f == 0 ? nullptr : &held,
                                               f == 0 ? std::vector<int64_t>{} : same, &codes);
    const web::SplatCodes decoded = RoundTrip(chunk, f == 0 ? nullptr : &held);
    ASSERT_EQ(decoded.records, codes.records) << "frame " << f;
    EXPECT_EQ(decoded.count, frame.size() * 9 / 10) << "the faint tenth pruned";
    const splat::Gaussians ordered = InStreamOrder(frame, codes);
    const splat::Gaussians g = web::SplatsFromCodes(decoded, e);
    double worst = 0;
    for (size_t j = 0; j < g.position.size(); ++j)
      worst = std::max(worst, std::abs(double(g.position[j]) - ordered.position[j]) / code_m);
    // Opaque Gaussians: the dead zone (e.dead_zone steps) plus a code's rounding.
    const double bound = std::max(0.5, e.dead_zone) * e.motion_step + 1;
    std::printf("frame %d: %zu bytes, worst position error %.2f codes (bound %.1f)\n", f,
                chunk.Serialise().size(), worst, bound);
    EXPECT_LE(worst, bound) << "frame " << f;
    if (f == 1) first_delta_worst = worst;
    if (f > 1) {
      EXPECT_LE(worst, std::max(first_delta_worst, bound)) << "frame " << f;
    }
    held = decoded;
    held.order = codes.order;
  }
}

TEST(WebSplatTest, LosslessChunksAreExact) {
  const splat::Gaussians model = RandomGaussians(300, 3, 4);
  web::SplatEncoding e = web::SplatEncoding::For(web::QualityByName("lossless"), 3);
  e.Include(model);
  web::SplatCodes codes;
  const splat::Gaussians g = web::SplatsFromCodes(
      RoundTrip(web::EncodeSplats(model, 0, e, nullptr, {}, &codes), nullptr), e);
  EXPECT_EQ(g.position, model.position);
  EXPECT_EQ(g.rotation, model.rotation);
  EXPECT_EQ(g.log_scale, model.log_scale);
  EXPECT_EQ(g.opacity, model.opacity);
  EXPECT_EQ(g.sh, model.sh);
}

}  // namespace
}  // namespace holocap
