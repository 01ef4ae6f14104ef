// Reconstruction: silhouettes, visual hull, depth fusion (TSDF on hashed sparse blocks),
// multi-view stereo, marching cubes, simplification and texturing, and the per-take pipeline
// that plans which of them a rig needs and writes one mesh per frame set.
//
// Everything projects through the distortion-aware CameraModel (mrcal lens models); inner
// loops use a lookup table built from the model's own projections (see FastProjector in
// reconstruction/projector.h), accurate to well under a hundredth of a pixel.
//
// Signs: signed distances are negative inside the subject, positive in free space. Voxel
// centres sit at integer multiples of the voxel size in world coordinates; blocks hold 8³
// voxels and exist only where something was observed, so memory follows the surface area,
// not the volume of the stage.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <deque>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include "core/box.h"
#include "core/camera.h"
#include "core/frame_tasks.h"
#include "core/mesh.h"
#include "core/report.h"
#include "core/take_plan.h"

namespace holocap {

// One calibrated view of a frame set.
struct View {
  std::string name;
  CameraModel camera;  // lens and cam_from_world
  cv::Mat image;       // CV_8UC3 BGR; may be empty for hull-only use
  cv::Mat mask;        // CV_8UC1, 255 = subject; may be empty when not needed
};

// ---------------------------------------------------------------------------------------------
// Silhouettes

enum class SilhouetteMode {
  kBackgroundSubtraction,  // against a clean plate of the same camera
  kThreshold,              // bright subject on a dark background (no clean plate)
  kOtsu,                   // the same, the threshold chosen per image (Otsu's method)
  kAlpha,                  // the image's own alpha channel (CV_8UC4), exact: no morphology
};

// The morphology of thresholded silhouettes (ReconstructionOptions::silhouette_morphology).
enum class SilhouetteMorphology { kAuto, kRecipe, kNone };
const char* ToString(SilhouetteMorphology morphology);
// "auto", "recipe" or "none"; throws Error naming the choices otherwise.
SilhouetteMorphology SilhouetteMorphologyFromString(const std::string& text);

struct SilhouetteOptions {
  SilhouetteMode mode = SilhouetteMode::kBackgroundSubtraction;
  // Background subtraction: a pixel is foreground when its colour distance (Euclidean over
  // the channels) to the clean plate exceeds noise_sigmas times the noise, estimated robustly
  // (1.4826 x median of the distances, most pixels being background), and at least
  // min_difference DN.
  double noise_sigmas = 3;
  double min_difference = 8;
  // Hysteresis: pixels above this lower bound (hysteresis_sigmas x noise and at least
  // hysteresis_min_difference DN) join the foreground when connected to it, so that skin or
  // hair close to the wall's colour is not cut from the silhouette. 0 sigmas = off.
  double hysteresis_sigmas = 1.8;
  double hysteresis_min_difference = 6;
  // Threshold mode: foreground where the largest channel exceeds threshold (0..1 of full
  // scale). 0.19 is the Middlebury recipe. Otsu mode chooses it per image and, with hysteresis
  // on (hysteresis_sigmas > 0), joins pixels above half of it connected to those above it.
  double threshold = 0.19;
  // Morphology, in pixels: open (removes specks), then close as dilate/erode (fills holes and
  // thin gaps). The Middlebury recipe is dilate 10, erode 7.
  int open_px = 1;
  int dilate_px = 3;
  int erode_px = 3;
  // When > 0, the morphology's radii above are for images this many pixels wide and scale
  // with each image's width (the Middlebury recipe is for 640: at 160 px its net 3 px growth
  // would widen a limb by half).
  int morphology_width = 0;
  // Connected components smaller than this fraction of the image are dropped.
  double min_component_fraction = 0.0005;

