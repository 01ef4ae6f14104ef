// Visual hull by octree carving of a signed field. Each view's silhouette becomes a signed
// 2D distance (pixels, negative inside); at a point it is turned into metres by depth over
// focal length, and the hull is where the largest of them (or, conservatively, the (k+1)-th
// largest) is negative. Octree cells whose bounding sphere cannot contain a sign change are
// decided whole; only blocks the surface crosses are evaluated voxel by voxel.
#include <omp.h>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <unordered_set>

#include "core/check_option.h"
#include "core/error.h"
#include "core/projector.h"
#include "core/threads.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

void HullOptions::Check() const {
  HOLOCAP_CHECK_OPTION_GT(voxel_m, 0);
  HOLOCAP_CHECK_OPTION_LT(voxel_m, 1);
  HOLOCAP_CHECK_OPTION(bounds.valid(), bounds, "an empty box");
  HOLOCAP_CHECK_OPTION_GE(tolerated_bad_views, 0);
  HOLOCAP_CHECK_OPTION_GE(min_views, 1);
  HOLOCAP_CHECK_OPTION_GT(margin_px, -10);
  HOLOCAP_CHECK_OPTION_LT(margin_px, 100);
  HOLOCAP_CHECK_OPTION_GE(min_subject_px, 0);
  HOLOCAP_CHECK_OPTION_GE(threads, 0);
}

double VisualHull::Field(const Eigen::Vector3d& point_in_world) const {
  constexpr double kInfinity = std::numeric_limits<double>::infinity();
  if (volume == nullptr) return kInfinity;
  double sdf;
  if (volume->Sample(point_in_world, &sdf)) return sdf;
  const Eigen::Vector3i voxel = volume->VoxelOf(point_in_world);
  if (inside_blocks.count(SparseVolume::Key(SparseVolume::BlockOf(voxel)))) return -kInfinity;
  // Within a voxel of evaluated blocks, the nearest voxel decides.
  const Voxel* nearest = volume->FindVoxel(voxel);
  return nearest != nullptr && nearest->weight > 0 ? nearest->sdf : kInfinity;
}

bool VisualHull::Contains(const Eigen::Vector3d& point_in_world, double tolerance_m) const {
  return Field(point_in_world) <= tolerance_m;
}

Box VisualHull::Extent() const {
  Box extent = Box::Empty();
  if (volume == nullptr) return extent;
  volume->ForEachBlock([&](const Eigen::Vector3i& block, const VoxelBlock& data) {
    for (int z = 0; z < kBlockSide; ++z)
      for (int y = 0; y < kBlockSide; ++y)
        for (int x = 0; x < kBlockSide; ++x) {
          const Voxel& voxel = data.at(x, y, z);
          if (voxel.weight > 0 && voxel.sdf < 0)
            extent.Extend(volume->CenterOf(block * kBlockSide + Eigen::Vector3i(x, y, z)));
        }
  });
  for (uint64_t key : inside_blocks) {
    const Eigen::Vector3i block = SparseVolume::Unkey(key);
    extent.Extend(volume->CenterOf(block * kBlockSide));
    extent.Extend(volume->CenterOf(block * kBlockSide + Eigen::Vector3i::Constant(kBlockSide - 1)));
  }
  return extent;
}

