// holocap capture --rig RIG --out TAKE --seconds S | --frames N: record a take from a rig's
// sensors, showing live per-sensor fps, drops, sync spread and MB/s on a terminal.
#include <csignal>
#include <iomanip>
#include <iostream>
#include <sstream>

#include "app/commands.h"
#include "app/options.h"
#include "capture/recorder.h"
#include "core/error.h"
#include "core/progress.h"

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

}  // namespace

static void AddCaptureCommand(CLI::App& app) {
  auto* command = app.add_subcommand(
      "capture", "Record a take from a rig's sensors (every frame written or counted)");
  struct Args {
    std::string rig, out;
    RecorderOptions options;
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
  command->add_flag("--overwrite", args->options.take.overwrite,
                    "Replace an existing take directory");
  command->callback([args, nodes] {
    if (args->options.seconds <= 0 && args->options.frames <= 0)
      Fail("capture: give --seconds S or --frames N");
    CheckNamingFlags([&] { args->options.Check(); },
                     {{"capture: lost_after_periods", "--lost-after-periods"},
                      {"capture: writer_threads", "--writers"},
                      {"capture: queue_frames", "--queue"},
                      {"capture: trigger_priority", "--trigger-priority"},
                      {"capture: codec", "--codec"}});
    RigDescription rig = RigDescription::Load(args->rig);
    args->options.take.command = "capture";
    args->options.take.inputs = {args->rig};
    if (!rig.hosts.empty())
      return CaptureOnRigNodes(rig, args->rig, args->out, args->options, *nodes);
    Recorder recorder(rig, args->out, args->options);
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
          progress.Update(status.frame_sets, StatusLine(status));
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
    FailUnlessUsable(summary, "capture");
  });
}

HOLOCAP_COMMAND(20, AddCaptureCommand);

}  // namespace holocap
