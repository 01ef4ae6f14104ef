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
#include <map>
#include <set>
#include <unordered_map>

#include "core/error.h"
#include "reconstruction/projector.h"
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

// Global edge id: the voxel at the edge's lower corner (20 bits per axis, +-524288 voxels) and
// the axis (2 bits above them).
uint64_t EdgeKey(const Eigen::Vector3i& voxel, int axis) {
  constexpr int64_t offset = int64_t{1} << 19;
  constexpr uint64_t mask = (uint64_t{1} << 20) - 1;
  return ((static_cast<uint64_t>(voxel.x() + offset) & mask)) |
         ((static_cast<uint64_t>(voxel.y() + offset) & mask) << 20) |
         ((static_cast<uint64_t>(voxel.z() + offset) & mask) << 40) |
         (static_cast<uint64_t>(axis) << 60);
}

struct BlockMesh {
  std::vector<uint64_t> vertex_keys;
  std::vector<Eigen::Vector3f> positions;
  std::vector<Eigen::Vector3f> colors;
  std::vector<Eigen::Vector3i> faces;  // indices into this block's vertices
};

}  // namespace

void MeshingOptions::Check() const {
  if (!(min_weight >= 0)) Fail("meshing min_weight must be >= 0 (got ", min_weight, ")");
  if (!(simplify_cell_m >= 0))
    Fail("meshing simplify_cell_m must be >= 0 (got ", simplify_cell_m, ")");
}

Mesh ExtractMesh(const SparseVolume& volume, const MeshingOptions& options) {
  options.Check();
  const CubeTables& tables = Tables();
  const std::vector<Eigen::Vector3i> coordinates = volume.BlockCoordinates();
  const double voxel = volume.voxel_m();
  const float truncation = static_cast<float>(volume.truncation_m());
  const bool truncated = std::isfinite(truncation);
  bool any_color = false;
  volume.ForEachBlock([&](const Eigen::Vector3i&, const VoxelBlock& block) {
    if (any_color) return;
    for (const Voxel& v : block.voxels) {
      if (v.weight > 0 && (v.r | v.g | v.b)) {
        any_color = true;
        return;
      }
    }
  });
  std::vector<BlockMesh> parts(coordinates.size());
#pragma omp parallel for schedule(dynamic, 8)
  for (size_t bi = 0; bi < coordinates.size(); ++bi) {
    const Eigen::Vector3i block = coordinates[bi];
    // This block and its seven positive neighbours cover every cube whose lower corner is in it.
    const VoxelBlock* neighbours[8];
    for (int n = 0; n < 8; ++n) neighbours[n] = volume.Find(block + CornerOffset(n));
    auto voxel_at = [&](int x, int y, int z) -> const Voxel* {
      int n = (x >= kBlockSide) | ((y >= kBlockSide) << 1) | ((z >= kBlockSide) << 2);
      const VoxelBlock* data = neighbours[n];
      if (data == nullptr) return nullptr;
      return &data->at(x % kBlockSide, y % kBlockSide, z % kBlockSide);
    };
    BlockMesh& part = parts[bi];
    std::unordered_map<uint64_t, int> local;
    for (int z = 0; z < kBlockSide; ++z) {
      for (int y = 0; y < kBlockSide; ++y) {
        for (int x = 0; x < kBlockSide; ++x) {
          const Voxel* corners[8];
          int mask = 0;
          bool usable = true;
          for (int c = 0; c < 8; ++c) {
            Eigen::Vector3i o = CornerOffset(c);
            corners[c] = voxel_at(x + o.x(), y + o.y(), z + o.z());
            if (corners[c] == nullptr || corners[c]->weight <= options.min_weight) {
              usable = false;
              break;
            }
            if (corners[c]->sdf < 0) mask |= 1 << c;
          }
          if (!usable || mask == 0 || mask == 255) continue;
          if (truncated) {
            // A sign change between two truncated values is a jump across space no sensor
            // resolved (the back of a thin part, an occlusion edge): no surface there.
            bool jump = false;
            for (const EdgeDef& e : tables.edges) {
              float a = corners[e.c0]->sdf, b = corners[e.c1]->sdf;
              if ((a < 0) != (b < 0) && std::abs(a) >= 0.999f * truncation &&
                  std::abs(b) >= 0.999f * truncation) {
                jump = true;
                break;
              }
            }
            if (jump) continue;
          }
          const Eigen::Vector3i origin = block * kBlockSide + Eigen::Vector3i(x, y, z);
          int ids[12];
          for (const auto& tri : tables.triangles[mask]) {
            for (int k = 0; k < 3; ++k) {
              const EdgeDef& e = tables.edges[tri[k]];
              uint64_t key = EdgeKey(origin + CornerOffset(e.c0), e.axis);
              auto [it, inserted] = local.try_emplace(key, static_cast<int>(part.positions.size()));
              if (inserted) {
                const Voxel& a = *corners[e.c0];
                const Voxel& b = *corners[e.c1];
                float t = a.sdf / (a.sdf - b.sdf);
                Eigen::Vector3f pa = (origin + CornerOffset(e.c0)).cast<float>();
                Eigen::Vector3f pb = (origin + CornerOffset(e.c1)).cast<float>();
                part.positions.push_back(((1 - t) * pa + t * pb) * static_cast<float>(voxel));
                part.colors.push_back((1 - t) * Eigen::Vector3f(a.r, a.g, a.b) +
                                      t * Eigen::Vector3f(b.r, b.g, b.b));
                part.vertex_keys.push_back(key);
              }
              ids[k] = it->second;
            }
            if (ids[0] != ids[1] && ids[1] != ids[2] && ids[0] != ids[2]) {
              part.faces.emplace_back(ids[0], ids[1], ids[2]);
            }
          }
        }
      }
    }
  }
  // Weld: a vertex on a block boundary is produced by every block whose cubes use its edge.
  Mesh mesh;
  std::unordered_map<uint64_t, int> global;
  for (const BlockMesh& part : parts) {
    std::vector<int> remap(part.positions.size());
    for (size_t i = 0; i < part.positions.size(); ++i) {
      auto [it, inserted] =
          global.try_emplace(part.vertex_keys[i], static_cast<int>(mesh.vertices.size()));
      if (inserted) {
        mesh.vertices.push_back(part.positions[i]);
        if (any_color) {
          Eigen::Vector3f c = part.colors[i].array().round().min(255.0f).max(0.0f);
          mesh.colors.push_back(c.cast<uint8_t>());
        }
      }
      remap[i] = it->second;
    }
    for (const auto& f : part.faces)
      mesh.faces.emplace_back(remap[f.x()], remap[f.y()], remap[f.z()]);
  }
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
    auto [it, inserted] = cell_index.try_emplace(EdgeKey(cell, 0), static_cast<int>(sums.size()));
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
