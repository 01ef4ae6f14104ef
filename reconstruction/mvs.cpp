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

#include "core/check_option.h"
#include "core/error.h"
#include "core/projector.h"
#include "core/threads.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

void MvsOptions::Check() const {
  HOLOCAP_CHECK_OPTION_IN(neighbors, 1, 16);
  HOLOCAP_CHECK_OPTION_IN(window_radius, 1, 10);
  HOLOCAP_CHECK_OPTION_GT(depth_step_px, 0);
  HOLOCAP_CHECK_OPTION_LE(depth_step_px, 4);
  HOLOCAP_CHECK_OPTION_GE(hull_margin_m, 0);
  HOLOCAP_CHECK_OPTION_GT(search_depth_m, 0);
  HOLOCAP_CHECK_OPTION_GT(min_ncc, -1);
  HOLOCAP_CHECK_OPTION_LT(min_ncc, 1);
  HOLOCAP_CHECK_OPTION_IN(best_k, 1, neighbors);
  HOLOCAP_CHECK_OPTION_IN(min_consistent_views, 0, neighbors);
  HOLOCAP_CHECK_OPTION_GT(max_reprojection_px, 0);
  HOLOCAP_CHECK_OPTION_GT(max_relative_depth, 0);
  HOLOCAP_CHECK_OPTION_IN(min_consistent_fraction, 0, 1);
  HOLOCAP_CHECK_OPTION_GE(threads, 0);
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

// One reference view's plane sweep: the per-pixel search range from the hull, the planes,
// the warp and NCC of every source per plane, the best of the k best kept per pixel, and the
// parabola that places the depth between planes.
class PlaneSweep {
 public:
  PlaneSweep(const std::vector<View>& views, const std::vector<cv::Mat>& grays, size_t ref,
             const std::vector<int>& sources, const MvsOptions& options)
      : views_(views),
        grays_(grays),
        ref_(ref),
        view_(views[ref]),
        sources_(sources),
        options_(options),
        w_(view_.camera.width()),
        h_(view_.camera.height()),
        r_(options.window_radius),
        win_(2 * r_ + 1),
        n_win_(static_cast<float>(win_ * win_)) {}

  SweepResult Run(const cv::Mat& near) {
    result_.depth = cv::Mat(h_, w_, CV_32F, cv::Scalar(kNan));
    if (static_cast<int>(sources_.size()) < options_.best_k) return result_;
    double zmin = 1e9, zmax = -1e9;
    if (!SearchRange(near, &zmin, &zmax)) return result_;
    ChoosePlanes(zmin, zmax);
    PrepareWarps();
    for (size_t k = 0; k < planes_.size(); ++k) {
      for (int s = 0; s < static_cast<int>(sources_.size()); ++s) {
        WarpSource(s, planes_[k]);
        ScoreSource(s);
      }
      KeepBest(k);
    }
    RefineDepths();
    return result_;
  }

 private:
  // Per-pixel search range [lo, hi] from the hull, on the silhouette, and the region of
  // interest around it; false when there is nothing to search.
  bool SearchRange(const cv::Mat& near, double* zmin, double* zmax) {
    lo_ = cv::Mat(h_, w_, CV_32F, cv::Scalar(kNan));
    hi_ = cv::Mat(h_, w_, CV_32F, cv::Scalar(kNan));
    cv::Mat active_pixels = cv::Mat::zeros(h_, w_, CV_8U);
    for (int y = 0; y < h_; ++y) {
      for (int x = 0; x < w_; ++x) {
        float z = near.at<float>(y, x);
        if (!std::isfinite(z) || view_.mask.at<uint8_t>(y, x) == 0) continue;
        // Never nearer than half the hull's depth: a scene's own length, whatever its scale.
        lo_.at<float>(y, x) = std::max(0.5f * z, z - static_cast<float>(options_.hull_margin_m));
        hi_.at<float>(y, x) = z + static_cast<float>(options_.search_depth_m);
        active_pixels.at<uint8_t>(y, x) = 255;
      }
    }
    roi_ = cv::boundingRect(active_pixels);
    if (roi_.area() == 0) return false;
    roi_ = cv::Rect(roi_.x - r_ - 1, roi_.y - r_ - 1, roi_.width + 2 * r_ + 2,
                    roi_.height + 2 * r_ + 2) &
           cv::Rect(0, 0, w_, h_);
    // Window pixels of active pixels need warps too: widen each pixel's range to its window's.
    cv::Mat lo_fill = lo_.clone(), hi_fill = hi_.clone();
    lo_fill.setTo(1e9f, lo_ != lo_);
    hi_fill.setTo(-1e9f, hi_ != hi_);
    cv::erode(lo_fill, lo_win_, cv::Mat::ones(win_, win_, CV_8U));
    cv::dilate(hi_fill, hi_win_, cv::Mat::ones(win_, win_, CV_8U));
    cv::minMaxLoc(lo_win_(roi_), zmin, nullptr);
    cv::minMaxLoc(hi_win_(roi_), nullptr, zmax);
    return *zmax > *zmin;
  }

  // Plane spacing: the depth change that moves a point depth_step_px in the nearest source.
  void ChoosePlanes(double zmin, double zmax) {
    FastProjector ref_projector(view_.camera);
    double baseline = 1e9;
    for (int s : sources_) {
      baseline = std::min(
          baseline, (views_[s].camera.center_in_world() - view_.camera.center_in_world()).norm());
    }
    const double focal = ref_projector.focal();
    for (double z = zmin; z <= zmax;) {
      planes_.push_back(static_cast<float>(z));
      z += std::max(1e-5 * z, options_.depth_step_px * z * z / (focal * baseline));
    }
    result_.planes = static_cast<int64_t>(planes_.size());
  }

  // The reference's rays and window sums, each source's projector and source_from_ref, and
  // the per-pixel buffers of the sweep.
  void PrepareWarps() {
    rays_ = NormalisedRays(view_.camera);
    const Pose world_from_ref = view_.camera.world_from_cam();
    for (int s : sources_) {
      projectors_.emplace_back(views_[s].camera);
      Pose source_from_ref = views_[s].camera.cam_from_world() * world_from_ref;
      rotation_.push_back(source_from_ref.rotation().cast<float>());
      translation_.push_back(source_from_ref.translation().cast<float>());
    }
    ref_gray_ = grays_[ref_](roi_);
    BoxSum(ref_gray_, &sum_r_);
    BoxSum(ref_gray_.mul(ref_gray_), &sum_rr_);

    const int rw = roi_.width, rh = roi_.height;
    best_score_ = cv::Mat(rh, rw, CV_32F, cv::Scalar(-2));
    best_plane_ = cv::Mat(rh, rw, CV_32S, cv::Scalar(-1));
    prev_score_ = cv::Mat(rh, rw, CV_32F, cv::Scalar(-2));
    before_best_ = cv::Mat(rh, rw, CV_32F, cv::Scalar(-2));
    after_best_ = cv::Mat(rh, rw, CV_32F, cv::Scalar(-2));
    const int ns = static_cast<int>(sources_.size());
    warped_.resize(ns);
    valid_.resize(ns);
    ncc_.resize(ns);
    for (int s = 0; s < ns; ++s) {
      warped_[s] = cv::Mat(rh, rw, CV_32F);
      valid_[s] = cv::Mat(rh, rw, CV_32F);
      ncc_[s] = cv::Mat(rh, rw, CV_32F);
    }
  }

  void BoxSum(const cv::Mat& in, cv::Mat* sum) const {
    cv::boxFilter(in, *sum, CV_32F, cv::Size(win_, win_), cv::Point(-1, -1), false,
                  cv::BORDER_CONSTANT);
  }

  // Source s sampled where the reference's rays meet the plane at depth z (0 and not valid
  // outside a pixel's widened range or the source's image).
  void WarpSource(int s, float z) {
    const cv::Mat& src = grays_[sources_[s]];
    for (int y = 0; y < roi_.height; ++y) {
      float* wrow = warped_[s].ptr<float>(y);
      float* vrow = valid_[s].ptr<float>(y);
      const float* lrow = lo_win_.ptr<float>(y + roi_.y) + roi_.x;
      const float* hrow = hi_win_.ptr<float>(y + roi_.y) + roi_.x;
      const cv::Vec2f* ray = rays_.ptr<cv::Vec2f>(y + roi_.y) + roi_.x;
      for (int x = 0; x < roi_.width; ++x) {
        wrow[x] = 0;
        vrow[x] = 0;
        if (z < lrow[x] || z > hrow[x] || !std::isfinite(ray[x][0])) continue;
        Eigen::Vector3f p =
            rotation_[s] * Eigen::Vector3f(ray[x][0] * z, ray[x][1] * z, z) + translation_[s];
        float u, v, value;
        if (!projectors_[s].Project(p, &u, &v) || !SampleBilinear(src, u, v, &value)) {
          continue;
        }
        wrow[x] = value;
        vrow[x] = 1;
      }
    }
  }

  // NCC of the reference against warped source s over every full window; -1 where the
  // window is not fully warped or is textureless.
  void ScoreSource(int s) {
    cv::Mat sum_w, sum_ww, sum_rw, count;
    BoxSum(warped_[s], &sum_w);
    BoxSum(warped_[s].mul(warped_[s]), &sum_ww);
    BoxSum(warped_[s].mul(ref_gray_), &sum_rw);
    BoxSum(valid_[s], &count);
    for (int y = 0; y < roi_.height; ++y) {
      float* out = ncc_[s].ptr<float>(y);
      for (int x = 0; x < roi_.width; ++x) {
        out[x] = -1;
        if (count.at<float>(y, x) < n_win_ - 0.5f) continue;
        float sr = sum_r_.at<float>(y, x), sw = sum_w.at<float>(y, x);
        float var_r = sum_rr_.at<float>(y, x) - sr * sr / n_win_;
        float var_w = sum_ww.at<float>(y, x) - sw * sw / n_win_;
        // Textureless windows (under ~1.5 DN of contrast) match anything: no vote.
        if (var_r < 2.0f * n_win_ || var_w < 2.0f * n_win_) continue;
        out[x] = (sum_rw.at<float>(y, x) - sr * sw / n_win_) / std::sqrt(var_r * var_w);
      }
    }
  }

  // Plane k's cost per pixel (the mean of the k best source NCCs) against the best so far,
  // with the costs of the planes either side of the best for the parabola.
  void KeepBest(size_t k) {
    const float z = planes_[k];
    const int ns = static_cast<int>(sources_.size());
    const int k_best = options_.best_k;
    for (int y = 0; y < roi_.height; ++y) {
      const float* lrow = lo_.ptr<float>(y + roi_.y) + roi_.x;
      const float* hrow = hi_.ptr<float>(y + roi_.y) + roi_.x;
      float* best = best_score_.ptr<float>(y);
      int* plane = best_plane_.ptr<int>(y);
      float* prev = prev_score_.ptr<float>(y);
      float* before = before_best_.ptr<float>(y);
      float* after = after_best_.ptr<float>(y);
      for (int x = 0; x < roi_.width; ++x) {
        if (!(z >= lrow[x] && z <= hrow[x])) {
          prev[x] = -2;
          continue;
        }
        float scores[16];
        for (int s = 0; s < ns; ++s) scores[s] = ncc_[s].at<float>(y, x);
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

  // The best plane's depth per searched pixel scoring at least min_ncc, moved between planes
  // by the parabola through its neighbours.
  void RefineDepths() {
    for (int y = 0; y < roi_.height; ++y) {
      for (int x = 0; x < roi_.width; ++x) {
        if (!std::isfinite(lo_.at<float>(y + roi_.y, x + roi_.x))) continue;
        ++result_.searched;
        int k = best_plane_.at<int>(y, x);
        float score = best_score_.at<float>(y, x);
        if (k < 0 || score < options_.min_ncc) continue;
        float z = planes_[k];
        float b = before_best_.at<float>(y, x), a = after_best_.at<float>(y, x);
        // A parabola through the best and its neighbours places the minimum between planes.
        if (b > -2 && a > -2 && k > 0 && k + 1 < static_cast<int>(planes_.size())) {
          float denominator = b - 2 * score + a;
          if (denominator < 0) {
            float offset = std::clamp(0.5f * (b - a) / denominator, -0.5f, 0.5f);
            float step = offset > 0 ? planes_[k + 1] - z : z - planes_[k - 1];
            z += offset * step;
          }
        }
        result_.depth.at<float>(y + roi_.y, x + roi_.x) = z;
        ++result_.matched;
      }
    }
  }

  const std::vector<View>& views_;
  const std::vector<cv::Mat>& grays_;
  const size_t ref_;
  const View& view_;
  const std::vector<int>& sources_;
  const MvsOptions& options_;
  const int w_, h_;
  const int r_, win_;  // window radius and side
  const float n_win_;  // pixels per window

  cv::Mat lo_, hi_;          // the hull's search range per pixel, NaN off the silhouette
  cv::Mat lo_win_, hi_win_;  // ... widened to each pixel's window
  cv::Rect roi_;             // the searched pixels and their windows
  std::vector<float> planes_;
  cv::Mat rays_;
  std::vector<FastProjector> projectors_;
  std::vector<Eigen::Matrix3f> rotation_;  // source_from_ref
  std::vector<Eigen::Vector3f> translation_;
  cv::Mat ref_gray_, sum_r_, sum_rr_;  // all within roi_ from here on
  cv::Mat best_score_, best_plane_, prev_score_, before_best_, after_best_;
  std::vector<cv::Mat> warped_, valid_, ncc_;  // per source, for the current plane
  SweepResult result_;
};

void CheckViews(const std::vector<View>& views, const VisualHull& hull) {
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
}

// Geometric consistency: view i's depths that at least min_consistent_views of its sources'
// depth maps confirm (the source's depth at the projection, brought back into view i, lands
// within max_reprojection_px and max_relative_depth); NaN elsewhere.
cv::Mat ConsistentDepth(const std::vector<View>& views, const std::vector<SweepResult>& sweeps,
                        const std::vector<int>& sources, int i, const MvsOptions& options,
                        int64_t* consistent) {
  const View& view = views[i];
  const cv::Mat& depth = sweeps[i].depth;
  cv::Mat filtered(depth.size(), CV_32F, cv::Scalar(kNan));
  const cv::Mat rays = NormalisedRays(view.camera);
  FastProjector self(view.camera);
  std::vector<FastProjector> others;
  std::vector<cv::Mat> other_rays;
  for (int s : sources) {
    others.emplace_back(views[s].camera);
    other_rays.push_back(NormalisedRays(views[s].camera));
  }
  const Eigen::Matrix3f world_from_cam_r = view.camera.world_from_cam().rotation().cast<float>();
  const Eigen::Vector3f world_from_cam_t = view.camera.world_from_cam().translation().cast<float>();
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
        const cv::Mat& other = sweeps[sources[s]].depth;
        if (px < 0 || py < 0 || px >= other.cols || py >= other.rows) continue;
        float d_other = other.at<float>(py, px);
        cv::Vec2f r_other = other_rays[s].at<cv::Vec2f>(py, px);
        if (!std::isfinite(d_other) || !std::isfinite(r_other[0])) continue;
        Eigen::Vector3f back = others[s].camera().world_from_cam().cast<float>() *
                               Eigen::Vector3f(r_other[0] * d_other, r_other[1] * d_other, d_other);
        float bu, bv, bz;
        if (!self.ProjectWorld(back, &bu, &bv, &bz)) continue;
        float reprojection = std::hypot(bu - x, bv - y);
        if (reprojection <= options.max_reprojection_px &&
            std::abs(bz - d) <= options.max_relative_depth * d) {
          ++agree;
        }
      }
      if (agree >= options.min_consistent_views) {
        filtered.at<float>(y, x) = d;
        ++*consistent;
      }
    }
  }
  return filtered;
}

}  // namespace

