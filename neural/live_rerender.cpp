// Live-rerender pairs from a scan take, and applying a trained model to `holocap live`'s
// compositions. No LibTorch here (the trainer is live_rerender_train.cpp).
#include <algorithm>
#include <cmath>
#include <map>
#include <opencv2/imgproc.hpp>
#include <random>

#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/image.h"
#include "core/progress.h"
#include "core/take.h"
#include "core/take_plan.h"
#include "neural/internal/live_rerender.h"

namespace holocap {

namespace fs = std::filesystem;
using Json = nlohmann::json;

void LiveRerenderOptions::Check() const {
  net.Check();
  live.Check();
  MeshRasterOptions{.supersample = supersample}.Check();
  HOLOCAP_CHECK_OPTION_IN(live_frames, 4, 1000);
  HOLOCAP_CHECK_OPTION_IN(targets_per_frame, 1, 100);
  HOLOCAP_CHECK_OPTION_GE(min_turn_deg, 0);
  HOLOCAP_CHECK_OPTION_LE(min_turn_deg, max_turn_deg);
  HOLOCAP_CHECK_OPTION_LE(max_turn_deg, 180);
  HOLOCAP_CHECK_OPTION_IN(jitter_m, 0, 0.5);
  HOLOCAP_CHECK_OPTION_IN(jitter_deg, 0, 45);
  HOLOCAP_CHECK_OPTION_GE(validation_every, 2);
  HOLOCAP_CHECK_OPTION(image_width == 0 || image_width >= 32, image_width,
                       "0: native, else at least 32 px");
  HOLOCAP_CHECK_OPTION(std::isfinite(minutes), minutes, "a budget must end");
  HOLOCAP_CHECK_OPTION(minutes > 0 || iterations > 0, minutes,
                       "give a positive time budget (minutes) or an iteration count");
  HOLOCAP_CHECK_OPTION_GE(iterations, 0);
  HOLOCAP_CHECK_OPTION_IN(batch, 1, 64);
  HOLOCAP_CHECK_OPTION(crop_px == 0 || crop_px >= 16, crop_px, "0: whole images, else at least 16");
  HOLOCAP_CHECK_OPTION_GT(learning_rate, 0);
  HOLOCAP_CHECK_OPTION_LT(learning_rate, 1);
  HOLOCAP_CHECK_OPTION_IN(subject_weight, 1, 100);
  HOLOCAP_CHECK_OPTION_IN(alpha_weight, 0, 100);
  HOLOCAP_CHECK_OPTION_GE(eval_every, 1, "iterations");
  HOLOCAP_CHECK_OPTION_GE(threads, 0, "0: all cores");
}

Json LiveRerenderOptions::ToJson() const {
  return {{"net", net.ToJson()},
          {"live", live.ToJson()},
          {"ground_truth_cameras", ground_truth_cameras},
          {"live_frames", live_frames},
          {"targets_per_frame", targets_per_frame},
          {"min_turn_deg", min_turn_deg},
          {"max_turn_deg", max_turn_deg},
          {"validation_every", validation_every},
          {"jitter_m", jitter_m},
          {"jitter_deg", jitter_deg},
          {"image_width", image_width},
          {"supersample", supersample},
          {"minutes", minutes},
          {"iterations", iterations},
          {"batch", batch},
          {"crop_px", crop_px},
          {"learning_rate", learning_rate},
          {"subject_weight", subject_weight},
          {"alpha_weight", alpha_weight},
          {"eval_every", eval_every},
          {"seed", seed},
          {"threads", threads}};
}

GBuffer LiveRerenderBuffers(const Mesh& composed, const CameraModel& camera,
                            const MeshRasterOptions& raster) {
  GBuffer buffers = RasteriseMesh(composed, camera, raster);
  buffers.position = cv::Mat();
  buffers.normal.setTo(cv::Scalar::all(0));
  return buffers;
}

namespace neural {
namespace {

// The scan's poses of the depth sensor (world_from_cam, the scan's frame) by frame set, for the
// frames it fused.
std::map<int64_t, Pose> ScanPoses(const fs::path& scan_dir) {
  const fs::path file = scan_dir / "trajectory.json";
  if (!fs::is_regular_file(file))
    Fail("live rerender: scan '", scan_dir.string(),
         "' holds no trajectory.json (a `holocap scan` output)");
  std::map<int64_t, Pose> poses;
  try {
    for (const Json& frame : Json::parse(ReadFileToString(file))) {
      if (!frame.at("fused").get<bool>()) continue;
      poses[frame.at("set").get<int64_t>()] =
          PoseFromRt(frame.at("cam_from_world").get<Rt>()).inverse();
    }
  } catch (const Json::exception& e) {
    Fail("live rerender: ", file.string(), " is damaged: ", e.what());
  }
  return poses;
}

// A colour frame as 8-bit BGR (what the compositor colours from).
cv::Mat Bgr8(const cv::Mat& frame) {
  cv::Mat bgr = frame;
  if (bgr.channels() == 1) cv::cvtColor(bgr, bgr, cv::COLOR_GRAY2BGR);
  if (bgr.channels() == 4) cv::cvtColor(bgr, bgr, cv::COLOR_BGRA2BGR);
  if (bgr.depth() == CV_16U) bgr.convertTo(bgr, CV_8U, 1.0 / 257);
  return bgr;
}

// ... and as float BGR in [0, 1] at `size` (area-averaged).
cv::Mat FloatBgr(const cv::Mat& bgr8, const cv::Size& size) {
  cv::Mat scaled = bgr8;
  if (bgr8.size() != size) cv::resize(bgr8, scaled, size, 0, 0, cv::INTER_AREA);
  cv::Mat out;
  scaled.convertTo(out, CV_32FC3, 1.0 / 255);
  return out;
}

// One frame of the scan take composed as the live frame.
struct ComposedFrame {
  int64_t set = 0;
  Pose world_from_depth = Pose::Identity();
  CameraModel camera;  // the colour camera at this frame, training resolution
  Mesh composed;
  cv::Mat target, silhouette;
};

// The subject's turn between two frames: the angle of the sensor's rotation relative to it.
double TurnDeg(const ComposedFrame& a, const ComposedFrame& b) {
  const Eigen::Matrix3d relative =
      a.world_from_depth.rotation().transpose() * b.world_from_depth.rotation();
  return Eigen::AngleAxisd(relative).angle() * 180 / M_PI;
}

// `mesh` moved by a random rigid motion about its centroid (LiveRerenderOptions::jitter_m).
Mesh Jittered(const Mesh& mesh, double jitter_m, double jitter_deg, std::mt19937_64& rng) {
  if (mesh.vertices.empty() || (jitter_m == 0 && jitter_deg == 0)) return mesh;
  std::normal_distribution<double> normal(0, 1);
  Eigen::Vector3d axis(normal(rng), normal(rng), normal(rng));
  axis = axis.norm() > 1e-9 ? axis.normalized() : Eigen::Vector3d::UnitZ();
  const Eigen::Matrix3f turn = Eigen::AngleAxisd(jitter_deg * normal(rng) * M_PI / 180, axis)
                                   .toRotationMatrix()
                                   .cast<float>();
  const Eigen::Vector3f shift =
      (jitter_m * Eigen::Vector3d(normal(rng), normal(rng), normal(rng))).cast<float>();
  Eigen::Vector3f centre = Eigen::Vector3f::Zero();
  for (const Eigen::Vector3f& v : mesh.vertices)
    centre += v / static_cast<float>(mesh.vertices.size());
  Mesh moved = mesh;
  for (Eigen::Vector3f& v : moved.vertices) v = turn * (v - centre) + centre + shift;
  for (Eigen::Vector3f& n : moved.normals) n = turn * n;
  return moved;
}

// The scan take's sensors, poses and compositions.
class PairBuilder {
 public:
  PairBuilder(const fs::path& scan_take, const fs::path& scan_dir,
              const LiveRerenderOptions& options)
      : take_(Take::Open(scan_take)),
        scan_(ReadScan(scan_dir)),
        albedo_(ReadScanAlbedo(scan_dir, scan_)),
        poses_(ScanPoses(scan_dir)),
        options_(options) {
    raster_.supersample = options.supersample;
    raster_.threads = options.threads;
  }

