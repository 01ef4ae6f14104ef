// Splat avatars: anisotropic 3D Gaussians (Kerbl et al. 2023) trained on the CPU against a
// take's calibrated cameras, seeded from holocap's own reconstruction of the frame, and played
// back natively by `holocap render`. The whole public interface of holocap_splat; the kernels
// it runs are in splat/kernels.h.
//
// The method, after the paper:
//   Gaussians  position, rotation (quaternion), log-scale, logit-opacity, colour as spherical
//              harmonics up to degree 3 (the degree an option, raised progressively)
//   renderer   EWA projection through the camera's pinhole intrinsics, 16x16 tiles with
//              per-tile depth-sorted lists, front-to-back compositing (splat/kernels.h)
//   loss       (1 - lambda) L1 + lambda D-SSIM, lambda = 0.2
//   optimiser  Adam with the paper's per-parameter rates (the position's decaying), densified
//              by the view-space positional gradient (clone small Gaussians, split large ones)
//              and pruned (transparent, too large, degenerate, out of the volume)
//
// What differs for a calibrated rig: the Gaussians start on the frame's reconstructed surface
// (reconstruction/: the hull, TSDF or MVS the take's plan chooses), one per surface sample,
// coloured by the training cameras that see it, not from random or SfM points. Lenses that
// distort are handled by undistorting the training images to the pinhole of the same
// intrinsics core (said in the plan).
//
// Dynamic takes train frame to frame (after 3DGStream and QUEEN): frame 0 trains fully; each
// later frame starts from the frame before's Gaussians and learns their motion and changes for a
// short budget, adds Gaussians only where the new frame's positional gradient asks
// (densification) or where the new frame's reconstructed surface lies far from every Gaussian,
// and is stored as a compact, quantised delta of the frame before (the format below) and scored
// on the held-out cameras at once. A static take (one frame set, or scene "static") trains one
// frame and nothing temporal; the plan says so.
//
// Per-frame runs (segment_frames > 0, `--segment-frames S`, what `--shard K/N` splits): a chain
// cannot be cut between machines, since a frame starts from the one before. So frame 0 is the
// run's plan (trained once, by the first task, core/frame_tasks.h PlanOnce; the others read it),
// and the later frames form segments of S: a segment's first frame starts from frame 0's
// Gaussians (for segment_start_iterations: it learns the whole motion since frame 0) and is
// stored as a delta of frame 0; the rest of the segment chain as above. A shard does whole
// segments. Every later frame starts from its base as decoded, with its own random stream and
// the rates frame 0 ended with, and trains for iterations only (never a wall-clock budget), so a
// frame's bytes are the same whichever task trains it, and a task that finds a frame complete
// (its record and delta intact) decodes it instead. model.json is written when every frame is
// complete (by the task that completes the run, or `holocap report OUT --merge`).
//
// The per-frame delta, deltas/<frame, 6 digits>.bin in the model directory: one zstd frame
// whose content is, little-endian:
//   char[4]   "HSD1"
//   uint32    previous      Gaussians of the delta's base: the frame before, or the frame
//                           model.json's delta_bases names (format_version 2; a model without
//                           one is format 1, each delta's base the frame before)
//   uint32    added         Gaussians appended in full at the end
//   uint32    sh_degree     the model's (coefficients per channel K = (degree + 1)^2)
//   float32   steps[5]      quantisation steps of the five groups below
//   uint8     kept[B]       B = ceil(previous / 8); bit i (least significant first) of byte
//                           i / 8: the frame before's Gaussian i survives (else removed)
//   then for each group g in order, position (3 values, metres), rotation (4, the quaternion's
//   raw w x y z), log_scale (3), opacity (1, logit), colour (3, the degree-0 coefficients):
//     uint8   changed[B]    bit i: Gaussian i (a survivor) changed in this group
//     int16   q[changed x values]  in order of i: value = previous + q x steps[g] (float32)
//   then the added Gaussians as gaussians.bin stores a model (each field for every added
//   Gaussian in turn: position, rotation, log_scale, opacity, sh; float32).
// The next frame is the survivors in their order, updated, then the added ones. Spherical
// harmonics above degree 0 are not changed by a delta (an added Gaussian brings its own).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <limits>
#include <memory>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/box.h"
#include "core/camera.h"
#include "core/frame_tasks.h"
#include "core/report.h"
#include "core/take_plan.h"
#include "splat/kernels.h"

