// The per-take pipeline: plan the methods from the rig, reconstruct frame sets in parallel,
// write meshes and report.json, measure against ground truth where the take has it.
#include <omp.h>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <exception>
#include <limits>
#include <map>
#include <mutex>
#include <numeric>
#include <optional>

#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/image.h"
#include "core/mesh.h"
#include "core/progress.h"
#include "core/projector.h"
#include "core/rig_alignment.h"
#include "core/take.h"
#include "core/threads.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

const char* ToString(ReconstructionMethod method) {
  switch (method) {
    case ReconstructionMethod::kAuto:
      return "auto";
    case ReconstructionMethod::kHull:
      return "hull";
    case ReconstructionMethod::kTsdf:
      return "tsdf";
    case ReconstructionMethod::kMvs:
      return "mvs";
  }
  return "?";
}

ReconstructionMethod ReconstructionMethodFromString(const std::string& text) {
  for (auto m : {ReconstructionMethod::kAuto, ReconstructionMethod::kHull,
                 ReconstructionMethod::kTsdf, ReconstructionMethod::kMvs}) {
    if (text == ToString(m)) return m;
  }
  Fail("unknown reconstruction method '", text, "' (known: auto, hull, tsdf, mvs)");
}

const char* ToString(SilhouetteMorphology morphology) {
  switch (morphology) {
    case SilhouetteMorphology::kAuto:
      return "auto";
    case SilhouetteMorphology::kRecipe:
      return "recipe";
    case SilhouetteMorphology::kNone:
      return "none";
  }
  return "?";
}

SilhouetteMorphology SilhouetteMorphologyFromString(const std::string& text) {
  for (auto m :
       {SilhouetteMorphology::kAuto, SilhouetteMorphology::kRecipe, SilhouetteMorphology::kNone}) {
    if (text == ToString(m)) return m;
  }
  Fail("unknown silhouette morphology '", text, "' (known: auto, recipe, none)");
}

void ReconstructionOptions::Check() const {
  HOLOCAP_CHECK_OPTION_GE(voxel_m, 0, "in (0, 1) m, or 0 for the plan's");
  HOLOCAP_CHECK_OPTION_LT(voxel_m, 1, "in (0, 1) m, or 0 for the plan's");
  HOLOCAP_CHECK_OPTION(!bounds || bounds->valid(), bounds, "an empty box");
  HOLOCAP_CHECK_OPTION_GE(tighten_sets, 0);
  HOLOCAP_CHECK_OPTION_IN(max_touched_faces, 1, 7, "7: never");
  HOLOCAP_CHECK_OPTION_GT(max_fill_fraction, 0);
  HOLOCAP_CHECK_OPTION_LE(max_fill_fraction, 1);
  HOLOCAP_CHECK_OPTION_GE(max_view_ratio, 1);
  HOLOCAP_CHECK_OPTION_GE(min_moving_fraction, 0);
  HOLOCAP_CHECK_OPTION_LT(min_moving_fraction, 1);
  HOLOCAP_CHECK_OPTION_GE(min_silhouette_agreement, 0);
  HOLOCAP_CHECK_OPTION_IN(max_close_px_at_640, 2, 50);
  HOLOCAP_CHECK_OPTION_GE(min_closing_jump_px, 0);
  HOLOCAP_CHECK_OPTION_LT(min_closing_jump_px, 10);
  HOLOCAP_CHECK_OPTION_LT(min_silhouette_agreement, 1);
  for (double size_m : sweep_voxels_m) {
    HOLOCAP_CHECK_OPTION(size_m > 0 && size_m < 1, sweep_voxels_m, "each in (0, 1) m");
  }
  HOLOCAP_CHECK_OPTION_GE(threads, 0);
  tasks.Check();
  HOLOCAP_CHECK_OPTION_GT(completion_margin_px, -10);
  HOLOCAP_CHECK_OPTION_LT(completion_margin_px, 100);
  silhouette.Check();
  mvs.Check();
  meshing.Check();
  texture.Check();
}

nlohmann::json ReconstructionOptions::ToJson() const {
  auto box = [](const Box& b) {
    return nlohmann::json{{"min", {b.min.x(), b.min.y(), b.min.z()}},
                          {"max", {b.max.x(), b.max.y(), b.max.z()}}};
  };
  return {{"method", ToString(method)},
          {"voxel_m", voxel_m},
          {"bounds", bounds ? box(*bounds) : nlohmann::json("the plan's")},
          {"tighten_sets", tighten_sets},
          {"max_touched_faces", max_touched_faces},
          {"max_fill_fraction", max_fill_fraction},
          {"max_view_ratio", max_view_ratio},
          {"min_silhouette_agreement", min_silhouette_agreement},
          {"min_moving_fraction", min_moving_fraction},
          {"silhouette_morphology", ToString(silhouette_morphology)},
          {"max_close_px_at_640", max_close_px_at_640},
          {"min_closing_jump_px", min_closing_jump_px},
          {"silhouette",
           {{"mode", silhouette.mode == SilhouetteMode::kThreshold ? "threshold"
                     : silhouette.mode == SilhouetteMode::kOtsu    ? "otsu"
                     : silhouette.mode == SilhouetteMode::kAlpha   ? "alpha"
                                                                   : "background"},
            {"noise_sigmas", silhouette.noise_sigmas},
            {"min_difference", silhouette.min_difference},
            {"hysteresis_sigmas", silhouette.hysteresis_sigmas},
            {"hysteresis_min_difference", silhouette.hysteresis_min_difference},
            {"threshold", silhouette.threshold},
            {"open_px", silhouette.open_px},
            {"dilate_px", silhouette.dilate_px},
            {"erode_px", silhouette.erode_px},
            {"morphology_width", silhouette.morphology_width}}},
          {"hull",
           {{"tolerated_bad_views", hull.tolerated_bad_views},
            {"min_views", hull.min_views},
            {"margin_px", hull.margin_px}}},
          {"tsdf",
           {{"truncation_voxels", tsdf.truncation_voxels},
            {"band_voxels", tsdf.band_voxels},
            {"max_weight", tsdf.max_weight},
            {"depth_noise_k", tsdf.depth_noise_k},
            {"smoothing_radius_px", tsdf.smoothing_radius_px},
            {"max_incidence_deg", tsdf.max_incidence_deg},
            {"carve_background", tsdf.carve_background},
            {"carve_weight", tsdf.carve_weight}}},
          {"mvs",
           {{"neighbors", mvs.neighbors},
            {"window_radius", mvs.window_radius},
            {"depth_step_px", mvs.depth_step_px},
            {"min_ncc", mvs.min_ncc},
            {"min_consistent_views", mvs.min_consistent_views},
            {"min_angle_deg", mvs.min_angle_deg},
            {"max_angle_deg", mvs.max_angle_deg},
            {"max_reference_views", mvs.max_reference_views},
            {"tile_px", mvs.tile_px}}},
          {"tsdf_hull_completion", tsdf_hull_completion},
          {"completion_margin_px", completion_margin_px},
          {"meshing", {{"simplify_cell_m", meshing.simplify_cell_m}}},
          {"texture",
           {{"texels_per_cell", texture.texels_per_cell},
            {"max_views", texture.max_views},
            {"min_cos_incidence", texture.min_cos_incidence},
            {"depth_tolerance_m", texture.depth_tolerance_m},
            {"occlusion_scale", texture.occlusion_scale},
            {"fill_unseen", texture.fill_unseen},
            {"fill_smoothing_iterations", texture.fill_smoothing_iterations},
            {"atlas", texture.atlas}}},
          {"write_glb", write_glb},
          {"sweep_voxels_m", sweep_voxels_m},
          {"threads", threads},
          {"tasks", tasks.ToJson()}};
}

