// The scanner's keyframe pose graph (scan/pose_graph.cpp), kept apart so that only
// one translation unit includes Ceres.
#pragma once

#include <string>
#include <vector>

#include "core/pose.h"

namespace holocap::scan {

struct PoseEdge {
  int a = 0, b = 0;                  // keyframe indices
  Pose a_from_b = Pose::Identity();  // measured: world_from_a^-1 * world_from_b
  double weight = 1;
};

struct PoseGraphResult {
  std::vector<Pose> world_from_keyframe;
  bool converged = false;
  double initial_cost = 0, final_cost = 0;
  std::string message;
};

// Keyframe poses (world_from_cam) that best agree with the edges (Huber-robust), the first
// held fixed. Unchanged when the solve fails (said in `message`).
PoseGraphResult OptimizePoseGraph(const std::vector<Pose>& world_from_keyframe,
                                  const std::vector<PoseEdge>& edges, int threads);

}  // namespace holocap::scan