namespace holocap {

class AvatarModel;         // avatar/avatar.h: what playback renders
class AvatarKindRegistry;  // avatar/avatar.h

struct SplatOptions {
  // Model.
  int sh_degree = 3;                // spherical-harmonic degree reached (0..3)
  int sh_degree_every = 1000;       // iterations between raising the active degree by one
  int64_t max_gaussians = 400000;   // densification stops adding at this count (said in the
                                    // report when it bit)
  int64_t max_seed_points = 20000;  // surface samples the model starts from
  double seed_scale_factor = 1.0;   // initial scale: this x the mean spacing of the seeds
  double initial_opacity = 0.1;     // of every seeded Gaussian

  // Data (the shared training flags; the same held-out choice as Neural Volumes).
  int image_width = 0;               // training/evaluation width (cameras rescaled); 0: native
  int heldout_cameras = 2;           // cameras never trained on, spread around the rig
  std::vector<std::string> heldout;  // or these by name (overrides heldout_cameras)
  TakeSelection take;                // frame sets, clean plate and cameras (core/take_plan.h)
  std::string recon_dir;             // seed from this reconstruction (recon/<set>.ply) instead
                                     // of running one
  std::string seed_method = "auto";  // the seed's reconstruction when run now: "auto" (TSDF
                                     // fusion with depth sensors, else multi-view stereo),
                                     // "hull", "tsdf" or "mvs" (take.color_only: no depth)
  std::string scene = "auto";        // "auto" (dynamic iff several frame sets), "static" (the
                                     // first frame set only), "dynamic"

  // Optimisation.
  double minutes = 5;  // wall-clock budget
  // > 0: a budget of the process's CPU seconds (user + system, every thread) instead of the
  // wall clock, counted from the start of LoadSplatScene: reading the take and the seed's
  // reconstruction spend it too; scoring the held-out views does not. A dynamic take shares
  // what the seed left between frame 0 and the later frames as minutes : frame_minutes.
  double cpu_minutes = 0;
  int64_t iterations = 0;       // > 0: stop after this many iterations (whichever first)
  double learning_rate = 1.0;   // multiplies every parameter group's rate (1: the paper's)
  double position_lr = 1.6e-4;  // x the scene's extent, decaying to 1/100 over the run
  double sh_lr = 2.5e-3;        // degree 0; higher degrees / 20
  double opacity_lr = 0.05;
  double scale_lr = 5e-3;
  double rotation_lr = 1e-3;
  double ssim_weight = 0.2;  // lambda of (1 - lambda) L1 + lambda D-SSIM
  // Training resolution (the plan's "resolution"): an iteration draws at most this many pixels
  // at the start (the views halved until they fit; 0: full resolution throughout), halving
  // less as training goes, full resolution from full_resolution_at of the budget on.
  int64_t pixel_budget = int64_t{640} * 480;
  double full_resolution_at = 0.5;
  // A take whose silhouettes are the frames' own alpha: every iteration composites the target
  // over a random uniform colour by the alpha and renders over that colour, so that only what
  // the alpha holds is learned (the subject, as alpha datasets publish it) and no Gaussian
  // stands for the surroundings the frames also show (3D Gaussian splatting's random
  // background). false: trained over the view's background as takes without alpha are.
  bool random_background = true;
  double min_scale_px = 0.1;  // scale floor: this many pixels' footprint at the scene's
                              // median distance (keeps covariances positive definite)
  // Bounds in the image: x the view's width, the width the image spans at the scene's median
  // distance (image width x distance / focal, metres), so that a bound is the same share of
  // the picture, the same pixels, for a 10 cm object and a 2 m person.
  double max_scale_view = 0.5;  // scale cap, x the view's width
  uint64_t seed = 1;
  FrameTaskOptions tasks;  // per-frame runs: this task's shard and --redo (never part of what
                           // decides a frame's bytes)