  void Check() const;  // throws Error naming the bad field
};

// A CV_8UC1 mask (255 = foreground). `clean_plate` is required for background subtraction and
// must match the image's size and type; ignored in the other modes. Alpha mode needs a CV_8UC4
// image and keeps alpha >= 128 as it is (no morphology, no component filtering); the other
// modes read the colour channels of 1-, 3- or 4-channel images (alpha ignored). Throws Error on
// bad input.
cv::Mat ExtractSilhouette(const cv::Mat& image, const cv::Mat& clean_plate,
                          const SilhouetteOptions& options);
// Intersection over union of two masks (non-zero = set); 1 when both are empty.
double MaskIoU(const cv::Mat& a, const cv::Mat& b);
// The per-pixel, per-channel median of frames of one size and type (8-bit, 1 to 4 channels):
// the background of a camera whose subject moves (each pixel shows the background in most of
// them). Throws Error for no frames or frames that differ in size or type.
cv::Mat TemporalMedian(const std::vector<cv::Mat>& frames);

// ---------------------------------------------------------------------------------------------
// Sparse voxel volume (hashed 8³ blocks), shared by the hull and the TSDF

struct Voxel {
  float sdf = 0;     // metres (TSDF: truncated)
  float weight = 0;  // 0 = never observed: such voxels never produce a surface
  uint8_t r = 0, g = 0, b = 0;
};

inline constexpr int kBlockSide = 8;
inline constexpr int kBlockVoxels = kBlockSide * kBlockSide * kBlockSide;

struct VoxelBlock {
  Voxel voxels[kBlockVoxels];
  Voxel& at(int x, int y, int z) { return voxels[(z * kBlockSide + y) * kBlockSide + x]; }
  const Voxel& at(int x, int y, int z) const {
    return voxels[(z * kBlockSide + y) * kBlockSide + x];
  }
};

// The blocks of a volume in chunks of 64, each chunk allocated zeroed (never-observed voxels)
// and never moved: a block's address stays valid as others are added.
class BlockStore {
 public:
  static constexpr size_t kChunk = 64;
  BlockStore() = default;
  BlockStore(const BlockStore& other);
  BlockStore& operator=(const BlockStore& other);
  BlockStore(BlockStore&&) noexcept = default;
  BlockStore& operator=(BlockStore&&) noexcept = default;
  size_t size() const { return size_; }
  size_t capacity() const { return chunks_.size() * kChunk; }
  VoxelBlock& operator[](size_t i) { return chunks_[i / kChunk][i % kChunk]; }
  const VoxelBlock& operator[](size_t i) const { return chunks_[i / kChunk][i % kChunk]; }
  VoxelBlock& Add();            // a zero-weight block
  void Reserve(size_t blocks);  // their memory allocated and zeroed now

 private:
  std::vector<std::unique_ptr<VoxelBlock[]>> chunks_;
  size_t size_ = 0;
};

class SparseVolume {
 public:
  // `truncation_m` marks the values that carry no surface position: a sign change between two
  // values at +-truncation is a jump across unobserved space, not a surface (no double layers).
  // Use infinity for a field without truncation (the hull).
  SparseVolume(double voxel_m, Box bounds, double truncation_m);

  double voxel_m() const { return voxel_m_; }
  double truncation_m() const { return truncation_m_; }
  const Box& bounds() const { return bounds_; }
  size_t block_count() const { return blocks_.size(); }
  size_t memory_bytes() const;  // blocks (reserved ones too) plus the hash table
  // Memory for this many blocks allocated and zeroed now, so that adding them later touches no
  // new memory (as Open3D's VoxelBlockGrid does for its block_count at construction).
  void Reserve(size_t blocks);

  // Block coordinates of the block holding voxel (i, j, k) and the key packing them.
  static Eigen::Vector3i BlockOf(const Eigen::Vector3i& voxel);
  static uint64_t Key(const Eigen::Vector3i& block);
  static Eigen::Vector3i Unkey(uint64_t key);
  Eigen::Vector3i VoxelOf(const Eigen::Vector3d& point_in_world) const;  // nearest centre
  Eigen::Vector3d CenterOf(const Eigen::Vector3i& voxel) const;
  // Whether a block's voxel centres can lie in the bounds.
  bool BlockInBounds(const Eigen::Vector3i& block) const;

  VoxelBlock* Find(const Eigen::Vector3i& block);
  const VoxelBlock* Find(const Eigen::Vector3i& block) const;
  VoxelBlock& Allocate(const Eigen::Vector3i& block);  // zero-weight voxels when new
  const Voxel* FindVoxel(const Eigen::Vector3i& voxel) const;
  // Visits every block (coordinates, data); not thread-safe against allocation.
  void ForEachBlock(const std::function<void(const Eigen::Vector3i&, const VoxelBlock&)>& fn) const;
  std::vector<Eigen::Vector3i> BlockCoordinates() const;

  // Trilinear sdf at a point; false when any of the 8 voxels around it is unobserved.
  bool Sample(const Eigen::Vector3d& point_in_world, double* sdf) const;

 private:
  double voxel_m_;
  Box bounds_;
  double truncation_m_;
  std::unordered_map<uint64_t, size_t> index_;
  BlockStore blocks_;
  std::vector<Eigen::Vector3i> coordinates_;
};

// ---------------------------------------------------------------------------------------------
// Visual hull

struct HullOptions {
  double voxel_m = 0.004;  // leaf voxel edge
  Box bounds;              // the capture volume; nothing outside is carved in
  // Conservative mode: a point survives when at most this many views put it outside their
  // silhouette (1 tolerates one bad silhouette, such as an empty or truncated mask).
  int tolerated_bad_views = 0;
  int min_views = 2;       // a point seen (inside the image) by fewer views is outside
  double margin_px = 1.0;  // silhouettes grown by this much before carving (edge pixels);
                           // negative shrinks them
  // The smallest subject a hull is: a ball of the hull's volume must span at least this many
  // pixels across in the views (the median over the views that see the hull's centre). The
  // silhouettes' morphology (3 px) and the margin reshape anything smaller by half its size:
  // such a hull is where specks or edges of disagreeing silhouettes meet, not a subject. A
  // person at 3 m spans ~25 px in a 160 px image, Middlebury's 10 cm dinosaur 320 px.
  double min_subject_px = 8;
  int threads = 0;  // 0: all cores

