#include <omp.h>

#include <chrono>
#include <cstdio>
#include <map>
#include <memory>

#include "core/error.h"
#include "core/fs.h"
#include "core/image.h"
#include "core/mesh.h"
#include "core/progress.h"
#include "core/take.h"
#include "core/threads.h"
#include "core/trajectory.h"
#include "sim/sim.h"
#include "sim/world.h"

namespace holocap {
namespace {

using Json = nlohmann::json;
using Clock = std::chrono::steady_clock;

std::string SetName(int64_t set) {
  char name[32];
  std::snprintf(name, sizeof(name), "%06lld", static_cast<long long>(set));
  return name;
}

Json PoseJson(const Pose& pose) {
  const Rt rt = RtFromPose(pose);
  Json matrix = Json::array();
  for (int r = 0; r < 4; ++r) {
    matrix.push_back(
        {pose.matrix()(r, 0), pose.matrix()(r, 1), pose.matrix()(r, 2), pose.matrix()(r, 3)});
  }
  return {{"rt", rt}, {"matrix", matrix}};
}

double Seconds(Clock::time_point since) {
  return std::chrono::duration<double>(Clock::now() - since).count();
}

// The noise models as gt/sim.json states them.
Json NoiseJson(const SimOptions& options) {
  return {{"color",
           {{"enabled", options.noise},
            {"model",
             "DN = 255 * gain * clamp(e, 0, full_well) / full_well, e = radiance * "
             "exposure_us / reference_exposure_us * full_well + N(0, e + read^2)"},
            {"full_well_electrons", options.full_well_electrons},
            {"read_noise_electrons", options.read_noise_electrons},
            {"reference_exposure_us", options.reference_exposure_us}}},
          {"depth",
           {{"enabled", options.noise},
            {"model",
             "z_measured = round_mm(z + N(0, (k z^2)^2)); NaN beyond max incidence, next "
             "to depth jumps, outside [min, max], and at random dropouts"},
            {"k_per_m", options.depth_noise_k},
            {"max_incidence_deg", options.depth_max_incidence_deg},
            {"edge_threshold_m", options.depth_edge_threshold_m},
            {"min_m", options.depth_min_m},
            {"max_m", options.depth_max_m},
            {"dropout_probability", options.depth_dropout_probability},
            {"quantisation_m", 0.001}}}};
}

// One simulated take, step by step: the ground truth that does not change over the take, then
// each frame set (render, ground truth, append), then gt/board.json and gt/sim.json.
class Simulation {
 public:
  Simulation(const SimOptions& options, const std::filesystem::path& out, Report* report)
      : options_(options),
        report_(report),
        threads_(ResolveThreads(options.threads)),
        world_(options),
        scene_(world_.scene()),
        gt_(out / "gt"),
        moving_subject_(scene_.kind() == sim::SceneKind::kSubject) {
    if (report_ != nullptr) {
      report_->options() = options_.ToJson();
      report_->plan() = {{"rig", world_.rig().name},
                         {"sensors", world_.size()},
                         {"scene", options_.scene},
                         {"threads", threads_},
                         {"motion_blur", options_.motion_blur}};
    }
    TakeWriterOptions writer_options;
    writer_options.overwrite = options_.overwrite;
    writer_options.command = "sim";
    std::error_code ec;
    if (std::filesystem::exists(options_.rig, ec)) writer_options.inputs = {options_.rig};
    writer_options.manifest_every = 30;
    const Json metadata = {{"simulated", true},
                           {"scene", options_.scene},
                           {"seed", options_.seed},
                           {"clean_plate_frames", options_.clean_plate_frames},
                           {"trajectory", options_.trajectory}};
    writer_ =
        std::make_unique<TakeWriter>(out, world_.rig(), world_.streams(), metadata, writer_options);
  }

  SimSummary Run(Clock::time_point start) {
    start_ = start;
    WriteStaticGroundTruth();
    world_.PrepareRayTables(threads_);
    setup_seconds_ = Seconds(start_);
    Progress progress("sim", options_.frames);
    try {
      for (int64_t set = 0; set < options_.frames; ++set) {
        SimulateSet(set);
        const double rate =
            60.0 * summary_.frame_sets / std::max(1e-9, Seconds(start_) - setup_seconds_);
        if (report_ != nullptr) report_->AddPoint("frame_sets_per_minute", rate, set);
        char status[64];
        std::snprintf(status, sizeof(status), "%.1f sets/min", rate);
        progress.Increment(status);
      }
      writer_->Close();
      summary_.End(Termination::kSuccess,
                   Cat(summary_.frame_sets, " frame sets of ", world_.size(), " sensors, ",
                       summary_.frames_dropped, " frames dropped"));
    } catch (const Error& e) {
      summary_.End(Termination::kFailure,
                   Cat("stopped after ", summary_.frame_sets, " frame sets: ", e.what()));
    }
    progress.Finish();
    WriteBoardAndSimJson();
    Conclude();
    return summary_;
  }

