// Laying one calibration of a rig onto another of the same rig, for measuring one against the
// other (a solve against the simulated truth, a reconstruction against true meshes). Which
// world a calibration is anchored to is a choice of gauge; what it promises is where each
// camera is and how it is turned relative to the others.
#pragma once

#include <map>
#include <string>
#include <vector>

#include "core/camera.h"
#include "core/pose.h"

namespace holocap {

// Mean of rotations (chordal L2 on quaternions) and of translations. Throws Error when empty.
Pose AveragePoses(const std::vector<Pose>& poses);

// The rigid motion to_from_from that best lays the cameras `in_from` (cam_from_world in world
// "from") onto the same cameras `in_to` (matched by name; the others are ignored): the chordal
// mean of the cameras' rotation differences, over those within 3x the median distance of the
// medoid difference (one badly solved camera must not turn the whole rig by its share of its
// error), then the mean offset of the camera centres within 3x the median spread of their
// per-axis median. Identity when the two share no camera.
Pose AlignRigs(const std::map<std::string, CameraModel>& in_from,
               const std::map<std::string, CameraModel>& in_to);

}  // namespace holocap