  void Check() const;
};

struct HullSummary : Summary {
  int64_t octree_cells = 0;    // cells tested before reaching blocks
  int64_t surface_blocks = 0;  // blocks evaluated voxel by voxel
  int64_t inside_blocks = 0;   // blocks wholly inside, never evaluated voxel by voxel
  double volume_m3 = 0;
  double subject_px = 0;  // a ball of volume_m3 across, in pixels (median over the views)
  double seconds = 0;
};

// The hull as a signed field (metres, from each view's 2D distance transform scaled by depth
// over focal length; the intersection is the max over views, the conservative mode the
// (k+1)-th largest). Stored only in blocks near the surface; wholly-inside blocks are a set.
struct VisualHull {
  std::unique_ptr<SparseVolume> volume;
  std::unordered_set<uint64_t> inside_blocks;
  // The signed field at a point (metres, trilinear in evaluated blocks): -infinity in blocks
  // wholly inside, +infinity elsewhere outside.
  double Field(const Eigen::Vector3d& point_in_world) const;
  // Whether a point lies in the hull, allowing `tolerance_m` outside its surface.
  bool Contains(const Eigen::Vector3d& point_in_world, double tolerance_m = 0) const;
  // The box of the voxel centres inside the hull; empty for an empty hull.
  Box Extent() const;
};

// Carves through an octree of cells down to 8³-voxel blocks, evaluating voxels only in blocks
// that the surface crosses. Views need camera and mask. Throws Error for views without masks
// or with masks of the wrong size. An empty hull, or one smaller than options.min_subject_px,
// is reported kDegenerate.
VisualHull ComputeVisualHull(const std::vector<View>& views, const HullOptions& options,
                             HullSummary* summary = nullptr);

// The closing a take's thresholded silhouettes need, measured on their boundaries (the rule
// and why: reconstruction/silhouette_morphology.cpp). Closing by a disk of radius r fills
// background narrower than 2r; a clean boundary gains steadily with r (its concave corners and
// narrow concavities), a boundary that a threshold cut holes, cracks or bites into gains a jump
// at the radius that spans them and then returns to the steady rate.
struct ClosingChoice {
  int close_px = 0;  // the closing's radius, in the images' own pixels (0: none)
  // Per radius 0..max (radii_px): the area the closing adds in fills that are holes or long
  // and narrow (cracks, bites, narrow concavities), summed over the views and divided by their
  // boundary pixels (a mean depth, px), and how many such fills.
  std::vector<int> radii_px;
  std::vector<double> fill_px;
  std::vector<int> fills;
  double steady_step_px = 0;  // the median step of fill_px from one radius to the next
  double min_jump_px = 0;     // the smallest step counted as a jump (besides twice the steady)
  int holes = 0;              // background regions the masks enclose, over the views
  std::string why;            // the rule and the measured numbers it read

