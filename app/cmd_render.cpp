// holocap render TAKE --model DIR --path orbit|PATH.json --out DIR|file.mp4: free-viewpoint
// playback of any trained model (model.json names its kind); and, with --recon, `holocap live`'s
// compositions rerendered by a network trained on the scan take at the take's own cameras.
#include <cstdio>
#include <filesystem>
#include <optional>

#include "app/commands.h"
#include "app/options.h"
#include "avatar/model_training.h"
#include "core/error.h"
#include "core/report.h"
#include "neural/live_rerender.h"
#include "neural/neural.h"
#include "neural/rerender.h"
#include "playback/playback.h"
#include "splat/splat.h"

namespace holocap {

#if HOLOCAP_WITH_NEURAL
namespace {

struct RenderArgs {
  std::string take;
  std::string model;
  std::string path = "orbit";
  std::string out;
  int size = 512;
  int views = 60;
  int64_t frame = -1;
  bool no_skip = false;
  bool no_exr = false;
  bool overwrite = false;
  bool partial_model = false;
  double fps = 30;
  double step = 1.0;
  int threads = 0;
  std::string recon;
  std::vector<std::string> cameras;
  bool ground_truth_cameras = false;
};

// --recon: every composed frame at the named cameras of the take.
void RenderLiveCommand(const RenderArgs& args) {
  if (args.model.empty()) Fail("--recon needs --model (holocap train rerender SCAN_TAKE --scan)");
  const std::filesystem::path out(args.out);
  const OutputDirectory claimed =
      OutputDirectory::Claim(out, {"render", args.overwrite, {args.model, args.recon}});
  Report report("render");
  report.SetFailureDestination(out / "report.json");
  report.options() = {{"take", args.take},
                      {"model", args.model},
                      {"recon", args.recon},
                      {"cameras", args.cameras},
                      {"ground_truth_cameras", args.ground_truth_cameras},
                      {"out", args.out}};
  const LiveRenderSummary summary = RenderLiveRecon(args.take, args.recon, args.model, args.cameras,
                                                    out, args.ground_truth_cameras, &report);
  report.Write(out / "report.json");
  std::printf("%s\nimages (<camera>/<set>.png) and report: %s\n", summary.message.c_str(),
              out.c_str());
  EndCommand(summary, "rendering");
}

void FillRenderCommand(CLI::App* command) {
  auto args = std::make_shared<RenderArgs>();
  command
      ->add_option("TAKE", args->take,
                   "The take the model was trained on (default model: TAKE/models/nvol)")
      ->required();
  command->add_option("--model", args->model, "Model directory (holds model.json)");
  command->add_option("--path", args->path, "orbit, or a camera path JSON file")
      ->capture_default_str();
  command
      ->add_option("--size", args->size, "Output width and height of the orbit (JSON paths: width)")
      ->capture_default_str();
  command->add_option("--views", args->views, "Views of the orbit")->capture_default_str();
  command->add_option("--frame", args->frame, "Show only this frame (-1: play the sequence)")
      ->capture_default_str();
  command->add_option("--fps", args->fps, "Video frame rate")->capture_default_str();
  command->add_option("--step", args->step, "Ray-marching step in voxels")->capture_default_str();
  command->add_option("--threads", args->threads, "Threads (0: all cores)")->capture_default_str();
  command->add_option("--out", args->out, "A directory (PNG + EXR frames) or a file.mp4")
      ->required();
  AddOverwriteFlag(command, &args->overwrite);
  command->add_flag("--no-skip", args->no_skip, "Evaluate every sample (no empty-space skipping)");
  command->add_flag("--no-exr", args->no_exr, "Directory output: PNG frames only");
  command->add_flag("--partial-model", args->partial_model,
                    "Render a model whose training did not finish (its report.json says "
                    "FAILURE or DEGENERATE); refused without it");
  command->add_option("--recon", args->recon,
                      "Composed frames of `holocap live` (its recon/): rerender each at --cameras "
                      "with a model trained by `holocap train rerender SCAN_TAKE --scan SCAN`");
  command
      ->add_option("--cameras", args->cameras,
                   "With --recon: cameras of TAKE to render at (names, comma-separated)")
      ->delimiter(',');
  command->add_flag("--ground-truth-cameras", args->ground_truth_cameras,
                    "With --recon: a simulated take's true cameras (gt/cameras) instead of calib/");
  NameFieldFlags(command, {{"OrbitOptions::width", "--size"},
                           {"OrbitOptions::height", "--size"},
                           {"render.step_voxels", "--step"}});
  command->callback([args] {
    if (!args->recon.empty()) return RenderLiveCommand(*args);
    // Checked before anything is allocated: 8192 px square is 1 GiB of float RGBA per frame.
    if (args->size < 8 || args->size > 8192)
      Fail("--size ", args->size, " is outside 8..8192 pixels");
    if (args->views < 1 || args->views > 100000)
      Fail("--views ", args->views, " is outside 1..100000");
    const std::filesystem::path model_dir =
        args->model.empty() ? std::filesystem::path(args->take) / "models" / "nvol"
                            : std::filesystem::path(args->model);
    // Claimed before the model is read: a refused output costs nothing.
    const std::filesystem::path out(args->out);
    const bool to_video = out.extension() == ".mp4";
    OutputRequest request{"render", args->overwrite, {model_dir}};
    if (args->path != "orbit") request.inputs.push_back(args->path);
    TakeLock file_lock;
    std::optional<OutputDirectory> claimed;
    if (to_video) {
      file_lock = ClaimOutputFile(out, request);
      ClaimOutputFile(out.string() + ".report.json", request);
    } else {
      claimed = OutputDirectory::Claim(out, request);
    }
    const std::string partial =
        RequireFinishedModel(model_dir, args->partial_model, "--partial-model");
    if (!partial.empty()) std::printf("render: %s\n", partial.c_str());
    auto model = OpenModel(model_dir);
    CameraPath path;
    if (args->path == "orbit") {
      OrbitOptions orbit;
      orbit.views = args->views;
      orbit.width = args->size;
      orbit.height = args->size;
      orbit.fps = args->fps;
      orbit.advance_frames = args->frame < 0;
      orbit.frame = std::max<int64_t>(args->frame, 0);
      path = OrbitPath(*model, orbit);
    } else {
      // The training cameras' aspect; square for a model that names none.
      int height = args->size;
      if (!model->cameras().empty()) {
        const CameraModel& first = model->cameras().front();
        height =
            2 * static_cast<int>(std::lround(0.5 * args->size * first.height() / first.width()));
      }
      path = ReadCameraPath(args->path, *model, args->size, height);
      if (args->frame >= 0)
        for (auto& f : path.frames) f = args->frame;
    }
    PlaybackOptions options;
    options.out = args->out;
    options.exr = !args->no_exr;
    options.render.skip_empty = !args->no_skip;
    options.render.step_voxels = args->step;
    options.render.threads = args->threads;
    Report report("render");
    report.SetFailureDestination(to_video ? std::filesystem::path(out.string() + ".report.json")
                                          : out / "report.json");
    report.options() = {{"take", args->take},
                        {"model", model_dir.string()},
                        {"path", args->path},
                        {"size", args->size},
                        {"views", args->views},
                        {"frame", args->frame},
                        {"skip_empty", !args->no_skip},
                        {"step_voxels", args->step},
                        {"out", args->out},
                        {"partial_model", args->partial_model}};
    report.plan() = {{"method", model->method()},
                     {"model_frames", model->frame_count()},
                     {"views", path.size()}};
    if (!partial.empty()) report.plan()["partial_model"] = partial;
    PlaybackSummary summary = RenderPath(*model, path, options, &report);
    report.SetSummary(summary);
    const std::filesystem::path report_file =
        to_video ? std::filesystem::path(out.string() + ".report.json") : out / "report.json";
    // Beside a usable report when this run's is not (core/report.h): printed where it went.
    const std::filesystem::path written = report.Write(report_file);
    std::printf("%s model, %lld frame(s) -> %s\nreport: %s\n", model->method().c_str(),
                static_cast<long long>(model->frame_count()), out.c_str(), written.c_str());
    EndCommand(summary, "rendering");
  });
}

}  // namespace

#endif  // HOLOCAP_WITH_NEURAL

HOLOCAP_LIBTORCH_COMMAND(70, "render",
                         "Render a trained avatar along a camera path to frames or an MP4",
                         FillRenderCommand);

}  // namespace holocap