std::vector<cv::Mat> ComputeMvsDepth(const std::vector<View>& views, const VisualHull& hull,
                                     const MvsOptions& options, MvsSummary* summary_out) {
  options.Check();
  auto start = std::chrono::steady_clock::now();
  CheckViews(views, hull);
  MeshingOptions meshing;
  meshing.normals = false;
  const Mesh hull_mesh = ExtractMesh(*hull.volume, meshing);
  const int threads = ResolveThreads(options.threads);
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
    sweeps[i] = PlaneSweep(views, grays, i, sources[i], options).Run(near);
  }
  MvsSummary summary;
  for (const auto& s : sweeps) {
    summary.pixels_searched += s.searched;
    summary.pixels_matched += s.matched;
    summary.planes += s.planes;
  }
  std::vector<cv::Mat> filtered(n);
  int64_t consistent_total = 0;
#pragma omp parallel for num_threads(threads) reduction(+ : consistent_total) schedule(dynamic, 1)
  for (int i = 0; i < n; ++i) {
    filtered[i] = ConsistentDepth(views, sweeps, sources[i], i, options, &consistent_total);
  }
  summary.pixels_consistent = consistent_total;
  summary.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  const double fraction =
      summary.pixels_searched > 0
          ? static_cast<double>(summary.pixels_consistent) / summary.pixels_searched
          : 0;
  if (summary.pixels_consistent == 0) {
    summary.End(Termination::kDegenerate,
                Cat("no depth survived: ", summary.pixels_matched, " of ", summary.pixels_searched,
                    " pixels matched, none consistent across views"));
  } else if (fraction < options.min_consistent_fraction) {
    summary.End(
        Termination::kDegenerate,
        Cat("too few consistent depths: ", summary.pixels_consistent, " of ",
            summary.pixels_searched, " pixels inside the hull's silhouettes (",
            std::round(1000 * fraction) / 10, "%, at least ", 100 * options.min_consistent_fraction,
            "%): the views do not match on the subject"));
  } else {
    summary.End(Termination::kSuccess, Cat(summary.pixels_consistent, " consistent depths of ",
                                           summary.pixels_searched, " pixels searched"));
  }
  if (summary_out != nullptr) *summary_out = summary;
  return filtered;
}

}  // namespace holocap
