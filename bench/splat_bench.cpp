// Splats against Neural Volumes doing the same work (the default): both from the same inputs in
// two rows (colour only: `--no-depth`, the splats seeded by the colour cameras' visual hull; and
// with the depth sensors: the splats seeded by TSDF fusion, Neural Volumes, which learn from
// colour alone, given the same take), each model a `holocap train` process of its own with the
// same budget of process CPU seconds (`--cpu-minutes`, enforced by the trainers, loading and
// seeding inside it), on a simulated studio8 walk whose cameras come from calibrating a
// simulated board take of the same rig and size, and on Middlebury dinoSparseRing (real, its
// own calibration). All runs start at once, so the machine's load falls on each alike; wait4
// accounts each process's CPU. Prints held-out PSNR against CPU seconds for every run and one
// table. With --playback MODEL: only that splat model's playback, the vectorised rasteriser
// against the scalar reference loop, interleaved. Never passes or fails on time. Usage:
//   splat_bench [--cpu-minutes 3] [--width 160] [--dino-width 320] [--size 640] [--frames 8]
//               [--holocap build/app/holocap] [--work /tmp/splat-bench]
//   splat_bench --playback /tmp/splat-bench-studio8/studio8-splat [--rounds 3]
#include <fcntl.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <exception>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <vector>

#include "avatar/avatar.h"
#include "bench/bench_data.h"
#include "core/error.h"
#include "playback/playback.h"
#include "splat/splat.h"

namespace {

namespace fs = std::filesystem;
using namespace holocap;

std::string Load() {
  std::ifstream file("/proc/loadavg");
  std::string a, b, c;
  file >> a >> b >> c;
  return a + " " + b + " " + c;
}

// CPU seconds (user + system, every thread) this process has used so far.
double CpuSeconds() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return usage.ru_utime.tv_sec + usage.ru_stime.tv_sec +
         1e-6 * (usage.ru_utime.tv_usec + usage.ru_stime.tv_usec);
}

// A 24-view orbit at 512x512 played: views per second of rendering and CPU seconds per view.
struct OrbitPlay {
  double fps = 0, cpu_s_per_view = 0;
};

// Plays a 24-view orbit at 512x512 of frame 0 (or the sequence played while turning with
// `sequence`; nothing written), after one view that loads and warms the model.
OrbitPlay PlayOrbit(AvatarModel& model, const fs::path& out, bool sequence) {
  OrbitOptions orbit;
  orbit.views = 24;
  orbit.advance_frames = sequence;
  const CameraPath path = OrbitPath(model, orbit);
  PlaybackOptions options;
  options.out = out;
  options.write_frames = false;
  model.Render(path.cameras[0], 0, options.render);
  const double cpu_start = CpuSeconds();
  const PlaybackSummary summary = RenderPath(model, path, options);
  return {summary.render_fps, (CpuSeconds() - cpu_start) / std::max<int64_t>(1, summary.views)};
}

// One `holocap train` run as a child process: its command line, model directory and log, and
// what the kernel accounted for it (CPU seconds of the whole process, user + system).
struct ChildRun {
  std::string data_set, row, method;
  std::vector<std::string> argv;
  fs::path out, log;
  pid_t pid = -1;
  int status = 0;
  double cpu_s = 0, wall_s = 0;
  std::chrono::steady_clock::time_point started;
};

std::string Joined(const std::vector<std::string>& words) {
  std::string text;
  for (const auto& word : words) text += (text.empty() ? "" : " ") + word;
  return text;
}

