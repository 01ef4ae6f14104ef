// Plane-sweep multi-view stereo inside the visual hull. Each reference view (all of them, or
// at most max_reference_views spread over the directions the views see the subject from) is
// matched against its nearest source views by angle at the subject. Its pixels search depths
// from just in front of the hull to the farthest point inside it within the search depth
// along their rays, tile by tile: a tile sweeps only the planes its pixels reach. Each source
// is warped onto a fronto-parallel plane and compared by NCC with box-filtered window sums; the
// depth of the best mean of the k best source NCCs is refined by a parabola; then depths that
// no check view's (the nearest reference views') depth map confirms are dropped.
#include <omp.h>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <numbers>
#include <optional>

#include "core/check_option.h"
#include "core/error.h"
#include "core/progress.h"
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
  HOLOCAP_CHECK_OPTION_GE(min_angle_deg, 0);
  HOLOCAP_CHECK_OPTION_GT(max_angle_deg, min_angle_deg);
  HOLOCAP_CHECK_OPTION_LE(max_angle_deg, 180);
  HOLOCAP_CHECK_OPTION_GE(max_reference_views, 0);
  HOLOCAP_CHECK_OPTION_IN(tile_px, 8, 512);
  HOLOCAP_CHECK_OPTION_GE(threads, 0);
}

namespace {

constexpr float kNan = std::numeric_limits<float>::quiet_NaN();
// The warp projects every this many pixels of a row exactly, the others by interpolation.
constexpr int kWarpStridePx = 4;

// How far view s is from view r as a partner for stereo: the angle the two make at the subject
// plus ln of their distances' ratio; infinity outside [min_angle, max_angle].
double PartnerCost(const CameraModel& r, const CameraModel& s, const Eigen::Vector3d& subject,
                   double min_angle, double max_angle) {
  const Eigen::Vector3d to_r = r.center_in_world() - subject;
  const Eigen::Vector3d to_s = s.center_in_world() - subject;
  const double angle = std::acos(std::clamp(to_r.normalized().dot(to_s.normalized()), -1.0, 1.0));
  if (angle < min_angle || angle > max_angle) return std::numeric_limits<double>::infinity();
  return angle + std::abs(std::log(to_s.norm() / to_r.norm()));
}

// The `count` candidates of least PartnerCost to view r (finite cost only), nearest first. A
// sparse rig with fewer than `count` of them within max_angle_deg (a ring of eight has two)
// fills up with the nearest by angle short of 90 degrees, as its views 90 degrees apart still
// see the sides the reference sees obliquely (studio8: Chamfer 5.91 mm with them, 7.68 without).
std::vector<int> NearestPartners(const std::vector<CameraModel>& cameras, int r,
                                 const std::vector<int>& candidates, const Eigen::Vector3d& subject,
                                 const MvsOptions& options, int count) {
  const double min_angle = options.min_angle_deg * std::numbers::pi / 180;
  const double max_angle = options.max_angle_deg * std::numbers::pi / 180;
  std::vector<std::pair<double, int>> order, fillers;
  for (int s : candidates) {
    if (s == r) continue;
    const double cost = PartnerCost(cameras[r], cameras[s], subject, min_angle, max_angle);
    if (std::isfinite(cost)) {
      order.emplace_back(cost, s);
      continue;
    }
    const double filler =
        PartnerCost(cameras[r], cameras[s], subject, max_angle, std::numbers::pi / 2);
    if (std::isfinite(filler)) fillers.emplace_back(filler, s);
  }
  std::sort(order.begin(), order.end());
  std::sort(fillers.begin(), fillers.end());
  order.insert(order.end(), fillers.begin(), fillers.end());
  std::vector<int> out;
  out.reserve(count);
  for (size_t i = 0; i < order.size() && static_cast<int>(i) < count; ++i)
    out.push_back(order[i].second);
  return out;
}

// Farthest-point sampling of the directions from the subject to the candidate cameras: the
// first candidate, then each time the one whose smallest angle to those chosen is largest.
// Sorted.
std::vector<int> SpreadViews(const std::vector<CameraModel>& cameras,
                             const std::vector<int>& candidates, const Eigen::Vector3d& subject,
                             int count) {
  const int n = static_cast<int>(candidates.size());
  std::vector<Eigen::Vector3d> directions;
  directions.reserve(candidates.size());
  for (int i : candidates)
    directions.push_back((cameras[i].center_in_world() - subject).normalized());
  std::vector<int> chosen = {0};  // indices into candidates
  std::vector<double> nearest_cos(n, -2);
  std::vector<bool> taken(n, false);
  taken[0] = true;
  while (static_cast<int>(chosen.size()) < std::min(count, n)) {
    const Eigen::Vector3d& last = directions[chosen.back()];
    int farthest = -1;
    for (int i = 0; i < n; ++i) {
      nearest_cos[i] = std::max(nearest_cos[i], directions[i].dot(last));
      if (taken[i]) continue;
      if (farthest < 0 || nearest_cos[i] < nearest_cos[farthest]) farthest = i;
    }
    chosen.push_back(farthest);
    taken[farthest] = true;
  }
  std::vector<int> out;
  out.reserve(chosen.size());
  for (int c : chosen) out.push_back(candidates[c]);
  std::sort(out.begin(), out.end());
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
  int64_t searched = 0, matched = 0, planes = 0, hypotheses = 0;
};

// One reference view's plane sweep: the per-pixel search range (from `near`, the hull's depth,
// to `far`, the farthest point inside the hull within the search depth), the ladder of planes,
// then tile by tile the warp and NCC of every source on each plane the tile's pixels reach,
// the best of the k best kept per pixel, and the parabola that places the depth between planes.
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

