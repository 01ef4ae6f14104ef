// The chunks of the web stream format (README "The stream format"), encoded and decoded
// natively: the export writes them, measures what they lose by decoding them exactly as the
// player does, and the tests decode them to check the player. Internal to holocap_playback.
#pragma once

#include <cstdint>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "neural/neural.h"
#include "playback/playback.h"

namespace holocap::web {

// What each quality level keeps.
struct QualityLevel {
  std::string name;
  int position_bits = 16;     // mesh vertices per axis over the frame's box; 0: float32
  int uv_bits = 16;           // texture coordinates; 0: float32
  double simplify_edges = 0;  // mesh error bound in median edges of the frame's mesh (about the
                              // reconstruction's voxel); 0: every face kept, atlas as recorded
  int cell_px = 8;            // simplified meshes: side of an atlas cell (two faces per cell)
  const char* texture_codec = "webp";  // "webp" | "jpeg" | "png"
  int texture_quality = 80;            // WebP/JPEG quality (1..100)
  double texture_scale = 1.0;          // atlas size kept
  int color_bits = 8;        // volume colour per channel; 0 with density_levels 0: float32
  int density_levels = 256;  // volume density codes (log scale), 0: float32
};
// Throws Error naming the unknown level and the known ones.
QualityLevel QualityByName(const std::string& name);

inline constexpr char kChunkMagic[9] = "HOLOCAPC";

// A chunk: magic, u32 format version, u32 header size, the JSON header (kind, frame, sections
// [{name, offset, bytes, codec, raw_bytes}], the kind's fields), then the sections' bytes.
struct Chunk {
  nlohmann::json header;
  std::string payload;
  // Appends a section, deflating it when codec is "deflate" (zlib stream).
  void AddSection(const std::string& name, const std::string& bytes, const std::string& codec);
  std::string Serialise() const;
};
// Parses a chunk; throws Error for a bad magic, an unknown version or a truncated chunk.
Chunk ParseChunk(const std::string& bytes);
// A section's bytes, inflated when deflated (other codecs are returned as stored).
std::string SectionBytes(const Chunk& chunk, const std::string& name);

// The atlas layout of simplified meshes: face f lies in cell f / 2 (row by row, `columns` cells
// of cell_px texels a row, `rows` rows), in the cell's lower (even f) or upper (odd f) half,
// inset so that bilinear reads inside a half stay in it. The layout fixes every texture
// coordinate, so the stream carries none.
struct CellLayout {
  int cell_px = 8;
  int columns = 1;
  int rows = 1;
};
CellLayout CellLayoutFor(size_t faces, int cell_px);
// Texture coordinate (glTF convention, v down) of corner 0..2 of face `face`.
Eigen::Vector2f CellCornerUv(size_t face, int corner, const CellLayout& layout);

// A mesh as the simplified stream carries it: welded vertices in order of first use, faces in
// vertex-cache order, the atlas in the cell layout.
struct CellMesh {
  std::vector<Eigen::Vector3f> vertices;
  std::vector<uint32_t> indices;  // 3 per face
  CellLayout layout;
  cv::Mat atlas;                    // CV_8UC3 BGR
  double error_m = 0;               // the simplifier's error estimate
  double max_texel_distance_m = 0;  // texels to the original surface they were coloured from
};
// Welds corners with equal positions: unique positions and one index per corner.
void WeldCorners(const std::vector<Eigen::Vector3f>& corners, std::vector<Eigen::Vector3f>* unique,
                 std::vector<uint32_t>* indices);
// Median edge length of a mesh (marching cubes: about its voxel), 0 without faces.
double MedianEdgeM(const TexturedMeshFrame& mesh);
// Simplifies (meshoptimizer, error bound max_error_m; 0 keeps every face), reorders and re-bakes
// the atlas from the original textured surface.
CellMesh SimplifyForStream(const TexturedMeshFrame& mesh, double max_error_m, int cell_px);
// Fills cells->atlas: each texel the colour of the original surface's nearest point within
// reach_m (grey beyond).
void BakeCellAtlas(const TexturedMeshFrame& original, double reach_m, CellMesh* cells);
// Bilinear read (BGR in [0, 1]) of an atlas at texture coordinate (u, v), clamped at its edges.
cv::Vec3f SampleAtlas(const cv::Mat& atlas, float u, float v);

// Encodes one frame's textured mesh; `decoded` receives what a decoder reads back.
Chunk EncodeMesh(const TexturedMeshFrame& mesh, int64_t frame, const QualityLevel& quality,
                 TexturedMeshFrame* decoded, double* max_position_error_m);
TexturedMeshFrame DecodeMesh(const Chunk& chunk);

// Encodes one frame's baked volume as occupied bricks; `decoded` receives what a decoder reads.
Chunk EncodeVolume(const BakedFrame& volume, int64_t frame, const QualityLevel& quality,
                   double min_transmittance, BakedFrame* decoded);
BakedFrame DecodeVolume(const Chunk& chunk);

// A baked volume marched through a camera exactly as the native renderer marches it (same
// samples, skipping and stopping).
RenderedView RenderBakedFrame(const BakedFrame& volume, const CameraModel& camera,
                              double min_transmittance);

// The player's files (index.html and its modules), embedded at build time: path -> bytes.
const std::vector<std::pair<std::string, std::string>>& PlayerFiles();

}  // namespace holocap::web
