// A frame's textured mesh made small enough to stream: welded, simplified by meshoptimizer to a
// geometric error bound, reordered for locality, and its atlas re-baked in the cell layout (the
// reconstruction's texture charts do not survive simplification, so every texel of the new atlas
// takes the colour of the nearest point of the original textured surface).
#include <meshoptimizer.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <map>
#include <unordered_map>

#include "core/error.h"
#include "playback/internal/web_stream.h"

namespace holocap::web {
namespace {

// Barycentric weights of the point of triangle abc nearest to p (regions of the triangle's
// vertices, edges and face tested in turn).
Eigen::Vector3f NearestOnTriangle(const Eigen::Vector3f& p, const Eigen::Vector3f& a,
                                  const Eigen::Vector3f& b, const Eigen::Vector3f& c) {
  const Eigen::Vector3f ab = b - a, ac = c - a, ap = p - a;
  const float d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0 && d2 <= 0) return {1, 0, 0};
  const Eigen::Vector3f bp = p - b;
  const float d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0 && d4 <= d3) return {0, 1, 0};
  const float vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) {
    const float t = d1 / (d1 - d3);
    return {1 - t, t, 0};
  }
  const Eigen::Vector3f cp = p - c;
  const float d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0 && d5 <= d6) return {0, 0, 1};
  const float vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) {
    const float t = d2 / (d2 - d6);
    return {1 - t, 0, t};
  }
  const float va = d3 * d6 - d5 * d4;
  if (va <= 0 && d4 - d3 >= 0 && d5 - d6 >= 0) {
    const float t = (d4 - d3) / ((d4 - d3) + (d5 - d6));
    return {0, 1 - t, t};
  }
  const float sum = va + vb + vc;
  if (!(sum > 0)) return {1, 0, 0};  // degenerate (zero-area) triangle
  return {va / sum, vb / sum, vc / sum};
}

// The original surface's colour near any point: its faces hashed into cubes of side `cube_m`,
// each face listed in every cube its box grown by `reach_m` touches, so that one cube lists every
// face within reach_m of a point inside it.
class SurfaceColour {
 public:
  SurfaceColour(const TexturedMeshFrame& mesh, double reach_m)
      : mesh_(mesh), cube_m_(static_cast<float>(2 * reach_m)) {
    for (size_t f = 0; f < mesh.faces(); ++f) {
      Eigen::Vector3f lo = mesh.positions[3 * f], hi = lo;
      for (int k = 1; k < 3; ++k) {
        lo = lo.cwiseMin(mesh.positions[3 * f + k]);
        hi = hi.cwiseMax(mesh.positions[3 * f + k]);
      }
      const Eigen::Vector3i c0 = Cube(lo.array() - reach_m), c1 = Cube(hi.array() + reach_m);
      for (int z = c0.z(); z <= c1.z(); ++z)
        for (int y = c0.y(); y <= c1.y(); ++y)
          for (int x = c0.x(); x <= c1.x(); ++x)
            cubes_[Key({x, y, z})].push_back(static_cast<uint32_t>(f));
    }
  }

  // BGR in [0, 1] at the original surface's point nearest to p; false when no face is near.
  bool At(const Eigen::Vector3f& p, cv::Vec3f* bgr, float* distance_m) const {
    auto it = cubes_.find(Key(Cube(p.array())));
    if (it == cubes_.end()) return false;
    float best = std::numeric_limits<float>::infinity();
    uint32_t best_face = 0;
    Eigen::Vector3f best_w;
    for (uint32_t f : it->second) {
      const Eigen::Vector3f* v = &mesh_.positions[3 * f];
      const Eigen::Vector3f w = NearestOnTriangle(p, v[0], v[1], v[2]);
      const float d = (w.x() * v[0] + w.y() * v[1] + w.z() * v[2] - p).squaredNorm();
      if (d < best) best = d, best_face = f, best_w = w;
    }
    if (!std::isfinite(best)) return false;
    *distance_m = std::sqrt(best);
    const size_t c = 3 * best_face;
    if (!mesh_.atlas.empty()) {
      const Eigen::Vector2f uv =
          best_w.x() * mesh_.uvs[c] + best_w.y() * mesh_.uvs[c + 1] + best_w.z() * mesh_.uvs[c + 2];
      *bgr = SampleAtlas(mesh_.atlas, uv.x(), uv.y());
    } else {
      cv::Vec3f rgb(0, 0, 0);
      for (int k = 0; k < 3; ++k)
        for (int ch = 0; ch < 3; ++ch) rgb[ch] += best_w[k] * mesh_.colors[c + k][ch] / 255.0f;
      *bgr = cv::Vec3f(rgb[2], rgb[1], rgb[0]);
    }
    return true;
  }

