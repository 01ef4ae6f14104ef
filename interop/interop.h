// Import of recordings and calibrations from other tools' formats into holocap takes, and
// export of a take's cameras (and frames) to them.
//
//   format       source                                               conventions converted
//   middlebury   *_par.txt beside its images (name K R t per line)    none (K[R|t], pixel centres
//                                                                     at integers as holocap)
//   krt          Neural Volumes' KRT file + camN/imageNNNN images     none; KRT units via
//                                                                     metres_per_unit
//   colmap       cameras.txt, images.txt, points3D.txt + images/      image origin at the corner
//                                                                     of the top-left pixel: cx-0.5
//   nerf         transforms.json (Blender camera_angle_x, or          OpenGL camera axes, c2w,
//                nerfstudio fl_x/fl_y/cx/cy/k1../p1..)                corner pixel origin
//   panoptic     CMU Panoptic calibration_*.json + hdImgs/<cam>/      centimetres -> metres
//   mrcal        <sensor>.cameramodel files beside <sensor>/ folders  none
//
// An imported take is an ordinary take: take.json through TakeWriter, every frame copied
// losslessly as PNG (decoded pixels kept exactly; `replay:` yields them back), and
// calib/<sensor>.cameramodel. Each distinct posed camera becomes a sensor; views of one camera
// that share exact intrinsics and pose (a static camera filmed several times) become
// successive frame sets of one sensor, and numbered image files (camN/image0042) are aligned
// into frame sets by their number.
//
// Worlds stay the source's (not re-oriented to z-up), scaled to metres. Where a source's
// rotations share a non-orthonormal part S (R_i = Q_i S, as Middlebury's do at 1e-6), holocap's
// world is S times the source's: each camera then projects a source point X at S X exactly as
// K[R|t] projects X. take.json's metadata.interop.world_from_source holds that map.
//
// Lens models: PINHOLE, OPENCV4/5/8 map exactly both ways (COLMAP SIMPLE_PINHOLE, PINHOLE,
// SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV; nerfstudio OPENCV with k1..k3, p1, p2). A model
// the other side lacks (fisheye models, thin-prism terms, splined mrcal models, skewed K) is
// refused with an Error that names it: no conversion here is approximate.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <cstdint>
#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "core/camera.h"
#include "core/report.h"

