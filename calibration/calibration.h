// Calibration: AprilTag and chessboard boards, their detection, seeding, the multi-camera mrcal
// solve, projection uncertainty, cross-validation, depth-sensor extrinsics and the outputs a
// take gets (calib/<sensor>.cameramodel, calib/report.json, pictures).
//
// The board model is mrcal's: width_n x height_n points on one regular grid (core/board.h).
// One observation is one camera seeing the board in one frame set: every grid point gets a
// pixel and a weight, weight < 0 where the point was not seen (mrcal's convention).
//
// The solve is staged like mrcal's own mrcal-calibrate-cameras: board poses and rig geometry
// first with a stereographic lens, then the intrinsics core, then everything in the final lens
// model with regularisation and outlier rejection. mrcal 2.2 solves one lens model per problem,
// so a rig whose cameras ask for different models is solved jointly in the most general model
// of the cameras that do not ask for a splined one (when they are at least half the rig), then
// each camera whose model that cannot stand in for is re-solved alone in its own model (its
// intrinsics and its pose relative to the reference, against the joint solve's board poses);
// the report's notes and stages say which cameras were.
//
// Projection uncertainty follows mrcal's Python projection_uncertainty() ("mean-frames"): the
// observation noise is propagated through the Jacobian returned by mrcal_optimizer_callback,
// Var(b) = s^2 inv(JtJ) Jobs^t Jobs inv(JtJ), and the projection of a point at a working
// distance is differentiated through the intrinsics, the camera's extrinsics and the mean of
// the board poses. The same propagation gives each camera's 1-sigma of its intrinsics and of its
// rotation and centre relative to the reference camera.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <limits>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <vector>

#include "core/board.h"
#include "core/camera.h"
#include "core/pose.h"
#include "core/report.h"

namespace holocap {

class Take;

// ---------------------------------------------------------------------------------------------
// Printing boards.

// The board rendered to scale at `dpi` (8-bit grey, white margin included).
cv::Mat RenderBoardImage(const BoardLayout& layout, double dpi = 300);
// Writes the board as PNG (rendered at `dpi`) or PDF (vector squares on one page exactly the
// board's size, so it prints to scale at 100%), by extension. Throws Error for another extension or
// an unwritable file.
void WriteBoardPrint(const BoardLayout& layout, const std::filesystem::path& file,
                     double dpi = 300);

// ---------------------------------------------------------------------------------------------
// Detection.

// Which finder reads chessboard layouts: holocap's own (OpenCV's findChessboardCorners, each
// corner refined on the image edges) or mrcal's `mrgingham` program (square grids only).
// AprilTag and ChArUco boards have one detector each and ignore it.
enum class ChessboardFinder { kHolocap, kMrgingham };
// "holocap" or "mrgingham"; anything else throws Error naming the choices.
ChessboardFinder ParseChessboardFinder(const std::string& name);
const char* ToString(ChessboardFinder finder);

struct DetectionOptions {
  int threads = 0;  // frames detected in parallel; 0: all cores
  ChessboardFinder chessboard_finder = ChessboardFinder::kHolocap;  // chessboard layouts' finder
  bool refine_corners = true;         // refine libapriltag's corners on the image edges
  int refine_half_window_px = 0;      // edge-refinement reach across an edge; 0: automatic
  int max_hamming = 1;                // reject tags decoded with more corrected bits
  double min_decision_margin = 30;    // reject weak decodes (libapriltag's decision_margin)
  int min_tags = 4;                   // AprilTag (ChArUco) boards: fewer tags (markers) seen =
                                      // partial, rejected
  double min_tag_side_px = 12;        // reject tags whose sides are shorter (too far, too blurred)
  double quad_sigma = 0;              // libapriltag's blur before quad finding
  double max_corner_residual_px = 2;  // reject a view whose corners leave a local homography by
                                      // more than this (shifted or swapped corners)
  void Check() const;
  nlohmann::json ToJson() const;
};

// One camera's view of the board.
struct BoardObservation {
  std::string sensor;
  int64_t frame_set = 0;     // the take's frame-set index (shared views share it)
  int64_t timestamp_ns = 0;  // the frame's timestamp, in its stream's clock
  // width_n * height_n rows (row-major, grid index j * width_n + i): x, y pixel, weight
  // (1 = seen, < 0 = not seen or rejected).
  Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor> points;
  // AprilTag boards: the black border, in bits, of most of the tags the corners come from (1:
  // libapriltag's, holocap's prints; 2: Kalibr's prints); 0 for other boards.
  int tag_border_bits = 0;
  int seen() const;  // points with weight > 0
};

// Why a view was not used.
struct RejectedView {
  std::string sensor;
  int64_t frame_set = 0;
  std::string reason;
};

class BoardDetector {
 public:
  BoardDetector(const BoardLayout& layout, const DetectionOptions& options = {});
  ~BoardDetector();
  BoardDetector(const BoardDetector&) = delete;
  BoardDetector& operator=(const BoardDetector&) = delete;

