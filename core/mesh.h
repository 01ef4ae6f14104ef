// Triangle meshes and point clouds, with PLY input/output (binary little-endian, or ASCII on
// read) that standard viewers open.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <filesystem>
#include <vector>

namespace holocap {

struct Mesh {
  std::vector<Eigen::Vector3f> vertices;             // in world coordinates, metres
  std::vector<Eigen::Vector3i> faces;                // counter-clockwise seen from outside
  std::vector<Eigen::Vector3f> normals;              // per vertex, optional (empty or sized)
  std::vector<Eigen::Matrix<uint8_t, 3, 1>> colors;  // per vertex RGB, optional

  bool empty() const { return vertices.empty(); }
  // Recomputes area-weighted per-vertex normals.
  void ComputeNormals();
  // Appends another mesh (indices shifted).
  void Append(const Mesh& other);
  double SurfaceArea() const;
  // Uniform random points on the surface (area-weighted), deterministic for a seed.
  std::vector<Eigen::Vector3d> SampleSurface(size_t count, uint64_t seed) const;
};

// The vertices each vertex shares a face edge with, as compressed rows: vertex i's are
// neighbours[start[i]] .. neighbours[start[i + 1] - 1]. An edge is listed once for every face
// that has it (an edge of two faces twice).
struct VertexNeighbours {
  std::vector<int32_t> start, neighbours;
};
VertexNeighbours NeighboursOf(const Mesh& mesh);

// Atomic; with `durable`, the data and the directory entry are fsync'ed (core/fs.h).
void WritePly(const std::filesystem::path& file, const Mesh& mesh, bool durable = false);
Mesh ReadPly(const std::filesystem::path& file);

}  // namespace holocap