 private:
  // gt/cameras, the mask and depth folders, gt/meshes/static.ply; fills sensors_json_.
  void WriteStaticGroundTruth() {
    CreateDirectories(gt_ / "cameras");
    for (int i = 0; i < world_.size(); ++i) {
      const sim::SimSensorState& sensor = world_.sensor(i);
      sensor.model.Write(gt_ / "cameras" / (sensor.spec.name + ".cameramodel"));
      CreateDirectories(gt_ / "masks" / sensor.spec.name);
      if (sensor.spec.role == SensorRole::kDepth)
        CreateDirectories(gt_ / "depth" / sensor.spec.name);
      Json entry = {{"role", ToString(sensor.spec.role)},
                    {"lensmodel", sensor.model.lensmodel()},
                    {"width", sensor.model.width()},
                    {"height", sensor.model.height()},
                    {"cam_from_world", PoseJson(sensor.model.cam_from_world())},
                    {"clock_offset_ns", sensor.clock_offset_ns},
                    {"exposure_offset_s", sensor.exposure_offset_s},
                    {"exposure_us", sensor.exposure_us},
                    {"gain_db", sensor.gain_db}};
      if (!sensor.spec.paired_with.empty()) {
        const int color = world_.IndexOf(sensor.spec.paired_with);
        entry["paired_with"] = sensor.spec.paired_with;
        entry["depth_from_color"] =
            PoseJson(sensor.model.cam_from_world() * world_.sensor(color).model.world_from_cam());
      }
      sensors_json_[sensor.spec.name] = entry;
    }
    if (scene_.kind() != sim::SceneKind::kBoard) CreateDirectories(gt_ / "meshes");
    if (scene_.kind() == sim::SceneKind::kObject) {
      WritePly(
          gt_ / "meshes" / "static.ply",
          world_.frame().Transformed(scene_.At(0, options_.clean_plate_frames)->subject_mesh()));
    }
  }

  // The sensors that deliver frame set `set`; the others are counted dropped.
  std::vector<int> PresentSensors(int64_t set) {
    std::vector<int> present;
    for (int i = 0; i < world_.size(); ++i) {
      if (world_.Dropped(i, set)) {
        writer_->CountDropped(world_.sensor(i).spec.name, 1);
        dropped_json_.push_back({{"set", set}, {"sensor", world_.sensor(i).spec.name}});
        ++summary_.frames_dropped;
      } else {
        present.push_back(i);
      }
    }
    return present;
  }

  void SimulateSet(int64_t set) {
    const Clock::time_point render_start = Clock::now();
    const std::vector<int> present = PresentSensors(set);
    std::vector<sim::SensorFrame> rendered(present.size());
    for (size_t k = 0; k < present.size(); ++k)
      rendered[k] = world_.Render(present[k], set, threads_);
    render_seconds_ += Seconds(render_start);

    FrameSet frame_set = WriteFrameGroundTruth(set, present, rendered);
    for (size_t k = 0; k < present.size(); ++k) {
      const std::string& sensor = world_.sensor(present[k]).spec.name;
      frames_json_.push_back({{"set", set},
                              {"sensor", sensor},
                              {"time_s", rendered[k].time_s},
                              {"timestamp_ns", rendered[k].timestamp_ns}});
      if (world_.trajectory().moving()) {
        const CameraModel truth = world_.TrueModelAt(present[k], rendered[k].time_s);
        frames_json_.back()["cam_from_world"] = PoseJson(truth.cam_from_world());
        tum_[sensor] += TumLine(rendered[k].time_s, truth.world_from_cam());
      }
    }
    writer_->Append(frame_set);
    summary_.frames_written += static_cast<int64_t>(present.size());
    if (moving_subject_ && !scene_.IsCleanPlate(set)) {
      const double t_s = static_cast<double>(set) / world_.fps();
      WritePly(gt_ / "meshes" / (SetName(set) + ".ply"),
               world_.frame().Transformed(world_.SnapshotAt(t_s, set)->subject_mesh()));
    }
    if (scene_.kind() == sim::SceneKind::kBoard) {
      Json pose = PoseJson(world_.frame().FromSim(scene_.WorldFromBoard(set)));
      pose["set"] = set;
      board_poses_.push_back(pose);
    }
    ++summary_.frame_sets;
  }

