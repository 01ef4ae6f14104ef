// Solved calibration against the simulated truth.
#include <algorithm>
#include <cmath>
#include <limits>

#include "calibration/calibration.h"
#include "calibration/internal/common.h"
#include "core/error.h"

namespace holocap {
namespace calibration_internal {

Pose WorldFromReference(const CalibrationSummary& summary, const CameraModel& reference_truth,
                        const std::map<int64_t, Pose>& world_from_board, const BoardLayout& layout,
                        bool* from_boards) {
  const std::vector<Eigen::Vector3d> grid = Board(layout).GridPoints();
  // A symmetric board's solved numbering may be turned against the truth's in any frame set:
  // each frame's points are matched under the turn that lays them closest to the true ones,
  // the solved rig placed by the reference camera's true pose for this.
  std::vector<std::vector<int>> orders;
  for (int turn : AmbiguousBoardTurns(layout))
    orders.push_back(TurnedGridOrder(layout.width_n(), layout.height_n(), turn));
  const Pose rough_world_from_ref = reference_truth.world_from_cam();
  std::vector<Eigen::Vector3d> in_ref, in_world;
  for (const auto& [set, ref_from_board] : summary.ref_from_board) {
    auto it = world_from_board.find(set);
    if (it == world_from_board.end()) continue;
    const std::vector<int>* best = &orders.front();
    double best_distance = std::numeric_limits<double>::infinity();
    for (const auto& order : orders) {
      double distance = 0;
      for (size_t r = 0; r < grid.size(); ++r) {
        distance += (rough_world_from_ref * ref_from_board * grid[r] - it->second * grid[order[r]])
                        .squaredNorm();
      }
      if (distance < best_distance) {
        best_distance = distance;
        best = &order;
      }
    }
    for (size_t r = 0; r < grid.size(); ++r) {
      in_ref.push_back(ref_from_board * grid[r]);
      in_world.push_back(it->second * grid[(*best)[r]]);
    }
  }
  if (from_boards != nullptr) *from_boards = in_ref.size() >= 3;
  return in_ref.size() >= 3 ? FitRigid(in_ref, in_world) : reference_truth.world_from_cam();
}

}  // namespace calibration_internal

namespace {

// Both models' cores mean the same thing only within a projection family.
bool CoresComparable(const std::string& a, const std::string& b) {
  auto family = [](const std::string& m) {
    if (m.rfind("LENSMODEL_OPENCV", 0) == 0 || m == "LENSMODEL_PINHOLE") return 0;
    if (m == "LENSMODEL_STEREOGRAPHIC" || m.rfind("LENSMODEL_SPLINED_STEREOGRAPHIC", 0) == 0)
      return 1;
    return 2;
  };
  return family(a) == family(b) && family(a) != 2;
}

// The solved rig laid onto the true one (AlignRigs).
Pose TrueWorldFromSolved(const CalibrationSummary& summary,
                         const std::map<std::string, CameraModel>& truth) {
  std::map<std::string, CameraModel> solved;
  for (const auto& cam : summary.cameras) {
    if (cam.solved) solved.emplace(cam.name, cam.model);
  }
  return AlignRigs(solved, truth);
}

// Sums over every camera's imager samples.
struct ProjectionTally {
  double sum2 = 0, observed_sum2 = 0;
  int64_t samples = 0, within = 0, with_sigma = 0, observed_n = 0;
};

// Core and pose errors of one camera, into `result` and its json `j`.
void CompareCoreAndPose(const CalibratedCamera& cam, const CameraModel& real,
                        const Pose& true_world_from_ref_cam, const Pose& true_world_from_solved,
                        GroundTruthComparison* result, nlohmann::json* j) {
  const CameraModel& solved = cam.model;
  if (CoresComparable(solved.lensmodel(), real.lensmodel()) && solved.has_core() &&
      real.has_core()) {
    const auto& a = solved.intrinsics();
    const auto& b = real.intrinsics();
    const double focal = std::max(std::abs(a[0] - b[0]) / b[0], std::abs(a[1] - b[1]) / b[1]);
    const double pp = std::hypot(a[2] - b[2], a[3] - b[3]);
    result->focal_rel_err_max = std::max(result->focal_rel_err_max, focal);
    result->principal_point_err_px_max = std::max(result->principal_point_err_px_max, pp);
    (*j)["focal_rel_err"] = focal;
    (*j)["principal_point_err_px"] = pp;
  } else {
    (*j)["core_comparable"] = false;  // e.g. a splined model against a pinhole-family lens
  }
  // Geometry relative to the reference camera: gauge-free, but the reference camera's own
  // pose error is in every camera's figure.
  const Pose solved_cam_from_ref = solved.cam_from_world();
  const Pose true_cam_from_ref = real.cam_from_world() * true_world_from_ref_cam;
  const Pose delta = solved_cam_from_ref * true_cam_from_ref.inverse();
  const double rotation = RotationAngleDeg(delta.linear());
  const double translation = 1000 * (solved_cam_from_ref.inverse().translation() -
                                     true_cam_from_ref.inverse().translation())
                                        .norm();
  result->rotation_err_deg_max_from_reference =
      std::max(result->rotation_err_deg_max_from_reference, rotation);
  result->translation_err_mm_max_from_reference =
      std::max(result->translation_err_mm_max_from_reference, translation);
  (*j)["rotation_err_deg_from_reference"] = rotation;
  (*j)["translation_err_mm_from_reference"] = translation;
  // Against the rig alignment.
  const Pose aligned = true_world_from_solved * solved.world_from_cam();
  const double aligned_rotation =
      RotationAngleDeg(real.cam_from_world().linear() * aligned.linear());
  const double aligned_translation =
      1000 * (aligned.translation() - real.world_from_cam().translation()).norm();
  result->rotation_err_deg_max = std::max(result->rotation_err_deg_max, aligned_rotation);
  result->translation_err_mm_max = std::max(result->translation_err_mm_max, aligned_translation);
  (*j)["rotation_err_deg"] = aligned_rotation;
  (*j)["translation_err_mm"] = aligned_translation;
}

// Projection over the imager at the working distance, the solved point placed in the world
// through the board-anchored frame.
void CompareProjection(const CalibratedCamera& cam, const CameraModel& real,
                       const Pose& world_from_ref, GroundTruthComparison* result,
                       ProjectionTally* tally, nlohmann::json* j) {
  const CameraModel& solved = cam.model;
  Eigen::Matrix2Xd pixels = cam.uncertainty.pixels;
  int grid_x = cam.uncertainty.grid_x;
  if (grid_x == 0) {
    grid_x = 16;
    pixels.resize(2, 16 * 12);
    for (int k = 0; k < 16 * 12; ++k) {
      pixels.col(k) << ((k % 16) + 0.5) * solved.width() / 16 - 0.5,
          ((k / 16) + 0.5) * solved.height() / 12 - 0.5;
    }
  }
  const double distance = cam.uncertainty.distance_m > 0
                              ? cam.uncertainty.distance_m
                              : std::max(0.5, cam.median_board_distance_m);
  const Eigen::Matrix3Xd rays = solved.UnprojectMany(pixels);
  double cam_sum2 = 0, cam_max = 0, cam_observed_sum2 = 0;
  int cam_n = 0, cam_within = 0, cam_observed_n = 0;
  for (int k = 0; k < pixels.cols(); ++k) {
    if (!rays.col(k).allFinite()) continue;
    const Eigen::Vector3d world =
        world_from_ref * (solved.world_from_cam() * (rays.col(k) * distance));
    Eigen::Vector2d q;
    if (!real.ProjectWorld(world, &q)) continue;
    const double diff = (q - pixels.col(k)).norm();
    cam_sum2 += diff * diff;
    cam_max = std::max(cam_max, diff);
    ++cam_n;
    if (cam.uncertainty.observed.size() > 0 && cam.uncertainty.observed(k / grid_x, k % grid_x)) {
      tally->observed_sum2 += diff * diff;
      ++tally->observed_n;
      cam_observed_sum2 += diff * diff;
      ++cam_observed_n;
    }
    if (cam.uncertainty.grid_x > 0) {
      const double sigma = cam.uncertainty.worst_sigma_px(k / grid_x, k % grid_x);
      if (std::isfinite(sigma)) {
        ++tally->with_sigma;
        const bool ok = diff <= 3 * sigma;
        tally->within += ok;
        cam_within += ok;
      }
    }
  }
  tally->sum2 += cam_sum2;
  tally->samples += cam_n;
  result->projection_diff_max_px = std::max(result->projection_diff_max_px, cam_max);
  (*j)["projection_diff_rms_px"] = cam_n > 0 ? std::sqrt(cam_sum2 / cam_n) : 0.0;
  (*j)["projection_diff_max_px"] = cam_max;
  if (cam_observed_n > 0)
    (*j)["projection_diff_rms_observed_px"] = std::sqrt(cam_observed_sum2 / cam_observed_n);
  if (cam.uncertainty.grid_x > 0 && cam_n > 0) {
    (*j)["within_3sigma_fraction"] = static_cast<double>(cam_within) / cam_n;
  }
}

}  // namespace

nlohmann::json GroundTruthComparison::ToJson() const {
  return {{"focal_rel_err_max", focal_rel_err_max},
          {"principal_point_err_px_max", principal_point_err_px_max},
          {"rotation_err_deg_max", rotation_err_deg_max},
          {"translation_err_mm_max", translation_err_mm_max},
          {"rotation_err_deg_max_from_reference", rotation_err_deg_max_from_reference},
          {"translation_err_mm_max_from_reference", translation_err_mm_max_from_reference},
          {"pose_comparison",
           "each camera's pose after the rigid motion that best lays the solved rig onto the true "
           "one (rotations: chordal mean of the cameras within 3x the median distance of the "
           "medoid; positions: mean offset of those within 3x the median spread); "
           "*_from_reference: cam_from_reference against the truth, which carries the reference "
           "camera's own error into every camera"},
          {"depth_rotation_err_deg_max", depth_rotation_err_deg_max},
          {"depth_translation_err_mm_max", depth_translation_err_mm_max},
          {"world_up_err_deg", world_up_err_deg},
          {"world_floor_err_mm", world_floor_err_mm},
          {"world_comparison",
           "the written world's z axis and its floor at its origin, after the same rigid motion, "
           "against the truth's z and z = 0"},
          {"projection_diff_rms_px", projection_diff_rms_px},
          {"projection_diff_max_px", projection_diff_max_px},
          {"projection_diff_rms_observed_px", projection_diff_rms_observed_px},
          {"within_3sigma_fraction", within_3sigma_fraction},
          {"cameras", per_camera}};
}

GroundTruthComparison CompareWithTruth(const CalibrationSummary& summary,
                                       const std::map<std::string, CameraModel>& truth,
                                       const std::map<int64_t, Pose>& world_from_board,
                                       const BoardLayout& layout,
                                       const Pose& written_world_from_ref,
                                       const std::map<std::string, CameraModel>& depth_in_ref) {
  auto ref_truth = truth.find(summary.reference_camera);
  if (ref_truth == truth.end())
    Fail("no true model of reference camera ", summary.reference_camera);
  const Pose world_from_ref = calibration_internal::WorldFromReference(summary, ref_truth->second,
                                                                       world_from_board, layout);
  const Pose true_world_from_ref_cam = ref_truth->second.world_from_cam();
  const Pose true_world_from_solved = TrueWorldFromSolved(summary, truth);

  GroundTruthComparison result;
  const Pose true_from_written = true_world_from_solved * written_world_from_ref.inverse();
  result.world_up_err_deg =
      RotationAngleDeg(Eigen::Quaterniond::FromTwoVectors(true_from_written.linear().col(2),
                                                          Eigen::Vector3d::UnitZ())
                           .toRotationMatrix());
  result.world_floor_err_mm = 1000 * true_from_written.translation().z();
  ProjectionTally tally;
  for (const auto& cam : summary.cameras) {
    if (!cam.solved) continue;
    auto t = truth.find(cam.name);
    if (t == truth.end()) Fail("no true model of camera ", cam.name);
    nlohmann::json j;
    CompareCoreAndPose(cam, t->second, true_world_from_ref_cam, true_world_from_solved, &result,
                       &j);
    CompareProjection(cam, t->second, world_from_ref, &result, &tally, &j);
    result.per_camera[cam.name] = j;
  }
  for (const auto& [name, model] : depth_in_ref) {
    auto t = truth.find(name);
    if (t == truth.end()) continue;
    const Pose aligned = true_world_from_solved * model.world_from_cam();
    const double rotation =
        RotationAngleDeg(t->second.cam_from_world().linear() * aligned.linear());
    const double translation =
        1000 * (aligned.translation() - t->second.world_from_cam().translation()).norm();
    result.depth_rotation_err_deg_max = std::max(result.depth_rotation_err_deg_max, rotation);
    result.depth_translation_err_mm_max =
        std::max(result.depth_translation_err_mm_max, translation);
    result.per_camera[name] = {{"rotation_err_deg", rotation}, {"translation_err_mm", translation}};
  }
  result.projection_diff_rms_px = tally.samples > 0 ? std::sqrt(tally.sum2 / tally.samples) : 0;
  result.projection_diff_rms_observed_px =
      tally.observed_n > 0 ? std::sqrt(tally.observed_sum2 / tally.observed_n) : 0;
  result.within_3sigma_fraction =
      tally.with_sigma > 0 ? static_cast<double>(tally.within) / tally.with_sigma : 0;
  return result;
}

}  // namespace holocap