// Starts `run` (stdout and stderr into run.log) under `nice_level`.
void Start(ChildRun* run, int nice_level) {
  fs::remove_all(run->out);
  run->started = std::chrono::steady_clock::now();
  run->pid = fork();
  if (run->pid < 0) Fail("fork: ", std::strerror(errno));
  if (run->pid == 0) {
    const int fd = open(run->log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (fd >= 0) {
      dup2(fd, 1);
      dup2(fd, 2);
      close(fd);
    }
    if (nice_level != 0 && nice(nice_level) == -1 && errno != 0) _exit(126);
    std::vector<char*> args;
    for (auto& word : run->argv) args.push_back(word.data());
    args.push_back(nullptr);
    execv(args[0], args.data());
    _exit(127);
  }
}

// Waits for every run, each one's CPU seconds from wait4's accounting of that process alone.
void WaitAll(std::vector<ChildRun>* runs) {
  for (size_t left = runs->size(); left > 0; --left) {
    int status = 0;
    rusage usage{};
    const pid_t pid = wait4(-1, &status, 0, &usage);
    if (pid < 0) Fail("wait4: ", std::strerror(errno));
    for (ChildRun& run : *runs) {
      if (run.pid != pid) continue;
      run.status = status;
      run.cpu_s = usage.ru_utime.tv_sec + usage.ru_stime.tv_sec +
                  1e-6 * (usage.ru_utime.tv_usec + usage.ru_stime.tv_usec);
      run.wall_s =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - run.started).count();
      std::printf("done: %s %s %s: exit %d, %.1f CPU s, %.1f s wall, load %s\n",
                  run.data_set.c_str(), run.row.c_str(), run.method.c_str(),
                  WIFEXITED(status) ? WEXITSTATUS(status) : -1, run.cpu_s, run.wall_s,
                  Load().c_str());
      std::fflush(stdout);
    }
  }
}

// Runs a command to its end (preparing the data); throws when it fails.
void RunToEnd(const std::vector<std::string>& argv, const fs::path& log) {
  ChildRun run;
  run.argv = argv;
  run.log = log;
  std::printf("$ %s\n", Joined(argv).c_str());
  std::fflush(stdout);
  Start(&run, 0);
  std::vector<ChildRun> one{run};
  WaitAll(&one);
  if (!WIFEXITED(one[0].status) || WEXITSTATUS(one[0].status) != 0)
    Fail(Joined(argv), " failed; see ", log.string());
}

// Mean squared error of PSNRs averaged as the trainers average them (per image).
double MeanPsnr(const std::vector<double>& psnrs) {
  double mse = 0;
  for (double p : psnrs) mse += std::pow(10.0, -p / 10.0);
  return -10.0 * std::log10(mse / static_cast<double>(std::max<size_t>(1, psnrs.size())));
}

// Held-out PSNR against the run's CPU clock (seconds since it began, held-out scoring
// excluded) and its wall clock, as the run's report recorded it.
void PrintCpuSeries(const ChildRun& run, const nlohmann::json& report) {
  std::printf("\n%s, %s, %s: held-out PSNR against CPU seconds\n%8s %8s %7s %10s %10s  %s\n",
              run.data_set.c_str(), run.row.c_str(), run.method.c_str(), "cpu_s", "wall_s", "iter",
              "whole_dB", "subject_dB", "scored on");
  const auto& series = report["series"];
  const bool splat = run.method == "splats";
  for (size_t i = 0; i < series.size(); ++i) {
    if (series[i]["metric"] != "heldout_psnr_db") continue;
    double fg = 0, cpu = 0;
    int64_t frame = -1;  // a splat frame's final score (else a score during frame 0's training)
    for (size_t j = i + 1; j < series.size() && j < i + 6; ++j) {
      if (series[j]["metric"] == "heldout_psnr_db") break;
      if (series[j]["metric"] == "heldout_psnr_fg_db") fg = series[j]["value"];
      if (series[j]["metric"] == "cpu_s") cpu = series[j]["value"];
      if (series[j]["metric"] == "frame_heldout_psnr_db") frame = series[j]["iter"];
    }
    const std::string on = !splat      ? "the evaluated frames, all of them"
                           : frame < 0 ? "frame 0, while training"
                                       : Cat("frame ", frame, ", trained");
    std::printf("%8.1f %8.1f %7lld %10.2f %10.2f  %s\n", cpu, series[i]["t_s"].get<double>(),
                static_cast<long long>(series[i]["iter"].get<int64_t>()),
                series[i]["value"].get<double>(), fg, on.c_str());
  }
}

