// holocap import FORMAT SRC --out TAKE: a recording or calibration from another tool as a take.
#include <cstdio>
#include <memory>

#include "app/commands.h"
#include "app/options.h"
#include "core/error.h"
#include "interop/interop.h"

namespace holocap {
namespace {

struct ImportArgs {
  std::string format;
  std::string source;
  std::string out;
  std::string images;
  ImportOptions options;
};

}  // namespace

static void AddImportCommand(CLI::App& app) {
  auto* command = app.add_subcommand("import",
                                     "Import a recording from another tool (middlebury, krt, "
                                     "colmap, nerf, panoptic, mrcal) as a take");
  auto args = std::make_shared<ImportArgs>();
  ImportOptions& o = args->options;
  command->add_option("FORMAT", args->format, "middlebury | krt | colmap | nerf | panoptic | mrcal")
      ->required();
  command
      ->add_option("SRC", args->source,
                   "The source: *_par.txt or its folder, KRT file, COLMAP folder, transforms.json, "
                   "calibration_*.json, or a folder of .cameramodel files")
      ->required();
  command->add_option("--out", args->out, "The take directory to create")->required();
  command->add_option("--images", args->images,
                      "Image root, where the format's default place is not right");
  command
      ->add_option("--metres-per-unit", o.metres_per_unit,
                   "Length unit of the source in metres (0: the format's; Panoptic is in cm)")
      ->capture_default_str();
  command
      ->add_option(
          "--max-rotation-residual", o.max_rotation_residual,
          "Accept rotations whose non-orthonormal parts differ by up to this (then not exact)")
      ->capture_default_str();
  command
      ->add_option("--fps", o.fps,
                   "Frame-set rate stamped on the frames (sources carry no timestamps)")
      ->capture_default_str();
  command->add_flag("--overwrite", o.overwrite, "Replace an existing take directory");
  command->callback([args] {
    ImportOptions options = args->options;
    options.format = InteropFormatFromString(args->format);
    options.images = args->images;
    Report report("import");
    ImportSummary summary = ImportTake(args->source, args->out, options, &report);
    report.Write(std::filesystem::path(args->out) / "report.json");
    std::printf("%s: %s\n", ToString(summary.termination), summary.message.c_str());
    if (summary.metrics.contains("colmap_points") &&
        summary.metrics["colmap_points"].contains("mean_reprojection_error_px")) {
      const auto& points = summary.metrics["colmap_points"];
      std::printf(
          "points3D: %lld points, %lld observations, mean reprojection error %.6f px "
          "(the file's: %.6f px, largest per-point difference %.3g px)\n",
          points["count"].get<long long>(), points["observations"].get<long long>(),
          points["mean_reprojection_error_px"].get<double>(),
          points["file_mean_reprojection_error_px"].get<double>(),
          points["max_per_point_difference_px"].get<double>());
    }
    std::fflush(stdout);
    FailUnlessUsable(summary, "import");
  });
}

HOLOCAP_COMMAND(25, AddImportCommand);

}  // namespace holocap
