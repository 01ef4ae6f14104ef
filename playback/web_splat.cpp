// The splat stream's chunks (README "The stream format"): Gaussians quantised per attribute
// group, key frames in full and later frames as deltas of the frame before as decoded (kept and
// changed bits over the frame before's Gaussians, the changed ones' codes as byte differences
// from the frame before's, the added ones' codes).
#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <map>
#include <numeric>

#include "core/error.h"
#include "playback/internal/web_stream.h"

namespace holocap::web {
namespace {

constexpr double kInvSqrt2 = 0.70710678118654752;

template <typename T>
void Put(std::string* out, T value) {
  out->append(reinterpret_cast<const char*>(&value), sizeof(T));
}
template <typename T>
T Get(const char* at) {
  T value;
  std::memcpy(&value, at, sizeof(T));
  return value;
}

// Records of `width` bytes as byte planes (byte 0 of every record, then byte 1, ...) and back:
// the high bytes of neighbouring codes repeat, so deflate packs the planes tightly.
std::string ToPlanes(const std::string& records, size_t width) {
  const size_t n = width > 0 ? records.size() / width : 0;
  std::string planes(records.size(), '\0');
  for (size_t i = 0; i < n; ++i)
    for (size_t b = 0; b < width; ++b) planes[b * n + i] = records[i * width + b];
  return planes;
}
std::string FromPlanes(const std::string& planes, size_t width, size_t n, const char* what) {
  if (planes.size() != width * n)
    Fail("splat chunk section '", what, "' holds ", planes.size(), " bytes, not ", width * n);
  std::string records(planes.size(), '\0');
  for (size_t i = 0; i < n; ++i)
    for (size_t b = 0; b < width; ++b) records[i * width + b] = planes[b * n + i];
  return records;
}

float Sigmoid(float x) { return 1.0f / (1.0f + std::exp(-x)); }

// The unit quaternion (w, x, y, z) as its three smallest components on `bits` bits each and the
// index of the largest (made positive): index << 30 | a << 20 | b << 10 | c for 10 bits.
uint32_t SmallestThree(const float* raw, int bits) {
  double q[4];
  double norm = 0;
  for (int k = 0; k < 4; ++k) norm += double(raw[k]) * raw[k];
  norm = std::sqrt(norm);
  for (int k = 0; k < 4; ++k) q[k] = norm > 0 ? raw[k] / norm : (k == 0 ? 1 : 0);
  int largest = 0;
  for (int k = 1; k < 4; ++k)
    if (std::abs(q[k]) > std::abs(q[largest])) largest = k;
  const double sign = q[largest] < 0 ? -1 : 1;
  uint32_t code = static_cast<uint32_t>(largest) << 30;
  int shift = 2 * bits;
  for (int k = 0; k < 4; ++k) {
    if (k == largest) continue;
    code |= Quantise(sign * q[k], -kInvSqrt2, kInvSqrt2, bits) << shift;
    shift -= bits;
  }
  return code;
}
void FromSmallestThree(uint32_t code, int bits, float* q) {
  const int largest = static_cast<int>(code >> 30);
  const uint32_t mask = (1u << bits) - 1;
  double sum = 0;
  int shift = 2 * bits;
  for (int k = 0; k < 4; ++k) {
    if (k == largest) continue;
    q[k] = Dequantise((code >> shift) & mask, -kInvSqrt2, kInvSqrt2, bits);
    sum += double(q[k]) * q[k];
    shift -= bits;
  }
  q[largest] = static_cast<float>(std::sqrt(std::max(0.0, 1.0 - sum)));
}

// The opacity a code stands for, kept off 0 and 1 so that its logit is finite.
float OpacityOf(uint32_t code, int bits) {
  const double levels = std::ldexp(1.0, bits) - 1;
  const double o = std::clamp(code / levels, 0.5 / levels, 1 - 0.5 / levels);
  return static_cast<float>(std::log(o / (1 - o)));
}

void Widen(double value, double* lo, double* hi) {
  if (!std::isfinite(value)) return;
  *lo = std::min(*lo, value);
  *hi = std::max(*hi, value);
}

// Gaussian i's record of group g.
void AppendRecord(const splat::Gaussians& g, int64_t i, int group, const SplatEncoding& e,
                  std::string* out) {
  const int k_stored = g.coefficients(), k_streamed = splat::ShCoefficients(e.sh_degree);
  if (e.float32) {
    switch (group) {
      case 0:
        out->append(reinterpret_cast<const char*>(&g.position[3 * i]), 12);
        return;
      case 1:
        out->append(reinterpret_cast<const char*>(&g.rotation[4 * i]), 16);
        return;
      case 2:
        out->append(reinterpret_cast<const char*>(&g.log_scale[3 * i]), 12);
        return;
      case 3:
        Put<float>(out, g.opacity[i]);
        return;
      default:
        out->append(reinterpret_cast<const char*>(&g.sh[3 * i * k_stored]),
                    size_t{12} * k_streamed);
        return;
    }
  }
  switch (group) {
    case 0:
      for (int a = 0; a < 3; ++a)
        Put<uint16_t>(out, static_cast<uint16_t>(Quantise(g.position[3 * i + a], e.box_min[a],
                                                          e.box_max[a], e.position_bits)));
      return;
    case 1:
      Put<uint32_t>(out, SmallestThree(&g.rotation[4 * i], e.rotation_bits));
      return;
    case 2:
      for (int a = 0; a < 3; ++a)
        Put<uint8_t>(out, static_cast<uint8_t>(Quantise(g.log_scale[3 * i + a], e.log_scale_min,
                                                        e.log_scale_max, e.scale_bits)));
      return;
    case 3:
      Put<uint8_t>(out,
                   static_cast<uint8_t>(Quantise(Sigmoid(g.opacity[i]), 0, 1, e.opacity_bits)));
      return;
    default:
      for (int k = 0; k < k_streamed; ++k) {
        for (int c = 0; c < 3; ++c) {
          const float value = g.sh[(i * k_stored + k) * 3 + c];
          const uint32_t code = k == 0 ? Quantise(value, e.dc_min, e.dc_max, e.dc_bits)
                                       : Quantise(value, -e.rest_max, e.rest_max, e.rest_bits);
          Put<uint8_t>(out, static_cast<uint8_t>(code));
        }
      }
  }
}

bool Bit(const std::string& bits, size_t offset, int64_t i) {
  return (static_cast<uint8_t>(bits[offset + i / 8]) >> (i % 8)) & 1;
}
void SetBit(std::string* bits, size_t offset, int64_t i) {
  (*bits)[offset + i / 8] = static_cast<char>((*bits)[offset + i / 8] | (1 << (i % 8)));
}

}  // namespace

SplatEncoding SplatEncoding::For(const QualityLevel& quality, int model_degree) {
  SplatEncoding e;
  e.float32 = quality.splat_position_bits == 0;
  e.position_bits = e.float32 ? 0 : quality.splat_position_bits;
  e.sh_degree = std::clamp(e.float32 ? model_degree : quality.splat_sh_degree, 0, model_degree);
  e.rest_bits = quality.splat_rest_bits;
  e.motion_cell_bits = std::max(0, e.position_bits - 5);  // a 32nd of the box a side
  const double inf = std::numeric_limits<double>::infinity();
  e.box_min.setConstant(inf);
  e.box_max.setConstant(-inf);
  e.log_scale_min = e.dc_min = inf;
  e.log_scale_max = e.dc_max = -inf;
  e.rest_max = 0;
  return e;
}

void SplatEncoding::Include(const splat::Gaussians& g) {
  const int k_stored = g.coefficients(), k_streamed = splat::ShCoefficients(sh_degree);
  for (int64_t i = 0; i < g.size(); ++i) {
    for (int a = 0; a < 3; ++a) {
      Widen(g.position[3 * i + a], &box_min[a], &box_max[a]);
      Widen(g.log_scale[3 * i + a], &log_scale_min, &log_scale_max);
    }
    for (int k = 0; k < k_streamed; ++k) {
      for (int c = 0; c < 3; ++c) {
        const double value = g.sh[(i * k_stored + k) * 3 + c];
        if (k == 0)
          Widen(value, &dc_min, &dc_max);
        else if (std::isfinite(value))
          rest_max = std::max(rest_max, std::abs(value));
      }
    }
  }
}

namespace {

struct Rung {
  int position_bits, rotation_bits, value_bits;
  int step_at_12_bits;  // the motion step in codes of 12-bit positions
  int hold;
  double prune_opacity, dead_zone;
  int sh_degree;
};
constexpr Rung kRungs[kSplatRungs - 1] = {
    {14, 10, 8, 1, 1, 0.01, 0.5, 3}, {13, 9, 7, 2, 2, 0.02, 0.5, 1},
    {13, 8, 6, 4, 3, 0.02, 1.0, 0},  {12, 7, 5, 8, 3, 0.05, 1.0, 0},
    {12, 7, 5, 16, 6, 0.05, 1.0, 0}, {12, 7, 5, 32, 6, 0.05, 1.0, 0},
    {12, 7, 5, 64, 6, 0.10, 1.0, 0}, {12, 6, 5, 64, 8, 0.10, 2.0, 0},
    {12, 6, 5, 64, 8, 0.15, 2.0, 0}, {11, 6, 5, 128, 8, 0.15, 2.0, 0},
    {11, 6, 4, 128, 8, 0.15, 2.0, 0}};
const Rung& RungAt(int rung) { return kRungs[std::clamp(rung, 1, kSplatRungs - 1) - 1]; }

// Rung `r`'s motion step for positions of `position_bits` bits.
int MotionStep(const Rung& r, int position_bits) {
  return std::max(1, static_cast<int>(std::ldexp(r.step_at_12_bits, position_bits - 12)));
}

}  // namespace

SplatEncoding SplatRung(const SplatEncoding& level, int rung) {
  if (rung <= 0 || level.float32) return level;
  const Rung& r = RungAt(rung);
  SplatEncoding e = level;
  e.position_bits = std::min(level.position_bits, r.position_bits);
  e.rotation_bits = std::min(level.rotation_bits, r.rotation_bits);
  e.scale_bits = std::min(level.scale_bits, r.value_bits);
  e.opacity_bits = std::min(level.opacity_bits, r.value_bits);
  e.dc_bits = std::min(level.dc_bits, r.value_bits);
  e.rest_bits = std::min(level.rest_bits, r.value_bits);
  e.sh_degree = std::min(level.sh_degree, r.sh_degree);
  e.motion_cell_bits = std::max(0, e.position_bits - 5);
  e.motion_step = MotionStep(r, e.position_bits);
  e.hold = std::max(level.hold, r.hold);
  e.prune_opacity = std::max(level.prune_opacity, r.prune_opacity);
  e.dead_zone = std::max(level.dead_zone, r.dead_zone);
  return e;
}

SplatEncoding SplatDeltaRung(const SplatEncoding& level, int key_rung, int rung) {
  SplatEncoding key = SplatRung(level, key_rung);
  if (rung <= key_rung || level.float32) return key;
  SplatEncoding e = key;
  const Rung& r = RungAt(rung);
  e.motion_step = std::max(key.motion_step, MotionStep(r, key.position_bits));
  e.hold = std::max(key.hold, r.hold);
  e.prune_opacity = std::max(key.prune_opacity, r.prune_opacity);
  e.dead_zone = std::max(key.dead_zone, r.dead_zone);
  return e;
}

nlohmann::json SplatEncoding::ToJson() const {
  if (float32) return {{"values", "float32"}, {"sh_degree", sh_degree}};
  auto finite = [](double v) { return std::isfinite(v) ? v : 0.0; };
  return {{"values", "quantised"},
          {"position_bits", position_bits},
          {"box_min", {finite(box_min.x()), finite(box_min.y()), finite(box_min.z())}},
          {"box_max", {finite(box_max.x()), finite(box_max.y()), finite(box_max.z())}},
          {"rotation_bits", rotation_bits},
          {"scale_bits", scale_bits},
          {"log_scale_min", finite(log_scale_min)},
          {"log_scale_max", finite(log_scale_max)},
          {"opacity_bits", opacity_bits},
          {"sh_degree", sh_degree},
          {"dc_bits", dc_bits},
          {"dc_min", finite(dc_min)},
          {"dc_max", finite(dc_max)},
          {"rest_bits", rest_bits},
          {"rest_max", rest_max},
          {"motion_cell_bits", motion_cell_bits},
          {"motion_step", motion_step},
          {"hold", hold},
          {"prune_opacity", prune_opacity},
          {"dead_zone", dead_zone}};
}

SplatEncoding SplatEncoding::FromJson(const nlohmann::json& j) {
  SplatEncoding e;
  try {
    e.sh_degree = j.at("sh_degree").get<int>();
    if (e.sh_degree < 0 || e.sh_degree > splat::kMaxShDegree)
      Fail("splat chunk: spherical-harmonic degree ", e.sh_degree);
    e.float32 = j.at("values") == "float32";
    if (e.float32) return e;
    e.position_bits = j.at("position_bits");
    for (int a = 0; a < 3; ++a) {
      e.box_min[a] = j.at("box_min").at(a);
      e.box_max[a] = j.at("box_max").at(a);
    }
    e.rotation_bits = j.at("rotation_bits");
    e.scale_bits = j.at("scale_bits");
    e.log_scale_min = j.at("log_scale_min");
    e.log_scale_max = j.at("log_scale_max");
    e.opacity_bits = j.at("opacity_bits");
    e.dc_bits = j.at("dc_bits");
    e.dc_min = j.at("dc_min");
    e.dc_max = j.at("dc_max");
    e.rest_bits = j.at("rest_bits");
    e.rest_max = j.at("rest_max");
    e.motion_cell_bits = j.at("motion_cell_bits");
    e.motion_step = j.at("motion_step");
    e.hold = j.at("hold");
    e.prune_opacity = j.value("prune_opacity", 0.0);
    e.dead_zone = j.value("dead_zone", 0.5);
  } catch (const nlohmann::json::exception& error) {
    Fail("splat chunk: bad encoding (", error.what(), ")");
  }
  for (int bits : {e.scale_bits, e.opacity_bits, e.dc_bits, e.rest_bits})
    if (bits < 1 || bits > 8) Fail("splat chunk: ", bits, "-bit codes in a byte");
  if (e.position_bits < 1 || e.position_bits > 16 || e.rotation_bits < 1 || e.rotation_bits > 10)
    Fail("splat chunk: bad position or rotation bits");
  if (e.motion_cell_bits < 0 || e.motion_cell_bits > 16 || e.motion_step < 1 ||
      e.motion_step > 4096 || e.hold < 0)
    Fail("splat chunk: bad motion cells, motion step or hold");
  return e;
}

std::array<size_t, kSplatGroups> SplatEncoding::RecordBytes() const {
  const size_t k = static_cast<size_t>(splat::ShCoefficients(sh_degree));
  if (float32) return {12, 16, 12, 4, 12 * k};
  return {6, 4, 3, 1, 3 * k};
}

SplatCodes QuantiseSplats(const splat::Gaussians& g, const SplatEncoding& e) {
  SplatCodes codes;
  codes.count = g.size();
  for (int group = 0; group < kSplatGroups; ++group) {
    codes.records[group].reserve(e.RecordBytes()[group] * g.size());
    for (int64_t i = 0; i < g.size(); ++i) AppendRecord(g, i, group, e, &codes.records[group]);
  }
  return codes;
}

splat::Gaussians SplatsFromCodes(const SplatCodes& codes, const SplatEncoding& e) {
  splat::Gaussians g;
  g.sh_degree = e.sh_degree;
  g.Resize(codes.count);
  const auto widths = e.RecordBytes();
  for (int group = 0; group < kSplatGroups; ++group) {
    if (codes.records[group].size() != widths[group] * codes.count)
      Fail("splat codes of group ", kSplatGroupNames[group], " do not match their count");
  }
  const int k = g.coefficients();
  if (e.float32) {
    std::vector<float>* fields[kSplatGroups] = {&g.position, &g.rotation, &g.log_scale, &g.opacity,
                                                &g.sh};
    for (int group = 0; group < kSplatGroups; ++group)
      std::memcpy(fields[group]->data(), codes.records[group].data(), codes.records[group].size());
    return g;
  }
  const auto& [position, rotation, scale, opacity, color] = codes.records;
  for (int64_t i = 0; i < codes.count; ++i) {
    for (int a = 0; a < 3; ++a) {
      g.position[3 * i + a] = Dequantise(Get<uint16_t>(&position[6 * i + 2 * int64_t{a}]),
                                         e.box_min[a], e.box_max[a], e.position_bits);
      g.log_scale[3 * i + a] = Dequantise(static_cast<uint8_t>(scale[3 * i + a]), e.log_scale_min,
                                          e.log_scale_max, e.scale_bits);
    }
    FromSmallestThree(Get<uint32_t>(&rotation[4 * i]), e.rotation_bits, &g.rotation[4 * i]);
    g.opacity[i] = OpacityOf(static_cast<uint8_t>(opacity[i]), e.opacity_bits);
    for (int j = 0; j < 3 * k; ++j) {
      const uint8_t code = static_cast<uint8_t>(color[3 * i * k + j]);
      g.sh[3 * i * k + j] = j < 3 ? Dequantise(code, e.dc_min, e.dc_max, e.dc_bits)
                                  : Dequantise(code, -e.rest_max, e.rest_max, e.rest_bits);
    }
  }
  return g;
}

namespace {

uint16_t Zigzag16(int32_t v) { return static_cast<uint16_t>(v >= 0 ? 2 * v : -2 * v - 1); }
int32_t Unzigzag16(uint16_t z) {
  return (z & 1) != 0 ? -static_cast<int32_t>((z + 1) / 2) : static_cast<int32_t>(z / 2);
}
uint16_t PositionCode(const std::string& position, int64_t i, int a) {
  return Get<uint16_t>(&position[6 * i + 2 * int64_t{a}]);
}

// Gaussians (indices into `position`'s records) sorted by the Morton code of their positions, so
// that neighbours in the stream are neighbours in space.
void MortonSort(const std::string& position, std::vector<int64_t>* indices) {
  std::vector<std::pair<uint64_t, int64_t>> keyed;
  keyed.reserve(indices->size());
  for (int64_t i : *indices) {
    uint64_t code = 0;
    for (int b = 15; b >= 0; --b)
      for (int a = 0; a < 3; ++a) code = code << 1 | ((PositionCode(position, i, a) >> b) & 1u);
    keyed.emplace_back(code, i);
  }
  std::stable_sort(keyed.begin(), keyed.end(),
                   [](const auto& x, const auto& y) { return x.first < y.first; });
  for (size_t k = 0; k < keyed.size(); ++k) (*indices)[k] = keyed[k].second;
}

// Position records (6 bytes: three 16-bit codes) as each code's zigzagged difference (modulo
// 2^16) from the record before's (the first from 0), appended to `out`; and back.
void AppendChained(const std::string& records, std::string* out) {
  uint16_t before[3] = {0, 0, 0};
  for (size_t at = 0; at + 6 <= records.size(); at += 6) {
    for (int a = 0; a < 3; ++a) {
      const uint16_t code = Get<uint16_t>(&records[at + 2 * static_cast<size_t>(a)]);
      Put<uint16_t>(out, Zigzag16(static_cast<int16_t>(static_cast<uint16_t>(code - before[a]))));
      before[a] = code;
    }
  }
}
std::string Unchained(const std::string& chained, size_t from) {
  std::string records;
  uint16_t before[3] = {0, 0, 0};
  for (size_t at = from; at + 6 <= chained.size(); at += 6) {
    for (int a = 0; a < 3; ++a) {
      before[a] = static_cast<uint16_t>(
          before[a] + Unzigzag16(Get<uint16_t>(&chained[at + 2 * static_cast<size_t>(a)])));
      Put<uint16_t>(&records, before[a]);
    }
  }
  return records;
}

// The motion cell of a position record: its codes' cells of 2^bits codes a side.
uint64_t CellOf(const std::string& position, int64_t i, int bits) {
  return (uint64_t{PositionCode(position, i, 0)} >> bits) << 32 |
         (uint64_t{PositionCode(position, i, 1)} >> bits) << 16 |
         (uint64_t{PositionCode(position, i, 2)} >> bits);
}

// Whether Gaussian i's group `group` (not position) moved beyond the encoding's hold from what
// the decoder holds (record `from` of `before`).
bool Moved(const std::string& now, int64_t i, const std::string& before, int64_t from, int group,
           size_t width, const SplatEncoding& e) {
  if (now.compare(i * width, width, before, from * width, width) == 0) return false;
  if (e.float32 || e.hold == 0) return true;
  if (group == 1) {
    float a[4], b[4];
    FromSmallestThree(Get<uint32_t>(&now[4 * i]), e.rotation_bits, a);
    FromSmallestThree(Get<uint32_t>(&before[4 * from]), e.rotation_bits, b);
    const double dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3];
    const double sign = dot < 0 ? -1 : 1,
                 step = 2 * kInvSqrt2 / (std::ldexp(1.0, e.rotation_bits) - 1);
    for (int k = 0; k < 4; ++k)
      if (std::abs(a[k] - sign * b[k]) > e.hold * step) return true;
    return false;
  }
  for (size_t b = 0; b < width; ++b) {
    const int d =
        static_cast<uint8_t>(now[i * width + b]) - static_cast<uint8_t>(before[from * width + b]);
    if (std::abs(d) > e.hold) return true;
  }
  return false;
}

// A position in code units of the encoding's box (unrounded, clamped to the codes' range).
double CodeUnits(double value, double lo, double hi, int bits) {
  const double levels = std::ldexp(1.0, bits) - 1;
  return hi > lo ? std::clamp((value - lo) / (hi - lo), 0.0, 1.0) * levels : 0.0;
}

// A key frame's sections: the streamed Gaussians (Morton order where quantised), positions
// chained from the Gaussian before, every other group as it is.
void AddKeyFrameSections(const SplatCodes& all, const std::array<size_t, kSplatGroups>& widths,
                         const std::vector<bool>& streamed, bool quantised, SplatCodes* codes,
                         Chunk* chunk) {
  for (int64_t i = 0; i < static_cast<int64_t>(streamed.size()); ++i)
    if (streamed[i]) codes->order.push_back(i);
  if (quantised) MortonSort(all.records[0], &codes->order);
  for (int group = 0; group < kSplatGroups; ++group)
    for (int64_t i : codes->order)
      codes->records[group].append(all.records[group], i * widths[group], widths[group]);
  std::string position = codes->records[0];
  if (quantised) {
    position.clear();
    AppendChained(codes->records[0], &position);
  }
  chunk->AddSection(kSplatGroupNames[0], ToPlanes(position, widths[0]), "deflate");
  for (int group = 1; group < kSplatGroups; ++group)
    chunk->AddSection(kSplatGroupNames[group], ToPlanes(codes->records[group], widths[group]),
                      "deflate");
}

// The stream's place (slot) of each of the model's Gaussians of the frame before (-1: not
// streamed), after checking that frame's codes hold its count.
std::vector<int64_t> SlotsOf(const SplatCodes& previous,
                             const std::array<size_t, kSplatGroups>& widths) {
  const int64_t n = previous.count;
  for (int group = 0; group < kSplatGroups; ++group)
    if (previous.records[group].size() != widths[group] * n)
      Fail("a splat delta's frame before does not match its count");
  std::vector<int64_t> slot_of;
  if (previous.order.empty()) {
    slot_of.resize(n);
    std::iota(slot_of.begin(), slot_of.end(), int64_t{0});
  } else {
    if (static_cast<int64_t>(previous.order.size()) != n) Fail("a splat delta's order");
    slot_of.assign(*std::max_element(previous.order.begin(), previous.order.end()) + 1, -1);
    for (int64_t s = 0; s < n; ++s) slot_of[previous.order[s]] = s;
  }
  return slot_of;
}

// Each motion cell's mean motion (code units, rounded) over the survivors (slot in the frame
// before, Gaussian now) whose frame-before position lies in it, written to `bytes` (zigzag, 2
// bytes an axis, in the cells' order); `target`: each survivor's position now in code units.
std::map<uint64_t, std::array<int32_t, 3>> CellMotion(
    const splat::Gaussians& gaussians, const SplatEncoding& e, const std::string& before_position,
    const std::vector<std::pair<int64_t, int64_t>>& survivors,
    std::vector<std::array<double, 3>>* target, std::string* bytes) {
  std::map<uint64_t, std::array<double, 4>> cells;  // sums of motion (codes) and the count
  for (size_t k = 0; k < survivors.size(); ++k) {
    const auto [slot, i] = survivors[k];
    auto& cell = cells[CellOf(before_position, slot, e.motion_cell_bits)];
    for (int a = 0; a < 3; ++a) {
      (*target)[k][a] =
          CodeUnits(gaussians.position[3 * i + a], e.box_min[a], e.box_max[a], e.position_bits);
      cell[a] += (*target)[k][a] - PositionCode(before_position, slot, a);
    }
    cell[3] += 1;
  }
  std::map<uint64_t, std::array<int32_t, 3>> motion;
  for (const auto& [key, sum] : cells) {
    auto& m = motion[key];
    for (int a = 0; a < 3; ++a) {
      m[a] = static_cast<int32_t>(std::clamp<double>(std::lround(sum[a] / sum[3]), -32767, 32767));
      Put<uint16_t>(bytes, Zigzag16(m[a]));
    }
  }
  return motion;
}

}  // namespace