namespace {

std::string SetName(int64_t set) {
  char name[32];
  std::snprintf(name, sizeof(name), "%06lld", static_cast<long long>(set));
  return name;
}

std::string Fixed(double value, int digits) {
  char text[64];
  std::snprintf(text, sizeof(text), "%.*f", digits, value);
  return text;
}

// How this run reconstructs the take's frames (the take's own selection is the TakePlan).
struct MethodPlan {
  ReconstructionMethod method = ReconstructionMethod::kAuto;
  int outer_threads = 1;
  int inner_threads = 1;
  bool depth_background = false;
  bool hull_completion = false;  // TSDF: completed from the visual hull
  SilhouetteOptions silhouette;  // the plan's source applied to the options' parameters
  MvsOptions mvs;                // the options' search scaled to the scene
  MvsViewChoice mvs_views;       // MVS: the reference views and each one's partners
  // Depths fused (TSDF: the depth sensors'; MVS: the stereo's), from the scene's distances.
  double depth_min_m = 0;
  double depth_max_m = 0;
  std::string depth_range_source;
  bool check_fill = true;  // the bounds are not the hull's own extent
  int hull_min_views = 2;  // the hull method's: points fewer cameras see are outside
};

// Which faces of `bounds` a hull reaches (within 1.5 voxels) and the fraction of the bounds'
// volume it fills; a reason when that is implausible for a subject inside them, else empty.
std::string ImplausibleHull(const VisualHull& hull, const HullSummary& summary, const Box& bounds,
                            const ReconstructionOptions& options, bool check_fill) {
  const Box extent = hull.Extent();
  if (extent.empty()) return "";
  const double reach = 1.5 * hull.volume->voxel_m();
  int touched = 0;
  for (int axis = 0; axis < 3; ++axis) {
    touched += extent.min(axis) <= bounds.min(axis) + reach;
    touched += extent.max(axis) >= bounds.max(axis) - reach;
  }
  const double fill = summary.volume_m3 / bounds.Volume();
  if (touched < options.max_touched_faces && !(check_fill && fill > options.max_fill_fraction))
    return "";
  return Cat("the hull fills ", static_cast<int>(std::round(100 * fill)), "% of its bounds and ",
             "touches ", touched,
             " of their 6 faces: the silhouettes do not separate a subject from its background "
             "(try --clean-plate N, --silhouette-threshold T or --bounds)");
}

// Everything one frame needs, read once (the clean plates are shared by all frames).
struct Plates {
  std::map<std::string, cv::Mat> color;
  std::map<std::string, cv::Mat> depth;
};

struct FrameOutput : Summary {
  Mesh mesh;
  nlohmann::json metrics = nlohmann::json::object();
};

// A colour frame as every step reads it: BGR, grey expanded and alpha dropped. Throws Error
// naming the camera for frames that are not 8-bit grey, BGR or BGRA.
cv::Mat ColourOf(const cv::Mat& frame, const std::string& name) {
  const int channels = frame.channels();
  if (frame.depth() != CV_8U || (channels != 1 && channels != 3 && channels != 4))
    Fail("colour frames of '", name, "' must be 8-bit grey, BGR or BGRA");
  if (channels == 3) return frame;
  cv::Mat bgr;
  cv::cvtColor(frame, bgr, channels == 1 ? cv::COLOR_GRAY2BGR : cv::COLOR_BGRA2BGR);
  return bgr;
}

// A camera's silhouette of a frame as the take stores it, from the plan's source: its alpha
// channel, or its colour against the clean plate (when that is the source) or a threshold.
cv::Mat Silhouette(const cv::Mat& frame, const std::string& name, const Plates& plates,
                   const SilhouetteOptions& options) {
  if (options.mode == SilhouetteMode::kAlpha) return ExtractSilhouette(frame, {}, options);
  auto plate = plates.color.find(name);  // none without a clean plate
  return ExtractSilhouette(ColourOf(frame, name),
                           plate == plates.color.end() ? cv::Mat() : plate->second, options);
}

// The depth pixels whose point lies in `hull` or within `margin_m` plus 3 sigma(z) of the
// depth noise of it: a depth sensor's foreground when the take has no depth clean plate (floor
// and walls lie outside the colour cameras' hull). CV_8U, 255 = foreground.
cv::Mat DepthInHull(const cv::Mat& depth_m, const CameraModel& camera, const VisualHull& hull,
                    double margin_m, double depth_noise_k) {
  const cv::Mat rays = NormalisedRays(camera);
  const Pose world_from_cam = camera.world_from_cam();
  cv::Mat inside = cv::Mat::zeros(depth_m.size(), CV_8U);
  for (int y = 0; y < depth_m.rows; ++y) {
    const float* depth = depth_m.ptr<float>(y);
    const cv::Vec2f* ray = rays.ptr<cv::Vec2f>(y);
    uint8_t* out = inside.ptr<uint8_t>(y);
    for (int x = 0; x < depth_m.cols; ++x) {
      const double z = depth[x];
      if (!(z > 0 && std::isfinite(z)) || !std::isfinite(ray[x][0])) continue;
      const Eigen::Vector3d point =
          world_from_cam * Eigen::Vector3d(ray[x][0] * z, ray[x][1] * z, z);
      if (hull.Contains(point, margin_m + 3 * depth_noise_k * z * z)) out[x] = 255;
    }
  }
  return inside;
}

// Reconstructs one frame set at one voxel size by the plan's method; each method is a step.
class FrameReconstructor {
 public:
  FrameReconstructor(const Take& take, const TakePlan& take_plan, const Plates& plates,
                     const MethodPlan& plan, const ReconstructionOptions& options, double voxel,
                     int threads)
      : take_(take),
        take_plan_(take_plan),
        plates_(plates),
        plan_(plan),
        options_(options),
        bounds_(take_plan.bounds),
        voxel_(voxel),
        threads_(threads) {
    tsdf_options_ = options.tsdf;
    tsdf_options_.voxel_m = voxel;
    tsdf_options_.bounds = bounds_;
    tsdf_options_.threads = threads;
    tsdf_options_.depth_min_m = plan.depth_min_m;
    tsdf_options_.depth_max_m = plan.depth_max_m;
  }

  FrameOutput Run(int64_t set) {
    out_.End(Termination::kSuccess, "");  // until a step finds the frame cannot give a surface
    set_ = set;
    ReadViews(set);
    if (plan_.method == ReconstructionMethod::kHull) {
      HullFrame();
    } else if (plan_.method == ReconstructionMethod::kTsdf) {
      TsdfFrame();
    } else {
      MvsFrame();
    }
    if (!silhouette_agreement_.is_null())
      out_.metrics["silhouette_agreement"] = silhouette_agreement_;
    if (tsdf_ && out_.IsUsable()) out_.mesh = ExtractMesh(tsdf_->volume(), options_.meshing);
    if (out_.mesh.faces.empty() && out_.IsUsable())
      out_.End(Termination::kDegenerate, "no surface was found");
    if (out_.IsUsable() && out_.message.empty())
      out_.message =
          Cat(out_.mesh.vertices.size(), " vertices, ", out_.mesh.faces.size(), " triangles");
    return std::move(out_);
  }

 private:
  // The frame set's colour views (BGR) with their silhouettes where the method needs them.
  void ReadViews(int64_t set) {
    std::vector<std::string> needed = take_plan_.color_sensors;
    if (plan_.method == ReconstructionMethod::kTsdf)
      needed.insert(needed.end(), take_plan_.depth_sensors.begin(), take_plan_.depth_sensors.end());
    frames_ = take_.Read(static_cast<size_t>(set), needed);
    const bool need_masks = plan_.method != ReconstructionMethod::kTsdf || plan_.hull_completion;
    for (const std::string& name : take_plan_.ReconstructionSensors()) {
      const Frame* frame = frames_.Find(name);
      View view{name, take_plan_.cameras.at(name), ColourOf(frame->image, name), {}};
      if (need_masks) view.mask = Silhouette(frame->image, name, plates_, plan_.silhouette);
      views_.push_back(std::move(view));
    }
  }

  // The views' visual hull at `voxel` grown by `margin_px`, checked for plausibility; the
  // summary says why when it is not usable.
  VisualHull Hull(double voxel, double margin_px, int min_views, HullSummary* summary) const {
    HullOptions hull_options = options_.hull;
    hull_options.voxel_m = voxel;
    hull_options.bounds = bounds_;
    hull_options.margin_px = margin_px;
    hull_options.min_views = min_views;
    hull_options.threads = threads_;
    VisualHull hull = ComputeVisualHull(views_, hull_options, summary);
    std::string implausible =
        summary->IsUsable() ? ImplausibleHull(hull, *summary, bounds_, options_, plan_.check_fill)
                            : "";
    if (implausible.empty() && summary->IsUsable()) implausible = DisagreeingSilhouettes(hull);
    if (!implausible.empty()) summary->End(Termination::kDegenerate, implausible);
    return hull;
  }

  // How well the hull explains the silhouettes it was carved from: in each view, the IoU of
  // the hull's silhouette and the view's own. Silhouettes of one subject agree (the hull's
  // outline is theirs, up to its voxels); silhouettes holding background that differs between
  // views do not (each view keeps parts that the others carve away). A reason when a quarter
  // of the views or more agree less than options.min_silhouette_agreement, else empty; in the
  // frame's metrics.
  std::string DisagreeingSilhouettes(const VisualHull& hull) const {
    const Mesh mesh = ExtractMesh(*hull.volume, options_.meshing);
    if (mesh.faces.empty()) return "";
    std::vector<double> ious;
    nlohmann::json per_view = nlohmann::json::object();
    for (const View& view : views_) {
      ious.push_back(MaskIoU(RenderSilhouette(mesh, view.camera), view.mask));
      per_view[view.name] = ious.back();
    }
    std::vector<double> sorted = ious;
    std::sort(sorted.begin(), sorted.end());
    const double quartile = sorted[(sorted.size() - 1) / 4];
    silhouette_agreement_ = {{"lower_quartile_iou", quartile},
                             {"median_iou", sorted[sorted.size() / 2]},
                             {"min_iou", sorted.front()},
                             {"views", per_view}};
    if (quartile >= options_.min_silhouette_agreement) return "";
    int below = 0;
    for (double iou : ious) below += iou < options_.min_silhouette_agreement;
    return Cat("the hull explains its silhouettes poorly: in ", below, " of ", ious.size(),
               " views the IoU of the view's silhouette and the hull's is below ",
               options_.min_silhouette_agreement, " (lowest ", Fixed(sorted.front(), 2),
               "): the silhouettes hold background that differs between views (try "
               "--clean-plate N, --silhouette-threshold T or --silhouettes alpha)");
  }

  // The hull method: the visual hull and its surface.
  void HullFrame() {
    HullSummary summary;
    VisualHull hull = Hull(voxel_, options_.hull.margin_px, plan_.hull_min_views, &summary);
    out_.metrics["hull"] = {{"seconds", summary.seconds},
                            {"volume_m3", summary.volume_m3},
                            {"subject_px", summary.subject_px},
                            {"surface_blocks", summary.surface_blocks},
                            {"octree_cells", summary.octree_cells}};
    out_.End(summary.termination, summary.message);
    if (out_.IsUsable()) out_.mesh = ExtractMesh(*hull.volume, options_.meshing);
  }