  nlohmann::json ToJson() const;
  static ClosingChoice FromJson(const nlohmann::json& json);  // throws on missing fields
};

// The closing for thresholded, unclosed `masks` (CV_8UC1, 255 = subject; the views of one
// frame set, or a few): radii 1..max_radius_px (2 or more) are measured; a step of the fill
// curve larger than both twice its median step and `min_jump_px` at a radius up to half the
// largest is a jump, and the closing is the last radius of the first run of jumps; 0 (none)
// without one. Deterministic; throws Error on no masks or bad arguments.
ClosingChoice ChooseClosing(const std::vector<cv::Mat>& masks, int max_radius_px,
                            double min_jump_px);

// ---------------------------------------------------------------------------------------------
// Depth fusion

struct TsdfOptions {
  double voxel_m = 0.004;        // voxel edge
  double truncation_voxels = 4;  // truncation distance in voxels
  // A frame allocates and updates the blocks within this distance (voxels, along each
  // measurement's ray, at most the truncation) of its measurements, and always those holding the
  // voxels within one voxel of each measured point's cell (unless the band is the whole
  // truncation, which reaches them): the voxels the surface needs. Their voxels take the whole
  // truncation band; voxels further out in blocks it does not reach are left as they are
  // (studio8 at 4 mm, 2 maps with the background carving: the whole band 3990 blocks, 2 voxels
  // 3658, 1 voxel 3502, with completeness 4.19, 4.20 and 4.27 mm).
  double band_voxels = 1;
  float max_weight = 64;     // weights are capped so that the volume can follow change
  Box bounds;                // nothing outside is allocated
  double depth_min_m = 0.2;  // measurements outside [min, max] are ignored
  double depth_max_m = 8.0;
  // Sensor noise sigma(z) = depth_noise_k * z^2 (the simulated sensors' model; structured
  // light and ToF sensors follow it closely). It sets each measurement's weight
  // (sigma(1 m)/sigma(z))^2 and the range of the edge-preserving pre-filter.
  double depth_noise_k = 0.0012;
  // Edge-preserving smoothing of each depth map before fusion: pixels within this radius whose
  // depth is within 3 sigma(z) are averaged. 0 = off.
  int smoothing_radius_px = 3;
  // Measurements whose surface is seen more obliquely than this (from the depth map's own
  // normals) are dropped: at grazing incidence depth is unreliable and smears surfaces.
  double max_incidence_deg = 80;
  // With a foreground mask, a pixel outside it is free space: in front of its measurement (the
  // room) or, where it measured nothing, all along its ray (the mask says the subject is not
  // there). Voxels of the blocks a frame touches that lie more than the truncation in front of
  // it take +truncation, as a measurement would give them, so the surface closes at the
  // subject's silhouette instead of ending where a sensor's band ends.
  bool carve_background = true;
  // ... weighing this fraction of a measurement at the voxel's depth: where no sensor measured
  // the voxel it decides, where one did (a limb another sensor sees at a grazing angle, which
  // its mask leaves out) the measurement does (studio8: 0.1 beats 1 and 0.01 with 2 and with
  // 8 depth sensors).
  double carve_weight = 0.1;
  int threads = 0;  // 0: all cores
  // Blocks whose memory the volume allocates and zeroes when it is made (SparseVolume::Reserve);
  // 0: each as a frame first touches it.
  size_t reserve_blocks = 0;

  void Check() const;
};

struct TsdfFrameStats {
  int64_t valid_pixels = 0;     // finite, in range, foreground
  int64_t rejected_pixels = 0;  // NaN, inf, <= 0, out of range, grazing
  int64_t blocks_touched = 0;
  int64_t voxels_updated = 0;  // by a measurement or as free space
  int64_t voxels_carved = 0;   // ... of them as free space before a background pixel
  double seconds = 0;
  // The stages of `seconds`: the depth map prepared (filters, free space), blocks found and
  // allocated, voxels updated.
  double prepare_seconds = 0, allocate_seconds = 0, fuse_seconds = 0;
};

struct CompletionStats {
  int64_t blocks_added = 0;   // blocks no depth map reached
  int64_t voxels_filled = 0;  // unobserved voxels given the completion field
  int64_t voxels_carved = 0;  // ... of them inside the hull but in a depth map's free space
  double seconds = 0;
};

// A TSDF volume with colour.
class TsdfVolume {
 public:
  explicit TsdfVolume(const TsdfOptions& options);
  // Fuses one depth map (CV_32F z-depth in metres; NaN, 0, negative and inf mean no
  // measurement). `foreground` (CV_8U, optional) keeps only its non-zero pixels. With `color`
  // (CV_8UC3 BGR) and `color_camera`, voxels also average colour. Throws Error when sizes do
  // not match the cameras.
  TsdfFrameStats Integrate(const cv::Mat& depth_m, const CameraModel& depth_camera,
                           const cv::Mat& foreground = {}, const cv::Mat& color = {},
                           const CameraModel* color_camera = nullptr);
  // Hull-constrained completion, as studio pipelines close what their depth sensors miss:
  // every voxel no depth map observed, in the blocks around `hull`'s surface and in the
  // volume's own, takes the hull's signed field intersected with the free space the depth maps
  // saw (a point in front of a measured surface, the room's included, is outside by the
  // projective distance Integrate uses), truncated, with weight `weight` (a measurement at 1 m
  // weighs 1). Observed voxels keep their values, so the sensors' surface is unchanged where
  // they saw it. `depth_maps` are the sensors' raw z-depth maps, background included; they are
  // smoothed like Integrate's. Throws Error when a map does not match its camera.
  CompletionStats CompleteFromHull(const VisualHull& hull,
                                   const std::vector<std::pair<CameraModel, cv::Mat>>& depth_maps,
                                   float weight = 1e-3f);
  const SparseVolume& volume() const { return volume_; }
  const TsdfOptions& options() const { return options_; }