namespace {

struct HullView {
  FastProjector projector;
  cv::Mat signed_distance;  // CV_32F pixels, negative inside the silhouette
};

// Signed distance to the silhouette boundary in pixels (boundary between pixel centres).
cv::Mat SignedDistance(const cv::Mat& mask, double margin_px) {
  cv::Mat inside = mask != 0;
  cv::Mat outside = mask == 0;
  cv::Mat to_inside, to_outside;
  cv::distanceTransform(outside, to_inside, cv::DIST_L2, cv::DIST_MASK_PRECISE);  // outside px
  cv::distanceTransform(inside, to_outside, cv::DIST_L2, cv::DIST_MASK_PRECISE);  // inside px
  cv::Mat out(mask.size(), CV_32F);
  for (int y = 0; y < mask.rows; ++y) {
    const uint8_t* m = mask.ptr<uint8_t>(y);
    const float* ti = to_inside.ptr<float>(y);
    const float* to = to_outside.ptr<float>(y);
    float* o = out.ptr<float>(y);
    for (int x = 0; x < mask.cols; ++x) {
      // An empty mask gives distances of ~1e10 from OpenCV; keep them large but finite.
      float d = m[x] ? -(std::min(to[x], 1e6f) - 0.5f) : (std::min(ti[x], 1e6f) - 0.5f);
      o[x] = d - static_cast<float>(margin_px);
    }
  }
  return out;
}

constexpr float kOutside = 1e3f;  // field value where too few views see a point

// The field at a point: returns kOutside when fewer than min_views see it.
float FieldAt(const std::vector<HullView>& views, const Eigen::Vector3f& point, int min_views,
              int tolerated, float* scratch) {
  int seen = 0;
  for (const HullView& view : views) {
    Eigen::Vector3f p = view.projector.ToCamera(point);
    float u, v;
    if (!view.projector.Project(p, &u, &v)) continue;
    float d;
    if (!SampleBilinear(view.signed_distance, u, v, &d)) continue;
    scratch[seen++] = d * p.z() / view.projector.focal();
  }
  if (seen < min_views) return kOutside;
  int k = std::min(tolerated, seen - 1);
  std::nth_element(scratch, scratch + k, scratch + seen, std::greater<float>());
  return scratch[k];
}

// What a cell (bounding sphere centre, radius) looks like: -1 wholly inside, +1 wholly
// outside, 0 undecided. Views that see the whole cell bound the field over it; views that see
// only part of it cannot keep it, but the others can still carve it.
int ClassifyCell(const std::vector<HullView>& views, const Eigen::Vector3f& centre, float radius,
                 int min_views, int tolerated, float* scratch) {
  int seen = 0, partial = 0, carving = 0;
  for (const HullView& view : views) {
    Eigen::Vector3f p = view.projector.ToCamera(centre);
    if (p.z() < -radius) continue;  // wholly behind the camera
    float u, v;
    if (p.z() <= radius * 1.5f || !view.projector.Project(p, &u, &v)) {
      ++partial;  // too close to the camera to bound its footprint
      continue;
    }
    float reach = 1.3f * radius * view.projector.focal() / (p.z() - radius) + 1;
    if (!view.projector.InImage(u, v, -reach)) continue;  // the view cannot see any of the cell
    float d = 0;
    if (!view.projector.InImage(u, v, reach) || !SampleBilinear(view.signed_distance, u, v, &d)) {
      ++partial;
      continue;
    }
    // Metres at the near side of the sphere, with slack for lens distortion.
    float metres = d * (p.z() - radius) / view.projector.focal();
    scratch[seen++] = metres;
    carving += metres > 1.25f * radius;
  }
  if (carving > tolerated) return +1;
  if (seen + partial < min_views) return +1;
  if (partial > 0 || seen < min_views) return 0;
  int k = std::min(tolerated, seen - 1);
  std::nth_element(scratch, scratch + k, scratch + seen, std::greater<float>());
  return scratch[k] < -1.25f * radius ? -1 : 0;
}

// Each view's projector and silhouette distance; throws Error for a missing or mis-sized
// silhouette.
std::vector<HullView> PrepareViews(const std::vector<View>& views, double margin_px) {
  if (views.empty()) Fail("visual hull needs at least one view");
  std::vector<HullView> hull_views;
  for (const View& view : views) {
    if (view.mask.empty()) Fail("visual hull: view '", view.name, "' has no silhouette");
    if (view.mask.type() != CV_8UC1 || view.mask.cols != view.camera.width() ||
        view.mask.rows != view.camera.height()) {
      Fail("visual hull: silhouette of '", view.name, "' is ", view.mask.cols, "x", view.mask.rows,
           " CV_8U expected ", view.camera.width(), "x", view.camera.height());
    }
    hull_views.push_back({FastProjector(view.camera), SignedDistance(view.mask, margin_px)});
  }
  return hull_views;
}

// How many pixels across a ball of `diameter_m` at `centre` spans: the median over the views
// whose image its centre projects into (0 when none does).
double MedianSpanPx(const std::vector<View>& views, const Eigen::Vector3d& centre,
                    double diameter_m) {
  std::vector<double> spans;
  for (const View& view : views) {
    const Eigen::Vector3d in_cam = view.camera.cam_from_world() * centre;
    const Eigen::Vector3d half(0.5 * diameter_m, 0, 0);
    Eigen::Vector2d middle, left, right;
    if (in_cam.z() <= 0 || !view.camera.Project(in_cam, &middle) || !view.camera.InImage(middle) ||
        !view.camera.Project(in_cam - half, &left) || !view.camera.Project(in_cam + half, &right))
      continue;
    spans.push_back((right - left).norm());
  }
  if (spans.empty()) return 0;
  std::nth_element(spans.begin(), spans.begin() + spans.size() / 2, spans.end());
  return spans[spans.size() / 2];
}

// The hull's figures (octree cells tested, surface and inside blocks, volume, its span in the
// views) and its ending: DEGENERATE when empty or too small to be a subject.
HullSummary SummariseHull(const VisualHull& hull, const std::vector<View>& views,
                          const HullOptions& options, int64_t tested, int64_t surface_blocks,
                          int64_t inside_voxels, std::chrono::steady_clock::duration elapsed) {
  const double voxel = options.voxel_m;
  const int tolerated = options.tolerated_bad_views;
  HullSummary summary;
  summary.octree_cells = tested;
  summary.surface_blocks = surface_blocks;
  summary.inside_blocks = static_cast<int64_t>(hull.inside_blocks.size());
  summary.volume_m3 = (static_cast<double>(inside_voxels) +
                       static_cast<double>(hull.inside_blocks.size()) * kBlockVoxels) *
                      voxel * voxel * voxel;
  summary.seconds = std::chrono::duration<double>(elapsed).count();
  const double diameter_m = std::cbrt(6 * summary.volume_m3 / M_PI);
  if (summary.volume_m3 > 0)
    summary.subject_px = MedianSpanPx(views, hull.Extent().center(), diameter_m);
  if (summary.volume_m3 <= 0) {
    summary.End(Termination::kDegenerate,
                Cat("the hull is empty: no point in the bounds lies inside ",
                    tolerated > 0 ? "all but " + std::to_string(tolerated) + " of " : "all ",
                    views.size(), " silhouettes"));
  } else if (summary.subject_px < options.min_subject_px) {
    summary.End(
        Termination::kDegenerate,
        Cat("the hull is too small to be a subject: its ", std::round(summary.volume_m3 * 1e7) / 10,
            " cm3 are a ball ", std::round(diameter_m * 1e4) / 10, " mm across, ",
            std::round(summary.subject_px * 10) / 10, " px in the views (at least ",
            options.min_subject_px,
            " px: smaller is where specks or edges of the silhouettes meet)"));
  } else {
    summary.End(Termination::kSuccess,
                Cat("hull of ", summary.volume_m3 * 1e3, " litres from ", views.size(), " views"));
  }
  return summary;
}

}  // namespace

