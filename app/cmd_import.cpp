// holocap import FORMAT SRC --out TAKE: a recording or calibration from another tool as a take;
// holocap import images [FOLDER] [--camera NAME=SOURCE]... --out TAKE: photographs or videos.
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
  std::vector<std::string> cameras;  // NAME=SOURCE
  std::string pair_by = "auto";
  ImageImportOptions image_options;
};

// import images: the cameras from --camera NAME=SOURCE, or from the folder's sub-folders.
void RunImportImages(const ImportArgs& args, const CLI::App& command) {
  if (command.count("--images") + command.count("--metres-per-unit") +
          command.count("--max-rotation-residual") >
      0)
    Fail(
        "--images, --metres-per-unit and --max-rotation-residual are not options of import images");
  std::vector<CameraSource> cameras;
  for (const auto& item : args.cameras) {
    const size_t equals = item.find('=');
    if (equals == std::string::npos || equals == 0 || equals + 1 == item.size())
      Fail("--camera '", item, "' is not NAME=SOURCE (a folder, a glob or a video)");
    cameras.push_back({item.substr(0, equals), item.substr(equals + 1)});
  }
  if (!args.source.empty() && !cameras.empty())
    Fail("give the cameras either as a FOLDER of sub-folders or with --camera, not both");
  if (!args.source.empty()) cameras = CameraSourcesInFolder(args.source);
  ImageImportOptions options = args.image_options;
  options.pairing = FramePairingFromString(args.pair_by);
  options.fps = args.options.fps;
  options.overwrite = args.options.overwrite;
  Report report("import");
  ImageImportSummary summary = ImportImages(cameras, args.out, options, &report);
  report.Write(std::filesystem::path(args.out) / "report.json");
  std::printf("%s: %s\n%s\n", ToString(summary.termination), summary.message.c_str(),
              summary.PairingLine().c_str());
  std::fflush(stdout);
  FailUnlessUsable(summary, "import");
}

}  // namespace

static void AddImportCommand(CLI::App& app) {
  auto* command = app.add_subcommand("import",
                                     "Import a recording from another tool (middlebury, krt, "
                                     "colmap, nerf, panoptic, mrcal), or photographs and videos "
                                     "(images), as a take");
  auto args = std::make_shared<ImportArgs>();
  ImportOptions& o = args->options;
  command
      ->add_option("FORMAT", args->format,
                   "middlebury | krt | colmap | nerf | panoptic | mrcal | images")
      ->required();
  command->add_option("SRC", args->source,
                      "The source: *_par.txt or its folder, KRT file, COLMAP folder, "
                      "transforms.json, calibration_*.json, or a folder of .cameramodel files; "
                      "images: a folder with one sub-folder of images (or one video) per camera");
  command->add_option("--camera", args->cameras,
                      "images: NAME=SOURCE, one camera's folder, glob of images ('left*.jpg', "
                      "quoted) or video file; repeat per camera");
  command
      ->add_option("--pair-by", args->pair_by,
                   "images: pair frames into sets by number (in the file name), time (video "
                   "position, or timestamps.txt beside the images), order, or auto")
      ->capture_default_str();
  command
      ->add_option("--time-tolerance", args->image_options.time_tolerance_s,
                   "images, pairing by time: seconds frames may differ in one set (0: half the "
                   "shortest interval of one camera)")
      ->capture_default_str();
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
  command->callback([args, command] {
    if (args->format == "images") {
      RunImportImages(*args, *command);
      return;
    }
    if (args->source.empty()) Fail("import ", args->format, " needs SRC");
    if (!args->cameras.empty() ||
        command->count("--pair-by") + command->count("--time-tolerance") > 0)
      Fail("--camera, --pair-by and --time-tolerance are options of import images only");
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
