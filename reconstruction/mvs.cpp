// Plane-sweep multi-view stereo inside the visual hull. For each reference view, fronto-
// parallel planes are swept through the depth range the hull allows; each source view is
// warped onto the plane and compared by NCC with box-filtered window sums, so the cost per
// plane is a few passes over the subject's bounding box. The depth of the best mean of the k
// best source NCCs is refined by a parabola; then depths that no other view's depth map
// confirms are dropped.
#include <omp.h>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>

#include "core/error.h"
#include "reconstruction/projector.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

void MvsOptions::Check() const {
  if (neighbors < 1 || neighbors > 16)
    Fail("mvs neighbors must be in [1, 16] (got ", neighbors, ")");
  if (window_radius < 1 || window_radius > 10) Fail("mvs window_radius must be in [1, 10]");
  if (!(depth_step_px > 0 && depth_step_px <= 4)) Fail("mvs depth_step_px must be in (0, 4]");
  if (!(hull_margin_m >= 0) || !(search_depth_m > 0))
    Fail("mvs hull margin must be >= 0 and search depth > 0");
  if (!(min_ncc > -1 && min_ncc < 1)) Fail("mvs min_ncc must be in (-1, 1)");
  if (best_k < 1 || best_k > neighbors) Fail("mvs best_k must be in [1, neighbors]");
  if (min_consistent_views < 0 || min_consistent_views > neighbors) {
    Fail("mvs min_consistent_views must be in [0, neighbors]");
  }
  if (!(max_reprojection_px > 0 && max_relative_depth > 0))
    Fail("mvs consistency tolerances must be > 0");
  if (threads < 0) Fail("mvs threads must be >= 0");
}

