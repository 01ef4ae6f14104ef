// holocap capture --rig RIG --out TAKE --seconds S | --frames N: record a take from a rig's
// sensors, showing live per-sensor fps, drops, sync spread and MB/s on a terminal.
#include <csignal>
#include <iomanip>
#include <iostream>
#include <map>
#include <memory>
#include <optional>
#include <sstream>

#include "app/commands.h"
#include "app/options.h"
#include "capture/recorder.h"
#include "core/error.h"
#include "core/progress.h"
#include "live/live.h"

namespace holocap {
namespace {

Recorder* g_recorder = nullptr;

void OnInterrupt(int) {
  if (g_recorder != nullptr) g_recorder->RequestStop();
}

std::string StatusLine(const RecorderStatus& status) {
  std::ostringstream line;
  line << std::fixed << std::setprecision(1) << status.write_mb_s << " MB/s, spread "
       << status.spread_us_last / 1e3 << " ms (max " << status.spread_us_max / 1e3 << ") |";
  for (const auto& sensor : status.sensors) {
    line << " " << sensor.name << " " << std::setprecision(0) << sensor.fps << "fps";
    if (sensor.dropped > 0) line << " -" << sensor.dropped;
  }
  return line.str();
}

struct LiveFlags {
  std::string scan;   // --live: the subject's scan
  std::string out;    // --live-out (default TAKE/live)
  std::string calib;  // --calib: a folder of <sensor>.cameramodel
};

// `holocap capture --live SCAN`: the rig's one depth sensor and its paired colour camera,
// composed with the scan as the sets are written. Their models: --calib's files, else what the
// drivers know; `calibrated` says whether they are a calibration (not a simulation's truth).
std::unique_ptr<LiveStream> StartLive(const RigDescription& rig, const Recorder& recorder,
                                      const LiveFlags& flags, const std::string& take,
                                      std::map<std::string, CameraModel>* models,
                                      bool* calibrated) {
  const SensorSpec* depth = nullptr;
  for (const SensorSpec& spec : rig.sensors) {
    if (spec.role != SensorRole::kDepth) continue;
    if (depth != nullptr) Fail("capture --live: the rig has more than one depth sensor");
    depth = &spec;
  }
  if (depth == nullptr) Fail("capture --live: the rig has no depth sensor");
  if (depth->paired_with.empty())
    Fail("capture --live: depth sensor '", depth->name, "' names no paired colour camera");
  *models = recorder.KnownModels();
  *calibrated = recorder.TrueModelSensors().empty();
  if (!flags.calib.empty()) {
    *calibrated = true;
    models->clear();
    for (const SensorSpec& spec : rig.sensors) {
      const std::filesystem::path file =
          std::filesystem::path(flags.calib) / (spec.name + ".cameramodel");
      if (std::filesystem::exists(file)) models->emplace(spec.name, CameraModel::Read(file));
    }
  }
  for (const std::string& name : {depth->name, depth->paired_with}) {
    if (models->count(name)) continue;
    if (!flags.calib.empty())
      Fail("capture --live: no ", name, ".cameramodel in '", flags.calib, "'");
    Fail("capture --live: the driver of sensor '", name,
         "' knows no model of it; give --calib DIR (a calibrated take's calib/)");
  }
  const std::filesystem::path out =
      flags.out.empty() ? std::filesystem::path(take) / "live" : std::filesystem::path(flags.out);
  // The stream checks the scan first: a bad one is the command's only line.
  auto stream = std::make_unique<LiveStream>(flags.scan, depth->name, models->at(depth->name),
                                             depth->paired_with, models->at(depth->paired_with),
                                             out, false, LiveOptions{});
  std::cout << "live        cameras: "
            << (!flags.calib.empty() ? "--calib " + flags.calib
                : *calibrated        ? std::string("the drivers' calibrations")
                                     : std::string("the simulation's true models (never written "
                                                          "to calib/)"))
            << "\n";
  return stream;
}

// After a live capture: the models it composed with go into the take's calib/ when they are a
// calibration and cover every sensor of the take, so that `holocap live TAKE --scan SCAN` can
// compose every set. A simulation's true models never become a calibration.
void RecordLiveModels(const std::map<std::string, CameraModel>& models, bool calibrated,
                      const std::string& take) {
  const std::filesystem::path dir(take);
  if (!calibrated) return;
  if (!std::filesystem::exists(dir / "take.json")) return;
  const Take opened = Take::Open(dir);
  for (const StreamInfo& stream : opened.streams())
    if (!models.count(stream.name)) return;
  std::filesystem::create_directories(opened.calib_dir());
  for (const StreamInfo& stream : opened.streams())
    models.at(stream.name).Write(opened.calib_dir() / (stream.name + ".cameramodel"));
}

void PrintLive(const LiveSummary& live, const LiveStreamStatus& status) {
  std::cout << "live        " << status.offered << " sets offered, " << live.composed
            << " composed, " << status.skipped << " skipped (behind), " << live.refused
            << " refused, " << live.no_depth << " without depth; latency median "
            << live.metrics["latency_s"]["median"].get<double>() << " s\n"
            << ToString(live.termination) << ": " << live.message << std::endl;
}

}  // namespace

static void AddCaptureCommand(CLI::App& app) {
  auto* command = app.add_subcommand(
      "capture", "Record a take from a rig's sensors (every frame written or counted)");
  struct Args {
    std::string rig, out;
    RecorderOptions options;
    LiveFlags live;
  };
  auto args = std::make_shared<Args>();
  auto nodes = AddNodeCaptureFlags(command);
  command->add_option("--rig", args->rig, "Rig file (YAML or JSON) naming sensors by driver URI")
      ->required();
  command->add_option("--out", args->out, "The take directory to create")->required();
  auto* seconds = command->add_option("--seconds", args->options.seconds, "Record for this long");
  auto* frames = command->add_option("--frames", args->options.frames,
                                     "Record this many frame sets (triggers)");
  seconds->excludes(frames);
  command->add_option("--codec", args->options.codec,
                      "Frame files: png or zstd (default: each driver's choice)");
  command->add_option("--writers", args->options.writer_threads, "Writer threads")
      ->capture_default_str();
  command
      ->add_option("--queue", args->options.queue_frames, "Frames per sensor queued before drops")
      ->capture_default_str();
  command->add_option(
      "--trigger-phase", args->options.trigger_phase_s,
      "Software triggers on the CLOCK_REALTIME grid of the frame period plus this phase (s)");
  command
      ->add_option("--trigger-priority", args->options.trigger_priority,
                   "SCHED_FIFO priority of the software-trigger threads where permitted (0: normal "
                   "scheduling)")
      ->capture_default_str();
  command
      ->add_option("--lost-after-periods", args->options.lost_after_periods,
                   "Declare a sensor lost, ending the take, when it delivers nothing for this many "
                   "frame periods while frames are due")
      ->capture_default_str();
  command->add_flag("--durable", args->options.take.durable, "fsync every frame and index line");
  command->add_option("--live", args->live.scan,
                      "Compose the depth sensor's sets with this scan as they are recorded "
                      "(`holocap live`'s output, newest set first)");
  command->add_option("--live-out", args->live.out, "Output of --live (default TAKE/live)");
  command->add_option("--calib", args->live.calib,
                      "Camera models for --live (a calibrated take's calib/; default: the "
                      "drivers' own)");
  command->add_flag("--overwrite", args->options.take.overwrite,
                    "Replace an existing take directory");
  NameFieldFlags(command, {{"RecorderOptions::writer_threads", "--writers"},
                           {"RecorderOptions::queue_frames", "--queue"}});
  command->callback([args, nodes] {
    if (args->options.seconds <= 0 && args->options.frames <= 0)
      Fail("capture: give --seconds S or --frames N");
    args->options.Check();
    RigDescription rig = RigDescription::Load(args->rig);
    args->options.take.command = "capture";
    args->options.take.inputs = {args->rig};
    if (!rig.hosts.empty() && !args->live.scan.empty())
      Fail("capture --live: records on this machine only (the rig names capture hosts)");
    if (!rig.hosts.empty())
      return CaptureOnRigNodes(rig, args->rig, args->out, args->options, *nodes);
    if (!args->live.scan.empty()) args->options.take.inputs.push_back(args->live.scan);
    Recorder recorder(rig, args->out, args->options);
    std::map<std::string, CameraModel> live_models;
    bool live_calibrated = false;
    std::unique_ptr<LiveStream> live;
    if (!args->live.scan.empty()) {
      live = StartLive(rig, recorder, args->live, args->out, &live_models, &live_calibrated);
      recorder.set_on_set_written([&live](const FrameSet& set) { live->Offer(set); });
    }
    Report report("capture");
    report.options() = {{"rig", args->rig},
                        {"out", args->out},
                        {"seconds", args->options.seconds},
                        {"frames", args->options.frames},
                        {"codec", args->options.codec},
                        {"writers", args->options.writer_threads},
                        {"queue_frames", args->options.queue_frames},
                        {"trigger_phase_s", args->options.trigger_phase_s},
                        {"trigger_priority", args->options.trigger_priority},
                        {"lost_after_periods", args->options.lost_after_periods},
                        {"durable", args->options.take.durable}};
    report.plan() = {
        {"sync", ToString(rig.sync)}, {"fps", rig.fps}, {"sensors", rig.sensors.size()}};
    const int64_t total = args->options.frames > 0
                              ? args->options.frames
                              : static_cast<int64_t>(args->options.seconds * rig.fps);
    Progress progress("capture", total);
    g_recorder = &recorder;
    auto previous_int = std::signal(SIGINT, OnInterrupt);
    auto previous_term = std::signal(SIGTERM, OnInterrupt);
    RecorderSummary summary = recorder.Run(
        [&](const RecorderStatus& status) {
          std::string line = StatusLine(status);
          if (live) {
            const LiveStreamStatus s = live->status();
            line += Cat(" | live ", s.composed, " composed, ", s.skipped, " skipped");
          }
          progress.Update(status.frame_sets, line);
        },
        &report);
    std::signal(SIGINT, previous_int);
    std::signal(SIGTERM, previous_term);
    g_recorder = nullptr;
    progress.Finish();
    report.metrics() = summary.Metrics();
    report.SetSummary(summary);
    std::string report_failure;
    try {
      report.Write(std::filesystem::path(args->out) / "report.json");
    } catch (const Error& e) {
      // A full disk may refuse the report too; the take itself is already closed. Said in the
      // one error line, not a line of its own.
      report_failure = e.what();
    }
    std::cout << "take        " << args->out << "\n"
              << "frame sets  " << summary.frame_sets_complete << " complete, "
              << summary.frame_sets_incomplete << " incomplete, " << summary.frames_dropped
              << " frames dropped\n"
              << "sync spread max " << summary.sync_spread_us_max << " us, mean "
              << summary.sync_spread_us_mean << " us\n"
              << "written     " << summary.bytes_written / 1e6 << " MB in " << summary.seconds
              << " s (" << summary.write_mb_s << " MB/s)\n"
              << ToString(summary.termination) << ": " << summary.message << std::endl;
    if (!report_failure.empty()) {
      summary.message += Cat("; and ", report_failure);
      if (summary.IsUsable()) Fail("capture: ", summary.message);
    }
    std::optional<LiveSummary> composed;
    if (live) {
      composed = live->Finish();
      PrintLive(*composed, live->status());
      RecordLiveModels(live_models, live_calibrated, args->out);
    }
    FailUnlessUsable(summary, "capture");
    if (composed) FailUnlessUsable(*composed, "capture --live");
  });
}

HOLOCAP_COMMAND(20, AddCaptureCommand);

}  // namespace holocap
