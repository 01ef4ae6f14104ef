#include "avatar/training_data.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <opencv2/imgproc.hpp>

#include "core/error.h"
#include "core/image.h"
#include "core/mesh.h"
#include "core/take.h"
#include "core/take_plan.h"
#include "reconstruction/reconstruction.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;

// gt/ names files by frame set, six digits.
std::string SetFileName(int64_t set, const char* extension) {
  char name[32];
  std::snprintf(name, sizeof(name), "%06lld%s", static_cast<long long>(set), extension);
  return name;
}

// A frame's colour at the training size, as 8-bit BGR (a bgra8 frame's alpha is its
// silhouette, read apart by AlphaAtTrainingSize).
cv::Mat ToTrainingSize(const cv::Mat& image, const CameraModel& camera) {
  cv::Mat bgr = image;
  if (bgr.type() == CV_8UC1) cv::cvtColor(bgr, bgr, cv::COLOR_GRAY2BGR);
  if (bgr.type() == CV_8UC4) cv::cvtColor(bgr, bgr, cv::COLOR_BGRA2BGR);
  if (bgr.depth() == CV_16U) bgr.convertTo(bgr, CV_8U, 1.0 / 257.0);
  if (bgr.type() != CV_8UC3)
    Fail("neural volumes train on 8-bit colour frames, got cv type ", bgr.type());
  if (bgr.cols == camera.width() && bgr.rows == camera.height()) return bgr.clone();
  cv::Mat resized;
  cv::resize(bgr, resized, cv::Size(camera.width(), camera.height()), 0, 0, cv::INTER_AREA);
  return resized;
}

// A bgra8 frame's alpha at the training size as a 0/255 silhouette (covered at least half).
cv::Mat AlphaAtTrainingSize(const cv::Mat& image, const CameraModel& camera) {
  if (image.type() != CV_8UC4)
    Fail("the take's plan takes silhouettes from alpha, but a frame is cv type ", image.type());
  cv::Mat alpha, resized, mask;
  cv::extractChannel(image, alpha, 3);
  if (alpha.cols == camera.width() && alpha.rows == camera.height()) {
    resized = alpha;
  } else {
    cv::resize(alpha, resized, cv::Size(camera.width(), camera.height()), 0, 0, cv::INTER_AREA);
  }
  cv::threshold(resized, mask, 127, 255, cv::THRESH_BINARY);
  return mask;
}

cv::Mat MedianOverFrames(const std::vector<std::vector<cv::Mat>>& images, size_t view) {
  const cv::Mat& first = images.front()[view];
  cv::Mat median(first.size(), CV_8UC3);
  std::vector<uint8_t> values(images.size());
  for (int y = 0; y < first.rows; ++y) {
    for (int x = 0; x < first.cols; ++x) {
      for (int c = 0; c < 3; ++c) {
        for (size_t f = 0; f < images.size(); ++f)
          values[f] = images[f][view].at<cv::Vec3b>(y, x)[c];
        std::nth_element(values.begin(), values.begin() + values.size() / 2, values.end());
        median.at<cv::Vec3b>(y, x)[c] = values[values.size() / 2];
      }
    }
  }
  return median;
}

// The median colour of the image border: a static scene without a clean plate gets a uniform
// background of that colour (Middlebury's black cloth, a backdrop).
cv::Mat BorderColourBackground(const cv::Mat& image) {
  std::vector<uint8_t> channel[3];
  for (int x = 0; x < image.cols; ++x) {
    for (int y : {0, image.rows - 1}) {
      for (int c = 0; c < 3; ++c) channel[c].push_back(image.at<cv::Vec3b>(y, x)[c]);
    }
  }
  for (int y = 0; y < image.rows; ++y) {
    for (int x : {0, image.cols - 1}) {
      for (int c = 0; c < 3; ++c) channel[c].push_back(image.at<cv::Vec3b>(y, x)[c]);
    }
  }
  cv::Vec3b colour;
  for (int c = 0; c < 3; ++c) {
    std::nth_element(channel[c].begin(), channel[c].begin() + channel[c].size() / 2,
                     channel[c].end());
    colour[c] = channel[c][channel[c].size() / 2];
  }
  return cv::Mat(image.size(), CV_8UC3, cv::Scalar(colour[0], colour[1], colour[2]));
}

