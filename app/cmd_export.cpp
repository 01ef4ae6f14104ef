// holocap export colmap|nerf TAKE --out DIR: a take's cameras and colour frames for other tools.
#include <cstdio>
#include <memory>

#include "app/commands.h"
#include "app/options.h"
#include "core/error.h"
#include "interop/interop.h"

namespace holocap {
namespace {

struct ExportArgs {
  std::string format;
  std::string take;
  std::string out;
  bool no_images = false;
  ExportOptions options;
};

}  // namespace

static void AddExportCommand(CLI::App& app) {
  auto* command = app.add_subcommand(
      "export", "Export a take's cameras and frames as a COLMAP model or a NeRF transforms.json");
  auto args = std::make_shared<ExportArgs>();
  command->add_option("FORMAT", args->format, "colmap | nerf")->required();
  command->add_option("TAKE", args->take, "The take directory")->required();
  command->add_option("--out", args->out, "The directory to write")->required();
  command->add_flag("--ground-truth", args->options.ground_truth,
                    "Export the true cameras (gt/cameras, simulated takes) instead of calib/");
  command->add_flag("--no-images", args->no_images, "Write the cameras only, not the frames");
  command->add_flag(
      "--skip-unrepresentable", args->options.skip_unrepresentable,
      "Export the cameras the format holds exactly and skip the others (default: refuse)");
  command->add_flag("--overwrite", args->options.overwrite, "Write into a non-empty directory");
  command->callback([args] {
    ExportOptions options = args->options;
    options.format = InteropFormatFromString(args->format);
    options.copy_images = !args->no_images;
    Report report("export");
    ExportSummary summary = ExportTake(args->take, args->out, options, &report);
    report.Write(std::filesystem::path(args->out) / "report.json");
    std::printf("%s: %s\n", ToString(summary.termination), summary.message.c_str());
    for (const auto& skipped : summary.skipped) std::printf("  skipped %s\n", skipped.c_str());
    std::fflush(stdout);
    FailUnlessUsable(summary, "export");
  });
}

HOLOCAP_COMMAND(35, AddExportCommand);

}  // namespace holocap
