// One live frame completed by the scan: alignment, the subject's live surface, and the scan's
// triangles the sensor does not observe.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <optional>

#include "core/error.h"
#include "core/projector.h"
#include "live/internal/live.h"
#include "live/live.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
// Fewer valid live pixels than this: the frame has no usable depth.
constexpr int64_t kMinLivePoints = 200;
// Fewer scan points the sensor should see than this: nothing to judge the fit by.
constexpr int64_t kMinExpected = 50;

std::string Fixed(double value, int decimals) {
  char text[64];
  std::snprintf(text, sizeof(text), "%.*f", decimals, value);
  return text;
}

Mesh Transformed(const Mesh& mesh, const Pose& pose) {
  Mesh moved = mesh;
  const Eigen::Isometry3f transform = pose.cast<float>();
  for (Eigen::Vector3f& v : moved.vertices) v = transform * v;
  for (Eigen::Vector3f& n : moved.normals) n = transform.linear() * n;
  return moved;
}

Eigen::Matrix<uint8_t, 3, 1> ColorAt(const cv::Mat& bgr, float u, float v) {
  const int x = static_cast<int>(std::lround(u));
  const int y = static_cast<int>(std::lround(v));
  if (bgr.empty() || x < 0 || y < 0 || x >= bgr.cols || y >= bgr.rows)
    return Eigen::Matrix<uint8_t, 3, 1>(128, 128, 128);
  const cv::Vec3b pixel = bgr.at<cv::Vec3b>(y, x);
  return Eigen::Matrix<uint8_t, 3, 1>(pixel[2], pixel[1], pixel[0]);
}

// Keeps the faces `keep` says, and only the vertices they use.
Mesh KeepFaces(const Mesh& mesh, const std::vector<bool>& keep) {
  Mesh kept;
  std::vector<int> index(mesh.vertices.size(), -1);
  for (size_t f = 0; f < mesh.faces.size(); ++f) {
    if (!keep[f]) continue;
    Eigen::Vector3i face;
    for (int c = 0; c < 3; ++c) {
      const int v = mesh.faces[f][c];
      if (index[v] < 0) {
        index[v] = static_cast<int>(kept.vertices.size());
        kept.vertices.push_back(mesh.vertices[v]);
        if (!mesh.normals.empty()) kept.normals.push_back(mesh.normals[v]);
        if (!mesh.colors.empty()) kept.colors.push_back(mesh.colors[v]);
      }
      face[c] = index[v];
    }
    kept.faces.push_back(face);
  }
  return kept;
}

// A scan that kept the floor it stood on (a wide flat layer at its bottom, most of its vertices)
// loses it: the floor does not move with the subject, and the live frame has its own.
// Returns the floor's height along `up` (NaN: no floor layer, nothing cut).
double CutFloor(Mesh* scan, const Eigen::Vector3d& up) {
  constexpr double kBin = 0.01, kReach = 0.1, kLayer = 0.02, kCut = 0.03, kShare = 0.25;
  std::vector<double> height(scan->vertices.size());
  double lowest = std::numeric_limits<double>::infinity();
  for (size_t v = 0; v < height.size(); ++v) {
    height[v] = up.dot(scan->vertices[v].cast<double>());
    lowest = std::min(lowest, height[v]);
  }
  std::vector<int64_t> bins(static_cast<size_t>(kReach / kBin), 0);
  for (double h : height) {
    const size_t bin = static_cast<size_t>((h - lowest) / kBin);
    if (bin < bins.size()) ++bins[bin];
  }
  const size_t peak =
      static_cast<size_t>(std::max_element(bins.begin(), bins.end()) - bins.begin());
  const double level = lowest + (peak + 0.5) * kBin;
  int64_t layer = 0;
  for (double h : height) layer += std::abs(h - level) <= kLayer;
  if (layer < kShare * static_cast<double>(height.size()))
    return std::numeric_limits<double>::quiet_NaN();
  std::vector<bool> keep(scan->faces.size());
  for (size_t f = 0; f < scan->faces.size(); ++f) {
    const Eigen::Vector3i& face = scan->faces[f];
    keep[f] = height[face[0]] > level + kCut && height[face[1]] > level + kCut &&
              height[face[2]] > level + kCut;
  }
  *scan = KeepFaces(*scan, keep);
  return level;
}

}  // namespace