  const Board& board() const { return board_; }
  // Detects the board in an 8-bit grey or BGR image. Returns false with the reason when the
  // board is absent, partial or ambiguous (a ChArUco board may be partial: every corner found
  // between two of its markers is kept). Safe to call from several threads.
  bool Detect(const cv::Mat& image, BoardObservation* observation, std::string* reason) const;
  // Tag (or ArUco marker) ids of the layout's family (dictionary) found in the image, whether
  // or not they belong to the board (for telling "no board" from "a different board").
  std::vector<int> DetectTagIds(const cv::Mat& image) const;

 private:
  struct Impl;
  bool DetectChessboard(const cv::Mat& grey, BoardObservation* observation,
                        std::string* reason) const;
  bool DetectCharuco(const cv::Mat& grey, BoardObservation* observation, std::string* reason) const;
  Board board_;
  DetectionOptions options_;
  Impl* impl_;
};

struct DetectionSummary {
  int64_t frames = 0;  // images looked at
  int64_t views = 0;   // accepted board views
  std::vector<RejectedView> rejected;
  double seconds = 0;
  double frames_per_second = 0;
  std::map<std::string, int64_t> views_per_sensor;
  // AprilTag boards: accepted views by the border of their tags (BoardObservation).
  std::map<int, int64_t> views_per_tag_border_bits;
  std::vector<int> foreign_tag_ids;  // ids of the family seen that are not on the board
  nlohmann::json ToJson() const;
};

// Detects the board in every frame of the named colour sensors (all colour sensors if empty),
// in parallel. Throws Error for a sensor absent from the take and when no frame shows the
// board (naming tags of another board when those were seen instead).
std::vector<BoardObservation> DetectBoardsInTake(const Take& take, const BoardLayout& layout,
                                                 const std::vector<std::string>& sensors,
                                                 const DetectionOptions& options,
                                                 DetectionSummary* summary);

// Writes board views as mrcal's corners file (the corners.vnl that mrcal-calibrate-cameras
// reads with --corners-cache): `# filename x y level`, then per view its width_n * height_n
// points in grid order, `IMAGE x y 0` for a point seen and `IMAGE - - -` for one not, IMAGE
// being image_name(view). Throws Error when the file cannot be written.
void WriteCornersVnl(const std::vector<BoardObservation>& views,
                     const std::function<std::string(const BoardObservation&)>& image_name,
                     const std::filesystem::path& file);

// ---------------------------------------------------------------------------------------------
// The solve.

struct CalibrationCamera {
  std::string name;
  int width = 0;
  int height = 0;
  std::string lensmodel = "LENSMODEL_OPENCV8";  // the model asked for this camera
};

struct CalibrationOptions {
  std::string reference_camera;  // the camera at the rig's origin; empty: the first
  int min_views_per_camera = 8;  // fewer board views: the camera is flagged, not solved
  // Fewer seen points: the view is left out (metrics.warnings counts them). A board pose takes a
  // homography to seed (8 unknowns from 4 points); 6 points leave 4 equations to tell whether it
  // fits. Whole AprilTag views hold 16 or more, a partial ChArUco view may hold fewer than 12.
  int min_points_per_view = 6;
  bool regularization = true;     // mrcal's regularisation in the final stage
  bool outlier_rejection = true;  // mrcal's outlier rejection in the final stage
  bool solve_board_warp = false;  // solve mrcal's board warp (printed boards that bow)
  // AprilTag boards: the tag side, px, detection keeps a tag from (DetectionOptions::
  // min_tag_side_px; a take's calibration passes it on), for the reason given to a camera with
  // too few views; 0: that option's default.
  double tag_read_px = 0;
  double max_seed_rms_px = 50;  // a seed solve worse than this is reported as failed
  // Symmetric boards: a view whose seeded pose relative to its frame set's anchor view is
  // farther than this (rotation or baseline direction) from the two cameras' relative pose
  // under every numbering of the board is left out.
  double max_order_disagreement_deg = 20;
  // Uncertainty.
  bool uncertainty = true;            // propagate the observation noise (the costliest part)
  int uncertainty_grid_x = 16;        // imager sample points across ...
  int uncertainty_grid_y = 12;        // ... and down
  double uncertainty_distance_m = 0;  // distance of the projected points; 0: each camera's
                                      // median board distance
  double observed_pixel_sigma = 0;    // noise of one corner coordinate; 0: from the residuals
  double max_uncertainty_px = 1.0;    // worst 1-sigma where the board was seen above this:
                                      // ill-conditioned (degenerate)
  // A lens whose focal length's 1-sigma from the views alone (CalibratedCamera::
  // focal_sigma_views_rel) exceeds this share of it: its views do not constrain the lens
  // (degenerate), whatever the model. Checked with or without `uncertainty`.
  double max_focal_sigma_rel = 0.01;
  // A camera whose views' board normals all lie within this of each other saw the board in one
  // pose, however many frames repeat it: degenerate (one plane pose fixes no lens).
  double min_normal_spread_deg = 5;
  // The lens model's fit. A model that describes the lens leaves residuals at the corners'
  // noise; one that cannot (a pinhole for a distorted lens) leaves them far above it. The noise
  // expected is observed_pixel_sigma where given, else the RMS residual of each camera solved
  // again in a richer model (LENSMODEL_OPENCV8, for cameras whose model has fewer parameters
  // and is not splined; others are not checked). A camera whose RMS residual exceeds that noise
  // by more than max_residual_to_noise, or by more than the chi-square bound of its residual
  // count at p = 1e-6 where that is larger, makes the solve DEGENERATE.
  bool check_model_fit = true;
  // Under Gaussian noise an adequate model's RMS stays within sqrt(chi2_{1-1e-6}(n) / n) of the
  // noise: under 1.5 for n >= 48 residuals, about 1.05 for thousands. Corners carry a bias
  // besides their scatter (a richer model absorbs some of it), which that bound does not allow
  // for: 2 (4x the expected cost) keeps an adequate model clear of it while a lens model that
  // misses the distortion leaves residuals tens of times the noise.
  double max_residual_to_noise = 2;
  // Cross-validation.
  bool cross_validation = false;  // also solve two disjoint halves of the frames
  // ... whose projections may differ by at most this many times the 1-sigma the halves' own
  // uncertainty predicts for their difference (RMS over the imager where the board was seen,
  // of sqrt(sigma_a^2 + sigma_b^2) in each half's worst direction), else DEGENERATE: were the
  // uncertainty right, the mean squared difference is at most twice that sigma squared (a
  // round distribution), so its RMS is at most 1.41 sigma; 2 is passed by chance rarely.
  double max_cross_validation_ratio = 2;
  bool verbose = false;  // mrcal's own iteration log on stderr