// The point nearest to every optical axis (least squares) and a box around it reaching halfway
// to the nearest camera: where the rig's views overlap, the region a hull is carved in.
Box RigOverlapBox(const std::vector<CameraModel>& cameras) {
  Eigen::Matrix3d a = Eigen::Matrix3d::Zero();
  Eigen::Vector3d b = Eigen::Vector3d::Zero();
  for (const auto& camera : cameras) {
    const Eigen::Vector3d c = camera.center_in_world();
    const Eigen::Vector3d d = camera.world_from_cam().rotation().col(2);
    const Eigen::Matrix3d p = Eigen::Matrix3d::Identity() - d * d.transpose();
    a += p;
    b += p * c;
  }
  Eigen::Vector3d center = a.ldlt().solve(b);
  if (!center.allFinite()) center.setZero();
  double nearest = std::numeric_limits<double>::infinity();
  for (const auto& camera : cameras)
    nearest = std::min(nearest, (camera.center_in_world() - center).norm());
  Box box;
  box.min = center.array() - 0.6 * nearest;
  box.max = center.array() + 0.6 * nearest;
  return box;
}

}  // namespace

std::vector<int> TrainingData::TrainingViews() const {
  std::vector<int> out;
  for (size_t i = 0; i < views.size(); ++i)
    if (!views[i].heldout) out.push_back(static_cast<int>(i));
  return out;
}

std::vector<int> TrainingData::HeldoutViews() const {
  std::vector<int> out;
  for (size_t i = 0; i < views.size(); ++i)
    if (views[i].heldout) out.push_back(static_cast<int>(i));
  return out;
}

std::vector<int32_t> PixelsSeeingBox(const CameraModel& camera, const Eigen::Vector3f& box_min,
                                     const Eigen::Vector3f& box_max) {
  RayBatch rays = CameraRaysAllPixels(camera, box_min, box_max);
  std::vector<int32_t> pixels;
  for (int64_t i = 0; i < rays.size(); ++i) {
    if (rays.t_far[i] > rays.t_near[i]) pixels.push_back(static_cast<int32_t>(i));
  }
  return pixels;
}

namespace {

// Reads a planned take into training data, one named step at a time.
class TrainingDataLoader {
 public:
  TrainingDataLoader(const fs::path& take_dir, const TrainingDataOptions& options)
      : take_(Take::Open(take_dir)), options_(options), plan_(data_.plan) {}

  TrainingData Load() {
    PlanCameras();
    ReadFrames();
    ReadBackgrounds();
    ReadSilhouettes();
    ChooseBounds();
    MarkOccupancy();
    ChooseEncoderViews();
    return std::move(data_);
  }

