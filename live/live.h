// Live free-viewpoint video from one fixed RGB-D sensor, completed by a scan of the same subject
// (`holocap scan`). Each depth frame is a surface seen from one side; the scan is the whole
// subject in one pose. Per frame the scan is
//   1. aligned rigidly to the live surface: point-to-plane ICP from the scan's camera-facing
//      points to the live depth (projective association, Gauss-Newton, the gate shrinking from
//      coarse to fine), started from the frame before's alignment (the first frame tries the
//      scan where it is and the scan moved onto the centroid of the nearest live points, turned
//      to eight headings about the up axis; so does a frame the frame before's alignment no
//      longer fits rigidly);
//   2. bent where the subject's pose differs from the scan's: an embedded deformation graph
//      (nodes sampled on the scan every node_spacing_m, each vertex moved by its nearest nodes'
//      rigid motions blended by distance) fitted by Gauss-Newton to the same point-to-plane
//      pairs with an as-rigid-as-possible regulariser between neighbouring nodes, started from
//      the scan at rest (or, carry_deformation, from the frame before's deformation, step 1
//      then aligning the scan as that one left it);
//   3. composed with the live frame: the live depth of the subject (the pixels whose depth lies
//      near the deformed scan) meshed and coloured from the paired colour camera, plus every
//      triangle of the deformed scan the live frame does not observe (its back, what the
//      subject hides from the sensor), in the scan's colours; relit, when the scan knows the
//      light it was seen in (lighting.json, albedo.ply: scan/light.h), as that
//      light falls on the deformed scan where it stands in the live frame: each vertex's
//      albedo times the shading of its live normal, the light fixed to the sensor as it was
//      during the scan (the sensor stands where it stood for the scan, in the same room).
// A scan that does not fit (too few of its visible points near the live surface, or too large
// a residual after the fit) is refused for that frame; a frame without usable depth is
// reported and not composed.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <cstdint>
#include <filesystem>
#include <limits>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <vector>

#include "core/camera.h"
#include "core/mesh.h"
#include "core/pose.h"
#include "core/report.h"
#include "core/take.h"
#include "core/take_plan.h"
#include "scan/light.h"

namespace holocap {

struct LiveOptions {
  double depth_min_m = 0.3;  // live depth outside [min, max] is no measurement
  double depth_max_m = 4.5;
  // Scan points used for the alignment: the vertices are thinned to about this many.
  int alignment_samples = 6000;

  // Rigid ICP: the association gate starts at coarse_gate_m and halves each iteration down to
  // gate_m, where the last iterations run.
  int rigid_iterations = 12;
  double coarse_gate_m = 0.3;
  double gate_m = 0.04;
  double max_normal_angle_deg = 60;  // scan and live normals further apart: no pair
  double huber_m = 0.01;             // residuals beyond this weigh less (Huber)

  // Non-rigid correction (embedded deformation).
  bool nonrigid = true;
  // Nodes sampled on the scan this far apart. On the simulated walk (bench/live_bench) 7 cm and
  // 10 Gauss-Newton iterations fit closer than 10 cm and 5 (residual 6.3 against 7.2 mm, 80
  // against 76 % inliers, +0.2 dB at the held-out cameras) at three times the time a frame.
  double node_spacing_m = 0.07;
  int node_neighbours = 4;  // nodes that move each vertex (and each node's graph edges)
  int nonrigid_iterations = 10;
  // Weight of the as-rigid-as-possible term against the data term, per pair and per edge:
  // larger keeps the graph stiffer.
  double arap_weight = 1.0;
  // Each frame's deformation starts from the frame before's instead of from the scan at rest.
  // Off: on the simulated walk (bench/live_bench) starting at rest composes as many frames and
  // scores 0.5-0.6 dB higher at the held-out cameras on the frames both compose.
  bool carry_deformation = false;

  // The fit's checks: the alignment is refused when fewer than min_inlier_fraction of the scan
  // points the sensor should see (facing it, inside the image, over a measured pixel, not
  // hidden behind the live surface) lie within gate_m of the live surface, or when the
  // point-to-plane RMS of those that do exceeds max_residual_m.
  double min_inlier_fraction = 0.6;
  double max_residual_m = 0.015;
  // ... and when the rigid alignment alone (of the scan as the frame before left it) fits fewer
  // than this fraction, or when the fit needs a deformation larger than this RMS over the
  // scan's vertices: a scan of another object can be bent onto the subject, but only by moving
  // everything far (on the simulated walk the subject's own scan moves by at most 14 cm RMS
  // and fits 62 % or more rigidly; a scanned knot moved by 31-55 cm, fitting 16-33 % rigidly).
  double min_rigid_inlier_fraction = 0.4;
  double max_deformation_rms_m = 0.2;
  // ... and when the fitted scan explains less than this fraction of the live surface joined
  // to it (the live pixels it lies on, grown without a jump in depth above its soles and the
  // floor): a scan of something smaller than the subject fits a part of it, whatever it fits.
  // On the simulated walk the subject's own scan explains 87-100 % in every frame, a scanned
  // knot bent onto the subject 10-65 %. Checked on non-rigid fits only (a rigid one leaves the
  // limbs that moved: 62-100 % for the subject's own scan).
  double min_explained_fraction = 0.75;
  // Any refused frame makes the run DEGENERATE (its composition is missing); more than this
  // fraction of them is diagnosed as a scan that is not this subject.
  double max_refused_fraction = 0.2;

