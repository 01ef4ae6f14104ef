// holocap capture-node --listen ENDPOINT: serve a capture host's sensors to a coordinator.
// holocap capture --rig RIG (whose sensors name hosts): that coordinator (flags added to capture).
#include <csignal>
#include <iomanip>
#include <iostream>
#include <sstream>

#include "app/commands.h"
#include "app/options.h"
#include "core/error.h"
#include "core/progress.h"
#include "distributed/node.h"

namespace holocap {
namespace {

std::atomic<bool> g_stop{false};

void OnSignal(int) { g_stop = true; }

std::string NodeStatusLine(const NodeCaptureStatus& status) {
  std::ostringstream line;
  line << std::fixed << std::setprecision(1);
  for (const auto& node : status.nodes) {
    line << (line.tellp() > 0 ? " | " : "") << node.name;
    if (!node.answering) {
      line << " NOT ANSWERING";
      continue;
    }
    line << " " << node.fps << "fps -" << node.dropped << " spread " << node.spread_us_last / 1e3
         << "ms " << node.write_mb_s << "MB/s";
  }
  return line.str();
}

}  // namespace

static void AddCaptureNodeCommand(CLI::App& app) {
  auto* command = app.add_subcommand(
      "capture-node",
      "Serve this host's sensors to `holocap capture` on a rig whose sensors name hosts");
  auto options = std::make_shared<CaptureNodeOptions>();
  command->add_option("--listen", options->listen, "ZeroMQ endpoint to bind (tcp://ADDR:PORT)")
      ->required();
  command->add_option("--name", options->name, "The node's name in replies (default: host name)");
  command->add_option("--root", options->root,
                      "Write parts under this folder (default: where the coordinator says, on a "
                      "filesystem the hosts share)");
  command
      ->add_option("--takes", options->max_takes,
                   "Exit after recording this many takes (0: serve until SIGINT/SIGTERM)")
      ->capture_default_str();
  NameFieldFlags(command, {{"max_takes", "--takes"}});
  command->callback([options] {
    options->Check();
    g_stop = false;
    auto previous_int = std::signal(SIGINT, OnSignal);
    auto previous_term = std::signal(SIGTERM, OnSignal);
    ServeCaptureNode(*options, g_stop, [](const std::string& line) {
      std::cout << "capture-node: " << line << std::endl;
    });
    std::signal(SIGINT, previous_int);
    std::signal(SIGTERM, previous_term);
  });
}

HOLOCAP_COMMAND(21, AddCaptureNodeCommand);

std::shared_ptr<NodeCaptureOptions> AddNodeCaptureFlags(CLI::App* capture) {
  auto options = std::make_shared<NodeCaptureOptions>();
  const std::string group = "Rigs whose sensors name hosts";
  capture
      ->add_option("--parts", options->parts,
                   "Where the nodes write their parts (default: TAKE.parts; a path every host "
                   "sees, or each node's --root)")
      ->group(group);
  capture
      ->add_option("--node-timeout", options->reply_timeout_s,
                   "Seconds a node may leave a request unanswered before it is declared lost")
      ->capture_default_str()
      ->group(group);
  capture
      ->add_option("--start-lead", options->start_lead_s,
                   "Seconds from the start request to the first trigger on every node")
      ->capture_default_str()
      ->group(group);
  capture
      ->add_option("--max-clock-offset-us", options->max_clock_offset_us,
                   "Leave out (and name) a node whose clock is off by more than this")
      ->capture_default_str()
      ->group(group);
  capture
      ->add_option("--merge-tolerance-ns", options->merge.tolerance_ns,
                   "Largest spread of a merged set across nodes, ns (0: 0.4 frame periods)")
      ->group(group);
  NameFieldFlags(capture, {{"NodeCaptureOptions::reply_timeout_s", "--node-timeout"},
                           {"MergeOptions::tolerance_ns", "--merge-tolerance-ns"}});
  return options;
}

void CaptureOnRigNodes(const RigDescription& rig, const std::string& rig_file,
                       const std::string& out, const RecorderOptions& recorder,
                       NodeCaptureOptions& options) {
  options.out = out;
  options.frames = recorder.frames;
  options.seconds = recorder.seconds;
  options.recorder = recorder;
  options.merge.overwrite = recorder.take.overwrite;
  options.Check();
  Report report("capture");
  report.options() = {{"rig", rig_file},
                      {"out", out},
                      {"parts", options.parts.string()},
                      {"seconds", options.seconds},
                      {"frames", options.frames},
                      {"node_timeout_s", options.reply_timeout_s},
                      {"start_lead_s", options.start_lead_s},
                      {"max_clock_offset_us", options.max_clock_offset_us},
                      {"codec", recorder.codec},
                      {"writers", recorder.writer_threads},
                      {"queue_frames", recorder.queue_frames},
                      {"trigger_priority", recorder.trigger_priority},
                      {"lost_after_periods", recorder.lost_after_periods},
                      {"durable", recorder.take.durable}};
  report.plan() = {{"sync", ToString(rig.sync)},
                   {"fps", rig.fps},
                   {"sensors", rig.sensors.size()},
                   {"hosts", rig.hosts}};
  const int64_t total =
      options.frames > 0 ? options.frames : static_cast<int64_t>(options.seconds * rig.fps);
  Progress progress("capture", total);
  g_stop = false;
  auto previous_int = std::signal(SIGINT, OnSignal);
  auto previous_term = std::signal(SIGTERM, OnSignal);
  NodeCaptureSummary summary = CaptureOnNodes(
      rig, options, g_stop,
      [&](const NodeCaptureStatus& status) {
        int64_t least = total;
        for (const auto& node : status.nodes) least = std::min(least, node.frame_sets);
        progress.Update(least, NodeStatusLine(status));
      },
      &report);
  std::signal(SIGINT, previous_int);
  std::signal(SIGTERM, previous_term);
  progress.Finish();
  report.metrics() = summary.Metrics();
  report.SetSummary(summary);
  const std::filesystem::path report_file =
      summary.merged ? std::filesystem::path(out) / "report.json"
                     : std::filesystem::absolute(options.parts.empty() ? out + ".parts"
                                                                       : options.parts.string()) /
                           "report.json";
  std::filesystem::create_directories(report_file.parent_path());
  report.Write(report_file);
  for (const auto& node : summary.nodes) {
    std::cout << "node " << std::left << std::setw(12) << node.name << " " << std::setw(11)
              << node.state << " clock " << node.clock.offset_ns / 1e3 << " us ("
              << (node.clock.offset_source.empty() ? "not measured" : node.clock.offset_source)
              << "; " << node.clock.daemon.source << ": " << node.clock.daemon.detail << ")";
    if (!node.message.empty()) std::cout << "  " << node.message;
    std::cout << "\n";
  }
  if (summary.merged) {
    std::cout << "take        " << out << "\n"
              << "frame sets  " << summary.merge.sets_complete << " complete, "
              << summary.merge.sets_incomplete << " incomplete of " << summary.merge.slots
              << " slots\n"
              << "sync spread across nodes max " << summary.merge.spread_us_max << " us, mean "
              << summary.merge.spread_us_mean << " us\n";
  }
  std::cout << ToString(summary.termination) << ": " << summary.message << std::endl;
  FailUnlessUsable(summary, "capture");
}

}  // namespace holocap