  LivePairs Run() {
    PlanSensors();
    Compose();
    Pair();
    return std::move(pairs_);
  }

 private:
  void PlanSensors() {
    TakeSelection selection;
    selection.ground_truth_cameras = options_.ground_truth_cameras;
    plan_ = PlanTake(take_, selection);
    if (plan_.depth_sensors.size() != 1) {
      Fail("live rerender: scan take '", take_.dir().string(), "' has ", plan_.depth_sensors.size(),
           " depth sensors; it needs exactly one (the scan's)");
    }
    depth_name_ = plan_.depth_sensors.front();
    color_name_ = take_.stream(depth_name_).paired_with;
    if (color_name_.empty() || !plan_.cameras.count(color_name_)) {
      Fail("live rerender: depth sensor '", depth_name_, "' of '", take_.dir().string(),
           "' has no paired colour camera with a model");
    }
    const CameraModel& color = plan_.cameras.at(color_name_);
    color_from_depth_ = color.cam_from_world() * plan_.cameras.at(depth_name_).world_from_cam();
    const double scale =
        options_.image_width > 0 ? static_cast<double>(options_.image_width) / color.width() : 1.0;
    color_camera_ = scale == 1.0 ? color : color.Scaled(scale);
    pairs_.plan = {{"depth_sensor", depth_name_},
                   {"color_sensor", color_name_},
                   {"resolution", Cat(color_camera_.width(), "x", color_camera_.height())},
                   {"left_out", "world positions (the live subject walks; the scan's stood)"}};
  }