  // Densification and pruning.
  int64_t densify_from = 100;          // first iteration that densifies
  int64_t densify_until = 15000;       // last
  int64_t densify_every = 100;         // iterations between densifications
  double densify_gradient = 2e-4;      // mean view-space positional gradient (NDC units, as the
                                       // paper's) above which a Gaussian is cloned or split
  double split_scale_view = 0.01;      // larger than this x the view's width: split, else clone
  double prune_opacity = 0.005;        // more transparent Gaussians are removed
  double prune_scale_view = 0.1;       // larger than this x the view's width: removed
  int64_t opacity_reset_every = 3000;  // opacities lowered to 0.01 (0: never)

  // Bookkeeping.
  double eval_every_s = 20;           // held-out PSNR/SSIM every this many seconds
  int64_t eval_every_iterations = 0;  // > 0: every this many iterations instead
  double divergence_factor = 2.0;     // a loss above this x its running mean is a divergence
  double max_opacity_step = 1.0;      // a step moving the opacity logits that had a gradient by
                                      // more than this on average is a divergence too (the
                                      // paper's rate moves them 0.05)
  int max_divergences = 5;            // then training stops with FAILURE
  int64_t snapshot_every = 50;        // iterations between restore points of the guard
  int threads = 0;                    // 0: all cores

  // Frames after the first (dynamic takes). The budget of each is frame_minutes and/or
  // frame_iterations (whichever first), as minutes/iterations are frame 0's.
  double frame_minutes = 1;             // wall-clock budget of each later frame
  int64_t frame_iterations = 0;         // > 0: iterations of each later frame
  int64_t frame_densify_every = 50;     // iterations between a later frame's densifications
  double frame_position_lr_scale = 10;  // a later frame's position rate: this x position_lr
                                        // (the subject moves in few iterations), decaying to
                                        // 1/10 over the frame
  // A later frame's motion (after 3DGStream's deformation of the frame before): a translation
  // field on a grid of nodes over the subject's box, frame_motion_spacings x the seed's spacing
  // apart (at most 256 cells along the box's longest side), that moves every Gaussian by the
  // trilinear blend of its eight nodes, learned at the position rate above from the Gaussians'
  // positional gradients; each Gaussian's own position then learns at
  // frame_own_position_lr_scale x position_lr only. A body moves as a whole, so its Gaussians
  // move together and a stream codes the field, not every Gaussian's wander (with every
  // Gaussian learning its own motion at the high rate, each wanders about three of its sizes a
  // frame in no common direction). 0: every Gaussian learns its own motion.
  double frame_motion_spacings = 7;
  double frame_own_position_lr_scale = 0;
  int64_t max_added_per_frame = 1000;  // Gaussians a later frame may add (densified or seeded)
  double new_surface_spacings = 3;     // a later frame's surface sample farther than this x the
                                       // seed spacing from every Gaussian seeds a new one
  double max_frame_megabytes = 1.0;    // a delta larger than this is coarsened until it fits
  int64_t segment_frames = 0;  // > 0: a per-frame run (see the top of this file): the frames
                               // after the first in segments of this many, each segment's first
                               // frame a delta of frame 0; budgets in iterations only
  int64_t segment_start_iterations = 0;  // a segment's first frame's iterations (0: 4 x
                                         // frame_iterations: it learns the motion since frame 0)
  // Quantisation steps of a delta (coarsened together, x2 at a time, when over the bound).
  double delta_position_step_m = 5e-4;
  double delta_rotation_step = 2e-3;
  double delta_scale_step = 0.01;
  double delta_opacity_step = 0.05;
  double delta_color_step = 1.0 / 128;  // colour units ([0, 1]), of the degree-0 term

