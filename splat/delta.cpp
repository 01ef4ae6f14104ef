// The per-frame delta of a dynamic splat model (the format is documented in splat/splat.h).
#include <zstd.h>

#include <algorithm>
#include <cmath>
#include <cstring>

#include "core/error.h"
#include "core/fs.h"
#include "splat/splat.h"

namespace holocap {
namespace {

constexpr char kMagic[4] = {'H', 'S', 'D', '1'};
constexpr int kGroups = 5;
constexpr int kGroupValues[kGroups] = {3, 4, 3, 1, 3};

// Group g's value j of Gaussian i in `g` (colour: the degree-0 coefficients).
float& Value(splat::Gaussians& gaussians, int group, int64_t i, int j) {
  switch (group) {
    case 0:
      return gaussians.position[3 * i + j];
    case 1:
      return gaussians.rotation[4 * i + j];
    case 2:
      return gaussians.log_scale[3 * i + j];
    case 3:
      return gaussians.opacity[i];
    default:
      return gaussians.sh[3 * gaussians.coefficients() * i + j];
  }
}
float Value(const splat::Gaussians& gaussians, int group, int64_t i, int j) {
  return Value(const_cast<splat::Gaussians&>(gaussians), group, i, j);
}

float Step(const SplatDeltaSteps& steps, int group) {
  const float all[kGroups] = {steps.position_m, steps.rotation, steps.log_scale, steps.opacity,
                              steps.color};
  return all[group];
}

template <typename T>
void Put(std::string* out, T value) {
  out->append(reinterpret_cast<const char*>(&value), sizeof(T));
}

// Reads the decompressed bytes in order; any read past the end is an Error.
class Reader {
 public:
  explicit Reader(const std::string& bytes) : bytes_(bytes) {}
  const char* Take(size_t size) {
    if (offset_ + size > bytes_.size()) Fail("a splat delta is shorter than its header says");
    const char* at = bytes_.data() + offset_;
    offset_ += size;
    return at;
  }
  template <typename T>
  T Get() {
    T value;
    std::memcpy(&value, Take(sizeof(T)), sizeof(T));
    return value;
  }
  bool done() const { return offset_ == bytes_.size(); }
  size_t remaining() const { return bytes_.size() - offset_; }