 private:
  template <typename V>
  Eigen::Vector3i Cube(const V& p) const {
    return Eigen::Vector3i(static_cast<int>(std::floor(p[0] / cube_m_)),
                           static_cast<int>(std::floor(p[1] / cube_m_)),
                           static_cast<int>(std::floor(p[2] / cube_m_)));
  }
  static int64_t Key(const Eigen::Vector3i& c) {
    constexpr int64_t kSpan = 1 << 20;
    return ((c.z() + kSpan / 2) * kSpan + (c.y() + kSpan / 2)) * kSpan + (c.x() + kSpan / 2);
  }

  const TexturedMeshFrame& mesh_;
  float cube_m_;
  std::unordered_map<int64_t, std::vector<uint32_t>> cubes_;
};

// Corners of a cell's two halves, in texels from the cell's corner: each half is inset so that
// a bilinear read inside it never reaches the other half's texels.
Eigen::Vector2f CellCorner(int half, int corner, int cell_px) {
  const float s = static_cast<float>(cell_px);
  if (half == 0) {
    const Eigen::Vector2f lower[3] = {{0.5f, 0.5f}, {s - 1.5f, 0.5f}, {0.5f, s - 1.5f}};
    return lower[corner];
  }
  const Eigen::Vector2f upper[3] = {{s - 0.5f, s - 0.5f}, {1.5f, s - 0.5f}, {s - 0.5f, 1.5f}};
  return upper[corner];
}

// Barycentric weights of texel centre q in the half with corners a, b, c, clamped onto it.
Eigen::Vector3f TexelWeights(const Eigen::Vector2f& q, const Eigen::Vector2f& a,
                             const Eigen::Vector2f& b, const Eigen::Vector2f& c) {
  auto cross = [](const Eigen::Vector2f& u, const Eigen::Vector2f& v) {
    return u.x() * v.y() - u.y() * v.x();
  };
  const float area = cross(b - a, c - a);
  float wb = cross(q - a, c - a) / area, wc = cross(b - a, q - a) / area;
  wb = std::clamp(wb, 0.0f, 1.0f);
  wc = std::clamp(wc, 0.0f, 1.0f - wb);
  return {1 - wb - wc, wb, wc};
}

}  // namespace

Eigen::Vector2f CellCornerUv(size_t face, int corner, const CellLayout& layout) {
  const size_t cell = face / 2;
  const Eigen::Vector2f origin(static_cast<float>((cell % layout.columns) * layout.cell_px),
                               static_cast<float>((cell / layout.columns) * layout.cell_px));
  const Eigen::Vector2f t = origin + CellCorner(static_cast<int>(face % 2), corner, layout.cell_px);
  return {t.x() / (layout.columns * layout.cell_px), t.y() / (layout.rows * layout.cell_px)};
}

CellLayout CellLayoutFor(size_t faces, int cell_px) {
  CellLayout layout;
  layout.cell_px = cell_px;
  const size_t cells = std::max<size_t>((faces + 1) / 2, 1);
  layout.columns = static_cast<int>(std::ceil(std::sqrt(static_cast<double>(cells))));
  layout.rows = static_cast<int>((cells + layout.columns - 1) / layout.columns);
  return layout;
}

void WeldCorners(const std::vector<Eigen::Vector3f>& corners, std::vector<Eigen::Vector3f>* unique,
                 std::vector<uint32_t>* indices) {
  std::map<std::array<uint32_t, 3>, uint32_t> welded;
  unique->clear();
  indices->clear();
  for (const auto& p : corners) {
    std::array<uint32_t, 3> key;
    std::memcpy(key.data(), p.data(), 12);
    auto [it, added] = welded.emplace(key, static_cast<uint32_t>(unique->size()));
    if (added) unique->push_back(p);
    indices->push_back(it->second);
  }
}

