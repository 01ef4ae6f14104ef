// G-buffer rasterisation of a reconstruction through an mrcal lens: vertices projected by the
// reconstruction's tabulated projector (FastProjector, exact to well under a
// hundredth of a pixel), triangles split in 3D where the lens bends them, then filled in
// bands of rows, one band per task, so that threads never share a pixel.
#include "avatar/mesh_raster.h"

#include <omp.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>

#include "core/check_option.h"
#include "core/error.h"
#include "core/projector.h"
#include "core/threads.h"

namespace holocap {

namespace {

struct ScreenTriangle {
  Eigen::Vector2f pixel[3];
  float inv_z[3];
  Eigen::Vector3f color[3];  // BGR in [0, 1]
  Eigen::Vector3f world[3];
  Eigen::Vector3f normal[3];  // camera coordinates
};

struct SurfacePoint {
  Eigen::Vector3f world;
  Eigen::Vector3f color;
  Eigen::Vector3f normal;  // world
};

SurfacePoint Midpoint(const SurfacePoint& a, const SurfacePoint& b) {
  Eigen::Vector3f n = a.normal + b.normal;
  const float norm = n.norm();
  return {0.5f * (a.world + b.world), 0.5f * (a.color + b.color),
          norm > 0 ? Eigen::Vector3f(n / norm) : a.normal};
}

class TriangleSplitter {
 public:
  TriangleSplitter(const FastProjector& projector, const MeshRasterOptions& options)
      : projector_(projector),
        options_(options),
        rotation_(projector.camera().cam_from_world().rotation().cast<float>()) {}

  // Emits the pieces of a triangle that are small enough in the image; returns whether the
  // triangle had to be split.
  bool Split(const SurfacePoint (&corner)[3], int level, std::vector<ScreenTriangle>* out) const {
    Eigen::Vector3f cam[3];
    Eigen::Vector2f pixel[3];
    int valid = 0, in_front = 0;
    for (int i = 0; i < 3; ++i) {
      cam[i] = projector_.ToCamera(corner[i].world);
      if (cam[i].z() > 1e-6f) ++in_front;
      float u, v;
      if (projector_.Project(cam[i], &u, &v)) {
        pixel[i] = {u, v};
        ++valid;
      }
    }
    if (in_front == 0) return false;
    if (valid == 3) {
      float longest = 0;
      for (int i = 0; i < 3; ++i)
        longest = std::max(longest, (pixel[i] - pixel[(i + 1) % 3]).norm());
      if (longest <= options_.max_edge_px || level >= options_.max_subdivisions) {
        if (!Overlaps(pixel)) return false;
        ScreenTriangle t;
        for (int i = 0; i < 3; ++i) {
          t.pixel[i] = pixel[i];
          t.inv_z[i] = 1.0f / cam[i].z();
          t.color[i] = corner[i].color;
          t.world[i] = corner[i].world;
          t.normal[i] = rotation_ * corner[i].normal;
        }
        out->push_back(t);
        return false;
      }
    } else {
      // Partly outside the lens's field of view: worth splitting only when the triangle is
      // large in angle (a small one there is off the image anyway).
      if (level >= options_.max_subdivisions) return false;
      float min_z = std::numeric_limits<float>::infinity(), longest = 0;
      for (int i = 0; i < 3; ++i) {
        min_z = std::min(min_z, std::max(cam[i].z(), 1e-3f));
        longest = std::max(longest, (cam[i] - cam[(i + 1) % 3]).norm());
      }
      if (valid == 0 && longest / min_z < 0.05f) return false;
    }
    const SurfacePoint ab = Midpoint(corner[0], corner[1]), bc = Midpoint(corner[1], corner[2]),
                       ca = Midpoint(corner[2], corner[0]);
    const SurfacePoint pieces[4][3] = {
        {corner[0], ab, ca}, {ab, corner[1], bc}, {ca, bc, corner[2]}, {ab, bc, ca}};
    for (const auto& piece : pieces) Split(piece, level + 1, out);
    return true;
  }

 private:
  bool Overlaps(const Eigen::Vector2f (&p)[3]) const {
    const float x0 = std::min({p[0].x(), p[1].x(), p[2].x()}),
                x1 = std::max({p[0].x(), p[1].x(), p[2].x()});
    const float y0 = std::min({p[0].y(), p[1].y(), p[2].y()}),
                y1 = std::max({p[0].y(), p[1].y(), p[2].y()});
    return x1 >= -0.5f && y1 >= -0.5f && x0 <= projector_.width() - 0.5f &&
           y0 <= projector_.height() - 0.5f;
  }

