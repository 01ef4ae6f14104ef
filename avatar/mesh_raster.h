// Rasterising a reconstruction (a mesh with per-vertex colours, or fused points) into a
// calibrated camera: the G-buffers that neural rerendering learns from and the raw render that
// playback composites. Vertices go through the mrcal lens exactly (core/projector.h).
#pragma once

#include <cstdint>
#include <opencv2/core.hpp>

#include "core/camera.h"
#include "core/mesh.h"

namespace holocap {

struct MeshRasterOptions {
  // Vertices go through the lens model exactly, but a triangle's interior is filled in pixel
  // space, where a wide lens bends its straight edges: triangles whose projected edge exceeds
  // this are split in 3D (midpoints projected through the lens) until it holds.
  double max_edge_px = 16;
  int max_subdivisions = 5;      // splitting depth limit (4^5 pieces per triangle at most)
  double point_radius_px = 1.5;  // a mesh without faces (fused points) is splatted as squares
  int supersample = 1;           // samples per pixel along each axis (1..4): the buffers average
                                 // the covered samples and the mask holds the covered fraction,
                                 // as a camera integrates its pixel, instead of one sample at
                                 // the pixel centre (edge lengths and radii stay in output pixels)
  int threads = 0;               // 0: all cores
  void Check() const;            // throws Error naming the bad field
};

// What the network sees of a reconstruction through one camera.
struct GBuffer {
  cv::Mat color;     // CV_32FC3 BGR in [0, 1] (the reconstruction's vertex colours), 0 where empty
  cv::Mat depth;     // CV_32F z-depth in metres, NaN where empty
  cv::Mat normal;    // CV_32FC3 unit normal in camera coordinates (OpenCV axes), 0 where empty
  cv::Mat position;  // CV_32FC3 surface point in world coordinates (metres), 0 where empty:
                     // where on the body a pixel lies, whichever camera looks
  cv::Mat mask;      // CV_8U, 255 where a surface covers the pixel centre (supersampled: 255 x the
                     // covered fraction of the pixel's samples; colour, depth, normal and position
                     // then average the covered samples)
  int64_t triangles_drawn = 0;  // after splitting
  int64_t triangles_split = 0;  // triangles of the mesh that needed splitting
};

// Z-buffered rasterisation of a mesh (per-vertex colours and normals; normals are computed
// when the mesh has none) or, without faces, of its points. Parallel over bands of rows.
// Throws Error for a mesh with faces indexing missing vertices.
GBuffer RasteriseMesh(const Mesh& mesh, const CameraModel& camera,
                      const MeshRasterOptions& options = {});

// The raw textured-mesh render composited over a background (CV_32FC3 BGR in [0, 1], or empty
// for black) by the mask's coverage: what the reconstruction alone shows a camera.
cv::Mat CompositeRawRender(const GBuffer& buffers, const cv::Mat& background);

}  // namespace holocap