// Splats against Neural Volumes doing the same work: the same take, the same input sensors
// (row "colour": both --no-depth, the splats seeded by the colour cameras' visual hull; row
// "depth": the depth sensors allowed, the splats seeded by TSDF fusion), the same budget of
// process CPU seconds enforced by each trainer (--cpu-minutes: loading and seeding inside it),
// the same held-out cameras, frames and pixels. Every run is a `holocap train` process of its
// own, all started at once, so the machine's load falls on each alike; wait4 accounts each
// process's CPU seconds.
int RunEqualWork(const fs::path& root, const std::string& holocap, double cpu_minutes,
                 int studio8_width, int dino_width, int studio8_size, int frames, double eval_s,
                 int nice_level) {
  std::printf("equal work: %.2f CPU minutes per model per row, every run at once, nice %d\n",
              cpu_minutes, nice_level);
  std::printf("load at start: %s\n", Load().c_str());
  const fs::path cal = root / Cat("cal-", studio8_size);
  const fs::path walk = root / Cat("walk-", studio8_size, "-", frames);
  const std::string size = std::to_string(studio8_size);
  if (!fs::exists(cal / "calib" / "cam0.cameramodel")) {
    RunToEnd({holocap, "sim", "--rig", "studio8", "--board", "--frames", "60", "--size", size,
              "--out", cal.string(), "--overwrite"},
             root / "sim-cal.log");
    RunToEnd({holocap, "calibrate", cal.string()}, root / "calibrate.log");
  }
  if (!fs::exists(walk / "calib" / "cam0.cameramodel")) {
    RunToEnd({holocap, "sim", "--rig", "studio8", "--frames", std::to_string(frames + 1),
              "--clean-plate", "1", "--size", size, "--out", walk.string(), "--overwrite"},
             root / "sim-walk.log");
    // The walk's cameras are the board take's calibration, as a user's would be.
    fs::create_directories(walk / "calib");
    for (const auto& entry : fs::directory_iterator(cal / "calib")) {
      if (entry.path().extension() == ".cameramodel")
        fs::copy_file(entry.path(), walk / "calib" / entry.path().filename(),
                      fs::copy_options::overwrite_existing);
    }
  }
  const fs::path dino = bench::ImportDinoOnce(root);
  std::printf("studio8: %s (calib/ from %s), %d frames at %d px, trained at %d px\n", walk.c_str(),
              cal.c_str(), frames, studio8_size, studio8_width);
  std::printf("dinoSparseRing: %s (its own calibration), trained at %d px, 1 camera held out\n",
              dino.c_str(), dino_width);

  const std::string cpu = Cat(cpu_minutes);
  const std::string every = Cat(eval_s);
  std::vector<ChildRun> runs;
  auto add = [&](const std::string& data_set, const std::string& row, const std::string& method,
                 std::vector<std::string> argv) {
    ChildRun run;
    run.data_set = data_set;
    run.row = row;
    run.method = method;
    run.out = root / "runs" / Cat(data_set, "-", row, "-", method == "splats" ? "splat" : "nvol");
    run.log = run.out.string() + ".log";
    for (const std::string& word :
         {std::string("--out"), run.out.string(), std::string("--cpu-minutes"), cpu,
          std::string("--eval-every"), every, std::string("--overwrite")})
      argv.push_back(word);
    run.argv = std::move(argv);
    runs.push_back(std::move(run));
  };
  fs::create_directories(root / "runs");
  const std::string all_frames = std::to_string(frames);
  for (const bool depth : {false, true}) {
    const std::string row = depth ? "depth" : "colour";
    std::vector<std::string> nvol = {holocap,         "train",   "nvol",
                                     walk.string(),   "--width", Cat(studio8_width),
                                     "--eval-frames", all_frames};
    std::vector<std::string> splat = {holocap,       "train",   "splat",
                                      walk.string(), "--width", Cat(studio8_width)};
    if (!depth) {
      nvol.emplace_back("--no-depth");
      for (const char* word : {"--no-depth", "--seed-method", "hull"}) splat.emplace_back(word);
    }
    add("studio8", row, "Neural Volumes", nvol);
    add("studio8", row, "splats", splat);
  }
  // dinoSparseRing has no depth sensor: its colour row is its depth row.
  add("dino", "colour", "Neural Volumes",
      {holocap, "train", "nvol", dino.string(), "--width", Cat(dino_width), "--heldout", "1"});
  add("dino", "colour", "splats",
      {holocap, "train", "splat", dino.string(), "--width", Cat(dino_width), "--heldout", "1",
       "--seed-method", "hull"});
  for (ChildRun& run : runs) {
    std::printf("$ %s\n", Joined(run.argv).c_str());
    Start(&run, nice_level);
  }
  std::fflush(stdout);
  WaitAll(&runs);
  std::printf("load at the end: %s\n", Load().c_str());

  std::vector<std::string> lines;
  for (const ChildRun& run : runs) {
    std::ifstream file(run.out / "report.json");
    if (!file) {
      std::printf("%s %s %s: no report (see %s)\n", run.data_set.c_str(), run.row.c_str(),
                  run.method.c_str(), run.log.c_str());
      continue;
    }
    const nlohmann::json report = nlohmann::json::parse(file);
    PrintCpuSeries(run, report);
    const auto& m = report["metrics"];
    const bool splat = run.method == "splats";
    const double seed = m.value(splat ? "cpu_s_seed" : "cpu_s_loading", 0.0);
    const double training = m.value("cpu_s_training", 0.0);
    const double scoring = m.value("cpu_s_scoring", 0.0);
    double whole = m.value("heldout_psnr_db", 0.0), subject = m.value("heldout_psnr_fg_db", 0.0);
    if (splat && m.contains("frames") && m["frames"].size() > 1) {
      // Every frame, as Neural Volumes is scored (--eval-frames: all of them).
      std::vector<double> w, s;
      for (const auto& f : m["frames"]) {
        w.push_back(f.value("heldout_psnr_db", 0.0));
        s.push_back(f.value("heldout_psnr_fg_db", 0.0));
      }
      whole = MeanPsnr(w);
      subject = MeanPsnr(s);
    }
    lines.push_back(Cat(run.data_set, "|", run.row, "|", run.method, "|", seed, "|", training, "|",
                        seed + training, "|", run.cpu_s, "|", scoring, "|", whole, "|", subject,
                        "|", m.value("iterations", int64_t{0}), "|",
                        report["summary"].value("termination", std::string("?"))));
  }
  std::printf(
      "\nCPU seconds: seed = loading the take (+ the splats' seed reconstruction and colouring); "
      "training = the rest of the trainer's clock (held-out scoring excluded); budget clock = "
      "seed + training; process = wait4's user + system of the whole `holocap train` process "
      "(scoring, writing and start-up included). Held-out PSNR: every frame of the take, the "
      "same held-out cameras, the subject's silhouettes grown 3 px.\n");
  std::printf("%-8s %-7s %-15s %8s %9s %8s %9s %8s %9s %10s %8s %-15s\n", "data", "row", "method",
              "seed_s", "train_s", "clock_s", "process_s", "score_s", "whole_dB", "subject_dB",
              "iters", "ended");
  for (const std::string& line : lines) {
    std::vector<std::string> f;
    std::stringstream in(line);
    for (std::string item; std::getline(in, item, '|');) f.push_back(item);
    std::printf("%-8s %-7s %-15s %8.1f %9.1f %8.1f %9.1f %8.1f %9.2f %10.2f %8s %-15s\n",
                f[0].c_str(), f[1].c_str(), f[2].c_str(), std::stod(f[3]), std::stod(f[4]),
                std::stod(f[5]), std::stod(f[6]), std::stod(f[7]), std::stod(f[8]), std::stod(f[9]),
                f[10].c_str(), f[11].c_str());
  }
  std::printf("logs and reports: %s\n", (root / "runs").c_str());
  return 0;
}

