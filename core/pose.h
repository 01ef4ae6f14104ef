// Rigid transforms, named target_from_source, in double precision.
#pragma once

#include <Eigen/Geometry>
#include <array>
#include <string>

namespace holocap {

using Pose = Eigen::Isometry3d;
using Rt = std::array<double, 6>;  // mrcal's rt: Rodrigues rotation, then translation

// mrcal rt vector <-> Isometry (rt maps source to target just as the Isometry does).
Pose PoseFromRt(const Rt& rt);
Rt RtFromPose(const Pose& pose);

// How far a rotation read from a file may be from orthonormal: the largest |sigma_i - 1| of its
// singular values, which is its distance (spectral norm) from the nearest rotation. Real
// calibrations print rotations to ~1e-11 (CMU Panoptic: 5.7e-11), single-precision files to
// ~1e-7, Middlebury's to 7e-7; a larger residual is a damaged or non-rigid matrix.
inline constexpr double kRotationTolerance = 1e-6;

struct CheckedRotation {
  Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();  // orthonormal, det +1
  double residual = 0;  // max |sigma_i - 1| of the matrix given; 0 when it was orthonormal
  // Whether `rotation` differs from the matrix given by more than rounding (a note is due).
  bool reorthonormalised() const { return residual > 1e-14; }
};
// A rotation from a file, checked at the boundary: every entry finite and in [-1, 1] (up to
// `tolerance`), determinant positive, residual (above) at most `tolerance`. The rotation kept
// is the nearest one (the polar factor, through the SVD). Throws Error naming `where` and the
// entry or property at fault.
CheckedRotation CheckRotation(const Eigen::Matrix3d& matrix, const std::string& where,
                              double tolerance = kRotationTolerance);

// The rotation nearest to `matrix` (Frobenius norm; det +1), through the SVD.
Eigen::Matrix3d NearestRotation(const Eigen::Matrix3d& matrix);

// Angle of a rotation in degrees, in [0, 180].
double RotationAngleDeg(const Eigen::Matrix3d& rotation);

// cam_from_world for a camera at `eye` looking at `target`, OpenCV axes (x right, y down,
// z forward); `up` is the world's up direction (holocap worlds are z-up, floor at z = 0).
// Throws Error when eye == target or the view direction is parallel to `up`.
Pose CamFromWorldLookAt(const Eigen::Vector3d& eye, const Eigen::Vector3d& target,
                        const Eigen::Vector3d& up = Eigen::Vector3d::UnitZ());

}  // namespace holocap
