#include "playback/internal/web_stream.h"

#include <zlib.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "avatar/raymarch.h"
#include "core/error.h"

namespace holocap::web {
namespace {

template <typename T>
std::string Bytes(const std::vector<T>& values) {
  return std::string(reinterpret_cast<const char*>(values.data()), values.size() * sizeof(T));
}

template <typename T>
std::vector<T> Values(const std::string& bytes, size_t count, const char* what) {
  if (bytes.size() != count * sizeof(T))
    Fail("chunk section '", what, "' holds ", bytes.size(), " bytes, not ", count * sizeof(T));
  std::vector<T> values(count);
  std::memcpy(values.data(), bytes.data(), bytes.size());
  return values;
}

std::string Deflate(const std::string& raw) {
  uLongf size = compressBound(raw.size());
  std::string out(size, '\0');
  if (compress2(reinterpret_cast<Bytef*>(out.data()), &size,
                reinterpret_cast<const Bytef*>(raw.data()), raw.size(), 9) != Z_OK) {
    Fail("cannot deflate a chunk section of ", raw.size(), " bytes");
  }
  out.resize(size);
  return out;
}

std::string Inflate(const std::string& deflated, size_t raw_bytes, const std::string& name) {
  std::string out(raw_bytes, '\0');
  uLongf size = raw_bytes;
  if (uncompress(reinterpret_cast<Bytef*>(out.data()), &size,
                 reinterpret_cast<const Bytef*>(deflated.data()), deflated.size()) != Z_OK ||
      size != raw_bytes) {
    Fail("chunk section '", name, "' does not inflate to its ", raw_bytes, " bytes");
  }
  return out;
}

nlohmann::json Vec(const Eigen::Vector3d& v) { return {v.x(), v.y(), v.z()}; }
Eigen::Vector3d Vec(const nlohmann::json& j) {
  return {j.at(0).get<double>(), j.at(1).get<double>(), j.at(2).get<double>()};
}

// Each element minus the one `stride` before it, modulo 2^16 (the first ones kept): a mesh's
// neighbouring vertices and texture cells are near each other, so the differences are small and
// deflate packs them tightly.
std::vector<uint16_t> DeltaEncode(std::vector<uint16_t> codes, size_t stride) {
  for (size_t i = codes.size(); i-- > stride;)
    codes[i] = static_cast<uint16_t>(codes[i] - codes[i - stride]);
  return codes;
}
std::vector<uint16_t> DeltaDecode(std::vector<uint16_t> codes, size_t stride) {
  for (size_t i = stride; i < codes.size(); ++i)
    codes[i] = static_cast<uint16_t>(codes[i] + codes[i - stride]);
  return codes;
}
// Indices as zigzagged differences from the previous index.
std::vector<uint32_t> ZigzagDeltas(const std::vector<uint32_t>& indices) {
  std::vector<uint32_t> out(indices.size());
  int64_t previous = 0;
  for (size_t i = 0; i < indices.size(); ++i) {
    const int64_t d = static_cast<int64_t>(indices[i]) - previous;
    out[i] = static_cast<uint32_t>(d >= 0 ? 2 * d : -2 * d - 1);
    previous = indices[i];
  }
  return out;
}
std::vector<uint32_t> UndoZigzagDeltas(const std::vector<uint32_t>& codes) {
  std::vector<uint32_t> out(codes.size());
  int64_t previous = 0;
  for (size_t i = 0; i < codes.size(); ++i) {
    const int64_t d = codes[i] % 2 == 0 ? codes[i] / 2 : -(static_cast<int64_t>(codes[i]) + 1) / 2;
    previous += d;
    out[i] = static_cast<uint32_t>(previous);
  }
  return out;
}

}  // namespace

uint32_t Quantise(double value, double lo, double hi, int bits) {
  const double levels = std::ldexp(1.0, bits) - 1;
  const double t = hi > lo ? (value - lo) / (hi - lo) : 0.0;
  return static_cast<uint32_t>(std::lround(std::clamp(t, 0.0, 1.0) * levels));
}
float Dequantise(uint32_t code, double lo, double hi, int bits) {
  const double levels = std::ldexp(1.0, bits) - 1;
  return static_cast<float>(lo + (hi - lo) * (code / levels));
}

QualityLevel QualityByName(const std::string& name) {
  QualityLevel q;
  q.name = name;
  if (name == "low") {
    q.position_bits = 11;
    q.simplify_edges = 1.0;
    q.cell_px = 6;
    q.texture_quality = 60;
    q.texture_scale = 0.5;
    q.color_bits = 6;
    q.density_levels = 64;
    q.splat_position_bits = 14;
    q.splat_sh_degree = 0;
    q.splat_rest_bits = 4;
  } else if (name == "medium") {
    q.position_bits = 13;
    q.simplify_edges = 0.75;
    q.cell_px = 8;
    q.texture_quality = 75;
    q.color_bits = 7;
    q.density_levels = 128;
    q.splat_sh_degree = 1;
    q.splat_rest_bits = 5;
  } else if (name == "high") {
    q.position_bits = 14;
    q.simplify_edges = 0.35;
    q.cell_px = 8;
    q.texture_quality = 92;
    q.color_bits = 8;
    q.density_levels = 256;
  } else if (name == "lossless") {
    q.position_bits = 0;
    q.uv_bits = 0;
    q.texture_codec = "png";
    q.texture_quality = 100;
    q.color_bits = 0;
    q.density_levels = 0;
    q.splat_position_bits = 0;
  } else {
    Fail("unknown --quality '", name, "' (known: low, medium, high, lossless)");
  }
  return q;
}

void Chunk::AddSection(const std::string& name, const std::string& bytes,
                       const std::string& codec) {
  const std::string stored = codec == "deflate" ? Deflate(bytes) : bytes;
  header["sections"].push_back({{"name", name},
                                {"offset", payload.size()},
                                {"bytes", stored.size()},
                                {"codec", codec},
                                {"raw_bytes", bytes.size()}});
  payload += stored;
}

std::string Chunk::Serialise() const {
  const std::string text = header.dump();
  std::string out(kChunkMagic, 8);
  const uint32_t fields[2] = {static_cast<uint32_t>(kWebStreamFormatVersion),
                              static_cast<uint32_t>(text.size())};
  out.append(reinterpret_cast<const char*>(fields), sizeof(fields));
  return out + text + payload;
}

Chunk ParseChunk(const std::string& bytes) {
  if (bytes.size() < 16 || bytes.compare(0, 8, kChunkMagic) != 0) Fail("not a holocap chunk");
  uint32_t fields[2];
  std::memcpy(fields, bytes.data() + 8, sizeof(fields));
  if (fields[0] != kWebStreamFormatVersion)
    Fail("chunk format version ", fields[0], " is not ", kWebStreamFormatVersion);
  if (16 + static_cast<size_t>(fields[1]) > bytes.size()) Fail("chunk header is truncated");
  Chunk chunk;
  chunk.header = nlohmann::json::parse(bytes.substr(16, fields[1]), nullptr, false);
  if (chunk.header.is_discarded()) Fail("chunk header does not parse");
  chunk.payload = bytes.substr(16 + fields[1]);
  for (const auto& section : chunk.header.at("sections")) {
    if (section.at("offset").get<size_t>() + section.at("bytes").get<size_t>() >
        chunk.payload.size())
      Fail("chunk is truncated (section '", section.at("name").get<std::string>(), "')");
  }
  return chunk;
}

std::string SectionBytes(const Chunk& chunk, const std::string& name) {
  for (const auto& section : chunk.header.at("sections")) {
    if (section.at("name") != name) continue;
    const std::string stored =
        chunk.payload.substr(section.at("offset").get<size_t>(), section.at("bytes").get<size_t>());
    if (section.at("codec") != "deflate") return stored;
    return Inflate(stored, section.at("raw_bytes").get<size_t>(), name);
  }
  Fail("chunk has no section '", name, "'");
}

// ---------------------------------------------------------------------------------------------
// Meshes. Simplified levels ("layout": "cells"): welded vertices quantised over the frame's box
// as zigzagged differences from the previous vertex, indices as distances below the next new
// vertex, both as byte planes, texture coordinates implied by the cell layout. Unsimplified
// levels: welded positions (quantised or float32), zigzagged index differences and per-corner
// texture coordinates. Either carries the atlas as an image (or per-corner colours without one).

namespace {

// Values of T as sizeof(T) planes: every element's lowest byte, then every next byte, ...
// (differences of nearby values share their high bytes, which deflate then packs to nothing).
template <typename T>
std::string BytePlanes(const std::vector<T>& values) {
  std::string out(values.size() * sizeof(T), '\0');
  for (size_t i = 0; i < values.size(); ++i)
    for (size_t b = 0; b < sizeof(T); ++b)
      out[b * values.size() + i] = static_cast<char>((values[i] >> (8 * b)) & 0xff);
  return out;
}
template <typename T>
std::vector<T> FromBytePlanes(const std::string& bytes, size_t count, const char* what) {
  if (bytes.size() != count * sizeof(T))
    Fail("chunk section '", what, "' holds ", bytes.size(), " bytes, not ", count * sizeof(T));
  std::vector<T> values(count, 0);
  for (size_t i = 0; i < count; ++i)
    for (size_t b = 0; b < sizeof(T); ++b)
      values[i] |= static_cast<T>(static_cast<uint8_t>(bytes[b * count + i])) << (8 * b);
  return values;
}

uint16_t Zigzag16(int32_t d) { return static_cast<uint16_t>(d >= 0 ? 2 * d : -2 * d - 1); }
int32_t Unzigzag16(uint16_t c) { return c % 2 == 0 ? c / 2 : -(static_cast<int32_t>(c) + 1) / 2; }

// Indices whose vertices first appear in order (0, 1, 2, ...): each as how far it lies below
// the next vertex not yet used (0 for that new vertex).
std::vector<uint32_t> HighWaterCodes(const std::vector<uint32_t>& indices) {
  std::vector<uint32_t> codes(indices.size());
  uint32_t next = 0;
  for (size_t i = 0; i < indices.size(); ++i) {
    if (indices[i] > next) Fail("mesh vertices are not in order of first use");
    codes[i] = next - indices[i];
    if (indices[i] == next) ++next;
  }
  return codes;
}
std::vector<uint32_t> UndoHighWaterCodes(const std::vector<uint32_t>& codes) {
  std::vector<uint32_t> indices(codes.size());
  uint32_t next = 0;
  for (size_t i = 0; i < codes.size(); ++i) {
    if (codes[i] > next) Fail("chunk index code ", codes[i], " names a vertex before the first");
    indices[i] = next - codes[i];
    if (codes[i] == 0) ++next;
  }
  return indices;
}

struct PositionBox {
  Eigen::Vector3d lo = Eigen::Vector3d::Zero(), hi = Eigen::Vector3d::Zero();
};
PositionBox BoxOf(const std::vector<Eigen::Vector3f>& points) {
  PositionBox box;
  if (points.empty()) return box;
  box.lo = box.hi = points.front().cast<double>();
  for (const auto& p : points) {
    box.lo = box.lo.cwiseMin(p.cast<double>());
    box.hi = box.hi.cwiseMax(p.cast<double>());
  }
  return box;
}

// Quantised codes (3 per vertex) and the positions they restore; the largest error in *max_m.
std::vector<uint16_t> QuantisePositions(const std::vector<Eigen::Vector3f>& points,
                                        const PositionBox& box, int bits,
                                        std::vector<Eigen::Vector3f>* restored, double* max_m) {
  std::vector<uint16_t> codes;
  restored->resize(points.size());
  for (size_t v = 0; v < points.size(); ++v) {
    for (int a = 0; a < 3; ++a) {
      const uint32_t code = Quantise(points[v][a], box.lo[a], box.hi[a], bits);
      codes.push_back(static_cast<uint16_t>(code));
      (*restored)[v][a] = Dequantise(code, box.lo[a], box.hi[a], bits);
    }
    *max_m = std::max(*max_m, static_cast<double>(((*restored)[v] - points[v]).norm()));
  }
  return codes;
}

// The atlas as an image section (scaled and coded as the level says); returns what decodes.
cv::Mat AddAtlas(const cv::Mat& full, const QualityLevel& quality, double scale, Chunk* chunk) {
  cv::Mat atlas = full;
  if (scale < 1) cv::resize(full, atlas, cv::Size(), scale, scale, cv::INTER_AREA);
  std::vector<int> params;
  const std::string codec = quality.texture_codec;
  if (codec == "webp") params = {cv::IMWRITE_WEBP_QUALITY, quality.texture_quality};
  if (codec == "jpeg") params = {cv::IMWRITE_JPEG_QUALITY, quality.texture_quality};
  std::vector<uint8_t> encoded;
  if (!cv::imencode(codec == "jpeg" ? ".jpg" : "." + codec, atlas, encoded, params))
    Fail("cannot encode a texture atlas as ", codec);
  chunk->header["texture"] = {{"width", atlas.cols}, {"height", atlas.rows}, {"codec", codec}};
  chunk->AddSection("texture", Bytes(encoded), codec);
  return cv::imdecode(encoded, cv::IMREAD_COLOR);
}

nlohmann::json MeshHeader(int64_t frame, size_t faces, size_t vertices, const PositionBox& box,
                          const QualityLevel& quality) {
  return {{"kind", "mesh"},
          {"frame", frame},
          {"face_count", faces},
          {"vertex_count", vertices},
          {"box_min", Vec(box.lo)},
          {"box_max", Vec(box.hi)},
          {"position_bits", quality.position_bits},
          {"uv_bits", quality.uv_bits},
          {"sections", nlohmann::json::array()}};
}

Chunk EncodeCellMesh(const TexturedMeshFrame& mesh, int64_t frame, const QualityLevel& quality,
                     TexturedMeshFrame* decoded, double* max_position_error_m) {
  const CellMesh cells =
      SimplifyForStream(mesh, quality.simplify_edges * MedianEdgeM(mesh), quality.cell_px);
  const PositionBox box = BoxOf(cells.vertices);
  Chunk chunk;
  chunk.header = MeshHeader(frame, cells.indices.size() / 3, cells.vertices.size(), box, quality);
  chunk.header["uv_bits"] = 0;
  chunk.header["layout"] = {{"kind", "cells"},
                            {"cell_px", cells.layout.cell_px},
                            {"columns", cells.layout.columns},
                            {"rows", cells.layout.rows}};
  chunk.header["simplify_error_m"] = cells.error_m;
  std::vector<Eigen::Vector3f> restored;
  double quantisation_m = 0;
  std::vector<uint16_t> codes =
      QuantisePositions(cells.vertices, box, quality.position_bits, &restored, &quantisation_m);
  std::vector<uint16_t> differences(codes.size());
  for (size_t i = 0; i < codes.size(); ++i)
    differences[i] = Zigzag16(
        static_cast<int16_t>(static_cast<uint16_t>(codes[i] - (i >= 3 ? codes[i - 3] : 0))));
  chunk.AddSection("positions", BytePlanes(differences), "deflate");
  const std::vector<uint32_t> index_codes = HighWaterCodes(cells.indices);
  if (cells.vertices.size() <= 65536) {
    chunk.header["index_bytes"] = 2;
    chunk.AddSection("indices",
                     BytePlanes(std::vector<uint16_t>(index_codes.begin(), index_codes.end())),
                     "deflate");
  } else {
    chunk.header["index_bytes"] = 4;
    chunk.AddSection("indices", BytePlanes(index_codes), "deflate");
  }
  *max_position_error_m = cells.error_m + quantisation_m;
  decoded->positions.clear();
  decoded->uvs.clear();
  decoded->colors.clear();
  for (size_t c = 0; c < cells.indices.size(); ++c) {
    decoded->positions.push_back(restored[cells.indices[c]]);
    decoded->uvs.push_back(CellCornerUv(c / 3, static_cast<int>(c % 3), cells.layout));
  }
  decoded->atlas = AddAtlas(cells.atlas, quality, 1.0, &chunk);
  return chunk;
}

}  // namespace

Chunk EncodeMesh(const TexturedMeshFrame& mesh, int64_t frame, const QualityLevel& quality,
                 TexturedMeshFrame* decoded, double* max_position_error_m) {
  if (quality.simplify_edges > 0)
    return EncodeCellMesh(mesh, frame, quality, decoded, max_position_error_m);
  std::vector<uint32_t> indices;
  std::vector<Eigen::Vector3f> unique;
  WeldCorners(mesh.positions, &unique, &indices);
  const PositionBox box = BoxOf(mesh.positions);
  Chunk chunk;
  chunk.header = MeshHeader(frame, mesh.faces(), unique.size(), box, quality);
  std::vector<Eigen::Vector3f> restored(unique.size());
  double max_error = 0;
  if (quality.position_bits > 0) {
    const std::vector<uint16_t> codes =
        QuantisePositions(unique, box, quality.position_bits, &restored, &max_error);
    chunk.AddSection("positions", Bytes(DeltaEncode(codes, 3)), "deflate");
  } else {
    restored = unique;
    std::vector<float> raw;
    for (const auto& p : unique) raw.insert(raw.end(), {p.x(), p.y(), p.z()});
    chunk.AddSection("positions", Bytes(raw), "deflate");
  }
  chunk.AddSection("indices", Bytes(ZigzagDeltas(indices)), "deflate");
  decoded->positions.clear();
  for (uint32_t i : indices) decoded->positions.push_back(restored[i]);
  *max_position_error_m = max_error;

  decoded->uvs.clear();
  decoded->colors.clear();
  decoded->atlas.release();
  if (!mesh.atlas.empty()) {
    // An eighth of a texel of the full atlas, at most 16 bits.
    const int atlas_bits =
        static_cast<int>(std::ceil(std::log2(std::max(mesh.atlas.cols, mesh.atlas.rows))));
    const int uv_bits = quality.uv_bits > 0 ? std::min(quality.uv_bits, atlas_bits + 3) : 0;
    chunk.header["uv_bits"] = uv_bits;
    if (uv_bits > 0) {
      std::vector<uint16_t> codes;
      for (const auto& uv : mesh.uvs) {
        Eigen::Vector2f r;
        for (int a = 0; a < 2; ++a) {
          const uint32_t code = Quantise(uv[a], 0.0, 1.0, uv_bits);
          codes.push_back(static_cast<uint16_t>(code));
          r[a] = Dequantise(code, 0.0, 1.0, uv_bits);
        }
        decoded->uvs.push_back(r);
      }
      chunk.AddSection("uvs", Bytes(DeltaEncode(codes, 2)), "deflate");
    } else {
      std::vector<float> raw;
      for (const auto& uv : mesh.uvs) raw.insert(raw.end(), {uv.x(), uv.y()});
      decoded->uvs = mesh.uvs;
      chunk.AddSection("uvs", Bytes(raw), "deflate");
    }
    decoded->atlas = AddAtlas(mesh.atlas, quality, quality.texture_scale, &chunk);
  } else {
    std::vector<uint8_t> rgb;
    for (const auto& c : mesh.colors) rgb.insert(rgb.end(), {c[0], c[1], c[2]});
    chunk.AddSection("colors", Bytes(rgb), "deflate");
    decoded->colors = mesh.colors;
  }
  return chunk;
}

namespace {

// The welded vertices and per-corner indices of a mesh chunk.
void DecodeMeshGeometry(const Chunk& chunk, std::vector<Eigen::Vector3f>* unique,
                        std::vector<uint32_t>* indices) {
  const auto& h = chunk.header;
  const size_t faces = h.at("face_count"), vertices = h.at("vertex_count");
  const int position_bits = h.at("position_bits");
  const Eigen::Vector3d lo = Vec(h.at("box_min")), hi = Vec(h.at("box_max"));
  unique->resize(vertices);
  const std::string positions = SectionBytes(chunk, "positions");
  const bool cells = h.contains("layout");
  if (cells) {
    const auto differences = FromBytePlanes<uint16_t>(positions, 3 * vertices, "positions");
    std::vector<int32_t> codes(differences.size());
    for (size_t i = 0; i < codes.size(); ++i)
      codes[i] = static_cast<uint16_t>(Unzigzag16(differences[i]) + (i >= 3 ? codes[i - 3] : 0));
    for (size_t v = 0; v < vertices; ++v)
      for (int a = 0; a < 3; ++a)
        (*unique)[v][a] = Dequantise(codes[3 * v + a], lo[a], hi[a], position_bits);
  } else if (position_bits > 0) {
    const auto codes = DeltaDecode(Values<uint16_t>(positions, 3 * vertices, "positions"), 3);
    for (size_t v = 0; v < vertices; ++v)
      for (int a = 0; a < 3; ++a)
        (*unique)[v][a] = Dequantise(codes[3 * v + a], lo[a], hi[a], position_bits);
  } else {
    const auto raw = Values<float>(positions, 3 * vertices, "positions");
    for (size_t v = 0; v < vertices; ++v) (*unique)[v] = Eigen::Vector3f(&raw[3 * v]);
  }
  const std::string index_bytes = SectionBytes(chunk, "indices");
  if (!cells) {
    *indices = UndoZigzagDeltas(Values<uint32_t>(index_bytes, 3 * faces, "indices"));
  } else if (h.at("index_bytes") == 2) {
    const auto codes = FromBytePlanes<uint16_t>(index_bytes, 3 * faces, "indices");
    *indices = UndoHighWaterCodes(std::vector<uint32_t>(codes.begin(), codes.end()));
  } else {
    *indices = UndoHighWaterCodes(FromBytePlanes<uint32_t>(index_bytes, 3 * faces, "indices"));
  }
  for (uint32_t i : *indices)
    if (i >= vertices) Fail("chunk index ", i, " names a missing vertex");
}

}  // namespace

TexturedMeshFrame DecodeMesh(const Chunk& chunk) {
  const auto& h = chunk.header;
  const size_t faces = h.at("face_count");
  const int uv_bits = h.at("uv_bits");
  std::vector<Eigen::Vector3f> unique;
  std::vector<uint32_t> indices;
  DecodeMeshGeometry(chunk, &unique, &indices);
  TexturedMeshFrame mesh;
  for (uint32_t i : indices) mesh.positions.push_back(unique[i]);
  if (h.contains("layout")) {
    const CellLayout layout{h.at("layout").at("cell_px"), h.at("layout").at("columns"),
                            h.at("layout").at("rows")};
    for (size_t c = 0; c < 3 * faces; ++c)
      mesh.uvs.push_back(CellCornerUv(c / 3, static_cast<int>(c % 3), layout));
  } else if (h.contains("texture")) {
    const std::string uvs = SectionBytes(chunk, "uvs");
    if (uv_bits > 0) {
      const auto codes = DeltaDecode(Values<uint16_t>(uvs, 6 * faces, "uvs"), 2);
      for (size_t c = 0; c < 3 * faces; ++c)
        mesh.uvs.emplace_back(Dequantise(codes[2 * c], 0, 1, uv_bits),
                              Dequantise(codes[2 * c + 1], 0, 1, uv_bits));
    } else {
      const auto raw = Values<float>(uvs, 6 * faces, "uvs");
      for (size_t c = 0; c < 3 * faces; ++c) mesh.uvs.emplace_back(raw[2 * c], raw[2 * c + 1]);
    }
  }
  if (h.contains("texture")) {
    const std::string image = SectionBytes(chunk, "texture");
    mesh.atlas = cv::imdecode(std::vector<uint8_t>(image.begin(), image.end()), cv::IMREAD_COLOR);
  } else {
    const auto rgb = Values<uint8_t>(SectionBytes(chunk, "colors"), 9 * faces, "colors");
    for (size_t c = 0; c < 3 * faces; ++c)
      mesh.colors.emplace_back(rgb[3 * c], rgb[3 * c + 1], rgb[3 * c + 2]);
  }
  return mesh;
}

// ---------------------------------------------------------------------------------------------
// Volumes: the occupancy, the bricks (occupancy cells) a sample in an occupied cell can read,
// and their voxels as four planes (R, G, B, density), colour on color_bits and density on a
// log scale of density_levels codes (0: none), or float32 when lossless.

namespace {

struct DensityScale {
  double min = 0, max = 0;
  int levels = 0;
  uint8_t Encode(float sigma) const {
    if (!(sigma >= 0.5 * min)) return 0;
    const double t = std::log(std::clamp<double>(sigma, min, max) / min) / std::log(max / min);
    return static_cast<uint8_t>(1 + std::lround(t * (levels - 2)));
  }
  float Decode(uint8_t code) const {
    if (code == 0) return 0.0f;
    return static_cast<float>(min * std::pow(max / min, (code - 1.0) / (levels - 2)));
  }
};

// The bricks to store: occupied cells grown by one cell (trilinear reads reach into them).
std::vector<uint32_t> StoredBricks(const BakedFrame& volume) {
  const int n = volume.occupancy_cells;
  std::vector<uint32_t> bricks;
  if (n == 0) return {0};
  for (int z = 0; z < n; ++z)
    for (int y = 0; y < n; ++y)
      for (int x = 0; x < n; ++x) {
        bool near = false;
        for (int dz = -1; dz <= 1 && !near; ++dz)
          for (int dy = -1; dy <= 1 && !near; ++dy)
            for (int dx = -1; dx <= 1 && !near; ++dx) {
              const int cx = x + dx, cy = y + dy, cz = z + dz;
              if (cx < 0 || cy < 0 || cz < 0 || cx >= n || cy >= n || cz >= n) continue;
              near = volume.occupied[(static_cast<size_t>(cz) * n + cy) * n + cx] != 0;
            }
        if (near) bricks.push_back(static_cast<uint32_t>((z * n + y) * n + x));
      }
  return bricks;
}

// Calls visit(voxel index) for each voxel of each brick, brick by brick, x fastest.
template <typename Visit>
void ForEachBrickVoxel(int grid, int cells, const std::vector<uint32_t>& bricks, Visit visit) {
  const int brick = cells > 0 ? grid / cells : grid, n = std::max(cells, 1);
  for (uint32_t b : bricks) {
    const int bx = b % n, by = (b / n) % n, bz = b / (n * n);
    for (int z = 0; z < brick; ++z)
      for (int y = 0; y < brick; ++y)
        for (int x = 0; x < brick; ++x)
          visit((static_cast<size_t>(bz * brick + z) * grid + by * brick + y) * grid + bx * brick +
                x);
  }
}

}  // namespace

Chunk EncodeVolume(const BakedFrame& volume, int64_t frame, const QualityLevel& quality,
                   double min_transmittance, BakedFrame* decoded) {
  BakedFrame v = volume;
  if (v.occupancy_cells > 0 && v.grid % v.occupancy_cells != 0) {
    v.occupancy_cells = 0;  // bricks must tile the grid: store it whole, skip nothing
    v.occupied.clear();
  }
  const std::vector<uint32_t> bricks = StoredBricks(v);
  const bool lossless = quality.density_levels == 0;
  DensityScale density;
  density.levels = quality.density_levels;
  // Densities below min absorb less than 1e-5 of the light per step: nothing to see.
  density.min = 1e-5 / std::max(v.step_m, 1e-12);
  float max_sigma = 0;
  ForEachBrickVoxel(v.grid, v.occupancy_cells, bricks,
                    [&](size_t i) { max_sigma = std::max(max_sigma, v.rgba[4 * i + 3]); });
  density.max = std::max<double>(max_sigma, 2 * density.min);
  Chunk chunk;
  chunk.header = {
      {"kind", "volume"},
      {"frame", frame},
      {"grid", v.grid},
      {"clamped", v.clamped},
      {"box_min", Vec(v.box.min)},
      {"box_max", Vec(v.box.max)},
      {"occupancy_cells", v.occupancy_cells},
      {"brick", v.occupancy_cells > 0 ? v.grid / v.occupancy_cells : v.grid},
      {"brick_count", bricks.size()},
      {"step_m", v.step_m},
      {"min_transmittance", min_transmittance},
      {"voxel", lossless ? "float32" : "uint8"},
      {"color_bits", quality.color_bits},
      {"density",
       {{"scale", "log"}, {"levels", density.levels}, {"min", density.min}, {"max", density.max}}},
      {"sections", nlohmann::json::array()}};
  chunk.AddSection("occupancy", Bytes(v.occupied), "deflate");
  chunk.AddSection("bricks", Bytes(ZigzagDeltas(bricks)), "deflate");
  *decoded = v;
  std::fill(decoded->rgba.begin(), decoded->rgba.end(), 0.0f);
  const double colour_levels = std::ldexp(1.0, quality.color_bits) - 1;
  std::vector<uint8_t> codes;
  std::vector<float> raw;
  for (int c = 0; c < 4; ++c) {
    ForEachBrickVoxel(v.grid, v.occupancy_cells, bricks, [&](size_t i) {
      const float value = v.rgba[4 * i + c];
      if (lossless) {
        raw.push_back(value);
        decoded->rgba[4 * i + c] = value;
      } else if (c < 3) {
        const auto code =
            static_cast<uint8_t>(std::lround(std::clamp(value, 0.0f, 1.0f) * colour_levels));
        codes.push_back(code);
        decoded->rgba[4 * i + c] = static_cast<float>(code / colour_levels);
      } else {
        codes.push_back(density.Encode(value));
        decoded->rgba[4 * i + c] = density.Decode(codes.back());
      }
    });
  }
  if (!lossless) {
    // Each code as its difference (mod 256) from the one before it in its brick row: smooth
    // colours and densities turn into runs of small values that deflate packs tightly.
    const int brick = chunk.header.at("brick");
    for (size_t i = codes.size(); i-- > 0;)
      if (i % brick != 0) codes[i] = static_cast<uint8_t>(codes[i] - codes[i - 1]);
    chunk.header["voxel_rows"] = "differences";
  }
  chunk.AddSection("voxels", lossless ? Bytes(raw) : Bytes(codes), "deflate");
  return chunk;
}

BakedFrame DecodeVolume(const Chunk& chunk) {
  const auto& h = chunk.header;
  BakedFrame v;
  v.grid = h.at("grid");
  v.clamped = h.at("clamped");
  v.box.min = Vec(h.at("box_min"));
  v.box.max = Vec(h.at("box_max"));
  v.occupancy_cells = h.at("occupancy_cells");
  v.step_m = h.at("step_m");
  const size_t cells =
      static_cast<size_t>(v.occupancy_cells) * v.occupancy_cells * v.occupancy_cells;
  v.occupied = Values<uint8_t>(SectionBytes(chunk, "occupancy"), cells, "occupancy");
  const size_t brick_count = h.at("brick_count");
  const auto bricks =
      UndoZigzagDeltas(Values<uint32_t>(SectionBytes(chunk, "bricks"), brick_count, "bricks"));
  const int brick = h.at("brick");
  const size_t per_plane = brick_count * brick * brick * brick;
  v.rgba.assign(4 * static_cast<size_t>(v.grid) * v.grid * v.grid, 0.0f);
  const std::string voxels = SectionBytes(chunk, "voxels");
  const bool lossless = h.at("voxel") == "float32";
  DensityScale density{h.at("density").at("min"), h.at("density").at("max"),
                       h.at("density").at("levels")};
  const double colour_levels = std::ldexp(1.0, h.at("color_bits").get<int>()) - 1;
  auto codes = lossless ? std::vector<uint8_t>() : Values<uint8_t>(voxels, 4 * per_plane, "voxels");
  for (size_t i = 0; i < codes.size(); ++i)
    if (i % brick != 0) codes[i] = static_cast<uint8_t>(codes[i] + codes[i - 1]);
  const auto raw = lossless ? Values<float>(voxels, 4 * per_plane, "voxels") : std::vector<float>();
  size_t k = 0;
  for (int c = 0; c < 4; ++c) {
    ForEachBrickVoxel(v.grid, v.occupancy_cells, bricks, [&](size_t i) {
      float value = 0;
      if (lossless) {
        value = raw[k];
      } else {
        value = c < 3 ? static_cast<float>(codes[k] / colour_levels) : density.Decode(codes[k]);
      }
      v.rgba[4 * i + c] = value;
      ++k;
    });
  }
  return v;
}

RenderedView RenderBakedFrame(const BakedFrame& volume, const CameraModel& camera,
                              double min_transmittance) {
  OccupancyGrid occupancy;
  occupancy.size = volume.occupancy_cells;
  occupancy.occupied = volume.occupied;
  MarchVolume march;
  march.box_min = volume.box.min.cast<float>();
  march.box_max = volume.box.max.cast<float>();
  march.rgba = volume.rgba.data();
  march.grid = volume.grid;
  march.rgba_clamped = volume.clamped;
  march.occupancy = &occupancy;
  MarchOptions options;
  options.step_m = static_cast<float>(volume.step_m);
  options.min_transmittance = static_cast<float>(min_transmittance);
  const RayBatch rays = CameraRaysAllPixels(camera, march.box_min, march.box_max);
  MarchOutputs outputs;
  MarchPlayback(march, rays, options, &outputs);
  RenderedView view;
  const int w = camera.width(), h = camera.height();
  view.color.create(h, w, CV_32FC3);
  view.alpha.create(h, w, CV_32FC1);
  for (int y = 0, i = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x, ++i) {
      view.color.at<cv::Vec3f>(y, x) =
          cv::Vec3f(outputs.rgb[3 * i], outputs.rgb[3 * i + 1], outputs.rgb[3 * i + 2]);
      view.alpha.at<float>(y, x) = outputs.alpha[i];
    }
  }
  return view;
}

}  // namespace holocap::web
