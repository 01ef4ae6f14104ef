#include "sim/world.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <numbers>
#include <random>

#include "core/check_option.h"
#include "core/error.h"

namespace holocap {

BoardLayout SimOptions::DefaultSimBoard() {
  BoardLayout board;
  board.type = BoardType::kAprilGrid;
  board.family = "tag36h11";
  board.tags_across = 5;
  board.tags_down = 4;
  // 10 cm tags: the wide studio8 lenses see them large enough to decode in the views they
  // share with a neighbour.
  board.spacing = 0.10;
  board.margin = 0.10;
  return board;
}

void SimOptions::Check() const {
  HOLOCAP_CHECK_OPTION(!rig.empty(), rig, "a built-in rig or a rig file");
  HOLOCAP_CHECK_OPTION_GE(frames, 1);
  sim::SceneKindFromString(scene);
  HOLOCAP_CHECK_OPTION_GE(image_width, 0);
  HOLOCAP_CHECK_OPTION_GE(image_height, 0);
  HOLOCAP_CHECK_OPTION(image_height == 0 || image_width > 0, image_height,
                       "image_height needs image_width");
  HOLOCAP_CHECK_OPTION(image_width == 0 || image_width >= 8, image_width);
  HOLOCAP_CHECK_OPTION(image_height == 0 || image_height >= 8, image_height);
  HOLOCAP_CHECK_OPTION_GE(fps, 0, "0: the rig's");
  HOLOCAP_CHECK_OPTION(std::isfinite(fps), fps);
  HOLOCAP_CHECK_OPTION_GE(clean_plate_frames, 0);
  board.Check();
  HOLOCAP_CHECK_OPTION_GT(full_well_electrons, 0);
  HOLOCAP_CHECK_OPTION_GE(read_noise_electrons, 0);
  HOLOCAP_CHECK_OPTION_GT(exposure_us, 0);
  HOLOCAP_CHECK_OPTION_GT(exposure_scale, 0);
  HOLOCAP_CHECK_OPTION(std::isfinite(gain_db), gain_db);
  HOLOCAP_CHECK_OPTION_GT(reference_exposure_us, 0);
  HOLOCAP_CHECK_OPTION_IN(antialias, 1, 32);
  HOLOCAP_CHECK_OPTION_IN(motion_blur_samples, 1, 64);
  HOLOCAP_CHECK_OPTION_GE(depth_noise_k, 0);
  HOLOCAP_CHECK_OPTION_GT(depth_max_incidence_deg, 0);
  HOLOCAP_CHECK_OPTION_LE(depth_max_incidence_deg, 90);
  HOLOCAP_CHECK_OPTION_GT(depth_edge_threshold_m, 0);
  HOLOCAP_CHECK_OPTION_GE(depth_min_m, 0);
  HOLOCAP_CHECK_OPTION_GT(depth_max_m, depth_min_m);
  HOLOCAP_CHECK_OPTION_IN(depth_dropout_probability, 0, 1);
  HOLOCAP_CHECK_OPTION_GE(timestamp_jitter_ns, 0);
  HOLOCAP_CHECK_OPTION_GE(clock_offset_max_ns, 0);
  HOLOCAP_CHECK_OPTION_GE(drop_probability, 0);
  HOLOCAP_CHECK_OPTION_LT(drop_probability, 1);
  HOLOCAP_CHECK_OPTION_GE(threads, 0, "0: all cores");
  const sim::TrajectoryKind motion = sim::TrajectoryKindFromString(trajectory);
  HOLOCAP_CHECK_OPTION_IN(trajectory_deg_per_s, -3600, 3600);
  HOLOCAP_CHECK_OPTION(motion == sim::TrajectoryKind::kFixed ||
                           sim::SceneKindFromString(scene) != sim::SceneKind::kBoard,
                       trajectory,
                       "a moving sensor needs a subject or object scene, not the board");
  HOLOCAP_CHECK_OPTION_GT(world_scale, 0);
  HOLOCAP_CHECK_OPTION(std::isfinite(world_scale), world_scale);
  HOLOCAP_CHECK_OPTION(up.allFinite() && up.norm() > 0, up, "a non-zero direction");
  HOLOCAP_CHECK_OPTION_GT(subject_albedo, 0);
  HOLOCAP_CHECK_OPTION_LE(subject_albedo, 1);
  HOLOCAP_CHECK_OPTION_GT(background_albedo, 0);
  HOLOCAP_CHECK_OPTION_LE(background_albedo, 1);
  HOLOCAP_CHECK_OPTION(!board_still || sim::SceneKindFromString(scene) == sim::SceneKind::kBoard,
                       board_still, "a still board needs the board scene");
  HOLOCAP_CHECK_OPTION_IN(board_partial, 0, 1);
  HOLOCAP_CHECK_OPTION(
      board_partial == 0 || sim::SceneKindFromString(scene) == sim::SceneKind::kBoard,
      board_partial, "partial board views need the board scene");
}

nlohmann::json SimOptions::ToJson() const {
  return {{"rig", rig},
          {"frames", frames},
          {"scene", scene},
          {"seed", seed},
          {"image_width", image_width},
          {"image_height", image_height},
          {"fps", fps},
          {"clean_plate_frames", clean_plate_frames},
          {"board", board.ToJson()},
          {"board_still", board_still},
          {"board_partial", board_partial},
          {"upside_down", upside_down},
          {"trajectory", trajectory},
          {"trajectory_deg_per_s", trajectory_deg_per_s},
          {"noise", noise},
          {"full_well_electrons", full_well_electrons},
          {"read_noise_electrons", read_noise_electrons},
          {"exposure_us", exposure_us},
          {"exposure_scale", exposure_scale},
          {"gain_db", gain_db},
          {"reference_exposure_us", reference_exposure_us},
          {"antialias", antialias},
          {"motion_blur", motion_blur},
          {"motion_blur_samples", motion_blur_samples},
          {"depth_noise_k", depth_noise_k},
          {"depth_max_incidence_deg", depth_max_incidence_deg},
          {"depth_edge_threshold_m", depth_edge_threshold_m},
          {"depth_min_m", depth_min_m},
          {"depth_max_m", depth_max_m},
          {"depth_dropout_probability", depth_dropout_probability},
          {"timestamp_jitter_ns", timestamp_jitter_ns},
          {"clock_offset_max_ns", clock_offset_max_ns},
          {"drop_probability", drop_probability},
          {"threads", threads},
          {"world_scale", world_scale},
          {"up", {up.x(), up.y(), up.z()}},
          {"color_only", color_only},
          {"subject_albedo", subject_albedo},
          {"background_albedo", background_albedo},
          {"alpha", alpha}};
}

namespace sim {

WorldFrame::WorldFrame(const SimOptions& options) : scale_(options.world_scale) {
  const Eigen::Vector3d up = options.up.normalized();
  // The shortest turn from +z to `up`; straight down turns about x (the world's -z up).
  rotation_ = up.z() < -1 + 1e-12
                  ? Eigen::Matrix3d(Eigen::AngleAxisd(std::numbers::pi, Eigen::Vector3d::UnitX()))
                  : Eigen::Quaterniond::FromTwoVectors(Eigen::Vector3d::UnitZ(), up).matrix();
}

Pose WorldFrame::FromSim(const Pose& sim_from_x) const {
  Pose world_from_x = Pose::Identity();
  world_from_x.linear() = rotation_ * sim_from_x.linear();
  world_from_x.translation() = Point(sim_from_x.translation());
  return world_from_x;
}

CameraModel WorldFrame::Camera(const CameraModel& in_sim) const {
  CameraModel camera = in_sim;
  camera.set_cam_from_world(FromSim(in_sim.world_from_cam()).inverse());
  return camera;
}

Mesh WorldFrame::Transformed(const Mesh& in_sim) const {
  Mesh mesh = in_sim;
  const Eigen::Matrix3f linear = (scale_ * rotation_).cast<float>();
  for (Eigen::Vector3f& v : mesh.vertices) v = linear * v;
  const Eigen::Matrix3f turn = rotation_.cast<float>();
  for (Eigen::Vector3f& n : mesh.normals) n = turn * n;
  return mesh;
}

SimWorld::SimWorld(const SimOptions& options) : options_(options), frame_(options) {
  options_.Check();
  rig_ = LoadSimRig(options_.rig);
  if (options_.color_only) {
    std::erase_if(rig_.sensors, [](const SensorSpec& s) { return s.role == SensorRole::kDepth; });
  }
  rig_.Check();
  for (const std::string& name : options_.upside_down) {
    if (rig_.IndexOf(name) < 0) Fail("upside_down: the rig has no sensor '", name, "'");
  }
  fps_ = options_.fps > 0 ? options_.fps : rig_.fps;
  if (!(fps_ > 0)) Fail("sim: the rig's fps must be > 0");
  const std::filesystem::path base_dir = std::filesystem::exists(options_.rig)
                                             ? std::filesystem::path(options_.rig).parent_path()
                                             : std::filesystem::path();
  std::vector<CameraModel> colour_cameras;
  for (size_t i = 0; i < rig_.sensors.size(); ++i) {
    const SensorSpec& spec = rig_.sensors[i];
    SimSensorState state;
    state.spec = spec;
    state.sim_model =
        SimSensorModel(rig_, spec, options_.image_width, options_.image_height, base_dir);
    if (std::ranges::find(options_.upside_down, spec.name) != options_.upside_down.end()) {
      Pose turned = Pose::Identity();
      turned.linear() =
          Eigen::AngleAxisd(std::numbers::pi, Eigen::Vector3d::UnitZ()).toRotationMatrix();
      state.sim_model.set_cam_from_world(turned * state.sim_model.cam_from_world());
    }
    state.model = frame_.Camera(state.sim_model);
    state.stream.name = spec.name;
    state.stream.uri = spec.uri;
    state.stream.role = spec.role;
    state.stream.width = state.model.width();
    state.stream.height = state.model.height();
    state.stream.clock = "sim";
    state.stream.paired_with = spec.paired_with;
    if (spec.role == SensorRole::kDepth) {
      state.stream.pixel_format = "depth_m";
      state.stream.codec = ImageCodec::kExr;
    } else {
      state.stream.pixel_format = options_.alpha ? "bgra8" : "bgr8";
      state.stream.codec = ImageCodec::kPng;
      colour_cameras.push_back(state.sim_model);
    }
    std::mt19937_64 rng(MixSeed(options_.seed, 1, i));
    std::uniform_real_distribution<double> unit(0, 1);
    state.clock_offset_ns = (2 * unit(rng) - 1) * options_.clock_offset_max_ns;
    state.exposure_offset_s = rig_.sync == SyncMode::kFreeRun ? unit(rng) / fps_ : 0.0;
    state.exposure_us =
        (spec.exposure_us > 0 ? spec.exposure_us : options_.exposure_us) * options_.exposure_scale;
    state.gain_db = spec.gain_db + options_.gain_db;
    sensors_.push_back(std::move(state));
  }
  rays_.resize(sensors_.size());
  scene_ = std::make_unique<Scene>(SceneKindFromString(options_.scene), options_.board,
                                   colour_cameras, options_.clean_plate_frames, options_.seed,
                                   Appearance{options_.subject_albedo, options_.background_albedo});
  if (options_.board_still) scene_->HoldBoardStill();
  if (options_.board_partial > 0) scene_->ShowBoardPartly(options_.board_partial);
  trajectory_ = std::make_unique<Trajectory>(TrajectoryKindFromString(options_.trajectory),
                                             options_.trajectory_deg_per_s, scene_->CenterAtStart(),
                                             options_.seed);
  if (trajectory_->moving()) {
    const Trajectory* trajectory = trajectory_.get();
    scene_->HoldStill([trajectory](double t_s) { return trajectory->WorldFromSubject(t_s); });
  }
}

int SimWorld::IndexOf(const std::string& name) const {
  for (int i = 0; i < size(); ++i) {
    if (sensors_[i].spec.name == name) return i;
  }
  return -1;
}

std::vector<StreamInfo> SimWorld::streams() const {
  std::vector<StreamInfo> streams;
  for (const SimSensorState& state : sensors_) streams.push_back(state.stream);
  return streams;
}

void SimWorld::PrepareRayTables(int threads) {
  for (int i = 0; i < size(); ++i) {
    auto table = std::make_shared<const RayTable>(sensors_[i].sim_model, threads);
    std::lock_guard lock(mutex_);
    if (!rays_[i]) rays_[i] = std::move(table);
  }
}

const RayTable& SimWorld::Rays(int index) const {
  {
    std::lock_guard lock(mutex_);
    if (rays_[index]) return *rays_[index];
  }
  auto table = std::make_shared<const RayTable>(sensors_[index].sim_model, options_.threads);
  std::lock_guard lock(mutex_);
  if (!rays_[index]) rays_[index] = std::move(table);
  return *rays_[index];
}

std::shared_ptr<const Snapshot> SimWorld::SnapshotAt(double t_s, int64_t set) const {
  const auto key = std::make_pair(t_s, set);
  {
    std::lock_guard lock(mutex_);
    for (const auto& [cached_key, snapshot] : snapshots_) {
      if (cached_key == key) return snapshot;
    }
  }
  std::shared_ptr<const Snapshot> snapshot = scene_->At(t_s, set);
  std::lock_guard lock(mutex_);
  snapshots_.emplace_back(key, snapshot);
  // Enough for every sensor of a free-running rig and the motion-blur samples of a set.
  const size_t keep =
      2 * static_cast<size_t>(size()) + 2 * static_cast<size_t>(options_.motion_blur_samples);
  while (snapshots_.size() > keep) snapshots_.pop_front();
  return snapshot;
}

bool SimWorld::Dropped(int index, int64_t set) const {
  if (options_.drop_probability <= 0) return false;
  const uint64_t draw =
      MixSeed(options_.seed, 6, static_cast<uint64_t>(index), static_cast<uint64_t>(set));
  return static_cast<double>(draw >> 11) * (1.0 / 9007199254740992.0) < options_.drop_probability;
}

double SimWorld::TrueTime(int index, int64_t set) const {
  return static_cast<double>(set) / fps_ + sensors_[index].exposure_offset_s;
}

CameraModel SimWorld::SimModelAt(int index, double t_s) const {
  CameraModel model = sensors_[index].sim_model;
  if (trajectory_->moves_sensor()) {
    model.set_cam_from_world(trajectory_->WorldFromCam(model.world_from_cam(), t_s).inverse());
  }
  return model;
}

CameraModel SimWorld::TrueModelAt(int index, double t_s) const {
  CameraModel in_sim = SimModelAt(index, t_s);
  // Relative to a turning subject: cam_from_subject = cam_from_world * world_from_subject.
  in_sim.set_cam_from_world(in_sim.cam_from_world() * trajectory_->WorldFromSubject(t_s));
  return frame_.Camera(in_sim);
}

SensorFrame SimWorld::Render(int index, int64_t set, int threads) const {
  const SimSensorState& sensor = sensors_[index];
  const RayTable& rays = Rays(index);
  SensorFrame frame;
  frame.time_s = TrueTime(index, set);
  std::mt19937_64 rng(
      MixSeed(options_.seed, 2, static_cast<uint64_t>(index), static_cast<uint64_t>(set)));
  std::normal_distribution<double> jitter(0, 1);
  frame.timestamp_ns = kSimClockStartNs + std::llround(frame.time_s * 1e9 + sensor.clock_offset_ns +
                                                       options_.timestamp_jitter_ns * jitter(rng));
  const std::shared_ptr<const Snapshot> snapshot = SnapshotAt(frame.time_s, set);
  const uint64_t noise_seed =
      MixSeed(options_.seed, 3, static_cast<uint64_t>(index), static_cast<uint64_t>(set));

  if (sensor.spec.role == SensorRole::kDepth) {
    const DepthRender truth =
        RenderDepth(*snapshot, SimModelAt(index, frame.time_s), rays, threads);
    DepthSensorModel model;
    model.noise_k = options_.depth_noise_k;
    model.max_incidence_deg = options_.depth_max_incidence_deg;
    model.edge_threshold_m = options_.depth_edge_threshold_m;
    model.min_m = options_.depth_min_m;
    model.max_m = options_.depth_max_m;
    model.dropout_probability = options_.depth_dropout_probability;
    model.noise = options_.noise;
    // Measured in the simulation's metres, then scaled into the take's world like everything.
    frame.image = MeasureDepth(truth, model, noise_seed) * frame_.scale();
    frame.mask = truth.mask;
    frame.true_depth = truth.z * frame_.scale();
    return frame;
  }

  const uint64_t jitter_seed =
      MixSeed(options_.seed, 5, static_cast<uint64_t>(index), static_cast<uint64_t>(set));
  ColorRender render = RenderColor(*snapshot, SimModelAt(index, frame.time_s), rays,
                                   options_.antialias, jitter_seed, threads);
  frame.mask = render.mask;
  cv::Mat radiance = render.radiance;
  const bool blur = options_.motion_blur || trajectory_->kind() == TrajectoryKind::kHandheld;
  const int samples = blur ? options_.motion_blur_samples : 1;
  if (samples > 1) {
    // The exposure integrates the moving scene: average renders spread over it.
    radiance = cv::Mat::zeros(radiance.size(), radiance.type());
    const double exposure_s = sensor.exposure_us * 1e-6;
    for (int s = 0; s < samples; ++s) {
      const double t = frame.time_s + ((s + 0.5) / samples - 0.5) * exposure_s;
      const ColorRender sub = RenderColor(*SnapshotAt(t, set), SimModelAt(index, t), rays,
                                          options_.antialias, jitter_seed + s, threads);
      radiance += sub.radiance;
    }
    radiance /= samples;
  }
  ColorSensorModel model;
  model.noise = options_.noise;
  model.full_well_electrons = options_.full_well_electrons;
  model.read_noise_electrons = options_.read_noise_electrons;
  model.exposure_ratio = sensor.exposure_us / options_.reference_exposure_us;
  model.gain = std::pow(10.0, sensor.gain_db / 20);
  frame.image = MeasureColor(radiance, model, noise_seed);
  if (options_.alpha) {
    cv::Mat bgra;
    cv::merge(std::vector<cv::Mat>{frame.image, frame.mask}, bgra);
    frame.image = bgra;
  }
  return frame;
}

}  // namespace sim
}  // namespace holocap