  // The TSDF method: the colour cameras' hull (when completing), each depth sensor's
  // foreground (against its depth clean plate, else inside that hull), fusion, completion.
  void TsdfFrame() {
    std::optional<VisualHull> hull;
    if (plan_.hull_completion) {
      HullSummary summary;
      hull.emplace(Hull(voxel_, options_.completion_margin_px, options_.hull.min_views, &summary));
      out_.metrics["hull"] = {{"seconds", summary.seconds}, {"volume_m3", summary.volume_m3}};
      // Without a usable hull the depth sensors' surface stands alone; the frame says why.
      // With no depth clean plate either, the hull was what told the subject from the room
      // in depth: an implausible one leaves no foreground to trust.
      if (!summary.IsUsable()) {
        if (!plan_.depth_background && summary.termination == Termination::kDegenerate) {
          out_.End(Termination::kDegenerate,
                   "the depth sensors have no clean plate and the colour cameras' hull that "
                   "would tell the subject from the room is implausible: " +
                       summary.message);
          return;
        }
        hull.reset();
        out_.metrics["completion"] = {{"skipped", "hull: " + summary.message}};
      }
    }
    tsdf_.emplace(tsdf_options_);
    double seconds = 0;
    int64_t valid = 0, measured = 0;
    std::vector<std::pair<CameraModel, cv::Mat>> depth_maps;
    for (const std::string& name : take_plan_.depth_sensors) {
      const cv::Mat& depth = frames_.Find(name)->image;
      const CameraModel& camera = take_plan_.cameras.at(name);
      cv::Mat foreground;
      if (plan_.depth_background) {
        foreground = DepthForeground(depth, plates_.depth.at(name), options_.tsdf.depth_noise_k);
      } else if (hull) {
        foreground = DepthInHull(depth, camera, *hull, 2 * voxel_, options_.tsdf.depth_noise_k);
      }
      const std::string& paired = take_.stream(name).paired_with;
      const View* color_view = nullptr;
      for (const View& v : views_) color_view = v.name == paired ? &v : color_view;
      const TsdfFrameStats stats =
          color_view != nullptr
              ? tsdf_->Integrate(depth, camera, foreground, color_view->image, &color_view->camera)
              : tsdf_->Integrate(depth, camera, foreground);
      seconds += stats.seconds;
      valid += stats.valid_pixels;
      cv::Mat present = depth > 0;  // NaN compares false: a measurement, in or out of range
      if (!foreground.empty()) present &= foreground;
      measured += cv::countNonZero(present);
      depth_maps.emplace_back(camera, depth);
    }
    out_.metrics["tsdf"] = {{"integrate_seconds", seconds},
                            {"valid_pixels", valid},
                            {"measured_pixels", measured},
                            {"blocks", tsdf_->volume().block_count()},
                            {"memory_mb", tsdf_->volume().memory_bytes() / 1048576.0}};
    if (!FusedEnough(valid, measured, hull.has_value())) return;
    if (!hull) return;
    CompletionStats completion = tsdf_->CompleteFromHull(*hull, depth_maps);
    out_.metrics["completion"] = {{"seconds", completion.seconds},
                                  {"blocks_added", completion.blocks_added},
                                  {"voxels_filled", completion.voxels_filled},
                                  {"voxels_carved", completion.voxels_carved},
                                  {"memory_mb", tsdf_->volume().memory_bytes() / 1048576.0}};
  }

  // Whether the depth maps gave a fusion: at least a tenth of their measured (foreground)
  // pixels within the plan's depth range. When not, the frame is the colour cameras' hull
  // alone if there is one (said in its message and metrics), else DEGENERATE.
  bool FusedEnough(int64_t valid, int64_t measured, bool has_hull) {
    if (10 * valid >= measured && valid > 0) return true;
    const std::string why =
        Cat("only ", valid, " of ", measured, " measured depth pixels lie in the depth range [",
            Fixed(plan_.depth_min_m, 4), ", ", Fixed(plan_.depth_max_m, 4), "] m (",
            plan_.depth_range_source, ")");
    if (!has_hull) {
      out_.End(Termination::kDegenerate, "no depth fusion: " + why);
      return false;
    }
    out_.metrics["tsdf"]["fallback"] = "the colour cameras' visual hull alone: " + why;
    out_.message = "depth fusion fell back to the colour cameras' visual hull: " + why;
    return true;
  }

  // The MVS method: a conservative hull at twice the voxel, plane-sweep depth inside it, and
  // the depths fused.
  void MvsFrame() {
    HullSummary hull_summary;
    VisualHull hull =
        Hull(2 * voxel_, options_.hull.margin_px, options_.hull.min_views, &hull_summary);
    out_.metrics["hull"] = {{"seconds", hull_summary.seconds},
                            {"volume_m3", hull_summary.volume_m3}};
    if (!hull_summary.IsUsable()) {
      out_.End(hull_summary.termination, "hull: " + hull_summary.message);
      return;
    }
    MvsOptions mvs_options = plan_.mvs;
    mvs_options.threads = threads_;
    MvsSummary mvs_summary;
    std::vector<cv::Mat> depths =
        ComputeMvsDepth(views_, hull, mvs_options, &mvs_summary, &plan_.mvs_views,
                        Cat("reconstruct ", SetName(set_), ": stereo views"));
    out_.metrics["mvs"] = {{"seconds", mvs_summary.seconds},
                           {"range_seconds", mvs_summary.range_seconds},
                           {"sweep_seconds", mvs_summary.sweep_seconds},
                           {"consistency_seconds", mvs_summary.consistency_seconds},
                           {"reference_views", mvs_summary.reference_views},
                           {"pixels_searched", mvs_summary.pixels_searched},
                           {"pixels_matched", mvs_summary.pixels_matched},
                           {"pixels_consistent", mvs_summary.pixels_consistent},
                           {"planes", mvs_summary.planes},
                           {"pixel_hypotheses", mvs_summary.pixel_hypotheses}};
    if (!IsUsable(mvs_summary.termination)) {
      out_.End(mvs_summary.termination, "mvs: " + mvs_summary.message);
      return;
    }
    // Stereo depth is already consistent between views; its error grows like z^2 too.
    TsdfOptions tsdf_options = tsdf_options_;
    tsdf_options.smoothing_radius_px = 1;
    tsdf_.emplace(tsdf_options);
    double seconds = 0;
    int64_t valid = 0, measured = 0;
    for (size_t i = 0; i < views_.size(); ++i) {
      if (depths[i].empty()) continue;  // not a reference view: no depth of its own
      const TsdfFrameStats stats = tsdf_->Integrate(depths[i], views_[i].camera, views_[i].mask,
                                                    views_[i].image, &views_[i].camera);
      seconds += stats.seconds;
      valid += stats.valid_pixels;
      measured += cv::countNonZero((depths[i] > 0) & views_[i].mask);
    }
    // Stereo's pixels, not a depth sensor's: named apart from the TSDF method's.
    out_.metrics["tsdf"] = {{"integrate_seconds", seconds},
                            {"stereo_pixels_fused", valid},
                            {"stereo_pixels_measured", measured},
                            {"blocks", tsdf_->volume().block_count()}};
    FusedEnough(valid, measured, false);
  }

  const Take& take_;
  const TakePlan& take_plan_;
  const Plates& plates_;
  const MethodPlan& plan_;
  const ReconstructionOptions& options_;
  const Box bounds_;
  const double voxel_;
  const int threads_;
  TsdfOptions tsdf_options_;  // the options' with the frame's voxel, bounds and depth range
  int64_t set_ = 0;           // the frame set Run reconstructs
  FrameSet frames_;
  std::vector<View> views_;
  std::optional<TsdfVolume> tsdf_;  // the fused volume, when the method fuses
  FrameOutput out_;
  mutable nlohmann::json silhouette_agreement_;  // set by Hull()
};

// The mesh in the simulation's true world: calibrated models live in the world the calibration
// chose from the take, laid here onto the true cameras for measuring only.
Mesh InTrueWorld(const Take& take, const TakePlan& take_plan, const Mesh& mesh) {
  if (take_plan.ground_truth_cameras) return mesh;
  std::map<std::string, CameraModel> truth;
  for (const auto& [name, model] : take_plan.cameras) {
    if (std::filesystem::exists(take.gt_dir() / "cameras" / (name + ".cameramodel")))
      truth.emplace(name, take.Camera(name, true));
  }
  const Eigen::Isometry3f true_from_plan = AlignRigs(take_plan.cameras, truth).cast<float>();
  Mesh moved = mesh;
  for (auto& v : moved.vertices) v = true_from_plan * v;
  for (auto& n : moved.normals) n = true_from_plan.linear() * n;
  return moved;
}

void AddGroundTruthMetrics(const Take& take, int64_t set, const Mesh& plan_mesh,
                           const TakePlan& take_plan, const MethodPlan& plan,
                           nlohmann::json* metrics) {
  std::filesystem::path file = take.gt_dir() / "meshes" / (SetName(set) + ".ply");
  if (!std::filesystem::exists(file)) file = take.gt_dir() / "meshes" / "static.ply";
  if (!std::filesystem::exists(file)) return;
  Mesh truth = ReadPly(file);
  const Mesh mesh = InTrueWorld(take, take_plan, plan_mesh);
  // The simulated subject is a union of overlapping closed body parts: what lies inside another
  // part is not its surface, and completeness is measured on the outer surface only.
  const auto outer = OnOuterSurface(truth);
  SurfaceErrors e = CompareSurfaces(mesh, truth, 0.005, 40000, outer);
  SurfaceErrors all = CompareSurfaces(mesh, truth, 0.005);
  nlohmann::json gt = {{"chamfer_mm", e.chamfer_mm},
                       {"accuracy_mm", e.accuracy_mm},
                       {"completeness_mm", e.completeness_mm},
                       {"fscore_5mm", e.fscore},
                       {"precision_5mm", e.precision},
                       {"recall_5mm", e.recall},
                       {"chamfer_with_buried_faces_mm", all.chamfer_mm},
                       {"completeness_with_buried_faces_mm", all.completeness_mm}};
  if (plan.method == ReconstructionMethod::kTsdf) {
    // Depth sensors see only part of the subject: also measure on what they saw.
    std::vector<std::pair<CameraModel, cv::Mat>> seen;
    for (const auto& name : take_plan.depth_sensors) {
      auto depth_file = take.gt_dir() / "depth" / name / (SetName(set) + ".exr");
      if (std::filesystem::exists(depth_file))
        seen.emplace_back(take.Camera(name, true), ReadImage(depth_file));
    }
    if (!seen.empty()) {
      SurfaceErrors o = CompareSurfaces(mesh, truth, 0.005, 40000, SeenInDepthMaps(seen));
      gt["observed"] = {{"chamfer_mm", o.chamfer_mm},
                        {"accuracy_mm", o.accuracy_mm},
                        {"completeness_mm", o.completeness_mm},
                        {"fscore_5mm", o.fscore}};
    }
  }
  (*metrics)["gt"] = gt;
}

}  // namespace

std::map<std::string, cv::Mat> LearnBackgroundModel(const Take& take, TakePlan& plan,
                                                    const SilhouetteOptions& silhouette,
                                                    double min_moving_fraction) {
  std::map<std::string, cv::Mat> plates;
  if (plan.silhouettes != SilhouetteSource::kBackgroundModel) return plates;
  std::vector<double> fractions;
  SilhouetteOptions subtraction = silhouette;
  subtraction.mode = SilhouetteMode::kBackgroundSubtraction;
  for (const auto& name : plan.color_sensors) {
    std::vector<cv::Mat> frames;
    for (int64_t set : plan.background_sets)
      frames.push_back(ColourOf(take.ReadFrame(static_cast<size_t>(set), name), name));
    plates[name] = TemporalMedian(frames);
    const cv::Mat& middle = frames[frames.size() / 2];
    fractions.push_back(cv::countNonZero(ExtractSilhouette(middle, plates[name], subtraction)) /
                        static_cast<double>(middle.total()));
  }
  std::nth_element(fractions.begin(), fractions.begin() + fractions.size() / 2, fractions.end());
  const double moving = fractions[fractions.size() / 2];
  if (moving >= min_moving_fraction) return plates;
  plan.silhouettes = SilhouetteSource::kOtsu;
  plan.silhouette_reason =
      Cat("brightest channel above a threshold chosen per image (Otsu): the background model "
          "over ",
          plan.background_sets.size(), " frame sets holds the subject (it differs from ",
          "the median in ", Fixed(100 * moving, 3), "% of a middle frame's pixels): the ",
          "subject does not move");
  plan.background_sets.clear();
  return {};
}