Mesh MeshLiveSurface(const LiveSurface& live, const cv::Mat& subject, const cv::Mat& color_bgr,
                     const CameraModel& color_camera, double max_depth_jump_m) {
  Mesh mesh;
  std::vector<int> index(live.points.size(), -1);
  const FastProjector color(color_camera);
  for (int y = 0; y < live.height; ++y) {
    for (int x = 0; x < live.width; ++x) {
      const size_t i = static_cast<size_t>(y) * live.width + x;
      if (subject.at<uint8_t>(y, x) == 0 || !live.points[i].allFinite()) continue;
      index[i] = static_cast<int>(mesh.vertices.size());
      mesh.vertices.push_back(live.points[i]);
      float u = -1, v = -1, z = 0;
      if (color_bgr.empty() || !color.ProjectWorld(live.points[i], &u, &v, &z)) u = v = -1;
      mesh.colors.push_back(ColorAt(color_bgr, u, v));
    }
  }
  const Eigen::Vector3f center = live.camera.center_in_world().cast<float>();
  auto add = [&](size_t a, size_t b, size_t c) {
    if (index[a] < 0 || index[b] < 0 || index[c] < 0) return;
    const float lo = std::min({live.depth[a], live.depth[b], live.depth[c]});
    const float hi = std::max({live.depth[a], live.depth[b], live.depth[c]});
    if (hi - lo > max_depth_jump_m) return;
    const Eigen::Vector3f& pa = live.points[a];
    const Eigen::Vector3f n = (live.points[b] - pa).cross(live.points[c] - pa);
    if (n.dot(center - pa) >= 0) {
      mesh.faces.emplace_back(index[a], index[b], index[c]);
    } else {
      mesh.faces.emplace_back(index[a], index[c], index[b]);
    }
  };
  for (int y = 0; y + 1 < live.height; ++y) {
    for (int x = 0; x + 1 < live.width; ++x) {
      const size_t a = static_cast<size_t>(y) * live.width + x;
      add(a, a + live.width, a + 1);
      add(a + 1, a + live.width, a + live.width + 1);
    }
  }
  mesh.ComputeNormals();
  return mesh;
}

LiveCompositor::LiveCompositor(Mesh scan, const LiveOptions& options, const Eigen::Vector3d& up,
                               double floor_level_m, std::optional<ScanAlbedo> albedo)
    : scan_(std::move(scan)),
      options_(options),
      up_(up.normalized()),
      floor_level_m_(floor_level_m) {
  options_.Check();
  if (scan_.normals.size() != scan_.vertices.size()) scan_.ComputeNormals();
  if (scan_.colors.size() != scan_.vertices.size())
    scan_.colors.assign(scan_.vertices.size(), Eigen::Matrix<uint8_t, 3, 1>(128, 128, 128));
  if (albedo && options_.relight) {
    if (albedo->colors.size() != scan_.vertices.size())
      Fail("live: the scan's albedo has ", albedo->colors.size(), " colours for ",
           scan_.vertices.size(), " vertices");
    // The same cut as the scan's below keeps the same vertices in the same order.
    Mesh cut = scan_;
    cut.colors = std::move(albedo->colors);
    CutFloor(&cut, up_);
    albedo->colors = std::move(cut.colors);
    albedo_ = std::move(albedo);
  }
  scan_floor_m_ = CutFloor(&scan_, up_);
  if (scan_.faces.empty()) Fail("live: the scan has no triangles (besides a floor)");
  scan_centroid_ = Eigen::Vector3d::Zero();
  for (const Eigen::Vector3f& v : scan_.vertices) {
    scan_box_.extend(v);
    scan_centroid_ += v.cast<double>();
  }
  scan_centroid_ /= static_cast<double>(scan_.vertices.size());
}