  const FastProjector& projector_;
  const MeshRasterOptions& options_;
  Eigen::Matrix3f rotation_;
};

// A square splat of `radius` pixels as two triangles at the point's depth.
void SplatPoint(const FastProjector& projector, const SurfacePoint& point,
                const Eigen::Matrix3f& rotation, float radius, std::vector<ScreenTriangle>* out) {
  const Eigen::Vector3f cam = projector.ToCamera(point.world);
  float u, v;
  if (!projector.Project(cam, &u, &v)) return;
  const Eigen::Vector2f corner[4] = {{u - radius, v - radius},
                                     {u + radius, v - radius},
                                     {u + radius, v + radius},
                                     {u - radius, v + radius}};
  const Eigen::Vector3f normal = rotation * point.normal;
  for (const auto& [a, b, c] : {std::array<int, 3>{0, 1, 2}, std::array<int, 3>{0, 2, 3}}) {
    ScreenTriangle t;
    const int index[3] = {a, b, c};
    for (int i = 0; i < 3; ++i) {
      t.pixel[i] = corner[index[i]];
      t.inv_z[i] = 1.0f / cam.z();
      t.color[i] = point.color;
      t.world[i] = point.world;
      t.normal[i] = normal;
    }
    out->push_back(t);
  }
}

// Each s x s block of a supersampled buffer to one pixel: the covered fraction into the mask,
// the covered samples' mean colour, depth, world position and (renormalised) normal.
GBuffer AverageBlocks(const GBuffer& fine, int s, int width, int height, int threads) {
  GBuffer out;
  out.triangles_drawn = fine.triangles_drawn;
  out.triangles_split = fine.triangles_split;
  out.color = cv::Mat(height, width, CV_32FC3, cv::Scalar::all(0));
  out.normal = cv::Mat(height, width, CV_32FC3, cv::Scalar::all(0));
  out.position = cv::Mat(height, width, CV_32FC3, cv::Scalar::all(0));
  out.depth = cv::Mat(height, width, CV_32F, cv::Scalar(std::numeric_limits<float>::quiet_NaN()));
  out.mask = cv::Mat(height, width, CV_8U, cv::Scalar(0));
#pragma omp parallel for num_threads(threads) schedule(static)
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x) {
      int covered = 0;
      cv::Vec3f color(0, 0, 0), normal(0, 0, 0), position(0, 0, 0);
      float depth = 0;
      for (int dy = 0; dy < s; ++dy) {
        for (int dx = 0; dx < s; ++dx) {
          const int fy = y * s + dy, fx = x * s + dx;
          if (fine.mask.at<uint8_t>(fy, fx) == 0) continue;
          ++covered;
          color += fine.color.at<cv::Vec3f>(fy, fx);
          normal += fine.normal.at<cv::Vec3f>(fy, fx);
          position += fine.position.at<cv::Vec3f>(fy, fx);
          depth += fine.depth.at<float>(fy, fx);
        }
      }
      if (covered == 0) continue;
      const float n = static_cast<float>(covered);
      out.color.at<cv::Vec3f>(y, x) = color / n;
      const float length = static_cast<float>(cv::norm(normal));
      if (length > 0) out.normal.at<cv::Vec3f>(y, x) = normal / length;
      out.position.at<cv::Vec3f>(y, x) = position / n;
      out.depth.at<float>(y, x) = depth / n;
      out.mask.at<uint8_t>(y, x) = static_cast<uint8_t>(std::lround(255.0 * covered / (s * s)));
    }
  }
  return out;
}

}  // namespace

void MeshRasterOptions::Check() const {
  HOLOCAP_CHECK_OPTION_IN(max_edge_px, 1, 4096);
  HOLOCAP_CHECK_OPTION_IN(max_subdivisions, 0, 8);
  HOLOCAP_CHECK_OPTION_GT(point_radius_px, 0);
  HOLOCAP_CHECK_OPTION_LE(point_radius_px, 32);
  HOLOCAP_CHECK_OPTION_GE(threads, 0, "0: all cores");
  HOLOCAP_CHECK_OPTION_IN(supersample, 1, 4);
}

