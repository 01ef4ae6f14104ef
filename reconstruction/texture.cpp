// Rendering meshes into calibrated cameras (silhouette, depth), visibility-aware colouring of
// vertices and of a texture atlas, and binary glTF export.
#include <omp.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <nlohmann/json.hpp>

#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/projector.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

namespace {

struct Projected {
  std::vector<Eigen::Vector2f> pixels;
  std::vector<float> depth;  // z in the camera; <= 0 behind
  std::vector<uint8_t> valid;
};

Projected ProjectVertices(const Mesh& mesh, const CameraModel& camera) {
  Projected out;
  const size_t n = mesh.vertices.size();
  Eigen::Matrix3Xd points(3, n);
  const Pose& cam_from_world = camera.cam_from_world();
  for (size_t i = 0; i < n; ++i) points.col(i) = cam_from_world * mesh.vertices[i].cast<double>();
  Eigen::Matrix2Xd pixels = camera.ProjectMany(points);
  out.pixels.resize(n);
  out.depth.resize(n);
  out.valid.resize(n);
  for (size_t i = 0; i < n; ++i) {
    out.pixels[i] = pixels.col(i).cast<float>();
    out.depth[i] = static_cast<float>(points(2, i));
    out.valid[i] = points(2, i) > 1e-6 && pixels.col(i).allFinite();
  }
  return out;
}

// Z-buffer rasterisation of triangles in pixel space (depth interpolated linearly there; the
// triangles of a mesh are small against the lens's curvature), at `scale` times the image's
// resolution: pixel x of the image is (x + 0.5) * scale - 0.5 of the buffer.
cv::Mat Rasterise(const Mesh& mesh, const Projected& p, int width, int height, int scale = 1) {
  width *= scale;
  height *= scale;
  const float s = static_cast<float>(scale), offset = 0.5f * (s - 1);
  cv::Mat depth(height, width, CV_32F, cv::Scalar(std::numeric_limits<float>::infinity()));
  for (const auto& f : mesh.faces) {
    if (!p.valid[f.x()] || !p.valid[f.y()] || !p.valid[f.z()]) continue;
    const Eigen::Vector2f a = p.pixels[f.x()] * s + Eigen::Vector2f::Constant(offset);
    const Eigen::Vector2f b = p.pixels[f.y()] * s + Eigen::Vector2f::Constant(offset);
    const Eigen::Vector2f c = p.pixels[f.z()] * s + Eigen::Vector2f::Constant(offset);
    float area = (b - a).x() * (c - a).y() - (b - a).y() * (c - a).x();
    if (std::abs(area) < 1e-12f) continue;
    int x0 = std::max(0, static_cast<int>(std::ceil(std::min({a.x(), b.x(), c.x()}))));
    int x1 = std::min(width - 1, static_cast<int>(std::floor(std::max({a.x(), b.x(), c.x()}))));
    int y0 = std::max(0, static_cast<int>(std::ceil(std::min({a.y(), b.y(), c.y()}))));
    int y1 = std::min(height - 1, static_cast<int>(std::floor(std::max({a.y(), b.y(), c.y()}))));
    for (int y = y0; y <= y1; ++y) {
      float* row = depth.ptr<float>(y);
      for (int x = x0; x <= x1; ++x) {
        Eigen::Vector2f q(static_cast<float>(x), static_cast<float>(y));
        float w0 = ((b - q).x() * (c - q).y() - (b - q).y() * (c - q).x()) / area;
        float w1 = ((c - q).x() * (a - q).y() - (c - q).y() * (a - q).x()) / area;
        float w2 = 1 - w0 - w1;
        if (w0 < 0 || w1 < 0 || w2 < 0) continue;
        float z = w0 * p.depth[f.x()] + w1 * p.depth[f.y()] + w2 * p.depth[f.z()];
        if (z < row[x]) row[x] = z;
      }
    }
  }
  return depth;
}

struct ViewSampler {
  const View* view;
  FastProjector projector;
  cv::Mat depth;  // occlusion buffer at `scale` times the image's resolution
  int scale = 1;
  Eigen::Vector3f centre;
  float radians_per_pixel = 0;  // of the occlusion buffer, near the image centre
  // At image pixel (x0, y0): the nearest and farthest depth of the occlusion buffer over the
  // four image pixels x0..x0+1, y0..y0+1 (NaN where any is NaN), which Visible tests.
  cv::Mat nearest, farthest;
};

// The occlusion-buffer pixels inside image pixels i..i+1 along an axis of `size` buffer pixels.
inline int WindowStart(int i, int scale, int size) { return std::clamp(i * scale, 0, size - 1); }
inline int WindowEnd(int i, int scale, int size) {
  return std::clamp((i + 2) * scale - 1, 0, size - 1);
}

// ViewSampler::nearest and farthest: the extremes over each window, along rows, then columns.
void DepthExtremes(ViewSampler* s, int width, int height) {
  const cv::Mat& depth = s->depth;
  const int scale = s->scale;
  cv::Mat row_lo(depth.rows, width, CV_32F), row_hi(depth.rows, width, CV_32F);
  // NaN, once met, stays: v < NaN and v > NaN are false.
  const auto lower = [](float m, float v) { return v < m || v != v ? v : m; };
  const auto upper = [](float m, float v) { return v > m || v != v ? v : m; };
#pragma omp parallel for schedule(static)
  for (int y = 0; y < depth.rows; ++y) {
    const float* in = depth.ptr<float>(y);
    float* lo = row_lo.ptr<float>(y);
    float* hi = row_hi.ptr<float>(y);
    for (int x0 = 0; x0 < width; ++x0) {
      const int xs = WindowStart(x0, scale, depth.cols), xe = WindowEnd(x0, scale, depth.cols);
      float a = in[xs], b = in[xs];
      for (int x = xs + 1; x <= xe; ++x) a = lower(a, in[x]), b = upper(b, in[x]);
      lo[x0] = a, hi[x0] = b;
    }
  }
  s->nearest.create(height, width, CV_32F);
  s->farthest.create(height, width, CV_32F);
#pragma omp parallel for schedule(static)
  for (int y0 = 0; y0 < height; ++y0) {
    const int ys = WindowStart(y0, scale, depth.rows), ye = WindowEnd(y0, scale, depth.rows);
    float* lo = s->nearest.ptr<float>(y0);
    float* hi = s->farthest.ptr<float>(y0);
    for (int x0 = 0; x0 < width; ++x0) lo[x0] = row_lo.at<float>(ys, x0);
    for (int x0 = 0; x0 < width; ++x0) hi[x0] = row_hi.at<float>(ys, x0);
    for (int y = ys + 1; y <= ye; ++y) {
      const float* a = row_lo.ptr<float>(y);
      const float* b = row_hi.ptr<float>(y);
      for (int x0 = 0; x0 < width; ++x0)
        lo[x0] = lower(lo[x0], a[x0]), hi[x0] = upper(hi[x0], b[x0]);
    }
  }
}

// The angle one pixel spans near the image's centre (any lens model).
float RadiansPerPixel(const CameraModel& camera) {
  const Eigen::Vector2d c(0.5 * (camera.width() - 1), 0.5 * (camera.height() - 1));
  const Eigen::Vector3d a = camera.Unproject(c).normalized(),
                        b = camera.Unproject(c + Eigen::Vector2d(1, 0)).normalized();
  const double angle = std::acos(std::clamp(a.dot(b), -1.0, 1.0));
  return std::isfinite(angle) && angle > 0 ? static_cast<float>(angle) : 1e-3f;
}

cv::Vec3f SampleColor(const cv::Mat& image, float u, float v) {
  int x = std::clamp(static_cast<int>(std::floor(u)), 0, image.cols - 2);
  int y = std::clamp(static_cast<int>(std::floor(v)), 0, image.rows - 2);
  float fx = std::clamp(u - x, 0.0f, 1.0f), fy = std::clamp(v - y, 0.0f, 1.0f);
  cv::Vec3f c00 = image.at<cv::Vec3b>(y, x), c01 = image.at<cv::Vec3b>(y, x + 1);
  cv::Vec3f c10 = image.at<cv::Vec3b>(y + 1, x), c11 = image.at<cv::Vec3b>(y + 1, x + 1);
  return (1 - fy) * ((1 - fx) * c00 + fx * c01) + fy * ((1 - fx) * c10 + fx * c11);
}

// Whether a view sees a point of the mesh cleanly: its depth against the view's own rendering
// of the mesh at every occlusion-buffer pixel inside the four image pixels that a bilinear
// lookup reads. All four must lie on the point's surface: a tap in front is an occluder, an
// empty or farther one a silhouette edge where the image mixes in what lies behind. The taps
// lie up to 1.5 image pixels from the point, over which a surface at incidence angle t changes
// depth by that footprint * tan t, so the tolerance grows with it (cosines below 0.1 are cut).
bool Visible(const ViewSampler& s, float u, float v, float z, float cos_incidence,
             double tolerance) {
  if (!s.view->camera.InImage(Eigen::Vector2d(u, v), 0.5)) return false;
  const float cos_t = std::max(cos_incidence, 0.1f);
  const float slope = std::sqrt(std::max(0.0f, 1 - cos_t * cos_t)) / cos_t;
  const float image_footprint = z * s.radians_per_pixel * s.scale;
  const float allowed = static_cast<float>(tolerance) + 1.5f * image_footprint * slope;
  const int x0 = static_cast<int>(std::floor(u)), y0 = static_cast<int>(std::floor(v));
  if (x0 >= 0 && y0 >= 0 && x0 < s.nearest.cols && y0 < s.nearest.rows) {
    // Every occlusion-buffer pixel inside the four image pixels is within `allowed` of z
    // exactly when the nearest and the farthest are (r - z rounds monotonically in r).
    return std::abs(s.nearest.at<float>(y0, x0) - z) <= allowed &&
           std::abs(s.farthest.at<float>(y0, x0) - z) <= allowed;
  }
  // Every occlusion-buffer pixel inside the four image pixels.
  const int xs = WindowStart(x0, s.scale, s.depth.cols), xe = WindowEnd(x0, s.scale, s.depth.cols);
  const int ys = WindowStart(y0, s.scale, s.depth.rows), ye = WindowEnd(y0, s.scale, s.depth.rows);
  for (int y = ys; y <= ye; ++y) {
    const float* row = s.depth.ptr<float>(y);
    for (int x = xs; x <= xe; ++x) {
      if (!(std::abs(row[x] - z) <= allowed)) return false;
    }
  }
  return true;
}

// Blends the best `max_views` views by incidence cosine; false when none sees the point.
bool BlendColor(const std::vector<ViewSampler>& samplers, const Eigen::Vector3f& point,
                const Eigen::Vector3f& normal, const TextureOptions& options, cv::Vec3f* color) {
  struct Candidate {
    float weight;
    cv::Vec3f color;
  };
  Candidate best[8];
  int count = 0;
  const int keep = std::min(options.max_views, 8);
  for (const ViewSampler& s : samplers) {
    Eigen::Vector3f to_camera = s.centre - point;
    const float facing = normal.dot(to_camera);
    // A view behind the surface fails the test below whatever the norm (skips the square root).
    if (facing < 0 && options.min_cos_incidence >= 0) continue;
    float cos_incidence = facing / (to_camera.norm() + 1e-12f);
    if (cos_incidence < options.min_cos_incidence) continue;
    float u, v, z;
    if (!s.projector.ProjectWorld(point, &u, &v, &z)) continue;
    if (!Visible(s, u, v, z, cos_incidence, options.depth_tolerance_m)) continue;
    Candidate c{cos_incidence * cos_incidence, SampleColor(s.view->image, u, v)};
    if (count < keep) {
      best[count++] = c;
    } else {
      auto worst = std::min_element(best, best + count,
                                    [](auto& a, auto& b) { return a.weight < b.weight; });
      if (worst->weight < c.weight) *worst = c;
    }
  }
  if (count == 0) return false;
  cv::Vec3f sum(0, 0, 0);
  float total = 0;
  for (int i = 0; i < count; ++i) sum += best[i].weight * best[i].color, total += best[i].weight;
  *color = sum / total;
  return true;
}

// Colours the vertices no view saw from those it did, over the mesh's edges: a front grows
// from the seen vertices (each newly reached vertex takes the mean of its already coloured
// neighbours), then Jacobi iterations smooth the filled colours with the seen ones held fixed
// (a discrete harmonic fill). Vertices in parts of the mesh without a seen vertex stay as they
// are. Returns the number filled; `seen` is 1 for seen vertices, `rgb` their colours.
int64_t FillUnseen(const Mesh& mesh, const std::vector<uint8_t>& seen, int smoothing_iterations,
                   std::vector<Eigen::Vector3f>* rgb) {
  const size_t n = mesh.vertices.size();
  // Vertex adjacency from the faces' edges; duplicates only weigh an edge more.
  const VertexNeighbours adjacency = NeighboursOf(mesh);
  const std::vector<int32_t>& start = adjacency.start;
  const std::vector<int32_t>& neighbours = adjacency.neighbours;
  std::vector<uint8_t> coloured = seen;
  std::vector<int32_t> front, next, filled;
  for (size_t i = 0; i < n; ++i) {
    if (coloured[i]) continue;
    for (int32_t j = start[i]; j < start[i + 1]; ++j) {
      if (coloured[neighbours[j]]) {
        front.push_back(static_cast<int32_t>(i));
        break;
      }
    }
  }
  std::vector<uint8_t> queued(n, 0);
  for (int32_t v : front) queued[v] = 1;
  while (!front.empty()) {
    // Colours of a front come from the vertices coloured before it, so the order inside a
    // front does not matter (deterministic).
    std::vector<Eigen::Vector3f> colours(front.size());
    for (size_t k = 0; k < front.size(); ++k) {
      Eigen::Vector3f sum = Eigen::Vector3f::Zero();
      int count = 0;
      for (int32_t j = start[front[k]]; j < start[front[k] + 1]; ++j) {
        if (coloured[neighbours[j]]) sum += (*rgb)[neighbours[j]], ++count;
      }
      colours[k] = sum / static_cast<float>(std::max(count, 1));
    }
    next.clear();
    for (size_t k = 0; k < front.size(); ++k) {
      (*rgb)[front[k]] = colours[k];
      coloured[front[k]] = 1;
      filled.push_back(front[k]);
    }
    for (int32_t v : front) {
      for (int32_t j = start[v]; j < start[v + 1]; ++j) {
        const int32_t u = neighbours[j];
        if (!coloured[u] && !queued[u]) queued[u] = 1, next.push_back(u);
      }
    }
    front.swap(next);
  }
  std::vector<Eigen::Vector3f> smoothed(filled.size());
  for (int iteration = 0; iteration < smoothing_iterations; ++iteration) {
#pragma omp parallel for schedule(static)
    for (size_t k = 0; k < filled.size(); ++k) {
      Eigen::Vector3f sum = Eigen::Vector3f::Zero();
      const int32_t v = filled[k];
      for (int32_t j = start[v]; j < start[v + 1]; ++j) sum += (*rgb)[neighbours[j]];
      const int32_t degree = start[v + 1] - start[v];
      smoothed[k] = degree > 0 ? Eigen::Vector3f(sum / static_cast<float>(degree)) : (*rgb)[v];
    }
    for (size_t k = 0; k < filled.size(); ++k) (*rgb)[filled[k]] = smoothed[k];
  }
  return static_cast<int64_t>(filled.size());
}

}  // namespace