namespace {

// A frame's result as its record and the run's report hold it, and back.
nlohmann::json ToJson(const FrameResult& f) {
  return {{"set", f.set},
          {"seconds", f.seconds},
          {"vertices", f.vertices},
          {"faces", f.faces},
          {"termination", ToString(f.termination)},
          {"message", f.message},
          {"metrics", f.metrics}};
}

FrameResult FrameResultFromJson(const nlohmann::json& json) {
  FrameResult f;
  f.set = json.at("set").get<int64_t>();
  f.seconds = json.at("seconds").get<double>();
  f.vertices = json.at("vertices").get<int64_t>();
  f.faces = json.at("faces").get<int64_t>();
  const std::string termination = json.at("termination").get<std::string>();
  for (auto t : {Termination::kSuccess, Termination::kConvergence, Termination::kNoConvergence,
                 Termination::kDegenerate, Termination::kFailure}) {
    if (termination == ToString(t)) f.End(t, json.at("message").get<std::string>());
  }
  f.metrics = json.at("metrics");
  return f;
}

// SUCCESS only when every frame set gave a surface: a run with a failed frame set is
// DEGENERATE (its other meshes are written and usable alone), its message naming the failed
// sets (the first ten, and how many more) and the first one's reason. Frames whose depth fusion
// fell back to the colour cameras' hull: the plan and the message say so, with the first one's
// reason.
void EndByFrames(const std::vector<FrameResult>& frames, const std::string& method,
                 ReconstructionSummary* summary) {
  const int count = static_cast<int>(frames.size());
  std::vector<const FrameResult*> failed;
  for (const FrameResult& f : frames) {
    if (!f.IsUsable()) failed.push_back(&f);
  }
  if (failed.empty()) {
    summary->End(Termination::kSuccess, Cat(count, " frame set(s) reconstructed by ", method));
  } else {
    constexpr size_t kNamed = 10;
    std::string sets;
    for (size_t i = 0; i < std::min(failed.size(), kNamed); ++i)
      sets += Cat(i == 0 ? "" : ", ", failed[i]->set);
    if (failed.size() > kNamed) sets += Cat(" and ", failed.size() - kNamed, " more");
    summary->End(Termination::kDegenerate,
                 Cat(failed.size(), " of ", count, " frame sets gave no surface (set(s) ", sets,
                     "); first failure: set ", failed.front()->set, ": ", failed.front()->message));
  }
  int fallbacks = 0;
  std::string first;
  for (const FrameResult& f : frames) {
    if (!f.IsUsable() || !f.metrics.contains("tsdf") || !f.metrics["tsdf"].contains("fallback"))
      continue;
    if (fallbacks++ == 0)
      first = Cat("set ", f.set, ": ", f.metrics["tsdf"]["fallback"].get<std::string>());
  }
  if (fallbacks == 0) return;
  const std::string note =
      Cat("fell back to the colour cameras' visual hull in ", fallbacks, " frame set(s); ", first);
  summary->plan["depth_fusion"] = note;
  summary->message += "; depth fusion " + note;
  std::printf("reconstruct: depth fusion %s\n", note.c_str());
}

// The frames' results into a report's metrics: each frame, the held-out cameras' mean IoU and,
// on simulated takes, the mean of every ground-truth metric with the voxel sweep.
void AddFrameMetrics(const std::vector<FrameResult>& frames, const nlohmann::json& sweep,
                     nlohmann::json* metrics) {
  nlohmann::json frames_json = nlohmann::json::array();
  std::map<std::string, double> gt_sums;
  int gt_count = 0;
  double iou_sum = 0;
  int iou_count = 0;
  for (const FrameResult& f : frames) {
    frames_json.push_back(ToJson(f));
    if (f.metrics.contains("gt")) {
      ++gt_count;
      for (auto& [key, value] : f.metrics["gt"].items()) {
        if (value.is_number()) gt_sums[key] += value.get<double>();
      }
    }
    if (!f.metrics.contains("heldout_iou")) continue;
    for (auto& [name, iou] : f.metrics["heldout_iou"].items()) {
      iou_sum += iou.get<double>();
      ++iou_count;
    }
  }
  (*metrics)["frames"] = frames_json;
  if (iou_count > 0) (*metrics)["heldout_iou_mean"] = iou_sum / iou_count;
  if (gt_count > 0) {
    for (auto& [key, sum] : gt_sums) (*metrics)["gt"][key] = sum / gt_count;
    (*metrics)["gt"]["frames"] = gt_count;
    (*metrics)["gt"]["voxel_sweep"] = sweep;
  }
}

// The run's report.json from its records alone (run.json's options and plan, each frame's
// result, the first frame's voxel sweep): the same bytes whichever tasks made the records,
// timings aside. FAILURE naming the incomplete frame sets while any is.
ReconstructionSummary SummariseRun(const RunState& run, Report* report) {
  ReconstructionSummary summary;
  summary.plan = run.header.value("plan", nlohmann::json::object());
  report->options() = run.header.value("options", nlohmann::json::object());
  nlohmann::json sweep = nlohmann::json::array();
  nlohmann::json per_frame = nlohmann::json::array();
  double first_start = std::numeric_limits<double>::infinity(), last_end = 0, peak_mb = 0;
  double total_seconds = 0;
  for (const auto& [set, record] : run.complete) {
    summary.frames.push_back(FrameResultFromJson(record["result"]));
    if (set == run.sets.front() && record["result"].contains("voxel_sweep"))
      sweep = record["result"]["voxel_sweep"];
    per_frame.push_back(summary.frames.back().seconds);
    total_seconds += summary.frames.back().seconds;
    first_start = std::min(first_start, record.value("started_unix_s", 0.0));
    last_end = std::max(last_end, record.value("finished_unix_s", 0.0));
    peak_mb = std::max(peak_mb, record.value("peak_rss_mb", 0.0));
  }
  EndByFrames(summary.frames, summary.plan.value("method", "?"), &summary);
  if (!run.done()) {
    summary.End(Termination::kFailure,
                Cat(run.Describe(), ": run the run's tasks again (each redoes only its ",
                    "incomplete frame sets), then merge"));
  }
  report->plan() = summary.plan;
  nlohmann::json& metrics = report->metrics();
  AddFrameMetrics(summary.frames, sweep, &metrics);
  const double wall_s = run.complete.empty() ? 0 : last_end - first_start;
  const size_t count = summary.frames.size();
  metrics["timing"] = {{"per_frame_s", per_frame},
                       {"mean_frame_s", count > 0 ? total_seconds / count : 0},
                       {"wall_s", wall_s},
                       {"frames_per_minute", wall_s > 0 ? 60.0 * count / wall_s : 0},
                       {"frames_by_task", run.frames_by_task},
                       {"cpu_s_by_task", run.cpu_s_by_task}};
  metrics["peak_rss_mb"] = peak_mb;
  double t_s = 0;
  int64_t iter = 0;
  for (const auto& point : sweep) {
    t_s += point["seconds"].get<double>();
    report->AddPointAt("gt.chamfer_mm", point["chamfer_mm"].get<double>(), iter, t_s);
    report->AddPointAt("seconds_per_frame", point["seconds"].get<double>(), iter, t_s);
    report->AddPointAt("voxel_mm", point["voxel_mm"].get<double>(), iter, t_s);
    ++iter;
  }
  report->SetSummary(summary);
  report->Write(run.out / "report.json");
  summary.seconds = wall_s;
  return summary;
}

// Reconstructs a planned take: method, plates and threads chosen once, then every frame set,
// the voxel sweep on simulated takes, and the summary. Each step is a method.
class TakeReconstructor {
 public:
  TakeReconstructor(const Take& take, const TakePlan& take_plan, const std::filesystem::path& out,
                    const ReconstructionOptions& options, Report* report)
      : take_(take), take_plan_(take_plan), out_(out), options_(options), report_(report) {}

  ReconstructionSummary Run() {
    PlanRun();
    ChooseVoxel();
    ChooseDepthRange();
    CheckBoundsSeen();
    ChooseTaskFrames();
    PlanStereo();
    DescribePlan();
    CreateDirectories(out_);
    if (!implausible_.empty()) {
      EndImplausible();
      return summary_;
    }
    StartRecords();
    ReconstructFrames();
    FinishTask();
    return summary_;
  }

 private:
  std::string Where() const { return Cat("take '", take_.dir().string(), "'"); }
  bool is_tsdf() const { return plan_.method == ReconstructionMethod::kTsdf; }
  bool needs_plate() const { return plan_.method != ReconstructionMethod::kTsdf; }

  // The sensors a method reads, every frame set holding each of them.
  std::vector<std::string> NeededSensors() const {
    std::vector<std::string> needed = take_plan_.color_sensors;
    if (is_tsdf())
      needed.insert(needed.end(), take_plan_.depth_sensors.begin(), take_plan_.depth_sensors.end());
    return needed;
  }

