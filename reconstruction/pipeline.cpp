// The per-take pipeline: plan the methods from the rig, reconstruct frame sets in parallel,
// write meshes and report.json, measure against ground truth where the take has it.
#include <omp.h>
#include <opencv2/imgproc.hpp>
#include <sys/resource.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <exception>
#include <map>
#include <mutex>
#include <optional>

#include "core/error.h"
#include "core/fs.h"
#include "core/mesh.h"
#include "core/progress.h"
#include "core/take.h"
#include "reconstruction/projector.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

const char* ToString(ReconstructionMethod method) {
  switch (method) {
    case ReconstructionMethod::kAuto: return "auto";
    case ReconstructionMethod::kHull: return "hull";
    case ReconstructionMethod::kTsdf: return "tsdf";
    case ReconstructionMethod::kMvs: return "mvs";
  }
  return "?";
}

ReconstructionMethod ReconstructionMethodFromString(const std::string& text) {
  for (auto m : {ReconstructionMethod::kAuto, ReconstructionMethod::kHull, ReconstructionMethod::kTsdf,
                 ReconstructionMethod::kMvs}) {
    if (text == ToString(m)) return m;
  }
  Fail("unknown reconstruction method '", text, "' (known: auto, hull, tsdf, mvs)");
}

void ReconstructionOptions::Check() const {
  if (!(voxel_m > 0 && voxel_m < 1)) Fail("voxel must be in (0, 1) m (got ", voxel_m, ")");
  if (first_frame < 0) Fail("first frame must be >= 0 (got ", first_frame, ")");
  if (last_frame >= 0 && last_frame <= first_frame) {
    Fail("frame range ", first_frame, ":", last_frame, " is empty");
  }
  if (!bounds.valid()) Fail("reconstruction bounds are empty");
  for (double v : sweep_voxels_m) {
    if (!(v > 0 && v < 1)) Fail("sweep voxel sizes must be in (0, 1) m (got ", v, ")");
  }
  if (threads < 0) Fail("threads must be >= 0");
  if (!(completion_margin_px > -10 && completion_margin_px < 100)) {
    Fail("completion margin must be in (-10, 100) px (got ", completion_margin_px, ")");
  }
  silhouette.Check();
  mvs.Check();
  meshing.Check();
  texture.Check();
}

nlohmann::json ReconstructionOptions::ToJson() const {
  auto box = [](const Box& b) {
    return nlohmann::json{{"min", {b.min.x(), b.min.y(), b.min.z()}}, {"max", {b.max.x(), b.max.y(), b.max.z()}}};
  };
  return {{"method", ToString(method)},
          {"voxel_m", voxel_m},
          {"first_frame", first_frame},
          {"last_frame", last_frame},
          {"clean_plate_frames", clean_plate_frames},
          {"bounds", box(bounds)},
          {"silhouette",
           {{"mode", silhouette.mode == SilhouetteMode::kThreshold ? "threshold" : "background"},
            {"noise_sigmas", silhouette.noise_sigmas},
            {"min_difference", silhouette.min_difference},
            {"hysteresis_sigmas", silhouette.hysteresis_sigmas},
            {"hysteresis_min_difference", silhouette.hysteresis_min_difference},
            {"threshold", silhouette.threshold},
            {"open_px", silhouette.open_px},
            {"dilate_px", silhouette.dilate_px},
            {"erode_px", silhouette.erode_px}}},
          {"hull", {{"tolerated_bad_views", hull.tolerated_bad_views}, {"min_views", hull.min_views},
                    {"margin_px", hull.margin_px}}},
          {"tsdf", {{"truncation_voxels", tsdf.truncation_voxels}, {"max_weight", tsdf.max_weight},
                    {"depth_noise_k", tsdf.depth_noise_k}, {"smoothing_radius_px", tsdf.smoothing_radius_px},
                    {"max_incidence_deg", tsdf.max_incidence_deg}}},
          {"mvs", {{"neighbors", mvs.neighbors}, {"window_radius", mvs.window_radius},
                   {"depth_step_px", mvs.depth_step_px}, {"min_ncc", mvs.min_ncc},
                   {"min_consistent_views", mvs.min_consistent_views}}},
          {"tsdf_hull_completion", tsdf_hull_completion},
          {"completion_margin_px", completion_margin_px},
          {"meshing", {{"simplify_cell_m", meshing.simplify_cell_m}}},
          {"texture", {{"texels_per_cell", texture.texels_per_cell}, {"max_views", texture.max_views},
                       {"min_cos_incidence", texture.min_cos_incidence}, {"depth_tolerance_m", texture.depth_tolerance_m},
                       {"occlusion_scale", texture.occlusion_scale}, {"fill_unseen", texture.fill_unseen},
                       {"fill_smoothing_iterations", texture.fill_smoothing_iterations}, {"atlas", texture.atlas}}},
          {"write_glb", write_glb},
          {"sweep_voxels_m", sweep_voxels_m},
          {"threads", threads}};
}

