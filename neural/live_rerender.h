// A rerendering network for the live compositions of one fixed RGB-D sensor (live/live.h),
// after Pandey et al. 2019 ("Volumetric capture of humans with a single RGBD camera via
// semi-parametric learning"): it learns on the scan take alone. There the subject turns before
// the fixed sensor and the scan's trajectory gives every frame's sensor pose relative to the
// subject, so any frame i can play the live frame (its depth and colour composed with the scan,
// exactly as `holocap live` composes) and any frame j turned 60-180 degrees away the held-out
// view: the composition of frame i is rasterised at frame j's colour camera and the network
// learns to turn those buffers into frame j's image inside frame j's depth-based silhouette
// (the silhouette of frame j's own composition: a user's take has no true masks). It repairs
// what the composition gets wrong from afar (seams, holes, blurred texture) rather than
// learning an identity on views the scan was built from.
//
// The network's inputs leave out world positions (the live subject walks, the scan's subject
// stood still) and normals: in the scan take the light keeps one direction in the sensor's
// frame, so camera-frame normals teach the network that one light's shading, which held-out
// cameras elsewhere do not see (on live_bench's walk a network with normals scored 1.1 dB below
// the raw composition at 180 degrees, without them 0.5 dB above it).
//
// This header pulls in no LibTorch header.
#pragma once

#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "core/mesh.h"
#include "core/report.h"
#include "live/live.h"
#include "neural/neural.h"
#include "neural/rerender.h"

namespace holocap {

struct LiveRerenderOptions {
  UNetConfig net;
  LiveOptions live;  // the composition of each live frame, as `holocap live` makes it

  // Pairs.
  int live_frames = 48;       // frames of the scan take composed as the live frame, spread
                              // over the turn; each is also a target of the others
  int targets_per_frame = 8;  // views of each composition: frames turned between
  double min_turn_deg = 60;   // min_turn_deg and max_turn_deg from it, spread over that range
  double max_turn_deg = 180;
  int validation_every = 4;  // the pairs of every this-many-th live frame are validation only
  // Each pair's composition is moved by a random rigid motion about its centre (each axis
  // N(0, jitter_m), a turn N(0, jitter_deg) about a random axis) before it is rasterised: the
  // scan take's compositions fit their targets exactly, the live one's are off by the
  // alignment's error, and a network trained on exact ones sharpens texture into the wrong place.
  double jitter_m = 0.02;
  double jitter_deg = 3;
  int image_width = 0;  // training width (cameras rescaled); 0: the colour camera's own
  int supersample = 2;  // raster samples per pixel along each axis (playback alike)
  bool ground_truth_cameras = false;  // the scan take's gt/cameras instead of calib/ (asked for)

  // Optimisation.
  double minutes = 3;           // wall-clock budget
  int64_t iterations = 0;       // > 0: stop after this many (whichever first)
  int batch = 4;                // crops per iteration
  int crop_px = 64;             // square crops centred on a pixel of the target's silhouette
                                // (rounded up to a multiple of 2^depth, at most the image)
  double learning_rate = 1e-3;  // Adam, decayed to a tenth over the budget (cosine)
  double subject_weight = 4;    // loss weight of the target's silhouette and the rendered
                                // coverage (the rest weighs 1)
  double alpha_weight = 1;      // L1 of alpha against the target's silhouette
  int64_t eval_every = 200;     // validation PSNR every this many iterations (and at the end);
                                // the weights where it peaked are kept
  uint64_t seed = 1;
  int threads = 0;  // 0: all cores

  void Check() const;  // throws Error naming the bad field
  nlohmann::json ToJson() const;
};

// FAILURE when the loss became non-finite; DEGENERATE when the kept network scores no better
// than the raw composition on the validation pairs (or no pair could be made);
// CONVERGENCE when the validation PSNR peaked before the budget ran out; else NO_CONVERGENCE.
struct LiveRerenderSummary : Summary {
  nlohmann::json plan;
  int64_t composed_frames = 0, refused_frames = 0;
  int64_t train_pairs = 0, validation_pairs = 0;
  int64_t iterations = 0;
  double seconds = 0;                    // training wall time
  double first_loss = 0, last_loss = 0;  // means over the first and last iterations
  // PSNR (peak 1) inside the targets' silhouettes, over black, on the validation pairs.
  double validation_psnr_db = 0, raw_psnr_db = 0;
  int64_t kept_iteration = 0;
};

// Trains on `scan_take` (one depth sensor and its paired colour camera) with its scan
// `scan_dir` (mesh.ply and trajectory.json of `holocap scan`) into `model_dir`: model.json
// (method "live-rerender"), unet.pt, validation.png (truth, raw composition and network output
// of one validation pair side by side) and, with `report`, report.json (options, plan, metrics
// and the series loss and validation_psnr_db). Throws Error for bad options, a take without
// exactly one depth sensor with a paired colour camera, or a missing or damaged scan.
LiveRerenderSummary TrainLiveRerender(const std::filesystem::path& scan_take,
                                      const std::filesystem::path& scan_dir,
                                      const std::filesystem::path& model_dir,
                                      const LiveRerenderOptions& options, Report* report = nullptr);

// A trained live-rerender model.
class LiveRerenderModel {
 public:
  // Throws Error when `model_dir` holds no model or a model of another kind.
  explicit LiveRerenderModel(const std::filesystem::path& model_dir, int threads = 0);
  // A composed live mesh (`holocap live`'s recon/<set>.ply) seen by `camera`: the network's
  // view (colour premultiplied by alpha, over black). `raw` (optional) receives the raw
  // raster of the same buffers (CV_32FC3 over black).
  RenderedView Render(const Mesh& composed, const CameraModel& camera,
                      cv::Mat* raw = nullptr) const;

 private:
  RerenderNetwork network_;
  MeshRasterOptions raster_;
  int threads_ = 0;
};

// The rasterised buffers the network sees: world positions and normals left out (see above).
GBuffer LiveRerenderBuffers(const Mesh& composed, const CameraModel& camera,
                            const MeshRasterOptions& raster);

// SUCCESS when every composed frame was rendered at every camera (an image that cannot be
// written throws Error).
struct LiveRenderSummary : Summary {
  int64_t frames = 0, images = 0;
};
// Renders every recon/<set>.ply of `recon_dir` (a `holocap live` output) at the named cameras
// of `take_dir` (its calib/, or with `ground_truth_cameras` a simulated take's gt/cameras) into
// OUT/<camera>/<set>.png (8-bit, over black). Throws Error for a model of another kind, an
// unknown camera, an uncalibrated take or an empty recon directory.
LiveRenderSummary RenderLiveRecon(const std::filesystem::path& take_dir,
                                  const std::filesystem::path& recon_dir,
                                  const std::filesystem::path& model_dir,
                                  const std::vector<std::string>& cameras,
                                  const std::filesystem::path& out, bool ground_truth_cameras,
                                  Report* report = nullptr);

// Lets OpenModel (avatar/avatar.h) name "live-rerender" model directories: such a model renders
// the meshes of `holocap live`, not a viewpoint of its own, so opening one as an avatar fails
// with the command that renders it (RenderLiveRecon).
void RegisterLiveRerenderAvatarKind(AvatarKindRegistry& registry);

}  // namespace holocap