  void ChooseMethod() {
    const auto& color = take_plan_.color_sensors;
    const auto& depth = take_plan_.depth_sensors;
    plan_.method = options_.method;
    if (plan_.method == ReconstructionMethod::kAuto) {
      // Stereo needs silhouettes that hold the whole subject (a clean plate's or alpha's).
      const bool exact_silhouettes = take_plan_.silhouettes == SilhouetteSource::kCleanPlate ||
                                     take_plan_.silhouettes == SilhouetteSource::kBackgroundModel ||
                                     take_plan_.silhouettes == SilhouetteSource::kAlpha;
      plan_.method = !depth.empty()      ? ReconstructionMethod::kTsdf
                     : exact_silhouettes ? ReconstructionMethod::kMvs
                                         : ReconstructionMethod::kHull;
    }
    if (is_tsdf() && depth.empty())
      Fail("method tsdf needs depth sensors; ", Where(), " has none (use hull or mvs)");
    const size_t reconstructed = take_plan_.ReconstructionSensors().size();
    if (!is_tsdf() && reconstructed < 2) {
      Fail("method ", ToString(plan_.method), " needs at least two colour cameras; the take has ",
           color.size(), " and ", take_plan_.heldout.size(), " of them are held out");
    }
    if (needs_plate() && take_plan_.silhouettes == SilhouetteSource::kNone) {
      Fail("method ", ToString(plan_.method), " needs silhouettes: ", Where(),
           " has no colour camera to take them from");
    }
    take_plan_.RequireFrames(take_, NeededSensors());
    // A point that fewer than half the cameras see is carved by too few of them: on a sparse
    // ring those points grow the hull's ghost wedges, which reach the bounds (a quarter or two
    // fifths leave them on dinoSparseRing; half also keeps what leaves a few cameras' frames).
    plan_.hull_min_views =
        std::max(options_.hull.min_views, static_cast<int>(reconstructed + 1) / 2);
    completion_ = "not a TSDF run";
    if (is_tsdf()) {
      const bool silhouettes = take_plan_.silhouettes != SilhouetteSource::kNone;
      plan_.hull_completion = options_.tsdf_hull_completion && reconstructed >= 2 && silhouettes;
      completion_ =
          plan_.hull_completion
              ? "visual hull of the colour cameras, carved by the depth sensors' free space, "
                "fills what the depth sensors did not see"
          : !options_.tsdf_hull_completion ? "off (asked for)"
          : reconstructed < 2              ? "off: fewer than two colour cameras"
                                           : "off: no silhouettes for the colour cameras";
    }
    threads_ = ResolveThreads(options_.threads);
    frame_count_ = static_cast<int>(take_plan_.sets.size());
  }

  // This task's part of the run's frame sets; they run in parallel when the task has at least
  // as many of them as threads.
  void ChooseTaskFrames() {
    std::vector<int64_t> all(frame_count_);
    std::iota(all.begin(), all.end(), 0);
    for (int64_t i : options_.tasks.shard.Of(all)) todo_.push_back(static_cast<int>(i));
    const int count = static_cast<int>(todo_.size());
    plan_.outer_threads = count >= threads_ ? threads_ : 1;
    plan_.inner_threads = count >= threads_ ? 1 : threads_;
  }

  // The plan's silhouette source applied to the options' parameters; the stage's options may
  // still ask for a fixed threshold (rerendering's --silhouettes threshold).
  void ChooseSilhouettes() {
    plan_.silhouette = options_.silhouette;
    const bool stage_threshold = options_.silhouette.mode == SilhouetteMode::kThreshold;
    if (stage_threshold && take_plan_.silhouettes != SilhouetteSource::kThreshold) {
      take_plan_.silhouettes = SilhouetteSource::kThreshold;
      take_plan_.silhouette_threshold = options_.silhouette.threshold;
      take_plan_.silhouette_reason = "a fixed threshold, asked for in the stage's options";
    }
    switch (take_plan_.silhouettes) {
      case SilhouetteSource::kAlpha:
        plan_.silhouette.mode = SilhouetteMode::kAlpha;
        break;
      case SilhouetteSource::kCleanPlate:
      case SilhouetteSource::kBackgroundModel:
        plan_.silhouette.mode = SilhouetteMode::kBackgroundSubtraction;
        break;
      case SilhouetteSource::kThreshold:
        plan_.silhouette.mode = SilhouetteMode::kThreshold;
        plan_.silhouette.threshold = take_plan_.silhouette_threshold;
        break;
      default:
        plan_.silhouette.mode = SilhouetteMode::kOtsu;
        break;
    }
    ChooseMorphology(stage_threshold);
  }

  bool Thresholded() const {
    return plan_.silhouette.mode == SilhouetteMode::kThreshold ||
           plan_.silhouette.mode == SilhouetteMode::kOtsu;
  }

  // Thresholded silhouettes take the closing measured on the take (auto), the Middlebury
  // README's recipe or none; the others keep the options' morphology. A fixed threshold the
  // stage asks for keeps the options' morphology too (rerendering's own silhouettes).
  void ChooseMorphology(bool stage_threshold) {
    const SilhouetteOptions& given = options_.silhouette;
    const std::string given_text = Cat("open ", given.open_px, " px, close as dilate ",
                                       given.dilate_px, " px and erode ", given.erode_px, " px");
    if (!Thresholded() || stage_threshold) {
      morphology_ = "the options'";
      morphology_why_ =
          Cat(given_text, stage_threshold ? " (a fixed threshold the stage asks for)"
                                          : " (silhouettes that are not thresholded)");
      return;
    }
    plan_.silhouette.open_px = 0;
    plan_.silhouette.morphology_width = 0;
    switch (options_.silhouette_morphology) {
      case SilhouetteMorphology::kRecipe:
        // The Middlebury README's, for its 640-pixel images, scaled to the take's width.
        plan_.silhouette.dilate_px = 10;
        plan_.silhouette.erode_px = 7;
        plan_.silhouette.morphology_width = 640;
        morphology_ = "recipe";
        morphology_why_ =
            "the Middlebury README's (dilate 10 px, erode 7 px at 640 px wide), asked for";
        break;
      case SilhouetteMorphology::kNone:
        plan_.silhouette.dilate_px = 0;
        plan_.silhouette.erode_px = 0;
        morphology_ = "none";
        morphology_why_ = "none, asked for";
        break;
      case SilhouetteMorphology::kAuto:
        plan_.silhouette.dilate_px = closing_.close_px;
        plan_.silhouette.erode_px = closing_.close_px;
        morphology_ = closing_.close_px > 0 ? Cat("closing ", closing_.close_px, " px") : "none";
        morphology_why_ = closing_measured_
                              ? closing_.why
                              : "none: not measured (the run reads no silhouettes, or its "
                                "bounds are implausible)";
        break;
    }
  }

  // The closing of thresholded silhouettes measured on the run's first frame set's unclosed
  // silhouettes: radii up to the recipe's dilation scaled to the images' width (a few image
  // operations per view and radius, no hull).
  void MeasureClosing() {
    if (!Thresholded() || options_.silhouette_morphology != SilhouetteMorphology::kAuto ||
        !(needs_plate() || plan_.hull_completion) || !implausible_.empty() ||
        take_plan_.sets.empty() || morphology_ == "the options'")
      return;
    std::vector<cv::Mat> masks;
    int width = 0;
    for (const View& view : SilhouetteViews(take_plan_.sets[0])) {
      masks.push_back(view.mask);
      width = std::max(width, view.mask.cols);
    }
    if (masks.empty()) return;
    const int max_radius =
        std::max(2, static_cast<int>(std::lround(options_.max_close_px_at_640 * width / 640.0)));
    closing_ = ChooseClosing(masks, max_radius, options_.min_closing_jump_px);
    closing_measured_ = true;
    ChooseMorphology(false);
  }

  // Colour silhouettes of one frame set from the cameras the run reconstructs from.
  std::vector<View> SilhouetteViews(int64_t set) const {
    const std::vector<std::string> names = take_plan_.ReconstructionSensors();
    FrameSet frames = take_.Read(static_cast<size_t>(set), names);
    std::vector<View> views;
    for (const auto& name : names) {
      views.push_back({name, take_plan_.cameras.at(name), {}, {}});
      views.back().mask = Silhouette(frames.Find(name)->image, name, plates_, plan_.silhouette);
    }
    return views;
  }

  // Bounds from the rig (not the user's) shrink to a coarse hull of frame sets spread over the
  // take, grown by a margin; a coarse hull that fills the cameras' shared view instead ends the
  // run DEGENERATE (the silhouettes do not separate a subject).
  void TightenBounds() {
    if (options_.bounds) {
      take_plan_.SetBounds(*options_.bounds, "the stage's options");
      plan_.check_fill = true;
      return;
    }
    const bool from_rig = take_plan_.bounds_source.rfind("cameras", 0) == 0;
    const bool masks = needs_plate() || plan_.hull_completion;
    plan_.check_fill = true;
    if (!from_rig || !masks || options_.tighten_sets == 0) return;
    const Box& view = take_plan_.view_bounds;
    // Cameras that see the subject whole may see past the box most of them share.
    const Box search =
        take_plan_.AboveFloor(Box{view.min - 0.25 * view.size(), view.max + 0.25 * view.size()});
    HullOptions hull_options = options_.hull;
    hull_options.voxel_m = search.size().maxCoeff() / 64;
    hull_options.bounds = search;
    hull_options.threads = threads_;
    // Outside the box most cameras share, points seen by a few cameras grow the hull's ghost
    // wedges: the coarse hull counts what half of them see, as the shared box does.
    const int cameras = static_cast<int>(take_plan_.ReconstructionSensors().size());
    hull_options.min_views = std::max(hull_options.min_views, (cameras + 1) / 2);
    const int count = std::min<int>(options_.tighten_sets, frame_count_);
    Box extent = Box::Empty();
    for (int i = 0; i < count; ++i) {
      const int64_t set = take_plan_.sets[count > 1 ? i * (frame_count_ - 1) / (count - 1) : 0];
      HullSummary summary;
      VisualHull hull = ComputeVisualHull(SilhouetteViews(set), hull_options, &summary);
      if (!summary.IsUsable()) continue;
      // Measured against the box the cameras share: silhouettes that cover every image give
      // a hull that is that box.
      const std::string implausible =
          ImplausibleHull(hull, summary, take_plan_.AboveFloor(view), options_, true);
      if (!implausible.empty()) {
        implausible_ =
            Cat("set ", set, ": a coarse ", implausible.substr(4), " (the box the cameras share)");
        return;
      }
      extent.Extend(hull.Extent());
    }
    if (extent.empty()) return;  // the frames say why
    const double margin = 2 * hull_options.voxel_m + 0.1 * extent.size().maxCoeff();
    take_plan_.SetBounds(
        extent.Grown(margin),
        Cat("cameras + coarse hull: the visual hull of ", count, " frame set(s) at ",
            Fixed(hull_options.voxel_m * 1e3, 1), " mm, grown by ", Fixed(margin * 1e3, 1),
            " mm; before it, ", take_plan_.bounds_source));
    plan_.check_fill = false;
  }