cv::Mat RenderDepth(const Mesh& mesh, const CameraModel& camera) {
  cv::Mat depth = Rasterise(mesh, ProjectVertices(mesh, camera), camera.width(), camera.height());
  depth.setTo(std::numeric_limits<float>::quiet_NaN(),
              depth == std::numeric_limits<float>::infinity());
  return depth;
}

cv::Mat RenderSilhouette(const Mesh& mesh, const CameraModel& camera) {
  cv::Mat depth = Rasterise(mesh, ProjectVertices(mesh, camera), camera.width(), camera.height());
  return depth < std::numeric_limits<float>::infinity();
}

void TextureOptions::Check() const {
  HOLOCAP_CHECK_OPTION_IN(texels_per_cell, 4, 64);
  HOLOCAP_CHECK_OPTION_GE(min_cos_incidence, 0);
  HOLOCAP_CHECK_OPTION_LT(min_cos_incidence, 1);
  HOLOCAP_CHECK_OPTION_GT(depth_tolerance_m, 0);
  HOLOCAP_CHECK_OPTION_IN(max_views, 1, 8);
  HOLOCAP_CHECK_OPTION_IN(occlusion_scale, 1, 4);
  HOLOCAP_CHECK_OPTION_IN(fill_smoothing_iterations, 0, 1000);
}

