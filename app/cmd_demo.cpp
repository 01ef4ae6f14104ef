// holocap demo: every stage that exists, in pipeline order, on a small simulated take into
// out/demo/, with one report of what ran.
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <iostream>

#include "app/commands.h"
#include "app/options.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/report.h"
#include "core/take.h"
#include "sim/sim.h"

namespace holocap {

#if HOLOCAP_WITH_NEURAL

namespace {

struct DemoArgs {
  std::string out = "out/demo";
  int64_t frames = 6;
  uint64_t seed = 1;
  bool overwrite = false;
};

// The first stage: a small studio8 take of the walking subject, its clean plate first.
Summary SimulateDemoTake(DemoContext& context) {
  SimOptions sim;
  sim.rig = "studio8";
  sim.frames = context.frames;
  sim.seed = context.seed;
  sim.clean_plate_frames = 1;
  sim.overwrite = true;
  Report sim_report("sim");
  SimSummary summary = SimulateTake(sim, context.take, &sim_report);
  sim_report.Write(context.take / "report.json");
  context.report->metrics()["sim"] = {{"frame_sets", summary.frame_sets},
                                      {"frame_sets_per_minute", summary.frame_sets_per_minute},
                                      {"seconds", summary.seconds}};
  std::printf("[demo] sim: %lld frame sets in %.1f s (%.1f frame sets/min)\n\n",
              static_cast<long long>(summary.frame_sets), summary.seconds,
              summary.frame_sets_per_minute);
  PrintTakeInfo(Take::Open(context.take), std::cout);
  std::printf("\n");
  return {summary.termination, summary.message};
}
HOLOCAP_DEMO_STAGE(10, "sim", SimulateDemoTake);

void FillDemoCommand(CLI::App* command) {
  auto args = std::make_shared<DemoArgs>();
  command->add_option("--out", args->out, "Output directory")->capture_default_str();
  command->add_option("--frames", args->frames, "Frame sets to simulate")->capture_default_str();
  command->add_option("--seed", args->seed, "Simulation seed")->capture_default_str();
  AddOverwriteFlag(command, &args->overwrite);
  command->callback([args] {
    Report report("demo");
    report.options() = {{"out", args->out}, {"frames", args->frames}, {"seed", args->seed}};
    report.plan()["stages"] = nlohmann::json::array();
    DemoContext context{.out = args->out,
                        .take = std::filesystem::path(args->out) / "take",
                        .frames = args->frames,
                        .seed = args->seed,
                        .report = &report};
    const OutputDirectory claimed =
        OutputDirectory::Claim(context.out, {"demo", args->overwrite, {}});
    report.SetFailureDestination(context.out / "report.json");
    auto stages = DemoStageTable();
    std::stable_sort(stages.begin(), stages.end(),
                     [](const auto& a, const auto& b) { return a.order < b.order; });
    Summary overall{Termination::kSuccess, ""};
    for (const auto& stage : stages) {
      std::printf("[demo] %s ...\n", stage.name.c_str());
      double start = report.ElapsedSeconds();
      Summary summary = stage.run(context);
      report.plan()["stages"].push_back({{"stage", stage.name},
                                         {"termination", ToString(summary.termination)},
                                         {"message", summary.message},
                                         {"seconds", report.ElapsedSeconds() - start}});
      report.Write(context.out / "report.json");
      if (!IsUsable(summary.termination)) {
        overall = {summary.termination, stage.name + ": " + summary.message};
        break;
      }
    }
    if (overall.message.empty()) overall.message = "every stage ran";
    report.SetSummary(overall);
    report.Write(context.out / "report.json");
    std::printf(
        "[demo] %s: %s\n[demo] report: %s\n[demo] every stage's report and plots: holocap report "
        "%s --out %s\n",
        ToString(overall.termination), overall.message.c_str(),
        (context.out / "report.json").c_str(), context.out.c_str(),
        (context.out / "plots").c_str());
    if (std::filesystem::is_regular_file(context.out / "site" / "manifest.json"))
      std::printf("[demo] watch it in a browser: holocap view %s\n",
                  (context.out / "site").c_str());
    if (!IsUsable(overall.termination)) Fail("demo stopped: ", overall.message);
  });
}

}  // namespace

#endif  // HOLOCAP_WITH_NEURAL

HOLOCAP_LIBTORCH_COMMAND(
    100, "demo", "Run every pipeline stage on a small simulated studio8 take into out/demo/",
    FillDemoCommand);

}  // namespace holocap