  // live_frames of the fused frames, spread over the take, composed with the scan.
  void Compose() {
    std::vector<int64_t> fused;
    for (int64_t set : plan_.sets)
      if (poses_.count(set)) fused.push_back(set);
    if (fused.size() < 2)
      Fail("live rerender: the scan fused ", fused.size(), " frames of '", take_.dir().string(),
           "' (is it this take's scan?)");
    const size_t count = std::min<size_t>(options_.live_frames, fused.size());
    LiveCompositor compositor(scan_, options_.live, plan_.up,
                              plan_.floor_m + plan_.floor_tolerance_m, albedo_);
    Progress progress("live rerender: compose", static_cast<int64_t>(count));
    for (size_t k = 0; k < count; ++k) {
      ComposedFrame frame;
      frame.set = fused[k * fused.size() / count];
      frame.world_from_depth = poses_.at(frame.set);
      CameraModel depth_camera = plan_.cameras.at(depth_name_);
      depth_camera.set_cam_from_world(frame.world_from_depth.inverse());
      CameraModel color_camera = plan_.cameras.at(color_name_);
      color_camera.set_cam_from_world(color_from_depth_ * frame.world_from_depth.inverse());
      const size_t set = static_cast<size_t>(frame.set);
      const cv::Mat color = Bgr8(take_.ReadFrame(set, color_name_));
      LiveResult result = compositor.Process(frame.set, take_.ReadFrame(set, depth_name_),
                                             depth_camera, color, color_camera);
      progress.Increment(ToString(result.frame.state));
      if (result.frame.state != LiveState::kComposed) {
        ++pairs_.refused;
        continue;
      }
      frame.camera = color_camera_;
      frame.camera.set_cam_from_world(color_from_depth_ * frame.world_from_depth.inverse());
      frame.composed = std::move(result.composed);
      const GBuffer own = RasteriseMesh(frame.composed, frame.camera, raster_);
      frame.silhouette = own.mask >= 128;
      const cv::Mat image = FloatBgr(color, own.mask.size());
      frame.target = cv::Mat(image.size(), CV_32FC3, cv::Scalar::all(0));
      image.copyTo(frame.target, frame.silhouette);
      frames_.push_back(std::move(frame));
    }
    progress.Finish();
    pairs_.composed = static_cast<int64_t>(frames_.size());
  }

