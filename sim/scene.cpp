#include "sim/scene.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <random>

#include "core/error.h"

namespace holocap::sim {
namespace {

constexpr double kPi = std::numbers::pi;
constexpr double kDeg = kPi / 180;

// ---------------------------------------------------------------------------------------------
// Procedural texture: value noise on a hashed integer lattice, smooth between lattice points,
// so it has detail at a chosen scale without aliasing below it.

uint32_t Hash(int x, int y, int z, uint32_t seed) {
  uint32_t h = seed * 0x9E3779B1u;
  h ^= static_cast<uint32_t>(x) * 0x85EBCA77u;
  h = (h << 13) | (h >> 19);
  h ^= static_cast<uint32_t>(y) * 0xC2B2AE3Du;
  h = (h << 17) | (h >> 15);
  h ^= static_cast<uint32_t>(z) * 0x27D4EB2Fu;
  h ^= h >> 15;
  h *= 0x2C1B3C6Du;
  h ^= h >> 12;
  h *= 0x297A2D39u;
  h ^= h >> 15;
  return h;
}

double Lattice(int x, int y, int z, uint32_t seed) {
  return Hash(x, y, z, seed) * (1.0 / 4294967296.0);
}

double ValueNoise(const Eigen::Vector3d& p, uint32_t seed) {
  const double fx = std::floor(p.x()), fy = std::floor(p.y()), fz = std::floor(p.z());
  const int x = static_cast<int>(fx), y = static_cast<int>(fy), z = static_cast<int>(fz);
  auto smooth = [](double t) { return t * t * (3 - 2 * t); };
  const double u = smooth(p.x() - fx), v = smooth(p.y() - fy), w = smooth(p.z() - fz);
  auto lerp = [](double a, double b, double t) { return a + (b - a) * t; };
  const double c00 = lerp(Lattice(x, y, z, seed), Lattice(x + 1, y, z, seed), u);
  const double c10 = lerp(Lattice(x, y + 1, z, seed), Lattice(x + 1, y + 1, z, seed), u);
  const double c01 = lerp(Lattice(x, y, z + 1, seed), Lattice(x + 1, y, z + 1, seed), u);
  const double c11 = lerp(Lattice(x, y + 1, z + 1, seed), Lattice(x + 1, y + 1, z + 1, seed), u);
  return lerp(lerp(c00, c10, v), lerp(c01, c11, v), w);
}

// Texture in [0, 1] with features of ~1/frequency metres and half as large.
double Detail(const Eigen::Vector3d& p, double frequency, uint32_t seed) {
  return 0.6 * ValueNoise(p * frequency, seed) + 0.4 * ValueNoise(p * (2.3 * frequency), seed + 7);
}

// ---------------------------------------------------------------------------------------------
// Closed meshes.

// A surface of revolution about z, from a top pole through `rings` (radius, z) to a bottom
// pole, scaled by (sx, sy) across: closed, counter-clockwise from outside.
Mesh Lathe(double z_top, const std::vector<Eigen::Vector2d>& rings, double z_bottom, int segments,
           double sx = 1, double sy = 1) {
  Mesh mesh;
  mesh.vertices.emplace_back(0, 0, z_top);
  for (const Eigen::Vector2d& ring : rings) {
    for (int j = 0; j < segments; ++j) {
      const double a = 2 * kPi * j / segments;
      mesh.vertices.emplace_back(sx * ring.x() * std::cos(a), sy * ring.x() * std::sin(a),
                                 ring.y());
    }
  }
  mesh.vertices.emplace_back(0, 0, z_bottom);
  const int bottom = static_cast<int>(mesh.vertices.size()) - 1;
  auto at = [&](int ring, int j) { return 1 + ring * segments + (j % segments); };
  for (int j = 0; j < segments; ++j) mesh.faces.emplace_back(0, at(0, j), at(0, j + 1));
  for (int r = 0; r + 1 < static_cast<int>(rings.size()); ++r) {
    for (int j = 0; j < segments; ++j) {
      mesh.faces.emplace_back(at(r, j), at(r + 1, j), at(r + 1, j + 1));
      mesh.faces.emplace_back(at(r, j), at(r + 1, j + 1), at(r, j + 1));
    }
  }
  const int last = static_cast<int>(rings.size()) - 1;
  for (int j = 0; j < segments; ++j) mesh.faces.emplace_back(at(last, j), bottom, at(last, j + 1));
  return mesh;
}

// A superellipsoid-like limb: semi-axes `semi` about `center`; `power` < 1 squares it off.
Mesh Ellipsoid(const Eigen::Vector3d& center, const Eigen::Vector3d& semi, double power = 1,
               int rings = 15, int segments = 24) {
  std::vector<Eigen::Vector2d> profile;
  auto signed_pow = [](double v, double e) { return std::copysign(std::pow(std::abs(v), e), v); };
  for (int r = 1; r <= rings; ++r) {
    const double theta = kPi * r / (rings + 1);
    profile.emplace_back(signed_pow(std::sin(theta), power), signed_pow(std::cos(theta), power));
  }
  for (Eigen::Vector2d& p : profile) p.y() *= semi.z();
  Mesh mesh = Lathe(semi.z(), profile, -semi.z(), segments, semi.x(), semi.y());
  for (Eigen::Vector3f& v : mesh.vertices) v += center.cast<float>();
  return mesh;
}

// A tube of radius `radius` around the closed trefoil knot, scaled by `scale`.
Mesh KnotTube(double scale, double radius, int along, int around) {
  auto curve = [&](double s) -> Eigen::Vector3d {
    return Eigen::Vector3d(std::sin(s) + 2 * std::sin(2 * s), std::cos(s) - 2 * std::cos(2 * s),
                           -std::sin(3 * s)) *
           scale;
  };
  Mesh mesh;
  for (int i = 0; i < along; ++i) {
    const double s = 2 * kPi * i / along;
    const Eigen::Vector3d c = curve(s);
    const Eigen::Vector3d tangent = (curve(s + 1e-4) - curve(s - 1e-4)).normalized();
    const Eigen::Vector3d n = tangent.cross(Eigen::Vector3d::UnitZ()).normalized();
    const Eigen::Vector3d b = tangent.cross(n);
    for (int j = 0; j < around; ++j) {
      const double a = 2 * kPi * j / around;
      mesh.vertices.push_back((c + radius * (std::cos(a) * n + std::sin(a) * b)).cast<float>());
    }
  }
  auto at = [&](int i, int j) { return (i % along) * around + (j % around); };
  for (int i = 0; i < along; ++i) {
    for (int j = 0; j < around; ++j) {
      mesh.faces.emplace_back(at(i, j), at(i, j + 1), at(i + 1, j + 1));
      mesh.faces.emplace_back(at(i, j), at(i + 1, j + 1), at(i + 1, j));
    }
  }
  return mesh;
}

Eigen::Matrix3d RotX(double a) { return Eigen::AngleAxisd(a, Eigen::Vector3d::UnitX()).matrix(); }
Eigen::Matrix3d RotY(double a) { return Eigen::AngleAxisd(a, Eigen::Vector3d::UnitY()).matrix(); }
Eigen::Matrix3d RotZ(double a) { return Eigen::AngleAxisd(a, Eigen::Vector3d::UnitZ()).matrix(); }

Pose MakePose(const Eigen::Matrix3d& rotation, const Eigen::Vector3d& translation) {
  Pose pose = Pose::Identity();
  pose.linear() = rotation;
  pose.translation() = translation;
  return pose;
}

// Humanoid part indices (body frame: x forward, y left, z up).
enum HumanoidPart {
  kPelvis,
  kTorso,
  kHead,
  kUpperArmL,
  kForearmL,
  kHandL,
  kUpperArmR,
  kForearmR,
  kHandR,
  kThighL,
  kShinL,
  kFootL,
  kThighR,
  kShinR,
  kFootR,
  kPartCount
};

// Walking speed around a circle of this radius about the stage centre.
constexpr double kWalkRadius = 0.5;
constexpr double kWalkAngularSpeed = 0.8;  // rad/s: 0.4 m/s
constexpr double kStepFrequency = 0.8;     // gait cycles per second

// ---------------------------------------------------------------------------------------------
// Board poses. The sequence visits each colour camera in turn, in rounds of three: a tilted
// close-up that fills much of that camera's imager (a 3x3 pattern of aim points, so that over
// the sequence boards reach every corner), then two views shared with its next neighbour, which
// link the cameras and give each camera more views. A pose counts only if every camera it is
// meant for sees the whole board with tags large enough to decode.

Eigen::Vector3d BoardCenter(const Board& board) {
  return Eigen::Vector3d(0.5 * (board.u_min() + board.u_max()),
                         0.5 * (board.v_min() + board.v_max()), 0);
}

// Whether the board's four outer corners lie in the room, 5 cm clear of its floor, ceiling and
// walls.
bool OutlineInsideRoom(const Board& board, const Pose& world_from_board) {
  for (const double u : {board.u_min(), board.u_max()}) {
    for (const double v : {board.v_min(), board.v_max()}) {
      const Eigen::Vector3d p = world_from_board * Eigen::Vector3d(u, v, 0);
      if (p.z() < 0.05 || p.z() > kRoomHeight - 0.05 || std::abs(p.x()) > kRoomHalf - 0.05 ||
          std::abs(p.y()) > kRoomHalf - 0.05) {
        return false;
      }
    }
  }
  return true;
}

// Smallest tag (square) side the board shows any of `viewers`, in pixels; 0 when a viewer does not
// see the whole board in its image or the board leaves the room.
double BoardPoseScore(const Board& board, const Pose& world_from_board,
                      const std::vector<const CameraModel*>& viewers) {
  const double corners[4][2] = {{board.u_min(), board.v_min()},
                                {board.u_max(), board.v_min()},
                                {board.u_min(), board.v_max()},
                                {board.u_max(), board.v_max()}};
  if (!OutlineInsideRoom(board, world_from_board)) return 0;
  double smallest = std::numeric_limits<double>::infinity();
  for (const CameraModel* camera : viewers) {
    for (const auto& c : corners) {
      const Eigen::Vector3d p = world_from_board * Eigen::Vector3d(c[0], c[1], 0);
      Eigen::Vector2d pixel;
      if ((camera->cam_from_world() * p).z() < 0.15 || !camera->ProjectWorld(p, &pixel) ||
          !camera->InImage(pixel, 2)) {
        return 0;
      }
    }
    // A tag's (square's) side at the board's four outer grid points, both ways.
    const int step = board.layout().feature_steps();
    for (int j : {0, board.height_n() - 1}) {
      for (int i : {0, board.width_n() - 1}) {
        const Eigen::Vector3d p = world_from_board * board.GridPoint(i, j);
        const Eigen::Vector3d pu = world_from_board * board.GridPoint(i == 0 ? step : i - step, j);
        const Eigen::Vector3d pv = world_from_board * board.GridPoint(i, j == 0 ? step : j - step);
        Eigen::Vector2d q, qu, qv;
        if (!camera->ProjectWorld(p, &q) || !camera->ProjectWorld(pu, &qu) ||
            !camera->ProjectWorld(pv, &qv)) {
          return 0;
        }
        smallest = std::min({smallest, (qu - q).norm(), (qv - q).norm()});
      }
    }
  }
  return std::isfinite(smallest) ? smallest : 0;
}

// A pose's score for a view meant to show the board partly: the smallest tag (square) side, from
// the grid spacing among the grid points `camera` sees in its image, when 35-85 % of them are
// there (the others beyond the image's edge), the board in front of the camera and inside the
// room; 0 otherwise.
double PartialBoardPoseScore(const Board& board, const Pose& world_from_board,
                             const CameraModel& camera) {
  if (!OutlineInsideRoom(board, world_from_board)) return 0;
  for (const double u : {board.u_min(), board.u_max()}) {
    for (const double v : {board.v_min(), board.v_max()}) {
      if ((camera.cam_from_world() * world_from_board * Eigen::Vector3d(u, v, 0)).z() < 0.15)
        return 0;
    }
  }
  const int width_n = board.width_n(), height_n = board.height_n();
  std::vector<Eigen::Vector2d> pixels(static_cast<size_t>(width_n) * height_n);
  std::vector<bool> inside(pixels.size(), false);
  int seen = 0;
  for (int j = 0; j < height_n; ++j) {
    for (int i = 0; i < width_n; ++i) {
      const size_t k = static_cast<size_t>(j) * width_n + i;
      inside[k] = camera.ProjectWorld(world_from_board * board.GridPoint(i, j), &pixels[k]) &&
                  camera.InImage(pixels[k], 2);
      seen += inside[k] ? 1 : 0;
    }
  }
  const double share = static_cast<double>(seen) / static_cast<double>(pixels.size());
  if (share < 0.35 || share > 0.85) return 0;
  double smallest = std::numeric_limits<double>::infinity();
  for (int j = 0; j < height_n; ++j) {
    for (int i = 0; i < width_n; ++i) {
      const size_t k = static_cast<size_t>(j) * width_n + i;
      if (!inside[k]) continue;
      if (i + 1 < width_n && inside[k + 1])
        smallest = std::min(smallest, (pixels[k + 1] - pixels[k]).norm());
      if (j + 1 < height_n && inside[k + width_n])
        smallest = std::min(smallest, (pixels[k + width_n] - pixels[k]).norm());
    }
  }
  return std::isfinite(smallest) ? smallest * board.layout().feature_steps() : 0;
}

// Radians per pixel near the image centre.
double AnglePerPixel(const CameraModel& camera) {
  const double cx = 0.5 * (camera.width() - 1), cy = 0.5 * (camera.height() - 1);
  const Eigen::Vector3d a = camera.Unproject({cx - 5, cy});
  const Eigen::Vector3d b = camera.Unproject({cx + 5, cy});
  return std::acos(std::clamp(a.dot(b), -1.0, 1.0)) / 10;
}

Pose PlanBoardPose(const Board& board, const std::vector<CameraModel>& cameras, int64_t set,
                   uint64_t seed, double partial_share) {
  std::mt19937_64 rng(seed * 0x9E3779B97F4A7C15ull + static_cast<uint64_t>(set) * 7919 + 17);
  std::uniform_real_distribution<double> unit(0, 1);
  const int n = static_cast<int>(cameras.size());
  const int64_t round = set / std::max(n, 1);
  const int c = static_cast<int>(set % std::max(n, 1));
  const bool shared = n > 1 && round % 3 != 0;
  const CameraModel& camera = cameras[c];
  const CameraModel& neighbour = cameras[(c + 1) % std::max(n, 1)];
  const double board_width = board.u_max() - board.u_min();
  const Eigen::Vector3d board_center = BoardCenter(board);
  // Tags need about 12 px to decode.
  const double min_spacing_px = 14;
  std::vector<const CameraModel*> viewers = {&camera};
  if (shared) viewers.push_back(&neighbour);
  // Partial views draw from their own generator, so that a take without them keeps its poses.
  std::mt19937_64 partial_rng(seed * 0xD1B54A32D192ED03ull + static_cast<uint64_t>(set) * 104729 +
                              3);
  const bool partial = !shared && partial_share > 0 && unit(partial_rng) < partial_share;

  Pose best = Pose::Identity();
  double best_score = 0;
  for (int attempt = 0; attempt < 300; ++attempt) {
    const double tilt_scale = attempt < 150 ? 1.0 : 0.5;
    Eigen::Vector3d viewpoint, center;
    double max_tilt;
    if (shared) {
      // On the way from the stage to the point between the two cameras; the closer, the larger
      // the tags, until the board leaves one of the two views.
      viewpoint = 0.5 * (camera.center_in_world() + neighbour.center_in_world());
      const Eigen::Vector3d stage(0, 0, 1.0);
      center = stage + (0.25 + 0.7 * unit(rng)) * (viewpoint - stage);
      center.z() = 0.8 + 0.8 * unit(rng);
      max_tilt = 25 * kDeg;
    } else {
      // Fraction of the image the board spans, across or down, whichever binds first.
      const double fill = 0.45 + 0.4 * unit(rng);
      const double board_height = board.v_max() - board.v_min();
      const double span_px =
          std::min<double>(camera.width(), camera.height() * board_width / board_height);
      const double distance = board_width / (fill * span_px * AnglePerPixel(camera));
      // The board's centre goes where the whole board still fits: the 3x3 cells divide the
      // range of centres, so the outer cells put the board against the imager's edges.
      const double half_x = 0.5 * fill * span_px, half_y = half_x * board_height / board_width;
      const double range_x = std::max(0.0, camera.width() - 2 * half_x);
      const double range_y = std::max(0.0, camera.height() - 2 * half_y);
      const int cell = static_cast<int>((round / 3) % 9);
      const int gx = cell % 3, gy = cell / 3;
      Eigen::Vector2d aim(half_x + (gx + 0.2 + 0.6 * unit(rng)) / 3 * range_x - 0.5,
                          half_y + (gy + 0.2 + 0.6 * unit(rng)) / 3 * range_y - 0.5);
      if (partial) {
        // The board's centre on or just inside one of the image's four edges (a random point
        // along it): about half of the board, up to a third more, lies beyond that edge.
        const int edge = static_cast<int>(4 * unit(partial_rng)) % 4;
        const double along = 0.15 + 0.7 * unit(partial_rng);
        const double inward = 0.3 * unit(partial_rng);
        const double w = camera.width() - 1.0, h = camera.height() - 1.0;
        aim = edge == 0   ? Eigen::Vector2d(inward * half_x, along * h)
              : edge == 1 ? Eigen::Vector2d(w - inward * half_x, along * h)
              : edge == 2 ? Eigen::Vector2d(along * w, inward * half_y)
                          : Eigen::Vector2d(along * w, h - inward * half_y);
      }
      viewpoint = camera.center_in_world();
      const Eigen::Vector3d ray_in_world = camera.world_from_cam().linear() * camera.Unproject(aim);
      center = viewpoint + distance * ray_in_world;
      max_tilt = 45 * kDeg;
    }
    // A view straight up or down has no upright (two cameras facing each other across the stage
    // put the point between them above it): the attempt is skipped.
    const Eigen::Vector3d view = center - viewpoint;
    if (view.norm() < 1e-3 || view.normalized().cross(Eigen::Vector3d::UnitZ()).norm() < 1e-3)
      continue;
    const Pose upright = CamFromWorldLookAt(viewpoint, center).inverse();
    const double tilt = tilt_scale * (0.25 + 0.75 * unit(rng)) * max_tilt;
    const double axis_angle = 2 * kPi * unit(rng);
    const Eigen::Vector3d axis =
        upright.linear() * Eigen::Vector3d(std::cos(axis_angle), std::sin(axis_angle), 0);
    const double roll = (2 * unit(rng) - 1) * 25 * kDeg;
    const Eigen::Matrix3d rotation =
        Eigen::AngleAxisd(tilt, axis).matrix() * upright.linear() * RotZ(roll);
    Pose world_from_board = MakePose(rotation, center - rotation * board_center);
    const double score = partial ? PartialBoardPoseScore(board, world_from_board, camera)
                                 : BoardPoseScore(board, world_from_board, viewers);
    if (score >= min_spacing_px) return world_from_board;
    if (score > best_score) {
      best_score = score;
      best = world_from_board;
    }
  }
  if (best_score > 0) return best;
  // Fall back to a frontal view in front of the camera, which is always usable.
  const Eigen::Vector3d center =
      camera.center_in_world() + 1.5 * board_width * (camera.world_from_cam().linear().col(2));
  const Pose upright = CamFromWorldLookAt(camera.center_in_world(), center).inverse();
  return MakePose(upright.linear(), center - upright.linear() * board_center);
}

}  // namespace

SceneKind SceneKindFromString(const std::string& text) {
  if (text == "subject") return SceneKind::kSubject;
  if (text == "object") return SceneKind::kObject;
  if (text == "board") return SceneKind::kBoard;
  Fail("unknown scene '", text, "' (known: subject, object, board)");
}

const char* ToString(SceneKind kind) {
  switch (kind) {
    case SceneKind::kSubject:
      return "subject";
    case SceneKind::kObject:
      return "object";
    case SceneKind::kBoard:
      return "board";
  }
  return "?";
}

std::vector<Part> MakeHumanoid() {
  std::vector<Part> parts(kPartCount);
  const Eigen::Vector3d shirt(0.75, 0.25, 0.2), trousers(0.2, 0.3, 0.6), skin(0.85, 0.65, 0.5),
      shoes(0.25, 0.2, 0.15), hair(0.35, 0.25, 0.15);
  auto set = [&](int index, const char* name, int parent, const Eigen::Vector3d& joint, Mesh mesh,
                 const Eigen::Vector3d& color) {
    parts[index] = {name, std::move(mesh), color, parent, joint};
  };
  set(kPelvis, "pelvis", -1, {0, 0, 0}, Ellipsoid({0, 0, 0}, {0.11, 0.17, 0.11}), trousers);
  set(kTorso, "torso", kPelvis, {0, 0, 0.06}, Ellipsoid({0, 0, 0.25}, {0.12, 0.19, 0.27}, 0.8),
      shirt);
  set(kHead, "head", kTorso, {0, 0, 0.52}, Ellipsoid({0.01, 0, 0.12}, {0.105, 0.09, 0.125}),
      0.5 * (skin + hair));
  for (int side = 0; side < 2; ++side) {
    const double y = side == 0 ? 1 : -1;
    const int base = side == 0 ? kUpperArmL : kUpperArmR;
    const std::string suffix = side == 0 ? "_l" : "_r";
    set(base, ("upper_arm" + suffix).c_str(), kTorso, {0, 0.235 * y, 0.45},
        Ellipsoid({0, 0, -0.15}, {0.05, 0.05, 0.17}), shirt);
    set(base + 1, ("forearm" + suffix).c_str(), base, {0, 0, -0.30},
        Ellipsoid({0, 0, -0.13}, {0.042, 0.042, 0.15}), skin);
    set(base + 2, ("hand" + suffix).c_str(), base + 1, {0, 0, -0.27},
        Ellipsoid({0, 0, -0.07}, {0.03, 0.045, 0.08}), skin);
    const int leg = side == 0 ? kThighL : kThighR;
    set(leg, ("thigh" + suffix).c_str(), kPelvis, {0, 0.09 * y, -0.05},
        Ellipsoid({0, 0, -0.21}, {0.075, 0.075, 0.24}), trousers);
    set(leg + 1, ("shin" + suffix).c_str(), leg, {0, 0, -0.43},
        Ellipsoid({0, 0, -0.21}, {0.055, 0.055, 0.23}), trousers);
    set(leg + 2, ("foot" + suffix).c_str(), leg + 1, {0, 0, -0.43},
        Ellipsoid({0.06, 0, -0.035}, {0.12, 0.05, 0.04}), shoes);
  }
  return parts;
}

std::vector<Part> MakeObject() {
  std::vector<Part> parts;
  Part knot;
  knot.name = "knot";
  knot.mesh = KnotTube(0.11, 0.07, 240, 24);
  knot.color = Eigen::Vector3d(0.8, 0.55, 0.2);
  knot.joint_in_parent = Eigen::Vector3d(0, 0, 1.05);
  parts.push_back(std::move(knot));
  Part pedestal;
  pedestal.name = "pedestal";
  pedestal.mesh = Lathe(0.55, {Eigen::Vector2d(0.25, 0.55), Eigen::Vector2d(0.25, 0.0)}, 0.0, 48);
  pedestal.color = Eigen::Vector3d(0.55, 0.6, 0.65);
  parts.push_back(std::move(pedestal));
  return parts;
}

Scene::Scene(SceneKind kind, const BoardLayout& board,
             const std::vector<CameraModel>& board_cameras, int64_t clean_plate_frames,
             uint64_t seed, const Appearance& appearance)
    : kind_(kind),
      board_cameras_(board_cameras),
      clean_plate_frames_(clean_plate_frames),
      seed_(seed),
      appearance_(appearance) {
  if (kind == SceneKind::kSubject) parts_ = MakeHumanoid();
  if (kind == SceneKind::kObject) parts_ = MakeObject();
  if (kind == SceneKind::kBoard) {
    if (board_cameras_.empty()) Fail("the board scene needs at least one colour camera");
    board_.emplace(board);
  }
}

Pose Scene::WorldFromBoard(int64_t set) const {
  if (!board_) Fail("scene '", ToString(kind_), "' has no board");
  // The sequence's first shared view is the first set of its second round.
  const auto cameras = static_cast<int64_t>(board_cameras_.size());
  const int64_t planned = !board_still_ ? set : cameras > 1 ? cameras : 0;
  return PlanBoardPose(*board_, board_cameras_, planned, seed_, board_partial_);
}

void Scene::HoldStill(std::function<Pose(double)> world_from_subject) {
  world_from_subject_ = std::move(world_from_subject);
}

Eigen::Vector3d Scene::CenterAtStart() const {
  Eigen::Vector3d center = Eigen::Vector3d::Zero();
  if (kind_ == SceneKind::kBoard || parts_.empty()) return center;
  const std::vector<Pose> poses = MovingPartPoses(0);
  for (const Pose& pose : poses) center += pose.translation();
  center /= static_cast<double>(poses.size());
  center.z() = 0;
  return center;
}

std::vector<Pose> Scene::PartPoses(double t_s) const {
  if (world_from_subject_) {
    std::vector<Pose> poses = MovingPartPoses(0);
    const Pose motion = world_from_subject_(t_s);
    for (Pose& pose : poses) pose = motion * pose;
    return poses;
  }
  return MovingPartPoses(t_s);
}

std::vector<Pose> Scene::MovingPartPoses(double t_s) const {
  std::vector<Pose> poses(parts_.size(), Pose::Identity());
  if (kind_ == SceneKind::kObject) {
    for (size_t p = 0; p < parts_.size(); ++p) {
      poses[p] = MakePose(RotZ(0.3 * static_cast<double>(p == 0)), parts_[p].joint_in_parent);
    }
    return poses;
  }
  if (kind_ != SceneKind::kSubject) return poses;

  const double phase = 2 * kPi * kStepFrequency * t_s;
  const double s = std::sin(phase);
  std::vector<Eigen::Matrix3d> joint(kPartCount, Eigen::Matrix3d::Identity());
  joint[kTorso] = RotZ(6 * kDeg * s) * RotY(3 * kDeg);
  joint[kHead] = RotY(4 * kDeg * std::sin(2 * phase)) * RotZ(-5 * kDeg * s);
  for (int side = 0; side < 2; ++side) {
    const double sign = side == 0 ? 1 : -1;
    const double leg_phase = side == 0 ? phase : phase + kPi;
    const double hip = 25 * kDeg * std::sin(leg_phase);
    const double swing = std::max(0.0, std::cos(leg_phase));
    const double knee = 8 * kDeg + 40 * kDeg * swing * swing;
    const double ankle = hip - knee + 5 * kDeg * std::sin(leg_phase);
    const int leg = side == 0 ? kThighL : kThighR;
    joint[leg] = RotY(-hip);
    joint[leg + 1] = RotY(knee);
    joint[leg + 2] = RotY(ankle);
    const int arm = side == 0 ? kUpperArmL : kUpperArmR;
    const double shoulder = -20 * kDeg * std::sin(leg_phase);
    joint[arm] = RotX(-sign * 9 * kDeg) * RotY(-shoulder);
    joint[arm + 1] = RotY(-(15 * kDeg + 10 * kDeg * (1 + std::sin(leg_phase))));
    joint[arm + 2] = RotX(sign * 5 * kDeg);
  }
  const double walk = kWalkAngularSpeed * t_s;
  const Eigen::Vector3d root(kWalkRadius * std::cos(walk), kWalkRadius * std::sin(walk), 1.0);
  poses[kPelvis] = MakePose(RotZ(walk + kPi / 2) * RotY(2 * kDeg * std::sin(2 * phase)), root);
  for (int p = 1; p < kPartCount; ++p) {
    const Part& part = parts_[p];
    poses[p] = poses[part.parent] * MakePose(joint[p], part.joint_in_parent);
  }
  // Stand on the floor: lift or lower the whole body so that its lowest point touches z = 0.
  double lowest = std::numeric_limits<double>::max();
  for (int p = 0; p < kPartCount; ++p) {
    for (const Eigen::Vector3f& v : parts_[p].mesh.vertices) {
      lowest = std::min(lowest, (poses[p] * v.cast<double>()).z());
    }
  }
  for (Pose& pose : poses) pose.translation().z() -= lowest - 1e-3;
  return poses;
}

std::shared_ptr<const Snapshot> Scene::At(double t_s, int64_t set) const {
  auto snapshot = std::make_shared<Snapshot>();
  snapshot->appearance_ = appearance_;
  if (board_) {
    snapshot->board_ = &*board_;
    snapshot->world_from_board_ = WorldFromBoard(set);
    snapshot->board_from_world_ = snapshot->world_from_board_.inverse();
  }
  if (parts_.empty() || IsCleanPlate(set)) return snapshot;

  snapshot->parts_ = &parts_;
  snapshot->parts_world_ = PartPoses(t_s);
  Mesh& mesh = snapshot->mesh_;
  for (size_t p = 0; p < parts_.size(); ++p) {
    snapshot->parts_local_.push_back(snapshot->parts_world_[p].inverse());
    const Mesh& local = parts_[p].mesh;
    const int offset = static_cast<int>(mesh.vertices.size());
    const Eigen::Matrix3f rotation = snapshot->parts_world_[p].linear().cast<float>();
    const Eigen::Vector3f translation = snapshot->parts_world_[p].translation().cast<float>();
    for (const Eigen::Vector3f& v : local.vertices) {
      mesh.vertices.push_back(rotation * v + translation);
    }
    for (const Eigen::Vector3i& f : local.faces) {
      mesh.faces.push_back(f + Eigen::Vector3i::Constant(offset));
      snapshot->face_part_.push_back(static_cast<int>(p));
    }
  }
  snapshot->face_normals_.resize(mesh.faces.size());
  for (size_t f = 0; f < mesh.faces.size(); ++f) {
    const Eigen::Vector3d a = mesh.vertices[mesh.faces[f][0]].cast<double>();
    const Eigen::Vector3d b = mesh.vertices[mesh.faces[f][1]].cast<double>();
    const Eigen::Vector3d c = mesh.vertices[mesh.faces[f][2]].cast<double>();
    const Eigen::Vector3d n = (b - a).cross(c - a);
    snapshot->face_normals_[f] = n.norm() > 0 ? n.normalized() : Eigen::Vector3d::UnitZ();
  }
  snapshot->bvh_.Build(mesh.vertices, mesh.faces);
  // Vertex colours for viewers of the ground-truth mesh: the albedo at each vertex.
  mesh.colors.resize(mesh.vertices.size());
  for (size_t f = 0; f < mesh.faces.size(); ++f) {
    for (int k = 0; k < 3; ++k) {
      SurfaceHit hit;
      hit.surface = kFirstPart + snapshot->face_part_[f];
      hit.point = mesh.vertices[mesh.faces[f][k]].cast<double>();
      const Eigen::Vector3d albedo = snapshot->Albedo(hit);
      mesh.colors[mesh.faces[f][k]] =
          (albedo * 255).array().round().min(255.0).max(0.0).cast<uint8_t>().matrix();
    }
  }
  return snapshot;
}

SurfaceHit Snapshot::Trace(const Eigen::Vector3d& origin, const Eigen::Vector3d& direction) const {
  SurfaceHit hit;
  hit.t = std::numeric_limits<double>::infinity();
  // The room, seen from inside: the nearest of the six planes ahead.
  for (int axis = 0; axis < 3; ++axis) {
    const double d = direction[axis];
    if (d == 0) continue;
    const double lo = axis == 2 ? 0.0 : -kRoomHalf;
    const double hi = axis == 2 ? kRoomHeight : kRoomHalf;
    const double plane = d > 0 ? hi : lo;
    const double t = (plane - origin[axis]) / d;
    if (t > 0 && t < hit.t) {
      hit.t = t;
      hit.normal = Eigen::Vector3d::Zero();
      hit.normal[axis] = d > 0 ? -1 : 1;
      if (axis == 2) {
        hit.surface = d > 0 ? kCeiling : kFloor;
      } else {
        hit.surface = 1 + 2 * axis + (d > 0 ? 1 : 0);
      }
    }
  }
  if (board_ != nullptr) {
    const Eigen::Vector3d o = board_from_world_ * origin;
    const Eigen::Vector3d d = board_from_world_.linear() * direction;
    if (d.z() != 0) {
      const double t = -o.z() / d.z();
      if (t > 0 && t < hit.t) {
        const Eigen::Vector3d p = o + t * d;
        if (board_->Contains(p.x(), p.y())) {
          hit.t = t;
          // The printed side faces -z: a ray travelling towards +z sees it.
          const bool front = d.z() > 0;
          hit.surface = front ? kBoardFront : kBoardBack;
          hit.board_uv = p.head<2>();
          hit.normal = world_from_board_.linear().col(2) * (front ? -1.0 : 1.0);
        }
      }
    }
  }
  if (!bvh_.empty()) {
    TriangleHit triangle;
    if (bvh_.Intersect(origin.cast<float>(), direction.cast<float>(), 0.0f,
                       static_cast<float>(hit.t), &triangle)) {
      hit.t = triangle.t;
      hit.surface = kFirstPart + face_part_[triangle.triangle];
      const Eigen::Vector3d& n = face_normals_[triangle.triangle];
      hit.normal = n.dot(direction) > 0 ? Eigen::Vector3d(-n) : n;
    }
  }
  hit.point = origin + hit.t * direction;
  return hit;
}

Eigen::Vector3d Snapshot::Albedo(const SurfaceHit& hit) const {
  const Eigen::Vector3d& p = hit.point;
  if (hit.surface >= kFirstPart) {
    const int part = hit.surface - kFirstPart;
    const Eigen::Vector3d local = parts_local_[part] * p;
    const double detail = Detail(local, 70, 11 + part);
    const double stripe = 0.5 + 0.5 * std::sin(local.z() * 90 + 4 * ValueNoise(local * 20, 5));
    return (*parts_)[part].color * (0.35 + 0.45 * detail + 0.2 * stripe) *
           appearance_.subject_albedo;
  }
  if (hit.surface == kBoardFront || hit.surface == kBoardBack) return BoardSideAlbedo(hit);
  return RoomAlbedo(hit) * appearance_.background_albedo;
}

Eigen::Vector3d Snapshot::BoardSideAlbedo(const SurfaceHit& hit) const {
  if (hit.surface == kBoardFront) {
    return Eigen::Vector3d::Constant(
        BoardAlbedo(board_->Reflectance(hit.board_uv.x(), hit.board_uv.y())));
  }
  return Eigen::Vector3d::Constant(0.35);
}

Eigen::Vector3d Snapshot::RoomAlbedo(const SurfaceHit& hit) {
  const Eigen::Vector3d& p = hit.point;
  switch (hit.surface) {
    case kFloor: {
      const int tile = static_cast<int>(std::floor(p.x() / 0.5) + std::floor(p.y() / 0.5));
      const double base = (tile % 2 == 0) ? 0.55 : 0.42;
      const double detail = Detail(p, 40, 3);
      return Eigen::Vector3d(0.75, 0.65, 0.5) * base * (0.6 + 0.6 * detail);
    }
    case kCeiling:
      return Eigen::Vector3d::Constant(0.5 + 0.1 * Detail(p, 5, 4));
    default: {
      // Walls: a blotchy backdrop with fine detail, a different tint per wall.
      const double tint = 0.08 * (hit.surface - 1);
      const double detail = Detail(p, 25, 20 + hit.surface);
      return Eigen::Vector3d(0.45 + tint, 0.55, 0.65 - tint) * (0.55 + 0.55 * detail);
    }
  }
}

double Snapshot::Irradiance(const Eigen::Vector3d& normal) {
  static const Eigen::Vector3d light = Eigen::Vector3d(0.35, 0.25, 1.0).normalized();
  return 0.45 + 0.6 * std::max(0.0, normal.dot(light));
}

Eigen::Vector3d Snapshot::Radiance(const SurfaceHit& hit) const {
  return Albedo(hit) * Irradiance(hit.normal);
}

}  // namespace holocap::sim
