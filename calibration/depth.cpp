// depth_from_color from board planes seen by a depth sensor and its colour camera, and the
// time offset between the two from the board's motion.
#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <random>

#include "calibration/calibration.h"
#include "core/check_option.h"
#include "core/error.h"
#include "core/take.h"

namespace holocap {
namespace {

struct Plane {
  Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();  // unit, pointing away from the sensor
  double offset = 0;                                  // normal . x = offset
};

// The board's outline shrunk by `inset` of its size, in board coordinates.
std::vector<Eigen::Vector3d> InnerOutline(const Board& board, double inset) {
  const double du = (board.u_max() - board.u_min()) * inset;
  const double dv = (board.v_max() - board.v_min()) * inset;
  return {{board.u_min() + du, board.v_min() + dv, 0},
          {board.u_max() - du, board.v_min() + dv, 0},
          {board.u_max() - du, board.v_max() - dv, 0},
          {board.u_min() + du, board.v_max() - dv, 0}};
}

bool InsidePolygon(const std::vector<Eigen::Vector2d>& polygon, const Eigen::Vector2d& q) {
  bool inside = false;
  for (size_t a = 0, b = polygon.size() - 1; a < polygon.size(); b = a++) {
    if ((polygon[a].y() > q.y()) != (polygon[b].y() > q.y()) &&
        q.x() < (polygon[b].x() - polygon[a].x()) * (q.y() - polygon[a].y()) /
                        (polygon[b].y() - polygon[a].y()) +
                    polygon[a].x()) {
      inside = !inside;
    }
  }
  return inside;
}

// The least-squares plane of the points within `band` of `plane` (none: false).
bool RefitPlane(const std::vector<Eigen::Vector3d>& points, double band, Plane* plane,
                size_t* inliers) {
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  size_t count = 0;
  for (const auto& p : points) {
    if (std::abs(plane->normal.dot(p) - plane->offset) < band) {
      mean += p;
      ++count;
    }
  }
  if (count < 3) return false;
  mean /= static_cast<double>(count);
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  for (const auto& p : points) {
    if (std::abs(plane->normal.dot(p) - plane->offset) < band)
      scatter += (p - mean) * (p - mean).transpose();
  }
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eigen(scatter);
  Eigen::Vector3d n = eigen.eigenvectors().col(0);
  if (n.dot(mean) < 0) n = -n;
  plane->normal = n;
  plane->offset = n.dot(mean);
  *inliers = count;
  return true;
}

// RANSAC plane, then least squares over a band that follows the measured noise: a depth
// sensor's noise grows as z squared and is skewed (depth is the inverse of a disparity), so a
// band narrower than the noise picks its mode, nearer the sensor than the surface, and a board
// 4 m away comes out centimetres too near. The band widens to three robust sigmas of the
// residuals (never below `band`, never past `max_band`) until it settles.
bool FitPlane(const std::vector<Eigen::Vector3d>& points, double band, double max_band,
              Plane* plane, double* sigma, size_t* inliers, std::mt19937_64* random) {
  if (points.size() < 50) return false;
  std::uniform_int_distribution<size_t> pick(0, points.size() - 1);
  size_t best = 0;
  Plane best_plane;
  for (int iteration = 0; iteration < 200; ++iteration) {
    const Eigen::Vector3d a = points[pick(*random)], b = points[pick(*random)],
                          c = points[pick(*random)];
    Eigen::Vector3d n = (b - a).cross(c - a);
    if (n.norm() < 1e-9) continue;
    n.normalize();
    const double d = n.dot(a);
    size_t count = 0;
    for (const auto& p : points) count += std::abs(n.dot(p) - d) < band;
    if (count > best) {
      best = count;
      best_plane = {n, d};
    }
  }
  if (best < points.size() / 2) return false;
  *plane = best_plane;
  double width = band;
  std::vector<double> residuals;
  for (int round = 0; round < 10; ++round) {
    if (!RefitPlane(points, width, plane, inliers)) return false;
    residuals.clear();
    for (const auto& p : points) {
      const double r = std::abs(plane->normal.dot(p) - plane->offset);
      if (r < max_band) residuals.push_back(r);
    }
    std::nth_element(residuals.begin(), residuals.begin() + residuals.size() / 2, residuals.end());
    *sigma = 1.4826 * residuals[residuals.size() / 2];
    const double next = std::clamp(3 * *sigma, band, max_band);
    if (std::abs(next - width) < 0.02 * width) break;
    width = next;
  }
  return *inliers >= points.size() / 2;
}

Plane BoardPlane(const Pose& cam_from_board) {
  Plane plane;
  plane.normal = cam_from_board.linear().col(2);
  plane.offset = plane.normal.dot(cam_from_board.translation());
  if (plane.offset < 0) {
    plane.normal = -plane.normal;
    plane.offset = -plane.offset;
  }
  return plane;
}

}  // namespace

void DepthAlignmentOptions::Check() const {
  HOLOCAP_CHECK_OPTION_GT(plane_inlier_m, 0);
  HOLOCAP_CHECK_OPTION_GE(max_plane_band_m, plane_inlier_m);
  HOLOCAP_CHECK_OPTION_GE(min_planes, 3, "three normals fix a rotation and translation");
  HOLOCAP_CHECK_OPTION_GT(min_normal_spread_deg, 0);
  HOLOCAP_CHECK_OPTION_LT(min_normal_spread_deg, 90);
  HOLOCAP_CHECK_OPTION_GE(max_time_offset_s, 0);
}

nlohmann::json DepthAlignmentSummary::ToJson() const {
  return {{"termination", ToString(termination)},
          {"message", message},
          {"depth_sensor", depth_sensor},
          {"color_sensor", color_sensor},
          {"rt_depth_from_color", RtFromPose(depth_from_color)},
          {"planes", planes},
          {"rejected_sets", rejected_sets},
          {"plane_rms_m", plane_rms_m},
          {"time_offset_s", time_offset_s},
          {"time_offset_valid", time_offset_valid}};
}

namespace {

// A board plane seen at one frame set: as the colour camera's pose puts it, as the depth
// sensor measured it (fitted to the depth points inside the board's outline), and when.
struct PlaneSample {
  int64_t set = 0;
  Plane color, depth;
  double sigma = 0;   // the depth points' robust spread about the plane (metres)
  double weight = 1;  // inliers / sigma^2
  double color_time_s = 0, depth_time_s = 0;
  std::vector<Eigen::Vector3d> points;
};

// The frame sets where both sensors saw the board: the outline is carried into the depth image
// through the current depth_from_color guess, and a plane is fitted to the depth inside it.
std::vector<PlaneSample> PlaneSamples(const Take& take, const std::string& depth_sensor,
                                      const CameraModel& depth_model,
                                      const std::string& color_sensor,
                                      const std::map<int64_t, Pose>& color_from_board,
                                      const Board& board, const Pose& depth_from_color,
                                      const DepthAlignmentOptions& options,
                                      std::mt19937_64* random) {
  std::vector<PlaneSample> samples;
  for (size_t i = 0; i < take.size(); ++i) {
    const FrameSetEntry& entry = take.entry(i);
    auto pose = color_from_board.find(entry.index);
    const auto* depth_item = entry.Find(depth_sensor);
    const auto* color_item = entry.Find(color_sensor);
    if (pose == color_from_board.end() || depth_item == nullptr || color_item == nullptr) continue;
    std::vector<Eigen::Vector2d> outline;
    bool visible = true;
    for (const auto& corner : InnerOutline(board, 0.12)) {
      Eigen::Vector2d q;
      if (!depth_model.Project(depth_from_color * (pose->second * corner), &q)) visible = false;
      outline.push_back(q);
    }
    if (!visible) continue;
    const cv::Mat depth = take.ReadFrame(i, depth_sensor);
    if (depth.type() != CV_32FC1)
      Fail("depth sensor '", depth_sensor, "' frames are not metres (CV_32F)");
    double x0 = 1e9, x1 = -1e9, y0 = 1e9, y1 = -1e9;
    for (const auto& q : outline) {
      x0 = std::min(x0, q.x());
      x1 = std::max(x1, q.x());
      y0 = std::min(y0, q.y());
      y1 = std::max(y1, q.y());
    }
    PlaneSample sample;
    std::vector<Eigen::Vector2d> pixels;
    for (int y = std::max(0, static_cast<int>(y0));
         y <= std::min(depth.rows - 1, static_cast<int>(y1)); ++y) {
      for (int x = std::max(0, static_cast<int>(x0));
           x <= std::min(depth.cols - 1, static_cast<int>(x1)); ++x) {
        const float z = depth.at<float>(y, x);
        if (!std::isfinite(z) || z <= 0) continue;
        if (!InsidePolygon(outline, Eigen::Vector2d(x, y))) continue;
        pixels.emplace_back(x, y);
      }
    }
    if (pixels.size() < 50) continue;
    Eigen::Matrix2Xd q(2, pixels.size());
    for (size_t k = 0; k < pixels.size(); ++k) q.col(k) = pixels[k];
    const Eigen::Matrix3Xd rays = depth_model.UnprojectMany(q);
    for (size_t k = 0; k < pixels.size(); ++k) {
      if (!rays.col(k).allFinite() || rays(2, k) <= 0) continue;
      const double z =
          depth.at<float>(static_cast<int>(pixels[k].y()), static_cast<int>(pixels[k].x()));
      sample.points.push_back(rays.col(k) * (z / rays(2, k)));
    }
    size_t inliers = 0;
    if (!FitPlane(sample.points, options.plane_inlier_m, options.max_plane_band_m, &sample.depth,
                  &sample.sigma, &inliers, random))
      continue;
    // The information the plane carries: its points over the noise's variance.
    sample.weight = static_cast<double>(inliers) / (sample.sigma * sample.sigma + 1e-12);
    sample.set = entry.index;
    sample.color = BoardPlane(pose->second);
    sample.color_time_s = color_item->timestamp_ns * 1e-9;
    sample.depth_time_s = depth_item->timestamp_ns * 1e-9;
    samples.push_back(std::move(sample));
  }
  return samples;
}

// The time offset: the board's distance from the depth sensor as measured, against the same
// distance predicted from the colour camera's board poses, differentiated in time. Sets
// time_offset_s/time_offset_valid when the board moved enough to tell.
void EstimateTimeOffset(const std::vector<PlaneSample>& samples, const Pose& depth_from_color,
                        const DepthAlignmentOptions& options, DepthAlignmentSummary* summary) {
  std::vector<double> t, predicted, measured;
  for (const auto& s : samples) {
    const Eigen::Vector3d normal = depth_from_color.linear() * s.color.normal;
    t.push_back(s.color_time_s);
    predicted.push_back(s.color.offset + normal.dot(depth_from_color.translation()));
    measured.push_back(s.depth.offset);
  }
  double num = 0, den = 0;
  for (size_t k = 1; k + 1 < t.size(); ++k) {
    const double dt = t[k + 1] - t[k - 1];
    if (!(dt > 0)) continue;
    const double rate = (predicted[k + 1] - predicted[k - 1]) / dt;
    num += (measured[k] - predicted[k]) * rate;
    den += rate * rate;
  }
  if (den > 1e-6) {
    summary->time_offset_s = num / den;
    summary->time_offset_valid = std::abs(summary->time_offset_s) <= options.max_time_offset_s;
  }
}

// depth_from_color from planes: the rotation from the normals (Kabsch), the translation from
// the plane offsets. False with the reason when the planes cannot fix it.
bool SolvePlanes(const std::vector<PlaneSample>& samples, const DepthAlignmentOptions& options,
                 Pose* depth_from_color, std::string* why) {
  if (static_cast<int>(samples.size()) < options.min_planes) {
    *why =
        Cat("only ", samples.size(), " board planes seen by both (needs ", options.min_planes, ")");
    return false;
  }
  // Each plane weighted by its information, relative to the mean (planes near the sensor and
  // facing it are measured best).
  double total = 0;
  for (const auto& s : samples) total += s.weight;
  std::vector<double> w;
  for (const auto& s : samples) w.push_back(s.weight * samples.size() / total);
  Eigen::Matrix3d h = Eigen::Matrix3d::Zero();
  for (size_t k = 0; k < samples.size(); ++k)
    h += w[k] * samples[k].color.normal * samples[k].depth.normal.transpose();
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(h, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d d = Eigen::Matrix3d::Identity();
  d(2, 2) = (svd.matrixV() * svd.matrixU().transpose()).determinant() < 0 ? -1 : 1;
  const Eigen::Matrix3d rotation = svd.matrixV() * d * svd.matrixU().transpose();
  // Normals spread: the smallest singular value of the stacked normals.
  Eigen::MatrixXd normals(samples.size(), 3);
  Eigen::VectorXd offsets(samples.size());
  for (size_t k = 0; k < samples.size(); ++k) {
    normals.row(k) = samples[k].depth.normal.transpose();
    offsets(k) = samples[k].depth.offset - samples[k].color.offset;
  }
  const Eigen::JacobiSVD<Eigen::MatrixXd> spread(normals);
  const double weakest =
      spread.singularValues()(2) / std::sqrt(static_cast<double>(samples.size()));
  if (weakest < std::sin(options.min_normal_spread_deg * M_PI / 180) / 2) {
    *why = Cat("the board planes are too close to parallel to fix depth_from_color (",
               samples.size(), " planes)");
    return false;
  }
  Eigen::MatrixXd weighted = normals;
  Eigen::VectorXd weighted_offsets = offsets;
  for (size_t k = 0; k < samples.size(); ++k) {
    weighted.row(k) *= std::sqrt(w[k]);
    weighted_offsets(k) *= std::sqrt(w[k]);
  }
  *depth_from_color = Pose::Identity();
  depth_from_color->linear() = rotation;
  depth_from_color->translation() = weighted.colPivHouseholderQr().solve(weighted_offsets);
  return true;
}

// How far a sample's measured plane is from the colour plane carried through the transform:
// the angle between the normals (degrees) and the offset difference (metres).
std::pair<double, double> PlaneMisfit(const PlaneSample& s, const Pose& depth_from_color) {
  const Eigen::Vector3d normal = depth_from_color.linear() * s.color.normal;
  const double offset = s.color.offset + normal.dot(depth_from_color.translation());
  const double angle = std::acos(std::clamp(normal.dot(s.depth.normal), -1.0, 1.0)) * 180 / M_PI;
  return {angle, std::abs(s.depth.offset - offset)};
}

double Median(std::vector<double> values) {
  std::nth_element(values.begin(), values.begin() + values.size() / 2, values.end());
  return values[values.size() / 2];
}

// Solves, then leaves out the planes whose misfit is far beyond the others' (a wall or the floor
// inside the outline, a board seen edge-on) and solves again, until none is.
bool SolveRobustly(std::vector<PlaneSample>* samples, const DepthAlignmentOptions& options,
                   Pose* depth_from_color, std::vector<int64_t>* rejected, std::string* why) {
  for (int round = 0; round < 20; ++round) {
    if (!SolvePlanes(*samples, options, depth_from_color, why)) return false;
    std::vector<double> angles, offsets;
    for (const auto& s : *samples) {
      auto [angle, offset] = PlaneMisfit(s, *depth_from_color);
      angles.push_back(angle);
      offsets.push_back(offset);
    }
    // Beyond five robust sigmas (1.4826 MAD about zero misfit), and never below what noise and
    // the board's own pose leave: a tenth of a degree, a millimetre.
    const double angle_limit = std::max(0.1, 5 * 1.4826 * Median(angles));
    const double offset_limit = std::max(0.001, 5 * 1.4826 * Median(offsets));
    std::vector<PlaneSample> kept;
    for (size_t k = 0; k < samples->size(); ++k) {
      if (angles[k] > angle_limit || offsets[k] > offset_limit)
        rejected->push_back((*samples)[k].set);
      else
        kept.push_back((*samples)[k]);
    }
    if (kept.size() == samples->size()) return true;
    *samples = std::move(kept);
  }
  return true;
}

}  // namespace

DepthAlignmentSummary AlignDepthToColor(const Take& take, const std::string& depth_sensor,
                                        const CameraModel& depth_model,
                                        const std::string& color_sensor,
                                        const CameraModel& color_model,
                                        const std::map<int64_t, Pose>& color_from_board,
                                        const BoardLayout& layout,
                                        const DepthAlignmentOptions& options) {
  options.Check();
  if (!take.has_stream(depth_sensor)) Fail("depth sensor '", depth_sensor, "' is not in the take");
  if (!take.has_stream(color_sensor)) Fail("camera '", color_sensor, "' is not in the take");
  const Board board(layout);
  DepthAlignmentSummary summary;
  summary.depth_sensor = depth_sensor;
  summary.color_sensor = color_sensor;
  std::mt19937_64 random(7);

  // Two passes: the board outline first through an identity guess (the sensors sit
  // centimetres apart), then through the first estimate. Each solve drops the planes that are
  // not the board (another surface inside the outline, a board seen edge-on) before it ends.
  Pose depth_from_color = Pose::Identity();
  std::vector<PlaneSample> samples;
  for (int pass = 0; pass < 2; ++pass) {
    samples = PlaneSamples(take, depth_sensor, depth_model, color_sensor, color_from_board, board,
                           depth_from_color, options, &random);
    summary.rejected_sets.clear();
    std::string why;
    if (!SolveRobustly(&samples, options, &depth_from_color, &summary.rejected_sets, &why)) {
      summary.planes = static_cast<int>(samples.size());
      summary.End(Termination::kDegenerate,
                  Cat(why, " (", depth_sensor, " and ", color_sensor, ")"));
      return summary;
    }
  }
  summary.planes = static_cast<int>(samples.size());
  summary.depth_from_color = depth_from_color;
  double sum2 = 0;
  int64_t n = 0;
  for (const auto& s : samples) {
    // The colour plane carried into the depth frame against the measured points.
    const Eigen::Vector3d normal = depth_from_color.linear() * s.color.normal;
    const double offset = s.color.offset + normal.dot(depth_from_color.translation());
    for (const auto& p : s.points) {
      const double r = normal.dot(p) - offset;
      if (std::abs(r) < std::clamp(3 * s.sigma, options.plane_inlier_m, options.max_plane_band_m)) {
        sum2 += r * r;
        ++n;
      }
    }
  }
  summary.plane_rms_m = n > 0 ? std::sqrt(sum2 / n) : 0;

  EstimateTimeOffset(samples, depth_from_color, options, &summary);
  std::string rejected;
  if (!summary.rejected_sets.empty()) {
    rejected =
        Cat("; ", summary.rejected_sets.size(), " plane(s) left out as not the board (frame sets");
    for (int64_t set : summary.rejected_sets) rejected += Cat(" ", set);
    rejected += ")";
  }
  summary.End(Termination::kSuccess, Cat(summary.planes, " board planes, plane residual ",
                                         1000 * summary.plane_rms_m, " mm RMS", rejected));
  return summary;
}

}  // namespace holocap
