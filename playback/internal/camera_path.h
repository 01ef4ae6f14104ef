// The camera of a view looking from `eye` at `target`: playback's orbits and camera paths.
#pragma once

#include <Eigen/Core>

#include "core/camera.h"

namespace holocap {

// A pinhole of horizontal field of view `fov_deg` at width x height, at `eye` looking at
// `target` with `up` up.
CameraModel LookAtCamera(const Eigen::Vector3d& eye, const Eigen::Vector3d& target,
                         const Eigen::Vector3d& up, double fov_deg, int width, int height);

}  // namespace holocap