Pose LiveCompositor::PredictedPose(int64_t set) const {
  const auto& [set0, pose0] = poses_.front();
  const auto& [set1, pose1] = poses_.back();
  if (set <= set1 || set1 <= set0) return pose1;
  const double ahead = static_cast<double>(set - set1) / static_cast<double>(set1 - set0);
  const Eigen::Vector3d& centroid = scan_centroid_;
  const Eigen::Vector3d c0 = pose0 * centroid, c1 = pose1 * centroid;
  Eigen::AngleAxisd turn(Eigen::Matrix3d(pose1.linear() * pose0.linear().transpose()));
  turn.angle() *= ahead;
  Pose pose = Pose::Identity();
  pose.linear() = turn.toRotationMatrix() * pose1.linear();
  pose.translation() = c1 + ahead * (c1 - c0) - pose.linear() * centroid;
  return pose;
}

// The scan turned by `yaw_rad` about the up axis and moved so that the centroid of its side
// that faces the sensor sits on the centroid of the nearest live points: where the scan was made
// elsewhere in the world than the live take (two takes calibrated apart share no world).
// Matching the seen side, not the whole scan, puts the scan's depth behind the live surface by
// what the subject's own shape says at that heading.
Pose LiveCompositor::CentredPose(const LiveSurface& live, double yaw_rad) const {
  const Eigen::AlignedBox3f& box = scan_box_;
  std::vector<float> depths;
  for (float d : live.depth)
    if (!std::isnan(d)) depths.push_back(d);
  if (depths.empty()) return Pose::Identity();
  std::nth_element(depths.begin(), depths.begin() + depths.size() / 20, depths.end());
  const float near = depths[depths.size() / 20] + box.sizes().norm() * 0.5f;
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  int64_t count = 0;
  for (size_t i = 0; i < live.points.size(); ++i) {
    if (std::isnan(live.depth[i]) || live.depth[i] > near) continue;
    sum += live.points[i].cast<double>();
    ++count;
  }
  if (count == 0) return Pose::Identity();
  const Eigen::Vector3d live_centroid = sum / static_cast<double>(count);
  const Eigen::Vector3d view = (live_centroid - live.camera.center_in_world()).normalized();
  Pose pose = Pose::Identity();
  pose.linear() = Eigen::AngleAxisd(yaw_rad, up_.normalized()).toRotationMatrix();
  // The scan's side facing the sensor at this heading (normals towards it; what the subject
  // hides from itself is not told apart).
  const Eigen::Vector3f toward = -(pose.linear().transpose() * view).cast<float>();
  Eigen::Vector3d seen = Eigen::Vector3d::Zero();
  int64_t facing = 0;
  for (size_t v = 0; v < scan_.vertices.size(); ++v) {
    if (scan_.normals[v].dot(toward) <= 0) continue;
    seen += scan_.vertices[v].cast<double>();
    ++facing;
  }
  const Eigen::Vector3d anchor =
      facing > 0 ? Eigen::Vector3d(seen / static_cast<double>(facing)) : scan_centroid_;
  pose.translation() = live_centroid - pose.linear() * anchor;
  // A subject stands on the floor in both takes: the scan's floor onto the live one.
  if (std::isfinite(floor_level_m_) && std::isfinite(scan_floor_m_)) {
    pose.translation() += (floor_level_m_ - up_.dot(pose * (scan_floor_m_ * up_))) * up_;
  }
  return pose;
}

void LiveCompositor::Relight(Mesh* deformed, const CameraModel& sensor) const {
  const Eigen::Matrix3d to_sensor = sensor.cam_from_world().linear();
  for (size_t v = 0; v < deformed->vertices.size(); ++v) {
    const double shading =
        albedo_->light.Shading((to_sensor * deformed->normals[v].cast<double>()).normalized());
    for (int c = 0; c < 3; ++c) {
      deformed->colors[v][c] =
          static_cast<uint8_t>(std::min(255.0, std::round(albedo_->colors[v][c] * shading)));
    }
  }
}