nlohmann::json TexturedMesh::Metrics() const {
  const double n = std::max<double>(1, static_cast<double>(mesh.vertices.size()));
  return {{"seen_vertices", seen_vertices},
          {"filled_vertices", filled_vertices},
          {"uncoloured_vertices", uncoloured_vertices},
          {"seen_fraction", seen_vertices / n},
          {"filled_fraction", filled_vertices / n},
          {"uncoloured_fraction", uncoloured_vertices / n},
          {"atlas_px", atlas.cols}};
}

TexturedMesh TextureMesh(const Mesh& mesh, const std::vector<View>& views,
                         const TextureOptions& options) {
  options.Check();
  TexturedMesh out;
  out.mesh = mesh;
  if (out.mesh.normals.size() != out.mesh.vertices.size()) out.mesh.ComputeNormals();
  std::vector<ViewSampler> samplers;
  for (const View& view : views) {
    if (view.image.empty()) continue;
    if (view.image.type() != CV_8UC3 || view.image.cols != view.camera.width() ||
        view.image.rows != view.camera.height()) {
      Fail("texturing: image of '", view.name, "' does not match its camera model");
    }
    const int scale = options.occlusion_scale;
    ViewSampler s{&view,
                  FastProjector(view.camera),
                  Rasterise(out.mesh, ProjectVertices(out.mesh, view.camera), view.camera.width(),
                            view.camera.height(), scale),
                  scale,
                  view.camera.center_in_world().cast<float>(),
                  RadiansPerPixel(view.camera) / scale,
                  {},
                  {}};
    DepthExtremes(&s, view.camera.width(), view.camera.height());
    samplers.push_back(std::move(s));
  }
  if (samplers.empty()) Fail("texturing needs at least one view with an image");
  const size_t n = out.mesh.vertices.size();
  out.mesh.colors.assign(n, Eigen::Matrix<uint8_t, 3, 1>(128, 128, 128));
  std::vector<uint8_t> seen(n, 0);
  std::vector<Eigen::Vector3f> rgb(n, Eigen::Vector3f::Constant(128));
#pragma omp parallel for schedule(dynamic, 256)
  for (size_t i = 0; i < n; ++i) {
    cv::Vec3f bgr;
    if (BlendColor(samplers, out.mesh.vertices[i], out.mesh.normals[i], options, &bgr)) {
      rgb[i] = Eigen::Vector3f(bgr[2], bgr[1], bgr[0]);
      seen[i] = 1;
    }
  }
  out.seen_vertices = std::count(seen.begin(), seen.end(), uint8_t{1});
  if (options.fill_unseen)
    out.filled_vertices = FillUnseen(out.mesh, seen, options.fill_smoothing_iterations, &rgb);
  out.uncoloured_vertices = static_cast<int64_t>(n) - out.seen_vertices - out.filled_vertices;
  for (size_t i = 0; i < n; ++i) {
    if (seen[i] == 0 && !options.fill_unseen) continue;
    for (int ch = 0; ch < 3; ++ch) out.mesh.colors[i][ch] = cv::saturate_cast<uint8_t>(rgb[i][ch]);
  }
  if (!options.atlas || out.mesh.faces.empty()) return out;

  // Atlas: two triangles per square cell, one in each half, inset so that bilinear lookups
  // of a triangle never reach its neighbour's texels.
  const int s = options.texels_per_cell;
  const int64_t cells = (static_cast<int64_t>(out.mesh.faces.size()) + 1) / 2;
  const int grid = static_cast<int>(std::ceil(std::sqrt(static_cast<double>(cells))));
  const int side = grid * s;
  if (side > 16384) Fail("texture atlas would be ", side, " texels wide: simplify the mesh first");
  out.atlas = cv::Mat(side, side, CV_8UC3, cv::Scalar(128, 128, 128));
  out.corner_uv.resize(out.mesh.faces.size() * 3);
  const float fs = static_cast<float>(s);
  const Eigen::Vector2f corners[2][3] = {
      {{0.5f, 0.5f}, {fs - 1.5f, 0.5f}, {0.5f, fs - 1.5f}},
      {{fs - 0.5f, fs - 0.5f}, {1.5f, fs - 0.5f}, {fs - 0.5f, 1.5f}}};
#pragma omp parallel for schedule(dynamic, 64)
  for (int64_t cell = 0; cell < cells; ++cell) {
    const int cx = static_cast<int>(cell % grid), cy = static_cast<int>(cell / grid);
    const Eigen::Vector2f origin(static_cast<float>(cx * s), static_cast<float>(cy * s));
    for (int half = 0; half < 2; ++half) {
      const size_t face = static_cast<size_t>(2 * cell + half);
      if (face >= out.mesh.faces.size()) break;
      const Eigen::Vector3i f = out.mesh.faces[face];
      for (int k = 0; k < 3; ++k) {
        Eigen::Vector2f t = origin + corners[half][k];
        out.corner_uv[3 * face + k] = Eigen::Vector2f(t.x() / side, t.y() / side);
      }
      const Eigen::Vector3f p[3] = {out.mesh.vertices[f.x()], out.mesh.vertices[f.y()],
                                    out.mesh.vertices[f.z()]};
      Eigen::Vector3f normal = (p[1] - p[0]).cross(p[2] - p[0]);
      if (normal.norm() > 0) normal.normalize();
      const Eigen::Vector2f a = corners[half][0], b = corners[half][1], c = corners[half][2];
      const float area = (b - a).x() * (c - a).y() - (b - a).y() * (c - a).x();
      for (int ty = 0; ty < s; ++ty) {
        for (int tx = 0; tx < s; ++tx) {
          // Texel centres on the diagonal and beyond belong to the other half.
          bool lower = (tx + ty) < s - 1 || ((tx + ty) == s - 1 && tx < ty);
          if (lower != (half == 0)) continue;
          Eigen::Vector2f q(tx + 0.5f, ty + 0.5f);
          float w1 = ((q - a).x() * (c - a).y() - (q - a).y() * (c - a).x()) / area;
          float w2 = ((b - a).x() * (q - a).y() - (b - a).y() * (q - a).x()) / area;
          w1 = std::clamp(w1, 0.0f, 1.0f);
          w2 = std::clamp(w2, 0.0f, 1.0f - w1);
          float w0 = 1 - w1 - w2;
          Eigen::Vector3f point = w0 * p[0] + w1 * p[1] + w2 * p[2];
          cv::Vec3f bgr;
          if (!BlendColor(samplers, point, normal, options, &bgr)) {
            const auto& c0 = out.mesh.colors[f.x()];
            const auto& c1 = out.mesh.colors[f.y()];
            const auto& c2 = out.mesh.colors[f.z()];
            for (int ch = 0; ch < 3; ++ch) bgr[2 - ch] = w0 * c0[ch] + w1 * c1[ch] + w2 * c2[ch];
          }
          out.atlas.at<cv::Vec3b>(cy * s + ty, cx * s + tx) =
              cv::Vec3b(cv::saturate_cast<uint8_t>(bgr[0]), cv::saturate_cast<uint8_t>(bgr[1]),
                        cv::saturate_cast<uint8_t>(bgr[2]));
        }
      }
    }
  }
  return out;
}