  void Check() const;
  nlohmann::json ToJson() const;
};

struct CameraUncertainty {
  int grid_x = 0, grid_y = 0;
  Eigen::MatrixXd worst_sigma_px;           // grid_y x grid_x worst-direction 1-sigma
  Eigen::Matrix2Xd pixels;                  // the sample pixels, row-major over the grid
  std::vector<Eigen::Matrix2d> covariance;  // per sample pixel
  Eigen::Matrix<bool, Eigen::Dynamic, Eigen::Dynamic> observed;  // grid cells holding data
  double distance_m = 0;
  double worst_px = 0;           // max over the grid
  double worst_observed_px = 0;  // max over the cells the board was seen in
  double mean_px = 0;
};

// How a camera saw the board: what decides whether its views can constrain its lens.
struct PoseSpread {
  // The angle between the board's normal and the ray to its centre, over the camera's views.
  double tilt_min_deg = 0, tilt_max_deg = 0;
  double normal_spread_deg = 0;  // the largest angle between two of its views' board normals
  double distance_min_m = 0, distance_max_m = 0;  // to the board's centre
  double coverage = 0;  // share of the imager's 8 x 6 cells holding an inlier corner
  nlohmann::json ToJson() const;
};

struct CalibratedCamera {
  std::string name;
  bool solved = false;  // false: flagged (see `flag`), no model
  std::string flag;     // why it is not trusted (empty when fine)
  CameraModel model;    // cam_from_world with world = the reference camera
  int views = 0;
  int points = 0;     // observed points used
  int outliers = 0;   // points mrcal rejected
  double rms_px = 0;  // of its inlier residuals
  double median_board_distance_m = 0;
  PoseSpread pose_spread;
  // The side of the board's tags (AprilTag), ArUco markers (ChArUco) or squares (chessboards),
  // pixels, in the views detection found (each view's median): the smallest view and the
  // median one (metrics "feature_side_px"). A camera flagged for too few views whose median is
  // under 1.5 times the size detection reads them from says so in its flag. NaN: no view.
  double feature_side_px_min = std::numeric_limits<double>::quiet_NaN();
  double feature_side_px_median = std::numeric_limits<double>::quiet_NaN();
  CameraUncertainty uncertainty;
  std::vector<Eigen::Vector2d> observed;   // inlier observed pixels (for pictures)
  std::vector<Eigen::Vector2d> residuals;  // their residuals (observed - projected)
  // The solve's own 1-sigma of its parameters, from the same noise propagation as the
  // projection uncertainty (NaN where a parameter was held fixed or the camera is the
  // reference): each intrinsic, and the pose relative to the reference camera.
  std::vector<double> intrinsics_sigma;
  double rotation_sigma_deg = std::numeric_limits<double>::quiet_NaN();  // worst axis
  double center_sigma_mm = std::numeric_limits<double>::quiet_NaN();     // worst direction
  // The focal length's 1-sigma relative to it (the larger of fx and fy) from the views alone,
  // without the regularisation that holds what no view fixes at its prior: infinite where the
  // views leave the focal length free (a board that never moves). NaN where it is not solved
  // (a splined model's core) or could not be computed.
  double focal_sigma_views_rel = std::numeric_limits<double>::quiet_NaN();
};

// One mrcal_optimize call and how it ended, in mrcal's own figures. mrcal 2.2 returns the RMS
// and the outlier count only (no iteration count, no convergence flag): the ending is judged at
// its result from its own residuals and Jacobian (the cost one more Gauss-Newton step would
// remove, against Ceres' default function tolerance of 1e-6).
struct SolveStage {
  std::string name;
  std::string lensmodel;
  double rms_px = 0;   // mrcal's rms_reproj_error__pixels (negative: mrcal failed)
  int outliers = 0;    // mrcal's Noutliers
  double seconds = 0;  // since the solve began, at the stage's end
  // CONVERGENCE: one more step would remove <= 1e-6 of the cost; NO_CONVERGENCE: more (mrcal
  // spent its iterations while the cost still fell); FAILURE: mrcal failed or gave NaN.
  Termination termination = Termination::kFailure;
  double cost = std::numeric_limits<double>::quiet_NaN();  // |x|^2 of mrcal's residuals at the end
  double expected_decrease =
      std::numeric_limits<double>::quiet_NaN();  // share of the cost one
                                                 // more Gauss-Newton step would remove (NaN: not
                                                 // judged)
};

// How a calibration ends (core/report.h's contract):
// | state          | when                                                                   | exit
// |
// |----------------|------------------------------------------------------------------------|------|
// | CONVERGENCE    | every camera solved and trusted, every mrcal stage converged           | 0 |
// | NO_CONVERGENCE | every camera trusted, but a stage's cost still fell when mrcal stopped  | 0 |
// | DEGENERATE     | a camera has too few views, shares none with the reference camera's    | 1 |
// |                | group, or is ill-conditioned (projection 1-sigma above the limit); the | | |
// | message names each camera and why                                      |      | | FAILURE |
// mrcal failed or gave NaN, or the seed does not fit (wrong board/lens)  | 1    |
// With cross-validation, halves that differ by more than max_cross_validation_ratio times their
// predicted sigma make it DEGENERATE too, naming the cameras (metrics "cross_validation").
struct CalibrationSummary : Summary {
  std::string lensmodel;  // the model solved
  std::string reference_camera;
  std::vector<CalibratedCamera> cameras;
  std::vector<SolveStage> stages;
  std::vector<std::string> warnings;
  std::vector<std::string> notes;   // how the solve was arranged (e.g. cameras re-solved alone)
  double rms_reprojection_px = 0;   // all inliers, all cameras
  double observed_pixel_sigma = 0;  // the noise the uncertainty assumed
  int frames = 0;                   // board poses solved
  int observations = 0;             // camera views solved
  int outliers = 0;
  double solve_seconds = 0;
  double uncertainty_seconds = 0;
  // Symmetric chessboards (a square one, say) may be numbered from different ends in the
  // cameras of one frame set: views whose numbering was turned to agree with the other cameras
  // of their frame set, and views that no turn made agree (left out of the solve).
  int reordered_views = 0;
  std::vector<RejectedView> dropped_views;
  // The views the solve was given, numbered alike within each frame set (turned as above, the
  // views left out removed), per camera in frame-set order: what `calibrate --write-corners`
  // writes.
  std::vector<BoardObservation> solved_views;
  // Solved board poses (ref_from_board) per frame set, for comparisons with truth.
  std::map<int64_t, Pose> ref_from_board;
  nlohmann::json cross_validation;  // empty unless requested
  // The board's warp (CalibrationOptions::solve_board_warp), mrcal's calobject_warp: metres the
  // board's centre stands out of its plane along x and along y (metrics "board_warp_m"); NaN
  // unless solved.
  double board_warp_x_m = std::numeric_limits<double>::quiet_NaN();
  double board_warp_y_m = std::numeric_limits<double>::quiet_NaN();
  // The lens model's fit (CalibrationOptions::check_model_fit): the noise expected, where it
  // came from, and per camera the RMS and worst residual coordinate against it and the limit.
  nlohmann::json model_fit;

