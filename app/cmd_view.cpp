// holocap view SITE|TAKE [--port N] [--host NAME]: serves a site of `holocap export web` on
// 127.0.0.1 (a take is exported to a temporary site first), and runs `holocap export web`.
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/signalfd.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "app/commands.h"
#include "app/options.h"
#include "avatar/model_training.h"
#include "core/error.h"
#include "core/fs.h"
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
  options.splat_mbps = request.splat_mbps;
  options.take.ground_truth_cameras = request.ground_truth_cameras;
  if (!request.frames.empty()) ParseFrames(request.frames, &options.take);
  options.overwrite = request.overwrite;
  if (!request.shard.empty()) options.tasks.shard = Shard::Parse(request.shard);
  options.tasks.redo = request.redo;
  return ExportWebSite(request.take, request.out, options, report);
}

void RunWebExport(const WebExportRequest& request) {
  // Models whose training did not finish: refused, or (--partial-model) said here and in the
  // report.
  nlohmann::json partial = nlohmann::json::array();
  for (const auto& model : request.models) {
    const std::string note = RequireFinishedModel(model, request.partial_models, "--partial-model");
    if (note.empty()) continue;
    std::printf("export web: %s\n", note.c_str());
    partial.push_back(note);
  }
  Report report("export web");
  WebExportSummary summary = ExportWeb(request, &report);
  if (!partial.empty()) {
    report.options()["partial_models"] = true;
    report.plan()["partial_models"] = partial;
    const Shard shard = request.shard.empty() ? Shard{} : Shard::Parse(request.shard);
    report.Write(TaskReportPath(request.out, shard));
  }
  for (const auto& s : summary.streams) {
    std::printf(
        "  %-16s %3lld frames  %8.3f MB/frame  %7.2f Mbps (largest segment %7.2f, chunk %7.2f)  "
        "PSNR %5.1f dB against uncompressed\n",
        s.name.c_str(), static_cast<long long>(s.frames), s.mb_per_frame, s.mbps,
        s.max_segment_mbps, s.max_chunk_mbps, s.psnr_db);
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

// SIGINT and SIGTERM held pending from the start of the command to its end: blocked in its
// thread before it starts any other, so that every thread after (the server's) inherits the mask
// and none is ended by them. The export's wait reads them from a signalfd; ServeSite's watcher
// takes them while it serves. They stay blocked to the end, so that a second Ctrl-C cannot cut
// the removal of the temporary site short.
class StopSignals {
 public:
  StopSignals() {
    sigemptyset(&signals_);
    sigaddset(&signals_, SIGINT);
    sigaddset(&signals_, SIGTERM);
    pthread_sigmask(SIG_BLOCK, &signals_, nullptr);
    fd_ = ::signalfd(-1, &signals_, SFD_CLOEXEC | SFD_NONBLOCK);
    if (fd_ < 0) Fail("cannot wait for SIGINT and SIGTERM: ", std::strerror(errno));
  }
  ~StopSignals() { ::close(fd_); }
  StopSignals(const StopSignals&) = delete;
  StopSignals& operator=(const StopSignals&) = delete;

  int fd() const { return fd_; }
  // Takes a pending SIGINT or SIGTERM; false when none is pending.
  bool Take() const {
    signalfd_siginfo info{};
    return ::read(fd_, &info, sizeof(info)) == static_cast<ssize_t>(sizeof(info));
  }

 private:
  sigset_t signals_{};
  int fd_ = -1;
};

// A temporary site: a folder made for it alone (mkdtemp: never one that was there before, nor a
// link), the export writing into a fresh sub-folder `site`; removed with everything in it when
// the object dies (the command served and stopped, failed, or was stopped during the export).
class TemporarySite {
 public:
  TemporarySite() {
    std::string dir = (fs::temp_directory_path() / "holocap-view-XXXXXX").string();
    if (::mkdtemp(dir.data()) == nullptr)
      Fail("cannot make a temporary folder '", dir, "': ", std::strerror(errno));
    dir_ = dir;
  }
  ~TemporarySite() {
    std::error_code ignored;
    fs::remove_all(dir_, ignored);
  }
  TemporarySite(const TemporarySite&) = delete;
  TemporarySite& operator=(const TemporarySite&) = delete;

  fs::path site() const { return dir_ / "site"; }

 private:
  fs::path dir_;
};

// Runs this program as `holocap export web ARGUMENTS...` in a child process, so that SIGINT or
// SIGTERM can end the export at any moment: the child is killed and reaped, and nothing writes
// into the temporary site once this returns. The child's stdout is dropped; its stderr (progress)
// is passed on, but for its error line, which is thrown as this command's Error. Returns false
// when a stop signal came first.
bool ExportInChild(const std::vector<std::string>& arguments, const StopSignals& stop) {
  std::error_code error;
  std::string program = fs::read_symlink("/proc/self/exe", error).string();
  if (error) Fail("cannot find this program to export the take: ", error.message());
  std::vector<std::string> words = arguments;
  std::vector<char*> argv{program.data()};
  for (std::string& word : words) argv.push_back(word.data());
  argv.push_back(nullptr);
  int output[2];
  if (::pipe2(output, O_CLOEXEC) != 0) Fail("cannot start the export: ", std::strerror(errno));
  const int null_output = ::open("/dev/null", O_WRONLY | O_CLOEXEC);
  sigset_t none;
  sigemptyset(&none);
  const pid_t parent = ::getpid();
  std::fflush(nullptr);
  const pid_t child = ::fork();
  if (child == 0) {
    // Async-signal-safe calls only until exec. Killed when this process ends, however it ends.
    ::prctl(PR_SET_PDEATHSIG, SIGKILL);
    if (::getppid() != parent) ::_exit(1);
    sigprocmask(SIG_SETMASK, &none, nullptr);
    ::dup2(null_output, STDOUT_FILENO);
    ::dup2(output[1], STDERR_FILENO);
    ::execv(program.c_str(), argv.data());
    ::_exit(127);
  }
  ::close(output[1]);
  if (null_output >= 0) ::close(null_output);
  if (child < 0) {
    ::close(output[0]);
    Fail("cannot start the export: ", std::strerror(errno));
  }
  constexpr std::string_view kErrorPrefix = "holocap: error: ";
  std::string pending, error_line;
  const auto pass_on = [&](const std::string& line) {
    if (line.starts_with(kErrorPrefix)) {
      error_line = line.substr(kErrorPrefix.size());
      while (!error_line.empty() && error_line.back() == '\n') error_line.pop_back();
    } else {
      std::fputs(line.c_str(), stderr);
    }
  };
  bool stopped = false;
  pollfd polled[2] = {{output[0], POLLIN, 0}, {stop.fd(), POLLIN, 0}};
  while (true) {
    if (::poll(polled, 2, -1) < 0) {
      if (errno == EINTR) continue;
      break;
    }
    if (polled[1].revents != 0 && stop.Take()) {
      stopped = true;
      break;
    }
    if (polled[0].revents == 0) continue;
    char buffer[4096];
    const ssize_t read = ::read(output[0], buffer, sizeof(buffer));
    if (read <= 0) break;  // the child has ended
    pending.append(buffer, static_cast<size_t>(read));
    for (size_t end; (end = pending.find('\n')) != std::string::npos; pending.erase(0, end + 1))
      pass_on(pending.substr(0, end + 1));
  }
  ::close(output[0]);
  if (!pending.empty()) pass_on(pending + "\n");
  // A Ctrl-C on a terminal reaches the export too, which may end before the signal is seen here.
  stopped = stopped || stop.Take();
  if (stopped) ::kill(child, SIGKILL);
  int status = 0;
  while (::waitpid(child, &status, 0) < 0 && errno == EINTR) {
  }
  if (stopped) return false;
  if (WIFEXITED(status) && WEXITSTATUS(status) == 0) return true;
  if (!error_line.empty()) throw Error(error_line);
  Fail("export web ended ", WIFSIGNALED(status) ? Cat("by signal ", WTERMSIG(status))
                                                : Cat("with status ", WEXITSTATUS(status)));
}

struct ViewArgs {
  std::string input;
  int port = 8080;
  std::string host;
  std::vector<std::string> models;
  bool ground_truth_cameras = false;
};

void FillViewCommand(CLI::App* command) {
  auto args = std::make_shared<ViewArgs>();
  command->add_option("SITE", args->input, "A site of `holocap export web`, or a take")->required();
  command->add_option("--port", args->port, "Port on 127.0.0.1 (0: any free one)")
      ->capture_default_str();
  command->add_option("--host", args->host,
                      "One more Host header value to answer besides 127.0.0.1, localhost and "
                      "[::1], with or without the port (the name a browser reaches this machine "
                      "by, through an SSH tunnel or a proxy); the server still listens on "
                      "127.0.0.1 only");
  command->add_option("--model", args->models,
                      "A take: the models to stream (default TAKE/models/nvol and "
                      "TAKE/models/splat when trained)");
  command->add_flag("--ground-truth-cameras", args->ground_truth_cameras,
                    "A take: export it with a simulated take's true cameras (gt/cameras) instead "
                    "of calib/");
  NameFieldFlags(command, {{"ViewServerOptions::allowed_host", "--host"}});
  command->callback([args] {
    ViewServerOptions options;
    options.port = args->port;
    options.allowed_host = args->host;
    options.Check();
    const StopSignals stop;
    fs::path site = args->input;
    std::optional<TemporarySite> temporary;
    if (fs::is_regular_file(site / "take.json")) {
      temporary.emplace();
      std::vector<std::string> models = args->models;
      for (const char* model : {"nvol", "splat"})
        if (args->models.empty() && fs::is_regular_file(site / "models" / model / "model.json"))
          models.push_back((site / "models" / model).string());
      std::vector<std::string> arguments = {"export", "web", fs::absolute(site).string(), "--out",
                                            temporary->site().string()};
      for (const std::string& model : models) {
        arguments.emplace_back("--model");
        arguments.push_back(fs::absolute(model).string());
      }
      if (args->ground_truth_cameras) arguments.emplace_back("--ground-truth-cameras");
      if (!ExportInChild(arguments, stop)) {
        temporary.reset();
        std::puts("stopped during the export; the temporary site is removed");
        return;
      }
      site = temporary->site();
      const nlohmann::json report = nlohmann::json::parse(ReadFileToString(site / "report.json"));
      std::printf("exported %s to %s (%s; removed when the command ends)\n", args->input.c_str(),
                  site.c_str(), report.at("summary").value("message", "").c_str());
    }
    ServeSite(site, options, [](const std::string& url) {
      std::printf("serving on %s (Ctrl-C stops)\n", url.c_str());
      std::fflush(stdout);
    });
    const bool removed = temporary.has_value();
    temporary.reset();
    std::puts(removed ? "stopped; the temporary site is removed" : "stopped");
  });
}

}  // namespace

#endif  // HOLOCAP_WITH_NEURAL

HOLOCAP_LIBTORCH_COMMAND(75, "view",
                         "Serve a site of export web (or a take, exported first) on 127.0.0.1",
                         FillViewCommand);

}  // namespace holocap