  void Check() const;  // throws Error naming the bad field and why
  nlohmann::json ToJson() const;
  int64_t SegmentStartIterations() const;  // segment_start_iterations, its default resolved
};

// One view of the scene a splat model trains on: a pinhole camera at the training size, its
// image, the subject's silhouette and the background the splats are composited over.
struct SplatView {
  std::string name;
  CameraModel camera;  // LENSMODEL_PINHOLE
  cv::Mat image;       // CV_8UC3 BGR
  cv::Mat mask;        // CV_8UC1, 255 = subject
  cv::Mat background;  // CV_8UC3 BGR
  bool heldout = false;
};

// Where the Gaussians start: points on the reconstructed surface with their colours.
struct SplatSeed {
  std::vector<Eigen::Vector3f> points;  // world, metres
  std::vector<Eigen::Vector3f> colors;  // BGR in [0, 1]
  double spacing_m = 0;                 // mean distance between neighbouring points
  std::string source;                   // for the plan ("hull of set 0, 12345 vertices")
};

// A frame after the first of a dynamic take: its images and silhouettes per view (the views'
// order) and its own reconstruction's surface samples (empty: none).
struct SplatFrame {
  int64_t set = 0;              // the take's frame-set number
  std::vector<cv::Mat> images;  // CV_8UC3 BGR
  std::vector<cv::Mat> masks;   // CV_8UC1
  SplatSeed seed;
};

struct SplatScene {
  std::vector<SplatView> views;          // frame 0's images and silhouettes
  std::vector<SplatFrame> later_frames;  // dynamic takes: frames 1, 2, ... (else empty)
  SplatSeed seed;
  Box box = Box::Empty();    // the volume the subject lives in (Gaussians leaving it are removed)
  bool alpha_masks = false;  // the silhouettes are the frames' own alpha (scored on white too)
  nlohmann::json plan = nlohmann::json::object();
  double load_cpu_s = 0;  // process CPU seconds LoadSplatScene took (the take read, the seed's
                          // reconstruction and colouring): within options.cpu_minutes
};

// One frame of a dynamic take, scored as soon as it is trained.
struct SplatFrameSummary {
  int64_t frame = 0, set = 0;
  int64_t iterations = 0;
  double seconds = 0;          // this frame's training
  double elapsed_s = 0;        // since training began, when it was scored
  double heldout_psnr_db = 0;  // held-out cameras, whole image
  double heldout_psnr_fg_db = 0;
  double background_psnr_fg_db = 0;
  double heldout_ssim = 0;
  // Composited on white against the frames' own alpha, as alpha datasets publish (NaN without
  // alpha).
  double heldout_psnr_white_db = std::numeric_limits<double>::quiet_NaN();
  int64_t gaussians = 0;
  int64_t added = 0, added_surface = 0, removed = 0, changed = 0;  // as the delta stores them
                                                                   // (added_surface: of added)
  // The new frame's surface samples farther than new_surface_spacings from every Gaussian of
  // the frame before, measured before the frame's motion is learned: a part that moved that far
  // counts as well as one never seen. What asked to be added; added_surface is what the room
  // took, and the densification of the frame gets what is left.
  int64_t surface_uncovered = 0;
  bool add_cap_reached = false;  // the frame added max_added_per_frame Gaussians
  int coarsened = 0;             // times the delta's steps were doubled to fit max_frame_megabytes
  double megabytes = 0;          // stored: gaussians.bin for frame 0, the delta for later frames
  int divergences = 0;
  nlohmann::json ToJson() const;
};

// NO_CONVERGENCE when the budget is spent; DEGENERATE when the seed is empty (an empty frame or
// reconstruction), when the held-out views show no subject, or when the held-out subject is no
// better than the background alone; FAILURE on repeated divergence or a non-finite result.
struct SplatSummary : Summary {
  nlohmann::json plan;
  int64_t iterations = 0;
  double seconds = 0;
  double first_loss = 0, last_loss = 0;
  double heldout_psnr_db = 0;        // held-out cameras, whole image
  double heldout_psnr_fg_db = 0;     // inside the subject's silhouettes (grown 3 px)
  double background_psnr_fg_db = 0;  // the same pixels as background alone
  double heldout_ssim = 0;
  double heldout_psnr_white_db = std::numeric_limits<double>::quiet_NaN();  // alpha takes
  double train_psnr_db = 0;  // the training views at the end
  int64_t gaussians = 0;
  int64_t seed_points = 0;
  bool cap_reached = false;  // densification stopped at max_gaussians
  int64_t cloned = 0, split = 0;
  int64_t pruned_transparent = 0, pruned_large = 0, pruned_degenerate = 0, pruned_outside = 0;
  int64_t floored_scales = 0;  // scale values lifted to the floor (collapsing Gaussians)
  int divergences = 0;
  // Process CPU seconds (user + system, every thread): loading the take and seeding, training
  // (everything after the seed but the held-out scoring) and the held-out scoring.
  double cpu_s_seed = 0, cpu_s_training = 0, cpu_s_scoring = 0;
  double megabytes = 0;   // the stored model (frame 0)
  double render_fps = 0;  // held-out view at the training size, after training
  // Dynamic takes: every frame, frame 0 first (static takes: frame 0 alone). The scores above
  // are the last frame's.
  std::vector<SplatFrameSummary> frames;
  bool temporal = false;  // frames after the first were trained
  // Wall time of one iteration by stage over the run's iterations (report.json metrics
  // "profile"): {"iterations", "seconds", "iterations_per_s", "stages": [{"stage",
  // "ms_per_iteration", "share"}]}, the stages projection, sort, binning, forward, loss_ssim,
  // backward, reduction, project_backward, statistic, adam, densification and other.
  nlohmann::json profile;
};

// The profile above as a table, one stage a line.
std::string FormatSplatProfile(const nlohmann::json& profile);

// Reads a take into a splat scene: the same views, held-out cameras, silhouettes and
// backgrounds as Neural Volumes (avatar/training_data.h), distortion removed, and the seed from the
// reconstruction of the first planned frame set (options.recon_dir, else one run now with the
// plan's method into model_dir/seed_recon). Throws Error for a take that cannot be trained on.
// `needed(frame, frames)` false for a later frame: only its set is kept (no images, silhouettes
// or seed; a per-frame run's task leaves the frames other tasks train).
using SplatFramesNeeded = std::function<bool(int64_t frame, int64_t frames)>;
SplatScene LoadSplatScene(const std::filesystem::path& take_dir,
                          const std::filesystem::path& model_dir, const SplatOptions& options,
                          const SplatFramesNeeded& needed = {});

// Trains on a scene into `model_dir` (model.json, gaussians.bin, cameras/, heldout/,
// report.json). `report` receives options, plan, metrics and the series heldout_psnr_db,
// heldout_psnr_fg_db, heldout_ssim, loss and gaussians against time and iteration.
SplatSummary TrainSplatsOn(const SplatScene& scene, const std::filesystem::path& model_dir,
                           const SplatOptions& options, Report* report = nullptr);
// LoadSplatScene then TrainSplatsOn; a per-frame run (options.segment_frames > 0) as
// TrainSplatFrames.
SplatSummary TrainSplats(const std::filesystem::path& take_dir,
                         const std::filesystem::path& model_dir, const SplatOptions& options,
                         Report* report = nullptr);

// A per-frame run's task (see the top of this file): frame 0 from the run's plan (made here when
// no task made it yet), then this task's segments (options.tasks.shard), each frame's delta
// written atomically and durably and its record (model_dir/frame-reports/<set>.json) last;
// complete frames are decoded, not trained again (options.tasks.redo: trained again). A whole
// run, or a task whose frames complete the run, merges it (MergeSplatFrames); a shard's own
// report goes to TaskReportPath. Throws Error for options a per-frame run cannot take.
SplatSummary TrainSplatFrames(const std::filesystem::path& take_dir,
                              const std::filesystem::path& model_dir, const SplatOptions& options,
                              Report* report = nullptr);
// The model of a per-frame run in `model_dir` (model.json, gaussians.bin, cameras/) and its
// report.json, merged from the plan and the frames' records: the same bytes as a one-process
// run's, timings aside. FAILURE naming the incomplete frame sets when a frame has no complete
// record (model.json is then not written). Throws Error when `model_dir` holds no such run.
SplatSummary MergeSplatFrames(const std::filesystem::path& model_dir, Report* report);

// A trained splat model on disk.
struct SplatModel {
  splat::Gaussians gaussians;        // frame 0
  int64_t frames = 1;                // frames it plays (later ones: deltas/<frame>.bin)
  std::vector<int64_t> bases;        // per frame, the frame its delta applies to (frame 0: -1);
                                     // empty: the frame before (format 1, chained models)
  std::vector<int64_t> frame_sets;   // the take's frame set each frame shows (model.json keeps
                                     // the first `frames`; empty in models trained without it)
  std::vector<CameraModel> cameras;  // the training views'
  Box box = Box::Empty();
  nlohmann::json plan;