Chunk EncodeSplats(const splat::Gaussians& gaussians, int64_t frame, const SplatEncoding& e,
                   const SplatCodes* previous, const std::vector<int64_t>& origin,
                   SplatCodes* codes) {
  const SplatCodes all = QuantiseSplats(gaussians, e);
  const auto widths = e.RecordBytes();
  const bool quantised = !e.float32;
  Chunk chunk;
  chunk.header = {{"kind", "splats"},
                  {"frame", frame},
                  {"key", previous == nullptr},
                  {"count", gaussians.size()},
                  {"stored", gaussians.size()},
                  {"encoding", e.ToJson()},
                  {"sections", nlohmann::json::array()}};
  // The Gaussians streamed: all but those fainter than the encoding prunes.
  std::vector<bool> streamed(gaussians.size(), true);
  int64_t count = gaussians.size();
  if (!e.float32 && e.prune_opacity > 0) {
    for (int64_t i = 0; i < gaussians.size(); ++i) {
      streamed[i] = Sigmoid(gaussians.opacity[i]) >= e.prune_opacity;
      count -= streamed[i] ? 0 : 1;
    }
  }
  chunk.header["count"] = count;
  codes->count = count;
  codes->order.clear();
  for (auto& records : codes->records) records.clear();
  auto append = [&](int group, int64_t i) {
    codes->records[group].append(all.records[group], i * widths[group], widths[group]);
  };
  if (previous == nullptr) {
    AddKeyFrameSections(all, widths, streamed, quantised, codes, &chunk);
    return chunk;
  }
  if (static_cast<int64_t>(origin.size()) != gaussians.size())
    Fail("a splat delta needs one origin per Gaussian");
  const int64_t n = previous->count;
  const std::vector<int64_t> slot_of = SlotsOf(*previous, widths);
  std::vector<std::pair<int64_t, int64_t>> survivors;  // (slot, i)
  std::vector<int64_t> added;
  int64_t last = -1;
  for (int64_t i = 0; i < gaussians.size(); ++i) {
    const int64_t from = origin[i];
    if (from >= 0) {
      if (from <= last) Fail("a splat delta's survivors must keep their order");
      last = from;
    }
    if (!streamed[i]) continue;
    // One the frame before did not stream (pruned) is added again.
    const int64_t slot =
        from >= 0 && from < static_cast<int64_t>(slot_of.size()) ? slot_of[from] : -1;
    if (slot < 0)
      added.push_back(i);
    else
      survivors.emplace_back(slot, i);
  }
  std::sort(survivors.begin(), survivors.end());
  if (quantised) MortonSort(all.records[0], &added);
  for (const auto& [slot, i] : survivors) codes->order.push_back(i);
  codes->order.insert(codes->order.end(), added.begin(), added.end());

  const size_t mask_bytes = static_cast<size_t>((n + 7) / 8);
  // Kept bits, then one changed bit per group, each over the frame before's Gaussians.
  std::string masks((1 + kSplatGroups) * mask_bytes, '\0');
  std::array<std::string, kSplatGroups> stored;
  int64_t changed_any = 0;
  // Quantised positions: the motion of the cells, then each survivor's residual.
  const std::string& before_position = previous->records[0];
  std::vector<std::array<double, 3>> target(survivors.size());
  std::string motion_bytes;
  const std::map<uint64_t, std::array<int32_t, 3>> motion =
      quantised ? CellMotion(gaussians, e, before_position, survivors, &target, &motion_bytes)
                : std::map<uint64_t, std::array<int32_t, 3>>{};
  const int32_t top = (int32_t{1} << e.position_bits) - 1;
  for (size_t k = 0; k < survivors.size(); ++k) {
    const auto [slot, i] = survivors[k];
    SetBit(&masks, 0, slot);
    bool changed = false;
    for (int group = 0; group < kSplatGroups; ++group) {
      const size_t w = widths[group];
      if (group == 0 && quantised) {
        const auto& m = motion.at(CellOf(before_position, slot, e.motion_cell_bits));
        // Still (no residual) while the cell's motion leaves it within the dead zone.
        const double widen = std::clamp(0.5 / Sigmoid(gaussians.opacity[i]), 1.0, 8.0);
        bool still = true;
        for (int a = 0; a < 3; ++a)
          still = still && std::abs(target[k][a] - PositionCode(before_position, slot, a) - m[a]) <=
                               e.dead_zone * e.motion_step * widen;
        for (int a = 0; a < 3; ++a) {
          const int32_t predicted = PositionCode(before_position, slot, a) + m[a];
          const auto r =
              still ? 0
                    : static_cast<int32_t>(std::clamp<double>(
                          std::lround((target[k][a] - predicted) / e.motion_step), -32767, 32767));
          Put<uint16_t>(&stored[0], Zigzag16(r));
          Put<uint16_t>(&codes->records[0],
                        static_cast<uint16_t>(std::clamp(predicted + r * e.motion_step, 0, top)));
        }
        continue;
      }
      if (!Moved(all.records[group], i, previous->records[group], slot, group, w, e)) {
        codes->records[group].append(previous->records[group], slot * w, w);
        continue;
      }
      SetBit(&masks, (1 + group) * mask_bytes, slot);
      append(group, i);
      // Each byte as its difference (modulo 256) from the frame before's: a small move leaves
      // small numbers, which deflate packs tighter than the codes.
      for (size_t b = 0; b < w; ++b)
        stored[group].push_back(static_cast<char>(all.records[group][i * w + b] -
                                                  previous->records[group][slot * w + b]));
      changed = true;
    }
    changed_any += changed;
  }
  std::string added_position;
  for (int64_t i : added) append(0, i);
  for (int group = 1; group < kSplatGroups; ++group)
    for (int64_t i : added) {
      append(group, i);
      stored[group].append(all.records[group], i * widths[group], widths[group]);
    }
  const std::string added_records =
      codes->records[0].substr(widths[0] * survivors.size(), std::string::npos);
  if (quantised)
    AppendChained(added_records, &stored[0]);
  else
    stored[0] += added_records;
  chunk.header["previous"] = n;
  chunk.header["added"] = added.size();
  chunk.header["removed"] = n - static_cast<int64_t>(survivors.size());
  chunk.header["stored"] = changed_any + static_cast<int64_t>(added.size());
  chunk.AddSection("masks", masks, "deflate");
  if (quantised) {
    chunk.header["cells"] = motion.size();
    chunk.AddSection("motion", ToPlanes(motion_bytes, 6), "deflate");
  }
  for (int group = 0; group < kSplatGroups; ++group)
    chunk.AddSection(kSplatGroupNames[group], ToPlanes(stored[group], widths[group]), "deflate");
  return chunk;
}