 private:
  TsdfOptions options_;
  SparseVolume volume_;
};

// ---------------------------------------------------------------------------------------------
// Meshing

struct MeshingOptions {
  float min_weight = 0;        // corners at or below this weight end a surface (0: unobserved)
  double simplify_cell_m = 0;  // > 0: vertex clustering on cells of this size after meshing
  bool normals = true;         // compute per-vertex normals
  void Check() const;
};

// Marching cubes over every block, welding vertices across block boundaries so the surface is
// seamless. Cubes with an unobserved corner, or whose sign change is a jump between truncated
// values, give no triangles. Colours come from the voxels when they carry any.
Mesh ExtractMesh(const SparseVolume& volume, const MeshingOptions& options = {});

// Vertex-clustering simplification: vertices in one cell of size `cell_m` merge into their
// mean (colour averaged); triangles that collapse are dropped, duplicates removed.
Mesh SimplifyMesh(const Mesh& mesh, double cell_m);

// ---------------------------------------------------------------------------------------------
// Multi-view stereo

struct MvsOptions {
  // Source views per reference view: the nearest by the angle the two views make at the
  // subject (their baseline as the subject sees it) plus how much their distances differ
  // (ln of the ratio), among those within [min_angle_deg, max_angle_deg]. Closer than the
  // minimum, a pair triangulates nothing; wider than the maximum, the source sees what the
  // reference faces at a grazing angle, or its far side: such views fill up only a sparse
  // rig's reference views that have fewer than `neighbors` within it, and never from 90
  // degrees. On a ring of eight, the two at 45 degrees qualify and the two at 90 fill up; on
  // Middlebury's ring of 16, four qualify.
  int neighbors = 4;
  double min_angle_deg = 3;
  double max_angle_deg = 60;
  // Views whose depth is searched (reference views): at most this many, spread over the
  // directions the views see the subject from by farthest-point sampling (the first view,
  // then each time the view farthest in angle from those chosen); every view still serves as
  // a source. 0: every view. Each reference view costs one sweep; fewer views fuse a little
  // less of the subject's outline (the simulator's knot seen by 97 views on a sphere, true
  // cameras: held-out IoU 0.9893 with 40, 0.9912 with 60; bench/mvs_many_views_results.txt).
  int max_reference_views = 60;
  // The sweep runs tile by tile: each tile of this side (pixels) searches only the planes its
  // pixels' ranges along their rays reach.
  int tile_px = 32;
  // NCC window is (2r+1)²: 5x5 keeps a window on one surface where the subject spans only a
  // few hundred pixels (7x7 straddles limbs and edges and loses a quarter of the Chamfer).
  int window_radius = 2;
  double depth_step_px = 0.5;   // plane spacing: the disparity step in the nearest source view
  double hull_margin_m = 0.02;  // the search starts this far in front of the hull's surface
  double search_depth_m = 0.2;  // ... and reaches this far behind it
  double min_ncc = 0.5;         // best mean NCC below this leaves the pixel empty
  int best_k = 2;               // cost = mean of the k best source NCCs (occlusion-robust)
  // Geometric consistency: a depth survives when at least min_consistent_views source depth
  // maps agree: reprojection within max_reprojection_px and depth within max_relative_depth.
  int min_consistent_views = 1;
  double max_reprojection_px = 1.0;
  double max_relative_depth = 0.01;
  // The least a subject gives: this fraction of the pixels searched (those inside the hull's
  // silhouette in each view) must keep a consistent depth, else the stereo is DEGENERATE.
  // A textured subject keeps most of them (54 % on Middlebury's dinosaur, 56 % on studio8's ring
  // at a twentieth of its size); views that do not see one surface keep a few by chance (1.3 %
  // with the subject's pixels replaced by noise that differs between views).
  double min_consistent_fraction = 0.1;
  int threads = 0;  // 0: all cores

