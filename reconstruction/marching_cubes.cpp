// Marching cubes over the sparse volume, and vertex-clustering simplification.
//
// The triangle table is derived, not transcribed: for each of the 256 sign cases, every cube
// face contributes segments that cut off its runs of inside corners (walking the face
// counter-clockwise seen from outside), and the segments chain into closed loops because each
// crossed edge starts a segment on one face and ends one on the other. The decision on an
// ambiguous face depends only on that face's corners, so two cubes sharing it always cut it
// the same way and the surface has no cracks.
#include <omp.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <map>
#include <set>
#include <unordered_map>

#include "core/check_option.h"
#include "core/error.h"
#include "core/projector.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

namespace {

// Corner c sits at (c & 1, (c >> 1) & 1, (c >> 2) & 1).
Eigen::Vector3i CornerOffset(int c) { return {c & 1, (c >> 1) & 1, (c >> 2) & 1}; }

struct EdgeDef {
  int c0, c1, axis;
};

struct CubeTables {
  std::array<EdgeDef, 12> edges;
  std::array<std::vector<std::array<int, 3>>, 256> triangles;  // edge ids
};

CubeTables BuildTables() {
  CubeTables tables;
  int count = 0;
  std::map<std::pair<int, int>, int> edge_of;
  for (int axis = 0; axis < 3; ++axis) {
    for (int c = 0; c < 8; ++c) {
      if (c & (1 << axis)) continue;
      tables.edges[count] = {c, c | (1 << axis), axis};
      edge_of[{c, c | (1 << axis)}] = edge_of[{c | (1 << axis), c}] = count;
      ++count;
    }
  }
  // Faces as corner cycles, counter-clockwise seen from outside the cube.
  std::vector<std::array<int, 4>> faces;
  for (int axis = 0; axis < 3; ++axis) {
    int b = (axis + 1) % 3, c = (axis + 2) % 3;
    for (int side = 0; side < 2; ++side) {
      std::array<int, 4> cycle;
      const int square[4][2] = {{0, 0}, {1, 0}, {1, 1}, {0, 1}};
      for (int i = 0; i < 4; ++i) {
        cycle[i] = (side << axis) | (square[i][0] << b) | (square[i][1] << c);
      }
      Eigen::Vector3d p0 = CornerOffset(cycle[0]).cast<double>();
      Eigen::Vector3d p1 = CornerOffset(cycle[1]).cast<double>();
      Eigen::Vector3d p2 = CornerOffset(cycle[2]).cast<double>();
      Eigen::Vector3d outward = Eigen::Vector3d::Zero();
      outward[axis] = side ? 1 : -1;
      if ((p1 - p0).cross(p2 - p1).dot(outward) < 0) std::reverse(cycle.begin(), cycle.end());
      faces.push_back(cycle);
    }
  }
  auto loops_of = [&](int mask) {
    std::map<int, int> next;  // segment start edge -> end edge
    for (const auto& cycle : faces) {
      bool in[4];
      for (int i = 0; i < 4; ++i) in[i] = (mask >> cycle[i]) & 1;
      for (int i = 0; i < 4; ++i) {
        int prev = (i + 3) % 4;
        if (in[prev] || !in[i]) continue;  // not the start of an inside run
        int j = i;
        while (in[(j + 1) % 4]) j = (j + 1) % 4;
        int enter = edge_of[{cycle[prev], cycle[i]}];
        int exit = edge_of[{cycle[j], cycle[(j + 1) % 4]}];
        next[enter] = exit;
      }
    }
    std::vector<std::vector<int>> loops;
    while (!next.empty()) {
      std::vector<int> loop;
      int start = next.begin()->first, e = start;
      do {
        loop.push_back(e);
        int n = next.at(e);
        next.erase(e);
        e = n;
      } while (e != start);
      loops.push_back(loop);
    }
    return loops;
  };
  // Returns a vector, not an Eigen expression: an expression would refer to the corner
  // temporaries after they are gone (and read whatever the stack then holds).
  auto midpoint = [&](int e) -> Eigen::Vector3d {
    return 0.5 *
           (CornerOffset(tables.edges[e].c0) + CornerOffset(tables.edges[e].c1)).cast<double>();
  };
  // Orientation is fixed once, from the case with only corner 0 inside, to the winding whose
  // triangles face away from the inside corner in extracted meshes (the tests check every face
  // of closed surfaces).
  bool flip = false;
  {
    auto loop = loops_of(1).at(0);
    Eigen::Vector3d normal =
        (midpoint(loop[1]) - midpoint(loop[0])).cross(midpoint(loop[2]) - midpoint(loop[0]));
    flip = normal.dot(Eigen::Vector3d(1, 1, 1)) < 0;
  }
  for (int mask = 0; mask < 256; ++mask) {
    for (auto loop : loops_of(mask)) {
      if (flip) std::reverse(loop.begin(), loop.end());
      for (size_t i = 1; i + 1 < loop.size(); ++i) {
        tables.triangles[mask].push_back({loop[0], loop[i], loop[i + 1]});
      }
    }
  }
  return tables;
}

const CubeTables& Tables() {
  static const CubeTables tables = BuildTables();
  return tables;
}

// A cell's key: 20 bits per axis (+-524288 cells).
uint64_t CellKey(const Eigen::Vector3i& cell) {
  constexpr int64_t offset = int64_t{1} << 19;
  constexpr uint64_t mask = (uint64_t{1} << 20) - 1;
  return ((static_cast<uint64_t>(cell.x() + offset) & mask)) |
         ((static_cast<uint64_t>(cell.y() + offset) & mask) << 20) |
         ((static_cast<uint64_t>(cell.z() + offset) & mask) << 40);
}

// The crossed edges a block owns: edge (voxel v, axis a) runs from v to v + unit(a), and the
// block holding v owns it. A bit per edge (id (voxel index) * 3 + axis) with running counts, so
// that a cube in any block finds an edge's vertex without a hash map.
struct BlockEdges {
  static constexpr int kWords = kBlockVoxels * 3 / 64;
  std::array<uint64_t, kWords> bits{};
  std::array<uint16_t, kWords> before{};  // crossed edges in the words before each
  int64_t base = 0;                       // the first vertex's index in the whole mesh
  std::vector<Eigen::Vector3f> positions;
  std::vector<Eigen::Vector3f> colors;