double MedianEdgeM(const TexturedMeshFrame& mesh) {
  std::vector<float> edges;
  for (size_t f = 0; f < mesh.faces(); ++f)
    edges.push_back((mesh.positions[3 * f + 1] - mesh.positions[3 * f]).norm());
  if (edges.empty()) return 0;
  std::nth_element(edges.begin(), edges.begin() + edges.size() / 2, edges.end());
  return edges[edges.size() / 2];
}

CellMesh SimplifyForStream(const TexturedMeshFrame& mesh, double max_error_m, int cell_px) {
  CellMesh out;
  std::vector<uint32_t> indices;
  WeldCorners(mesh.positions, &out.vertices, &indices);
  const size_t n = out.vertices.size();
  if (max_error_m > 0 && !indices.empty()) {
    const float scale = meshopt_simplifyScale(out.vertices[0].data(), n, sizeof(Eigen::Vector3f));
    std::vector<uint32_t> simplified(indices.size());
    float relative_error = 0;
    simplified.resize(meshopt_simplify(
        simplified.data(), indices.data(), indices.size(), out.vertices[0].data(), n,
        sizeof(Eigen::Vector3f), 0, static_cast<float>(max_error_m / scale), 0, &relative_error));
    indices.swap(simplified);
    out.error_m = relative_error * scale;
  }
  // Faces in vertex-cache order, vertices in order of first use (so that each new index is the
  // next one and neighbouring vertices lie near each other), unused vertices dropped.
  meshopt_optimizeVertexCache(indices.data(), indices.data(), indices.size(), n);
  std::vector<Eigen::Vector3f> ordered(n);
  ordered.resize(meshopt_optimizeVertexFetch(ordered.data(), indices.data(), indices.size(),
                                             out.vertices.data(), n, sizeof(Eigen::Vector3f)));
  out.vertices.swap(ordered);
  out.indices.swap(indices);
  out.layout = CellLayoutFor(out.indices.size() / 3, cell_px);
  BakeCellAtlas(mesh, std::max(2 * out.error_m, 2 * MedianEdgeM(mesh)), &out);
  return out;
}

void BakeCellAtlas(const TexturedMeshFrame& original, double reach_m, CellMesh* cells) {
  const CellLayout& layout = cells->layout;
  const int s = layout.cell_px;
  cells->atlas = cv::Mat(layout.rows * s, layout.columns * s, CV_8UC3, cv::Scalar(128, 128, 128));
  if (original.faces() == 0) return;
  const SurfaceColour surface(original, reach_m);
  const size_t faces = cells->indices.size() / 3;
  for (size_t f = 0; f < faces; ++f) {
    const int half = static_cast<int>(f % 2);
    const size_t cell = f / 2;
    const int x0 = static_cast<int>(cell % layout.columns) * s;
    const int y0 = static_cast<int>(cell / layout.columns) * s;
    const Eigen::Vector3f& p0 = cells->vertices[cells->indices[3 * f]];
    const Eigen::Vector3f& p1 = cells->vertices[cells->indices[3 * f + 1]];
    const Eigen::Vector3f& p2 = cells->vertices[cells->indices[3 * f + 2]];
    const Eigen::Vector2f a = CellCorner(half, 0, s), b = CellCorner(half, 1, s),
                          c = CellCorner(half, 2, s);
    for (int ty = 0; ty < s; ++ty) {
      for (int tx = 0; tx < s; ++tx) {
        // The diagonal's texels go to the lower half left of the cell's centre line.
        const int d = tx + ty - (s - 1);
        if ((d < 0 || (d == 0 && tx < ty)) != (half == 0)) continue;
        const Eigen::Vector3f w = TexelWeights(Eigen::Vector2f(tx + 0.5f, ty + 0.5f), a, b, c);
        cv::Vec3f bgr;
        float distance_m = 0;
        if (!surface.At(w.x() * p0 + w.y() * p1 + w.z() * p2, &bgr, &distance_m)) continue;
        cells->max_texel_distance_m =
            std::max(cells->max_texel_distance_m, static_cast<double>(distance_m));
        cells->atlas.at<cv::Vec3b>(y0 + ty, x0 + tx) = cv::Vec3b(
            cv::saturate_cast<uint8_t>(255 * bgr[0]), cv::saturate_cast<uint8_t>(255 * bgr[1]),
            cv::saturate_cast<uint8_t>(255 * bgr[2]));
      }
    }
  }
}

}  // namespace holocap::web