 private:
  const std::string& bytes_;
  size_t offset_ = 0;
};

bool Bit(const char* bits, int64_t i) { return (static_cast<uint8_t>(bits[i / 8]) >> (i % 8)) & 1; }

// The bytes at the start of a decompressed delta: magic, the three counts and the steps.
constexpr size_t kHeaderBytes = 4 + 3 * sizeof(uint32_t) + kGroups * sizeof(float);
// The most Gaussians a delta may name (previous or added), whatever its header says.
constexpr uint64_t kMaxDeltaGaussians = uint64_t{1} << 26;
// Added Gaussians are trained floats, which zstd shrinks by a few times at most: a delta whose
// added part would grow past this many times its compressed size (plus a slack) is a bomb.
constexpr uint64_t kMaxAddedExpansion = 256;

// The first `size` bytes of the decompressed delta (fewer only if it ends sooner).
std::string DecompressStart(const std::string& delta, size_t size) {
  std::string out(size, '\0');
  ZSTD_DCtx* context = ZSTD_createDCtx();
  if (context == nullptr) Fail("zstd cannot make a decompression context");
  ZSTD_inBuffer in{delta.data(), delta.size(), 0};
  ZSTD_outBuffer to{out.data(), out.size(), 0};
  while (to.pos < to.size) {
    const size_t before_in = in.pos, before_out = to.pos;
    const size_t result = ZSTD_decompressStream(context, &to, &in);
    if (ZSTD_isError(result)) {
      ZSTD_freeDCtx(context);
      Fail("a splat delta does not decompress: ", ZSTD_getErrorName(result));
    }
    if (result == 0 || (in.pos == before_in && to.pos == before_out)) break;
  }
  ZSTD_freeDCtx(context);
  out.resize(to.pos);
  return out;
}

// The delta decompressed, once its header has been read and what it declares (the previous
// frame's `expected_previous` Gaussians when known, -1 when not) bounds what it may expand to.
std::string Decompress(const std::string& delta, int64_t expected_previous) {
  const unsigned long long size = ZSTD_getFrameContentSize(delta.data(), delta.size());
  if (size == ZSTD_CONTENTSIZE_ERROR || size == ZSTD_CONTENTSIZE_UNKNOWN)
    Fail("a splat delta is not a zstd frame of known size");
  const std::string start = DecompressStart(delta, kHeaderBytes);
  if (start.size() < kHeaderBytes) Fail("a splat delta is shorter than its header");
  if (std::memcmp(start.data(), kMagic, 4) != 0) Fail("a splat delta does not start HSD1");
  uint32_t counts[3];
  std::memcpy(counts, start.data() + 4, sizeof(counts));
  const uint64_t previous = counts[0], added = counts[1], degree = counts[2];
  if (degree > static_cast<uint64_t>(splat::kMaxShDegree))
    Fail("a splat delta names degree ", degree);
  if (expected_previous >= 0 && previous != static_cast<uint64_t>(expected_previous)) {
    Fail("a splat delta of ", previous, " Gaussians does not follow a frame of ",
         expected_previous);
  }
  if (previous > kMaxDeltaGaussians || added > kMaxDeltaGaussians)
    Fail("a splat delta names ", previous, " and ", added, " Gaussians, past the ",
         kMaxDeltaGaussians, " a frame may have");
  const uint64_t floats = 11 + 3 * (degree + 1) * (degree + 1);
  const uint64_t added_bytes = added * floats * sizeof(float);
  if (added_bytes > kMaxAddedExpansion * delta.size() + (uint64_t{1} << 20)) {
    Fail("a splat delta of ", delta.size(), " bytes declares ", added,
         " added Gaussians, more than its bytes can hold");
  }
  uint64_t values = 0;
  for (const int count : kGroupValues) values += static_cast<uint64_t>(count);
  const uint64_t most = kHeaderBytes + (1 + kGroups) * ((previous + 7) / 8) +
                        previous * values * sizeof(int16_t) + added_bytes;
  if (size > most) {
    Fail("a splat delta would decompress to ", size, " bytes; its header allows ", most);
  }
  std::string bytes(size, '\0');
  const size_t n = ZSTD_decompress(bytes.data(), bytes.size(), delta.data(), delta.size());
  if (ZSTD_isError(n) || n != size) Fail("a splat delta does not decompress");
  return bytes;
}

// The header's fields, read and checked.
struct Header {
  uint32_t previous = 0, added = 0, sh_degree = 0;
  float steps[kGroups] = {};
};
Header ReadHeader(Reader* reader) {
  if (std::memcmp(reader->Take(4), kMagic, 4) != 0) Fail("a splat delta does not start HSD1");
  Header header;
  header.previous = reader->Get<uint32_t>();
  header.added = reader->Get<uint32_t>();
  header.sh_degree = reader->Get<uint32_t>();
  if (header.sh_degree > splat::kMaxShDegree) Fail("a splat delta names degree ", header.sh_degree);
  for (float& step : header.steps) step = reader->Get<float>();
  return header;
}

}  // namespace

SplatDeltaSteps SplatDeltaSteps::Doubled() const {
  return {2 * position_m, 2 * rotation, 2 * log_scale, 2 * opacity, 2 * color};
}

std::string EncodeSplatDelta(const splat::Gaussians& previous, const splat::Gaussians& next,
                             const std::vector<int64_t>& origin, const SplatDeltaSteps& steps) {
  if (static_cast<int64_t>(origin.size()) != next.size() || previous.sh_degree != next.sh_degree) {
    Fail("a splat delta needs one origin per Gaussian and one degree");
  }
  const int64_t n = previous.size();
  const size_t mask_bytes = static_cast<size_t>((n + 7) / 8);
  std::vector<int64_t> continued(n, -1);  // previous index -> next index
  std::vector<int64_t> added;
  int64_t last = -1;
  for (int64_t i = 0; i < next.size(); ++i) {
    if (origin[i] < 0) {
      added.push_back(i);
      continue;
    }
    if (origin[i] <= last || origin[i] >= n) Fail("a splat delta's survivors must keep order");
    continued[origin[i]] = i;
    last = origin[i];
  }
  std::string bytes(kMagic, 4);
  Put<uint32_t>(&bytes, static_cast<uint32_t>(n));
  Put<uint32_t>(&bytes, static_cast<uint32_t>(added.size()));
  Put<uint32_t>(&bytes, static_cast<uint32_t>(previous.sh_degree));
  for (int g = 0; g < kGroups; ++g) Put<float>(&bytes, Step(steps, g));
  std::string kept(mask_bytes, '\0');
  for (int64_t i = 0; i < n; ++i)
    if (continued[i] >= 0) kept[i / 8] |= static_cast<char>(1 << (i % 8));
  bytes += kept;
  for (int g = 0; g < kGroups; ++g) {
    const float step = Step(steps, g);
    std::string changed(mask_bytes, '\0');
    std::vector<int16_t> values;
    for (int64_t i = 0; i < n; ++i) {
      if (continued[i] < 0) continue;
      int16_t q[4] = {0, 0, 0, 0};
      bool any = false;
      for (int j = 0; j < kGroupValues[g]; ++j) {
        const double d = (Value(next, g, continued[i], j) - Value(previous, g, i, j)) / step;
        q[j] = static_cast<int16_t>(std::clamp(std::lround(d), -32767L, 32767L));
        any = any || q[j] != 0;
      }
      if (!any) continue;
      changed[i / 8] |= static_cast<char>(1 << (i % 8));
      values.insert(values.end(), q, q + kGroupValues[g]);
    }
    bytes += changed;
    bytes.append(reinterpret_cast<const char*>(values.data()), values.size() * sizeof(int16_t));
  }
  splat::Gaussians appended;
  appended.sh_degree = next.sh_degree;
  for (int64_t i : added) appended.AppendFrom(next, i);
  for (const std::vector<float>* field : {&appended.position, &appended.rotation,
                                          &appended.log_scale, &appended.opacity, &appended.sh}) {
    bytes.append(reinterpret_cast<const char*>(field->data()), field->size() * sizeof(float));
  }
  std::string compressed(ZSTD_compressBound(bytes.size()), '\0');
  const size_t size =
      ZSTD_compress(compressed.data(), compressed.size(), bytes.data(), bytes.size(), 9);
  if (ZSTD_isError(size)) Fail("zstd could not compress a splat delta");
  compressed.resize(size);
  return compressed;
}

splat::Gaussians ApplySplatDelta(const splat::Gaussians& previous, const std::string& delta) {
  const std::string bytes = Decompress(delta, previous.size());
  Reader reader(bytes);
  const Header header = ReadHeader(&reader);
  if (static_cast<int64_t>(header.previous) != previous.size() ||
      static_cast<int>(header.sh_degree) != previous.sh_degree) {
    Fail("a splat delta of ", header.previous, " Gaussians (degree ", header.sh_degree,
         ") does not follow a frame of ", previous.size(), " (degree ", previous.sh_degree, ")");
  }
  const int64_t n = previous.size();
  const size_t mask_bytes = static_cast<size_t>((n + 7) / 8);
  const char* kept = reader.Take(mask_bytes);
  splat::Gaussians updated = previous;  // changed in place, then the survivors selected
  for (int g = 0; g < kGroups; ++g) {
    const char* changed = reader.Take(mask_bytes);
    for (int64_t i = 0; i < n; ++i) {
      if (!Bit(changed, i)) continue;
      for (int j = 0; j < kGroupValues[g]; ++j) {
        const int16_t q = reader.Get<int16_t>();
        Value(updated, g, i, j) =
            Value(previous, g, i, j) + static_cast<float>(q) * header.steps[g];
      }
    }
  }
  splat::Gaussians next;
  next.sh_degree = previous.sh_degree;
  for (int64_t i = 0; i < n; ++i)
    if (Bit(kept, i)) next.AppendFrom(updated, i);
  const size_t floats = 11 + 3 * static_cast<size_t>(previous.coefficients());
  if (reader.remaining() != header.added * floats * sizeof(float))
    Fail("a splat delta's added Gaussians do not fill its end");
  splat::Gaussians appended;
  appended.sh_degree = previous.sh_degree;
  appended.Resize(header.added);
  for (std::vector<float>* field : {&appended.position, &appended.rotation, &appended.log_scale,
                                    &appended.opacity, &appended.sh}) {
    const size_t size = field->size() * sizeof(float);
    std::memcpy(field->data(), reader.Take(size), size);
  }
  for (int64_t i = 0; i < appended.size(); ++i) next.AppendFrom(appended, i);
  return next;
}

splat::Gaussians ApplySplatDeltaFile(const splat::Gaussians& previous,
                                     const std::filesystem::path& file) {
  const std::string delta = ReadFileToString(file);
  try {
    return ApplySplatDelta(previous, delta);
  } catch (const Error& e) {
    Fail("'", file.string(), "': ", e.what());
  }
}

SplatDeltaCounts CountSplatDelta(const std::string& delta) {
  const std::string bytes = Decompress(delta, -1);
  Reader reader(bytes);
  const Header header = ReadHeader(&reader);
  const int64_t n = header.previous;
  const size_t mask_bytes = static_cast<size_t>((n + 7) / 8);
  SplatDeltaCounts counts;
  const char* kept = reader.Take(mask_bytes);
  for (int64_t i = 0; i < n; ++i) counts.removed += !Bit(kept, i);
  for (int g = 0; g < kGroups; ++g) {
    const char* changed = reader.Take(mask_bytes);
    int64_t in_group = 0;
    for (int64_t i = 0; i < n; ++i) in_group += Bit(changed, i);
    reader.Take(in_group * kGroupValues[g] * sizeof(int16_t));
    counts.changed += in_group;
  }
  counts.added = header.added;
  return counts;
}

std::vector<int64_t> SplatDeltaOrigins(const std::string& delta) {
  const std::string bytes = Decompress(delta, -1);
  Reader reader(bytes);
  const Header header = ReadHeader(&reader);
  const char* kept = reader.Take(static_cast<size_t>((header.previous + 7) / 8));
  std::vector<int64_t> origin;
  for (int64_t i = 0; i < header.previous; ++i)
    if (Bit(kept, i)) origin.push_back(i);
  origin.insert(origin.end(), header.added, -1);
  return origin;
}

}  // namespace holocap
