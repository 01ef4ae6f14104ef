#include "neural/data.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <opencv2/imgproc.hpp>

#include "core/error.h"
#include "core/image.h"
#include "core/mesh.h"
#include "core/take.h"
#include "reconstruction/reconstruction.h"

namespace holocap::neural {
namespace {

namespace fs = std::filesystem;

// gt/ names files by frame set, six digits.
std::string SetFileName(int64_t set, const char* extension) {
  char name[32];
  std::snprintf(name, sizeof(name), "%06lld%s", static_cast<long long>(set), extension);
  return name;
}

cv::Mat ToTrainingSize(const cv::Mat& image, const CameraModel& camera) {
  cv::Mat bgr = image;
  if (bgr.type() == CV_8UC1) cv::cvtColor(bgr, bgr, cv::COLOR_GRAY2BGR);
  if (bgr.depth() == CV_16U) bgr.convertTo(bgr, CV_8U, 1.0 / 257.0);
  if (bgr.type() != CV_8UC3) Fail("neural volumes train on 8-bit colour frames, got cv type ", bgr.type());
  if (bgr.cols == camera.width() && bgr.rows == camera.height()) return bgr.clone();
  cv::Mat resized;
  cv::resize(bgr, resized, cv::Size(camera.width(), camera.height()), 0, 0, cv::INTER_AREA);
  return resized;
}

cv::Mat MedianOverFrames(const std::vector<std::vector<cv::Mat>>& images, size_t view) {
  const cv::Mat& first = images.front()[view];
  cv::Mat median(first.size(), CV_8UC3);
  std::vector<uint8_t> values(images.size());
  for (int y = 0; y < first.rows; ++y) {
    for (int x = 0; x < first.cols; ++x) {
      for (int c = 0; c < 3; ++c) {
        for (size_t f = 0; f < images.size(); ++f) values[f] = images[f][view].at<cv::Vec3b>(y, x)[c];
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
    std::nth_element(channel[c].begin(), channel[c].begin() + channel[c].size() / 2, channel[c].end());
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
  for (const auto& camera : cameras) nearest = std::min(nearest, (camera.center_in_world() - center).norm());
  Box box;
  box.min = center.array() - 0.6 * nearest;
  box.max = center.array() + 0.6 * nearest;
  return box;
}

}  // namespace

std::vector<int> TrainingData::TrainingViews() const {
  std::vector<int> out;
  for (size_t i = 0; i < views.size(); ++i) if (!views[i].heldout) out.push_back(static_cast<int>(i));
  return out;
}

std::vector<int> TrainingData::HeldoutViews() const {
  std::vector<int> out;
  for (size_t i = 0; i < views.size(); ++i) if (views[i].heldout) out.push_back(static_cast<int>(i));
  return out;
}

std::vector<int> SpreadAround(const std::vector<CameraModel>& cameras,
                              const std::vector<int>& candidates, int count,
                              const Eigen::Vector3d& center) {
  // Farthest-point sampling of the viewing directions seen from `center`: works whatever the
  // world's up axis (Middlebury's is not z).
  std::vector<int> picked;
  if (count <= 0 || candidates.empty()) return picked;
  auto direction = [&](int i) { return (cameras[i].center_in_world() - center).normalized(); };
  picked.push_back(candidates.front());
  while (static_cast<int>(picked.size()) < std::min<int>(count, candidates.size())) {
    int best = -1;
    double best_distance = -1;
    for (int c : candidates) {
      if (std::find(picked.begin(), picked.end(), c) != picked.end()) continue;
      double nearest = std::numeric_limits<double>::infinity();
      for (int p : picked) nearest = std::min(nearest, (direction(c) - direction(p)).norm());
      if (nearest > best_distance) {
        best_distance = nearest;
        best = c;
      }
    }
    picked.push_back(best);
  }
  std::sort(picked.begin(), picked.end());
  return picked;
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

TrainingData LoadTrainingData(const fs::path& take_dir, const NeuralVolumeOptions& options) {
  options.Check();
  Take take = Take::Open(take_dir);
  TrainingData data;
  nlohmann::json& plan = data.plan;

  bool ground_truth = options.ground_truth_cameras;
  if (!ground_truth && !take.has_calibration()) {
    if (!take.has_ground_truth() || !fs::is_directory(take.gt_dir() / "cameras")) {
      Fail("take ", take_dir.string(), " has no calib/ camera models (calibrate it first) and no gt/cameras");
    }
    ground_truth = true;
  }
  plan["cameras"] = ground_truth ? "gt/cameras (true models: the take is not calibrated)"
                                 : "calib/ (calibrated models)";

  std::vector<std::string> names;
  for (const auto& stream : take.streams()) {
    if (stream.role == SensorRole::kColor) names.push_back(stream.name);
  }
  if (names.size() < 2) Fail("take ", take_dir.string(), " has ", names.size(), " colour camera(s); neural volumes need at least 2");

  std::vector<CameraModel> full_cameras;
  for (const auto& name : names) full_cameras.push_back(take.Camera(name, ground_truth));

  // Frame sets.
  int64_t clean_plate = options.clean_plate_frames;
  if (clean_plate < 0) clean_plate = take.metadata().value("clean_plate_frames", int64_t{0});
  const int64_t available = static_cast<int64_t>(take.size()) - clean_plate;
  if (available <= 0) Fail("take ", take_dir.string(), " has no frame set after its ", clean_plate, " clean-plate set(s)");
  const int64_t first = std::min(options.first_frame, available - 1);
  const int64_t last = options.last_frame < 0 ? available : std::min(options.last_frame, available);
  if (last <= first) Fail("frame range [", options.first_frame, ", ", options.last_frame, ") selects no frame set of ", available);
  for (int64_t f = first; f < last; ++f) data.sets.push_back(clean_plate + f);
  if (options.scene == "auto") data.dynamic = data.sets.size() > 1;
  else data.dynamic = options.scene == "dynamic";
  plan["frames"] = data.sets.size();
  plan["clean_plate_frames"] = clean_plate;
  plan["scene"] = data.dynamic ? "dynamic" : "static";

  // Held-out cameras.
  std::vector<int> all(names.size());
  for (size_t i = 0; i < all.size(); ++i) all[i] = static_cast<int>(i);
  const Box overlap = RigOverlapBox(full_cameras);
  const Eigen::Vector3d rig_center = 0.5 * (overlap.min + overlap.max);
  std::vector<int> heldout;
  if (!options.heldout.empty()) {
    for (const auto& name : options.heldout) {
      auto it = std::find(names.begin(), names.end(), name);
      if (it == names.end()) Fail("held-out camera '", name, "' is not a colour sensor of the take");
      heldout.push_back(static_cast<int>(it - names.begin()));
    }
  } else {
    // Spread the held-out cameras, starting from the second one so that cam0 (often the
    // reference) keeps training.
    std::vector<int> rotated(all.begin() + 1, all.end());
    rotated.push_back(all.front());
    heldout = SpreadAround(full_cameras, rotated, options.heldout_cameras, rig_center);
  }
  if (heldout.size() + 1 > names.size()) Fail("holding out ", heldout.size(), " of ", names.size(), " cameras leaves none to train on");

  for (size_t i = 0; i < names.size(); ++i) {
    TrainingView view;
    view.name = names[i];
    const CameraModel& full = full_cameras[i];
    const double scale = (options.image_width > 0 && options.image_width < full.width())
                             ? static_cast<double>(options.image_width) / full.width() : 1.0;
    view.camera = scale == 1.0 ? full : full.Scaled(scale);
    view.heldout = std::find(heldout.begin(), heldout.end(), static_cast<int>(i)) != heldout.end();
    data.views.push_back(std::move(view));
  }
  plan["heldout_cameras"] = nlohmann::json::array();
  plan["training_cameras"] = nlohmann::json::array();
  for (const auto& view : data.views) plan[view.heldout ? "heldout_cameras" : "training_cameras"].push_back(view.name);
  plan["image_size"] = {data.views.front().camera.width(), data.views.front().camera.height()};

  data.images.resize(data.sets.size());
  for (size_t f = 0; f < data.sets.size(); ++f) {
    FrameSet set = take.Read(data.sets[f], names);
    for (size_t v = 0; v < names.size(); ++v) {
      const Frame* frame = set.Find(names[v]);
      if (frame == nullptr) Fail("frame set ", data.sets[f], " lacks camera ", names[v]);
      data.images[f].push_back(ToTrainingSize(frame->image, data.views[v].camera));
    }
  }

  // Backgrounds.
  if (clean_plate > 0) {
    FrameSet plate = take.Read(0, names);
    for (size_t v = 0; v < names.size(); ++v) {
      const Frame* frame = plate.Find(names[v]);
      if (frame == nullptr) Fail("the clean plate lacks camera ", names[v]);
      data.views[v].background = ToTrainingSize(frame->image, data.views[v].camera);
    }
    plan["background"] = "clean plate (frame set 0)";
  } else if (data.dynamic && data.sets.size() >= 3) {
    for (size_t v = 0; v < names.size(); ++v) data.views[v].background = MedianOverFrames(data.images, v);
    plan["background"] = "per-pixel temporal median of each camera's frames (no clean plate)";
  } else {
    for (size_t v = 0; v < names.size(); ++v) data.views[v].background = BorderColourBackground(data.images[0][v]);
    plan["background"] = "uniform, the median colour of each image's border (static, no clean plate)";
  }

  // Silhouettes of the training views, for the hull.
  const std::vector<int> training = data.TrainingViews();
  std::string silhouette_source;
  SilhouetteOptions silhouette;
  silhouette.dilate_px = 2;
  silhouette.erode_px = 1;
  auto mask_of = [&](size_t f, int v) -> cv::Mat {
    const auto& camera = data.views[v].camera;
    if (clean_plate > 0) {
      silhouette.mode = SilhouetteMode::kBackgroundSubtraction;
      return ExtractSilhouette(data.images[f][v], data.views[v].background, silhouette);
    }
    fs::path gt_mask = take.gt_dir() / "masks" / data.views[v].name / SetFileName(data.sets[f], ".png");
    if (fs::exists(gt_mask)) {
      cv::Mat mask = ReadImage(gt_mask), resized;
      cv::resize(mask, resized, cv::Size(camera.width(), camera.height()), 0, 0, cv::INTER_NEAREST);
      return resized;
    }
    silhouette.mode = SilhouetteMode::kThreshold;
    return ExtractSilhouette(data.images[f][v], cv::Mat(), silhouette);
  };
  if (clean_plate > 0) silhouette_source = "background subtraction against the clean plate";
  else if (fs::is_directory(take.gt_dir() / "masks")) silhouette_source = "gt/masks (no clean plate)";
  else silhouette_source = "threshold on a dark background (no clean plate)";

  data.masks.resize(data.sets.size());
  for (size_t f = 0; f < data.sets.size(); ++f) {
    for (size_t v = 0; v < data.views.size(); ++v) data.masks[f].push_back(mask_of(f, static_cast<int>(v)));
  }

  // Bounds: the hull of every frame, else the ground-truth meshes, else the stage.
  VolumeBoundsSource source = options.bounds;
  std::vector<VisualHull> hulls;
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
  Eigen::Vector3d hi = -lo;
  if (source == VolumeBoundsSource::kAuto || source == VolumeBoundsSource::kHull) {
    HullOptions hull_options;
    hull_options.bounds = overlap;
    hull_options.voxel_m = (overlap.max - overlap.min).maxCoeff() / 96.0;
    // A point must lie in most training views: points only a few cameras can see are where a
    // sparse ring's hull grows its ghost wedges.
    hull_options.min_views = std::max(2, static_cast<int>(std::ceil(0.6 * training.size())));
    hull_options.tolerated_bad_views = training.size() >= 8 ? 1 : 0;
    hull_options.margin_px = 1.0;
    hull_options.threads = options.threads;
    bool ok = true;
    for (size_t f = 0; f < data.sets.size() && ok; ++f) {
      std::vector<View> views;
      for (int v : training) {
        View view;
        view.name = data.views[v].name;
        view.camera = data.views[v].camera;
        view.mask = data.masks[f][v];
        views.push_back(std::move(view));
      }
      HullSummary summary;
      VisualHull hull = ComputeVisualHull(views, hull_options, &summary);
      if (!IsUsable(summary.termination)) {
        ok = false;
        break;
      }
      // The hull's extent, from the blocks it holds.
      for (const auto& block : hull.volume->BlockCoordinates()) {
        const Eigen::Vector3d a = hull.volume->CenterOf(block * kBlockSide);
        const Eigen::Vector3d b = hull.volume->CenterOf(block * kBlockSide + Eigen::Vector3i::Constant(kBlockSide - 1));
        for (int i = 0; i < kBlockSide; ++i) {
          for (int j = 0; j < kBlockSide; ++j) {
            for (int k = 0; k < kBlockSide; ++k) {
              const Eigen::Vector3d p = a + (b - a).cwiseProduct(Eigen::Vector3d(i, j, k) / (kBlockSide - 1));
              if (!hull.Contains(p)) continue;
              lo = lo.cwiseMin(p);
              hi = hi.cwiseMax(p);
            }
          }
        }
      }
      for (uint64_t key : hull.inside_blocks) {
        const Eigen::Vector3i block = SparseVolume::Unkey(key);
        lo = lo.cwiseMin(hull.volume->CenterOf(block * kBlockSide));
        hi = hi.cwiseMax(hull.volume->CenterOf(block * kBlockSide + Eigen::Vector3i::Constant(kBlockSide - 1)));
      }
      hulls.push_back(std::move(hull));
    }
    if (ok && (hi.array() > lo.array()).all()) {
      source = VolumeBoundsSource::kHull;
      plan["silhouettes"] = silhouette_source;
    } else {
      if (options.bounds == VolumeBoundsSource::kHull) Fail("the visual hull of the training views is empty: no volume to bound");
      hulls.clear();
      source = VolumeBoundsSource::kGroundTruth;
    }
  }
  if (source == VolumeBoundsSource::kGroundTruth) {
    lo.setConstant(std::numeric_limits<double>::infinity());
    hi = -lo;
    for (int64_t set : data.sets) {
      fs::path file = take.gt_dir() / "meshes" / SetFileName(set, ".ply");
      if (!fs::exists(file)) file = take.gt_dir() / "meshes" / "000000.ply";
      if (!fs::exists(file)) continue;
      for (const auto& v : ReadPly(file).vertices) {
        lo = lo.cwiseMin(v.cast<double>());
        hi = hi.cwiseMax(v.cast<double>());
      }
    }
    if (!(hi.array() > lo.array()).all()) {
      if (options.bounds == VolumeBoundsSource::kGroundTruth) Fail("take ", take_dir.string(), " has no gt/meshes to bound the volume");
      source = VolumeBoundsSource::kStage;
    }
  }
  if (source == VolumeBoundsSource::kStage) {
    const Box stage;
    lo = stage.min;
    hi = stage.max;
  }
  data.box_min = lo.array() - options.bounds_margin_m;
  data.box_max = hi.array() + options.bounds_margin_m;
  plan["bounds"] = {{"source", ToString(source)},
                    {"box_min", {data.box_min.x(), data.box_min.y(), data.box_min.z()}},
                    {"box_max", {data.box_max.x(), data.box_max.y(), data.box_max.z()}}};

  // Occupancy for skipping: cells the hull reaches (grown by one cell), per frame.
  data.occupancy.assign(data.sets.size(), OccupancyGrid{});
  if (!hulls.empty() && options.occupancy_cells > 0) {
    const int n = options.occupancy_cells;
    const Eigen::Vector3d cell = (data.box_max - data.box_min) / n;
    const double tolerance = 0.5 * cell.norm();
    double occupied_fraction = 0;
    for (size_t f = 0; f < hulls.size(); ++f) {
      OccupancyGrid& grid = data.occupancy[f];
      grid.size = n;
      grid.occupied.assign(static_cast<int64_t>(n) * n * n, 0);
      for (int z = 0; z < n; ++z) {
        for (int y = 0; y < n; ++y) {
          for (int x = 0; x < n; ++x) {
            const Eigen::Vector3d center = data.box_min + cell.cwiseProduct(Eigen::Vector3d(x + 0.5, y + 0.5, z + 0.5));
            grid.occupied[(static_cast<int64_t>(z) * n + y) * n + x] = hulls[f].Contains(center, tolerance);
          }
        }
      }
      grid.Dilate(1);
      occupied_fraction += static_cast<double>(grid.OccupiedCount()) / grid.occupied.size();
    }
    plan["occupancy"] = {{"source", "visual hull per frame, grown by one cell"},
                         {"cells", n},
                         {"occupied_fraction", occupied_fraction / hulls.size()}};
  } else {
    plan["occupancy"] = {{"source", "none (no hull): every sample is evaluated"}};
  }

  if (data.dynamic) {
    std::vector<CameraModel> cameras;
    for (const auto& view : data.views) cameras.push_back(view.camera);
    data.encoder_views = SpreadAround(cameras, training, options.encoder_views, rig_center);
    plan["encoder_views"] = nlohmann::json::array();
    for (int v : data.encoder_views) plan["encoder_views"].push_back(data.views[v].name);
  }
  return data;
}

}  // namespace holocap::neural
