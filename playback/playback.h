// Playback: free-viewpoint renders of any trained avatar (neural/neural.h's AvatarModel: a
// Neural Volume today, any kind registered there tomorrow) along a camera path, written as
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
#include <string>
#include <vector>

#include "core/camera.h"
#include "core/report.h"
#include "neural/neural.h"

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

}  // namespace holocap