 private:
  // The take's plan, the held-out cameras and the training views at the training width.
  void PlanCameras() {
    take_plan_ = PlanTake(take_, options_.take);
    // The background model as reconstruction learns it (or the plan's fall back to Otsu).
    background_model_ = LearnBackgroundModel(take_, take_plan_, SilhouetteOptions{},
                                             ReconstructionOptions{}.min_moving_fraction);
    names_ = take_plan_.color_sensors;
    if (names_.size() < 2) {
      Fail("take ", take_.dir().string(), " has ", names_.size(),
           " colour camera(s); neural volumes need at least 2");
    }
    const std::vector<CameraModel> full_cameras = take_plan_.Cameras(names_);
    data_.sets = take_plan_.sets;
    data_.dynamic = options_.scene == "auto" ? data_.sets.size() > 1 : options_.scene == "dynamic";
    overlap_ = RigOverlapBox(full_cameras);
    rig_center_ = 0.5 * (overlap_.min + overlap_.max);
    std::vector<int> heldout;
    if (!options_.heldout.empty()) {
      heldout = take_plan_.ColorIndices(options_.heldout, "held-out");
    } else {
      // Spread the held-out cameras, starting from the second one so that cam0 (often the
      // reference) keeps training.
      std::vector<int> rotated;
      for (size_t i = 1; i < names_.size(); ++i) rotated.push_back(static_cast<int>(i));
      rotated.push_back(0);
      heldout = SpreadAround(full_cameras, rotated, options_.heldout_cameras, rig_center_);
    }
    if (heldout.size() + 1 > names_.size()) {
      Fail("holding out ", heldout.size(), " of ", names_.size(),
           " cameras leaves none to train on");
    }
    for (size_t i = 0; i < names_.size(); ++i) {
      TrainingView view;
      view.name = names_[i];
      const CameraModel& full = full_cameras[i];
      const double scale = (options_.image_width > 0 && options_.image_width < full.width())
                               ? static_cast<double>(options_.image_width) / full.width()
                               : 1.0;
      view.camera = scale == 1.0 ? full : full.Scaled(scale);
      view.heldout =
          std::find(heldout.begin(), heldout.end(), static_cast<int>(i)) != heldout.end();
      if (view.heldout) take_plan_.heldout.push_back(view.name);
      data_.views.push_back(std::move(view));
    }
    if (!take_plan_.depth_sensors.empty())
      take_plan_.LeaveOut("depth sensors", "Neural Volumes learn from colour alone");
    plan_ = take_plan_.ToJson();
    plan_["scene"] = data_.dynamic ? "dynamic" : "static";
    plan_["training_cameras"] = nlohmann::json::array();
    for (const auto& view : data_.views) {
      if (!view.heldout) plan_["training_cameras"].push_back(view.name);
    }
    plan_["image_size"] = {data_.views.front().camera.width(), data_.views.front().camera.height()};
  }

  void ReadFrames() {
    take_plan_.RequireFrames(take_, names_);
    data_.images.resize(data_.sets.size());
    for (size_t f = 0; f < data_.sets.size(); ++f) {
      FrameSet set = take_.Read(data_.sets[f], names_);
      const bool alpha = take_plan_.silhouettes == SilhouetteSource::kAlpha;
      if (alpha) alpha_masks_.emplace_back();
      for (size_t v = 0; v < names_.size(); ++v) {
        const cv::Mat& image = set.Find(names_[v])->image;
        data_.images[f].push_back(ToTrainingSize(image, data_.views[v].camera));
        if (alpha) alpha_masks_.back().push_back(AlphaAtTrainingSize(image, data_.views[v].camera));
      }
    }
  }

  void ReadBackgrounds() {
    if (take_plan_.has_clean_plate()) {
      FrameSet plate = take_.Read(take_plan_.plate_set(), names_);
      for (size_t v = 0; v < names_.size(); ++v) {
        data_.views[v].background =
            ToTrainingSize(plate.Find(names_[v])->image, data_.views[v].camera);
      }
      plan_["background"] = Cat("clean plate (frame set ", take_plan_.plate_set(), ")");
    } else if (!background_model_.empty()) {
      for (size_t v = 0; v < names_.size(); ++v) {
        data_.views[v].background =
            ToTrainingSize(background_model_.at(names_[v]), data_.views[v].camera);
      }
      plan_["background"] =
          Cat("per-pixel temporal median of each camera's frames over ",
              take_plan_.background_sets.size(), " frame sets of the take (no clean plate)");
    } else if (data_.dynamic && data_.sets.size() >= 3) {
      for (size_t v = 0; v < names_.size(); ++v)
        data_.views[v].background = MedianOverFrames(data_.images, v);
      plan_["background"] = "per-pixel temporal median of each camera's frames (no clean plate)";
    } else {
      for (size_t v = 0; v < names_.size(); ++v)
        data_.views[v].background = BorderColourBackground(data_.images[0][v]);
      plan_["background"] =
          "uniform, the median colour of each image's border (static, no clean plate)";
    }
  }

  bool Subtracted() const { return take_plan_.has_clean_plate() || !background_model_.empty(); }