namespace {

constexpr float kNan = std::numeric_limits<float>::quiet_NaN();

std::vector<int> NearestViews(const std::vector<View>& views, size_t ref, int count) {
  std::vector<std::pair<double, int>> order;
  const Eigen::Vector3d centre = views[ref].camera.center_in_world();
  const Eigen::Vector3d axis = views[ref].camera.world_from_cam().rotation().col(2);
  for (size_t i = 0; i < views.size(); ++i) {
    if (i == ref) continue;
    // Views facing away see the other side of the subject.
    if (views[i].camera.world_from_cam().rotation().col(2).dot(axis) < 0) continue;
    order.emplace_back((views[i].camera.center_in_world() - centre).norm(), static_cast<int>(i));
  }
  std::sort(order.begin(), order.end());
  std::vector<int> out;
  for (size_t i = 0; i < order.size() && static_cast<int>(i) < count; ++i)
    out.push_back(order[i].second);
  return out;
}

cv::Mat Gray(const cv::Mat& image) {
  cv::Mat gray, out;
  cv::cvtColor(image, gray, cv::COLOR_BGR2GRAY);
  gray.convertTo(out, CV_32F);
  return out;
}

struct SweepResult {
  cv::Mat depth;  // CV_32F, NaN = none
  int64_t searched = 0, matched = 0, planes = 0;
};

SweepResult SweepView(const std::vector<View>& views, const std::vector<cv::Mat>& grays, size_t ref,
                      const std::vector<int>& sources, const cv::Mat& near,
                      const MvsOptions& options) {
  SweepResult result;
  const View& view = views[ref];
  const int w = view.camera.width(), h = view.camera.height();
  result.depth = cv::Mat(h, w, CV_32F, cv::Scalar(kNan));
  if (static_cast<int>(sources.size()) < options.best_k) return result;
  const int r = options.window_radius;
  const int win = 2 * r + 1;
  const float n_win = static_cast<float>(win * win);

  // Per-pixel search range [lo, hi] from the hull, on the silhouette.
  cv::Mat lo(h, w, CV_32F, cv::Scalar(kNan)), hi(h, w, CV_32F, cv::Scalar(kNan));
  cv::Mat active_pixels = cv::Mat::zeros(h, w, CV_8U);
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      float z = near.at<float>(y, x);
      if (!std::isfinite(z) || view.mask.at<uint8_t>(y, x) == 0) continue;
      lo.at<float>(y, x) = std::max(0.05f, z - static_cast<float>(options.hull_margin_m));
      hi.at<float>(y, x) = z + static_cast<float>(options.search_depth_m);
      active_pixels.at<uint8_t>(y, x) = 255;
    }
  }
  cv::Rect roi = cv::boundingRect(active_pixels);
  if (roi.area() == 0) return result;
  roi = cv::Rect(roi.x - r - 1, roi.y - r - 1, roi.width + 2 * r + 2, roi.height + 2 * r + 2) &
        cv::Rect(0, 0, w, h);
  // Window pixels of active pixels need warps too: widen each pixel's range to its window's.
  cv::Mat lo_win, hi_win;
  {
    cv::Mat lo_fill = lo.clone(), hi_fill = hi.clone();
    lo_fill.setTo(1e9f, lo != lo);
    hi_fill.setTo(-1e9f, hi != hi);
    cv::erode(lo_fill, lo_win, cv::Mat::ones(win, win, CV_8U));
    cv::dilate(hi_fill, hi_win, cv::Mat::ones(win, win, CV_8U));
  }
  double zmin = 1e9, zmax = -1e9;
  cv::minMaxLoc(lo_win(roi), &zmin, nullptr);
  cv::minMaxLoc(hi_win(roi), nullptr, &zmax);
  if (!(zmax > zmin)) return result;

  // Plane spacing: the depth change that moves a point depth_step_px in the nearest source.
  recon::FastProjector ref_projector(view.camera);
  double baseline = 1e9;
  for (int s : sources)
    baseline = std::min(baseline,
                        (views[s].camera.center_in_world() - view.camera.center_in_world()).norm());
  const double focal = ref_projector.focal();
  std::vector<float> planes;
  for (double z = zmin; z <= zmax;) {
    planes.push_back(static_cast<float>(z));
    z += std::max(1e-4, options.depth_step_px * z * z / (focal * baseline));
  }
  result.planes = static_cast<int64_t>(planes.size());

  const cv::Mat rays = recon::NormalisedRays(view.camera);
  const Pose world_from_ref = view.camera.world_from_cam();
  std::vector<recon::FastProjector> projectors;
  std::vector<Eigen::Matrix3f> rotation;  // source_from_ref
  std::vector<Eigen::Vector3f> translation;
  for (int s : sources) {
    projectors.emplace_back(views[s].camera);
    Pose source_from_ref = views[s].camera.cam_from_world() * world_from_ref;
    rotation.push_back(source_from_ref.rotation().cast<float>());
    translation.push_back(source_from_ref.translation().cast<float>());
  }
  const cv::Mat ref_gray = grays[ref](roi);
  cv::Mat sum_r, sum_rr;
  cv::boxFilter(ref_gray, sum_r, CV_32F, cv::Size(win, win), cv::Point(-1, -1), false,
                cv::BORDER_CONSTANT);
  cv::boxFilter(ref_gray.mul(ref_gray), sum_rr, CV_32F, cv::Size(win, win), cv::Point(-1, -1),
                false, cv::BORDER_CONSTANT);

  const int rw = roi.width, rh = roi.height;
  const int ns = static_cast<int>(sources.size());
  const int k_best = options.best_k;
  cv::Mat best_score(rh, rw, CV_32F, cv::Scalar(-2)), best_plane(rh, rw, CV_32S, cv::Scalar(-1));
  cv::Mat prev_score(rh, rw, CV_32F, cv::Scalar(-2)), before_best(rh, rw, CV_32F, cv::Scalar(-2)),
      after_best(rh, rw, CV_32F, cv::Scalar(-2));
  std::vector<cv::Mat> warped(ns), valid(ns), ncc(ns);
  for (int s = 0; s < ns; ++s) {
    warped[s] = cv::Mat(rh, rw, CV_32F);
    valid[s] = cv::Mat(rh, rw, CV_32F);
    ncc[s] = cv::Mat(rh, rw, CV_32F);
  }
  for (size_t k = 0; k < planes.size(); ++k) {
    const float z = planes[k];
    for (int s = 0; s < ns; ++s) {
      const cv::Mat& src = grays[sources[s]];
      for (int y = 0; y < rh; ++y) {
        float* wrow = warped[s].ptr<float>(y);
        float* vrow = valid[s].ptr<float>(y);
        const float* lrow = lo_win.ptr<float>(y + roi.y) + roi.x;
        const float* hrow = hi_win.ptr<float>(y + roi.y) + roi.x;
        const cv::Vec2f* ray = rays.ptr<cv::Vec2f>(y + roi.y) + roi.x;
        for (int x = 0; x < rw; ++x) {
          wrow[x] = 0;
          vrow[x] = 0;
          if (z < lrow[x] || z > hrow[x] || !std::isfinite(ray[x][0])) continue;
          Eigen::Vector3f p =
              rotation[s] * Eigen::Vector3f(ray[x][0] * z, ray[x][1] * z, z) + translation[s];
          float u, v, value;
          if (!projectors[s].Project(p, &u, &v) || !recon::SampleBilinear(src, u, v, &value))
            continue;
          wrow[x] = value;
          vrow[x] = 1;
        }
      }
      cv::Mat sum_w, sum_ww, sum_rw, count;
      const cv::Size size(win, win);
      cv::boxFilter(warped[s], sum_w, CV_32F, size, cv::Point(-1, -1), false, cv::BORDER_CONSTANT);
      cv::boxFilter(warped[s].mul(warped[s]), sum_ww, CV_32F, size, cv::Point(-1, -1), false,
                    cv::BORDER_CONSTANT);
      cv::boxFilter(warped[s].mul(ref_gray), sum_rw, CV_32F, size, cv::Point(-1, -1), false,
                    cv::BORDER_CONSTANT);
      cv::boxFilter(valid[s], count, CV_32F, size, cv::Point(-1, -1), false, cv::BORDER_CONSTANT);
      for (int y = 0; y < rh; ++y) {
        float* out = ncc[s].ptr<float>(y);
        for (int x = 0; x < rw; ++x) {
          out[x] = -1;
          if (count.at<float>(y, x) < n_win - 0.5f) continue;
          float sr = sum_r.at<float>(y, x), sw = sum_w.at<float>(y, x);
          float var_r = sum_rr.at<float>(y, x) - sr * sr / n_win;
          float var_w = sum_ww.at<float>(y, x) - sw * sw / n_win;
          // Textureless windows (under ~1.5 DN of contrast) match anything: no vote.
          if (var_r < 2.0f * n_win || var_w < 2.0f * n_win) continue;
          out[x] = (sum_rw.at<float>(y, x) - sr * sw / n_win) / std::sqrt(var_r * var_w);
        }
      }
    }
    for (int y = 0; y < rh; ++y) {
      const float* lrow = lo.ptr<float>(y + roi.y) + roi.x;
      const float* hrow = hi.ptr<float>(y + roi.y) + roi.x;
      float* best = best_score.ptr<float>(y);
      int* plane = best_plane.ptr<int>(y);
      float* prev = prev_score.ptr<float>(y);
      float* before = before_best.ptr<float>(y);
      float* after = after_best.ptr<float>(y);
      for (int x = 0; x < rw; ++x) {
        if (!(z >= lrow[x] && z <= hrow[x])) {
          prev[x] = -2;
          continue;
        }
        float scores[16];
        for (int s = 0; s < ns; ++s) scores[s] = ncc[s].at<float>(y, x);
        std::partial_sort(scores, scores + k_best, scores + ns, std::greater<float>());
        float cost = 0;
        for (int i = 0; i < k_best; ++i) cost += scores[i];
        cost /= k_best;
        if (plane[x] == static_cast<int>(k) - 1 && plane[x] >= 0) after[x] = cost;
        if (cost > best[x]) {
          best[x] = cost;
          plane[x] = static_cast<int>(k);
          before[x] = prev[x];
          after[x] = -2;
        }
        prev[x] = cost;
      }
    }
  }
  for (int y = 0; y < rh; ++y) {
    for (int x = 0; x < rw; ++x) {
      if (!std::isfinite(lo.at<float>(y + roi.y, x + roi.x))) continue;
      ++result.searched;
      int k = best_plane.at<int>(y, x);
      float score = best_score.at<float>(y, x);
      if (k < 0 || score < options.min_ncc) continue;
      float z = planes[k];
      float b = before_best.at<float>(y, x), a = after_best.at<float>(y, x);
      // A parabola through the best and its neighbours places the minimum between planes.
      if (b > -2 && a > -2 && k > 0 && k + 1 < static_cast<int>(planes.size())) {
        float denominator = b - 2 * score + a;
        if (denominator < 0) {
          float offset = std::clamp(0.5f * (b - a) / denominator, -0.5f, 0.5f);
          float step = offset > 0 ? planes[k + 1] - z : z - planes[k - 1];
          z += offset * step;
        }
      }
      result.depth.at<float>(y + roi.y, x + roi.x) = z;
      ++result.matched;
    }
  }
  return result;
}

}  // namespace