  bool Has(int edge) const { return (bits[edge >> 6] >> (edge & 63)) & 1; }
  int64_t Vertex(int edge) const {
    const uint64_t below = bits[edge >> 6] & ((uint64_t{1} << (edge & 63)) - 1);
    return base + before[edge >> 6] + __builtin_popcountll(below);
  }
};

// Edge id of voxel (x, y, z) of a block along `axis`.
int EdgeId(int x, int y, int z, int axis) {
  return ((z * kBlockSide + y) * kBlockSide + x) * 3 + axis;
}

// A block's voxel at (x, y, z), each coordinate in [0, 2 * kBlockSide): this block or one of
// its seven positive neighbours (`near`, by CornerOffset index; nullptr where not allocated).
const Voxel* VoxelNear(const VoxelBlock* const* near, int x, int y, int z) {
  const int n = (x >= kBlockSide) | ((y >= kBlockSide) << 1) | ((z >= kBlockSide) << 2);
  return near[n] == nullptr ? nullptr
                            : &near[n]->at(x % kBlockSide, y % kBlockSide, z % kBlockSide);
}

// Blocks by index, each with the indices of its seven positive neighbours (-1: none).
struct BlockIndex {
  std::vector<Eigen::Vector3i> coordinates;
  std::vector<const VoxelBlock*> data;
  std::vector<std::array<int, 8>> near;  // by CornerOffset index; near[b][0] == b

