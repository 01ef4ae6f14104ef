#include "core/pose.h"

#include <Eigen/SVD>
#include <algorithm>
#include <cmath>

#include "core/error.h"

namespace holocap {

Pose PoseFromRt(const Rt& rt) {
  Eigen::Vector3d r(rt[0], rt[1], rt[2]);
  Pose pose = Pose::Identity();
  double angle = r.norm();
  if (angle > 0) pose.linear() = Eigen::AngleAxisd(angle, r / angle).toRotationMatrix();
  pose.translation() = Eigen::Vector3d(rt[3], rt[4], rt[5]);
  return pose;
}

Rt RtFromPose(const Pose& pose) {
  Eigen::AngleAxisd axis_angle(pose.linear());
  Eigen::Vector3d r = axis_angle.axis() * axis_angle.angle();
  const Eigen::Vector3d& t = pose.translation();
  return {r.x(), r.y(), r.z(), t.x(), t.y(), t.z()};
}

CheckedRotation CheckRotation(const Eigen::Matrix3d& matrix, const std::string& where,
                              double tolerance) {
  for (int row = 0; row < 3; ++row) {
    for (int col = 0; col < 3; ++col) {
      const double value = matrix(row, col);
      if (!std::isfinite(value))
        Fail(where, ": rotation entry R[", row, "][", col, "] is ", value, ", not finite");
      if (std::abs(value) > 1 + tolerance) {
        Fail(where, ": rotation entry R[", row, "][", col, "] is ", value,
             ", outside [-1, 1] where every entry of a rotation lies");
      }
    }
  }
  const double determinant = matrix.determinant();
  if (!(determinant > 0)) {
    Fail(where, ": the rotation has determinant ", determinant,
         determinant < 0 ? " (a mirror, not a rotation)" : " (degenerate, not a rotation)");
  }
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(matrix);
  CheckedRotation out;
  out.residual = (svd.singularValues().array() - 1).abs().maxCoeff();
  if (!(out.residual <= tolerance)) {
    Fail(where, ": the rotation is not orthonormal: its singular values differ from 1 by ",
         out.residual, " (at most ", tolerance, " is re-orthonormalised)");
  }
  // A matrix orthonormal to rounding is kept bit for bit.
  out.rotation = out.reorthonormalised() ? NearestRotation(matrix) : matrix;
  return out;
}

Eigen::Matrix3d NearestRotation(const Eigen::Matrix3d& matrix) {
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(matrix, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d rotation = svd.matrixU() * svd.matrixV().transpose();
  if (rotation.determinant() < 0) {
    Eigen::Matrix3d u = svd.matrixU();
    u.col(2) *= -1;
    rotation = u * svd.matrixV().transpose();
  }
  return rotation;
}

double RotationAngleDeg(const Eigen::Matrix3d& rotation) {
  // atan2 form keeps precision for tiny angles, where acos((trace-1)/2) loses it.
  Eigen::Vector3d axis_sin(rotation(2, 1) - rotation(1, 2), rotation(0, 2) - rotation(2, 0),
                           rotation(1, 0) - rotation(0, 1));
  double sin_angle = 0.5 * axis_sin.norm();
  double cos_angle = 0.5 * (rotation.trace() - 1.0);
  return std::atan2(sin_angle, cos_angle) * 180.0 / M_PI;
}

Pose CamFromWorldLookAt(const Eigen::Vector3d& eye, const Eigen::Vector3d& target,
                        const Eigen::Vector3d& up) {
  Eigen::Vector3d z = target - eye;
  if (z.norm() < 1e-12) Fail("look-at: the eye and the target coincide");
  z.normalize();
  Eigen::Vector3d x = z.cross(up);
  if (x.norm() < 1e-9) Fail("look-at: the view direction is parallel to the up direction");
  x.normalize();
  Eigen::Vector3d y = z.cross(x);  // points down in the image when `up` is up in the world
  Eigen::Matrix3d world_from_cam_rotation;
  world_from_cam_rotation.col(0) = x;
  world_from_cam_rotation.col(1) = y;
  world_from_cam_rotation.col(2) = z;
  Pose world_from_cam = Pose::Identity();
  world_from_cam.linear() = world_from_cam_rotation;
  world_from_cam.translation() = eye;
  return world_from_cam.inverse();
}

}  // namespace holocap