  // The silhouettes the take plan chose, as reconstruction takes them: alpha, the clean plate
  // or the background model subtracted, else a threshold (Otsu's per image, or the given one)
  // closed by `close_px` (0: none; reconstruction's rule, MeasureClosing).
  cv::Mat SilhouetteOf(size_t f, int v, int close_px) {
    if (!alpha_masks_.empty()) return alpha_masks_[f][v];
    SilhouetteOptions silhouette;
    silhouette.dilate_px = 2;
    silhouette.erode_px = 1;
    if (Subtracted()) {
      silhouette.mode = SilhouetteMode::kBackgroundSubtraction;
      return ExtractSilhouette(data_.images[f][v], data_.views[v].background, silhouette);
    }
    silhouette.open_px = 0;
    silhouette.dilate_px = close_px;
    silhouette.erode_px = close_px;
    silhouette.morphology_width = 0;
    if (take_plan_.silhouettes == SilhouetteSource::kThreshold) {
      silhouette.mode = SilhouetteMode::kThreshold;
      silhouette.threshold = take_plan_.silhouette_threshold;
    } else {
      silhouette.mode = SilhouetteMode::kOtsu;
    }
    return ExtractSilhouette(data_.images[f][v], cv::Mat(), silhouette);
  }

  // Thresholded silhouettes take the closing reconstruction measures (ChooseClosing on the
  // first frame set's unclosed silhouettes of the training views, at the training width, with
  // reconstruction's defaults), not one dataset's recipe; the plan says which and why.
  int MeasureClosing() {
    if (!alpha_masks_.empty() || Subtracted() || data_.sets.empty()) return 0;
    std::vector<cv::Mat> masks;
    for (int v : data_.TrainingViews()) masks.push_back(SilhouetteOf(0, v, 0));
    if (masks.empty()) return 0;
    const ReconstructionOptions defaults;
    const int width = data_.views.front().camera.width();
    const int max_radius =
        std::max(2, static_cast<int>(std::lround(defaults.max_close_px_at_640 * width / 640.0)));
    const ClosingChoice closing = ChooseClosing(masks, max_radius, defaults.min_closing_jump_px);
    plan_["silhouette_morphology"] = {
        {"chosen", closing.close_px > 0 ? Cat("closing ", closing.close_px, " px") : "none"},
        {"why", closing.why}};
    return closing.close_px;
  }

  void ReadSilhouettes() {
    data_.alpha_masks = !alpha_masks_.empty();
    if (!alpha_masks_.empty())
      silhouette_source_ = "the frames' own alpha channel (bgra8)";
    else if (take_plan_.has_clean_plate())
      silhouette_source_ = "background subtraction against the clean plate";
    else
      silhouette_source_ =
          Cat(ToString(take_plan_.silhouettes), " (", take_plan_.silhouette_reason, ")");
    const int close_px = MeasureClosing();
    data_.masks.resize(data_.sets.size());
    for (size_t f = 0; f < data_.sets.size(); ++f) {
      for (size_t v = 0; v < data_.views.size(); ++v)
        data_.masks[f].push_back(SilhouetteOf(f, static_cast<int>(v), close_px));
    }
  }

  // The hull of every frame's training views; false when one frame's is empty.
  bool HullBounds() {
    const std::vector<int> training = data_.TrainingViews();
    HullOptions hull_options;
    hull_options.bounds = overlap_;
    hull_options.voxel_m = (overlap_.max - overlap_.min).maxCoeff() / 96.0;
    // A point must lie in most training views: points only a few cameras can see are where a
    // sparse ring's hull grows its ghost wedges.
    hull_options.min_views = std::max(2, static_cast<int>(std::ceil(0.6 * training.size())));
    hull_options.tolerated_bad_views = training.size() >= 8 ? 1 : 0;
    hull_options.margin_px = 1.0;
    // Views at the training width (a 48 px one shows a person 7 px across): the hull bounds
    // what the silhouettes hold, however few pixels that is; an empty one is refused below.
    hull_options.min_subject_px = 0;
    hull_options.threads = options_.threads;
    for (size_t f = 0; f < data_.sets.size(); ++f) {
      std::vector<View> views;
      for (int v : training) {
        View view;
        view.name = data_.views[v].name;
        view.camera = data_.views[v].camera;
        view.mask = data_.masks[f][v];
        views.push_back(std::move(view));
      }
      HullSummary summary;
      VisualHull hull = ComputeVisualHull(views, hull_options, &summary);
      if (!summary.IsUsable()) return false;
      GrowToHull(hull);
      hulls_.push_back(std::move(hull));
    }
    return (hi_.array() > lo_.array()).all();
  }