std::vector<cv::Mat> ComputeMvsDepth(const std::vector<View>& views, const VisualHull& hull,
                                     const MvsOptions& options, MvsSummary* summary_out) {
  options.Check();
  auto start = std::chrono::steady_clock::now();
  if (views.size() < 2) Fail("multi-view stereo needs at least two views");
  for (const View& view : views) {
    if (view.image.type() != CV_8UC3 || view.mask.type() != CV_8UC1 ||
        view.image.cols != view.camera.width() || view.image.rows != view.camera.height() ||
        view.mask.size() != view.image.size()) {
      Fail("multi-view stereo: view '", view.name,
           "' needs a CV_8UC3 image and a CV_8U mask of its camera's size");
    }
  }
  if (hull.volume == nullptr) Fail("multi-view stereo needs a visual hull");
  MeshingOptions meshing;
  meshing.normals = false;
  const Mesh hull_mesh = ExtractMesh(*hull.volume, meshing);
  const int threads = recon::ResolveThreads(options.threads);
  const int n = static_cast<int>(views.size());
  std::vector<cv::Mat> grays(n);
  std::vector<std::vector<int>> sources(n);
  std::vector<SweepResult> sweeps(n);
  for (int i = 0; i < n; ++i) {
    grays[i] = Gray(views[i].image);
    sources[i] = NearestViews(views, i, options.neighbors);
  }
#pragma omp parallel for num_threads(threads) schedule(dynamic, 1)
  for (int i = 0; i < n; ++i) {
    cv::Mat near = RenderDepth(hull_mesh, views[i].camera);
    sweeps[i] = SweepView(views, grays, i, sources[i], near, options);
  }
  MvsSummary summary;
  for (const auto& s : sweeps) {
    summary.pixels_searched += s.searched;
    summary.pixels_matched += s.matched;
    summary.planes += s.planes;
  }
  // Geometric consistency between the depth maps.
  std::vector<cv::Mat> filtered(n);
  int64_t consistent_total = 0;
#pragma omp parallel for num_threads(threads) reduction(+ : consistent_total) schedule(dynamic, 1)
  for (int i = 0; i < n; ++i) {
    const View& view = views[i];
    const cv::Mat& depth = sweeps[i].depth;
    filtered[i] = cv::Mat(depth.size(), CV_32F, cv::Scalar(kNan));
    const cv::Mat rays = recon::NormalisedRays(view.camera);
    recon::FastProjector self(view.camera);
    std::vector<recon::FastProjector> others;
    std::vector<cv::Mat> other_rays;
    for (int s : sources[i]) {
      others.emplace_back(views[s].camera);
      other_rays.push_back(recon::NormalisedRays(views[s].camera));
    }
    const Eigen::Matrix3f world_from_cam_r = view.camera.world_from_cam().rotation().cast<float>();
    const Eigen::Vector3f world_from_cam_t =
        view.camera.world_from_cam().translation().cast<float>();
    for (int y = 0; y < depth.rows; ++y) {
      for (int x = 0; x < depth.cols; ++x) {
        float d = depth.at<float>(y, x);
        cv::Vec2f ray = rays.at<cv::Vec2f>(y, x);
        if (!std::isfinite(d) || !std::isfinite(ray[0])) continue;
        Eigen::Vector3f world =
            world_from_cam_r * Eigen::Vector3f(ray[0] * d, ray[1] * d, d) + world_from_cam_t;
        int agree = 0;
        for (size_t s = 0; s < others.size(); ++s) {
          float u, v, z;
          if (!others[s].ProjectWorld(world, &u, &v, &z)) continue;
          int px = static_cast<int>(std::lround(u)), py = static_cast<int>(std::lround(v));
          const cv::Mat& other = sweeps[sources[i][s]].depth;
          if (px < 0 || py < 0 || px >= other.cols || py >= other.rows) continue;
          float d_other = other.at<float>(py, px);
          cv::Vec2f r_other = other_rays[s].at<cv::Vec2f>(py, px);
          if (!std::isfinite(d_other) || !std::isfinite(r_other[0])) continue;
          Eigen::Vector3f back =
              others[s].camera().world_from_cam().cast<float>() *
              Eigen::Vector3f(r_other[0] * d_other, r_other[1] * d_other, d_other);
          float bu, bv, bz;
          if (!self.ProjectWorld(back, &bu, &bv, &bz)) continue;
          float reprojection = std::hypot(bu - x, bv - y);
          if (reprojection <= options.max_reprojection_px &&
              std::abs(bz - d) <= options.max_relative_depth * d)
            ++agree;
        }
        if (agree >= options.min_consistent_views) {
          filtered[i].at<float>(y, x) = d;
          ++consistent_total;
        }
      }
    }
  }
  summary.pixels_consistent = consistent_total;
  summary.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  if (summary.pixels_consistent == 0) {
    summary.End(Termination::kDegenerate,
                Cat("no depth survived: ", summary.pixels_matched, " of ", summary.pixels_searched,
                    " pixels matched, none consistent across views"));
  } else {
    summary.End(Termination::kSuccess, Cat(summary.pixels_consistent, " consistent depths of ",
                                           summary.pixels_searched, " pixels searched"));
  }
  if (summary_out != nullptr) *summary_out = summary;
  return filtered;
}

}  // namespace holocap