// A trained splat model's playback with the vectorised rasteriser against the scalar reference
// loop, interleaved round by round (the load moves between runs): frame 0's orbit and the
// sequence's, fps and CPU seconds per view, the medians and the ratio of each round.
int RunPlayback(const fs::path& model_dir, const fs::path& root, int rounds) {
  const char* kKernels[] = {"vector", "scalar"};
  const char* kPaths[] = {"frame0", "sequence"};
  std::vector<double> fps[2][2], cpu[2][2], ratio[2];
  std::printf("playback of %s: 24-view orbit at 512x512, nothing written, %d rounds\n",
              model_dir.c_str(), rounds);
  std::printf("%6s %9s %7s %8s %12s %14s\n", "round", "path", "kernel", "fps", "cpu_s/view",
              "load");
  for (int round = 0; round < rounds; ++round) {
    for (int path = 0; path < 2; ++path) {
      double round_fps[2] = {0, 0};
      for (int kernel = 0; kernel < 2; ++kernel) {
        splat::RasterOptions options;
        options.vectorized = kernel == 0;
        auto model = OpenSplatModel(model_dir, options);
        const OrbitPlay play = PlayOrbit(*model, root / "play-splat", path == 1);
        fps[path][kernel].push_back(play.fps);
        cpu[path][kernel].push_back(play.cpu_s_per_view);
        round_fps[kernel] = play.fps;
        std::printf("%6d %9s %7s %8.2f %12.4f %14s\n", round, kPaths[path], kKernels[kernel],
                    play.fps, play.cpu_s_per_view, Load().c_str());
      }
      ratio[path].push_back(round_fps[0] / std::max(round_fps[1], 1e-9));
    }
  }
  auto median = [](std::vector<double> values) {
    std::sort(values.begin(), values.end());
    const size_t n = values.size();
    return n % 2 == 1 ? values[n / 2] : 0.5 * (values[n / 2 - 1] + values[n / 2]);
  };
  std::printf("\nmedians over %d rounds\n%9s %7s %8s %12s %16s %14s\n", rounds, "path", "kernel",
              "fps", "cpu_s/view", "fps_at_cpu_2", "vector/scalar");
  for (int path = 0; path < 2; ++path) {
    for (int kernel = 0; kernel < 2; ++kernel) {
      const double cpu_s = median(cpu[path][kernel]);
      // Views per second were the two cores this process's alone: CPU time spread over both.
      std::printf("%9s %7s %8.2f %12.4f %16.2f %14.2f\n", kPaths[path], kKernels[kernel],
                  median(fps[path][kernel]), cpu_s, 2 / std::max(cpu_s, 1e-9),
                  kernel == 0 ? median(ratio[path]) : 1.0);
    }
  }
  return 0;
}