  // Composition.
  double subject_gate_m = 0.06;  // live pixels within this depth of the deformed scan (in a
                                 // 5x5 window) are the subject
  // ... and so are live pixels joined to those without a jump in depth (max_depth_jump_m)
  // within this distance of the deformed scan's box (0: none joined)
  double subject_reach_m = 0.3;
  double observed_gate_m = 0.03;   // scan vertices this close to the live subject are observed
  double max_depth_jump_m = 0.04;  // no live triangle across a larger jump in depth
  double floor_margin_m = 0.03;    // live points this close above the floor plane are left out

  // The scan's unobserved part relit (step 3) when the scan holds its light and albedo; false
  // composes the colours as the scan saw them.
  bool relight = true;
  bool write_glb = true;  // recon/<set>.glb (vertex colours) beside recon/<set>.ply
  int threads = 0;        // 0: all cores

  void Check() const;  // throws Error naming the field
  nlohmann::json ToJson() const;
};

// A live depth frame as a surface: world points and normals per depth pixel.
struct LiveSurface {
  CameraModel camera;  // the depth sensor (lens and cam_from_world)
  int width = 0, height = 0;
  std::vector<Eigen::Vector3f> points;   // world; NaN: no measurement
  std::vector<Eigen::Vector3f> normals;  // world, unit, towards the sensor; NaN: none
  std::vector<float> depth;              // z-depth per pixel; NaN: none
  int64_t valid = 0;                     // pixels with a point and a normal
};
// `depth_m`: CV_32F z-depth in metres (NaN: none) of the sensor `camera`.
LiveSurface MakeLiveSurface(const cv::Mat& depth_m, const CameraModel& camera, double depth_min_m,
                            double depth_max_m);

// How well posed scan points fit a live surface.
struct FitStats {
  int64_t expected = 0;  // scan points the sensor should see
  int64_t inliers = 0;   // of them within the gate (and the normal angle) of the live surface
  double inlier_fraction = 0;
  double residual_m = std::numeric_limits<double>::quiet_NaN();  // point-to-plane RMS, inliers
};
FitStats MeasureFit(const std::vector<Eigen::Vector3f>& points,
                    const std::vector<Eigen::Vector3f>& normals, const LiveSurface& live,
                    double gate_m, double max_normal_angle_deg);

struct RigidAlignment {
  Pose world_from_scan = Pose::Identity();
  FitStats fit;  // at the final gate
  int iterations = 0;
};
// Point-to-plane ICP of the scan's vertices (with normals) onto the live surface from
// `initial`.
RigidAlignment AlignRigid(const Mesh& scan, const LiveSurface& live, const Pose& initial,
                          const LiveOptions& options);

// An embedded deformation graph over a mesh.
struct DeformationGraph {
  std::vector<Eigen::Vector3d> nodes;           // rest positions
  std::vector<std::vector<int>> edges;          // per node: its neighbouring nodes
  std::vector<std::array<int, 4>> vertex_node;  // per vertex: up to 4 nodes (-1: none)
  std::vector<Eigen::Vector4f> vertex_weight;   // ... and their weights (sum 1)
  std::vector<Eigen::Matrix3d> rotation;        // per node: its motion
  std::vector<Eigen::Vector3d> translation;
  // Samples nodes every `spacing_m` over the mesh's vertices; `neighbours` (1 to 4) nodes
  // move each vertex. Nodes and vertices are tied to their nearest nodes along the mesh's
  // edges (within 2 spacings), so that limbs that pass close (legs, an arm by the torso) move
  // apart; a piece that no node reaches along the surface is tied through space.
  DeformationGraph(const Mesh& mesh, double spacing_m, int neighbours);
  Eigen::Vector3d Apply(size_t vertex, const Eigen::Vector3d& rest) const;
  Eigen::Vector3d ApplyNormal(size_t vertex, const Eigen::Vector3d& rest) const;
  // The same deformation of the mesh moved rigidly by `world_from_rest` (nodes moved, motions
  // turned into the new frame), and back: the motions of such a posed graph, in this one's frame.
  DeformationGraph Posed(const Pose& world_from_rest) const;
  void TakeMotions(const DeformationGraph& posed, const Pose& world_from_rest);
};

struct NonRigidFit {
  Mesh deformed;                 // the mesh with every vertex (and normal) moved
  FitStats before, after;        // at the final gate
  double deformation_rms_m = 0;  // vertex displacement, RMS and max
  double deformation_max_m = 0;
  int64_t nodes = 0;
};
// Fits the deformation graph of `aligned` (the scan after its rigid alignment, world
// coordinates) to the live surface. `graph` (optional): the graph of `aligned`, its motions the
// start (the frame before's) and the result; without it a new graph starts at rest.
NonRigidFit FitNonRigid(const Mesh& aligned, const LiveSurface& live, const LiveOptions& options,
                        DeformationGraph* graph = nullptr);

// The live frame meshed: the subject's pixels (`subject`: CV_8U, 255 = subject) joined into
// triangles with their neighbours, coloured from `color_bgr` seen by `color_camera` (mid grey
// where the colour camera has no view).
Mesh MeshLiveSurface(const LiveSurface& live, const cv::Mat& subject, const cv::Mat& color_bgr,
                     const CameraModel& color_camera, double max_depth_jump_m);

enum class LiveState { kComposed, kNoDepth, kRefused, kSkipped };
const char* ToString(LiveState state);

struct LiveFrame {
  int64_t set = 0;
  LiveState state = LiveState::kSkipped;
  std::string why;  // not composed: the reason
  Pose world_from_scan = Pose::Identity();
  // The frame before's alignment did not hold and the pose was searched for again.
  bool relocalised = false;
  int64_t live_points = 0;           // valid live pixels
  double rigid_inlier_fraction = 0;  // after the rigid alignment
  double rigid_residual_m = std::numeric_limits<double>::quiet_NaN();
  double inlier_fraction = 0;  // after the non-rigid correction (what is composed)
  double residual_m = std::numeric_limits<double>::quiet_NaN();
  double deformation_rms_m = 0;
  double deformation_max_m = 0;
  int64_t subject_pixels = 0;  // live pixels kept as the subject
  // Of the live surface joined to the fitted scan, the fraction it lies on (NaN: not measured)
  double explained_fraction = std::numeric_limits<double>::quiet_NaN();
  int64_t live_faces = 0;  // triangles from the live frame
  int64_t scan_faces = 0;  // ... and from the scan (what the sensor does not see)
  double seconds = 0;      // alignment + composition
  nlohmann::json ToJson() const;
};

// One frame's result: the composed mesh and the live part alone.
struct LiveResult {
  LiveFrame frame;
  Mesh live;      // the subject's live surface
  Mesh composed;  // live + the unobserved deformed scan
};

// The light a scan was seen in and its vertices' albedo (`holocap scan` writes both).
struct ScanAlbedo {
  ScanLight light;
  std::vector<Eigen::Matrix<uint8_t, 3, 1>> colors;  // per scan vertex, RGB
};

// Frame after frame of one fixed sensor: keeps the alignment of the frame before.
class LiveCompositor {
 public:
  // `scan`: the scan's mesh (world coordinates of the scan take) with vertex colours; a floor
  // it kept (a flat layer at its bottom, along `up`, holding a quarter of its vertices) is cut.
  // `floor_level_m`: the floor plane's own height along `up` (NaN: none; a TakePlan's is
  // floor_m + floor_tolerance_m). `albedo` (one colour per scan vertex): the unobserved scan is
  // relit with it (LiveOptions::relight).
  LiveCompositor(Mesh scan, const LiveOptions& options,
                 const Eigen::Vector3d& up = Eigen::Vector3d::UnitZ(),
                 double floor_level_m = std::numeric_limits<double>::quiet_NaN(),
                 std::optional<ScanAlbedo> albedo = std::nullopt);
  // `depth_m` from `depth_camera`, `color_bgr` (CV_8UC3, may be empty) from `color_camera`.
  LiveResult Process(int64_t set, const cv::Mat& depth_m, const CameraModel& depth_camera,
                     const cv::Mat& color_bgr, const CameraModel& color_camera);