  void Check() const;
};

struct MvsSummary : Summary {
  int64_t reference_views = 0;  // views whose depth was searched
  int64_t pixels_searched = 0;
  int64_t pixels_matched = 0;     // best NCC above min_ncc
  int64_t pixels_consistent = 0;  // surviving the geometric check
  int64_t planes = 0;             // depth planes of the reference views' ladders, summed
  // Pixels x planes x source views warped and scored (window borders included), summed.
  int64_t pixel_hypotheses = 0;
  double seconds = 0;
  // Where the seconds went: the hull's depth range per view (its depth rendered, the rays
  // marched through it) and the sweeps, each summed over the reference views (one thread
  // each); the consistency check's wall clock.
  double range_seconds = 0, sweep_seconds = 0, consistency_seconds = 0;
};

// Which views multi-view stereo searches and against which: the reference views and, for
// each view, its source views (matched against) and its check views (reference views whose
// depth confirms its own). Indices into the views; empty lists for views that are not
// references.
struct MvsViewChoice {
  std::vector<int> references;
  std::vector<std::vector<int>> sources;
  std::vector<std::vector<int>> checks;
  std::string why;  // how the references were chosen, in words
};
// The choice for cameras around a subject at `subject_in_world` (MvsOptions: neighbors,
// min/max_angle_deg, max_reference_views). A view that does not see the subject's centre is
// no one's source.
MvsViewChoice ChooseMvsViews(const std::vector<CameraModel>& cameras,
                             const Eigen::Vector3d& subject_in_world, const MvsOptions& options);

// What a stereo run will cost, from the views' silhouettes before it runs: pixels (each
// reference view's silhouette) x depth planes (the hull margin and search depth over the plane
// step its nearest source gives at its distance to the subject) x source views, at a rate
// measured on this machine now (one tile swept against synthetic views), over `threads`.
struct MvsEstimate {
  int64_t pixel_hypotheses = 0;
  double seconds_per_hypothesis = 0;  // per pixel x plane x source, one thread
  int threads = 1;
  double seconds = 0;  // the sweeps' wall clock, estimated
};
MvsEstimate EstimateMvs(const std::vector<View>& views, const MvsViewChoice& choice,
                        const Eigen::Vector3d& subject_in_world, const MvsOptions& options,
                        int threads);
// Seconds per pixel x plane x source view of the sweep on this machine now, one thread.
double MeasureSweepRate(const MvsOptions& options);

// Plane-sweep depth (z-depth, metres, NaN = none) for each reference view of `choice` (chosen
// here around the hull's centre when null), searched inside the hull's depth range along each
// ray and cross-checked against its check views; an empty Mat for every other view. Views
// need image, mask and camera. Reference views run in parallel across cores; with a
// `progress_label`, a Progress line counts them (core/progress.h).
std::vector<cv::Mat> ComputeMvsDepth(const std::vector<View>& views, const VisualHull& hull,
                                     const MvsOptions& options, MvsSummary* summary = nullptr,
                                     const MvsViewChoice* choice = nullptr,
                                     const std::string& progress_label = "");

// ---------------------------------------------------------------------------------------------
// Texturing and export

struct TextureOptions {
  int texels_per_cell = 8;             // atlas: two triangles share one square cell of this side
  double min_cos_incidence = 0.1;      // views seeing a surface more obliquely do not contribute
  double depth_tolerance_m = 0.01;     // visibility: the view's own rendered depth under the image
                                       // pixels a lookup reads is within this (plus what the
                                       // surface's slope spans over them) of the point's: no
                                       // occluder, no silhouette edge
  int occlusion_scale = 2;             // occlusion buffers at this multiple of each image's size
  int max_views = 3;                   // blend the best views (highest incidence cosine)
  bool fill_unseen = true;             // vertices no view sees take their seen neighbours' colour,
                                       // diffused over the mesh's edges
  int fill_smoothing_iterations = 20;  // Jacobi smoothing of the filled colours afterwards
  bool atlas = true;                   // also build the atlas (vertex colour is always set)
  void Check() const;
};

struct TexturedMesh {
  Mesh mesh;                               // with per-vertex colour
  std::vector<Eigen::Vector2f> corner_uv;  // 3 per face, glTF convention (v down)
  cv::Mat atlas;                           // CV_8UC3 BGR; empty without an atlas
  int64_t seen_vertices = 0;               // coloured from the views
  int64_t filled_vertices = 0;             // seen by no view, coloured from seen neighbours
  int64_t uncoloured_vertices = 0;         // neither (no seen vertex in their part of the mesh,
                                           // or filling off): mid grey
  nlohmann::json Metrics() const;          // counts and fractions for reports
};

// Colours every vertex (and every atlas texel) by blending the views that see it, weighted by
// incidence; visibility from each view's own rendered depth of the mesh. Vertices no view sees
// are filled from their seen neighbours over the mesh (front propagation, then smoothing).
TexturedMesh TextureMesh(const Mesh& mesh, const std::vector<View>& views,
                         const TextureOptions& options = {});

// Binary glTF 2.0 (.glb): positions, normals, vertex colours and, with an atlas, texture
// coordinates and the atlas as an embedded PNG. Atomic write (`durable`: fsync'ed, core/fs.h).
void WriteGlb(const std::filesystem::path& file, const TexturedMesh& textured,
              bool durable = false);

// Renders a mesh's silhouette into a camera (triangles through the lens model): CV_8U, 255 =
// covered. Used to compare hulls with held-out views.
cv::Mat RenderSilhouette(const Mesh& mesh, const CameraModel& camera);
// Renders a mesh's z-depth (metres, NaN where empty) into a camera.
cv::Mat RenderDepth(const Mesh& mesh, const CameraModel& camera);

// Foreground of a depth map against a depth clean plate (the empty room): pixels measured in
// front of the plate by more than 4 sigma(z) of the noise model and at least 2 cm, or where the
// plate has no measurement in a 7x7 neighbourhood (out of range); isolated pixels dropped.
// CV_8U, 255 = foreground.
cv::Mat DepthForeground(const cv::Mat& depth_m, const cv::Mat& clean_plate_m, double depth_noise_k);

// ---------------------------------------------------------------------------------------------
// Accuracy against ground truth

struct SurfaceErrors {
  double accuracy_mm = 0;      // mean distance, reconstruction -> truth
  double completeness_mm = 0;  // mean distance, truth -> reconstruction
  double chamfer_mm = 0;       // mean of the two
  double precision = 0;        // fraction of reconstruction within the threshold of truth
  double recall = 0;           // fraction of truth within the threshold of reconstruction
  double fscore = 0;           // harmonic mean of precision and recall
  int64_t samples = 0;
};
// Distances between surfaces sampled uniformly (area-weighted, `samples` each way).
// `truth_filter`, when set, keeps only truth samples it accepts (e.g. those a sensor saw).
SurfaceErrors CompareSurfaces(const Mesh& reconstruction, const Mesh& truth,
                              double fscore_threshold_m = 0.005, size_t samples = 40000,
                              const std::function<bool(const Eigen::Vector3d&)>& truth_filter = {});

// A truth filter for CompareSurfaces: points on the outer surface of a truth made of closed
// parts that overlap (the simulated subject is a union of body parts, each a closed mesh): a
// point more than `tolerance_m` inside another closed part is buried in the solid, surface no
// sensor can see and no reconstruction of the subject has. Open parts are kept as they are.
std::function<bool(const Eigen::Vector3d&)> OnOuterSurface(const Mesh& truth,
                                                           double tolerance_m = 1e-4);

// A truth filter for CompareSurfaces: points that one of the (camera, true z-depth map) pairs
// sees, i.e. whose depth there matches the map within `tolerance_m`.
std::function<bool(const Eigen::Vector3d&)> SeenInDepthMaps(
    const std::vector<std::pair<CameraModel, cv::Mat>>& true_depths, double tolerance_m = 0.01);

// ---------------------------------------------------------------------------------------------
// The per-take pipeline

enum class ReconstructionMethod { kAuto, kHull, kTsdf, kMvs };
const char* ToString(ReconstructionMethod method);
ReconstructionMethod ReconstructionMethodFromString(const std::string& text);  // throws Error

struct ReconstructionOptions {
  ReconstructionMethod method = ReconstructionMethod::kAuto;  // auto: depth -> tsdf, else mvs
  // TSDF and hull voxel (the hull for MVS uses 2x); 0: the plan's (implied by its bounds).
  double voxel_m = 0;
  // Which frame sets, cameras, clean plates, bounds and silhouette source: the TakePlan given
  // beside these options. `bounds`, when set, replaces the plan's (a stage's own box).
  std::optional<Box> bounds;
  // Bounds from the rig (not the user's) are tightened to a coarse hull of up to this many
  // frame sets, spread over the take, grown by a margin (0: the rig's box as it is).
  int tighten_sets = 8;
  // Plausibility: a frame's hull touching this many faces of its bounds, or filling more than
  // this fraction of bounds it was not tightened to, cannot be a subject inside them
  // (silhouettes that do not separate one); DEGENERATE.
  int max_touched_faces = 4;
  double max_fill_fraction = 0.6;
  // ... and a mesh wider than this multiple of the cameras' shared view on any axis.
  double max_view_ratio = 1.5;
  // ... and a hull whose silhouette agrees with a quarter of the views' own or more (IoU in
  // each view) less than this: silhouettes that keep background differing from view to view.
  double min_silhouette_agreement = 0.5;
  // A background model (the plan's temporal median) whose middle frame differs from it in
  // less than this fraction of the pixels (the median of the cameras) holds a subject that did
  // not move: the run falls back to a threshold chosen per image and says so.
  double min_moving_fraction = 0.001;
  SilhouetteOptions silhouette;
  // Thresholded silhouettes (Otsu or a given level) take this morphology instead of
  // `silhouette`'s: kAuto the closing ChooseClosing measures on the first frame set's unclosed
  // silhouettes (none where their boundary is clean; no growth: Otsu's hysteresis already
  // takes the pixels connected to the subject down to half its level), kRecipe the
  // Middlebury README's (dilate 10 px, erode 7 px at 640 px, no opening), kNone none.
  SilhouetteMorphology silhouette_morphology = SilhouetteMorphology::kAuto;
  // The largest closing kAuto measures, in pixels at 640 px wide (the recipe's dilation),
  // scaled to the images' width.
  int max_close_px_at_640 = 10;
  // A step of the fill curve counts as a jump only above this depth (px per boundary pixel)
  // as well as above twice the curve's steady step: 0.05 px is a 2 px crack 10 px long per
  // 400 px of boundary, less than any closing would change in a hull.
  double min_closing_jump_px = 0.05;
  HullOptions hull;  // voxel and bounds are set from the fields above
  // Voxel and bounds likewise; the depth range fused is the plan's (from half the nearest to
  // four times the farthest z-depth of the bounds in the sensors whose depth is fused), so
  // tsdf.depth_min_m and depth_max_m apply only to bounds behind every camera. A frame whose
  // measured depth lies out of that range (fewer than a tenth of its pixels fused) is the
  // colour cameras' hull alone, said in its message and the plan's "depth_fusion", or
  // DEGENERATE without a hull.
  TsdfOptions tsdf;
  // TSDF: what the depth sensors did not see is completed from the colour cameras' visual hull
  // carved by the sensors' free space (TsdfVolume::CompleteFromHull). Needs silhouettes, so a
  // clean plate or threshold silhouettes, and two colour cameras; the plan says when it is off.
  bool tsdf_hull_completion = true;
  // Silhouettes of the completion's hull grow by this many pixels; negative shrinks them. The
  // completion wants the surface, not a container: a silhouette's edge pixels are partly
  // background, so its boundary lies half a pixel inside them on average. (The hull that MVS
  // searches and the hull method use options.hull.margin_px, a conservative margin.)
  double completion_margin_px = -0.5;
  MvsOptions mvs;
  MeshingOptions meshing;
  TextureOptions texture;
  bool write_glb = true;  // recon/<set>.glb beside recon/<set>.ply
  // On takes with ground truth, the first frame is also reconstructed at these voxel sizes to
  // record error against time (empty: none).
  std::vector<double> sweep_voxels_m = {0.016, 0.008};
  int threads = 0;  // 0: all cores; frames run in parallel when there are
                    // at least as many frames as threads
  // This task's part of the run's frame sets (--shard K/N) and whether complete frames are
  // done again (core/frame_tasks.h). The run is planned from all its sets whatever the shard,
  // so every frame's outputs are the same bytes however the run is split.
  FrameTaskOptions tasks;