VisualHull ComputeVisualHull(const std::vector<View>& views, const HullOptions& options,
                             HullSummary* summary_out) {
  options.Check();
  auto start = std::chrono::steady_clock::now();
  std::vector<HullView> hull_views = PrepareViews(views, options.margin_px);
  const int threads = ResolveThreads(options.threads);
  const int tolerated = options.tolerated_bad_views;
  const int min_views = options.min_views;
  VisualHull hull;
  hull.volume = std::make_unique<SparseVolume>(options.voxel_m, options.bounds,
                                               std::numeric_limits<double>::infinity());
  SparseVolume& volume = *hull.volume;
  const double voxel = options.voxel_m;

  // Block range covering the bounds.
  Eigen::Vector3i lo =
      SparseVolume::BlockOf((options.bounds.min / voxel).array().floor().cast<int>());
  Eigen::Vector3i hi =
      SparseVolume::BlockOf((options.bounds.max / voxel).array().ceil().cast<int>());
  int span = (hi - lo).maxCoeff() + 1;
  int size = 1;
  while (size < span) size *= 2;

  struct Cell {
    Eigen::Vector3i origin;  // in blocks
    int size;                // in blocks
  };
  std::vector<Cell> level = {{lo, size}};
  std::vector<uint64_t> surface, inside;
  int64_t tested = 0;
  const size_t n_views = hull_views.size();
  while (!level.empty()) {
    std::vector<std::vector<Cell>> next(threads);
    std::vector<std::vector<uint64_t>> surface_t(threads), inside_t(threads);
    tested += static_cast<int64_t>(level.size());
#pragma omp parallel num_threads(threads)
    {
      int t = omp_get_thread_num();
      std::vector<float> scratch(n_views);
#pragma omp for schedule(dynamic, 16)
      for (size_t i = 0; i < level.size(); ++i) {
        const Cell cell = level[i];
        Eigen::Vector3i cell_hi = cell.origin + Eigen::Vector3i::Constant(cell.size - 1);
        if ((cell_hi.array() < lo.array()).any() || (cell.origin.array() > hi.array()).any())
          continue;
        Eigen::Vector3d first = (cell.origin * kBlockSide).cast<double>() * voxel;
        Eigen::Vector3d last =
            ((cell_hi + Eigen::Vector3i::Ones()) * kBlockSide - Eigen::Vector3i::Ones())
                .cast<double>() *
            voxel;
        Eigen::Vector3f centre = (0.5 * (first + last)).cast<float>();
        float radius = static_cast<float>(0.5 * (last - first).norm()) + 1e-6f;
        int state = ClassifyCell(hull_views, centre, radius, min_views, tolerated, scratch.data());
        if (state > 0) continue;
        if (state < 0) {
          for (int z = 0; z < cell.size; ++z)
            for (int y = 0; y < cell.size; ++y)
              for (int x = 0; x < cell.size; ++x)
                inside_t[t].push_back(SparseVolume::Key(cell.origin + Eigen::Vector3i(x, y, z)));
          continue;
        }
        if (cell.size == 1) {
          surface_t[t].push_back(SparseVolume::Key(cell.origin));
          continue;
        }
        int half = cell.size / 2;
        for (int c = 0; c < 8; ++c) {
          next[t].push_back(
              {cell.origin + half * Eigen::Vector3i(c & 1, (c >> 1) & 1, (c >> 2) & 1), half});
        }
      }
    }
    level.clear();
    for (int t = 0; t < threads; ++t) {
      level.insert(level.end(), next[t].begin(), next[t].end());
      surface.insert(surface.end(), surface_t[t].begin(), surface_t[t].end());
      inside.insert(inside.end(), inside_t[t].begin(), inside_t[t].end());
    }
  }
  // Surface blocks and their neighbours are evaluated voxel by voxel, so that every cube the
  // surface crosses has all eight corners (the neighbours may be outside the bounds: there the
  // field is "outside", which closes a subject cut by the bounds).
  std::unordered_set<uint64_t> evaluate;
  for (uint64_t key : surface) {
    Eigen::Vector3i block = SparseVolume::Unkey(key);
    for (int dz = -1; dz <= 1; ++dz)
      for (int dy = -1; dy <= 1; ++dy)
        for (int dx = -1; dx <= 1; ++dx)
          evaluate.insert(SparseVolume::Key(block + Eigen::Vector3i(dx, dy, dz)));
  }
  hull.inside_blocks.insert(inside.begin(), inside.end());
  std::vector<Eigen::Vector3i> coordinates;
  std::vector<VoxelBlock*> blocks;
  for (uint64_t key : evaluate) {
    coordinates.push_back(SparseVolume::Unkey(key));
    blocks.push_back(&volume.Allocate(coordinates.back()));
  }
  int64_t inside_voxels = 0;
  const Box& bounds = options.bounds;
#pragma omp parallel num_threads(threads) reduction(+ : inside_voxels)
  {
    std::vector<float> scratch(n_views);
#pragma omp for schedule(dynamic, 4)
    for (size_t b = 0; b < blocks.size(); ++b) {
      const Eigen::Vector3i base = coordinates[b] * kBlockSide;
      const bool block_inside = hull.inside_blocks.count(SparseVolume::Key(coordinates[b])) > 0;
      for (int z = 0; z < kBlockSide; ++z) {
        for (int y = 0; y < kBlockSide; ++y) {
          for (int x = 0; x < kBlockSide; ++x) {
            Eigen::Vector3d world = (base + Eigen::Vector3i(x, y, z)).cast<double>() * voxel;
            Voxel& out = blocks[b]->at(x, y, z);
            out.weight = 1;
            if (!bounds.Contains(world)) {
              out.sdf = static_cast<float>(voxel);
              continue;
            }
            out.sdf =
                FieldAt(hull_views, world.cast<float>(), min_views, tolerated, scratch.data());
            if (out.sdf < 0 && !block_inside) ++inside_voxels;
          }
        }
      }
    }
  }
  HullSummary summary =
      SummariseHull(hull, views, options, tested, static_cast<int64_t>(surface.size()),
                    inside_voxels, std::chrono::steady_clock::now() - start);
  if (summary_out != nullptr) *summary_out = summary;
  return hull;
}

}  // namespace holocap