  const CalibratedCamera* Find(const std::string& name) const;
  nlohmann::json ToJson() const;
};

// Calibrates the cameras from their board observations. Never throws for numerical trouble
// (the summary says what went wrong); throws Error for broken preconditions (no cameras, an
// observation of an unknown camera, options that fail Check()).
CalibrationSummary Calibrate(const BoardLayout& layout,
                             const std::vector<CalibrationCamera>& cameras,
                             const std::vector<BoardObservation>& observations,
                             const CalibrationOptions& options, Report* report = nullptr);

// ---------------------------------------------------------------------------------------------
// Comparing with ground truth (simulated takes and tests).

struct GroundTruthComparison {
  double focal_rel_err_max = 0;
  double principal_point_err_px_max = 0;
  // Each camera's pose after the rigid motion that best lays the solved rig onto the true one.
  double rotation_err_deg_max = 0;
  double translation_err_mm_max = 0;  // of the camera centres
  // cam_from_reference against the truth (the reference camera's own error in every camera).
  double rotation_err_deg_max_from_reference = 0;
  double translation_err_mm_max_from_reference = 0;
  double projection_diff_rms_px = 0;  // true vs solved projection over the imagers
  double projection_diff_max_px = 0;
  double projection_diff_rms_observed_px = 0;  // only where the board was seen
  double within_3sigma_fraction = 0;           // of the imager samples with |diff| <= 3 worst sigma
  // The world the models were written in, after the rigid motion above: the angle between its
  // z axis and the truth's, and the true height of its origin (on its floor).
  double world_up_err_deg = 0;
  double world_floor_err_mm = 0;
  // The aligned depth sensors' poses after the same rigid motion (depth_from_color composed
  // with their colour camera's solved pose).
  double depth_rotation_err_deg_max = 0;
  double depth_translation_err_mm_max = 0;
  std::map<std::string, nlohmann::json> per_camera;
  nlohmann::json ToJson() const;
};

// `truth` holds each camera's true model (cam_from_world); `world_from_board` the true board
// pose per frame set. For the projections, the solved rig is placed in the world by the rigid
// fit of its board points to the true ones (the same mean-of-frames anchoring the uncertainty
// assumes); for the poses, by AlignRigs. `written_world_from_ref` is the world the models are
// written in (relative to the reference camera): its up axis and floor are measured against the
// truth's. `depth_in_ref`: aligned depth sensors (in the reference camera's frame), compared
// when `truth` holds them. Nothing is moved but for measuring.
GroundTruthComparison CompareWithTruth(const CalibrationSummary& summary,
                                       const std::map<std::string, CameraModel>& truth,
                                       const std::map<int64_t, Pose>& world_from_board,
                                       const BoardLayout& layout,
                                       const Pose& written_world_from_ref = Pose::Identity(),
                                       const std::map<std::string, CameraModel>& depth_in_ref = {});

// ---------------------------------------------------------------------------------------------
// Depth sensors.

struct DepthAlignmentOptions {
  double plane_inlier_m = 0.01;       // RANSAC band around the fitted board plane
  double max_plane_band_m = 0.15;     // the band's widest, as it follows the depth noise
  int min_planes = 3;                 // board poses needed (non-parallel normals)
  double min_normal_spread_deg = 10;  // smallest angle between normals that counts as spread
  double max_time_offset_s = 0.05;    // searched range of the time offset
  void Check() const;
};

// SUCCESS: the transform (and the time offset where the board moved enough) was fitted;
// DEGENERATE: too few board planes, or too close to parallel, to fix it.
struct DepthAlignmentSummary : Summary {
  std::string depth_sensor;
  std::string color_sensor;
  Pose depth_from_color = Pose::Identity();
  int planes = 0;                      // board planes the transform was fitted to
  std::vector<int64_t> rejected_sets;  // planes left out as not the board (frame sets)
  double plane_rms_m = 0;    // board-plane residuals of the fitted transform (within 3 sigma)
  double time_offset_s = 0;  // depth clock minus colour clock, from board motion
  bool time_offset_valid = false;
  nlohmann::json ToJson() const;
};

// depth_from_color from the board planes seen by both: each frame's board plane in the colour
// camera (from the solved board pose) and in the depth sensor (RANSAC plane fit of its depth
// image, back-projected through `depth_model`, inside the board's outline). The time offset
// is the shift that best aligns the two sensors' board-distance signals over time.
DepthAlignmentSummary AlignDepthToColor(const Take& take, const std::string& depth_sensor,
                                        const CameraModel& depth_model,
                                        const std::string& color_sensor,
                                        const CameraModel& color_model,
                                        const std::map<int64_t, Pose>& color_from_board,
                                        const BoardLayout& layout,
                                        const DepthAlignmentOptions& options);

// ---------------------------------------------------------------------------------------------
// A whole take.

struct TakeCalibrationOptions {
  std::filesystem::path board_file;  // board YAML; empty: gt/board.json, then the sim board
  std::string lensmodel;             // for every camera; empty: per camera from the rig
                                     // (sensor option calib_lensmodel), else OPENCV8
  std::vector<std::string> sensors;  // colour sensors to calibrate; empty: all
  int64_t floor_board_set = -1;      // frame set showing the board lying on the floor; -1: the
                                     // take's metadata "floor_board_set", else none
  bool pictures = true;              // residual, coverage and uncertainty PNGs
  bool depth_sensors = true;         // depth_from_color for paired depth sensors
  // Also run every detector that reads the board (chessboards, ChArUco) on every view and
  // measure their agreement (CompareBoardDetectors); the solve is the same. An AprilTag board
  // is refused before detection.
  bool compare_detectors = false;
  DetectionOptions detection;
  CalibrationOptions solve;
  DepthAlignmentOptions depth;
  void Check() const;
};

// The calibration's state and message (the depth sensors' own are in `depth`).
struct TakeCalibrationSummary : Summary {
  DetectionSummary detection;
  CalibrationSummary calibration;
  std::vector<DepthAlignmentSummary> depth;
  std::string world_frame;  // "floor board", "depth floor", "cameras" or "reference camera"
  std::string world_reason;
  bool has_ground_truth = false;
  GroundTruthComparison ground_truth;
  std::vector<std::filesystem::path> written;  // models, report and pictures
  std::filesystem::path report_file;           // where its report went
  // With compare_detectors: metrics.detector_agreement and its printed table.
  nlohmann::json detector_agreement;
  std::string detector_table;
};

// The lens model the take's rig asks for `sensor` (its option calib_lensmodel), else OPENCV8.
// Throws Error for a model mrcal does not know.
std::string RigLensModel(const Take& take, const std::string& sensor);

// Detects, solves, writes calib/<sensor>.cameramodel for every trusted camera and aligned depth
// sensor, calib/report.json and the pictures. The models' world is z up, the floor at z = 0,
// metres, from what the take shows (calibration_internal::ChooseTakeWorld: a board on the
// floor, else the floor seen by depth sensors, else the cameras' up and the lowest board point);
// the report's plan says which (world_frame, world_reason). Simulated takes are calibrated the
// same way: their truth is used only to measure. Throws Error for bad input (no board visible, a
// board file that does not match the prints, a sensor absent from the take).
TakeCalibrationSummary CalibrateTake(const std::filesystem::path& take_dir,
                                     const TakeCalibrationOptions& options,
                                     Report* report = nullptr);

// Takes over the calibration of another take of the same rig (`from`: a calibrated take, or a
// folder of <sensor>.cameramodel files): writes take_dir/calib/<sensor>.cameramodel for every
// colour and depth sensor, each model scaled when its sensor records at another size by one
// factor (a binned mode), and calib/report.json naming where they came from. Throws Error when a
// sensor has no model there, a size is not the same imager scaled, or the source's own report
// did not end usable. A studio calibrates one board take and gives its models to every take.
// The report's options name the detector the source's corners came from (its report's, null
// when it has none). `chessboard_finder`, when set (the CLI's --detector), is the finder the
// caller asks for: a source whose report does not say it solved that finder's corners (another
// finder, none named, or mrgingham asked of a board that is not a chessboard) is refused.
TakeCalibrationSummary AdoptCalibration(
    const std::filesystem::path& take_dir, const std::filesystem::path& from,
    Report* report = nullptr,
    const std::optional<ChessboardFinder>& chessboard_finder = std::nullopt);

}  // namespace holocap