SplatCodes DecodeSplats(const Chunk& chunk, const SplatCodes* previous) {
  const nlohmann::json& h = chunk.header;
  if (h.value("kind", "") != "splats") Fail("not a splat chunk");
  const SplatEncoding e = SplatEncoding::FromJson(h.at("encoding"));
  const bool quantised = !e.float32;
  const auto widths = e.RecordBytes();
  SplatCodes codes;
  codes.count = h.at("count").get<int64_t>();
  if (codes.count < 0) Fail("splat chunk: negative count");
  if (h.at("key").get<bool>()) {
    for (int group = 0; group < kSplatGroups; ++group) {
      const char* name = kSplatGroupNames[group];
      codes.records[group] =
          FromPlanes(SectionBytes(chunk, name), widths[group], codes.count, name);
    }
    if (quantised) codes.records[0] = Unchained(codes.records[0], 0);
    return codes;
  }
  const int64_t n = h.at("previous").get<int64_t>(), added = h.at("added").get<int64_t>();
  if (previous == nullptr || previous->count != n)
    Fail("splat delta of a frame of ", n, " Gaussians does not follow the frame before (",
         previous == nullptr ? int64_t{-1} : previous->count, ")");
  const size_t mask_bytes = static_cast<size_t>((n + 7) / 8);
  const std::string masks = SectionBytes(chunk, "masks");
  if (masks.size() != (1 + kSplatGroups) * mask_bytes) Fail("splat delta: masks cut short");
  int64_t survivors = 0;
  for (int64_t i = 0; i < n; ++i) survivors += Bit(masks, 0, i);
  if (added < 0 || survivors + added != codes.count)
    Fail("splat delta: survivors and added do not make count");
  for (int group = 0; group < kSplatGroups; ++group)
    if (previous->records[group].size() != widths[group] * n)
      Fail("splat delta: the frame before's codes");
  std::map<uint64_t, std::array<int32_t, 3>> motion;
  if (quantised) {
    const std::string& before = previous->records[0];
    for (int64_t i = 0; i < n; ++i)
      if (Bit(masks, 0, i)) motion[CellOf(before, i, e.motion_cell_bits)];
    const int64_t cells = h.at("cells").get<int64_t>();
    if (cells != static_cast<int64_t>(motion.size()))
      Fail("splat delta: ", cells, " motion cells where the survivors fill ", motion.size());
    const std::string bytes = FromPlanes(SectionBytes(chunk, "motion"), 6, cells, "motion");
    size_t at = 0;
    for (auto& [key, m] : motion)
      for (int a = 0; a < 3; ++a, at += 2) m[a] = Unzigzag16(Get<uint16_t>(&bytes[at]));
  }
  const int32_t top = quantised ? (int32_t{1} << e.position_bits) - 1 : 0;
  for (int group = 0; group < kSplatGroups; ++group) {
    const size_t w = widths[group], offset = (1 + group) * mask_bytes;
    const bool moving = group == 0 && quantised;
    int64_t changed = 0;
    for (int64_t i = 0; i < n; ++i)
      changed += Bit(masks, 0, i) && (moving || Bit(masks, offset, i));
    const char* name = kSplatGroupNames[group];
    const std::string stored = FromPlanes(SectionBytes(chunk, name), w, changed + added, name);
    const std::string& before = previous->records[group];
    std::string& out = codes.records[group];
    out.reserve(w * codes.count);
    size_t next = 0;
    for (int64_t i = 0; i < n; ++i) {
      if (!Bit(masks, 0, i)) continue;
      if (moving) {
        const auto& m = motion.at(CellOf(before, i, e.motion_cell_bits));
        for (int a = 0; a < 3; ++a, next += 2) {
          const int32_t r = Unzigzag16(Get<uint16_t>(&stored[next]));
          Put<uint16_t>(&out, static_cast<uint16_t>(std::clamp(
                                  PositionCode(before, i, a) + m[a] + r * e.motion_step, 0, top)));
        }
      } else if (Bit(masks, offset, i)) {
        for (size_t b = 0; b < w; ++b)
          out.push_back(static_cast<char>(stored[next + b] + before[i * w + b]));
        next += w;
      } else {
        out.append(before, i * w, w);
      }
    }
    if (moving)
      out += Unchained(stored, next);
    else
      out.append(stored, next, std::string::npos);
  }
  return codes;
}

}  // namespace holocap::web
