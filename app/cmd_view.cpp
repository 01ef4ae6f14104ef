// holocap view SITE|TAKE [--port N]: serves a site of `holocap export web` on 127.0.0.1 (a take
// is exported to a temporary site first), and runs `holocap export web`.
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <optional>

#include "app/commands.h"
#include "app/options.h"
#include "core/error.h"
#include "core/report.h"
#include "neural/rerender.h"
#include "playback/playback.h"
#include "splat/splat.h"

namespace holocap {

#if HOLOCAP_WITH_NEURAL
namespace {

namespace fs = std::filesystem;

WebExportSummary ExportWeb(const WebExportRequest& request, Report* report) {
  WebExportOptions options;
  if (!request.qualities.empty()) options.qualities = request.qualities;
  options.recon = request.recon;
  options.meshes = !request.no_meshes;
  for (const auto& model : request.models) options.models.push_back(model);
  options.fps = request.fps;
  if (request.key_every != 0) options.splat_key_every = request.key_every;
  options.take.ground_truth_cameras = request.ground_truth_cameras;
  if (!request.frames.empty()) ParseFrames(request.frames, &options.take);
  options.overwrite = request.overwrite;
  if (!request.shard.empty()) options.tasks.shard = Shard::Parse(request.shard);
  options.tasks.redo = request.redo;
  return ExportWebSite(request.take, request.out, options, report);
}

void RunWebExport(const WebExportRequest& request) {
  Report report("export web");
  WebExportSummary summary = ExportWeb(request, &report);
  for (const auto& s : summary.streams) {
    std::printf(
        "  %-16s %3lld frames  %8.3f MB/frame  %7.2f Mbps  PSNR %5.1f dB against uncompressed\n",
        s.name.c_str(), static_cast<long long>(s.frames), s.mb_per_frame, s.mbps, s.psnr_db);
  }
  const Shard shard = request.shard.empty() ? Shard{} : Shard::Parse(request.shard);
  std::printf("%s: %s\nsite: %s\nreport: %s\n", ToString(summary.termination),
              summary.message.c_str(), request.out.c_str(),
              TaskReportPath(request.out, shard).c_str());
  if (std::filesystem::exists(fs::path(request.out) / "manifest.json"))
    std::printf("watch it: holocap view %s\n", request.out.c_str());
  std::fflush(stdout);
  FailUnlessUsable(summary, "export web");
}

const bool kWebExportRegistered = [] {
  WebExportCommand() = RunWebExport;
  // `holocap report SITE --merge`: the manifest once every group of a sharded export is done.
  RunMergers()["export web"] = [](const fs::path& site, Report* report) -> Summary {
    return MergeWebSite(site, report);
  };
  return true;
}();

// The demo's last stage: its meshes, Neural Volume and splats as a site (out/demo/site).
Summary ExportDemoSite(DemoContext& context) {
  WebExportRequest request;
  request.take = context.take.string();
  request.out = (context.out / "site").string();
  request.recon = (context.out / "recon").string();
  for (const char* model : {"nvol", "splat"})
    if (fs::is_regular_file(context.out / model / "model.json"))
      request.models.push_back((context.out / model).string());
  request.overwrite = true;
  Report report("export web");
  const WebExportSummary summary = ExportWeb(request, &report);
  nlohmann::json streams = nlohmann::json::object();
  for (const auto& s : summary.streams) streams[s.name] = s.ToJson();
  context.report->metrics()["web"] = {
      {"frames", summary.frames}, {"bytes", summary.bytes}, {"streams", streams}};
  std::printf("[demo] web: %s -> %s\n\n", summary.message.c_str(), request.out.c_str());
  return {summary.termination, summary.message};
}
HOLOCAP_DEMO_STAGE(60, "web", ExportDemoSite);

// A temporary site, removed when the command ends (served and stopped, or failed).
class TemporarySite {
 public:
  TemporarySite()
      : dir_(fs::temp_directory_path() / ("holocap-view-" + std::to_string(::getpid()))) {}
  ~TemporarySite() {
    std::error_code ignored;
    fs::remove_all(dir_, ignored);
  }
  const fs::path& dir() const { return dir_; }

 private:
  fs::path dir_;
};

struct ViewArgs {
  std::string input;
  int port = 8080;
  std::vector<std::string> models;
};

void FillViewCommand(CLI::App* command) {
  auto args = std::make_shared<ViewArgs>();
  command->add_option("SITE", args->input, "A site of `holocap export web`, or a take")->required();
  command->add_option("--port", args->port, "Port on 127.0.0.1 (0: any free one)")
      ->capture_default_str();
  command->add_option("--model", args->models,
                      "A take: the models to stream (default TAKE/models/nvol and "
                      "TAKE/models/splat when trained)");
  command->callback([args] {
    ViewServerOptions options;
    options.port = args->port;
    options.Check();
    fs::path site = args->input;
    std::optional<TemporarySite> temporary;
    if (fs::is_regular_file(site / "take.json")) {
      temporary.emplace();
      WebExportRequest request;
      request.take = args->input;
      request.out = temporary->dir().string();
      request.models = args->models;
      for (const char* model : {"nvol", "splat"})
        if (args->models.empty() && fs::is_regular_file(site / "models" / model / "model.json"))
          request.models.push_back((site / "models" / model).string());
      request.overwrite = true;
      Report report("export web");
      const WebExportSummary summary = ExportWeb(request, &report);
      FailUnlessUsable(summary, "export web");
      std::printf("exported %s to %s (%s; removed when the server stops)\n", args->input.c_str(),
                  temporary->dir().c_str(), summary.message.c_str());
      site = temporary->dir();
    }
    ServeSite(site, options, [](const std::string& url) {
      std::printf("serving on %s (Ctrl-C stops)\n", url.c_str());
      std::fflush(stdout);
    });
    std::printf("stopped\n");
  });
}

}  // namespace

#endif  // HOLOCAP_WITH_NEURAL

HOLOCAP_LIBTORCH_COMMAND(75, "view",
                         "Serve a site of export web (or a take, exported first) on 127.0.0.1",
                         FillViewCommand);

}  // namespace holocap