  SweepResult Run(const cv::Mat& near, const cv::Mat& far) {
    result_.depth = cv::Mat(h_, w_, CV_32F, cv::Scalar(kNan));
    if (static_cast<int>(sources_.size()) < options_.best_k) return result_;
    double zmin = 1e9, zmax = -1e9;
    if (!SearchRange(near, far, &zmin, &zmax)) return result_;
    ChoosePlanes(zmin, zmax);
    PrepareWarps();
    const int tile = options_.tile_px;
    for (int y = roi_.y; y < roi_.y + roi_.height; y += tile) {
      for (int x = roi_.x; x < roi_.x + roi_.width; x += tile) {
        SweepTile(cv::Rect(x, y, tile, tile) & roi_);
      }
    }
    RefineDepths();
    return result_;
  }

 private:
  // Per-pixel search range [lo, hi] on the silhouette, and the region of interest around it;
  // false when there is nothing to search.
  bool SearchRange(const cv::Mat& near, const cv::Mat& far, double* zmin, double* zmax) {
    lo_ = cv::Mat(h_, w_, CV_32F, cv::Scalar(kNan));
    hi_ = cv::Mat(h_, w_, CV_32F, cv::Scalar(kNan));
    cv::Mat active_pixels = cv::Mat::zeros(h_, w_, CV_8U);
    for (int y = 0; y < h_; ++y) {
      for (int x = 0; x < w_; ++x) {
        float z = near.at<float>(y, x);
        if (!std::isfinite(z) || view_.mask.at<uint8_t>(y, x) == 0) continue;
        // Never nearer than half the hull's depth: a scene's own length, whatever its scale.
        lo_.at<float>(y, x) = std::max(0.5f * z, z - static_cast<float>(options_.hull_margin_m));
        hi_.at<float>(y, x) =
            std::min(z + static_cast<float>(options_.search_depth_m), far.at<float>(y, x));
        active_pixels.at<uint8_t>(y, x) = 255;
      }
    }
    roi_ = cv::boundingRect(active_pixels);
    if (roi_.area() == 0) return false;
    // Window pixels of active pixels need warps too: widen each pixel's range to its window's.
    cv::Mat lo_fill = lo_.clone(), hi_fill = hi_.clone();
    lo_fill.setTo(1e9f, lo_ != lo_);
    hi_fill.setTo(-1e9f, hi_ != hi_);
    cv::erode(lo_fill, lo_win_, cv::Mat::ones(win_, win_, CV_8U));
    cv::dilate(hi_fill, hi_win_, cv::Mat::ones(win_, win_, CV_8U));
    cv::minMaxLoc(lo_fill(roi_), zmin, nullptr);
    cv::minMaxLoc(hi_fill(roi_), nullptr, zmax);
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
  // the per-pixel state of the sweep.
  void PrepareWarps() {
    rays_ = NormalisedRays(view_.camera);
    const Pose world_from_ref = view_.camera.world_from_cam();
    for (int s : sources_) {
      projectors_.emplace_back(views_[s].camera);
      Pose source_from_ref = views_[s].camera.cam_from_world() * world_from_ref;
      rotation_.push_back(source_from_ref.rotation().cast<float>());
      translation_.push_back(source_from_ref.translation().cast<float>());
    }
    const cv::Mat& ref_gray = grays_[ref_];
    BoxSum(ref_gray, &sum_r_);
    BoxSum(ref_gray.mul(ref_gray), &sum_rr_);
    best_score_ = cv::Mat(h_, w_, CV_32F, cv::Scalar(-2));
    best_plane_ = cv::Mat(h_, w_, CV_32S, cv::Scalar(-1));
    prev_score_ = cv::Mat(h_, w_, CV_32F, cv::Scalar(-2));
    before_best_ = cv::Mat(h_, w_, CV_32F, cv::Scalar(-2));
    after_best_ = cv::Mat(h_, w_, CV_32F, cv::Scalar(-2));
    const size_t ns = sources_.size();
    warped_.resize(ns);
    valid_.resize(ns);
    ncc_.resize(ns);
  }

  void BoxSum(const cv::Mat& in, cv::Mat* sum) const {
    cv::boxFilter(in, *sum, CV_32F, cv::Size(win_, win_), cv::Point(-1, -1), false,
                  cv::BORDER_CONSTANT);
  }

  // One tile: the planes of the ladder its pixels' ranges reach, each swept over the tile and
  // the window border around it.
  void SweepTile(const cv::Rect& tile) {
    double tile_lo = 1e9, tile_hi = -1e9;
    for (int y = tile.y; y < tile.y + tile.height; ++y) {
      const float* lrow = lo_.ptr<float>(y);
      const float* hrow = hi_.ptr<float>(y);
      for (int x = tile.x; x < tile.x + tile.width; ++x) {
        if (!std::isfinite(lrow[x])) continue;
        tile_lo = std::min<double>(tile_lo, lrow[x]);
        tile_hi = std::max<double>(tile_hi, hrow[x]);
      }
    }
    if (tile_hi < tile_lo) return;  // no pixel of the tile is searched
    const size_t first =
        std::lower_bound(planes_.begin(), planes_.end(), static_cast<float>(tile_lo)) -
        planes_.begin();
    const size_t last =
        std::upper_bound(planes_.begin(), planes_.end(), static_cast<float>(tile_hi)) -
        planes_.begin();
    const cv::Rect border =
        cv::Rect(tile.x - r_, tile.y - r_, tile.width + 2 * r_, tile.height + 2 * r_) &
        cv::Rect(0, 0, w_, h_);
    const int ns = static_cast<int>(sources_.size());
    result_.hypotheses += static_cast<int64_t>(border.area()) * static_cast<int64_t>(last - first) *
                          static_cast<int64_t>(ns);
    for (size_t k = first; k < last; ++k) {
      for (int s = 0; s < ns; ++s) {
        WarpSource(s, planes_[k], border);
        ScoreSource(s, tile, border);
      }
      KeepBest(k, tile);
    }
  }

  // Source s sampled where the reference's rays through `border` meet the plane at depth z (0
  // and not valid outside a pixel's widened range or the source's image). Each row projects
  // exactly every kWarpStridePx-th pixel (and its last) and interpolates linearly between: over
  // a few pixels a plane's warp through a lens bends by far less than a hundredth of a pixel.
  void WarpSource(int s, float z, const cv::Rect& border) {
    const cv::Mat& src = grays_[sources_[s]];
    warped_[s].create(border.size(), CV_32F);
    valid_[s].create(border.size(), CV_32F);
    const int width = border.width;
    const int nodes = (width - 1 + kWarpStridePx - 1) / kWarpStridePx + 1;
    node_u_.resize(nodes);
    node_v_.resize(nodes);
    node_ok_.resize(nodes);
    for (int y = 0; y < border.height; ++y) {
      float* wrow = warped_[s].ptr<float>(y);
      float* vrow = valid_[s].ptr<float>(y);
      const float* lrow = lo_win_.ptr<float>(y + border.y) + border.x;
      const float* hrow = hi_win_.ptr<float>(y + border.y) + border.x;
      const cv::Vec2f* ray = rays_.ptr<cv::Vec2f>(y + border.y) + border.x;
      for (int n = 0; n < nodes; ++n) {
        node_ok_[n] =
            ProjectRay(s, ray[std::min(n * kWarpStridePx, width - 1)], z, &node_u_[n], &node_v_[n]);
      }
      for (int x = 0; x < width; ++x) {
        wrow[x] = 0;
        vrow[x] = 0;
        if (z < lrow[x] || z > hrow[x]) continue;
        const int n = x / kWarpStridePx;
        const int x0 = n * kWarpStridePx;
        float u, v, value;
        if (x == x0 && node_ok_[n]) {
          u = node_u_[n];
          v = node_v_[n];
        } else if (x != x0 && node_ok_[n] && node_ok_[n + 1]) {
          const float f = static_cast<float>(x - x0) /
                          static_cast<float>(std::min(x0 + kWarpStridePx, width - 1) - x0);
          u = node_u_[n] + f * (node_u_[n + 1] - node_u_[n]);
          v = node_v_[n] + f * (node_v_[n + 1] - node_v_[n]);
        } else if (!ProjectRay(s, ray[x], z, &u, &v)) {
          continue;
        }
        if (!SampleBilinear(src, u, v, &value)) continue;
        wrow[x] = value;
        vrow[x] = 1;
      }
    }
  }

  // Where the reference's ray (normalised, z = 1) at depth z projects in source s.
  bool ProjectRay(int s, const cv::Vec2f& ray, float z, float* u, float* v) const {
    if (!std::isfinite(ray[0])) return false;
    const Eigen::Vector3f p =
        rotation_[s] * Eigen::Vector3f(ray[0] * z, ray[1] * z, z) + translation_[s];
    return projectors_[s].Project(p, u, v);
  }

  // NCC of the reference against warped source s over every full window of the tile's
  // pixels; -1 where the window is not fully warped or is textureless.
  void ScoreSource(int s, const cv::Rect& tile, const cv::Rect& border) {
    const cv::Mat ref = grays_[ref_](border);
    BoxSum(warped_[s], &sum_w_);
    BoxSum(warped_[s].mul(warped_[s]), &sum_ww_);
    BoxSum(warped_[s].mul(ref), &sum_rw_);
    BoxSum(valid_[s], &count_);
    ncc_[s].create(tile.size(), CV_32F);
    const int dx = tile.x - border.x, dy = tile.y - border.y;
    for (int y = 0; y < tile.height; ++y) {
      float* out = ncc_[s].ptr<float>(y);
      const float* count = count_.ptr<float>(y + dy) + dx;
      const float* sum_w = sum_w_.ptr<float>(y + dy) + dx;
      const float* sum_ww = sum_ww_.ptr<float>(y + dy) + dx;
      const float* sum_rw = sum_rw_.ptr<float>(y + dy) + dx;
      const float* sum_r = sum_r_.ptr<float>(y + tile.y) + tile.x;
      const float* sum_rr = sum_rr_.ptr<float>(y + tile.y) + tile.x;
      for (int x = 0; x < tile.width; ++x) {
        out[x] = -1;
        if (count[x] < n_win_ - 0.5f) continue;
        const float sr = sum_r[x], sw = sum_w[x];
        const float var_r = sum_rr[x] - sr * sr / n_win_;
        const float var_w = sum_ww[x] - sw * sw / n_win_;
        // Textureless windows (under ~1.5 DN of contrast) match anything: no vote.
        if (var_r < 2.0f * n_win_ || var_w < 2.0f * n_win_) continue;
        out[x] = (sum_rw[x] - sr * sw / n_win_) / std::sqrt(var_r * var_w);
      }
    }
  }

  // Plane k's cost per pixel of the tile (the mean of the k best source NCCs) against the best
  // so far, with the costs of the planes either side of the best for the parabola.
  void KeepBest(size_t k, const cv::Rect& tile) {
    const float z = planes_[k];
    const int ns = static_cast<int>(sources_.size());
    const int k_best = options_.best_k;
    for (int y = 0; y < tile.height; ++y) {
      const int iy = y + tile.y;
      const float* lrow = lo_.ptr<float>(iy) + tile.x;
      const float* hrow = hi_.ptr<float>(iy) + tile.x;
      float* best = best_score_.ptr<float>(iy) + tile.x;
      int* plane = best_plane_.ptr<int>(iy) + tile.x;
      float* prev = prev_score_.ptr<float>(iy) + tile.x;
      float* before = before_best_.ptr<float>(iy) + tile.x;
      float* after = after_best_.ptr<float>(iy) + tile.x;
      for (int x = 0; x < tile.width; ++x) {
        if (!(z >= lrow[x] && z <= hrow[x])) {
          prev[x] = -2;
          continue;
        }
        float scores[16];
        for (int s = 0; s < ns; ++s) scores[s] = ncc_[s].ptr<float>(y)[x];
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
    for (int y = roi_.y; y < roi_.y + roi_.height; ++y) {
      for (int x = roi_.x; x < roi_.x + roi_.width; ++x) {
        if (!std::isfinite(lo_.at<float>(y, x))) continue;
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
        result_.depth.at<float>(y, x) = z;
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

  cv::Mat lo_, hi_;          // the search range per pixel, NaN off the silhouette
  cv::Mat lo_win_, hi_win_;  // ... widened to each pixel's window
  cv::Rect roi_;             // the searched pixels
  std::vector<float> planes_;
  cv::Mat rays_;
  std::vector<FastProjector> projectors_;
  std::vector<Eigen::Matrix3f> rotation_;  // source_from_ref
  std::vector<Eigen::Vector3f> translation_;
  cv::Mat sum_r_, sum_rr_;  // the reference's window sums, whole image
  // Per pixel, whole image: the best cost and plane, the last plane's cost, the costs either
  // side of the best.
  cv::Mat best_score_, best_plane_, prev_score_, before_best_, after_best_;
  std::vector<cv::Mat> warped_, valid_, ncc_;  // per source, for the current tile and plane
  cv::Mat sum_w_, sum_ww_, sum_rw_, count_;    // the current source's window sums
  std::vector<float> node_u_, node_v_;         // a row's exactly projected pixels
  std::vector<uint8_t> node_ok_;
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

// The farthest z-depth inside the hull within `search_m` behind `near`, per pixel: rays every
// kFarStridePx pixels marched from the hull's depth in steps of its voxel, each pixel taking the
// farthest of the 3x3 marched rays around it plus a voxel. Infinity where no ray was marched.
constexpr int kFarStridePx = 4;

cv::Mat HullFar(const VisualHull& hull, const CameraModel& camera, const cv::Mat& near,
                const cv::Mat& rays, double search_m) {
  const int w = near.cols, h = near.rows;
  const int gw = (w + kFarStridePx - 1) / kFarStridePx, gh = (h + kFarStridePx - 1) / kFarStridePx;
  const double voxel = hull.volume->voxel_m();
  const Pose world_from_cam = camera.world_from_cam();
  cv::Mat grid(gh, gw, CV_32F, cv::Scalar(-1e9f));
  for (int j = 0; j < gh; ++j) {
    for (int i = 0; i < gw; ++i) {
      const int x = std::min(i * kFarStridePx + kFarStridePx / 2, w - 1);
      const int y = std::min(j * kFarStridePx + kFarStridePx / 2, h - 1);
      const double z0 = near.at<float>(y, x);
      const cv::Vec2f& ray = rays.at<cv::Vec2f>(y, x);
      if (!std::isfinite(z0) || !std::isfinite(ray[0])) continue;
      const Eigen::Vector3d origin = world_from_cam.translation();
      const Eigen::Vector3d direction =
          world_from_cam.linear() * Eigen::Vector3d(ray[0], ray[1], 1);
      double last_inside = z0;
      for (double z = z0; z <= z0 + search_m; z += voxel) {
        if (hull.Contains(origin + z * direction)) last_inside = z;
      }
      grid.at<float>(j, i) = static_cast<float>(last_inside + voxel);
    }
  }
  cv::dilate(grid, grid, cv::Mat::ones(3, 3, CV_8U));
  cv::Mat far;
  cv::resize(grid, far, cv::Size(gw * kFarStridePx, gh * kFarStridePx), 0, 0, cv::INTER_NEAREST);
  far = far(cv::Rect(0, 0, w, h)).clone();
  far.setTo(std::numeric_limits<float>::infinity(), far < -1e8f);
  return far;
}

// Geometric consistency: view i's depths that at least min_consistent_views of its check
// views' depth maps confirm (the check view's depth at the projection, brought back into view
// i, lands within max_reprojection_px and max_relative_depth); NaN elsewhere.
cv::Mat ConsistentDepth(const std::vector<View>& views, const std::vector<SweepResult>& sweeps,
                        const std::vector<int>& checks, int i, const MvsOptions& options,
                        int64_t* consistent) {
  const View& view = views[i];
  const cv::Mat& depth = sweeps[i].depth;
  cv::Mat filtered(depth.size(), CV_32F, cv::Scalar(kNan));
  const cv::Mat rays = NormalisedRays(view.camera);
  FastProjector self(view.camera);
  std::vector<FastProjector> others;
  std::vector<cv::Mat> other_rays;
  for (int s : checks) {
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
        const cv::Mat& other = sweeps[checks[s]].depth;
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

double SecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

}  // namespace

MvsViewChoice ChooseMvsViews(const std::vector<CameraModel>& cameras,
                             const Eigen::Vector3d& subject_in_world, const MvsOptions& options) {
  options.Check();
  const int n = static_cast<int>(cameras.size());
  MvsViewChoice choice;
  choice.sources.resize(n);
  choice.checks.resize(n);
  std::vector<int> seeing;
  for (int i = 0; i < n; ++i) {
    Eigen::Vector2d pixel;
    if ((cameras[i].cam_from_world() * subject_in_world).z() > 0 &&
        cameras[i].ProjectWorld(subject_in_world, &pixel) && cameras[i].InImage(pixel, 0)) {
      seeing.push_back(i);
    }
  }
  const int most = options.max_reference_views;
  if (seeing.empty()) {
    choice.why = "no view sees the subject's centre";
  } else if (most == 0 || static_cast<int>(seeing.size()) <= most) {
    choice.references = seeing;
    choice.why = Cat("every view that sees the subject's centre (", seeing.size(), " of ", n,
                     most == 0 ? "; no limit" : Cat("; at most ", most), ")");
  } else {
    choice.references = SpreadViews(cameras, seeing, subject_in_world, most);
    choice.why = Cat(most, " of the ", seeing.size(), " views that see the subject's centre (", n,
                     " in all), spread over the directions they see it from by farthest-point ",
                     "sampling (at most ", most, " reference views, each a sweep); every view ",
                     "is a source");
  }
  for (int r : choice.references) {
    choice.sources[r] =
        NearestPartners(cameras, r, seeing, subject_in_world, options, options.neighbors);
    choice.checks[r] = NearestPartners(cameras, r, choice.references, subject_in_world, options,
                                       options.neighbors);
  }
  return choice;
}

double MeasureSweepRate(const MvsOptions& options) {
  // A reference and its sources 5 cm apart in a row, random texture: two tiles square.
  const int side = 2 * options.tile_px;
  const int sources = options.neighbors;
  cv::RNG rng(1);
  std::vector<View> views;
  views.reserve(sources + 1);
  for (int i = 0; i <= sources; ++i) {
    Pose cam_from_world = Pose::Identity();
    cam_from_world.translation() = Eigen::Vector3d(-0.05 * i, 0, 0);
    View view{"", CameraModel::Pinhole(8.0 * side, side, side, cam_from_world),
              cv::Mat(side, side, CV_8UC3), cv::Mat(side, side, CV_8U, cv::Scalar(255))};
    rng.fill(view.image, cv::RNG::UNIFORM, 0, 256);
    views.push_back(std::move(view));
  }
  std::vector<cv::Mat> grays;
  grays.reserve(views.size());
  for (const View& view : views) grays.push_back(Gray(view.image));
  std::vector<int> source_list;
  source_list.reserve(sources);
  for (int i = 1; i <= sources; ++i) source_list.push_back(i);
  const cv::Mat near(side, side, CV_32F, cv::Scalar(1.0f));
  const cv::Mat far(side, side, CV_32F,
                    cv::Scalar(static_cast<float>(1.0 + options.search_depth_m)));
  int64_t hypotheses = 0;
  const auto start = std::chrono::steady_clock::now();
  // At least a tenth of a second of sweeping: a rate, not a timer's resolution.
  while (hypotheses == 0 || SecondsSince(start) < 0.1) {
    hypotheses += PlaneSweep(views, grays, 0, source_list, options).Run(near, far).hypotheses;
  }
  return SecondsSince(start) / static_cast<double>(std::max<int64_t>(hypotheses, 1));
}

MvsEstimate EstimateMvs(const std::vector<View>& views, const MvsViewChoice& choice,
                        const Eigen::Vector3d& subject_in_world, const MvsOptions& options,
                        int threads) {
  MvsEstimate estimate;
  const int tile = options.tile_px, r = options.window_radius;
  for (int ref : choice.references) {
    const View& view = views[ref];
    const std::vector<int>& sources = choice.sources[ref];
    if (sources.empty() || view.mask.empty()) continue;
    // The tiles the silhouette touches, each with its window border.
    int64_t pixels = 0;
    const cv::Rect image(0, 0, view.mask.cols, view.mask.rows);
    for (int y = 0; y < image.height; y += tile) {
      for (int x = 0; x < image.width; x += tile) {
        const cv::Rect cell = cv::Rect(x, y, tile, tile) & image;
        if (cv::countNonZero(view.mask(cell)) == 0) continue;
        pixels += (cv::Rect(x - r, y - r, tile + 2 * r, tile + 2 * r) & image).area();
      }
    }
    const double depth = (view.camera.cam_from_world() * subject_in_world).z();
    double baseline = std::numeric_limits<double>::infinity();
    for (int s : sources) {
      baseline = std::min(
          baseline, (views[s].camera.center_in_world() - view.camera.center_in_world()).norm());
    }
    const double step = options.depth_step_px * depth * depth /
                        (FastProjector(view.camera).focal() * std::max(baseline, 1e-9));
    const double planes = std::ceil((options.hull_margin_m + options.search_depth_m) / step);
    estimate.pixel_hypotheses +=
        static_cast<int64_t>(static_cast<double>(pixels) * planes * sources.size());
  }
  estimate.seconds_per_hypothesis = MeasureSweepRate(options);
  estimate.threads =
      std::max(1, std::min(ResolveThreads(threads), static_cast<int>(choice.references.size())));
  estimate.seconds = static_cast<double>(estimate.pixel_hypotheses) *
                     estimate.seconds_per_hypothesis / estimate.threads;
  return estimate;
}

std::vector<cv::Mat> ComputeMvsDepth(const std::vector<View>& views, const VisualHull& hull,
                                     const MvsOptions& options, MvsSummary* summary_out,
                                     const MvsViewChoice* choice_in,
                                     const std::string& progress_label) {
  options.Check();
  auto start = std::chrono::steady_clock::now();
  CheckViews(views, hull);
  MeshingOptions meshing;
  meshing.normals = false;
  const Mesh hull_mesh = ExtractMesh(*hull.volume, meshing);
  const int threads = ResolveThreads(options.threads);
  const int n = static_cast<int>(views.size());
  MvsViewChoice chosen;
  if (choice_in == nullptr) {
    std::vector<CameraModel> cameras;
    cameras.reserve(views.size());
    for (const View& view : views) cameras.push_back(view.camera);
    chosen = ChooseMvsViews(cameras, hull.Extent().center(), options);
  }
  const MvsViewChoice& choice = choice_in != nullptr ? *choice_in : chosen;
  if (static_cast<int>(choice.sources.size()) != n || static_cast<int>(choice.checks.size()) != n)
    Fail("multi-view stereo: the view choice is for ", choice.sources.size(), " views, not ", n);
  std::vector<cv::Mat> grays(n);
  for (int i = 0; i < n; ++i) grays[i] = Gray(views[i].image);
  const std::vector<int>& references = choice.references;
  const int m = static_cast<int>(references.size());
  std::vector<SweepResult> sweeps(n);
  std::optional<Progress> progress;
  if (!progress_label.empty()) progress.emplace(progress_label, m);
  double range_seconds = 0, sweep_seconds = 0;
#pragma omp parallel for num_threads(threads) schedule(dynamic, 1) \
    reduction(+ : range_seconds, sweep_seconds)
  for (int j = 0; j < m; ++j) {
    const int i = references[j];
    const auto range_start = std::chrono::steady_clock::now();
    const cv::Mat near = RenderDepth(hull_mesh, views[i].camera);
    const cv::Mat far = HullFar(hull, views[i].camera, near, NormalisedRays(views[i].camera),
                                options.search_depth_m);
    const auto sweep_start = std::chrono::steady_clock::now();
    range_seconds += std::chrono::duration<double>(sweep_start - range_start).count();
    sweeps[i] = PlaneSweep(views, grays, i, choice.sources[i], options).Run(near, far);
    sweep_seconds += SecondsSince(sweep_start);
    if (progress) progress->Increment();
  }
  if (progress) progress->Finish();
  MvsSummary summary;
  summary.reference_views = m;
  summary.range_seconds = range_seconds;
  summary.sweep_seconds = sweep_seconds;
  for (const auto& s : sweeps) {
    summary.pixels_searched += s.searched;
    summary.pixels_matched += s.matched;
    summary.planes += s.planes;
    summary.pixel_hypotheses += s.hypotheses;
  }
  const auto consistency_start = std::chrono::steady_clock::now();
  std::vector<cv::Mat> filtered(n);
  int64_t consistent_total = 0;
#pragma omp parallel for num_threads(threads) reduction(+ : consistent_total) schedule(dynamic, 1)
  for (int j = 0; j < m; ++j) {
    const int i = references[j];
    filtered[i] = ConsistentDepth(views, sweeps, choice.checks[i], i, options, &consistent_total);
  }
  summary.consistency_seconds = SecondsSince(consistency_start);
  summary.pixels_consistent = consistent_total;
  summary.seconds = SecondsSince(start);
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
