// The chunks of the web stream format (README "The stream format"), encoded and decoded
// natively: the export writes them, measures what they lose by decoding them exactly as the
// player does, and the tests decode them to check the player. Internal to holocap_playback.
#pragma once

#include <array>
#include <cstdint>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "avatar/avatar.h"
#include "playback/playback.h"
#include "splat/kernels.h"

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
  int color_bits = 8;            // volume colour per channel; 0 with density_levels 0: float32
  int density_levels = 256;      // volume density codes (log scale), 0: float32
  int splat_position_bits = 16;  // splat centres per axis over the stream's box; 0: every
                                 // splat value float32
  int splat_sh_degree = 3;       // spherical-harmonic degree streamed (at most the model's)
  int splat_rest_bits = 6;       // spherical-harmonic coefficients above degree 0
};
// Throws Error naming the unknown level and the known ones.
QualityLevel QualityByName(const std::string& name);

inline constexpr char kChunkMagic[9] = "HOLOCAPC";

// A chunk: magic, u32 format version, u32 header size, the JSON header (kind, frame, sections
// [{name, offset, bytes, codec, raw_bytes}], the kind's fields), then the sections' bytes.
// (nlohmann::json's default constructor checks its invariant with an assertion that clang-tidy
// counts as a throw; it throws nothing.)
// NOLINTNEXTLINE(bugprone-exception-escape)
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

// Uniform quantisation of [lo, hi] on `bits` bits (values outside clamped) and back.
uint32_t Quantise(double value, double lo, double hi, int bits);
float Dequantise(uint32_t code, double lo, double hi, int bits);

// A splat stream's quantisation, the same for every chunk of the stream (so that a Gaussian whose
// codes stay the same from one frame to the next costs nothing in a delta). Every chunk's header
// carries it as `encoding`.
struct SplatEncoding {
  bool float32 = false;  // every value as the model stores it (lossless)
  int position_bits = 16;
  Eigen::Vector3d box_min = Eigen::Vector3d::Zero(), box_max = Eigen::Vector3d::Ones();
  int rotation_bits = 10;  // smallest three of the unit quaternion
  int scale_bits = 8;      // log-scales over [log_scale_min, log_scale_max]
  double log_scale_min = 0, log_scale_max = 0;
  int opacity_bits = 8;  // sigmoid(logit) over [0, 1]
  int sh_degree = 0;     // the degree streamed
  int dc_bits = 8;       // degree-0 coefficients over [dc_min, dc_max]
  double dc_min = 0, dc_max = 0;
  int rest_bits = 6;  // higher coefficients over [-rest_max, rest_max]
  double rest_max = 0;
  // Deltas (quantised only): each survivor's position is its code in the frame before, plus the
  // mean motion of its cell (cells of 2^motion_cell_bits codes a side, over the frame before's
  // codes), plus a residual in steps of motion_step codes, chosen against what the decoder
  // holds (so that errors do not accumulate).
  int motion_cell_bits = 6;
  int motion_step = 1;
  // The other groups of a survivor are sent again only when a code moved more than `hold` steps
  // from what the decoder holds (rotation: a component of the quaternion, in its steps).
  int hold = 0;
  // The encoder's choices (recorded, not needed to decode): Gaussians fainter than
  // prune_opacity are left out of the stream; a survivor's position residual stays 0 while
  // its error is within dead_zone motion steps, widened up to 8 times for faint Gaussians
  // (0.5 / opacity).
  double prune_opacity = 0;
  double dead_zone = 0.5;

  // The encoding of a quality level for Gaussians of at most `model_degree` (ranges empty until
  // Include widens them over every frame of the stream).
  static SplatEncoding For(const QualityLevel& quality, int model_degree);
  void Include(const splat::Gaussians& gaussians);
  nlohmann::json ToJson() const;
  static SplatEncoding FromJson(const nlohmann::json& json);  // throws Error
  // Bytes per Gaussian of each attribute group: position, rotation, scale, opacity, colour.
  std::array<size_t, 5> RecordBytes() const;
};
// The rungs a size budget (`export web --splat-mbps`) climbs down, coarsest last: rung 0 is the
// level's own encoding, each later one fewer bits, larger motion steps and holds, fainter
// Gaussians pruned (never more bits or a higher degree than the level's). Ranges as `level`'s.
inline constexpr int kSplatRungs = 12;
SplatEncoding SplatRung(const SplatEncoding& level, int rung);
// A delta's rung: what a delta that follows a key frame at `key_rung` can change (a delta's
// records are byte differences from the frame before's, so it keeps the key frame's bits and
// degree): rung `rung`'s motion step (in the key frame's position codes), hold, pruning and
// dead zone, never finer than the key frame's. The key frame's encoding where rung <= key_rung.
SplatEncoding SplatDeltaRung(const SplatEncoding& level, int key_rung, int rung);
inline constexpr int kSplatGroups = 5;
inline constexpr const char* kSplatGroupNames[kSplatGroups] = {"position", "rotation", "scale",
                                                               "opacity", "color"};

// A splat frame as a decoder holds it: each Gaussian's codes per attribute group, RecordBytes()
// bytes a Gaussian, Gaussian after Gaussian (what the next frame's delta refers to).
struct SplatCodes {
  int64_t count = 0;
  std::array<std::string, kSplatGroups> records;
  // The encoder's side only: the Gaussian of the model's frame each record stands for (the
  // stream orders Gaussians its own way: a key frame in Morton order of their positions, a delta
  // its survivors in the frame before's order, then the added ones in Morton order).
  std::vector<int64_t> order;
};
SplatCodes QuantiseSplats(const splat::Gaussians& gaussians, const SplatEncoding& encoding);
// The Gaussians the codes stand for (degree encoding.sh_degree, raw parameters as the kernels
// take them).
splat::Gaussians SplatsFromCodes(const SplatCodes& codes, const SplatEncoding& encoding);
// Encodes a frame of Gaussians: a key frame when `previous` is null, else a delta of the frame
// before as decoded (`origin[i]`: the index in the model's frame before that Gaussian i continues,
// ascending over the survivors, or -1 for an added one; previous->order maps it to the stream's
// order). `codes` receives the frame's codes as the decoder reads them, with their order.
Chunk EncodeSplats(const splat::Gaussians& gaussians, int64_t frame, const SplatEncoding& encoding,
                   const SplatCodes* previous, const std::vector<int64_t>& origin,
                   SplatCodes* codes);
// Decodes a splat chunk; a delta needs the frame before's codes. Throws Error for a chunk that
// is corrupt or does not follow `previous`.
SplatCodes DecodeSplats(const Chunk& chunk, const SplatCodes* previous);

// The player's files (index.html and its modules), embedded at build time: path -> bytes.
const std::vector<std::pair<std::string, std::string>>& PlayerFiles();

}  // namespace holocap::web