  // Grows [lo_, hi_] to the hull's extent, from the blocks it holds.
  void GrowToHull(const VisualHull& hull) {
    for (const auto& block : hull.volume->BlockCoordinates()) {
      const Eigen::Vector3d a = hull.volume->CenterOf(block * kBlockSide);
      const Eigen::Vector3d b =
          hull.volume->CenterOf(block * kBlockSide + Eigen::Vector3i::Constant(kBlockSide - 1));
      for (int i = 0; i < kBlockSide; ++i) {
        for (int j = 0; j < kBlockSide; ++j) {
          for (int k = 0; k < kBlockSide; ++k) {
            const Eigen::Vector3d p =
                a + (b - a).cwiseProduct(Eigen::Vector3d(i, j, k) / (kBlockSide - 1));
            if (!hull.Contains(p)) continue;
            lo_ = lo_.cwiseMin(p);
            hi_ = hi_.cwiseMax(p);
          }
        }
      }
    }
    for (uint64_t key : hull.inside_blocks) {
      const Eigen::Vector3i block = SparseVolume::Unkey(key);
      lo_ = lo_.cwiseMin(hull.volume->CenterOf(block * kBlockSide));
      hi_ = hi_.cwiseMax(
          hull.volume->CenterOf(block * kBlockSide + Eigen::Vector3i::Constant(kBlockSide - 1)));
    }
  }

  bool GroundTruthBounds() {
    lo_.setConstant(std::numeric_limits<double>::infinity());
    hi_ = -lo_;
    for (int64_t set : data_.sets) {
      fs::path file = take_.gt_dir() / "meshes" / SetFileName(set, ".ply");
      if (!fs::exists(file)) file = take_.gt_dir() / "meshes" / "000000.ply";
      if (!fs::exists(file)) continue;
      for (const auto& v : ReadPly(file).vertices) {
        lo_ = lo_.cwiseMin(v.cast<double>());
        hi_ = hi_.cwiseMax(v.cast<double>());
      }
    }
    return (hi_.array() > lo_.array()).all();
  }

  // The hull of every frame, else the take plan's bounds; the ground-truth meshes only when asked
  // for (--bounds gt): the truth never stands in by itself.
  void ChooseBounds() {
    VolumeBoundsSource source = options_.bounds;
    lo_ = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
    hi_ = -lo_;
    if (source == VolumeBoundsSource::kAuto || source == VolumeBoundsSource::kHull) {
      if (HullBounds()) {
        source = VolumeBoundsSource::kHull;
        plan_["silhouettes"] = silhouette_source_;
      } else {
        if (options_.bounds == VolumeBoundsSource::kHull)
          Fail("the visual hull of the training views is empty: no volume to bound");
        hulls_.clear();
        source = VolumeBoundsSource::kStage;
      }
    }
    if (source == VolumeBoundsSource::kGroundTruth && !GroundTruthBounds())
      Fail("take ", take_.dir().string(), " has no gt/meshes to bound the volume");
    if (source == VolumeBoundsSource::kStage) {
      // The take plan's scene bounds: the user's, else the rig's own (never a fixed studio).
      lo_ = take_plan_.bounds.min;
      hi_ = take_plan_.bounds.max;
      plan_["bounds_plan"] = take_plan_.bounds_source;
    }
    data_.box.min = lo_.array() - options_.bounds_margin_m;
    data_.box.max = hi_.array() + options_.bounds_margin_m;
    plan_["bounds"] = {{"source", ToString(source)},
                       {"box_min", {data_.box.min.x(), data_.box.min.y(), data_.box.min.z()}},
                       {"box_max", {data_.box.max.x(), data_.box.max.y(), data_.box.max.z()}}};
  }

