// Helpers shared by the calibration sources (not part of the public interface).
#pragma once

#include <Eigen/Core>
#include <Eigen/SparseCore>
#include <algorithm>
#include <cstddef>
#include <functional>
#include <limits>
#include <map>
#include <opencv2/core.hpp>
#include <string>
#include <thread>
#include <vector>

#include "calibration/calibration.h"
#include "core/pose.h"
#include "core/report.h"
#include "core/rig_alignment.h"
#include "core/threads.h"

namespace holocap::calibration_internal {

// The rigid transform b_from_a minimising sum |b - T a|² (Kabsch/Umeyama without scale).
Pose FitRigid(const std::vector<Eigen::Vector3d>& a, const std::vector<Eigen::Vector3d>& b);

// A board's grid numbered after turning it by `quarter_turns` x 90 degrees in its own plane
// (2: numbered from the opposite end; 1 and 3 only for a square grid): order[r] is the index,
// in the grid's own numbering, of the point the turned numbering gives index r.
std::vector<int> TurnedGridOrder(int width_n, int height_n, int quarter_turns);

// The turns (in quarter turns, 0 first) that map a board onto itself as a detector sees it once
// its own asymmetry is used: {0} for AprilTag boards and chessboards whose width_n + height_n is
// odd (their corner squares' colours tell the ends apart), {0, 2} for other non-square
// chessboards and square ones with an odd side (a quarter turn changes the corner colour),
// {0, 1, 2, 3} for square chessboards with an even side.
std::vector<int> AmbiguousBoardTurns(const BoardLayout& layout);

// One image of a take to look at: the frame set's position in the take and the sensor.
struct ViewJob {
  size_t set = 0;
  std::string sensor;
};

// Every image the take holds of `sensors`, frame set by frame set, sensors in the given order.
std::vector<ViewJob> ViewJobs(const Take& take, const std::vector<std::string>& sensors);

// Runs work(k) for every k < `count` on `threads` threads (0: all cores), each k once. An Error
// thrown by work stops nothing else; the first one is thrown again once every thread is done.
void RunViewJobs(size_t count, int threads, const std::function<void(size_t)>& work);

// Throws Error unless mrcal knows the (configured) lens model name.
void CheckLensmodelName(const std::string& name);

// Refines `corner` in an 8-bit grey image from the straight edges that leave it along `rays`:
// 2 rays for the L corner of a dark or light square (a tag's), 4 for a chessboard's X
// junction (rays k and k + 2 opposite). Each edge is measured up to `reach_in_px` to its side
// facing the first two rays' wedge and `reach_out_px` to the other, where the image must be
// uniform, and up to `length_px` along it, where it must be straight and alone. False (corner
// unchanged) when the edges cannot be measured or the result moves beyond the reach.
bool RefineEdgeCorner(const cv::Mat& grey, const std::vector<Eigen::Vector2d>& rays,
                      double reach_in_px, double reach_out_px, double length_px,
                      Eigen::Vector2d* corner);

// How a least-squares solve ended, judged at its result.
struct SolverEnd {
  Termination termination = Termination::kFailure;
  double cost = std::numeric_limits<double>::quiet_NaN();               // |x|^2
  double expected_decrease = std::numeric_limits<double>::quiet_NaN();  // share of the cost
  bool IsUsable() const { return holocap::IsUsable(termination); }
};

// The share of the cost one more step may still remove at convergence (Ceres' default
// function_tolerance).
inline constexpr double kCostTolerance = 1e-6;

// The ending of a solve whose residuals are `x` and Jacobian transposed `jt` (Nstate x
// Nmeasurements; empty: not judged) at its result, `rms_px` its reported RMS: FAILURE when the
// RMS is negative (mrcal's failure) or anything is NaN; NO_CONVERGENCE when one more
// Gauss-Newton step would remove more than kCostTolerance of the cost; else CONVERGENCE.
SolverEnd JudgeSolverEnd(const Eigen::SparseMatrix<double>& jt, const Eigen::VectorXd& x,
                         double rms_px);

// The solved reference frame in the world: the rigid fit of the solved board poses to the true
// ones (`from_boards` true) when they are known, otherwise the reference camera's true pose.
Pose WorldFromReference(const CalibrationSummary& summary, const CameraModel& reference_truth,
                        const std::map<int64_t, Pose>& world_from_board, const BoardLayout& layout,
                        bool* from_boards = nullptr);

// The world the written models live in: world_from_ref carries the reference camera's frame
// (the solve's) into it.
struct TakeWorld {
  Pose world_from_ref = Pose::Identity();
  std::string frame;  // "floor board", "depth floor", "cameras" or "reference camera"
  std::string why;    // one line for the report's plan
};

// The up direction of cameras mounted level (no roll): the direction most nearly orthogonal to
// all their x axes, signed by their mean image up (-y); that mean itself when the x axes are
// too close to parallel to fix it. `why` says which.
Eigen::Vector3d UpOfLevelCameras(const std::vector<CameraModel>& cameras, std::string* why);

// The world of a take's calibration (z up, the floor at z = 0, metres), from the first the take
// shows of: (1) the board lying on the floor in frame set `floor_board_set` (-1: the take's
// metadata "floor_board_set", else none); (2) the floor plane the depth sensors `depth_in_ref`
// (models in the reference camera's frame) see in up to 8 sets spread over the take, within 30
// degrees of (3)'s up; (3) the level cameras' up (UpOfLevelCameras) with the floor at the
// lowest board corner seen. The origin lies under where the optical axes meet (the board's
// centre in (1)). Throws Error when `floor_board_set` shows no solved board pose.
TakeWorld ChooseTakeWorld(const Take& take, const BoardLayout& layout,
                          const CalibrationSummary& cal,
                          const std::map<std::string, CameraModel>& depth_in_ref,
                          int64_t floor_board_set);

}  // namespace holocap::calibration_internal

namespace holocap {}
