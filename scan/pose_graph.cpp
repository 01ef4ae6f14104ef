// The scanner's pose graph over keyframes (Ceres): relative-pose edges between consecutive
// keyframes and loop edges, the first keyframe held fixed.
#include <ceres/ceres.h>
#include <ceres/rotation.h>

#include "scan/internal/pose_graph.h"

namespace holocap::scan {
namespace {

// Residual of one edge: the measured relative pose (b seen from a) against the poses'.
struct RelativePoseError {
  RelativePoseError(const Pose& a_from_b, double weight)
      : weight_(weight), translation_(a_from_b.translation()) {
    const Eigen::Matrix3d r = a_from_b.linear();
    ceres::RotationMatrixToAngleAxis(ceres::ColumnMajorAdapter3x3(r.data()), rotation_.data());
  }

  template <typename T>
  bool operator()(const T* a, const T* b, T* residual) const {
    // Poses are world_from_cam: angle-axis (3) then translation (3).
    T ra[9], rb[9], rm[9];
    ceres::AngleAxisToRotationMatrix(a, ceres::ColumnMajorAdapter3x3(ra));
    ceres::AngleAxisToRotationMatrix(b, ceres::ColumnMajorAdapter3x3(rb));
    const T measured[3] = {T(rotation_[0]), T(rotation_[1]), T(rotation_[2])};
    ceres::AngleAxisToRotationMatrix(measured, ceres::ColumnMajorAdapter3x3(rm));
    // a_from_b = Ra^T Rb, Ra^T (tb - ta); error rotation = Rm^T (Ra^T Rb).
    T relative[9];
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) {
        relative[i + 3 * j] = T(0);
        for (int k = 0; k < 3; ++k) relative[i + 3 * j] += ra[k + 3 * i] * rb[k + 3 * j];
      }
    }
    T error[9];
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) {
        error[i + 3 * j] = T(0);
        for (int k = 0; k < 3; ++k) error[i + 3 * j] += rm[k + 3 * i] * relative[k + 3 * j];
      }
    }
    T angle_axis[3];
    const T* error_matrix = error;
    ceres::RotationMatrixToAngleAxis(ceres::ColumnMajorAdapter3x3(error_matrix), angle_axis);
    for (int i = 0; i < 3; ++i) {
      T t = T(0);
      for (int k = 0; k < 3; ++k) t += ra[k + 3 * i] * (b[3 + k] - a[3 + k]);
      residual[i] = T(weight_) * angle_axis[i];
      residual[3 + i] = T(weight_) * (t - T(translation_[i]));
    }
    return true;
  }

  double weight_;
  Eigen::Vector3d translation_;
  Eigen::Vector3d rotation_;
};

std::array<double, 6> Parameters(const Pose& pose) {
  std::array<double, 6> p{};
  const Eigen::Matrix3d r = pose.linear();
  ceres::RotationMatrixToAngleAxis(ceres::ColumnMajorAdapter3x3(r.data()), p.data());
  for (int i = 0; i < 3; ++i) p[3 + i] = pose.translation()[i];
  return p;
}

Pose FromParameters(const std::array<double, 6>& p) {
  Eigen::Matrix3d r;
  ceres::AngleAxisToRotationMatrix(p.data(), ceres::ColumnMajorAdapter3x3(r.data()));
  Pose pose = Pose::Identity();
  pose.linear() = r;
  pose.translation() = Eigen::Vector3d(p[3], p[4], p[5]);
  return pose;
}

}  // namespace

PoseGraphResult OptimizePoseGraph(const std::vector<Pose>& world_from_keyframe,
                                  const std::vector<PoseEdge>& edges, int threads) {
  PoseGraphResult result;
  result.world_from_keyframe = world_from_keyframe;
  if (world_from_keyframe.size() < 2 || edges.empty()) {
    result.message = "fewer than two keyframes or no edges: nothing to refine";
    return result;
  }
  std::vector<std::array<double, 6>> parameters;
  for (const Pose& pose : world_from_keyframe) parameters.push_back(Parameters(pose));
  ceres::Problem problem;
  for (const PoseEdge& edge : edges) {
    auto* cost = new ceres::AutoDiffCostFunction<RelativePoseError, 6, 6, 6>(
        new RelativePoseError(edge.a_from_b, edge.weight));
    problem.AddResidualBlock(cost, new ceres::HuberLoss(0.05), parameters[edge.a].data(),
                             parameters[edge.b].data());
  }
  problem.SetParameterBlockConstant(parameters.front().data());
  ceres::Solver::Options options;
  options.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
  options.max_num_iterations = 50;
  options.num_threads = std::max(1, threads);
  ceres::Solver::Summary summary;
  ceres::Solve(options, &problem, &summary);
  result.converged = summary.termination_type == ceres::CONVERGENCE;
  result.message = summary.BriefReport();
  result.initial_cost = summary.initial_cost;
  result.final_cost = summary.final_cost;
  if (!summary.IsSolutionUsable()) return result;
  for (size_t k = 0; k < parameters.size(); ++k)
    result.world_from_keyframe[k] = FromParameters(parameters[k]);
  return result;
}

}  // namespace holocap::scan
