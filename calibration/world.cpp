// The world a take's calibration is written in: z up, the floor at z = 0, metres, chosen from
// what the take shows.
#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>

#include "calibration/calibration.h"
#include "calibration/internal/common.h"
#include "core/error.h"
#include "core/take.h"
#include "core/take_plan.h"

namespace holocap::calibration_internal {
namespace {

// The world whose z is `up` (unit, in the reference camera's frame), whose floor is
// {x : up . x = floor_offset}, whose origin is `near` dropped onto the floor and whose x axis is
// `x_hint` made horizontal (or any horizontal direction when it is vertical).
Pose WorldOnFloor(const Eigen::Vector3d& up, double floor_offset, const Eigen::Vector3d& near,
                  const Eigen::Vector3d& x_hint) {
  Eigen::Vector3d x = x_hint - up.dot(x_hint) * up;
  if (x.norm() < 1e-6) x = up.unitOrthogonal();
  x.normalize();
  Pose ref_from_world = Pose::Identity();
  ref_from_world.linear().col(0) = x;
  ref_from_world.linear().col(1) = up.cross(x);
  ref_from_world.linear().col(2) = up;
  ref_from_world.translation() = near - (up.dot(near) - floor_offset) * up;
  return ref_from_world.inverse();
}

std::vector<CameraModel> TrustedCameras(const CalibrationSummary& cal) {
  std::vector<CameraModel> cameras;
  for (const auto& c : cal.cameras) {
    if (c.solved && c.flag.empty()) cameras.push_back(c.model);
  }
  return cameras;
}

Eigen::Vector3d MeanCenter(const std::vector<CameraModel>& cameras) {
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const auto& c : cameras) mean += c.center_in_world() / static_cast<double>(cameras.size());
  return mean;
}

// Where the rig looks: where the optical axes pass closest, else the cameras' mean centre.
Eigen::Vector3d LookedAt(const std::vector<CameraModel>& cameras) {
  const RigView view = ViewOfRig(cameras);
  return view.converges ? view.center : MeanCenter(cameras);
}

// (1) The board lying flat on the floor, printed side up, in frame set `set`.
TakeWorld FloorBoardWorld(const CalibrationSummary& cal, const BoardLayout& layout, int64_t set,
                          const std::string& source, const std::vector<CameraModel>& cameras) {
  auto pose = cal.ref_from_board.find(set);
  if (pose == cal.ref_from_board.end())
    Fail("frame set ", set, " (", source,
         ") should show the board on the floor, but no camera saw it there");
  const Board board(layout);
  const Eigen::Vector3d centre =
      pose->second * Eigen::Vector3d(0.5 * (board.u_min() + board.u_max()),
                                     0.5 * (board.v_min() + board.v_max()), 0);
  Eigen::Vector3d up = pose->second.linear().col(2);
  if (up.dot(MeanCenter(cameras) - centre) < 0) up = -up;
  TakeWorld world;
  world.world_from_ref = WorldOnFloor(up, up.dot(centre), centre, pose->second.linear().col(0));
  world.frame = "floor board";
  world.why = Cat("the board lies on the floor in frame set ", set, " (", source,
                  "): z along its normal towards the cameras, the origin at its centre, x along "
                  "its rows; its thickness is taken as nothing");
  return world;
}

// Up to 8 frame sets spread over the take: the board moves, the floor stays.
std::vector<std::pair<CameraModel, cv::Mat>> DepthMaps(
    const Take& take, const std::map<std::string, CameraModel>& depth_in_ref) {
  std::vector<std::pair<CameraModel, cv::Mat>> maps;
  const size_t sets = take.size(), step = std::max<size_t>(1, sets / 8);
  for (size_t set = 0; set < sets; set += step) {
    for (const auto& [name, model] : depth_in_ref) {
      if (take.entry(set).Find(name) != nullptr)
        maps.emplace_back(model, take.ReadFrame(set, name));
    }
  }
  return maps;
}

// The lowest point of the board's outline over every solved board pose, along `up`.
double LowestBoardPoint(const CalibrationSummary& cal, const BoardLayout& layout,
                        const Eigen::Vector3d& up) {
  const Board board(layout);
  double lowest = std::numeric_limits<double>::infinity();
  for (const auto& [set, ref_from_board] : cal.ref_from_board) {
    for (double u : {board.u_min(), board.u_max()}) {
      for (double v : {board.v_min(), board.v_max()})
        lowest = std::min(lowest, up.dot(ref_from_board * Eigen::Vector3d(u, v, 0)));
    }
  }
  return lowest;
}

}  // namespace