GBuffer RasteriseMesh(const Mesh& mesh, const CameraModel& camera,
                      const MeshRasterOptions& options) {
  options.Check();
  const int width = camera.width(), height = camera.height();
  if (width <= 0 || height <= 0) Fail("rasterise: the camera has no imager size");
  if (options.supersample > 1) {
    const int s = options.supersample;
    MeshRasterOptions fine = options;
    fine.supersample = 1;
    fine.max_edge_px = options.max_edge_px * s;
    fine.point_radius_px = options.point_radius_px * s;
    return AverageBlocks(RasteriseMesh(mesh, camera.Scaled(s), fine), s, width, height,
                         ResolveThreads(options.threads));
  }
  const int64_t vertex_count = static_cast<int64_t>(mesh.vertices.size());
  for (const auto& f : mesh.faces) {
    if (f.minCoeff() < 0 || f.maxCoeff() >= vertex_count)
      Fail("rasterise: a face indexes a vertex the mesh does not have");
  }
  if (!mesh.colors.empty() && mesh.colors.size() != mesh.vertices.size())
    Fail("rasterise: colours do not match vertices");
  if (!mesh.normals.empty() && mesh.normals.size() != mesh.vertices.size())
    Fail("rasterise: normals do not match vertices");

  Mesh with_normals;
  const Mesh* source = &mesh;
  if (mesh.normals.empty() && !mesh.faces.empty()) {
    with_normals = mesh;
    with_normals.ComputeNormals();
    source = &with_normals;
  }
  const int threads = ResolveThreads(options.threads);
  const FastProjector projector(camera);
  const Eigen::Matrix3f rotation = camera.cam_from_world().rotation().cast<float>();
  auto surface_point = [&](int i) {
    SurfacePoint p;
    p.world = source->vertices[i];
    p.color = source->colors.empty() ? Eigen::Vector3f(0.5f, 0.5f, 0.5f)
                                     : Eigen::Vector3f(source->colors[i][2], source->colors[i][1],
                                                       source->colors[i][0]) /
                                           255.0f;
    // Points without normals face the camera.
    p.normal = source->normals.empty()
                   ? Eigen::Vector3f(rotation.transpose() * Eigen::Vector3f(0, 0, -1))
                   : source->normals[i];
    return p;
  };

  // Screen triangles, gathered per thread then joined: the static schedule keeps the faces'
  // order, so equal depths resolve the same way on every run.
  std::vector<std::vector<ScreenTriangle>> per_thread(threads);
  int64_t split = 0;
  const int64_t primitives =
      mesh.faces.empty() ? vertex_count : static_cast<int64_t>(mesh.faces.size());
#pragma omp parallel for num_threads(threads) schedule(static) reduction(+ : split)
  for (int64_t i = 0; i < primitives; ++i) {
    auto& out = per_thread[omp_get_thread_num()];
    if (mesh.faces.empty()) {
      SplatPoint(projector, surface_point(static_cast<int>(i)), rotation,
                 static_cast<float>(options.point_radius_px), &out);
    } else {
      const auto& f = mesh.faces[i];
      const SurfacePoint corner[3] = {surface_point(f.x()), surface_point(f.y()),
                                      surface_point(f.z())};
      if (TriangleSplitter(projector, options).Split(corner, 0, &out)) ++split;
    }
  }
  std::vector<ScreenTriangle> triangles;
  for (auto& part : per_thread) triangles.insert(triangles.end(), part.begin(), part.end());

  GBuffer out;
  out.triangles_drawn = static_cast<int64_t>(triangles.size());
  out.triangles_split = split;
  out.color = cv::Mat(height, width, CV_32FC3, cv::Scalar::all(0));
  out.normal = cv::Mat(height, width, CV_32FC3, cv::Scalar::all(0));
  out.position = cv::Mat(height, width, CV_32FC3, cv::Scalar::all(0));
  out.depth = cv::Mat(height, width, CV_32F, cv::Scalar(std::numeric_limits<float>::quiet_NaN()));
  out.mask = cv::Mat(height, width, CV_8U, cv::Scalar(0));
  if (triangles.empty()) return out;

  // Bin triangles into bands of rows; each band is filled by one task.
  const int band_rows = std::max(4, height / (threads * 8));
  const int bands = (height + band_rows - 1) / band_rows;
  std::vector<std::vector<int32_t>> binned(bands);
  for (size_t i = 0; i < triangles.size(); ++i) {
    const auto& p = triangles[i].pixel;
    const float y0 = std::min({p[0].y(), p[1].y(), p[2].y()}),
                y1 = std::max({p[0].y(), p[1].y(), p[2].y()});
    const int first = std::max(0, static_cast<int>(std::ceil(y0)) / band_rows);
    const int last =
        std::min(bands - 1, static_cast<int>(std::floor(std::min(y1, height - 1.0f))) / band_rows);
    for (int b = first; b <= last; ++b) binned[b].push_back(static_cast<int32_t>(i));
  }

#pragma omp parallel for num_threads(threads) schedule(dynamic)
  for (int band = 0; band < bands; ++band) {
    const int row0 = band * band_rows, row1 = std::min(height, row0 + band_rows);
    std::vector<float> inv_z_best(static_cast<size_t>(row1 - row0) * width, 0.0f);
    for (int32_t index : binned[band]) {
      const ScreenTriangle& t = triangles[index];
      const Eigen::Vector2f a = t.pixel[0], b = t.pixel[1], c = t.pixel[2];
      const float area = (b - a).x() * (c - a).y() - (b - a).y() * (c - a).x();
      if (std::abs(area) < 1e-12f) continue;
      const int x0 = std::max(0, static_cast<int>(std::ceil(std::min({a.x(), b.x(), c.x()}))));
      const int x1 =
          std::min(width - 1, static_cast<int>(std::floor(std::max({a.x(), b.x(), c.x()}))));
      const int y0 = std::max(row0, static_cast<int>(std::ceil(std::min({a.y(), b.y(), c.y()}))));
      const int y1 =
          std::min(row1 - 1, static_cast<int>(std::floor(std::max({a.y(), b.y(), c.y()}))));
      for (int y = y0; y <= y1; ++y) {
        float* best = &inv_z_best[static_cast<size_t>(y - row0) * width];
        for (int x = x0; x <= x1; ++x) {
          const Eigen::Vector2f q(static_cast<float>(x), static_cast<float>(y));
          const float w0 = ((b - q).x() * (c - q).y() - (b - q).y() * (c - q).x()) / area;
          const float w1 = ((c - q).x() * (a - q).y() - (c - q).y() * (a - q).x()) / area;
          const float w2 = 1 - w0 - w1;
          if (w0 < 0 || w1 < 0 || w2 < 0) continue;
          // 1/z is affine in the image of a (small) triangle; attributes over z are too.
          const float inv_z = w0 * t.inv_z[0] + w1 * t.inv_z[1] + w2 * t.inv_z[2];
          if (!(inv_z > best[x])) continue;
          best[x] = inv_z;
          const float p0 = w0 * t.inv_z[0] / inv_z, p1 = w1 * t.inv_z[1] / inv_z,
                      p2 = w2 * t.inv_z[2] / inv_z;
          const Eigen::Vector3f color = p0 * t.color[0] + p1 * t.color[1] + p2 * t.color[2];
          const Eigen::Vector3f world = p0 * t.world[0] + p1 * t.world[1] + p2 * t.world[2];
          Eigen::Vector3f normal = p0 * t.normal[0] + p1 * t.normal[1] + p2 * t.normal[2];
          const float norm = normal.norm();
          if (norm > 0) normal /= norm;
          out.color.at<cv::Vec3f>(y, x) = {color.x(), color.y(), color.z()};
          out.normal.at<cv::Vec3f>(y, x) = {normal.x(), normal.y(), normal.z()};
          out.position.at<cv::Vec3f>(y, x) = {world.x(), world.y(), world.z()};
          out.depth.at<float>(y, x) = 1.0f / inv_z;
          out.mask.at<uint8_t>(y, x) = 255;
        }
      }
    }
  }
  return out;
}

cv::Mat CompositeRawRender(const GBuffer& buffers, const cv::Mat& background) {
  cv::Mat out = background.empty() ? cv::Mat(buffers.color.size(), CV_32FC3, cv::Scalar::all(0))
                                   : background.clone();
  if (out.size() != buffers.color.size() || out.type() != CV_32FC3) {
    Fail("raw render: the background is ", out.cols, "x", out.rows, " but the buffers are ",
         buffers.color.cols, "x", buffers.color.rows, " (both must be CV_32FC3)");
  }
  for (int y = 0; y < out.rows; ++y) {
    for (int x = 0; x < out.cols; ++x) {
      const uint8_t m = buffers.mask.at<uint8_t>(y, x);
      if (m == 0) continue;
      const float a = m / 255.0f;
      out.at<cv::Vec3f>(y, x) =
          a * buffers.color.at<cv::Vec3f>(y, x) + (1 - a) * out.at<cv::Vec3f>(y, x);
    }
  }
  return out;
}

}  // namespace holocap
