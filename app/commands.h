// The `holocap` subcommands: one file each, each parsing its options and calling one stage's
// public API.
#pragma once

#include <CLI/CLI.hpp>
#include <filesystem>
#include <functional>
#include <iosfwd>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "core/report.h"

namespace holocap {

class Take;

// Each cmd_*.cpp registers its subcommand with HOLOCAP_COMMAND(order, AddFn); `order` sets
// where it appears in --help (pipeline order: sim 10, capture 20, info 30, ...).
struct CommandEntry {
  int order;
  std::function<void(CLI::App&)> add;
};
std::vector<CommandEntry>& CommandTable();

// The commands that learn or play an avatar (demo, train, render) need LibTorch, whose start-up
// costs every command a second and ~170 MB: they live in holocap-neural, beside holocap, which
// hands them over (execv, the same arguments) before parsing. holocap-neural runs them itself.
void HandOverNeuralCommands(int argc, char** argv);
struct CommandRegistrar {
  CommandRegistrar(int order, std::function<void(CLI::App&)> add) {
    CommandTable().push_back({order, std::move(add)});
  }
};
#define HOLOCAP_COMMAND(order, add_function) \
  static const ::holocap::CommandRegistrar add_function##_registrar(order, add_function)

// `holocap demo` runs every registered stage in order on a small simulated take. A stage
// file registers with HOLOCAP_DEMO_STAGE(order, "name", Fn), Fn(DemoContext&) -> Summary;
// sim is 10, calibration 20, reconstruction 30, neural 40, playback 50.
struct DemoContext {
  std::filesystem::path out;   // out/demo
  std::filesystem::path take;  // the simulated studio8 take of the walking subject
  int64_t frames = 0;
  uint64_t seed = 1;
  Report* report = nullptr;  // out/demo/report.json: stages add metrics under their name
};
struct DemoStage {
  int order;
  std::string name;
  std::function<Summary(DemoContext&)> run;
};
std::vector<DemoStage>& DemoStageTable();
struct DemoStageRegistrar {
  DemoStageRegistrar(int order, std::string name, std::function<Summary(DemoContext&)> run) {
    DemoStageTable().push_back({order, std::move(name), std::move(run)});
  }
};
#define HOLOCAP_DEMO_STAGE(order, name, run_function)                                   \
  static const ::holocap::DemoStageRegistrar run_function##_demo_registrar(order, name, \
                                                                           run_function)

// `holocap export web`: parsed in app/cmd_export.cpp beside the other formats, run by
// app/cmd_view.cpp in holocap-neural (it bakes volumes; holocap hands `export web` over).
struct WebExportRequest {
  std::string take;
  std::string out;
  std::vector<std::string> models;     // --model, repeatable
  std::string recon;                   // --recon (default TAKE/recon)
  std::vector<std::string> qualities;  // --quality low,medium,high,lossless
  bool no_meshes = false;
  double fps = 0;
  int key_every = 0;  // --key-every (0: the default)
  bool ground_truth_cameras = false;
  bool overwrite = false;
  std::string frames;  // --frames (the timeline's sets, counted after the clean plate)
  std::string shard;   // --shard K/N (empty: the whole run)
  bool redo = false;   // --redo
};
std::function<void(const WebExportRequest&)>& WebExportCommand();

// `holocap report OUT --merge` of a per-frame run whose command lives in holocap-neural (train
// splat): its merge, by the run's command, registered by that command's file (holocap hands
// `report ... --merge` over). Each returns the merged run's summary, report.json written.
using RunMerger = std::function<Summary(const std::filesystem::path& out, Report* report)>;
std::map<std::string, RunMerger>& RunMergers();

// Every driver compiled into this build, registered in DriverRegistry::Global().
void RegisterBuiltinDrivers();

// `holocap capture` on a rig whose sensors name hosts (app/cmd_capture_node.cpp): the flags
// it adds to the capture command, and the run that coordinates the hosts' capture nodes.
struct NodeCaptureOptions;
struct RecorderOptions;
struct RigDescription;
std::shared_ptr<NodeCaptureOptions> AddNodeCaptureFlags(CLI::App* capture);
void CaptureOnRigNodes(const RigDescription& rig, const std::string& rig_file,
                       const std::string& out, const RecorderOptions& recorder,
                       NodeCaptureOptions& options);

// What `holocap info` prints about a take.
void PrintTakeInfo(const Take& take, std::ostream& out);

}  // namespace holocap