cv::Mat LiveCompositor::SubjectMask(const LiveSurface& live, const Mesh& deformed,
                                    double* explained_fraction) const {
  const cv::Mat scan_depth = RenderDepth(deformed, live.camera);
  cv::Mat subject(live.height, live.width, CV_8U, cv::Scalar(0));
  std::vector<int> front;  // the subject's pixels, grown from those near the scan
  constexpr int kRadius = 2;
  for (int y = 0; y < live.height; ++y) {
    for (int x = 0; x < live.width; ++x) {
      const float d = live.depth[static_cast<size_t>(y) * live.width + x];
      if (std::isnan(d)) continue;
      bool near = false;
      for (int dy = -kRadius; dy <= kRadius && !near; ++dy) {
        for (int dx = -kRadius; dx <= kRadius && !near; ++dx) {
          const int xx = x + dx, yy = y + dy;
          if (xx < 0 || yy < 0 || xx >= live.width || yy >= live.height) continue;
          near = std::abs(scan_depth.at<float>(yy, xx) - d) < options_.subject_gate_m;
        }
      }
      if (near) {
        subject.at<uint8_t>(y, x) = 255;
        front.push_back(y * live.width + x);
      }
    }
  }
  // The subject goes on where its surface does: a limb the scan was not bent onto (a leg
  // swung further than the scan's) is joined to the body without a jump in depth. Only within
  // subject_reach_m of the deformed scan's box, and 5 cm above its soles: the floor joins the
  // feet without a jump, and a floor known to a few centimetres is not cut exactly.
  const bool reach = options_.subject_reach_m > 0;
  if (deformed.vertices.empty() || (!reach && explained_fraction == nullptr)) return subject;
  Eigen::AlignedBox3f box;
  float lowest = std::numeric_limits<float>::infinity();
  const Eigen::Vector3f up = up_.cast<float>();
  for (const Eigen::Vector3f& v : deformed.vertices) {
    box.extend(v);
    lowest = std::min(lowest, up.dot(v));
  }
  box.min().array() -= static_cast<float>(options_.subject_reach_m);
  box.max().array() += static_cast<float>(options_.subject_reach_m);
  constexpr float kAboveSoles = 0.05f;
  const float above = lowest + kAboveSoles;
  const float jump = static_cast<float>(options_.max_depth_jump_m);
  // Grown from the pixels on the scan without a jump in depth, above the soles: within the box
  // (`inside`, the subject) or anywhere (`joined`, what the scan should explain).
  auto grow = [&](cv::Mat* mask, std::vector<int> seeds, bool inside) {
    while (!seeds.empty()) {
      const int i = seeds.back();
      seeds.pop_back();
      const int x = i % live.width, y = i / live.width;
      const float d = live.depth[static_cast<size_t>(i)];
      const int next[4][2] = {{x - 1, y}, {x + 1, y}, {x, y - 1}, {x, y + 1}};
      for (const auto& [xx, yy] : next) {
        if (xx < 0 || yy < 0 || xx >= live.width || yy >= live.height) continue;
        const size_t j = static_cast<size_t>(yy) * live.width + xx;
        if (mask->at<uint8_t>(yy, xx) || !(std::abs(live.depth[j] - d) < jump) ||
            !live.points[j].allFinite() || (inside && !box.contains(live.points[j])) ||
            up.dot(live.points[j]) < above)
          continue;
        mask->at<uint8_t>(yy, xx) = 255;
        seeds.push_back(static_cast<int>(j));
      }
    }
  };
  if (explained_fraction != nullptr) {
    cv::Mat joined = subject.clone();
    grow(&joined, front, /*inside=*/false);
    const int on_scan = static_cast<int>(front.size()), all = cv::countNonZero(joined);
    *explained_fraction = all > 0 ? static_cast<double>(on_scan) / all : 0;
  }
  if (reach) grow(&subject, std::move(front), /*inside=*/true);
  return subject;
}

Mesh LiveCompositor::UnobservedScan(const Mesh& deformed, const LiveSurface& live,
                                    const cv::Mat& subject) const {
  const FastProjector projector(live.camera);
  const Eigen::Vector3f center = live.camera.center_in_world().cast<float>();
  std::vector<bool> observed(deformed.vertices.size(), false);
  for (size_t v = 0; v < deformed.vertices.size(); ++v) {
    const Eigen::Vector3f& p = deformed.vertices[v];
    if (deformed.normals[v].dot(center - p) <= 0) continue;
    float u, w, z;
    if (!projector.ProjectWorld(p, &u, &w, &z)) continue;
    const int x = static_cast<int>(std::lround(u));
    const int y = static_cast<int>(std::lround(w));
    if (x < 0 || y < 0 || x >= live.width || y >= live.height) continue;
    if (subject.at<uint8_t>(y, x) == 0) continue;
    const float d = live.depth[static_cast<size_t>(y) * live.width + x];
    observed[v] = std::abs(d - z) < options_.observed_gate_m;
  }
  std::vector<bool> keep(deformed.faces.size());
  for (size_t f = 0; f < deformed.faces.size(); ++f) {
    const Eigen::Vector3i& face = deformed.faces[f];
    keep[f] = !(observed[face[0]] && observed[face[1]] && observed[face[2]]);
  }
  return KeepFaces(deformed, keep);
}