  // The voxel the plan's bounds imply, unless the options give one; MVS searches a depth range
  // scaled to the scene.
  void ChooseVoxel() {
    if (options_.voxel_m > 0) {
      take_plan_.voxel_m = options_.voxel_m;
      take_plan_.voxel_source = "asked for (--voxel)";
    }
    voxel_ = take_plan_.voxel_m;
    plan_.mvs = options_.mvs;
    // A surface more than half the scene's smallest side behind the hull's is its far side,
    // which other views see; the margin in front stays a few voxels.
    plan_.mvs.search_depth_m =
        std::min(options_.mvs.search_depth_m, 0.5 * take_plan_.bounds.size().minCoeff());
    plan_.mvs.hull_margin_m = std::min(options_.mvs.hull_margin_m, 10 * voxel_);
  }

  // The depths fused: from half the nearest to four times the farthest z-depth of the bounds'
  // corners in the cameras whose depth is fused (a scene's distances, whatever its scale).
  void ChooseDepthRange() {
    const std::vector<std::string> names =
        is_tsdf() ? take_plan_.depth_sensors : take_plan_.ReconstructionSensors();
    double nearest = std::numeric_limits<double>::infinity(), farthest = 0;
    const Box& box = take_plan_.bounds;
    for (const CameraModel& camera : take_plan_.Cameras(names)) {
      for (int corner = 0; corner < 8; ++corner) {
        const double z = (camera.cam_from_world() * box.Corner(corner)).z();
        nearest = std::min(nearest, std::max(z, 0.0));
        farthest = std::max(farthest, z);
      }
    }
    if (!(farthest > 0)) {  // the bounds lie behind every camera: nothing to fuse anyway
      plan_.depth_min_m = options_.tsdf.depth_min_m;
      plan_.depth_max_m = options_.tsdf.depth_max_m;
      plan_.depth_range_source = "the options' (the bounds lie behind the cameras)";
      return;
    }
    plan_.depth_min_m = 0.5 * nearest;
    plan_.depth_max_m = 4 * farthest;
    plan_.depth_range_source =
        Cat("half the nearest and four times the farthest z-depth of the bounds' corners in the ",
            is_tsdf() ? "depth sensors" : "colour cameras", " (", Fixed(nearest, 4), " and ",
            Fixed(farthest, 4), " m)");
  }

  // MVS: which views are searched and against which (around the bounds' centre), and what the
  // sweeps will cost: an estimate from the first frame set's silhouettes and a rate measured
  // now. A simulated take's voxel sweep would run the whole stereo again at each voxel (its
  // cost follows the pixels, not the voxel): left out.
  void PlanStereo() {
    if (plan_.method != ReconstructionMethod::kMvs || !implausible_.empty()) return;
    const Eigen::Vector3d subject = take_plan_.bounds.center();
    plan_.mvs_views =
        ChooseMvsViews(take_plan_.Cameras(take_plan_.ReconstructionSensors()), subject, plan_.mvs);
    if (!take_plan_.sets.empty()) {
      stereo_estimate_ = EstimateMvs(SilhouetteViews(take_plan_.sets[0]), plan_.mvs_views, subject,
                                     plan_.mvs, plan_.inner_threads);
    }
  }

  // Cameras that do not see the bounds cannot reconstruct anything in them.
  void CheckBoundsSeen() {
    if (!implausible_.empty()) return;
    const std::vector<std::string> names = take_plan_.ReconstructionSensors().empty()
                                               ? take_plan_.depth_sensors
                                               : take_plan_.ReconstructionSensors();
    const int seeing = CamerasSeeing(take_plan_.Cameras(names), take_plan_.bounds.center());
    const int needed = std::min<int>(names.size(), std::max<int>(2, (names.size() + 1) / 2));
    if (seeing >= needed) return;
    implausible_ =
        Cat("the cameras do not see the bounds: ", seeing, " of ", names.size(),
            " see their centre (", take_plan_.bounds_source, "; at least ", needed, " must)");
  }

  // A run that cannot give a plausible result: DEGENERATE with the reason, and the report.
  void EndImplausible() {
    summary_.End(Termination::kDegenerate, implausible_);
    summary_.seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
    if (report_ == nullptr) return;
    report_->SetSummary(summary_);
    report_->Write(out_ / "report.json");
  }

  // A mesh wider than the cameras' shared view on some axis is not a subject they all see.
  std::string MeshLargerThanView(const FrameOutput& frame) const {
    if (!frame.IsUsable() || frame.mesh.vertices.empty()) return "";
    Box extent = Box::Empty();
    for (const auto& v : frame.mesh.vertices) extent.Extend(v.cast<double>());
    const Eigen::Vector3d view = take_plan_.view_bounds.size();
    const Eigen::Vector3d size = extent.size();
    for (int axis = 0; axis < 3; ++axis) {
      if (size(axis) > options_.max_view_ratio * view(axis)) {
        return Cat("the mesh is ", Fixed(size(axis), 3), " m across along ", "xyz"[axis],
                   ", more than ", options_.max_view_ratio, "x the ", Fixed(view(axis), 3),
                   " m the cameras share: it is not a subject they see");
      }
    }
    return "";
  }

  // The mesh's silhouette in each held-out camera against the plan's silhouette of its image.
  nlohmann::json HeldoutIoU(const Mesh& mesh, const FrameSet& colour) const {
    nlohmann::json out = nlohmann::json::object();
    for (const auto& name : take_plan_.heldout) {
      const cv::Mat observed =
          Silhouette(colour.Find(name)->image, name, plates_, plan_.silhouette);
      out[name] = MaskIoU(RenderSilhouette(mesh, take_plan_.cameras.at(name)), observed);
    }
    return out;
  }

  // The run's plan up to its bounds, made once for all its tasks (core/frame_tasks.h PlanOnce):
  // the background model and the coarse hull cost as much as several frames, so the task that
  // takes the plan's lock first makes them and every other task reads what they chose.
  void PlanRun() {
    const StoredPlan stored = PlanOnce(out_, "reconstruct", PlanFingerprint(), task_,
                                       [this](std::vector<std::string>* files) {
                                         LearnBackground();
                                         ChooseMethodAndPlates();
                                         TightenBounds();
                                         MeasureClosing();
                                         return SavePlan(files);
                                       });
    if (!stored.made) {
      ApplyPlan(stored.plan);
      ChooseMethodAndPlates();
    }
    plan_origin_ = stored.made ? Cat("made by this task (", stored.why, ")")
                               : Cat("read from ", (out_ / kPlanDir).string(), " (made by ",
                                     stored.made_by, ")");
  }

  void ChooseMethodAndPlates() {
    ChooseMethod();
    ChooseSilhouettes();
    ReadPlates();
  }

  // What decides the plan: the options (less threads and the task's part), the take's plan
  // before this stage's steps, its recording and its camera models.
  std::string PlanFingerprint() const {
    nlohmann::json options = options_.ToJson();
    options.erase("threads");
    options.erase("tasks");
    return HashBytes(nlohmann::json{
        {"options", options}, {"take_plan", take_plan_.ToJson()}, {"take", TakeIdentity()}}
                         .dump());
  }

  // The take's recording and camera models as hashes: a re-recorded or recalibrated take is
  // another run even where its plan reads the same.
  nlohmann::json TakeIdentity() const {
    std::string recording = ReadFileToString(take_.dir() / "take.json");
    std::error_code ec;
    if (fs::exists(take_.dir() / "index.jsonl", ec))
      recording += ReadFileToString(take_.dir() / "index.jsonl");
    std::string cameras;
    for (const auto& [name, camera] : take_plan_.cameras) cameras += name + camera.ToString();
    return {{"recording", HashBytes(recording)}, {"cameras", HashBytes(cameras)}};
  }

  // What PlanRun's costly steps chose, as OUT/plan/plan.json stores it (doubles round-trip
  // exactly through JSON), the background model's images written beside it as PNG.
  nlohmann::json SavePlan(std::vector<std::string>* files) const {
    nlohmann::json background = nlohmann::json::object();
    if (take_plan_.silhouettes == SilhouetteSource::kBackgroundModel) {
      for (const auto& name : take_plan_.color_sensors) {
        files->push_back(Cat("background-", name, ".png"));
        WritePng(out_ / kPlanDir / files->back(), plates_.color.at(name));
        background[name] = files->back();
      }
    }
    const Box& b = take_plan_.bounds;
    return {{"silhouettes", static_cast<int>(take_plan_.silhouettes)},
            {"silhouette_reason", take_plan_.silhouette_reason},
            {"silhouette_threshold", take_plan_.silhouette_threshold},
            {"background_sets", take_plan_.background_sets},
            {"background", background},
            {"bounds_min", {b.min.x(), b.min.y(), b.min.z()}},
            {"bounds_max", {b.max.x(), b.max.y(), b.max.z()}},
            {"bounds_source", take_plan_.bounds_source},
            {"voxel_m", take_plan_.voxel_m},
            {"voxel_source", take_plan_.voxel_source},
            {"check_fill", plan_.check_fill},
            {"closing", closing_measured_ ? closing_.ToJson() : nlohmann::json(nullptr)},
            {"implausible", implausible_}};
  }

  // A plan SavePlan stored: the take's plan and this stage's as the task that made it left them.
  void ApplyPlan(const nlohmann::json& stored) {
    take_plan_.silhouettes = static_cast<SilhouetteSource>(stored.at("silhouettes").get<int>());
    take_plan_.silhouette_reason = stored.at("silhouette_reason").get<std::string>();
    take_plan_.silhouette_threshold = stored.at("silhouette_threshold").get<double>();
    take_plan_.background_sets = stored.at("background_sets").get<std::vector<int64_t>>();
    for (const auto& [name, file] : stored.at("background").items())
      plates_.color[name] = ReadImage(out_ / kPlanDir / file.get<std::string>());
    const auto corner = [](const nlohmann::json& xyz) {
      return Eigen::Vector3d(xyz.at(0).get<double>(), xyz.at(1).get<double>(),
                             xyz.at(2).get<double>());
    };
    take_plan_.bounds = Box{corner(stored.at("bounds_min")), corner(stored.at("bounds_max"))};
    take_plan_.bounds_source = stored.at("bounds_source").get<std::string>();
    take_plan_.voxel_m = stored.at("voxel_m").get<double>();
    take_plan_.voxel_source = stored.at("voxel_source").get<std::string>();
    plan_.check_fill = stored.at("check_fill").get<bool>();
    closing_measured_ = !stored.at("closing").is_null();
    if (closing_measured_) closing_ = ClosingChoice::FromJson(stored.at("closing"));
    implausible_ = stored.at("implausible").get<std::string>();
  }

