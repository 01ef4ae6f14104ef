#include <omp.h>

#include <chrono>
#include <cstdio>

#include "core/error.h"
#include "core/fs.h"
#include "core/image.h"
#include "core/mesh.h"
#include "core/progress.h"
#include "core/take.h"
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

}  // namespace

SimSummary SimulateTake(const SimOptions& options, const std::filesystem::path& out,
                        Report* report) {
  const Clock::time_point start = Clock::now();
  options.Check();
  const int threads = options.threads > 0 ? options.threads : omp_get_max_threads();
  sim::SimWorld world(options);
  const sim::Scene& scene = world.scene();
  if (report != nullptr) {
    report->options() = options.ToJson();
    report->plan() = {{"rig", world.rig().name},
                      {"sensors", world.size()},
                      {"scene", options.scene},
                      {"threads", threads},
                      {"motion_blur", options.motion_blur}};
  }

  TakeWriterOptions writer_options;
  writer_options.overwrite = options.overwrite;
  writer_options.manifest_every = 30;
  const Json metadata = {{"simulated", true},
                         {"scene", options.scene},
                         {"seed", options.seed},
                         {"clean_plate_frames", options.clean_plate_frames}};
  TakeWriter writer(out, world.rig(), world.streams(), metadata, writer_options);

  // Ground truth that does not change over the take.
  const std::filesystem::path gt = out / "gt";
  CreateDirectories(gt / "cameras");
  Json sensors_json = Json::object();
  for (int i = 0; i < world.size(); ++i) {
    const sim::SimSensorState& sensor = world.sensor(i);
    sensor.model.Write(gt / "cameras" / (sensor.spec.name + ".cameramodel"));
    CreateDirectories(gt / "masks" / sensor.spec.name);
    if (sensor.spec.role == SensorRole::kDepth) CreateDirectories(gt / "depth" / sensor.spec.name);
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
      const int color = world.IndexOf(sensor.spec.paired_with);
      entry["paired_with"] = sensor.spec.paired_with;
      entry["depth_from_color"] =
          PoseJson(sensor.model.cam_from_world() * world.sensor(color).model.world_from_cam());
    }
    sensors_json[sensor.spec.name] = entry;
  }
  const bool moving_subject = scene.kind() == sim::SceneKind::kSubject;
  if (scene.kind() != sim::SceneKind::kBoard) CreateDirectories(gt / "meshes");
  if (scene.kind() == sim::SceneKind::kObject) {
    WritePly(gt / "meshes" / "static.ply", scene.At(0, options.clean_plate_frames)->subject_mesh());
  }

  world.PrepareRayTables(threads);
  const double setup_seconds = Seconds(start);

  SimSummary summary;
  Json frames_json = Json::array();
  Json dropped_json = Json::array();
  Json board_poses = Json::array();
  Progress progress("sim", options.frames);
  double render_seconds = 0;
  try {
    for (int64_t set = 0; set < options.frames; ++set) {
      const Clock::time_point render_start = Clock::now();
      const std::string name = SetName(set);
      std::vector<int> present;
      for (int i = 0; i < world.size(); ++i) {
        if (world.Dropped(i, set)) {
          writer.CountDropped(world.sensor(i).spec.name, 1);
          dropped_json.push_back({{"set", set}, {"sensor", world.sensor(i).spec.name}});
          ++summary.frames_dropped;
        } else {
          present.push_back(i);
        }
      }
      std::vector<sim::SensorFrame> rendered(present.size());
      for (size_t k = 0; k < present.size(); ++k) {
        rendered[k] = world.Render(present[k], set, threads);
      }
      render_seconds += Seconds(render_start);

      FrameSet frame_set;
      frame_set.index = set;
      frame_set.frames.resize(present.size());
      std::string write_error;
      // Encoding and writing each sensor's ground truth is independent: spread over the cores.
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
      for (size_t k = 0; k < present.size(); ++k) {
        const sim::SimSensorState& sensor = world.sensor(present[k]);
        Frame& frame = frame_set.frames[k];
        frame.sensor = sensor.spec.name;
        frame.image = rendered[k].image;
        frame.timestamp_ns = rendered[k].timestamp_ns;
        frame.sequence = static_cast<uint64_t>(set);
        try {
          WritePng(gt / "masks" / sensor.spec.name / (name + ".png"), rendered[k].mask);
          if (sensor.spec.role == SensorRole::kDepth) {
            WriteExrDepth(gt / "depth" / sensor.spec.name / (name + ".exr"),
                          rendered[k].true_depth);
          }
        } catch (const Error& e) {
#pragma omp critical(sim_write_error)
          write_error = e.what();
        }
      }
      if (!write_error.empty()) Fail(write_error);
      for (size_t k = 0; k < present.size(); ++k) {
        frames_json.push_back({{"set", set},
                               {"sensor", world.sensor(present[k]).spec.name},
                               {"time_s", rendered[k].time_s},
                               {"timestamp_ns", rendered[k].timestamp_ns}});
      }
      writer.Append(frame_set);
      summary.frames_written += static_cast<int64_t>(present.size());
      if (moving_subject && !scene.IsCleanPlate(set)) {
        WritePly(gt / "meshes" / (name + ".ply"),
                 world.SnapshotAt(static_cast<double>(set) / world.fps(), set)->subject_mesh());
      }
      if (scene.kind() == sim::SceneKind::kBoard) {
        Json pose = PoseJson(scene.WorldFromBoard(set));
        pose["set"] = set;
        board_poses.push_back(pose);
      }
      ++summary.frame_sets;
      const double rate =
          60.0 * summary.frame_sets / std::max(1e-9, Seconds(start) - setup_seconds);
      if (report != nullptr) report->AddPoint("frame_sets_per_minute", rate, set);
      char status[64];
      std::snprintf(status, sizeof(status), "%.1f sets/min", rate);
      progress.Increment(status);
    }
    writer.Close();
  } catch (const Error& e) {
    summary.termination = Termination::kFailure;
    summary.message = Cat("stopped after ", summary.frame_sets, " frame sets: ", e.what());
  }
  progress.Finish();

  if (scene.kind() == sim::SceneKind::kBoard) {
    Json board = {{"layout", options.board.ToJson()}, {"world_from_board", board_poses}};
    WriteFileAtomic(gt / "board.json", board.dump(1) + "\n");
  }
  const Json sim_json = {
      {"options", options.ToJson()},
      {"rig", world.rig().ToJson()},
      {"fps", world.fps()},
      {"clock", "sim"},
      {"clock_start_ns", sim::kSimClockStartNs},
      {"timestamp_model",
       "timestamp_ns = clock_start_ns + round(1e9 * (set / fps + exposure_offset_s) + "
       "clock_offset_ns + jitter), jitter ~ N(0, timestamp_jitter_ns)"},
      {"sensors", sensors_json},
      {"frames", frames_json},
      {"dropped", dropped_json},
      {"noise",
       {{"color",
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
          {"quantisation_m", 0.001}}}}},
      {"meshes", moving_subject ? "per set: gt/meshes/<set>.ply at set / fps"
                 : scene.kind() == sim::SceneKind::kObject ? "static: gt/meshes/static.ply"
                                                           : "none"},
      {"clean_plate_frames", options.clean_plate_frames},
      {"termination", ToString(summary.termination)}};
  try {
    WriteFileAtomic(gt / "sim.json", sim_json.dump(1) + "\n");
  } catch (const Error& e) {
    if (summary.termination != Termination::kFailure) {
      summary.termination = Termination::kFailure;
      summary.message = e.what();
    }
  }

  summary.seconds = Seconds(start);
  summary.render_seconds = render_seconds;
  summary.frame_sets_per_minute =
      summary.seconds > 0 ? 60.0 * summary.frame_sets / summary.seconds : 0;
  if (summary.termination == Termination::kSuccess) {
    summary.message = Cat(summary.frame_sets, " frame sets of ", world.size(), " sensors, ",
                          summary.frames_dropped, " frames dropped");
  }
  if (report != nullptr) {
    report->metrics() = {{"frame_sets", summary.frame_sets},
                         {"frames_written", summary.frames_written},
                         {"frames_dropped", summary.frames_dropped},
                         {"seconds", summary.seconds},
                         {"render_seconds", summary.render_seconds},
                         {"setup_seconds", setup_seconds},
                         {"frame_sets_per_minute", summary.frame_sets_per_minute}};
    report->SetSummary({summary.termination, summary.message});
  }
  return summary;
}

}  // namespace holocap
