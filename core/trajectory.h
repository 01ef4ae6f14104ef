// Camera trajectories: stamped poses and the TUM RGB-D benchmark's text format.
#pragma once

#include <string>
#include <vector>

#include "core/pose.h"

namespace holocap {

// Camera trajectories in the TUM RGB-D benchmark's text format: one line per pose,
// "time_s tx ty tz qx qy qz qw" of world_from_cam, '#' starts a comment.
struct StampedPose {
  double time_s = 0;
  Pose world_from_cam = Pose::Identity();
};
std::string TumLine(double time_s, const Pose& world_from_cam);  // with its newline
// Parses TUM text; throws Error naming `where` and the line for a malformed one.
std::vector<StampedPose> ParseTum(const std::string& text, const std::string& where);

}  // namespace holocap