  // The composition of `live` in the light of `target`'s frame. The sensor stands still in the
  // room while the subject turns, so in the scan's world the light turns with the sensor: each
  // vertex's colour (the live frame's light on it) times the ratio of its shading in the
  // target's sensor frame to its shading in the live frame's. Without a light, as it is.
  Mesh InTargetLight(const ComposedFrame& live, const ComposedFrame& target) const {
    if (!albedo_ || !options_.live.relight) return live.composed;
    Mesh lit = live.composed;
    if (lit.normals.size() != lit.vertices.size()) lit.ComputeNormals();
    const Eigen::Matrix3d from = live.world_from_depth.linear().transpose();
    const Eigen::Matrix3d to = target.world_from_depth.linear().transpose();
    for (size_t v = 0; v < lit.vertices.size(); ++v) {
      const Eigen::Vector3d n = lit.normals[v].cast<double>().normalized();
      const double ratio = albedo_->light.Shading(to * n) / albedo_->light.Shading(from * n);
      for (int c = 0; c < 3; ++c) {
        lit.colors[v][c] =
            static_cast<uint8_t>(std::min(255.0, std::round(lit.colors[v][c] * ratio)));
      }
    }
    return lit;
  }

  // Each composition at targets_per_frame frames turned min..max degrees away, spread over
  // that range; every validation_every-th composition's pairs are for validation.
  void Pair() {
    Progress progress("live rerender: pairs", static_cast<int64_t>(frames_.size()));
    std::mt19937_64 rng(options_.seed);
    for (size_t a = 0; a < frames_.size(); ++a) {
      std::vector<std::pair<double, size_t>> candidates;
      for (size_t b = 0; b < frames_.size(); ++b) {
        const double turn = TurnDeg(frames_[a], frames_[b]);
        if (b != a && turn >= options_.min_turn_deg && turn <= options_.max_turn_deg)
          candidates.emplace_back(turn, b);
      }
      std::sort(candidates.begin(), candidates.end());
      const size_t count = std::min<size_t>(options_.targets_per_frame, candidates.size());
      const bool validation =
          static_cast<int>(a % options_.validation_every) == options_.validation_every / 2;
      for (size_t k = 0; k < count; ++k) {
        const auto& [turn, b] = candidates[k * candidates.size() / count];
        LivePair pair;
        pair.live_set = frames_[a].set;
        pair.target_set = frames_[b].set;
        pair.turn_deg = turn;
        pair.buffers = LiveRerenderBuffers(Jittered(InTargetLight(frames_[a], frames_[b]),
                                                    options_.jitter_m, options_.jitter_deg, rng),
                                           frames_[b].camera, raster_);
        pair.target = frames_[b].target;
        pair.silhouette = frames_[b].silhouette;
        (validation ? pairs_.validation : pairs_.train).push_back(std::move(pair));
      }
      progress.Increment();
    }
    progress.Finish();
    pairs_.plan["live_frames"] =
        Cat(frames_.size(), " composed of ", frames_.size() + pairs_.refused, " (", pairs_.refused,
            " refused)");
    pairs_.plan["pairs"] =
        Cat(pairs_.train.size(), " trained, ", pairs_.validation.size(), " validation (every ",
            options_.validation_every, "th composition's), turned ", options_.min_turn_deg, "-",
            options_.max_turn_deg, " degrees, each composition jittered by ", options_.jitter_m,
            " m and ", options_.jitter_deg, " degrees RMS");
  }