 private:
  // The scan turned by `yaw_rad` about the up axis and moved onto the live subject's nearest
  // points, its floor on the live floor where both are known (where a search for its pose
  // starts).
  Pose CentredPose(const LiveSurface& live, double yaw_rad) const;
  // The last composed frame's pose moved on to `set` at the rate of the last two composed frames
  // (turning about the scan's centre, which moves on in a straight line).
  Pose PredictedPose(int64_t set) const;
  // The live pixels that are the subject; `explained_fraction` (optional): of the live surface
  // joined to the scan without a depth jump above its soles (however far), the fraction on it.
  cv::Mat SubjectMask(const LiveSurface& live, const Mesh& deformed,
                      double* explained_fraction = nullptr) const;
  Mesh UnobservedScan(const Mesh& deformed, const LiveSurface& live, const cv::Mat& subject) const;

  // The deformed scan's colours: its albedo in the light of the sensor `sensor`.
  void Relight(Mesh* deformed, const CameraModel& sensor) const;

  Mesh scan_;
  std::optional<ScanAlbedo> albedo_;  // floor cut like scan_
  // The scan's deformation graph, in the scan's frame; with carry_deformation it holds the last
  // composed frame's motions, where the next frame starts (the regulariser still measures
  // against the scan).
  std::optional<DeformationGraph> graph_;
  std::optional<DeformationGraph> rest_graph_;  // the scan's graph at rest
  LiveOptions options_;
  Eigen::Vector3d up_;
  double floor_level_m_;
  double scan_floor_m_ = std::numeric_limits<double>::quiet_NaN();  // the floor the scan stood on
  bool has_pose_ = false;
  Pose last_world_from_scan_ = Pose::Identity();
  std::vector<std::pair<int64_t, Pose>> poses_;  // the last two composed frames' sets and poses
  Eigen::Vector3d scan_centroid_;                // of the scan's vertices (floor cut)
  Eigen::AlignedBox3f scan_box_;
};

// SUCCESS: every frame with depth composed (depthless frames counted); DEGENERATE: a frame was
// refused (how many, and the first one's reason), diagnosed as a scan that does not fit the live
// subject above max_refused_fraction, or no frame could be composed; FAILURE: an output could
// not be written.
struct LiveSummary : Summary {
  std::vector<LiveFrame> frames;
  int64_t composed = 0, no_depth = 0, refused = 0;
  double seconds = 0;
  std::string depth_sensor, color_sensor;
  // The scan's part relit in its light (scan_light, the depth sensor's frame), or why not.
  bool relit = false;
  std::string relit_why;
  Eigen::Vector3d scan_light = Eigen::Vector3d::Zero();
  nlohmann::json metrics;
};

// Reads SCAN_DIR/mesh.ply (throws Error for a missing, damaged or empty scan, or a scan whose
// report.json says it failed).
Mesh ReadScan(const std::filesystem::path& scan_dir);
// SCAN_DIR's light and albedo when it holds them (lighting.json, albedo.ply) and the light was
// observed; nullopt otherwise, with `why` (may be null) saying why. Throws Error for a damaged
// file or an albedo mesh that is not `scan`'s.
std::optional<ScanAlbedo> ReadScanAlbedo(const std::filesystem::path& scan_dir, const Mesh& scan,
                                         std::string* why = nullptr);

// Runs the plan's frame sets of a take with one depth sensor (and its paired colour camera;
// any other camera is ignored) into `out`: recon/<set>.ply and .glb (the composed mesh, vertex
// colours: what `holocap export web --recon OUT/recon` plays), frames.json and report.json.
// Throws Error for bad options, a take without exactly one depth sensor, or a bad scan.
LiveSummary LiveTake(const std::filesystem::path& take_dir, const TakeSelection& selection,
                     const std::filesystem::path& scan_dir, const std::filesystem::path& out,
                     const LiveOptions& options, Report* report = nullptr);

// Live from sensors (`holocap capture --live SCAN`): the frame sets a recording writes, composed
// as they come on a thread of their own. The newest set wins: a set that arrives while the one
// before is still being composed replaces the set waiting, which is counted as skipped, so the
// output falls behind by at most one set and never by a growing queue; the recording keeps
// every set whatever happens here (`holocap live TAKE --scan SCAN` composes them all later).
struct LiveStreamStatus {
  int64_t offered = 0, composed = 0, refused = 0, no_depth = 0, skipped = 0;
  double last_latency_s = 0;  // from a set's arrival to its meshes written
};
class LiveStream {
 public:
  // Reads the scan (Error for a bad one) and starts the thread. `out` is claimed when the first
  // set arrives (the recording creates the take it may lie in); the floor and up axis come from
  // that set's depth.
  LiveStream(const std::filesystem::path& scan_dir, std::string depth_sensor,
             CameraModel depth_camera, std::string color_sensor, CameraModel color_camera,
             std::filesystem::path out, bool overwrite, const LiveOptions& options);
  ~LiveStream();
  LiveStream(const LiveStream&) = delete;
  LiveStream& operator=(const LiveStream&) = delete;
  // Hands over a set (any thread; returns at once, never throws).
  void Offer(const FrameSet& set);
  LiveStreamStatus status() const;
  // Composes the set still waiting, stops the thread and writes OUT/report.json (metrics as
  // LiveTake's, plus offered/skipped sets and latency). FAILURE when the output could not be
  // claimed or written; otherwise as LiveTake.
  LiveSummary Finish();

 private:
  struct State;
  std::unique_ptr<State> state_;
};

}  // namespace holocap