namespace {

void Pad(std::string* bytes, char fill) {
  while (bytes->size() % 4 != 0) bytes->push_back(fill);
}

template <typename T>
void AppendRaw(std::string* bytes, const T* data, size_t count) {
  bytes->append(reinterpret_cast<const char*>(data), count * sizeof(T));
}

}  // namespace

void WriteGlb(const std::filesystem::path& file, const TexturedMesh& textured, bool durable) {
  const Mesh& mesh = textured.mesh;
  if (mesh.vertices.empty() || mesh.faces.empty())
    Fail("cannot write an empty mesh to ", file.string());
  const bool atlas = !textured.atlas.empty() && textured.corner_uv.size() == mesh.faces.size() * 3;
  const bool colors = !atlas && mesh.colors.size() == mesh.vertices.size();
  const bool normals = mesh.normals.size() == mesh.vertices.size();
  // With an atlas every corner has its own texture coordinate, so corners are not shared.
  std::vector<Eigen::Vector3f> positions, vertex_normals;
  std::vector<Eigen::Vector2f> uvs;
  std::vector<uint32_t> indices;
  if (atlas) {
    for (size_t f = 0; f < mesh.faces.size(); ++f) {
      for (int k = 0; k < 3; ++k) {
        int v = mesh.faces[f][k];
        positions.push_back(mesh.vertices[v]);
        if (normals) vertex_normals.push_back(mesh.normals[v]);
        uvs.push_back(textured.corner_uv[3 * f + k]);
        indices.push_back(static_cast<uint32_t>(positions.size() - 1));
      }
    }
  } else {
    positions = mesh.vertices;
    if (normals) vertex_normals = mesh.normals;
    for (const auto& f : mesh.faces) {
      for (int k = 0; k < 3; ++k) indices.push_back(static_cast<uint32_t>(f[k]));
    }
  }
  for (auto& n : vertex_normals) {
    float norm = n.norm();
    n = norm > 0 ? Eigen::Vector3f(n / norm) : Eigen::Vector3f(0, 0, 1);
  }
  nlohmann::json json;
  json["asset"] = {{"version", "2.0"}, {"generator", "holocap"}};
  json["scene"] = 0;
  json["scenes"] = {{{"nodes", {0}}}};
  json["nodes"] = {{{"mesh", 0}}};
  json["bufferViews"] = nlohmann::json::array();
  json["accessors"] = nlohmann::json::array();
  std::string bin;
  auto add_view = [&](const void* data, size_t bytes, int target) {
    Pad(&bin, '\0');
    nlohmann::json view = {{"buffer", 0}, {"byteOffset", bin.size()}, {"byteLength", bytes}};
    if (target != 0) view["target"] = target;
    bin.append(static_cast<const char*>(data), bytes);
    json["bufferViews"].push_back(view);
    return static_cast<int>(json["bufferViews"].size() - 1);
  };
  auto add_accessor = [&](int view, int component, size_t count, const char* type,
                          bool normalized) {
    nlohmann::json accessor = {
        {"bufferView", view}, {"componentType", component}, {"count", count}, {"type", type}};
    if (normalized) accessor["normalized"] = true;
    json["accessors"].push_back(accessor);
    return static_cast<int>(json["accessors"].size() - 1);
  };
  constexpr int kArrayBuffer = 34962, kElementArrayBuffer = 34963;
  constexpr int kFloat = 5126, kUnsignedInt = 5125, kUnsignedByte = 5121;
  nlohmann::json attributes;
  int position = add_accessor(add_view(positions.data(), positions.size() * 12, kArrayBuffer),
                              kFloat, positions.size(), "VEC3", false);
  Eigen::Vector3f lo = positions[0], hi = positions[0];
  for (const auto& p : positions) lo = lo.cwiseMin(p), hi = hi.cwiseMax(p);
  json["accessors"][position]["min"] = {lo.x(), lo.y(), lo.z()};
  json["accessors"][position]["max"] = {hi.x(), hi.y(), hi.z()};
  attributes["POSITION"] = position;
  if (normals) {
    attributes["NORMAL"] =
        add_accessor(add_view(vertex_normals.data(), vertex_normals.size() * 12, kArrayBuffer),
                     kFloat, vertex_normals.size(), "VEC3", false);
  }
  if (colors) {
    // RGBA bytes: a 4-byte stride keeps the attribute aligned as glTF requires.
    std::vector<uint8_t> rgba;
    for (const auto& c : mesh.colors) rgba.insert(rgba.end(), {c[0], c[1], c[2], 255});
    attributes["COLOR_0"] = add_accessor(add_view(rgba.data(), rgba.size(), kArrayBuffer),
                                         kUnsignedByte, mesh.colors.size(), "VEC4", true);
  }
  if (atlas) {
    attributes["TEXCOORD_0"] = add_accessor(add_view(uvs.data(), uvs.size() * 8, kArrayBuffer),
                                            kFloat, uvs.size(), "VEC2", false);
  }
  int index_accessor =
      add_accessor(add_view(indices.data(), indices.size() * 4, kElementArrayBuffer), kUnsignedInt,
                   indices.size(), "SCALAR", false);
  nlohmann::json primitive = {
      {"attributes", attributes}, {"indices", index_accessor}, {"mode", 4}, {"material", 0}};
  json["meshes"] = {{{"primitives", {primitive}}}};
  nlohmann::json material = {
      {"pbrMetallicRoughness", {{"metallicFactor", 0.0}, {"roughnessFactor", 1.0}}},
      {"doubleSided", false}};
  if (atlas) {
    std::vector<uint8_t> png;
    if (!cv::imencode(".png", textured.atlas, png)) Fail("cannot encode the texture atlas");
    int image_view = add_view(png.data(), png.size(), 0);
    json["images"] = {{{"bufferView", image_view}, {"mimeType", "image/png"}}};
    json["samplers"] = {
        {{"magFilter", 9729}, {"minFilter", 9729}, {"wrapS", 33071}, {"wrapT", 33071}}};
    json["textures"] = {{{"source", 0}, {"sampler", 0}}};
    material["pbrMetallicRoughness"]["baseColorTexture"] = {{"index", 0}};
  }
  json["materials"] = {material};
  Pad(&bin, '\0');
  json["buffers"] = {{{"byteLength", bin.size()}}};
  std::string text = json.dump();
  Pad(&text, ' ');
  std::string out;
  const uint32_t header[3] = {0x46546C67u, 2u,
                              static_cast<uint32_t>(12 + 8 + text.size() + 8 + bin.size())};
  AppendRaw(&out, header, 3);
  const uint32_t json_chunk[2] = {static_cast<uint32_t>(text.size()), 0x4E4F534Au};
  AppendRaw(&out, json_chunk, 2);
  out += text;
  const uint32_t bin_chunk[2] = {static_cast<uint32_t>(bin.size()), 0x004E4942u};
  AppendRaw(&out, bin_chunk, 2);
  out += bin;
  WriteFileAtomic(file, out, durable);
}

}  // namespace holocap
