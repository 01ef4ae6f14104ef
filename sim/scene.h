// The simulated world: a static studio room, an optional subject (articulated humanoid or a
// static object, each a set of rigid closed triangle meshes) and an optional calibration
// board, with their exact appearance. A Snapshot is the world frozen at one instant.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "core/board.h"
#include "core/camera.h"
#include "core/mesh.h"
#include "core/pose.h"
#include "sim/bvh.h"

namespace holocap::sim {

enum class SceneKind { kSubject, kObject, kBoard };
SceneKind SceneKindFromString(const std::string& text);  // throws Error
const char* ToString(SceneKind kind);

// Surface ids: they tell anti-aliasing where surfaces meet and masks what is the subject.
inline constexpr int kFloor = 0;
inline constexpr int kCeiling = 5;  // walls are 1..4
inline constexpr int kBoardFront = 6;
inline constexpr int kBoardBack = 7;
inline constexpr int kFirstPart = 8;  // subject part p has id kFirstPart + p

// The room: [-kRoomHalf, kRoomHalf]^2 x [0, kRoomHeight].
inline constexpr double kRoomHalf = 5.0;
inline constexpr double kRoomHeight = 3.5;

struct SurfaceHit {
  double t = 0;                                        // distance along the unit ray
  int surface = -1;                                    // see the ids above
  Eigen::Vector3d point = Eigen::Vector3d::Zero();     // world
  Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();   // world, unit, facing the ray's origin
  Eigen::Vector2d board_uv = Eigen::Vector2d::Zero();  // board coordinates on kBoardFront
  bool is_subject() const { return surface >= kFirstPart; }
};

// One rigid piece of the subject: a closed mesh in its own frame and its clothing colour.
struct Part {
  std::string name;
  Mesh mesh;  // part coordinates, counter-clockwise from outside
  Eigen::Vector3d color = Eigen::Vector3d::Zero();
  int parent = -1;
  Eigen::Vector3d joint_in_parent = Eigen::Vector3d::Zero();
};

// How light the subject and the room are: each multiplies that surface's albedo (the board
// keeps its own, so that it still calibrates).
struct Appearance {
  double subject_albedo = 1;
  double background_albedo = 1;
};

class Snapshot {
 public:
  // Nearest surface along a unit ray (every ray hits the closed room).
  SurfaceHit Trace(const Eigen::Vector3d& origin, const Eigen::Vector3d& direction) const;
  // Linear RGB radiance leaving `hit` (Lambertian, no shadows).
  Eigen::Vector3d Radiance(const SurfaceHit& hit) const;
  // Diffuse reflectance (RGB) at a hit, before lighting.
  Eigen::Vector3d Albedo(const SurfaceHit& hit) const;
  // Lighting factor for a unit normal facing the viewer.
  static double Irradiance(const Eigen::Vector3d& normal);
  // The board's front albedo for a board reflectance in [0, 1].
  static double BoardAlbedo(double reflectance) { return 0.05 + 0.8 * reflectance; }

  bool has_subject() const { return !parts_world_.empty(); }
  // The subject (all parts) in world coordinates, vertex colours = albedo at the vertex.
  const Mesh& subject_mesh() const { return mesh_; }
  const Board* board() const { return board_; }
  const Pose& world_from_board() const { return world_from_board_; }

 private:
  friend class Scene;
  Eigen::Vector3d BoardSideAlbedo(const SurfaceHit& hit) const;
  static Eigen::Vector3d RoomAlbedo(const SurfaceHit& hit);  // floor, walls, ceiling
  const std::vector<Part>* parts_ = nullptr;
  std::vector<Pose> parts_world_;  // world_from_part
  std::vector<Pose> parts_local_;  // part_from_world
  Mesh mesh_;
  std::vector<int> face_part_;
  std::vector<Eigen::Vector3d> face_normals_;
  Bvh bvh_;
  const Board* board_ = nullptr;
  Pose world_from_board_ = Pose::Identity();
  Pose board_from_world_ = Pose::Identity();
  Appearance appearance_;
};

class Scene {
 public:
  // `board_cameras` are the rig's colour cameras: the board scene plans its poses so that each
  // of them gets tilted close-ups filling its image and views shared with its neighbour.
  Scene(SceneKind kind, const BoardLayout& board, const std::vector<CameraModel>& board_cameras,
        int64_t clean_plate_frames, uint64_t seed, const Appearance& appearance = {});

  SceneKind kind() const { return kind_; }
  // The world at time `t_s` during frame set `set` (the set decides the board pose and
  // whether it is a clean plate).
  std::shared_ptr<const Snapshot> At(double t_s, int64_t set) const;
  bool IsCleanPlate(int64_t set) const { return set < clean_plate_frames_; }
  const Board* board() const { return board_ ? &*board_ : nullptr; }
  Pose WorldFromBoard(int64_t set) const;  // board scene only
  // From now on the board stays at the first pose two cameras share (the first of a single
  // camera's poses) in every frame set.
  void HoldBoardStill() { board_still_ = true; }
  // From now on this share of the single-camera board views reaches past the image's edge
  // (SimOptions::board_partial).
  void ShowBoardPartly(double share) { board_partial_ = share; }
  const std::vector<Part>& parts() const { return parts_; }
  // world_from_part of every part at `t_s` (the humanoid's walk; the object is static).
  std::vector<Pose> PartPoses(double t_s) const;
  // From now on the subject holds its pose of t = 0, moved rigidly by world_from_subject(t)
  // (a scan's still subject, or one turning on the spot).
  void HoldStill(std::function<Pose(double)> world_from_subject);
  // The subject's centre at t = 0 on the floor: the mean of its parts' origins, z = 0.
  Eigen::Vector3d CenterAtStart() const;

 private:
  std::vector<Pose> MovingPartPoses(double t_s) const;  // the walk, or the static object
  SceneKind kind_;
  bool board_still_ = false;
  double board_partial_ = 0;
  std::vector<Part> parts_;
  std::optional<Board> board_;
  std::vector<CameraModel> board_cameras_;
  int64_t clean_plate_frames_ = 0;
  uint64_t seed_ = 1;
  Appearance appearance_;
  std::function<Pose(double)> world_from_subject_;  // set: the subject holds still
};

// The humanoid's parts (15 ellipsoidal limbs, each a closed mesh) and the static object's
// (a trefoil-knot tube above a cylindrical pedestal).
std::vector<Part> MakeHumanoid();
std::vector<Part> MakeObject();

}  // namespace holocap::sim