  void Check() const;
  nlohmann::json ToJson() const;
};

struct FrameResult : Summary {
  int64_t set = 0;
  double seconds = 0;
  int64_t vertices = 0;
  int64_t faces = 0;
  nlohmann::json metrics;  // per stage, and gt.* on simulated takes
};

struct ReconstructionSummary : Summary {
  nlohmann::json plan;  // the TakePlan's keys and the method's
  std::vector<FrameResult> frames;
  double seconds = 0;
};

// Reconstructs the plan's frame sets of a take into `out` (recon/<set:06d>.ply and .glb,
// report.json) with the plan's cameras (calib/, or gt/ on an uncalibrated simulated take).
// SUCCESS when every frame set gave a surface; DEGENERATE when any did not (the failed sets are
// named in the message and each frame's result is in the metrics; the others' meshes are
// written), when the cameras do not see the bounds, or when the
// result is implausible (a hull filling its bounds, a mesh larger than the cameras' shared
// view). Held-out cameras of the plan are never reconstructed from; the mesh's silhouette in
// each is compared with the plan's silhouette of its image (metrics "heldout_iou"). Throws Error
// for bad options, a method the take's sensors cannot support, or a planned frame set missing a
// frame the method reads.
// The background model of a plan whose silhouettes are kBackgroundModel: each colour camera's
// TemporalMedian over plan.background_sets (BGR), its clean plate from then on. When the
// cameras' median middle frame differs from its model in less than `min_moving_fraction` of
// its pixels (`silhouette`'s subtraction), the subject did not move: the plan falls back to
// Otsu with the reason, and nothing is returned. Empty for other sources.
std::map<std::string, cv::Mat> LearnBackgroundModel(const Take& take, TakePlan& plan,
                                                    const SilhouetteOptions& silhouette,
                                                    double min_moving_fraction);

// Each frame set's outputs are written atomically and durably, then its record
// (OUT/frame-reports/<set>.json, core/frame_tasks.h) last; a frame whose record is complete for
// the same options and plan is skipped (options.tasks.redo: done again). A task of a sharded
// run (options.tasks.shard) does its part of the plan's sets and writes its own report to
// TaskReportPath; report.json is the run's, merged from every frame's record once all are
// complete (by the task that completes the run, or by MergeReconstruction).
ReconstructionSummary ReconstructTake(const Take& take, const TakePlan& plan,
                                      const std::filesystem::path& out,
                                      const ReconstructionOptions& options,
                                      Report* report = nullptr);
// The same, opening and planning the take first.
ReconstructionSummary ReconstructTake(const std::filesystem::path& take_dir,
                                      const TakeSelection& selection,
                                      const std::filesystem::path& out,
                                      const ReconstructionOptions& options,
                                      Report* report = nullptr);

// The run's report.json in `out` merged from its frames' records (core/frame_tasks.h): the same
// bytes as a one-process run's, timings aside. FAILURE naming the incomplete frame sets when a
// frame has no complete record (a task that was killed or never ran); rerunning its shard
// redoes only those. Throws Error when `out` is not a reconstruction run's output.
ReconstructionSummary MergeReconstruction(const std::filesystem::path& out, Report* report);

}  // namespace holocap