int Main(int argc, char** argv) {
  CLI::App app("splats against Neural Volumes, the same inputs and CPU seconds");
  double cpu_minutes = 3;
  int width = 160, dino_width = 320, size = 640, frames = 8, nice_level = 5;
  double eval_s = 60;
  std::string work = "/tmp/splat-bench", holocap = "build/app/holocap";
  app.add_option("--cpu-minutes", cpu_minutes, "CPU budget of each model in each row")
      ->capture_default_str();
  app.add_option("--width", width, "Training and scoring width on studio8")->capture_default_str();
  app.add_option("--dino-width", dino_width, "Training and scoring width on dinoSparseRing")
      ->capture_default_str();
  app.add_option("--size", size, "Simulated width of the board take and the walk (studio8)")
      ->capture_default_str();
  app.add_option("--frames", frames, "Frames of the simulated walk (after its clean plate)")
      ->capture_default_str();
  app.add_option("--eval-every", eval_s, "Held-out scoring interval of both, wall seconds")
      ->capture_default_str();
  app.add_option("--nice", nice_level, "Niceness of the training processes")->capture_default_str();
  app.add_option("--holocap", holocap, "The holocap program")->capture_default_str();
  app.add_option("--work", work, "Working directory")->capture_default_str();
  std::string playback;
  int rounds = 3;
  app.add_option("--playback", playback,
                 "Only play this trained splat model, vectorised against scalar rasteriser");
  app.add_option("--rounds", rounds, "Interleaved rounds of --playback")->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  const fs::path root = fs::absolute(work);
  fs::create_directories(root);
  if (!playback.empty()) {
    holocap::RegisterSplatAvatarKind(holocap::AvatarKindRegistry::Global());
    return RunPlayback(playback, root, std::max(1, rounds));
  }
  return RunEqualWork(root, fs::absolute(holocap).string(), cpu_minutes, width, dino_width, size,
                      frames, eval_s, nice_level);
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return Main(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "splat_bench: error: %s\n", e.what());
  } catch (...) {
    std::fprintf(stderr, "splat_bench: error: an unknown exception\n");
  }
  return 1;
}