  explicit BlockIndex(const SparseVolume& volume) : coordinates(volume.BlockCoordinates()) {
    std::unordered_map<uint64_t, int> index_of;
    index_of.reserve(coordinates.size());
    data.resize(coordinates.size());
    for (size_t i = 0; i < coordinates.size(); ++i) {
      index_of.emplace(SparseVolume::Key(coordinates[i]), static_cast<int>(i));
      data[i] = volume.Find(coordinates[i]);
    }
    near.resize(coordinates.size());
    for (size_t i = 0; i < coordinates.size(); ++i) {
      for (int n = 0; n < 8; ++n) {
        const auto it = index_of.find(SparseVolume::Key(coordinates[i] + CornerOffset(n)));
        near[i][n] = it == index_of.end() ? -1 : it->second;
      }
    }
  }
  void Neighbours(size_t b, const VoxelBlock** out) const {
    for (int n = 0; n < 8; ++n) out[n] = near[b][n] < 0 ? nullptr : data[near[b][n]];
  }
};

// Block b's crossed edges (a sign change between two voxels both observed with more than
// `min_weight`) and their vertices, interpolated where the signed distance is zero.
void CrossedEdges(const BlockIndex& index, size_t b, float min_weight, double voxel,
                  BlockEdges* out) {
  const VoxelBlock* near[8];
  index.Neighbours(b, near);
  const Eigen::Vector3i base = index.coordinates[b] * kBlockSide;
  for (int z = 0; z < kBlockSide; ++z) {
    for (int y = 0; y < kBlockSide; ++y) {
      for (int x = 0; x < kBlockSide; ++x) {
        const Voxel& a = near[0]->at(x, y, z);
        if (!(a.weight > min_weight)) continue;
        for (int axis = 0; axis < 3; ++axis) {
          const Eigen::Vector3i to = Eigen::Vector3i(x, y, z) + Eigen::Vector3i::Unit(axis);
          const Voxel* other = VoxelNear(near, to.x(), to.y(), to.z());
          if (other == nullptr || !(other->weight > min_weight) || (a.sdf < 0) == (other->sdf < 0))
            continue;
          const int edge = EdgeId(x, y, z, axis);
          out->bits[edge >> 6] |= uint64_t{1} << (edge & 63);
          const float t = a.sdf / (a.sdf - other->sdf);
          const Eigen::Vector3f pa = (base + Eigen::Vector3i(x, y, z)).cast<float>();
          const Eigen::Vector3f pb = (base + to).cast<float>();
          out->positions.push_back(((1 - t) * pa + t * pb) * static_cast<float>(voxel));
          out->colors.push_back((1 - t) * Eigen::Vector3f(a.r, a.g, a.b) +
                                t * Eigen::Vector3f(other->r, other->g, other->b));
        }
      }
    }
  }
  int count = 0;
  for (int w = 0; w < BlockEdges::kWords; ++w) {
    out->before[w] = static_cast<uint16_t>(count);
    count += __builtin_popcountll(out->bits[w]);
  }
}

// The triangles of the cubes whose lower corner is in block b, as indices of the whole mesh's
// vertices (`edges`: every block's crossed edges, their bases set).
void BlockFaces(const BlockIndex& index, const std::vector<BlockEdges>& edges, size_t b,
                float min_weight, float truncation, std::vector<Eigen::Vector3i>* faces) {
  const CubeTables& tables = Tables();
  const bool truncated = std::isfinite(truncation);
  const VoxelBlock* near[8];
  index.Neighbours(b, near);
  for (int z = 0; z < kBlockSide; ++z) {
    for (int y = 0; y < kBlockSide; ++y) {
      for (int x = 0; x < kBlockSide; ++x) {
        const Voxel* corners[8];
        int mask = 0;
        bool usable = true;
        for (int c = 0; c < 8 && usable; ++c) {
          corners[c] = VoxelNear(near, x + (c & 1), y + ((c >> 1) & 1), z + ((c >> 2) & 1));
          usable = corners[c] != nullptr && corners[c]->weight > min_weight;
          if (usable && corners[c]->sdf < 0) mask |= 1 << c;
        }
        if (!usable || mask == 0 || mask == 255) continue;
        if (truncated) {
          // A sign change between two truncated values is a jump across space no sensor
          // resolved (the back of a thin part, an occlusion edge): no surface there.
          bool jump = false;
          for (const EdgeDef& e : tables.edges) {
            const float p = corners[e.c0]->sdf, q = corners[e.c1]->sdf;
            jump |= (p < 0) != (q < 0) && std::abs(p) >= 0.999f * truncation &&
                    std::abs(q) >= 0.999f * truncation;
          }
          if (jump) continue;
        }
        for (const auto& tri : tables.triangles[mask]) {
          int64_t ids[3];
          for (int k = 0; k < 3; ++k) {
            const EdgeDef& e = tables.edges[tri[k]];
            const int ox = x + (e.c0 & 1), oy = y + ((e.c0 >> 1) & 1), oz = z + ((e.c0 >> 2) & 1);
            const int n =
                (ox >= kBlockSide) | ((oy >= kBlockSide) << 1) | ((oz >= kBlockSide) << 2);
            const BlockEdges& owner = edges[index.near[b][n]];
            const int edge = EdgeId(ox % kBlockSide, oy % kBlockSide, oz % kBlockSide, e.axis);
            if (!owner.Has(edge)) Fail("marching cubes: a crossed edge has no vertex");
            ids[k] = owner.Vertex(edge);
          }
          faces->emplace_back(static_cast<int>(ids[0]), static_cast<int>(ids[1]),
                              static_cast<int>(ids[2]));
        }
      }
    }
  }
}

}  // namespace

void MeshingOptions::Check() const {
  HOLOCAP_CHECK_OPTION_GE(min_weight, 0);
  HOLOCAP_CHECK_OPTION_GE(simplify_cell_m, 0);
}

