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
  bool needs_libtorch = false;  // runs in holocap-neural; holocap hands it over
};
std::vector<CommandEntry>& CommandTable();
struct CommandRegistrar {
  CommandRegistrar(int order, std::function<void(CLI::App&)> add, bool needs_libtorch = false) {
    CommandTable().push_back({order, std::move(add), needs_libtorch});
  }
};
#define HOLOCAP_COMMAND(order, add_function) \
  static const ::holocap::CommandRegistrar add_function##_registrar(order, add_function)

// The subcommand at `path` ("render", "train nvol": words from the program's root, the parents
// created where no command made them yet) with its one-line help.
CLI::App* AddCommandAt(CLI::App& app, const std::string& path, const std::string& help);

// Commands that need LibTorch (Neural Volumes, rerendering: whatever links holocap_neural),
// whose start-up costs a second and ~170 MB, live in holocap-neural, beside holocap, built
// from the same command files: HOLOCAP_LIBTORCH_COMMAND(order, "train nvol", "help", Fill)
// adds the subcommand at that path and, where LibTorch is linked (HOLOCAP_WITH_NEURAL),
// Fill(CLI::App*) gives it its flags and callback; in holocap the same registration lists it
// and hands every use of it (--help included) to holocap-neural. The files that register such
// commands are compiled into both programs, their LibTorch parts inside
// `#if HOLOCAP_WITH_NEURAL`.
#if HOLOCAP_WITH_NEURAL
#define HOLOCAP_LIBTORCH_COMMAND(order, path, help, fill_function)    \
  static const ::holocap::CommandRegistrar fill_function##_registrar( \
      order, [](CLI::App& app) { fill_function(::holocap::AddCommandAt(app, path, help)); }, true)
#else
#define HOLOCAP_LIBTORCH_COMMAND(order, path, help, fill_function)                 \
  static const ::holocap::CommandRegistrar fill_function##_registrar(              \
      order,                                                                       \
      [](CLI::App& app) {                                                          \
        ::holocap::AddHandedOverCommand(::holocap::AddCommandAt(app, path, help)); \
      },                                                                           \
      true)
#endif

// True in holocap-neural, the program that links LibTorch.
bool ProgramHasLibTorch();
// A command of holocap that holocap-neural runs: listed in --help, every use of it handed over.
void AddHandedOverCommand(CLI::App* command);
// Replaces this process by holocap-neural with the same arguments (what holocap does for a
// command, a merge or an export it does not link); never returns. In holocap-neural it throws
// Error: there is nothing to hand over to.
[[noreturn]] void HandOverToLibTorchProgram(const std::string& what);
// The program's arguments, kept by main() for HandOverToLibTorchProgram.
void SetProgramArguments(int argc, char** argv);

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
  int key_every = 0;               // --key-every (0: the default)
  std::vector<double> splat_mbps;  // --splat-mbps (empty or 0: each level's own encoding)
  bool ground_truth_cameras = false;
  bool overwrite = false;
  std::string frames;           // --frames (the timeline's sets, counted after the clean plate)
  std::string shard;            // --shard K/N (empty: the whole run)
  bool redo = false;            // --redo
  bool partial_models = false;  // --partial-model: models whose training did not finish too
};
std::function<void(const WebExportRequest&)>& WebExportCommand();

// `holocap report OUT --merge` of a per-frame run whose command lives in holocap-neural (train
// splat): its merge, by the run's command, registered by that command's file (holocap hands
// `report ... --merge` over). Each returns the merged run's summary, report.json written.
using RunMerger = std::function<Summary(const std::filesystem::path& out, Report* report)>;
std::map<std::string, RunMerger>& RunMergers();

// Every driver compiled into this build, registered in DriverRegistry::Global().
void RegisterBuiltinDrivers();
// Every avatar kind this program links, registered in AvatarKindRegistry::Global()
// (app/avatar_kinds.cpp): splats everywhere, the LibTorch kinds in holocap-neural.
void RegisterAvatarKinds();

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