  // Each sensor's mask (and true depth) of the set, and the set's frames for the take.
  FrameSet WriteFrameGroundTruth(int64_t set, const std::vector<int>& present,
                                 const std::vector<sim::SensorFrame>& rendered) {
    const std::string name = SetName(set);
    FrameSet frame_set;
    frame_set.index = set;
    frame_set.frames.resize(present.size());
    std::string write_error;
    // Encoding and writing each sensor's ground truth is independent: spread over the cores.
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads_)
    for (size_t k = 0; k < present.size(); ++k) {
      const sim::SimSensorState& sensor = world_.sensor(present[k]);
      Frame& frame = frame_set.frames[k];
      frame.sensor = sensor.spec.name;
      frame.image = rendered[k].image;
      frame.timestamp_ns = rendered[k].timestamp_ns;
      frame.sequence = static_cast<uint64_t>(set);
      try {
        WritePng(gt_ / "masks" / sensor.spec.name / (name + ".png"), rendered[k].mask);
        if (sensor.spec.role == SensorRole::kDepth) {
          WriteExrDepth(gt_ / "depth" / sensor.spec.name / (name + ".exr"), rendered[k].true_depth);
        }
      } catch (const Error& e) {
#pragma omp critical(sim_write_error)
        write_error = e.what();
      }
    }
    if (!write_error.empty()) Fail(write_error);
    return frame_set;
  }

  void WriteBoardAndSimJson() {
    for (const auto& [sensor, lines] : tum_) {
      CreateDirectories(gt_ / "trajectory");
      WriteFileAtomic(gt_ / "trajectory" / (sensor + ".tum"), lines);
    }
    if (scene_.kind() == sim::SceneKind::kBoard) {
      // The board scales with the world: its layout in the take's metres.
      BoardLayout layout = options_.board;
      layout.spacing *= world_.frame().scale();
      layout.margin *= world_.frame().scale();
      Json board = {{"layout", layout.ToJson()}, {"world_from_board", board_poses_}};
      WriteFileAtomic(gt_ / "board.json", board.dump(1) + "\n");
    }
    const Json sim_json = {
        {"options", options_.ToJson()},
        {"rig", world_.rig().ToJson()},
        {"fps", world_.fps()},
        {"clock", "sim"},
        {"clock_start_ns", sim::kSimClockStartNs},
        {"timestamp_model",
         "timestamp_ns = clock_start_ns + round(1e9 * (set / fps + exposure_offset_s) + "
         "clock_offset_ns + jitter), jitter ~ N(0, timestamp_jitter_ns)"},
        {"sensors", sensors_json_},
        {"frames", frames_json_},
        {"dropped", dropped_json_},
        {"noise", NoiseJson(options_)},
        {"meshes", moving_subject_ ? "per set: gt/meshes/<set>.ply at set / fps"
                   : scene_.kind() == sim::SceneKind::kObject ? "static: gt/meshes/static.ply"
                                                              : "none"},
        {"clean_plate_frames", options_.clean_plate_frames},
        {"termination", ToString(summary_.termination)}};
    try {
      WriteFileAtomic(gt_ / "sim.json", sim_json.dump(1) + "\n");
    } catch (const Error& e) {
      if (summary_.IsUsable()) summary_.End(Termination::kFailure, e.what());
    }
  }

  // Timings and the report's metrics and summary.
  void Conclude() {
    summary_.seconds = Seconds(start_);
    summary_.render_seconds = render_seconds_;
    summary_.frame_sets_per_minute =
        summary_.seconds > 0 ? 60.0 * summary_.frame_sets / summary_.seconds : 0;
    if (report_ == nullptr) return;
    report_->metrics() = {{"frame_sets", summary_.frame_sets},
                          {"frames_written", summary_.frames_written},
                          {"frames_dropped", summary_.frames_dropped},
                          {"seconds", summary_.seconds},
                          {"render_seconds", summary_.render_seconds},
                          {"setup_seconds", setup_seconds_},
                          {"frame_sets_per_minute", summary_.frame_sets_per_minute}};
    report_->SetSummary(summary_);
  }

  const SimOptions& options_;
  Report* report_;
  const int threads_;
  sim::SimWorld world_;
  const sim::Scene& scene_;
  const std::filesystem::path gt_;
  const bool moving_subject_;
  std::unique_ptr<TakeWriter> writer_;
  Clock::time_point start_;
  double setup_seconds_ = 0;
  double render_seconds_ = 0;
  SimSummary summary_;
  Json sensors_json_ = Json::object();
  Json frames_json_ = Json::array();
  Json dropped_json_ = Json::array();
  Json board_poses_ = Json::array();
  std::map<std::string, std::string> tum_;  // moving takes: each sensor's true trajectory
};

}  // namespace

SimSummary SimulateTake(const SimOptions& options, const std::filesystem::path& out,
                        Report* report) {
  const Clock::time_point start = Clock::now();
  options.Check();
  Simulation simulation(options, out, report);
  return simulation.Run(start);
}

}  // namespace holocap
