// Rigid transforms, named target_from_source, in double precision.
#pragma once

#include <Eigen/Geometry>
#include <array>

namespace holocap {

using Pose = Eigen::Isometry3d;
using Rt = std::array<double, 6>;  // mrcal's rt: Rodrigues rotation, then translation

// mrcal rt vector <-> Isometry (rt maps source to target just as the Isometry does).
Pose PoseFromRt(const Rt& rt);
Rt RtFromPose(const Pose& pose);

// Angle of a rotation in degrees, in [0, 180].
double RotationAngleDeg(const Eigen::Matrix3d& rotation);

// cam_from_world for a camera at `eye` looking at `target`, OpenCV axes (x right, y down,
// z forward); `up` is the world's up direction (holocap worlds are z-up, floor at z = 0).
// Throws Error when eye == target or the view direction is parallel to `up`.
Pose CamFromWorldLookAt(const Eigen::Vector3d& eye, const Eigen::Vector3d& target,
                        const Eigen::Vector3d& up = Eigen::Vector3d::UnitZ());

}  // namespace holocap