  // model.json + gaussians.bin (write_gaussians false: model.json alone), atomic.
  void Save(const std::filesystem::path& dir, bool write_gaussians = true) const;
  static SplatModel Load(const std::filesystem::path& dir);  // throws Error
  // The frame `frame`'s delta applies to (-1 for frame 0).
  int64_t Base(int64_t frame) const;
  // Frame `frame` (0 .. frames - 1) reconstructed from frame 0 and the deltas of the model in
  // `dir`, following each delta's base; pass a frame on that way (and its number), e.g. the
  // frame before, to apply the deltas after it only. Throws Error.
  splat::Gaussians Frame(const std::filesystem::path& dir, int64_t frame,
                         const splat::Gaussians* previous = nullptr,
                         int64_t previous_frame = -1) const;
};

// Where frame `frame`'s delta lies in a model directory.
std::filesystem::path SplatDeltaFile(const std::filesystem::path& dir, int64_t frame);

// The quantisation steps of a delta, in the format's group order (colour: of the degree-0
// coefficient, = colour units / 0.2821).
struct SplatDeltaSteps {
  float position_m = 5e-4f, rotation = 2e-3f, log_scale = 0.01f, opacity = 0.05f, color = 0.03f;
  SplatDeltaSteps Doubled() const;
};
// Encodes `next` as a delta of `previous` (the format above, compressed). origin[i] is the
// index in `previous` that next's Gaussian i continues, or -1 for a Gaussian to add; survivors'
// origins must increase along `next`. Values beyond int16 steps are clamped.
std::string EncodeSplatDelta(const splat::Gaussians& previous, const splat::Gaussians& next,
                             const std::vector<int64_t>& origin, const SplatDeltaSteps& steps);
// The frame a delta encodes, from the frame before. Throws Error for a delta that does not
// fit `previous` or is corrupt.
splat::Gaussians ApplySplatDelta(const splat::Gaussians& previous, const std::string& delta);
// ApplySplatDelta on the delta file `file` (a regular file); its errors name the file.
splat::Gaussians ApplySplatDeltaFile(const splat::Gaussians& previous,
                                     const std::filesystem::path& file);
// Counts of a delta: survivors changed per group summed, removed, added.
struct SplatDeltaCounts {
  int64_t changed = 0, removed = 0, added = 0;
};
SplatDeltaCounts CountSplatDelta(const std::string& delta);
// Where each Gaussian of the frame a delta encodes comes from: its index in the frame before, or
// -1 for an added one (the `origin` EncodeSplatDelta was given). Throws Error for a corrupt delta.
std::vector<int64_t> SplatDeltaOrigins(const std::string& delta);

// A pinhole camera in the kernels' terms (the intrinsics core of any lens model).
splat::PinholeCamera ToPinhole(const CameraModel& camera);

// Renders Gaussians through a camera: colour CV_32FC3 BGR over `background` (empty: black),
// alpha CV_32FC1 and depth CV_32FC1 (z, metres, 0 where nothing is drawn).
struct SplatRender {
  cv::Mat color, alpha, depth;
};
SplatRender RenderSplats(const splat::Gaussians& gaussians, const CameraModel& camera,
                         const cv::Mat& background = {}, int sh_degree = splat::kMaxShDegree);
// The buffers a renderer keeps between views, so that a view of the same size allocates only
// the images it returns.
struct SplatRenderScratch {
  splat::ProjectedArrays<float> projected;
  splat::RasterState state;
};
// The same with the kernels' options (the SH degree drawn, the rasteriser) and reusable
// buffers (nullptr: allocated for this view).
SplatRender RenderSplats(const splat::Gaussians& gaussians, const CameraModel& camera,
                         const cv::Mat& background, const splat::RasterOptions& options,
                         SplatRenderScratch* scratch);

// A splat model directory opened for playback with the given kernel options (what
// RegisterSplatModelKind's OpenModel gives, with the defaults).
std::unique_ptr<AvatarModel> OpenSplatModel(const std::filesystem::path& dir,
                                            const splat::RasterOptions& options = {});

// Lets OpenModel (avatar/avatar.h) open "splat" model directories, so `holocap render` plays
// them.
void RegisterSplatAvatarKind(AvatarKindRegistry& registry);

}  // namespace holocap