namespace holocap {

enum class InteropFormat { kMiddlebury, kKrt, kColmap, kNerf, kPanoptic, kMrcal };
const char* ToString(InteropFormat format);                      // "middlebury", "krt", ...
InteropFormat InteropFormatFromString(const std::string& text);  // throws Error naming the choices

// ---------------------------------------------------------------------------------------------
// Parsers: text in the source's own conventions, nothing converted. Each throws one Error
// naming `origin`, the line or field and what is wrong; none crashes on any input.

// A K[R|t] camera as Middlebury, Neural Volumes and CMU Panoptic store it: x ~ K (R X + t).
struct KrtCamera {
  std::string name;
  Eigen::Matrix3d K = Eigen::Matrix3d::Identity();
  std::vector<double> distortion;  // OpenCV order (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4]]])
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t = Eigen::Vector3d::Zero();
  int width = 0;  // 0 where the file does not say (taken from the images)
  int height = 0;
  std::string rotation_origin;  // where R was read ("file:line", "file: cameras[3].R")
};

// "name k11..k33 r11..r33 t1 t2 t3" per line after a first line holding the count.
std::vector<KrtCamera> ParseMiddleburyPar(const std::string& text, const std::string& origin);
// Per camera: name; 3 lines of K; 1 line of distortion; 3 lines of [R|t]; a blank line.
std::vector<KrtCamera> ParseNeuralVolumesKrt(const std::string& text, const std::string& origin);
std::string FormatNeuralVolumesKrt(const std::vector<KrtCamera>& cameras);
// {"cameras": [{"name", "resolution": [w, h], "K", "distCoef", "R", "t"}]}; t as in the file.
std::vector<KrtCamera> ParsePanopticCalibration(const std::string& text, const std::string& origin);

// COLMAP's text model, as documented at colmap.github.io/format.html.
struct ColmapCamera {
  int64_t id = 0;
  std::string model;  // "PINHOLE", "OPENCV", ...
  int width = 0;
  int height = 0;
  std::vector<double> params;  // COLMAP's order; principal point with the corner origin
};
struct ColmapImage {
  int64_t id = 0;
  Eigen::Quaterniond cam_from_world_rotation = Eigen::Quaterniond::Identity();  // qw qx qy qz
  Eigen::Vector3d cam_from_world_translation = Eigen::Vector3d::Zero();
  int64_t camera_id = 0;
  std::string name;
  std::vector<Eigen::Vector2d> points2d;  // corner origin
  std::vector<int64_t> point3d_ids;       // -1: unmatched
};
struct ColmapPoint {
  int64_t id = 0;
  Eigen::Vector3d xyz = Eigen::Vector3d::Zero();
  std::array<int, 3> rgb = {0, 0, 0};
  double error = 0;  // the file's mean reprojection error of the point, pixels
  std::vector<std::pair<int64_t, int64_t>> track;  // (image id, index into its points2d)
};
struct ColmapModel {
  std::map<int64_t, ColmapCamera> cameras;
  std::vector<ColmapImage> images;
  std::vector<ColmapPoint> points;
};
std::map<int64_t, ColmapCamera> ParseColmapCameras(const std::string& text,
                                                   const std::string& origin);
std::vector<ColmapImage> ParseColmapImages(const std::string& text, const std::string& origin);
std::vector<ColmapPoint> ParseColmapPoints(const std::string& text, const std::string& origin);
std::string FormatColmapCameras(const std::map<int64_t, ColmapCamera>& cameras);
std::string FormatColmapImages(const std::vector<ColmapImage>& images);
std::string FormatColmapPoints(const std::vector<ColmapPoint>& points);

// transforms.json: intrinsics at the top level and/or per frame (per frame wins).
struct NerfIntrinsics {
  std::optional<double> fl_x, fl_y, cx, cy;              // pixels; cx, cy with the corner origin
  std::optional<double> camera_angle_x, camera_angle_y;  // radians (Blender synthetic)
  std::optional<int> w, h;
  std::optional<std::string> camera_model;   // "OPENCV", "OPENCV_FISHEYE", ...
  std::map<std::string, double> distortion;  // k1 k2 k3 k4 p1 p2 as given
};
struct NerfFrame {
  std::string file_path;  // as written (relative to the file; may lack an extension)
  Eigen::Matrix4d world_from_cam_gl = Eigen::Matrix4d::Identity();  // transform_matrix (c2w)
  NerfIntrinsics intrinsics;  // top level merged with the frame's own
};
std::vector<NerfFrame> ParseNerfTransforms(const std::string& text, const std::string& origin);

// ---------------------------------------------------------------------------------------------
// Camera conventions, exact both ways; each throws Error for what the target cannot hold.

// K and distortion (OpenCV order) as a mrcal model with the given pose; K must have no skew.
// The image size comes from `camera` and must be set.
CameraModel CameraFromKrt(const KrtCamera& camera, const Pose& cam_from_world);
// mrcal lens model <-> COLMAP model; principal points shifted by the half pixel.
CameraModel CameraFromColmap(const ColmapCamera& camera, const Pose& cam_from_world);
ColmapCamera ColmapFromCamera(const CameraModel& camera, int64_t id);
// mrcal lens model <-> transforms.json intrinsics; world_from_cam_gl <-> cam_from_world.
CameraModel CameraFromNerf(const NerfIntrinsics& intrinsics,
                           const Eigen::Matrix4d& world_from_cam_gl, int image_width,
                           int image_height, const std::string& origin);
NerfIntrinsics NerfFromCamera(const CameraModel& camera);
Eigen::Matrix4d NerfWorldFromCamGl(const Pose& cam_from_world);

// Splits rotations R_i that share a symmetric non-orthonormal part S (R_i = Q_i S) into the
// rotations Q_i and S. `residual` is max_i |S_i - S| (0 up to rounding when they share it).
struct RigidWorld {
  Eigen::Matrix3d world_from_source = Eigen::Matrix3d::Identity();  // S
  std::vector<Eigen::Matrix3d> rotations;                           // Q_i, orthonormal, det +1
  double non_orthonormality = 0;                                    // max |R_i^T R_i - I|
  double residual = 0;
};
RigidWorld SplitRigidWorld(const std::vector<Eigen::Matrix3d>& rotations);

// ---------------------------------------------------------------------------------------------
// Import and export.

struct ImportOptions {
  InteropFormat format = InteropFormat::kColmap;  // the source's format
  std::filesystem::path images;  // image root; empty: where the format keeps them (see .cpp)
  double metres_per_unit = 0;    // source length unit; 0: the format's (Panoptic cm, else m)
  // Largest max_i |S_i - S| (see RigidWorld) accepted as one shared non-rigid world part; up to
  // it, each camera keeps the nearest rotation (re-orthonormalised, said in the notes), so real
  // calibrations printed to ~1e-11 import; a larger one is refused. Each rotation is also
  // checked alone (CheckRotation, core/pose.h).
  double max_rotation_residual = kRotationTolerance;
  double fps = 30;          // sources carry no timestamps: set i is stamped i / fps
  int png_compression = 1;  // 0..9, lossless at every level
  bool overwrite = false;   // replace an existing take directory
  void Check() const;
};

// A source read and converted, before anything is written.
struct ImportedView {
  std::string sensor;       // the take's sensor name
  std::string source_name;  // what the source calls it
  CameraModel camera;
  std::map<int64_t, std::filesystem::path> frames;  // frame number -> image file
};
struct ImportedRig {
  InteropFormat format = InteropFormat::kColmap;
  std::filesystem::path source;
  std::vector<ImportedView> views;
  Eigen::Matrix3d world_from_source = Eigen::Matrix3d::Identity();  // incl. the unit scale
  nlohmann::json metrics = nlohmann::json::object();
  std::vector<std::string> notes;  // what was converted, skipped or dropped, for the report
};
// Reads and converts a source (calibration and the list of images; images are opened only for
// their size where the source lacks it). Throws Error for a malformed or unsupported source.
ImportedRig ReadForeignRig(const std::filesystem::path& source, const ImportOptions& options);

struct ImportSummary : Summary {
  int sensors = 0;
  int64_t frame_sets = 0;
  int64_t frames = 0;
  nlohmann::json metrics = nlohmann::json::object();
};
// Writes the take. `report` (optional) receives options, plan and metrics.
ImportSummary ImportTake(const std::filesystem::path& source, const std::filesystem::path& take_dir,
                         const ImportOptions& options, Report* report = nullptr);

struct ExportOptions {
  InteropFormat format = InteropFormat::kColmap;  // kColmap or kNerf
  bool ground_truth = false;  // export gt/cameras (simulated takes) instead of calib/
  bool copy_images = true;    // write the colour frames as PNG under DIR/images/<sensor>/
  // Export the cameras the format can hold and list the others in `skipped`; false: refuse the
  // whole export, naming every camera the format cannot hold exactly.
  bool skip_unrepresentable = false;
  bool overwrite = false;  // allow a non-empty output directory
  void Check() const;
};
struct ExportSummary : Summary {
  int cameras = 0;
  int64_t images = 0;
  std::vector<std::string> skipped;  // streams not exported (depth, witness, lens), with why
};
// COLMAP: DIR/sparse/0/{cameras,images,points3D}.txt and DIR/images/; NeRF: DIR/transforms.json
// and DIR/images/. Throws Error for a model the format cannot hold exactly.
ExportSummary ExportTake(const std::filesystem::path& take_dir,
                         const std::filesystem::path& out_dir, const ExportOptions& options,
                         Report* report = nullptr);

// ---------------------------------------------------------------------------------------------
// Photographs and videos as a take (holocap import images), and a take's frames as images or
// videos (holocap export images).
//
// Each camera is one source: a folder of images, a glob of image files, or a video file (read
// with OpenCV's FFmpeg backend; frame i of a video is numbered i and timed by its position in
// the video). Frames of different cameras are paired into frame sets by
//   number  the trailing number of the file name (left07.jpg with right07.jpg);
//   time    their timestamps: a video's own, or for images a sidecar file `timestamps.txt` in
//           the images' folder, one line per image: "<file name> <seconds>" ('#' comments);
//           frames of different cameras within the tolerance of each other share a set;
//   order   their rank (images in name order).
// kAuto takes number where every camera's frames carry distinct numbers and at least half of
// each camera's frames find a partner by them, else time where every frame has a timestamp,
// else order. A frame without a partner still forms a frame set alone (a camera's own view of
// a board helps its lens), and is counted and named as unpaired.
//
// No camera model is written: the take is uncalibrated until `holocap calibrate` solves it.
// Frames are kept as decoded (grey stays grey, 16-bit stays 16-bit, bgra8 keeps its alpha),
// losslessly as PNG. Every source is read and checked before the take's folder is made, so bad
// input (nothing found, an unreadable or truncated image, a camera named twice, a camera whose
// images differ in size or format) is one Error and no take.

enum class FramePairing { kAuto, kNumber, kTime, kOrder };
const char* ToString(FramePairing pairing);                    // "auto", "number", ...
FramePairing FramePairingFromString(const std::string& text);  // throws Error naming the choices

struct CameraSource {
  std::string camera;  // the sensor name in the take
  std::string source;  // a folder, a glob of image files, or a video file
};

struct ImageImportOptions {
  FramePairing pairing = FramePairing::kAuto;
  // Pairing by time: frames of different cameras at most this far apart share a set; 0: half
  // the shortest interval between two frames of one camera.
  double time_tolerance_s = 0;
  double fps = 30;          // sets stamped i / fps where the frames carry no timestamps
  int png_compression = 1;  // 0..9, lossless at every level
  bool overwrite = false;   // replace an existing imported take
  void Check() const;
};

// The cameras of FOLDER: each sub-folder holding images is a camera of its name, and so is
// each video file directly in FOLDER (named by its stem). Throws Error when it finds none.
std::vector<CameraSource> CameraSourcesInFolder(const std::filesystem::path& folder);

struct ImageImportSummary : Summary {
  int cameras = 0;
  int64_t frame_sets = 0;
  int64_t frames = 0;
  FramePairing pairing = FramePairing::kAuto;  // the rule used (never kAuto)
  std::string pairing_reason;                  // why that rule
  std::vector<std::string> unpaired;           // frames alone in their set ("left/left07.jpg")
  nlohmann::json metrics = nlohmann::json::object();
  std::string PairingLine() const;  // "paired by number ...: N sets; K unpaired (names)"
};
// Writes the take. `report` (optional) receives options, plan and metrics.
ImageImportSummary ImportImages(const std::vector<CameraSource>& cameras,
                                const std::filesystem::path& take_dir,
                                const ImageImportOptions& options, Report* report = nullptr);

struct ImageExportOptions {
  std::string format = "jpg";  // jpg | png: DIR/<sensor>/<set:06d>.<format>
  int jpeg_quality = 95;       // 1..100
  // true: one H.264 MP4 per camera (DIR/<sensor>.mp4, ffmpeg) instead of image folders, over
  // the frame sets that hold every exported camera (a video has no gaps).
  bool video = false;
  int crf = 18;                      // H.264 constant rate factor (0 lossless .. 51)
  double fps = 0;                    // video frame rate; 0: the take's
  std::vector<std::string> sensors;  // colour sensors to export; empty: all
  bool overwrite = false;            // allow a non-empty output directory
  void Check() const;
};
struct ImageExportSummary : Summary {
  int cameras = 0;
  int64_t images = 0;              // frames written (images, or video frames)
  int64_t sets_left_out = 0;       // video: frame sets missing a camera
  std::vector<std::string> notes;  // conversions (16-bit to 8, grey to colour in a video)
};
// The file name export images gives a frame set's image in its camera's folder: 000012.png.
std::string ExportedImageName(int64_t set_index, const std::string& format);
ImageExportSummary ExportImages(const std::filesystem::path& take_dir,
                                const std::filesystem::path& out_dir,
                                const ImageExportOptions& options, Report* report = nullptr);

}  // namespace holocap