LiveResult LiveCompositor::Process(int64_t set, const cv::Mat& depth_m,
                                   const CameraModel& depth_camera, const cv::Mat& color_bgr,
                                   const CameraModel& color_camera) {
  const auto start = std::chrono::steady_clock::now();
  LiveResult result;
  LiveFrame& frame = result.frame;
  frame.set = set;
  LiveSurface live =
      MakeLiveSurface(depth_m, depth_camera, options_.depth_min_m, options_.depth_max_m);
  if (std::isfinite(floor_level_m_)) {
    for (size_t i = 0; i < live.points.size(); ++i) {
      if (!live.points[i].allFinite() ||
          up_.cast<float>().dot(live.points[i]) >= floor_level_m_ + options_.floor_margin_m)
        continue;
      if (live.normals[i].allFinite()) --live.valid;
      live.points[i] = live.normals[i] = Eigen::Vector3f::Constant(kNaN);
      live.depth[i] = kNaN;
    }
  }
  frame.live_points = live.valid;
  auto finish = [&](LiveState state, std::string why) {
    frame.state = state;
    frame.why = std::move(why);
    frame.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    return result;
  };
  if (live.valid < kMinLivePoints) {
    return finish(LiveState::kNoDepth, Cat("no usable depth (", live.valid, " valid pixels)"));
  }
  if (options_.nonrigid && (!graph_ || !options_.carry_deformation)) {
    // The graph at rest is the same every frame: built once, copied.
    if (!rest_graph_) rest_graph_.emplace(scan_, options_.node_spacing_m, options_.node_neighbours);
    graph_ = rest_graph_;
  }
  // The scan as the frame before left it, aligned rigidly from where it was.
  Mesh previous = scan_;
  if (graph_) {
    for (size_t v = 0; v < previous.vertices.size(); ++v) {
      previous.vertices[v] = graph_->Apply(v, scan_.vertices[v].cast<double>()).cast<float>();
      previous.normals[v] = graph_->ApplyNormal(v, scan_.normals[v].cast<double>()).cast<float>();
    }
  }
  // From the frame before's alignment; the first frame from the scan where it is (it may
  // already sit on the subject: the same world).
  const bool first = !has_pose_;
  RigidAlignment rigid =
      AlignRigid(previous, live, first ? Pose::Identity() : last_world_from_scan_, options_);
  if (first || rigid.fit.inlier_fraction < options_.min_rigid_inlier_fraction) {
    // The first frame, or the subject moved too far since the last composed frame (frames
    // skipped, a quick turn): the last two composed frames' motion carried on to this set, and
    // the scan moved onto the subject's nearest points turned to kHeadings headings about the
    // up axis; the best fit wins.
    // The first frame has nothing to go by (the scan may lie where it was made, or in a world
    // of its own: two takes calibrated apart) and tries every heading; a later frame searches
    // the headings only until one fits.
    auto try_start = [&](const Pose& start_pose) {
      const RigidAlignment candidate = AlignRigid(previous, live, start_pose, options_);
      if (candidate.fit.inlier_fraction <= rigid.fit.inlier_fraction) return;
      rigid = candidate;
      frame.relocalised = !first;
    };
    if (poses_.size() == 2) try_start(PredictedPose(set));
    constexpr int kHeadings = 8;
    for (int k = 0; k < kHeadings; ++k) {
      const bool fits = rigid.fit.inlier_fraction >= options_.min_rigid_inlier_fraction;
      if (fits && !first) break;
      try_start(CentredPose(live, 2 * M_PI * k / kHeadings));
    }
  }
  frame.world_from_scan = rigid.world_from_scan;
  frame.rigid_inlier_fraction = rigid.fit.inlier_fraction;
  frame.rigid_residual_m = rigid.fit.residual_m;
  NonRigidFit fit;
  std::optional<DeformationGraph> posed;
  if (graph_) {
    posed = graph_->Posed(rigid.world_from_scan);
    fit = FitNonRigid(Transformed(scan_, rigid.world_from_scan), live, options_, &*posed);
  } else {
    fit.deformed = Transformed(scan_, rigid.world_from_scan);
    fit.before = fit.after = rigid.fit;
  }
  frame.inlier_fraction = fit.after.inlier_fraction;
  frame.residual_m = fit.after.residual_m;
  frame.deformation_rms_m = fit.deformation_rms_m;
  frame.deformation_max_m = fit.deformation_max_m;
  if (fit.after.expected < kMinExpected) {
    return finish(LiveState::kRefused, Cat("the aligned scan lies where the sensor sees nothing (",
                                           fit.after.expected, " scan points in view)"));
  }
  if (rigid.fit.inlier_fraction < options_.min_rigid_inlier_fraction) {
    return finish(LiveState::kRefused,
                  Cat("the scan does not fit the live surface rigidly: ",
                      Fixed(100 * rigid.fit.inlier_fraction, 1), " % of its visible points within ",
                      Fixed(100 * options_.gate_m, 1), " cm (needs ",
                      Fixed(100 * options_.min_rigid_inlier_fraction, 1), " %)"));
  }
  if (fit.deformation_rms_m > options_.max_deformation_rms_m) {
    return finish(LiveState::kRefused,
                  Cat("the scan does not fit the live surface without bending it ",
                      Fixed(100 * fit.deformation_rms_m, 1), " cm RMS (at most ",
                      Fixed(100 * options_.max_deformation_rms_m, 1), " cm)"));
  }
  if (fit.after.inlier_fraction < options_.min_inlier_fraction) {
    return finish(
        LiveState::kRefused,
        Cat("the scan does not fit the live surface: ", Fixed(100 * fit.after.inlier_fraction, 1),
            " % of its visible points within ", Fixed(100 * options_.gate_m, 1), " cm (needs ",
            Fixed(100 * options_.min_inlier_fraction, 1), " %)"));
  }
  if (!(fit.after.residual_m <= options_.max_residual_m)) {
    return finish(LiveState::kRefused, Cat("the scan does not fit the live surface: residual ",
                                           Fixed(1e3 * fit.after.residual_m, 1), " mm (at most ",
                                           Fixed(1e3 * options_.max_residual_m, 1), " mm)"));
  }
  double explained = 0;
  const cv::Mat subject = SubjectMask(live, fit.deformed, &explained);
  frame.explained_fraction = explained;
  // Only a fit that bends the scan is held to it: a rigid one leaves the limbs that moved.
  if (graph_ && explained < options_.min_explained_fraction) {
    return finish(LiveState::kRefused, Cat("the scan explains ", Fixed(100 * explained, 1),
                                           " % of the live surface joined to it (needs ",
                                           Fixed(100 * options_.min_explained_fraction, 1),
                                           " %): it fits a part of a larger subject"));
  }
  has_pose_ = true;
  last_world_from_scan_ = rigid.world_from_scan;
  if (poses_.size() == 2) poses_.erase(poses_.begin());
  poses_.emplace_back(set, rigid.world_from_scan);
  if (graph_) graph_->TakeMotions(*posed, rigid.world_from_scan);
  frame.subject_pixels = cv::countNonZero(subject);
  result.live = MeshLiveSurface(live, subject, color_bgr, color_camera, options_.max_depth_jump_m);
  if (albedo_) Relight(&fit.deformed, live.camera);
  const Mesh unobserved = UnobservedScan(fit.deformed, live, subject);
  frame.live_faces = static_cast<int64_t>(result.live.faces.size());
  frame.scan_faces = static_cast<int64_t>(unobserved.faces.size());
  result.composed = result.live;
  result.composed.Append(unobserved);
  return finish(LiveState::kComposed, "");
}

}  // namespace holocap