  const Take take_;
  const Mesh scan_;
  const std::optional<ScanAlbedo> albedo_;  // relights the compositions (LiveOptions::relight)
  const std::map<int64_t, Pose> poses_;
  const LiveRerenderOptions& options_;
  MeshRasterOptions raster_;
  TakePlan plan_;
  std::string depth_name_, color_name_;
  Pose color_from_depth_ = Pose::Identity();
  CameraModel color_camera_;
  std::vector<ComposedFrame> frames_;
  LivePairs pairs_;
};

}  // namespace

LivePairs MakeLivePairs(const fs::path& scan_take, const fs::path& scan_dir,
                        const LiveRerenderOptions& options) {
  return PairBuilder(scan_take, scan_dir, options).Run();
}

MaskedError ErrorInSilhouette(const cv::Mat& image, const LivePair& pair) {
  MaskedError error;
  for (int y = 0; y < pair.silhouette.rows; ++y) {
    for (int x = 0; x < pair.silhouette.cols; ++x) {
      if (pair.silhouette.at<uint8_t>(y, x) == 0) continue;
      const cv::Vec3f d = image.at<cv::Vec3f>(y, x) - pair.target.at<cv::Vec3f>(y, x);
      error.squared += d.dot(d) / 3;
      ++error.count;
    }
  }
  return error;
}

}  // namespace neural

namespace {

Json ReadLiveModelJson(const fs::path& model_dir) {
  const fs::path file = model_dir / "model.json";
  if (!fs::is_regular_file(file))
    Fail("'", model_dir.string(), "' holds no model.json (a trained model directory)");
  Json json;
  try {
    json = Json::parse(ReadFileToString(file));
  } catch (const Json::exception&) {
    Fail(file.string(), " is damaged (not JSON)");
  }
  const std::string method = json.value("method", std::string("unknown"));
  if (method != "live-rerender") {
    Fail("'", model_dir.string(), "' is a ", method,
         " model, not one trained on a scan take for live compositions (holocap train rerender "
         "SCAN_TAKE --scan SCAN)");
  }
  return json;
}

}  // namespace

LiveRerenderModel::LiveRerenderModel(const fs::path& model_dir, int threads)
    : network_(RerenderNetwork::Load(model_dir / "unet.pt",
                                     UNetConfig::FromJson(ReadLiveModelJson(model_dir).at("net")))),
      threads_(threads) {
  raster_.supersample = ReadLiveModelJson(model_dir).value("supersample", 1);
  raster_.threads = threads;
}

RenderedView LiveRerenderModel::Render(const Mesh& composed, const CameraModel& camera,
                                       cv::Mat* raw) const {
  const GBuffer buffers = LiveRerenderBuffers(composed, camera, raster_);
  if (raw != nullptr) *raw = CompositeRawRender(buffers, cv::Mat());
  return network_.Apply(buffers, threads_);
}

LiveRenderSummary RenderLiveRecon(const fs::path& take_dir, const fs::path& recon_dir,
                                  const fs::path& model_dir,
                                  const std::vector<std::string>& cameras, const fs::path& out,
                                  bool ground_truth_cameras, Report* report) {
  const LiveRerenderModel model(model_dir);
  const Take take = Take::Open(take_dir);
  TakeSelection selection;
  selection.ground_truth_cameras = ground_truth_cameras;
  const TakePlan plan = PlanTake(take, selection);
  if (cameras.empty()) Fail("name the cameras to render (--cameras)");
  for (const std::string& name : cameras) {
    if (!plan.cameras.count(name))
      Fail("take '", take_dir.string(), "' has no camera '", name, "' with a model");
  }
  std::vector<fs::path> meshes;
  if (fs::is_directory(recon_dir)) {
    for (const auto& entry : fs::directory_iterator(recon_dir))
      if (entry.path().extension() == ".ply") meshes.push_back(entry.path());
  }
  if (meshes.empty())
    Fail("'", recon_dir.string(), "' holds no composed meshes (recon/<set>.ply of holocap live)");
  std::sort(meshes.begin(), meshes.end());
  LiveRenderSummary summary;
  Progress progress("render", static_cast<int64_t>(meshes.size()));
  for (const fs::path& file : meshes) {
    const Mesh mesh = ReadPly(file);
    for (const std::string& name : cameras) {
      const RenderedView view = model.Render(mesh, plan.cameras.at(name));
      cv::Mat eight_bit;
      view.color.convertTo(eight_bit, CV_8UC3, 255);
      CreateDirectories(out / name);
      WritePng(out / name / (file.stem().string() + ".png"), eight_bit);
      ++summary.images;
    }
    ++summary.frames;
    progress.Increment();
  }
  progress.Finish();
  summary.End(Termination::kSuccess,
              Cat(summary.frames, " composed frames rendered at ", cameras.size(),
                  " camera(s): ", summary.images, " images"));
  if (report != nullptr) {
    report->metrics() = {{"frames", summary.frames}, {"images", summary.images}};
    report->SetSummary(summary);
  }
  return summary;
}

void RegisterLiveRerenderAvatarKind(AvatarKindRegistry& registry) {
  registry.Register(
      {"live-rerender", "rerendering of the compositions of holocap live",
       [](const fs::path& dir, const nlohmann::json&) -> std::unique_ptr<AvatarModel> {
         Fail((dir / "model.json").string(),
              ": a live rerender model renders `holocap live` meshes: holocap render ",
              "TAKE --model ", dir.string(), " --recon TAKE/live/recon --cameras NAMES");
       }});
}

}  // namespace holocap
