// Synthetic calibration problems for the tests: true cameras, board poses that each camera
// sees well, observations projected through the true models with known noise, and board
// images rendered exactly (each pixel the area mean of the board under its footprint).
#pragma once

#include <Eigen/Geometry>
#include <cmath>
#include <map>
#include <opencv2/core.hpp>
#include <random>
#include <string>
#include <vector>

#include "calibration/calibration.h"
#include "core/board.h"
#include "core/camera.h"

namespace holocap::testing {

struct SyntheticRig {
  BoardLayout layout;
  std::map<std::string, CameraModel> truth;
  std::vector<CalibrationCamera> cameras;
  std::vector<BoardObservation> observations;
  std::map<int64_t, Pose> world_from_board;
};

struct SyntheticOptions {
  std::vector<CameraModel> lenses;                   // one per camera; poses are set here
  double ring_radius = 2.0;                          // cameras on an arc of this radius ...
  double arc_deg = 100;                              // ... spanning this angle
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();  // shifts the whole rig and board
  int frames = 60;                                   // board poses
  double noise_px = 0.3;                             // Gaussian, per coordinate
  double min_distance = 0.9, max_distance = 1.8;     // board distance from the camera it faces
  double max_tilt_deg = 40;                          // board tilt away from facing that camera
  bool fronto_parallel = false;       // every pose square-on to its camera, same distance
  double min_visible_fraction = 0.5;  // a camera observes a pose seeing this much of it
  double pixel_margin = 0.2;          // board centres avoid this fraction of each image edge
  uint64_t seed = 1;
};

inline BoardLayout TestBoard() {
  BoardLayout layout;
  layout.family = "tag36h11";
  layout.tags_across = 5;
  layout.tags_down = 4;
  layout.spacing = 0.06;
  layout.margin = 0.06;
  return layout;
}

inline SyntheticRig MakeSyntheticRig(const SyntheticOptions& options,
                                     const BoardLayout& layout = TestBoard()) {
  SyntheticRig rig;
  rig.layout = layout;
  const Board board(layout);
  const std::vector<Eigen::Vector3d> grid = board.GridPoints();
  const Eigen::Vector3d board_centre((board.width_n() - 1) * layout.spacing / 2,
                                     (board.height_n() - 1) * layout.spacing / 2, 0);
  std::mt19937_64 random(options.seed);
  std::uniform_real_distribution<double> unit(0, 1);
  std::normal_distribution<double> noise(0, options.noise_px);
  const int n = static_cast<int>(options.lenses.size());
  std::vector<CameraModel> cams;
  for (int i = 0; i < n; ++i) {
    const double azimuth =
        (n == 1 ? 0.0 : (-0.5 + static_cast<double>(i) / (n - 1)) * options.arc_deg) * M_PI / 180;
    const Eigen::Vector3d eye =
        options.origin + Eigen::Vector3d(options.ring_radius * std::cos(azimuth),
                                         options.ring_radius * std::sin(azimuth),
                                         1.4 + 0.2 * (i % 2));
    const Eigen::Vector3d target = options.origin + Eigen::Vector3d(0, 0, 1.2);
    CameraModel cam = options.lenses[i];
    cam.set_cam_from_world(CamFromWorldLookAt(eye, target));
    const std::string name = "cam" + std::to_string(i);
    rig.truth.emplace(name, cam);
    rig.cameras.push_back({name, cam.width(), cam.height(), cam.lensmodel()});
    cams.push_back(cam);
  }
  for (int f = 0; f < options.frames; ++f) {
    const int facing = f % n;
    const CameraModel& cam = cams[facing];
    // A direction inside the central part of the facing camera's view.
    const double spread = 1 - 2 * options.pixel_margin;
    const Eigen::Vector2d pixel(cam.width() * (options.pixel_margin + spread * unit(random)),
                                cam.height() * (options.pixel_margin + spread * unit(random)));
    const Eigen::Vector3d ray = cam.Unproject(pixel);
    const double distance =
        options.fronto_parallel
            ? 0.5 * (options.min_distance + options.max_distance) / ray.z()  // one z-depth
            : options.min_distance + (options.max_distance - options.min_distance) * unit(random);
    const Eigen::Vector3d centre_in_cam = ray * distance;
    // Board +z (its back) points away from the camera; tilt it about a random axis.
    Eigen::Matrix3d cam_from_board_rotation = Eigen::Matrix3d::Identity();
    if (!options.fronto_parallel) {
      const double tilt = options.max_tilt_deg * M_PI / 180 * std::sqrt(unit(random));
      const double axis_angle = 2 * M_PI * unit(random);
      const Eigen::Vector3d axis(std::cos(axis_angle), std::sin(axis_angle), 0);
      const double spin = (unit(random) - 0.5) * 0.6;
      cam_from_board_rotation =
          Eigen::AngleAxisd(tilt, axis).toRotationMatrix() *
          Eigen::AngleAxisd(spin, Eigen::Vector3d::UnitZ()).toRotationMatrix();
    }
    Pose cam_from_board = Pose::Identity();
    cam_from_board.linear() = cam_from_board_rotation;
    cam_from_board.translation() = centre_in_cam - cam_from_board_rotation * board_centre;
    const Pose world_from_board = cam.world_from_cam() * cam_from_board;
    rig.world_from_board[f] = world_from_board;
    for (int i = 0; i < n; ++i) {
      const Pose view = cams[i].cam_from_world() * world_from_board;
      const Eigen::Vector3d normal = view.linear().col(2);
      if (normal.dot(view.translation()) < 0.3 * view.translation().norm()) continue;  // back side
      BoardObservation obs;
      obs.sensor = "cam" + std::to_string(i);
      obs.frame_set = f;
      obs.timestamp_ns = static_cast<int64_t>(f) * 33333333;
      obs.points.setZero(static_cast<Eigen::Index>(grid.size()), 3);
      int seen = 0;
      for (size_t k = 0; k < grid.size(); ++k) {
        Eigen::Vector2d q;
        const Eigen::Vector3d p = view * grid[k];
        if (cams[i].Project(p, &q) && p.z() > 0.1 && cams[i].InImage(q, 2)) {
          obs.points.row(static_cast<Eigen::Index>(k)) << q.x() + noise(random),
              q.y() + noise(random), 1.0;
          ++seen;
        } else {
          obs.points.row(static_cast<Eigen::Index>(k)) << 0, 0, -1.0;
        }
      }
      if (seen >= options.min_visible_fraction * grid.size()) rig.observations.push_back(obs);
    }
  }
  return rig;
}

// The board as `camera` sees it at cam_from_board: every pixel the exact mean reflectance of
// its footprint (black 20, white 230 DN), background 128, plus Gaussian noise.
inline cv::Mat RenderBoard(const CameraModel& camera, const Board& board,
                           const Pose& cam_from_board, double noise_dn = 0, uint64_t seed = 1) {
  const int w = camera.width(), h = camera.height();
  Eigen::Matrix2Xd corners(2, static_cast<Eigen::Index>(w + 1) * (h + 1));
  for (int y = 0; y <= h; ++y) {
    for (int x = 0; x <= w; ++x)
      corners.col(static_cast<Eigen::Index>(y) * (w + 1) + x) << x - 0.5, y - 0.5;
  }
  const Eigen::Matrix3Xd rays = camera.UnprojectMany(corners);
  const Pose board_from_cam = cam_from_board.inverse();
  const Eigen::Vector3d origin = board_from_cam.translation();
  // Board-plane coordinates of every pixel corner.
  Eigen::Matrix2Xd uv(2, corners.cols());
  std::vector<bool> hit(corners.cols(), false);
  for (Eigen::Index k = 0; k < corners.cols(); ++k) {
    if (!rays.col(k).allFinite()) continue;
    const Eigen::Vector3d d = board_from_cam.linear() * rays.col(k);
    if (std::abs(d.z()) < 1e-12) continue;
    const double t = -origin.z() / d.z();
    if (t <= 0) continue;
    uv.col(k) = (origin + t * d).head<2>();
    hit[k] = true;
  }
  std::mt19937_64 random(seed);
  std::normal_distribution<double> noise(0, noise_dn);
  cv::Mat image(h, w, CV_8UC1);
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const Eigen::Index k00 = static_cast<Eigen::Index>(y) * (w + 1) + x;
      const Eigen::Index ks[4] = {k00, k00 + 1, k00 + w + 2, k00 + w + 1};
      double value = 128;
      bool all = true, any = false;
      std::vector<Eigen::Vector2d> polygon;
      for (Eigen::Index k : ks) {
        if (!hit[k] || !board.Contains(uv(0, k), uv(1, k))) {
          all = false;
        } else {
          any = true;
        }
        if (hit[k]) polygon.push_back(uv.col(k));
      }
      if (all) {
        value = 20 + 210 * board.MeanReflectance(polygon);
      } else if (any && polygon.size() == 4) {
        const Eigen::Vector2d c = 0.25 * (polygon[0] + polygon[1] + polygon[2] + polygon[3]);
        value = board.Contains(c.x(), c.y()) ? 20 + 210 * board.Reflectance(c.x(), c.y()) : 128;
      }
      if (noise_dn > 0) value += noise(random);
      image.at<uint8_t>(y, x) = static_cast<uint8_t>(std::clamp(std::lround(value), 0L, 255L));
    }
  }
  return image;
}

}  // namespace holocap::testing