namespace {

std::string SetName(int64_t set) {
  char name[32];
  std::snprintf(name, sizeof(name), "%06lld", static_cast<long long>(set));
  return name;
}

double PeakRssMb() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return usage.ru_maxrss / 1024.0;
}

struct Sensors {
  std::vector<std::string> color;
  std::vector<std::string> depth;
  std::map<std::string, CameraModel> models;
};

struct Plan {
  ReconstructionMethod method = ReconstructionMethod::kAuto;
  bool ground_truth_cameras = false;
  int64_t clean_plate_frames = 0;
  std::vector<int64_t> sets;
  int outer_threads = 1;
  int inner_threads = 1;
  bool depth_background = false;
  bool hull_completion = false;  // TSDF: completed from the visual hull
};

// Everything one frame needs, read once (the clean plates are shared by all frames).
struct Plates {
  std::map<std::string, cv::Mat> color;
  std::map<std::string, cv::Mat> depth;
};

struct FrameOutput {
  Mesh mesh;
  nlohmann::json metrics = nlohmann::json::object();
  Termination termination = Termination::kSuccess;
  std::string message;
};

// Reconstructs one frame set at one voxel size.
FrameOutput ReconstructFrame(const Take& take, const Sensors& sensors, const Plates& plates,
                             const Plan& plan, const ReconstructionOptions& options, int64_t set,
                             double voxel, int threads) {
  FrameOutput out;
  std::vector<std::string> needed = sensors.color;
  if (plan.method == ReconstructionMethod::kTsdf) needed.insert(needed.end(), sensors.depth.begin(), sensors.depth.end());
  FrameSet frames = take.Read(static_cast<size_t>(set), needed);
  std::vector<View> views;
  const bool need_masks = plan.method != ReconstructionMethod::kTsdf || plan.hull_completion;
  for (const std::string& name : sensors.color) {
    const Frame* frame = frames.Find(name);
    View view{name, sensors.models.at(name), frame->image, {}};
    if (view.image.type() == CV_8UC1) cv::cvtColor(view.image, view.image, cv::COLOR_GRAY2BGR);
    if (view.image.type() != CV_8UC3) Fail("colour frames of '", name, "' must be 8-bit");
    if (need_masks) {
      auto plate = plates.color.find(name);  // none in threshold mode
      view.mask = ExtractSilhouette(view.image, plate == plates.color.end() ? cv::Mat() : plate->second,
                                    options.silhouette);
    }
    views.push_back(std::move(view));
  }
  Box bounds = options.bounds;
  if (plan.method == ReconstructionMethod::kHull) {
    HullOptions hull_options = options.hull;
    hull_options.voxel_m = voxel;
    hull_options.bounds = bounds;
    hull_options.threads = threads;
    HullSummary summary;
    VisualHull hull = ComputeVisualHull(views, hull_options, &summary);
    out.metrics["hull"] = {{"seconds", summary.seconds}, {"volume_m3", summary.volume_m3},
                           {"surface_blocks", summary.surface_blocks}, {"octree_cells", summary.octree_cells}};
    out.termination = summary.termination;
    out.message = summary.message;
    if (IsUsable(summary.termination)) out.mesh = ExtractMesh(*hull.volume, options.meshing);
  } else {
    TsdfOptions tsdf_options = options.tsdf;
    tsdf_options.voxel_m = voxel;
    tsdf_options.bounds = bounds;
    tsdf_options.threads = threads;
    std::optional<TsdfVolume> tsdf;
    if (plan.method == ReconstructionMethod::kTsdf) {
      tsdf.emplace(tsdf_options);
      double seconds = 0;
      int64_t valid = 0;
      std::vector<std::pair<CameraModel, cv::Mat>> depth_maps;
      for (const std::string& name : sensors.depth) {
        const Frame* frame = frames.Find(name);
        const std::string& paired = take.stream(name).paired_with;
        cv::Mat foreground;
        if (plan.depth_background) foreground = DepthForeground(frame->image, plates.depth.at(name), options.tsdf.depth_noise_k);
        const View* color_view = nullptr;
        for (const View& v : views) color_view = v.name == paired ? &v : color_view;
        TsdfFrameStats stats = color_view != nullptr
                                   ? tsdf->Integrate(frame->image, sensors.models.at(name), foreground,
                                                     color_view->image, &color_view->camera)
                                   : tsdf->Integrate(frame->image, sensors.models.at(name), foreground);
        seconds += stats.seconds;
        valid += stats.valid_pixels;
        depth_maps.emplace_back(sensors.models.at(name), frame->image);
      }
      out.metrics["tsdf"] = {{"integrate_seconds", seconds}, {"valid_pixels", valid},
                             {"blocks", tsdf->volume().block_count()},
                             {"memory_mb", tsdf->volume().memory_bytes() / 1048576.0}};
      if (plan.hull_completion) {
        HullOptions hull_options = options.hull;
        hull_options.voxel_m = voxel;
        hull_options.bounds = bounds;
        hull_options.margin_px = options.completion_margin_px;
        hull_options.threads = threads;
        HullSummary hull_summary;
        VisualHull hull = ComputeVisualHull(views, hull_options, &hull_summary);
        out.metrics["hull"] = {{"seconds", hull_summary.seconds}, {"volume_m3", hull_summary.volume_m3}};
        if (IsUsable(hull_summary.termination)) {
          CompletionStats completion = tsdf->CompleteFromHull(hull, depth_maps);
          out.metrics["completion"] = {{"seconds", completion.seconds},
                                       {"blocks_added", completion.blocks_added},
                                       {"voxels_filled", completion.voxels_filled},
                                       {"voxels_carved", completion.voxels_carved},
                                       {"memory_mb", tsdf->volume().memory_bytes() / 1048576.0}};
        } else {
          // The depth sensors' surface stands alone; the frame says why.
          out.metrics["completion"] = {{"skipped", "hull: " + hull_summary.message}};
        }
      }
    } else {
      HullOptions hull_options = options.hull;
      hull_options.voxel_m = 2 * voxel;
      hull_options.bounds = bounds;
      hull_options.threads = threads;
      HullSummary hull_summary;
      VisualHull hull = ComputeVisualHull(views, hull_options, &hull_summary);
      out.metrics["hull"] = {{"seconds", hull_summary.seconds}, {"volume_m3", hull_summary.volume_m3}};
      if (!IsUsable(hull_summary.termination)) {
        out.termination = hull_summary.termination;
        out.message = "hull: " + hull_summary.message;
        return out;
      }
      MvsOptions mvs_options = options.mvs;
      mvs_options.threads = threads;
      MvsSummary mvs_summary;
      std::vector<cv::Mat> depths = ComputeMvsDepth(views, hull, mvs_options, &mvs_summary);
      out.metrics["mvs"] = {{"seconds", mvs_summary.seconds}, {"pixels_matched", mvs_summary.pixels_matched},
                            {"pixels_consistent", mvs_summary.pixels_consistent}, {"planes", mvs_summary.planes}};
      if (!IsUsable(mvs_summary.termination)) {
        out.termination = mvs_summary.termination;
        out.message = "mvs: " + mvs_summary.message;
        return out;
      }
      // Stereo depth is already consistent between views; its error grows like z^2 too.
      tsdf_options.smoothing_radius_px = 1;
      tsdf.emplace(tsdf_options);
      double seconds = 0;
      for (size_t i = 0; i < views.size(); ++i) {
        seconds += tsdf->Integrate(depths[i], views[i].camera, views[i].mask, views[i].image, &views[i].camera).seconds;
      }
      out.metrics["tsdf"] = {{"integrate_seconds", seconds}, {"blocks", tsdf->volume().block_count()}};
    }
    out.mesh = ExtractMesh(tsdf->volume(), options.meshing);
  }
  if (out.mesh.faces.empty() && IsUsable(out.termination)) {
    out.termination = Termination::kDegenerate;
    out.message = "no surface was found";
  }
  if (IsUsable(out.termination) && out.message.empty()) {
    out.message = Cat(out.mesh.vertices.size(), " vertices, ", out.mesh.faces.size(), " triangles");
  }
  return out;
}