// Two passes over the blocks in parallel: every crossed edge's vertex, made once by the block
// that owns the edge (so nothing is welded afterwards), then every cube's triangles, which find
// their vertices through the owners' edge bits. Vertices no triangle uses (an edge whose cubes
// all touch an unobserved voxel or a jump) are left out at the end.
Mesh ExtractMesh(const SparseVolume& volume, const MeshingOptions& options) {
  options.Check();
  const BlockIndex index(volume);
  const size_t count = index.coordinates.size();
  const float min_weight = options.min_weight;
  const float truncation = static_cast<float>(volume.truncation_m());
  bool any_color = false;
  for (size_t b = 0; b < count && !any_color; ++b) {
    for (const Voxel& v : index.data[b]->voxels) any_color |= v.weight > 0 && (v.r | v.g | v.b);
  }
  std::vector<BlockEdges> edges(count);
#pragma omp parallel for schedule(dynamic, 16)
  for (size_t b = 0; b < count; ++b)
    CrossedEdges(index, b, min_weight, volume.voxel_m(), &edges[b]);
  int64_t vertices = 0;
  for (BlockEdges& e : edges)
    e.base = vertices, vertices += static_cast<int64_t>(e.positions.size());
  if (vertices > std::numeric_limits<int>::max()) Fail("marching cubes: too many vertices");
  std::vector<std::vector<Eigen::Vector3i>> faces(count);
#pragma omp parallel for schedule(dynamic, 16)
  for (size_t b = 0; b < count; ++b) BlockFaces(index, edges, b, min_weight, truncation, &faces[b]);
  // Keep the vertices that faces use, in their order.
  std::vector<int> remap(vertices, -1);
  for (const auto& part : faces)
    for (const auto& f : part) remap[f.x()] = remap[f.y()] = remap[f.z()] = 0;
  Mesh mesh;
  int64_t v = 0;
  for (const BlockEdges& e : edges) {
    for (size_t i = 0; i < e.positions.size(); ++i, ++v) {
      if (remap[v] < 0) continue;
      remap[v] = static_cast<int>(mesh.vertices.size());
      mesh.vertices.push_back(e.positions[i]);
      if (any_color) {
        const Eigen::Vector3f c = e.colors[i].array().round().min(255.0f).max(0.0f);
        mesh.colors.push_back(c.cast<uint8_t>());
      }
    }
  }
  size_t face_count = 0;
  for (const auto& part : faces) face_count += part.size();
  mesh.faces.reserve(face_count);
  for (const auto& part : faces)
    for (const auto& f : part) mesh.faces.emplace_back(remap[f.x()], remap[f.y()], remap[f.z()]);
  if (options.simplify_cell_m > 0) mesh = SimplifyMesh(mesh, options.simplify_cell_m);
  if (options.normals && !mesh.empty()) mesh.ComputeNormals();
  return mesh;
}

Mesh SimplifyMesh(const Mesh& mesh, double cell_m) {
  if (!(cell_m > 0)) Fail("simplification cell must be > 0 (got ", cell_m, ")");
  std::unordered_map<uint64_t, int> cell_index;
  std::vector<int> cluster(mesh.vertices.size());
  std::vector<Eigen::Vector3d> sums;
  std::vector<Eigen::Vector3d> color_sums;
  std::vector<int> counts;
  const bool has_color = mesh.colors.size() == mesh.vertices.size();
  for (size_t i = 0; i < mesh.vertices.size(); ++i) {
    Eigen::Vector3i cell = (mesh.vertices[i].cast<double>() / cell_m).array().floor().cast<int>();
    auto [it, inserted] = cell_index.try_emplace(CellKey(cell), static_cast<int>(sums.size()));
    if (inserted) {
      sums.emplace_back(Eigen::Vector3d::Zero());
      color_sums.emplace_back(Eigen::Vector3d::Zero());
      counts.push_back(0);
    }
    cluster[i] = it->second;
    sums[it->second] += mesh.vertices[i].cast<double>();
    if (has_color) color_sums[it->second] += mesh.colors[i].cast<double>();
    ++counts[it->second];
  }
  Mesh out;
  for (size_t c = 0; c < sums.size(); ++c) {
    out.vertices.push_back((sums[c] / counts[c]).cast<float>());
    if (has_color) {
      out.colors.push_back((color_sums[c] / counts[c]).array().round().cast<uint8_t>().matrix());
    }
  }
  std::set<std::array<int, 3>> seen;
  for (const auto& f : mesh.faces) {
    int a = cluster[f.x()], b = cluster[f.y()], c = cluster[f.z()];
    if (a == b || b == c || a == c) continue;
    // The same triangle (in any rotation or winding) once only.
    std::array<int, 3> sorted = {a, b, c};
    std::sort(sorted.begin(), sorted.end());
    if (!seen.insert(sorted).second) continue;
    out.faces.emplace_back(a, b, c);
  }
  if (!mesh.normals.empty()) out.ComputeNormals();
  return out;
}

}  // namespace holocap
