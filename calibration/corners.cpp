// Sub-pixel board corners from the straight edges that meet at them.
//
// A camera integrates light over each pixel, so across a straight step edge the darkness of a
// run of pixels along one image row adds up to exactly how far along that row the edge lies:
// with the row's pixels from x0 to x1 fully covering the transition, the edge crosses the
// row's centre line at x0 - 0.5 + sum((white - v) / (white - black)). This holds for any edge
// angle (the dark area of a row strip is its centre-line length times one), needs no
// interpolation and no threshold, and the noise of one row averages out over the many rows of
// an edge. The corner is then where the lines fitted to those edge points meet: extrapolated a
// pixel or two for a tag's L corner, interpolated for a chessboard's X junction.
#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <vector>

#include "calibration/internal/common.h"

namespace holocap::calibration_internal {
namespace {

struct Line {
  Eigen::Vector2d point;   // a point on it
  Eigen::Vector2d normal;  // unit
  double Distance(const Eigen::Vector2d& p) const { return normal.dot(p - point); }
};

// Edge points of one ray: row (or column) strips across the edge, each giving the exact
// crossing of its centre line. `others` are the lines of the other edges, whose neighbourhood
// the strips avoid.
std::vector<Eigen::Vector2d> EdgePoints(const cv::Mat& grey, const Eigen::Vector2d& corner,
                                        const Eigen::Vector2d& direction,
                                        const Eigen::Vector2d& inward, double reach_in,
                                        double reach_out, double length,
                                        const std::vector<Line>& others) {
  Eigen::Vector2d normal(-direction.y(), direction.x());
  if (normal.dot(inward) < 0) normal = -normal;  // +normal: the inner side
  const double reach = std::min(reach_in, reach_out);
  const bool rows = std::abs(direction.y()) >= std::abs(direction.x());
  const int along_axis = rows ? 1 : 0;  // strips are stacked along this image axis
  const int across_axis = 1 - along_axis;
  // The strip's extent below and above the edge along the across axis.
  const double scale = 1 / std::abs(normal[across_axis]);
  const double below = (normal[across_axis] > 0 ? reach_out : reach_in) * scale;
  const double above = (normal[across_axis] > 0 ? reach_in : reach_out) * scale;
  // Which end of a strip is dark: sampled once on the ray's two sides.
  const Eigen::Vector2d mid = corner + 0.5 * length * direction;
  auto sample = [&](const Eigen::Vector2d& p) {
    const int x = static_cast<int>(std::lround(p.x())), y = static_cast<int>(std::lround(p.y()));
    if (x < 0 || y < 0 || x >= grey.cols || y >= grey.rows) return -1.0;
    return static_cast<double>(grey.at<uint8_t>(y, x));
  };
  const double left = sample(mid + 0.8 * reach * normal);
  const double right = sample(mid - 0.8 * reach * normal);
  if (left < 0 || right < 0 || std::abs(left - right) < 10) return {};
  // Along the strip axis, does darkness lie at the low end?
  const bool dark_low = (left < right) == (normal[across_axis] < 0);

  struct Strip {
    int first = 0;  // first pixel along the strip
    int fixed = 0;  // the strip's row (or column)
    std::vector<double> values;
    std::vector<double> offsets;  // signed distance of each pixel from the edge estimate
  };
  std::vector<Strip> strips;
  const double start = corner[along_axis];
  const double sign = direction[along_axis] > 0 ? 1 : -1;
  for (int k = static_cast<int>(std::ceil(sign * start));; ++k) {
    const double fixed = sign * k;
    const double t = (fixed - start) / direction[along_axis];
    if (t > length) break;
    if (t < 0) continue;
    const Eigen::Vector2d on_edge = corner + t * direction;
    // Only pixels whose centres lie within the reach.
    const int lo = static_cast<int>(std::ceil(on_edge[across_axis] - below));
    const int hi = static_cast<int>(std::floor(on_edge[across_axis] + above));
    const int fixed_i = static_cast<int>(std::lround(fixed));
    if (lo < 0 || fixed_i < 0 || hi >= (rows ? grey.cols : grey.rows) ||
        fixed_i >= (rows ? grey.rows : grey.cols)) {
      continue;
    }
    Strip strip;
    strip.first = lo;
    strip.fixed = fixed_i;
    bool clear = true;
    for (int a = lo; a <= hi && clear; ++a) {
      Eigen::Vector2d p;
      p[across_axis] = a;
      p[along_axis] = fixed_i;
      for (const Line& other : others) clear = clear && std::abs(other.Distance(p)) >= 1.2;
      strip.values.push_back(rows ? grey.at<uint8_t>(fixed_i, a) : grey.at<uint8_t>(a, fixed_i));
      strip.offsets.push_back(normal.dot(p - on_edge));
    }
    if (clear) strips.push_back(std::move(strip));
  }
  // The two levels from pixels wholly on one side (beyond half a pixel's diagonal).
  double dark_sum = 0, light_sum = 0;
  int dark_n = 0, light_n = 0;
  const bool dark_left = left < right;
  for (const Strip& s : strips) {
    for (size_t i = 0; i < s.values.size(); ++i) {
      if (std::abs(s.offsets[i]) < 0.75) continue;
      const bool on_left = s.offsets[i] > 0;
      if (on_left == dark_left) {
        dark_sum += s.values[i];
        ++dark_n;
      } else {
        light_sum += s.values[i];
        ++light_n;
      }
    }
  }
  if (dark_n < 3 || light_n < 3) return {};
  const double dark = dark_sum / dark_n, light = light_sum / light_n;
  if (light - dark < 10) return {};
  std::vector<Eigen::Vector2d> points;
  for (const Strip& s : strips) {
    double darkness = 0;
    for (double v : s.values) darkness += (light - v) / (light - dark);
    const int n = static_cast<int>(s.values.size());
    Eigen::Vector2d p;
    p[across_axis] = dark_low ? s.first - 0.5 + darkness : s.first + n - 0.5 - darkness;
    p[along_axis] = s.fixed;
    points.push_back(p);
  }
  return points;
}

// Total-least-squares line through the points.
bool FitLine(const std::vector<Eigen::Vector2d>& points, Line* line) {
  if (points.size() < 3) return false;
  Eigen::Vector2d mean = Eigen::Vector2d::Zero();
  for (const auto& p : points) mean += p / static_cast<double>(points.size());
  Eigen::Matrix2d scatter = Eigen::Matrix2d::Zero();
  for (const auto& p : points) scatter += (p - mean) * (p - mean).transpose();
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> eigen(scatter);
  line->point = mean;
  line->normal = eigen.eigenvectors().col(0);
  return true;
}

bool Intersect(const Line& a, const Line& b, Eigen::Vector2d* p) {
  Eigen::Matrix2d m;
  m.row(0) = a.normal.transpose();
  m.row(1) = b.normal.transpose();
  const double det = m.determinant();
  if (std::abs(det) < 1e-3) return false;  // nearly parallel edges
  *p = m.inverse() * Eigen::Vector2d(a.normal.dot(a.point), b.normal.dot(b.point));
  return true;
}

}  // namespace

bool RefineEdgeCorner(const cv::Mat& grey, const std::vector<Eigen::Vector2d>& rays_in,
                      double reach_in_px, double reach_out_px, double length_px,
                      Eigen::Vector2d* corner) {
  if (grey.type() != CV_8UC1 || (rays_in.size() != 2 && rays_in.size() != 4)) return false;
  if (std::min(reach_in_px, reach_out_px) < 1.2 || length_px < 3) return false;
  const bool junction = rays_in.size() == 4;
  std::vector<Eigen::Vector2d> rays;
  for (const auto& r : rays_in) {
    if (!(r.norm() > 0)) return false;
    rays.push_back(r.normalized());
  }
  const Eigen::Vector2d start = *corner;
  Eigen::Vector2d c = start;
  for (int iteration = 0; iteration < 4; ++iteration) {
    // The edge lines as now estimated: one per ray, or one per opposite pair at a junction.
    std::vector<Line> lines(2);
    for (int l = 0; l < 2; ++l) {
      lines[l].point = c;
      lines[l].normal = Eigen::Vector2d(-rays[l].y(), rays[l].x());
    }
    Line fitted[2];
    for (int l = 0; l < 2; ++l) {
      const std::vector<Line> others = {lines[1 - l]};
      std::vector<Eigen::Vector2d> points =
          EdgePoints(grey, c, rays[l], rays[1 - l], reach_in_px, reach_out_px, length_px, others);
      if (junction) {
        const auto opposite = EdgePoints(grey, c, rays[l + 2], rays[1 - l], reach_in_px,
                                         reach_out_px, length_px, others);
        points.insert(points.end(), opposite.begin(), opposite.end());
      }
      if (!FitLine(points, &fitted[l])) return false;
    }
    Eigen::Vector2d next;
    if (!Intersect(fitted[0], fitted[1], &next)) return false;
    // Keep each ray pointing where it did, along its fitted line.
    for (int l = 0; l < 2; ++l) {
      Eigen::Vector2d along(fitted[l].normal.y(), -fitted[l].normal.x());
      if (along.dot(rays[l]) < 0) along = -along;
      rays[l] = along;
      if (junction) rays[l + 2] = -along;
    }
    const double moved = (next - c).norm();
    c = next;
    if (moved < 1e-3) break;
  }
  if (!c.allFinite() || (c - start).norm() > std::max(reach_in_px, reach_out_px)) return false;
  *corner = c;
  return true;
}

}  // namespace holocap::calibration_internal