void AddGroundTruthMetrics(const Take& take, int64_t set, const Mesh& mesh, const Sensors& sensors,
                           const Plan& plan, nlohmann::json* metrics) {
  std::filesystem::path file = take.gt_dir() / "meshes" / (SetName(set) + ".ply");
  if (!std::filesystem::exists(file)) file = take.gt_dir() / "meshes" / "static.ply";
  if (!std::filesystem::exists(file)) return;
  Mesh truth = ReadPly(file);
  // The simulated subject is a union of overlapping closed body parts: what lies inside another
  // part is not its surface, and completeness is measured on the outer surface only.
  const auto outer = OnOuterSurface(truth);
  SurfaceErrors e = CompareSurfaces(mesh, truth, 0.005, 40000, outer);
  SurfaceErrors all = CompareSurfaces(mesh, truth, 0.005);
  nlohmann::json gt = {{"chamfer_mm", e.chamfer_mm}, {"accuracy_mm", e.accuracy_mm},
                       {"completeness_mm", e.completeness_mm}, {"fscore_5mm", e.fscore},
                       {"precision_5mm", e.precision}, {"recall_5mm", e.recall},
                       {"chamfer_with_buried_faces_mm", all.chamfer_mm},
                       {"completeness_with_buried_faces_mm", all.completeness_mm}};
  if (plan.method == ReconstructionMethod::kTsdf) {
    // Depth sensors see only part of the subject: also measure on what they saw.
    std::vector<std::pair<CameraModel, cv::Mat>> seen;
    for (const auto& name : sensors.depth) {
      auto depth_file = take.gt_dir() / "depth" / name / (SetName(set) + ".exr");
      if (std::filesystem::exists(depth_file)) seen.emplace_back(take.Camera(name, true), ReadImage(depth_file));
    }
    if (!seen.empty()) {
      SurfaceErrors o = CompareSurfaces(mesh, truth, 0.005, 40000, SeenInDepthMaps(seen));
      gt["observed"] = {{"chamfer_mm", o.chamfer_mm}, {"accuracy_mm", o.accuracy_mm},
                        {"completeness_mm", o.completeness_mm}, {"fscore_5mm", o.fscore}};
    }
  }
  (*metrics)["gt"] = gt;
}

}  // namespace