  // The background model stands in for the colour cameras' clean plates (or the plan falls
  // back to Otsu when the subject does not move).
  void LearnBackground() {
    plates_.color =
        LearnBackgroundModel(take_, take_plan_, options_.silhouette, options_.min_moving_fraction);
  }

  void ReadPlates() {
    if (!take_plan_.has_clean_plate()) return;
    const size_t plate_set = static_cast<size_t>(take_plan_.plate_set());
    for (const auto& name : NeededSensors()) {
      const cv::Mat image = take_.ReadFrame(plate_set, name);
      if (take_.stream(name).role == SensorRole::kDepth)
        plates_.depth[name] = image;
      else
        plates_.color[name] = ColourOf(image, name);
    }
    plan_.depth_background = is_tsdf();
  }

  // Whether stereo searches inside the hull to carve what silhouettes cannot (concavities,
  // gaps between parts), and why.
  nlohmann::json StereoInsideHull(bool stereo) const {
    std::string why;
    if (options_.method != ReconstructionMethod::kAuto) {
      why = Cat(stereo ? "chosen" : "not chosen", ": the method is asked for (--method ",
                ToString(options_.method), ")");
    } else if (is_tsdf()) {
      why = "not chosen: the depth sensors measure the surface, concavities included";
    } else if (stereo) {
      why =
          "chosen: the silhouettes hold the whole subject (clean plate, background model or "
          "alpha), so stereo inside their hull carves the concavities the hull keeps";
    } else {
      why =
          "not chosen: thresholded silhouettes may lose the subject's darkest parts, and "
          "stereo searches only inside their hull; a textured subject on a plain background "
          "can ask for it (--method mvs)";
    }
    return {{"chosen", stereo}, {"why", why}};
  }

  void DescribePlan() {
    const std::string skipped =
        is_tsdf() ? (plan_.hull_completion ? "stereo" : "silhouettes, hull, stereo")
        : plan_.method == ReconstructionMethod::kHull ? "depth fusion, stereo"
                                                      : "depth sensors";
    TakePlan described = take_plan_;
    if (!is_tsdf()) {
      if (!described.depth_sensors.empty())
        described.LeaveOut("depth sensors", "the method reads colour cameras only");
      described.depth_sensors.clear();
    }
    const bool stereo = plan_.method == ReconstructionMethod::kMvs && implausible_.empty();
    const std::vector<std::string> names = take_plan_.ReconstructionSensors();
    std::vector<std::string> references;
    for (int i : plan_.mvs_views.references) references.push_back(names[i]);
    if (stereo && references.size() < names.size()) {
      described.LeaveOut("stereo depth of every view",
                         Cat(names.size() - references.size(), " of the ", names.size(),
                             " views are only matched against, their own depth not searched: ",
                             plan_.mvs_views.why));
    }
    if (stereo && SweepsVoxels()) {
      described.LeaveOut("voxel sweep",
                         "multi-view stereo's cost follows the pixels and planes, not the voxel: "
                         "each sweep voxel would run the whole stereo again");
    }
    nlohmann::json plan = described.ToJson();
    plan["method"] = ToString(plan_.method);
    plan["method_reason"] =
        options_.method != ReconstructionMethod::kAuto ? "asked for"
        : is_tsdf() ? "depth sensors present: TSDF fusion of their depth"
        : plan_.method == ReconstructionMethod::kMvs
            ? "no depth sensor: multi-view stereo inside the visual hull"
            : "no depth sensor, no clean plate and no alpha: the visual hull of thresholded "
              "silhouettes (a subject on a plain dark background gives stereo nothing to match "
              "around it)";
    if (!needs_plate() && !plan_.hull_completion) {
      plan["silhouettes"] = {{"source", "not needed"}, {"why", "the method reads depth alone"}};
    } else {
      plan["silhouettes"]["morphology"] = {{"choice", morphology_},
                                           {"asked", ToString(options_.silhouette_morphology)},
                                           {"why", morphology_why_}};
      if (closing_measured_) plan["silhouettes"]["morphology"]["measured"] = closing_.ToJson();
    }
    plan["stereo_inside_hull"] = StereoInsideHull(stereo);
    plan["completion"] = completion_;
    if (plan_.method == ReconstructionMethod::kHull)
      plan["hull_min_views"] = {{"views", plan_.hull_min_views},
                                {"why", "half the cameras reconstructed from"}};
    plan["depth_background"] =
        plan_.depth_background ? "depth clean plate" : "none (everything in the bounds is fused)";
    plan["voxel_m"] = voxel_;
    if (plan_.method != ReconstructionMethod::kHull) {
      plan["depth_range"] = {{"min_m", plan_.depth_min_m},
                             {"max_m", plan_.depth_max_m},
                             {"source", plan_.depth_range_source}};
    }
    plan["mvs_search"] = {{"hull_margin_m", plan_.mvs.hull_margin_m},
                          {"search_depth_m", plan_.mvs.search_depth_m}};
    if (stereo) {
      plan["stereo_views"] = {
          {"references", references}, {"why", plan_.mvs_views.why}, {"partners", StereoPartners()}};
      plan["stereo_estimate"] = {
          {"seconds", stereo_estimate_.seconds},
          {"pixel_hypotheses", stereo_estimate_.pixel_hypotheses},
          {"seconds_per_hypothesis", stereo_estimate_.seconds_per_hypothesis},
          {"threads", stereo_estimate_.threads},
          {"basis",
           "an estimate of each frame set's sweeps: the first frame set's silhouette "
           "tiles x the planes of the hull margin and search depth x the source views, "
           "at the sweep's rate measured on this machine as the run was planned"}};
    }
    plan["parallel"] = plan_.outer_threads > 1
                           ? Cat(plan_.outer_threads, " frames at once, 1 thread each")
                           : Cat("one frame at a time, ", plan_.inner_threads, " threads each");
    plan["texture"] = options_.texture.atlas ? "per-vertex colour and atlas" : "per-vertex colour";
    plan["skipped"] = skipped;
    summary_.plan = plan;
    std::printf("reconstruct: %s on %d frame set(s), voxel %.3g mm, cameras from %s\n",
                ToString(plan_.method), frame_count_, voxel_ * 1e3,
                take_plan_.ground_truth_cameras ? "gt/ (not calibrated)" : "calib/");
    std::printf("  %s\n", plan["method_reason"].get<std::string>().c_str());
    const Box& b = take_plan_.bounds;
    std::printf("  bounds (%.3f, %.3f, %.3f) to (%.3f, %.3f, %.3f) m: %s\n", b.min.x(), b.min.y(),
                b.min.z(), b.max.x(), b.max.y(), b.max.z(), take_plan_.bounds_source.c_str());
    std::printf("  voxel: %s\n", take_plan_.voxel_source.c_str());
    std::printf("  up (%.3f, %.3f, %.3f): %s\n", take_plan_.up.x(), take_plan_.up.y(),
                take_plan_.up.z(), take_plan_.up_source.c_str());
    if (needs_plate() || plan_.hull_completion) {
      std::printf("  silhouettes: %s (%s)\n", ToString(take_plan_.silhouettes),
                  take_plan_.silhouette_reason.c_str());
      std::printf("  silhouette morphology: %s: %s\n", morphology_.c_str(),
                  morphology_why_.c_str());
    }
    if (is_tsdf()) std::printf("  completion: %s\n", completion_.c_str());
    std::printf("  stereo inside the hull: %s\n",
                plan["stereo_inside_hull"]["why"].get<std::string>().c_str());
    if (stereo) {
      std::printf("  stereo views: %zu of %zu searched: %s\n", references.size(), names.size(),
                  plan_.mvs_views.why.c_str());
      std::printf("  stereo partners: %s\n", StereoPartners().c_str());
      std::printf(
          "  stereo estimate: %.0f s per frame set (%.3g pixel x plane x source hypotheses at "
          "%.3g ns each, %d thread(s); the rate measured now): an estimate\n",
          stereo_estimate_.seconds, static_cast<double>(stereo_estimate_.pixel_hypotheses),
          stereo_estimate_.seconds_per_hypothesis * 1e9, stereo_estimate_.threads);
    }
    std::printf("  %s\n", plan["parallel"].get<std::string>().c_str());
    std::printf("  plan: %s\n", plan_origin_.c_str());
    if (!options_.tasks.shard.whole()) {
      std::printf("  shard %s: %zu of the run's %d frame set(s)\n",
                  options_.tasks.shard.ToString().c_str(), todo_.size(), frame_count_);
    }
    std::fflush(stdout);
    if (report_ != nullptr) {
      report_->options() = options_.ToJson();
      report_->options()["take"] = take_.dir().string();
      report_->options()["out"] = out_.string();
      report_->plan() = plan;
    }
  }

  // Reconstructs, textures and writes the run's i-th frame set into `result`; measures it
  // against the truth if any. Returns the files written (durably), relative to the output.
  std::vector<std::string> ReconstructOne(int i, FrameResult* result) {
    const int64_t set = take_plan_.sets[i];
    auto frame_start = std::chrono::steady_clock::now();
    FrameOutput frame =
        FrameReconstructor(take_, take_plan_, plates_, plan_, options_, voxel_, plan_.inner_threads)
            .Run(set);
    const std::string too_large = MeshLargerThanView(frame);
    if (!too_large.empty()) frame.End(Termination::kDegenerate, too_large);
    result->set = set;
    result->End(frame.termination, frame.message);
    result->metrics = frame.metrics;
    std::vector<std::string> written;
    if (frame.IsUsable()) {
      std::vector<View> views;
      FrameSet colour = take_.Read(static_cast<size_t>(set), take_plan_.color_sensors);
      for (const auto& name : take_plan_.ReconstructionSensors()) {
        views.push_back(
            {name, take_plan_.cameras.at(name), ColourOf(colour.Find(name)->image, name), {}});
      }
      if (!take_plan_.heldout.empty())
        result->metrics["heldout_iou"] = HeldoutIoU(frame.mesh, colour);
      TextureOptions texture = options_.texture;
      texture.atlas = texture.atlas && options_.write_glb;
      // Visibility's depth tolerance follows the scene: at most four voxels (1 cm is 20 of them
      // on a 9 cm object).
      texture.depth_tolerance_m = std::min(texture.depth_tolerance_m, 4 * voxel_);
      TexturedMesh textured = TextureMesh(frame.mesh, views, texture);
      written.push_back(SetName(set) + ".ply");
      WritePly(out_ / written.back(), textured.mesh, /*durable=*/true);
      if (options_.write_glb) {
        written.push_back(SetName(set) + ".glb");
        WriteGlb(out_ / written.back(), textured, /*durable=*/true);
      }
      result->metrics["texture"] = textured.Metrics();
    }
    result->seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - frame_start).count();
    result->vertices = static_cast<int64_t>(frame.mesh.vertices.size());
    result->faces = static_cast<int64_t>(frame.mesh.faces.size());
    if (frame.IsUsable() && take_.has_ground_truth()) {
      AddGroundTruthMetrics(take_, set, frame.mesh, take_plan_, plan_, &result->metrics);
    }
    return written;
  }

