// The splat stream's chunks (README "The stream format"): Gaussians quantised per attribute
// group, key frames in full and later frames as deltas of the frame before as decoded (kept and
// changed bits over the frame before's Gaussians, the changed ones' codes as byte differences
// from the frame before's, the added ones' codes).
#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>

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
        out->append(reinterpret_cast<const char*>(&g.sh[3 * k_stored * i]), 12 * k_streamed);
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
          {"rest_max", rest_max}};
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
  } catch (const nlohmann::json::exception& error) {
    Fail("splat chunk: bad encoding (", error.what(), ")");
  }
  for (int bits : {e.scale_bits, e.opacity_bits, e.dc_bits, e.rest_bits})
    if (bits < 1 || bits > 8) Fail("splat chunk: ", bits, "-bit codes in a byte");
  if (e.position_bits < 1 || e.position_bits > 16 || e.rotation_bits < 1 || e.rotation_bits > 10)
    Fail("splat chunk: bad position or rotation bits");
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
      g.position[3 * i + a] = Dequantise(Get<uint16_t>(&position[6 * i + 2 * a]), e.box_min[a],
                                         e.box_max[a], e.position_bits);
      g.log_scale[3 * i + a] = Dequantise(static_cast<uint8_t>(scale[3 * i + a]), e.log_scale_min,
                                          e.log_scale_max, e.scale_bits);
    }
    FromSmallestThree(Get<uint32_t>(&rotation[4 * i]), e.rotation_bits, &g.rotation[4 * i]);
    g.opacity[i] = OpacityOf(static_cast<uint8_t>(opacity[i]), e.opacity_bits);
    for (int j = 0; j < 3 * k; ++j) {
      const uint8_t code = static_cast<uint8_t>(color[3 * k * i + j]);
      g.sh[3 * k * i + j] = j < 3 ? Dequantise(code, e.dc_min, e.dc_max, e.dc_bits)
                                  : Dequantise(code, -e.rest_max, e.rest_max, e.rest_bits);
    }
  }
  return g;
}

Chunk EncodeSplats(const splat::Gaussians& gaussians, int64_t frame, const SplatEncoding& e,
                   const SplatCodes* previous, const std::vector<int64_t>& origin,
                   SplatCodes* codes) {
  *codes = QuantiseSplats(gaussians, e);
  const auto widths = e.RecordBytes();
  Chunk chunk;
  chunk.header = {{"kind", "splats"},
                  {"frame", frame},
                  {"key", previous == nullptr},
                  {"count", gaussians.size()},
                  {"stored", gaussians.size()},
                  {"encoding", e.ToJson()},
                  {"sections", nlohmann::json::array()}};
  if (previous == nullptr) {
    for (int group = 0; group < kSplatGroups; ++group)
      chunk.AddSection(kSplatGroupNames[group], ToPlanes(codes->records[group], widths[group]),
                       "deflate");
    return chunk;
  }
  if (static_cast<int64_t>(origin.size()) != gaussians.size())
    Fail("a splat delta needs one origin per Gaussian");
  const int64_t n = previous->count;
  const size_t mask_bytes = static_cast<size_t>((n + 7) / 8);
  // Kept bits, then one changed bit per group, each over the frame before's Gaussians.
  std::string masks((1 + kSplatGroups) * mask_bytes, '\0');
  std::array<std::string, kSplatGroups> stored;
  std::vector<int64_t> added;
  int64_t last = -1, survivors = 0, changed_any = 0;
  for (int64_t i = 0; i < gaussians.size(); ++i) {
    const int64_t from = origin[i];
    if (from < 0) {
      added.push_back(i);
      continue;
    }
    if (from <= last || from >= n) Fail("a splat delta's survivors must keep their order");
    last = from;
    ++survivors;
    SetBit(&masks, 0, from);
    bool changed = false;
    for (int group = 0; group < kSplatGroups; ++group) {
      const size_t w = widths[group];
      if (codes->records[group].compare(i * w, w, previous->records[group], from * w, w) == 0)
        continue;
      SetBit(&masks, (1 + group) * mask_bytes, from);
      // Each byte as its difference (modulo 256) from the frame before's: a small move leaves
      // small numbers, which deflate packs tighter than the codes.
      for (size_t b = 0; b < w; ++b)
        stored[group].push_back(static_cast<char>(codes->records[group][i * w + b] -
                                                  previous->records[group][from * w + b]));
      changed = true;
    }
    changed_any += changed;
  }
  for (int group = 0; group < kSplatGroups; ++group) {
    for (int64_t i : added)
      stored[group].append(codes->records[group], i * widths[group], widths[group]);
  }
  chunk.header["previous"] = n;
  chunk.header["added"] = added.size();
  chunk.header["removed"] = n - survivors;
  chunk.header["stored"] = changed_any + static_cast<int64_t>(added.size());
  chunk.AddSection("masks", masks, "deflate");
  for (int group = 0; group < kSplatGroups; ++group)
    chunk.AddSection(kSplatGroupNames[group], ToPlanes(stored[group], widths[group]), "deflate");
  return chunk;
}

SplatCodes DecodeSplats(const Chunk& chunk, const SplatCodes* previous) {
  const nlohmann::json& h = chunk.header;
  if (h.value("kind", "") != "splats") Fail("not a splat chunk");
  const SplatEncoding e = SplatEncoding::FromJson(h.at("encoding"));
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
  if (survivors + added != codes.count) Fail("splat delta: survivors and added do not make count");
  for (int group = 0; group < kSplatGroups; ++group) {
    const size_t w = widths[group], offset = (1 + group) * mask_bytes;
    int64_t changed = 0;
    for (int64_t i = 0; i < n; ++i) changed += Bit(masks, 0, i) && Bit(masks, offset, i);
    const char* name = kSplatGroupNames[group];
    const std::string stored = FromPlanes(SectionBytes(chunk, name), w, changed + added, name);
    if (previous->records[group].size() != w * n) Fail("splat delta: the frame before's codes");
    std::string& out = codes.records[group];
    out.reserve(w * codes.count);
    size_t next = 0;
    for (int64_t i = 0; i < n; ++i) {
      if (!Bit(masks, 0, i)) continue;
      if (Bit(masks, offset, i)) {
        for (size_t b = 0; b < w; ++b)
          out.push_back(static_cast<char>(stored[next + b] + previous->records[group][i * w + b]));
        next += w;
      } else {
        out.append(previous->records[group], i * w, w);
      }
    }
    out.append(stored, next, std::string::npos);
  }
  return codes;
}

}  // namespace holocap::web