Eigen::Vector3d UpOfLevelCameras(const std::vector<CameraModel>& cameras, std::string* why) {
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  Eigen::Vector3d image_up = Eigen::Vector3d::Zero();
  for (const auto& c : cameras) {
    const Eigen::Matrix3d axes = c.world_from_cam().linear();
    scatter += axes.col(0) * axes.col(0).transpose();
    image_up -= axes.col(1);
  }
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eigen(scatter);
  const Eigen::Vector3d values = eigen.eigenvalues();
  if (image_up.norm() < 1e-9) image_up = Eigen::Vector3d::UnitZ();
  image_up.normalize();
  // Parallel x axes (cameras side by side, looking the same way) leave the up direction free
  // about them.
  if (!(values(1) > 0.05 * values(2))) {
    *why = Cat("the mean image up (-y) of ", cameras.size(),
               " cameras (their x axes are too close to parallel to say more)");
    return image_up;
  }
  Eigen::Vector3d up = eigen.eigenvectors().col(0);
  if (up.dot(image_up) < 0) up = -up;
  *why = Cat("the direction most nearly orthogonal to the x axes of ", cameras.size(),
             " cameras (level cameras), ",
             std::round(10 * std::acos(std::clamp(up.dot(image_up), -1.0, 1.0)) * 180 / M_PI) / 10,
             " degrees from their mean image up");
  return up;
}

TakeWorld ChooseTakeWorld(const Take& take, const BoardLayout& layout,
                          const CalibrationSummary& cal,
                          const std::map<std::string, CameraModel>& depth_in_ref,
                          int64_t floor_board_set) {
  const std::vector<CameraModel> cameras = TrustedCameras(cal);
  TakeWorld world;
  world.frame = "reference camera";
  world.why = "no trusted camera to place a floor by";
  if (cameras.empty()) return world;
  const std::string source =
      floor_board_set >= 0 ? "--floor-board-set" : "take metadata floor_board_set";
  if (floor_board_set < 0) floor_board_set = take.metadata().value("floor_board_set", int64_t{-1});
  if (floor_board_set >= 0) return FloorBoardWorld(cal, layout, floor_board_set, source, cameras);

  std::string up_why;
  const Eigen::Vector3d up = UpOfLevelCameras(cameras, &up_why);
  const Eigen::Vector3d near = LookedAt(cameras);
  const Eigen::Vector3d x_hint = Eigen::Vector3d::UnitZ();  // the reference camera's view
  std::string depth_why;
  if (!depth_in_ref.empty()) {
    Eigen::Vector3d normal;
    double offset = 0, tolerance = 0;
    if (FloorFromDepth(DepthMaps(take, depth_in_ref), up, &normal, &offset, &tolerance,
                       &depth_why)) {
      world.world_from_ref = WorldOnFloor(normal, offset, near, x_hint);
      world.frame = "depth floor";
      world.why =
          Cat("the floor plane seen by ", depth_in_ref.size(), " depth sensor(s) (", depth_why,
              "): z its normal, the origin under where the optical axes meet, "
              "x along the reference camera's view");
      return world;
    }
    depth_why = "; no floor in depth: " + depth_why;
  }
  if (cal.ref_from_board.empty()) {
    world.why = "no solved board pose to place a floor by";
    return world;
  }
  world.world_from_ref = WorldOnFloor(up, LowestBoardPoint(cal, layout, up), near, x_hint);
  world.frame = "cameras";
  world.why = Cat("z: ", up_why, depth_why,
                  "; the floor at the lowest board corner seen (a handheld board's lowest point: "
                  "lay the board on the floor for one frame set and pass --floor-board-set for "
                  "the true floor); the origin under where the optical axes meet, x along the "
                  "reference camera's view");
  return world;
}

}  // namespace holocap::calibration_internal
