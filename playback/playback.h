// Playback: free-viewpoint renders of any trained avatar (avatar/avatar.h's AvatarModel, of
// any kind registered in AvatarKindRegistry) along a camera path, written as
// frames (PNG colour+alpha, OpenEXR colour+alpha+depth) or as an MP4 through ffmpeg.
//
// Camera paths:
//   orbit     a circle around the avatar's box at the training cameras' mean distance and
//             height, around their mean "up" direction, playing the sequence as it turns
//   JSON      {"fps": 30, "views": 90,                      (views: interpolate to this many)
//              "keys": [{"eye": [x, y, z], "look_at": [x, y, z], "up": [0, 0, 1],
//                        "fov_deg": 40, "frame": 0}, ...]}
//             or keys {"cameramodel": "cam.cameramodel", "frame": 3} that render exactly
//             through an mrcal model (lens distortion included; path relative to the JSON
//             file), rescaled to the output width. Eye/look-at keys are interpolated
//             linearly (eye, look-at, field of view, frame); "up" defaults to the orbit's up.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "avatar/avatar.h"
#include "core/box.h"
#include "core/camera.h"
#include "core/frame_tasks.h"
#include "core/report.h"
#include "core/take_plan.h"

namespace holocap {

struct CameraPath {
  std::vector<CameraModel> cameras;  // one per output view
  std::vector<int64_t> frames;       // the avatar frame each view shows
  double fps = 30;                   // of the output video
  size_t size() const { return cameras.size(); }
};

struct OrbitOptions {
  int views = 60;   // views in the full circle
  int width = 512;  // output size in pixels
  int height = 512;
  double fov_deg = 0;          // horizontal field of view; 0: fit the avatar's box
  double radius_m = 0;         // 0: the training cameras' mean distance from the box's axis
  double height_m = 0;         // along "up" from the box centre; 0: the cameras' mean height
  bool use_height = false;     // whether height_m is given
  bool advance_frames = true;  // play the sequence while turning (else frame `frame` only)
  int64_t frame = 0;           // the frame shown when not advancing
  double fps = 30;
  void Check() const;  // throws Error naming the bad field
};

// The orbit for a model (its box and training cameras). Throws Error for bad options.
CameraPath OrbitPath(const AvatarModel& model, const OrbitOptions& options);

// Reads a JSON camera path (format above) rendering at width x height. Throws Error naming the
// file and field for a malformed path.
CameraPath ReadCameraPath(const std::filesystem::path& file, const AvatarModel& model, int width,
                          int height);
// The same on the text of a path file (`file` names it in errors and anchors its cameramodel
// keys); `default_up` for keys without "up". At most a million keys and views.
CameraPath ParseCameraPath(const std::string& text, const std::filesystem::path& file,
                           const Eigen::Vector3d& default_up, int width, int height);

// The up direction and centre the orbit uses: the mean of the training cameras' image-up
// axes in the world, and the box centre.
Eigen::Vector3d ModelUp(const AvatarModel& model);

struct PlaybackOptions {
  // A directory (frames NNNNNN.png: BGRA 8-bit, straight alpha; NNNNNN.exr: half R G B A and
  // float Z, z-depth in metres, NaN where empty) or a file ending in .mp4 (H.264 through
  // ffmpeg, colour over `background`).
  std::filesystem::path out;
  bool png = true;  // directory output: write PNG colour+alpha
  bool exr = true;  // directory output: write EXR colour+alpha+depth
  Eigen::Vector3d background = Eigen::Vector3d::Zero();  // BGR in [0, 1] behind the avatar (MP4)
  int crf = 18;                                          // H.264 quality (0..51, lower is better)
  bool write_frames = true;                              // false: render only (benchmarks)
  ViewRenderOptions render;
  void Check() const;
};

// SUCCESS once every view is rendered and written (a failure to write throws).
struct PlaybackSummary : Summary {
  int64_t views = 0;
  double seconds = 0;          // everything: rendering, encoding, writing
  double render_seconds = 0;   // rendering only
  double render_fps = 0;       // views per second of rendering
  double overall_fps = 0;      // views per second including writing
  double samples_per_ray = 0;  // mean over views (rays that enter the volume)
  std::filesystem::path output;
};

// Renders every view of the path and writes it. Throws Error for bad options, an unwritable
// output or a failing ffmpeg.
PlaybackSummary RenderPath(AvatarModel& model, const CameraPath& path,
                           const PlaybackOptions& options, Report* report = nullptr);

// Writes one view as EXR with channels R, G, B, A (half) and Z (float). Atomic.
void WriteViewExr(const std::filesystem::path& file, const RenderedView& view);

// ---------------------------------------------------------------------------------------------
// Textured meshes of a reconstruction (recon/<set>.glb) drawn natively, as the web player's mesh
// stream draws them: pinhole intrinsics core of the camera, perspective-correct texture
// coordinates, bilinear texels, a z-buffer, pixel centres at integer coordinates.

struct TexturedMeshFrame {
  std::vector<Eigen::Vector3f> positions;            // world, metres; one per corner (3 per face)
  std::vector<Eigen::Vector2f> uvs;                  // one per corner, glTF convention (v down)
  std::vector<Eigen::Matrix<uint8_t, 3, 1>> colors;  // RGB per corner when there is no atlas
  cv::Mat atlas;                                     // CV_8UC3 BGR, or empty
  size_t faces() const { return positions.size() / 3; }
};

// Reads a binary glTF 2.0 file as reconstruction/ writes it (positions, optional texture
// coordinates with an embedded PNG/JPEG atlas, or vertex colours; 32-bit indices). Throws Error
// naming the file for anything else.
TexturedMeshFrame ReadTexturedGlb(const std::filesystem::path& file);

// Colour (CV_32FC3 BGR in [0, 1], black where empty) and coverage (CV_32FC1, 0 or 1) of the
// mesh seen through the pinhole core of `camera` (fx, fy, cx, cy; distortion left out).
RenderedView RenderTexturedMesh(const TexturedMeshFrame& mesh, const CameraModel& camera);

// PSNR (dB, peak 1) of `picture` against `reference` over the pixels inside the projection of
// `box` through `camera` (its bounding rectangle, clipped to the picture): the subject's
// surroundings. Either image may be 8-bit, 16-bit or float in [0, 1] (BGR, 3 channels, the
// same size). `pixels` (optional) receives how many pixels were compared.
double PsnrInsideBoxDb(const cv::Mat& picture, const cv::Mat& reference, const CameraModel& camera,
                       const Box& box, int64_t* pixels = nullptr);

// ---------------------------------------------------------------------------------------------
// The web player: `holocap export web` writes a static site (index.html, the player's ES
// modules, manifest.json and per-frame chunks; README "The stream format") that plays a take's
// textured meshes, baked Neural Volumes and splats in a browser; `holocap view` serves it.

// Version 3 added the splat stream (a version-2 player would take its chunks for volumes);
// version 4 codes splat frames in Morton order, their motion as cells' mean motion plus residuals
// and holds attributes that barely change (its player refuses version-3 splat chunks by name).
// This holocap still plays version-2 sites.
inline constexpr int kWebStreamFormatVersion = 4;
inline constexpr int kOldestWebStreamFormatVersion = 2;

struct WebExportOptions {
  // Quality levels, one stream per kind and level: "low", "medium", "high" (quantised and
  // compressed harder to softer) or "lossless" (float geometry and volumes, PNG textures).
  std::vector<std::string> qualities = {"medium"};
  std::filesystem::path recon;                // the meshes; empty: TAKE/recon when it exists
  bool meshes = true;                         // false: no mesh stream even when recon exists
  std::vector<std::filesystem::path> models;  // volumetric models (model.json), one stream each
  double fps = 0;                             // playback rate; 0: the take's rig rate (else 30)
  double step_voxels = 1.0;                   // ray-marching step of the volume streams
  int splat_key_every = 10;                   // splat streams: a key frame at every multiple
                                              // of it on the timeline (1: every frame; the
                                              // others are deltas); also the frames of a
                                              // group, the unit of --shard
  // Budgets (Mbps at the site's rate) for every chunk of the quantised splat streams, each chunk
  // at the finest rung (its level's own first) that fits; empty or {0}: the levels' own
  // encodings. Several: one stream per level and budget (0: the level's own), named
  // "<model>-<level>-<budget>mbps" (the level's own: "<model>-<level>"), levels of one ladder.
  std::vector<double> splat_mbps;
  int error_width_px = 160;  // width of the views the export's error is
                             // measured on (the capture cameras, rescaled)
  int error_cameras = 2;     // capture cameras measured per frame
  // Every k-th frame of the timeline (from the first) is scored against the images of the
  // capture cameras each source never saw. 7, prime to the key-frame interval (10): the frames
  // scored fall at every distance from their key frame, deltas as often as key frames.
  int camera_score_every = 7;
  TakeSelection take;      // cameras (calib/ or gt/cameras)
  bool overwrite = false;  // write into a non-empty site made by export
  FrameTaskOptions tasks;  // this task's groups (--shard K/N), --redo
  void Check() const;      // throws Error naming the flag
  nlohmann::json ToJson() const;
};

struct WebStreamMetrics {
  std::string name;     // "mesh-medium", "nvol-high"
  std::string kind;     // "mesh" | "volume" | "splats"
  std::string quality;  // the level
  int64_t frames = 0;
  double mb_per_frame = 0;    // mean chunk size, 10^6 bytes
  double mbps = 0;            // at the manifest's fps
  double max_chunk_mbps = 0;  // the largest chunk's size at the manifest's fps
  // The largest segment's rate (a key frame and the frames up to the next, every mesh and
  // volume chunk its own): what a link must carry to fetch each segment within its playing time,
  // the peak segment bit rate HLS calls BANDWIDTH; --splat-mbps holds it (budget_mbps).
  double max_segment_mbps = 0;
  double budget_mbps = 0;  // splats under --splat-mbps: the stream's budget (0: none)
  double psnr_db = 0;      // decoded stream against the uncompressed one (capture cameras)
  double max_position_error_mm = 0;  // meshes: simplification and quantisation of the vertices
  double mean_faces = 0;             // meshes: faces per frame streamed
  double mean_gaussians = 0;         // splats: Gaussians per frame
  double mean_stored_gaussians = 0;  // splats: Gaussians whose codes a chunk carries (changed
                                     // or added in a delta, every one in a key frame)
  int64_t key_frames = 0;            // splats: chunks that decode alone
  // Against the camera: pictures through the capture cameras the stream's source was never
  // trained on nor reconstructed from (`heldout`), each over the stream's background for that
  // camera, against what the camera captured inside the subject's silhouette (grown by 3 px;
  // the simulation's true one where the take has gt/, else background subtraction against the
  // clean plate), in the camera's pinhole core (avatar/camera_score.h). NaN where unmeasured,
  // `unscored` saying why.
  std::vector<std::string> heldout;
  std::string unscored;
  double camera_native_psnr_db = 0;      // the source rendered natively (holocap render)
  double camera_streamed_psnr_db = 0;    // the decoded chunks drawn as the page draws them
  double camera_background_psnr_db = 0;  // the background alone (an empty picture)
  int64_t camera_pixels = 0;             // subject pixels compared, over every view scored
  nlohmann::json ToJson() const;
};

// SUCCESS once every chunk and the player are written and every stream scored against the
// camera is closer to it than its background alone; DEGENERATE when the take has nothing to
// stream (no meshes, no model), or when a stream's native render or its decoded chunks score no
// better against a held-out camera than the background alone on the same pixels (the site is
// written, the reason names the stream and both figures).
struct WebExportSummary : Summary {
  int64_t frames = 0;
  uint64_t bytes = 0;  // the whole site
  double seconds = 0;
  std::vector<WebStreamMetrics> streams;
};

// Writes the site into `site_dir` (claimed with the output-safety rules of core/output.h).
// `report` receives options, plan, metrics per stream and the series psnr_db against bytes.
// Throws Error for bad options, an unreadable take, mesh or model, or an unwritable site.
//
// The export is a per-frame run (core/frame_tasks.h) whose unit is a group: `splat_key_every`
// consecutive frames of the timeline, a splat key frame first (deltas never reach into the
// group before), so any group is written alone. The run's plan (the manifest's frames,
// cameras and bounds, its streams, each splat stream's quantisation over the whole timeline) is
// made once into SITE/plan; each group's chunks are written atomically, then its record
// SITE/frame-reports/<group's first set>.json (per stream and frame: the chunk's manifest
// entry and the error sums of its frame). `options.tasks.shard` does the K-th of N contiguous
// blocks of groups and skips complete ones. manifest.json, the player's files and report.json
// are written by MergeWebSite once every group is complete (here, when this task completes the
// run), manifest.json last; a task that writes a group first removes a manifest.json already
// there, so a player never opens a site whose chunks are being replaced. A shard's own report
// goes to TaskReportPath.
WebExportSummary ExportWebSite(const std::filesystem::path& take_dir,
                               const std::filesystem::path& site_dir,
                               const WebExportOptions& options, Report* report = nullptr);

// The site of an export web run from its plan and group records: the manifest (every stream's
// chunks and metrics summed over the groups in timeline order, so the bytes are the same however
// the run was split), the player's files and report.json. An incomplete run gets a FAILURE
// report naming its incomplete groups, and no manifest. Throws Error when `site_dir` holds no
// export web run.
WebExportSummary MergeWebSite(const std::filesystem::path& site_dir, Report* report);

// Whether `dir` is a site export web wrote (a manifest of a known version); `why` says what is
// missing or wrong when not.
bool IsWebSite(const std::filesystem::path& dir, std::string* why);

// Throws Error (naming the site, the set and the stream) unless `frame`, a frame of stream
// `stream` (files in SITE/`folder`) in set `set`'s record, is believable: its chunk null or a
// plain file name of the stream's folder, there with the bytes the record counts; its squared
// error and count finite, whole and in range (a squared error past 1 a value is no image's);
// its other figures finite and not negative.
void CheckWebFrameRecord(const nlohmann::json& frame, const std::filesystem::path& site,
                         const std::string& folder, const std::string& stream, int64_t set);

struct ViewServerOptions {
  int port = 8080;                 // 0: any free port
  std::string host = "127.0.0.1";  // the address listened on: loopback only
  std::string allowed_host;        // one more Host header value answered (--host: a name the
                                   // browser reaches this machine by, through a tunnel or a
                                   // proxy), with or without the port; empty: none
  int idle_timeout_s = 2;          // a connection silent this long is closed
  int workers = 64;                // connections served at once; an idle one holds a worker
                                   // for idle_timeout_s at most
  int max_ranges = 8;              // byte ranges one request may ask for
  void Check() const;
};

// Serves `site` over HTTP until SIGINT (Ctrl-C) or SIGTERM arrives, then returns (so that the
// caller can clean up); `listening` gets the URL once the port is bound. Throws Error (one line)
// for a folder that is not a site or a port that is taken.
//
// What it answers: GET and HEAD of a regular file inside the site once every symbolic link is
// resolved (`/` and a path ending in `/`: its index.html); 404 for anything else there (a link
// out of the site, a folder, a device, a FIFO, a path with `..`); 403 to a Host header that is
// not 127.0.0.1, localhost or [::1] (or options.allowed_host), with or without the port, so that
// a page of another site cannot read it through a DNS name rebound to 127.0.0.1; 416 (with
// `Content-Range: bytes */SIZE`) to a Range header of more than options.max_ranges ranges, of a
// range past the end, or of ranges longer together than the file; 405 to any other method.
void ServeSite(const std::filesystem::path& site, const ViewServerOptions& options,
               const std::function<void(const std::string& url)>& listening);

}  // namespace holocap