ReconstructionSummary ReconstructTake(const std::filesystem::path& take_dir, const std::filesystem::path& out,
                                      const ReconstructionOptions& options, Report* report) {
  options.Check();
  auto start = std::chrono::steady_clock::now();
  const Take take = Take::Open(take_dir);
  Plan plan;
  Sensors sensors;
  for (const StreamInfo& stream : take.streams()) {
    if (stream.role == SensorRole::kColor) sensors.color.push_back(stream.name);
    if (stream.role == SensorRole::kDepth) sensors.depth.push_back(stream.name);
  }
  if (sensors.color.empty() && sensors.depth.empty()) Fail("take '", take_dir.string(), "' has no colour or depth sensor");
  if (take.has_calibration()) {
    plan.ground_truth_cameras = false;
  } else if (take.has_ground_truth() && std::filesystem::is_directory(take.gt_dir() / "cameras")) {
    plan.ground_truth_cameras = true;
  } else {
    Fail("take '", take_dir.string(), "' is not calibrated (no calib/<sensor>.cameramodel for every sensor): run holocap calibrate first");
  }
  for (const auto& name : sensors.color) sensors.models.emplace(name, take.Camera(name, plan.ground_truth_cameras));
  for (const auto& name : sensors.depth) sensors.models.emplace(name, take.Camera(name, plan.ground_truth_cameras));

  plan.method = options.method;
  if (plan.method == ReconstructionMethod::kAuto) {
    plan.method = sensors.depth.empty() ? ReconstructionMethod::kMvs : ReconstructionMethod::kTsdf;
  }
  if (plan.method == ReconstructionMethod::kTsdf && sensors.depth.empty()) {
    Fail("method tsdf needs depth sensors; take '", take_dir.string(), "' has none (use hull or mvs)");
  }
  if (plan.method != ReconstructionMethod::kTsdf && sensors.color.size() < 2) {
    Fail("method ", ToString(plan.method), " needs at least two colour cameras; the take has ", sensors.color.size());
  }
  plan.clean_plate_frames = options.clean_plate_frames;
  if (plan.clean_plate_frames < 0) {
    plan.clean_plate_frames = take.metadata().value("clean_plate_frames", int64_t{0});
  }
  const bool need_plate = plan.method != ReconstructionMethod::kTsdf;
  if (need_plate && plan.clean_plate_frames == 0 && options.silhouette.mode == SilhouetteMode::kBackgroundSubtraction) {
    Fail("method ", ToString(plan.method), " needs silhouettes, and background subtraction needs a clean plate: "
         "take '", take_dir.string(), "' has none (record leading frames without the subject and pass --clean-plate N)");
  }
  if (plan.clean_plate_frames >= static_cast<int64_t>(take.size())) {
    Fail("take '", take_dir.string(), "' has ", take.size(), " frame sets, all of them clean plate");
  }
  const int64_t available = static_cast<int64_t>(take.size()) - plan.clean_plate_frames;
  const int64_t first = options.first_frame;
  const int64_t last = options.last_frame < 0 ? available : std::min(options.last_frame, available);
  if (first >= last) Fail("frame range ", first, ":", last, " selects nothing (the take has ", available, " frame sets after its clean plate)");
  for (int64_t f = first; f < last; ++f) plan.sets.push_back(plan.clean_plate_frames + f);

  // Every frame set must hold every camera the method reads.
  std::vector<std::string> needed = sensors.color;
  if (plan.method == ReconstructionMethod::kTsdf) needed.insert(needed.end(), sensors.depth.begin(), sensors.depth.end());
  for (int64_t set : plan.sets) {
    for (const auto& name : needed) {
      if (take.entry(static_cast<size_t>(set)).Find(name) == nullptr) {
        Fail("frame set ", set, " of take '", take_dir.string(), "' has no frame from '", name, "' (dropped); ",
             "choose another range with --frames");
      }
    }
  }
  Plates plates;
  if (plan.clean_plate_frames > 0) {
    const size_t plate_set = static_cast<size_t>(plan.clean_plate_frames - 1);
    for (const auto& name : needed) {
      if (take.entry(plate_set).Find(name) == nullptr) Fail("the clean plate (set ", plate_set, ") has no frame from '", name, "'");
      cv::Mat image = take.ReadFrame(plate_set, name);
      if (image.type() == CV_8UC1) cv::cvtColor(image, image, cv::COLOR_GRAY2BGR);
      (take.stream(name).role == SensorRole::kDepth ? plates.depth : plates.color)[name] = image;
    }
    plan.depth_background = plan.method == ReconstructionMethod::kTsdf;
  }
  std::string completion = "not a TSDF run";
  if (plan.method == ReconstructionMethod::kTsdf) {
    const bool silhouettes = options.silhouette.mode == SilhouetteMode::kThreshold || plan.clean_plate_frames > 0;
    plan.hull_completion = options.tsdf_hull_completion && sensors.color.size() >= 2 && silhouettes;
    completion = plan.hull_completion ? "visual hull of the colour cameras, carved by the depth sensors' free space, "
                                        "fills what the depth sensors did not see"
                 : !options.tsdf_hull_completion ? "off (asked for)"
                 : sensors.color.size() < 2     ? "off: fewer than two colour cameras"
                                                : "off: no clean plate for the colour cameras' silhouettes";
  }
  const int threads = recon::ResolveThreads(options.threads);
  const int frame_count = static_cast<int>(plan.sets.size());
  plan.outer_threads = frame_count >= threads ? threads : 1;
  plan.inner_threads = frame_count >= threads ? 1 : threads;

  ReconstructionSummary summary;
  nlohmann::json plan_json = {
      {"method", ToString(plan.method)},
      {"method_reason", options.method != ReconstructionMethod::kAuto ? "asked for"
                        : sensors.depth.empty() ? "no depth sensor: multi-view stereo inside the visual hull"
                                                : "depth sensors present: TSDF fusion of their depth"},
      {"cameras", plan.ground_truth_cameras ? "gt/cameras (the take has no calib/: true models of the simulation)"
                                            : "calib/"},
      {"color_sensors", sensors.color},
      {"depth_sensors", plan.method == ReconstructionMethod::kTsdf ? sensors.depth : std::vector<std::string>{}},
      {"silhouettes", need_plate || plan.hull_completion
                          ? (options.silhouette.mode == SilhouetteMode::kThreshold ? "threshold" : "background subtraction")
                          : "not needed"},
      {"completion", completion},
      {"depth_background", plan.depth_background ? "depth clean plate" : "none (everything in the bounds is fused)"},
      {"clean_plate_frames", plan.clean_plate_frames},
      {"frame_sets", plan.sets},
      {"voxel_m", options.voxel_m},
      {"parallel", plan.outer_threads > 1 ? Cat(plan.outer_threads, " frames at once, 1 thread each")
                                          : Cat("one frame at a time, ", plan.inner_threads, " threads each")},
      {"texture", options.texture.atlas ? "per-vertex colour and atlas" : "per-vertex colour"},
      {"skipped", plan.method == ReconstructionMethod::kTsdf ? (plan.hull_completion ? "stereo" : "silhouettes, hull, stereo")
                  : plan.method == ReconstructionMethod::kHull ? "depth fusion, stereo" : "depth sensors"}};
  summary.plan = plan_json;
  std::printf("reconstruct: %s on %d frame set(s), voxel %.1f mm, cameras from %s\n", ToString(plan.method),
              frame_count, options.voxel_m * 1e3, plan.ground_truth_cameras ? "gt/ (not calibrated)" : "calib/");
  std::printf("  %s\n", plan_json["method_reason"].get<std::string>().c_str());
  if (plan.method == ReconstructionMethod::kTsdf) std::printf("  completion: %s\n", completion.c_str());
  std::printf("  %s\n", plan_json["parallel"].get<std::string>().c_str());
  std::fflush(stdout);
  if (report != nullptr) {
    report->options() = options.ToJson();
    report->options()["take"] = take_dir.string();
    report->options()["out"] = out.string();
    report->plan() = plan_json;
  }
  CreateDirectories(out);

  summary.frames.resize(plan.sets.size());
  Progress progress("reconstruct", frame_count);
  std::mutex error_mutex;
  std::exception_ptr error;
#pragma omp parallel for num_threads(plan.outer_threads) schedule(dynamic, 1)
  for (int i = 0; i < frame_count; ++i) {
    try {
      const int64_t set = plan.sets[i];
      auto frame_start = std::chrono::steady_clock::now();
      FrameOutput frame = ReconstructFrame(take, sensors, plates, plan, options, set, options.voxel_m, plan.inner_threads);
      FrameResult& result = summary.frames[i];
      result.set = set;
      result.termination = frame.termination;
      result.message = frame.message;
      result.metrics = frame.metrics;
      if (IsUsable(frame.termination)) {
        std::vector<View> views;
        FrameSet colour = take.Read(static_cast<size_t>(set), sensors.color);
        for (const auto& name : sensors.color) {
          cv::Mat image = colour.Find(name)->image;
          if (image.type() == CV_8UC1) cv::cvtColor(image, image, cv::COLOR_GRAY2BGR);
          views.push_back({name, sensors.models.at(name), image, {}});
        }
        TextureOptions texture = options.texture;
        texture.atlas = texture.atlas && options.write_glb;
        TexturedMesh textured = TextureMesh(frame.mesh, views, texture);
        WritePly(out / (SetName(set) + ".ply"), textured.mesh);
        if (options.write_glb) WriteGlb(out / (SetName(set) + ".glb"), textured);
        result.metrics["texture"] = textured.Metrics();
      }
      result.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - frame_start).count();
      result.vertices = static_cast<int64_t>(frame.mesh.vertices.size());
      result.faces = static_cast<int64_t>(frame.mesh.faces.size());
      if (IsUsable(frame.termination) && take.has_ground_truth()) {
        AddGroundTruthMetrics(take, set, frame.mesh, sensors, plan, &result.metrics);
      }
      progress.Increment();
    } catch (...) {
      std::lock_guard lock(error_mutex);
      if (!error) error = std::current_exception();
    }
  }
  progress.Finish();
  if (error) std::rethrow_exception(error);

  // Error against time as the voxel size varies, on the first frame.
  nlohmann::json sweep = nlohmann::json::array();
  if (take.has_ground_truth() && !options.sweep_voxels_m.empty() && summary.frames[0].metrics.contains("gt")) {
    std::vector<double> voxels = options.sweep_voxels_m;
    voxels.push_back(options.voxel_m);
    std::sort(voxels.begin(), voxels.end(), std::greater<double>());
    voxels.erase(std::unique(voxels.begin(), voxels.end()), voxels.end());
    int64_t iter = 0;
    for (double voxel : voxels) {
      double seconds;
      nlohmann::json metrics;
      if (voxel == options.voxel_m) {
        seconds = summary.frames[0].seconds;
        metrics = summary.frames[0].metrics;
      } else {
        auto t0 = std::chrono::steady_clock::now();
        FrameOutput frame = ReconstructFrame(take, sensors, plates, plan, options, plan.sets[0], voxel, threads);
        seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        if (!IsUsable(frame.termination)) continue;
        AddGroundTruthMetrics(take, plan.sets[0], frame.mesh, sensors, plan, &metrics);
      }
      if (!metrics.contains("gt")) continue;
      double chamfer = metrics["gt"]["chamfer_mm"].get<double>();
      sweep.push_back({{"voxel_mm", voxel * 1e3}, {"seconds", seconds}, {"chamfer_mm", chamfer},
                       {"fscore_5mm", metrics["gt"]["fscore_5mm"]}});
      if (report != nullptr) {
        report->AddPoint("gt.chamfer_mm", chamfer, iter);
        report->AddPoint("seconds_per_frame", seconds, iter);
        report->AddPoint("voxel_mm", voxel * 1e3, iter);
      }
      ++iter;
    }
  }

  // Summary and metrics.
  nlohmann::json per_frame = nlohmann::json::array();
  nlohmann::json frames_json = nlohmann::json::array();
  int usable = 0;
  double total_seconds = 0;
  std::map<std::string, double> gt_sums;
  int gt_count = 0;
  for (const FrameResult& f : summary.frames) {
    per_frame.push_back(f.seconds);
    total_seconds += f.seconds;
    usable += IsUsable(f.termination);
    frames_json.push_back({{"set", f.set}, {"seconds", f.seconds}, {"vertices", f.vertices}, {"faces", f.faces},
                           {"termination", ToString(f.termination)}, {"message", f.message}, {"metrics", f.metrics}});
    if (f.metrics.contains("gt")) {
      ++gt_count;
      for (auto& [key, value] : f.metrics["gt"].items()) {
        if (value.is_number()) gt_sums[key] += value.get<double>();
      }
    }
  }
  summary.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  if (usable == frame_count) {
    summary.termination = Termination::kSuccess;
    summary.message = Cat(frame_count, " frame set(s) reconstructed by ", ToString(plan.method));
  } else {
    summary.termination = usable == 0 ? Termination::kDegenerate : Termination::kSuccess;
    summary.message = Cat(usable, " of ", frame_count, " frame sets gave a surface; first failure: ");
    for (const FrameResult& f : summary.frames) {
      if (!IsUsable(f.termination)) {
        summary.message += Cat("set ", f.set, ": ", f.message);
        break;
      }
    }
  }
  if (report != nullptr) {
    nlohmann::json& metrics = report->metrics();
    metrics["timing"] = {{"per_frame_s", per_frame},
                         {"mean_frame_s", total_seconds / frame_count},
                         {"wall_s", summary.seconds},
                         {"frames_per_minute", 60.0 * frame_count / summary.seconds}};
    metrics["peak_rss_mb"] = PeakRssMb();
    metrics["frames"] = frames_json;
    if (gt_count > 0) {
      for (auto& [key, sum] : gt_sums) metrics["gt"][key] = sum / gt_count;
      metrics["gt"]["frames"] = gt_count;
      metrics["gt"]["voxel_sweep"] = sweep;
    }
    report->SetSummary({summary.termination, summary.message});
    report->Write(out / "report.json");
  }
  return summary;
}

}  // namespace holocap