  // Occupancy for skipping: cells the hull reaches (grown by one cell), per frame.
  void MarkOccupancy() {
    data_.occupancy.assign(data_.sets.size(), OccupancyGrid{});
    if (hulls_.empty() || options_.occupancy_cells <= 0) {
      plan_["occupancy"] = {{"source", "none (no hull): every sample is evaluated"}};
      return;
    }
    const int n = options_.occupancy_cells;
    const Eigen::Vector3d cell = (data_.box.max - data_.box.min) / n;
    const double tolerance = 0.5 * cell.norm();
    double occupied_fraction = 0;
    for (size_t f = 0; f < hulls_.size(); ++f) {
      OccupancyGrid& grid = data_.occupancy[f];
      grid.size = n;
      grid.occupied.assign(static_cast<int64_t>(n) * n * n, 0);
      for (int z = 0; z < n; ++z) {
        for (int y = 0; y < n; ++y) {
          for (int x = 0; x < n; ++x) {
            const Eigen::Vector3d center =
                data_.box.min + cell.cwiseProduct(Eigen::Vector3d(x + 0.5, y + 0.5, z + 0.5));
            grid.occupied[(static_cast<int64_t>(z) * n + y) * n + x] =
                hulls_[f].Contains(center, tolerance);
          }
        }
      }
      grid.Dilate(1);
      occupied_fraction += static_cast<double>(grid.OccupiedCount()) / grid.occupied.size();
    }
    plan_["occupancy"] = {{"source", "visual hull per frame, grown by one cell"},
                          {"cells", n},
                          {"occupied_fraction", occupied_fraction / hulls_.size()}};
  }

  void ChooseEncoderViews() {
    if (!data_.dynamic) return;
    std::vector<CameraModel> cameras;
    for (const auto& view : data_.views) cameras.push_back(view.camera);
    data_.encoder_views =
        SpreadAround(cameras, data_.TrainingViews(), options_.encoder_views, rig_center_);
    plan_["encoder_views"] = nlohmann::json::array();
    for (int v : data_.encoder_views) plan_["encoder_views"].push_back(data_.views[v].name);
  }

  const Take take_;
  const TrainingDataOptions& options_;
  TrainingData data_;
  nlohmann::json& plan_;
  TakePlan take_plan_;
  std::vector<std::string> names_;
  Box overlap_;
  Eigen::Vector3d rig_center_ = Eigen::Vector3d::Zero();
  std::string silhouette_source_;
  std::map<std::string, cv::Mat> background_model_;  // full size, BGR; empty: none
  std::vector<std::vector<cv::Mat>> alpha_masks_;    // [frame][view] when the plan reads alpha
  std::vector<VisualHull> hulls_;
  Eigen::Vector3d lo_, hi_;
};

}  // namespace

const char* ToString(VolumeBoundsSource source) {
  switch (source) {
    case VolumeBoundsSource::kAuto:
      return "auto";
    case VolumeBoundsSource::kHull:
      return "hull";
    case VolumeBoundsSource::kGroundTruth:
      return "gt";
    case VolumeBoundsSource::kStage:
      return "stage";
  }
  return "?";
}

VolumeBoundsSource VolumeBoundsSourceFromString(const std::string& text) {
  for (auto source : {VolumeBoundsSource::kAuto, VolumeBoundsSource::kHull,
                      VolumeBoundsSource::kGroundTruth, VolumeBoundsSource::kStage}) {
    if (text == ToString(source)) return source;
  }
  Fail("unknown volume bounds source '", text, "' (auto, hull, gt, stage)");
}

void TrainingDataOptions::Check() const {
  if (image_width < 0) Fail("image_width must be >= 0 (0: native), got ", image_width);
  if (heldout_cameras < 0) Fail("heldout_cameras must be >= 0, got ", heldout_cameras);
  take.Check();
  if (scene != "auto" && scene != "static" && scene != "dynamic")
    Fail("scene must be auto, static or dynamic, got '", scene, "'");
  if (encoder_views < 1) Fail("encoder_views must be at least 1, got ", encoder_views);
  if (!(bounds_margin_m >= 0)) Fail("bounds_margin_m must be >= 0, got ", bounds_margin_m);
  if (occupancy_cells < 0) Fail("occupancy_cells must be >= 0, got ", occupancy_cells);
  if (threads < 0) Fail("threads must be >= 0, got ", threads);
}

TrainingData LoadTrainingData(const fs::path& take_dir, const TrainingDataOptions& options) {
  options.Check();
  return TrainingDataLoader(take_dir, options).Load();
}

}  // namespace holocap