  // The task's k-th frame set: skipped when its record is complete, else reconstructed and
  // recorded last (the run's first set with the voxel sweep). False when skipped.
  bool ReconstructOrSkip(int k) {
    const int i = todo_[k];
    const int64_t set = take_plan_.sets[i];
    if (!options_.tasks.redo) {
      if (const auto record = records_->Complete(set)) {
        summary_.frames[k] = FrameResultFromJson((*record)["result"]);
        return false;
      }
    }
    const double started = UnixSeconds();
    const std::vector<std::string> written = ReconstructOne(i, &summary_.frames[k]);
    nlohmann::json result = ToJson(summary_.frames[k]);
    if (i == 0) result["voxel_sweep"] = SweepVoxels(summary_.frames[k]);
    records_->Record(set, result, written, started, task_);
    return true;
  }

  void ReconstructFrames() {
    const int count = static_cast<int>(todo_.size());
    summary_.frames.resize(count);
    Progress progress("reconstruct", count);
    std::mutex error_mutex;
    std::exception_ptr error;
    std::atomic<int> skipped{0};
#pragma omp parallel for num_threads(plan_.outer_threads) schedule(dynamic, 1)
    for (int k = 0; k < count; ++k) {
      try {
        if (!ReconstructOrSkip(k)) ++skipped;
        progress.Increment();
      } catch (...) {
        std::lock_guard lock(error_mutex);
        if (!error) error = std::current_exception();
      }
    }
    progress.Finish();
    if (error) std::rethrow_exception(error);
    skipped_ = skipped;
    if (skipped_ > 0) {
      std::printf("reconstruct: %d of %d frame set(s) skipped: complete from an earlier run\n",
                  skipped_, count);
    }
  }

  // Whether the run's first frame is also reconstructed at the sweep's voxels: on simulated
  // takes, unless stereo, whose cost does not follow the voxel, would run again at each.
  bool SweepsVoxels() const {
    return take_.has_ground_truth() && !options_.sweep_voxels_m.empty() &&
           plan_.method != ReconstructionMethod::kMvs;
  }

  // How each stereo reference view chooses its partners, in words.
  std::string StereoPartners() const {
    return Cat("each reference view is matched against its ", plan_.mvs.neighbors,
               " nearest views by the angle the two make at the subject (their baseline as it "
               "sees it) plus ln of their distances' ratio, within ",
               plan_.mvs.min_angle_deg, " to ", plan_.mvs.max_angle_deg,
               " degrees (beyond, short of 90 degrees, only to fill up a sparse rig's; a view "
               "opposite is never one), and its depth checked against its nearest reference "
               "views alike");
  }

  // Error against time as the voxel size varies, on the run's first frame (simulated takes).
  nlohmann::json SweepVoxels(const FrameResult& first) {
    nlohmann::json sweep = nlohmann::json::array();
    if (!SweepsVoxels() || !first.metrics.contains("gt")) return sweep;
    std::vector<double> voxels = options_.sweep_voxels_m;
    voxels.push_back(voxel_);
    std::sort(voxels.begin(), voxels.end(), std::greater<double>());
    voxels.erase(std::unique(voxels.begin(), voxels.end()), voxels.end());
    for (double voxel : voxels) {
      double seconds;
      nlohmann::json metrics;
      if (voxel == voxel_) {
        seconds = first.seconds;
        metrics = first.metrics;
      } else {
        auto t0 = std::chrono::steady_clock::now();
        FrameOutput frame =
            FrameReconstructor(take_, take_plan_, plates_, plan_, options_, voxel, threads_)
                .Run(take_plan_.sets[0]);
        seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        if (!frame.IsUsable()) continue;
        AddGroundTruthMetrics(take_, take_plan_.sets[0], frame.mesh, take_plan_, plan_, &metrics);
      }
      if (!metrics.contains("gt")) continue;
      sweep.push_back({{"voxel_mm", voxel * 1e3},
                       {"seconds", seconds},
                       {"chamfer_mm", metrics["gt"]["chamfer_mm"]},
                       {"fscore_5mm", metrics["gt"]["fscore_5mm"]}});
    }
    return sweep;
  }

  // The run's records: its identity is what decides each frame's bytes (the options and the
  // plan, less threads, the task's shard and how the task runs its frames in parallel).
  void StartRecords() {
    nlohmann::json options = options_.ToJson();
    options.erase("threads");
    options.erase("tasks");
    nlohmann::json plan = summary_.plan;
    plan.erase("parallel");
    // The estimate is a measured rate: the run's own, not what decides its frames' bytes.
    nlohmann::json identity_plan = plan;
    identity_plan.erase("stereo_estimate");
    const nlohmann::json take = TakeIdentity();
    records_.emplace(out_, "reconstruct",
                     nlohmann::json{{"options", options},
                                    {"plan", identity_plan},
                                    {"recording", take["recording"]},
                                    {"cameras", take["cameras"]}},
                     take_plan_.sets);
    options["take"] = take_.dir().string();
    options["out"] = out_.string();
    records_->WriteRun({{"options", options}, {"plan", plan}});
  }

  // A whole run's report is the one merged from its records (as a sharded run's is); a shard
  // writes its own, and the run's too when its frames complete the run.
  void FinishTask() {
    const double wall_s =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
    const RunState run = ReadRunState(out_);
    const Shard& shard = options_.tasks.shard;
    if (shard.whole()) {
      Report local("reconstruct");
      summary_ = SummariseRun(run, report_ != nullptr ? report_ : &local);
      summary_.seconds = wall_s;
      return;
    }
    const int count = static_cast<int>(todo_.size());
    EndByFrames(summary_.frames, ToString(plan_.method), &summary_);
    if (count == 0) {
      summary_.End(Termination::kSuccess, Cat("shard ", shard.ToString(), " holds none of the ",
                                              frame_count_, " frame sets"));
    }
    summary_.seconds = wall_s;
    std::printf("reconstruct: shard %s did %d and skipped %d of its %d frame set(s); the run: %s\n",
                shard.ToString().c_str(), count - skipped_, skipped_, count,
                run.Describe().c_str());
    if (run.done()) {
      Report merged("reconstruct");
      const ReconstructionSummary all = SummariseRun(run, &merged);
      std::printf("reconstruct: the run is complete: %s (%s)\n", (out_ / "report.json").c_str(),
                  ToString(all.termination));
    }
    if (report_ == nullptr) return;
    nlohmann::json& metrics = report_->metrics();
    AddFrameMetrics(summary_.frames, nlohmann::json::array(), &metrics);
    metrics["timing"] = {{"frames_done", count - skipped_},
                         {"frames_skipped", skipped_},
                         {"wall_s", wall_s},
                         {"frames_per_minute", 60.0 * (count - skipped_) / wall_s}};
    metrics["peak_rss_mb"] = PeakRssMb();
    metrics["plan"] = plan_origin_;
    metrics["run"] = run.Describe();
    report_->plan() = summary_.plan;
    report_->SetSummary(summary_);
    report_->Write(TaskReportPath(out_, shard));
  }

  const Take& take_;
  TakePlan take_plan_;  // the caller's, with the bounds this run tightens
  const std::filesystem::path out_;
  const ReconstructionOptions& options_;
  Report* report_;
  const std::chrono::steady_clock::time_point start_ = std::chrono::steady_clock::now();
  MethodPlan plan_;
  MvsEstimate stereo_estimate_;  // MVS: what each frame set's sweeps will cost
  Plates plates_;
  std::string completion_;
  // The closing measured for thresholded silhouettes (kAuto), and what the morphology is and
  // why, for the plan.
  ClosingChoice closing_;
  bool closing_measured_ = false;
  std::string morphology_;
  std::string morphology_why_;
  std::string implausible_;  // why the run cannot give a plausible result, before any frame
  double voxel_ = 0;
  int threads_ = 1;
  int frame_count_ = 0;    // the run's frame sets
  std::vector<int> todo_;  // this task's: indices into the run's sets
  int skipped_ = 0;        // of them, complete from an earlier run
  const std::string task_ = DescribeTask(options_.tasks.shard);  // who this task is
  std::string plan_origin_;  // whether this task made the run's plan or read it
  std::optional<FrameRecords> records_;
  ReconstructionSummary summary_;
};

}  // namespace

ReconstructionSummary ReconstructTake(const Take& take, const TakePlan& plan,
                                      const std::filesystem::path& out,
                                      const ReconstructionOptions& options, Report* report) {
  options.Check();
  return TakeReconstructor(take, plan, out, options, report).Run();
}

ReconstructionSummary ReconstructTake(const std::filesystem::path& take_dir,
                                      const TakeSelection& selection,
                                      const std::filesystem::path& out,
                                      const ReconstructionOptions& options, Report* report) {
  options.Check();
  const Take take = Take::Open(take_dir);
  const TakePlan plan = PlanTake(take, selection);
  return ReconstructTake(take, plan, out, options, report);
}

ReconstructionSummary MergeReconstruction(const std::filesystem::path& out, Report* report) {
  const RunState run = ReadRunState(out);
  if (run.command != "reconstruct") {
    Fail("'", out.string(), "' holds a run of holocap ", run.command, ", not of reconstruct");
  }
  return SummariseRun(run, report);
}

}  // namespace holocap
