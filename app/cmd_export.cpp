// holocap export colmap|nerf|images|web TAKE --out DIR: a take's cameras and colour frames for
// other tools, its frames as image folders or MP4s (images), or (web) a static site that plays the
// take's meshes and volumes in a browser, in one process or as shards (--shard K/N) of a per-frame
// run.
#include <cstdio>
#include <memory>
#include <sstream>

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
  WebExportRequest web;
  std::string qualities = "medium";
  ImageExportOptions images;
  std::string video;
};

void RunExportImages(const ExportArgs& args, const CLI::App& command) {
  for (const char* web_only : {"--model", "--recon", "--no-meshes", "--partial-model", "--quality",
                               "--key-every", "--splat-mbps", "--frames", "--shard", "--redo",
                               "--ground-truth-cameras", "--no-images", "--skip-unrepresentable"}) {
    if (command.count(web_only) > 0) Fail(web_only, " is not an option of export images");
  }
  ImageExportOptions options = args.images;
  if (!args.video.empty() && args.video != "mp4")
    Fail("--video ", args.video, ": the one video format is mp4");
  options.video = !args.video.empty();
  options.fps = args.web.fps;
  options.overwrite = args.options.overwrite;
  Report report("export");
  const ImageExportSummary summary = ExportImages(args.take, args.out, options, &report);
  report.Write(std::filesystem::path(args.out) / "report.json");
  EndCommand(summary, "export");
}

}  // namespace

std::function<void(const WebExportRequest&)>& WebExportCommand() {
  static std::function<void(const WebExportRequest&)> run;
  return run;
}

static void AddExportCommand(CLI::App& app) {
  auto* command = app.add_subcommand(
      "export",
      "Export a take's cameras and frames as a COLMAP model or a NeRF transforms.json, its frames "
      "as images or videos (images), or a static web site that plays its meshes and volumes "
      "(web)");
  auto args = std::make_shared<ExportArgs>();
  command->add_option("FORMAT", args->format, "colmap | nerf | images | web")->required();
  command->add_option("TAKE", args->take, "The take directory")->required();
  command->add_option("--out", args->out, "The directory to write")->required();
  command->add_flag("--ground-truth-cameras,--ground-truth", args->options.ground_truth,
                    "Use a simulated take's true cameras (gt/cameras) instead of calib/ (an "
                    "uncalibrated take is refused otherwise)");
  command->add_flag("--no-images", args->no_images, "Write the cameras only, not the frames");
  command->add_flag(
      "--skip-unrepresentable", args->options.skip_unrepresentable,
      "Export the cameras the format holds exactly and skip the others (default: refuse)");
  command->add_flag("--overwrite", args->options.overwrite, "Write into a non-empty directory");
  command->add_option("--model", args->web.models,
                      "web: a trained volumetric model to stream (repeatable)");
  command->add_option("--recon", args->web.recon,
                      "web: the reconstruction's meshes (default TAKE/recon)");
  command->add_flag("--no-meshes", args->web.no_meshes, "web: no mesh stream");
  command->add_flag("--partial-model", args->web.partial_models,
                    "web: stream models whose training did not finish (their report.json says "
                    "FAILURE or DEGENERATE); refused without it");
  command
      ->add_option("--quality", args->qualities,
                   "web: quality levels, one stream each: low, medium, high, lossless")
      ->capture_default_str();
  command->add_option("--fps", args->web.fps,
                      "web: playback rate; images --video: the videos' rate (default: the take's)");
  command
      ->add_option("--format", args->images.format,
                   "images: jpg or png, one folder per camera, files named by frame set")
      ->capture_default_str();
  command->add_option("--video", args->video,
                      "images: mp4, one H.264 video per camera instead of image folders");
  command->add_option("--jpeg-quality", args->images.jpeg_quality, "images: JPEG quality 1..100")
      ->capture_default_str();
  command
      ->add_option("--crf", args->images.crf,
                   "images --video: H.264 constant rate factor (0 lossless .. 51)")
      ->capture_default_str();
  command
      ->add_option("--sensors", args->images.sensors,
                   "images: colour cameras to export, comma-separated (default: all)")
      ->delimiter(',');
  command->add_option("--key-every", args->web.key_every,
                      "web: a splat key frame at every multiple of it on the timeline "
                      "(default 10; 1: every frame a key frame); also the frames of a group, "
                      "the unit of --shard");
  command
      ->add_option("--splat-mbps", args->web.splat_mbps,
                   "web: a rate budget for every segment of the splat streams (a key frame "
                   "and its deltas, Mbps over its playing time): each segment at the finest "
                   "rung that fits (fewer bits, coarser motion, faint Gaussians pruned); "
                   "DEGENERATE where the coarsest does not; 0: the level's own; several "
                   "(4,8,16): a stream per level and budget, one ladder")
      ->delimiter(',');
  command->add_option("--frames", args->web.frames,
                      "web: only these frame sets of the meshes and models (a:b, or a list "
                      "0-9,15,20-29; counted after the clean plate)");
  command->add_option("--shard", args->web.shard,
                      "web: do task K of N of the export (K from 0): the K-th of N contiguous "
                      "blocks of its groups; the first task plans the site into SITE/plan, the "
                      "others read it; the manifest is written once every group is done "
                      "(holocap report SITE --merge)");
  command->add_flag("--redo", args->web.redo,
                    "web: write groups whose chunks are complete from an earlier run too");
  NameFieldFlags(command, {{"splat_key_every", "--key-every"},
                           {"splat_mbps", "--splat-mbps"},
                           {"qualities", "--quality"}});
  command->callback([args, command] {
    if (args->format == "images") {
      RunExportImages(*args, *command);
      return;
    }
    if (command->count("--format") + command->count("--video") + command->count("--jpeg-quality") +
            command->count("--crf") + command->count("--sensors") >
        0)
      Fail("--format, --video, --jpeg-quality, --crf and --sensors are options of export images");
    if (args->format == "web") {
      WebExportRequest request = args->web;
      request.take = args->take;
      request.out = args->out;
      request.ground_truth_cameras = args->options.ground_truth;
      request.overwrite = args->options.overwrite;
      std::stringstream list(args->qualities);
      for (std::string level; std::getline(list, level, ',');) request.qualities.push_back(level);
      // The export bakes volumes of any kind: holocap-neural runs it.
      if (!WebExportCommand()) HandOverToLibTorchProgram("holocap export web");
      WebExportCommand()(request);
      return;
    }
    if (!args->web.models.empty() || !args->web.recon.empty() || args->web.no_meshes ||
        !args->web.frames.empty() || !args->web.shard.empty() || args->web.redo ||
        args->web.partial_models)
      Fail(
          "--model, --recon, --no-meshes, --frames, --shard, --redo and --partial-model are "
          "options of export web only");
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
