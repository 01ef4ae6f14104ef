// Splats against Neural Volumes on Middlebury's dinoSparseRing (real, static): both trained in
// the same run for the same wall-clock budget at the same width with the same held-out camera
// (both read the take through neural/data.h's loader, which chooses it), their held-out PSNR
// against time, then native playback speed of each model at 512x512. With --studio8-frames N:
// a simulated studio8 walking subject of N frames instead (a clean plate first), Neural Volumes
// (dynamic) trained for the same total wall time as the splats' frame 0 (--minutes) plus N - 1
// later frames (--frame-minutes each), both at --width with the same two held-out cameras; the
// splats' per-frame table (held-out PSNR, seconds, MB) and both models' sequence playback at
// 512x512 measured in the same run. With --playback MODEL: only that splat model's playback,
// the vectorised rasteriser against the scalar reference loop, interleaved. Prints tables; never
// passes or fails on time. Usage:
//   splat_bench [--minutes 3] [--width 320] [--seed-points 20000] [--work /tmp/splat-bench]
//   splat_bench --studio8-frames 4 --minutes 2 --frame-minutes 0.5 --width 160 [--sim-width 320]
//   splat_bench --playback /tmp/splat-bench-studio8/studio8-splat [--rounds 3]
#include <sys/resource.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "bench/bench_data.h"
#include "core/error.h"
#include "core/report.h"
#include "neural/neural.h"
#include "playback/playback.h"
#include "sim/sim.h"
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

// Held-out PSNR (whole, subject) against time, as both trainers log it.
void PrintSeries(const char* name, const Report& report) {
  std::printf("\n%s: held-out PSNR against training time\n%8s %7s %10s %10s %8s\n", name, "t_s",
              "iter", "whole_dB", "subject_dB", "ssim");
  const auto& series = report.json()["series"];
  for (size_t i = 0; i < series.size(); ++i) {
    if (series[i]["metric"] != "heldout_psnr_db") continue;
    double fg = 0, ssim = 0;
    for (size_t j = i + 1; j < series.size() && j < i + 4; ++j) {
      if (series[j]["metric"] == "heldout_psnr_fg_db") fg = series[j]["value"];
      if (series[j]["metric"] == "heldout_ssim") ssim = series[j]["value"];
    }
    std::printf("%8.1f %7lld %10.2f %10.2f %8.4f\n", series[i]["t_s"].get<double>(),
                static_cast<long long>(series[i]["iter"].get<int64_t>()),
                series[i]["value"].get<double>(), fg, ssim);
  }
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

// Views per second of a model directory's orbit, as `holocap render` plays it.
double PlaybackFps(const fs::path& model_dir, const fs::path& out, bool sequence = false) {
  auto model = OpenModel(model_dir);
  return PlayOrbit(*model, out, sequence).fps;
}

// Both methods trained on one take, one after the other, and what they reported.
struct BothRuns {
  Report nvol_report{"train nvol"}, splat_report{"train splat"};
  NeuralVolumeSummary nvol;
  SplatSummary splat;
  SplatScene scene;
  double seed_s = 0;  // the splats' seed: reconstruction and colouring, before training
};

// Neural Volumes into root/<prefix>nvol, then splats into root/<prefix>splat (their evaluation
// as often as Neural Volumes'), the machine's load noted before each and after both.
void TrainBoth(const fs::path& take, const fs::path& root, const std::string& prefix,
               const NeuralVolumeOptions& nvol, SplatOptions splat, BothRuns* runs) {
  std::printf("load before Neural Volumes: %s\n", Load().c_str());
  fs::remove_all(root / (prefix + "nvol"));
  runs->nvol = TrainNeuralVolume(take, root / (prefix + "nvol"), nvol, &runs->nvol_report);
  std::printf("nvol: %s\n", runs->nvol.message.c_str());
  splat.eval_every_s = nvol.eval_every_s;
  std::printf("load before splats: %s\n", Load().c_str());
  fs::remove_all(root / (prefix + "splat"));
  const auto seed_start = std::chrono::steady_clock::now();
  runs->scene = LoadSplatScene(take, root / (prefix + "splat"), splat);
  runs->seed_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - seed_start).count();
  runs->splat = TrainSplatsOn(runs->scene, root / (prefix + "splat"), splat, &runs->splat_report);
  std::printf("splat: %s\n", runs->splat.message.c_str());
  std::printf("load after training: %s\n", Load().c_str());
}

// Splats frame to frame against dynamic Neural Volumes on a simulated studio8 take.
int RunStudio8(const fs::path& root, int frames, double minutes, double frame_minutes, int width,
               int sim_width, int64_t seed_points) {
  const fs::path take = root / Cat("studio8-", frames, "-", sim_width);
  if (!fs::exists(take / "take.json")) {
    SimOptions sim;
    sim.frames = frames + 1;
    sim.clean_plate_frames = 1;
    sim.image_width = sim_width;
    sim.overwrite = true;
    const SimSummary simulated = SimulateTake(sim, take);
    std::printf("simulated %s: %lld frame sets in %.1f s\n", take.c_str(),
                static_cast<long long>(simulated.frame_sets), simulated.seconds);
  }
  const double total_minutes = minutes + (frames - 1) * frame_minutes;
  std::printf(
      "studio8 walking subject: %d frames (+ clean plate), %d px wide (simulated at %d), "
      "2 held-out cameras; splats %.2f min frame 0 + %.2f min per later frame, Neural "
      "Volumes (dynamic) %.2f min\n",
      frames, width, sim_width, minutes, frame_minutes, total_minutes);
  NeuralVolumeOptions nvol;
  nvol.minutes = total_minutes;
  nvol.image_width = width;
  nvol.eval_every_s = std::max(10.0, total_minutes * 60 / 10);
  SplatOptions splat;
  splat.minutes = minutes;
  splat.frame_minutes = frame_minutes;
  splat.image_width = width;
  splat.max_seed_points = seed_points;
  BothRuns runs;
  TrainBoth(take, root, "studio8-", nvol, splat, &runs);
  PrintSeries("Neural Volumes", runs.nvol_report);
  PrintSeries("splats (frames one after another)", runs.splat_report);
  std::printf("\nsplats per frame (scored on the held-out cameras as soon as trained)\n");
  std::printf("%6s %6s %7s %9s %10s %10s %10s %9s %8s %8s %10s %9s\n", "frame", "set", "iters",
              "seconds", "whole_dB", "subject_dB", "background", "MB", "added", "surface",
              "uncovered", "Gaussians");
  for (const SplatFrameSummary& f : runs.splat.frames) {
    std::printf("%6lld %6lld %7lld %9.1f %10.2f %10.2f %10.2f %9.3f %8lld %8lld %10lld %9lld\n",
                static_cast<long long>(f.frame), static_cast<long long>(f.set),
                static_cast<long long>(f.iterations), f.seconds, f.heldout_psnr_db,
                f.heldout_psnr_fg_db, f.background_psnr_fg_db, f.megabytes,
                static_cast<long long>(f.added), static_cast<long long>(f.added_surface),
                static_cast<long long>(f.surface_uncovered), static_cast<long long>(f.gaussians));
  }
  std::printf(
      "added: Gaussians the delta adds (at most --max-added-per-frame); surface: of them seeded on "
      "the frame's own reconstruction; uncovered: its surface samples farther than 3 spacings from "
      "every Gaussian of the frame before, before the frame's motion is learned\n");
  // Interleaved, twice each: the machine's load moves between runs.
  double nvol_fps = 0, splat_fps = 0;
  for (int round = 0; round < 2; ++round) {
    nvol_fps = std::max(nvol_fps, PlaybackFps(root / "studio8-nvol", root / "play-nvol", true));
    splat_fps = std::max(splat_fps, PlaybackFps(root / "studio8-splat", root / "play-splat", true));
  }
  std::printf("load after playback: %s\n", Load().c_str());
  std::printf("\nheld-out cameras: %s (both)\n",
              runs.nvol.plan.value("heldout", nlohmann::json::array()).dump().c_str());
  std::printf("%-22s %8s %10s %10s %8s %10s %13s\n", "method", "iters", "whole_dB", "subject_dB",
              "ssim", "MB/frame", "fps_512_seq");
  std::printf("%-22s %8lld %10.2f %10.2f %8.4f %10s %13.2f\n", "Neural Volumes (dyn)",
              static_cast<long long>(runs.nvol.iterations), runs.nvol.heldout_psnr_db,
              runs.nvol.heldout_psnr_fg_db, runs.nvol.heldout_ssim, "-", nvol_fps);
  double largest_mb = 0, later_s = 0;
  for (size_t f = 1; f < runs.splat.frames.size(); ++f) {
    largest_mb = std::max(largest_mb, runs.splat.frames[f].megabytes);
    later_s += runs.splat.frames[f].seconds;
  }
  std::printf("%-22s %8lld %10.2f %10.2f %8.4f %10.3f %13.2f\n", "splats (last frame)",
              static_cast<long long>(runs.splat.iterations), runs.splat.heldout_psnr_db,
              runs.splat.heldout_psnr_fg_db, runs.splat.heldout_ssim, largest_mb, splat_fps);
  std::printf(
      "Neural Volumes' scores are over its evaluated frames; the splats' are the last "
      "frame's (each frame's above). Splats after frame 0: %.1f s per frame, largest delta "
      "%.3f MB; frame 0 stored %.2f MB.\n",
      later_s / std::max<size_t>(1, runs.splat.frames.size() - 1), largest_mb,
      runs.splat.megabytes);
  std::printf("splat seed: %s, %.1f s before training (reconstruction of every frame, colouring)\n",
              runs.scene.seed.source.c_str(), runs.seed_s);
  std::printf("reports: %s, %s\n", (root / "studio8-nvol" / "report.json").c_str(),
              (root / "studio8-splat" / "report.json").c_str());
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

}  // namespace

int main(int argc, char** argv) {
  holocap::RegisterNeuralVolumeAvatarKind(holocap::AvatarKindRegistry::Global());
  holocap::RegisterSplatAvatarKind(holocap::AvatarKindRegistry::Global());
  CLI::App app("splats against Neural Volumes on dinoSparseRing");
  double minutes = 3;
  int width = 320;
  int64_t seed_points = 20000;
  std::string work = "/tmp/splat-bench";
  app.add_option("--minutes", minutes, "Training budget of each method")->capture_default_str();
  app.add_option("--width", width, "Training and evaluation width of both")->capture_default_str();
  app.add_option("--seed-points", seed_points, "Surface samples the splats start from")
      ->capture_default_str();
  app.add_option("--work", work, "Working directory")->capture_default_str();
  int studio8_frames = 0;
  double frame_minutes = 0.5;
  int sim_width = 320;
  app.add_option("--studio8-frames", studio8_frames,
                 "A simulated studio8 take of this many frames instead of dinoSparseRing");
  app.add_option("--frame-minutes", frame_minutes, "Splats' budget of each later frame (studio8)")
      ->capture_default_str();
  app.add_option("--sim-width", sim_width, "Simulated image width (studio8)")
      ->capture_default_str();
  std::string playback;
  int rounds = 3;
  app.add_option("--playback", playback,
                 "Only play this trained splat model, vectorised against scalar rasteriser");
  app.add_option("--rounds", rounds, "Interleaved rounds of --playback")->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  const fs::path root(work);
  fs::create_directories(root);
  if (!playback.empty()) return RunPlayback(playback, root, std::max(1, rounds));
  if (studio8_frames > 0) {
    return RunStudio8(root, studio8_frames, minutes, frame_minutes, width, sim_width, seed_points);
  }
  const fs::path take = bench::ImportDinoOnce(root);
  std::printf("dinoSparseRing (static): 15 views trained, 1 held out, %d px wide, %.1f min each\n",
              width, minutes);

  NeuralVolumeOptions nvol;
  nvol.minutes = minutes;
  nvol.image_width = width;
  nvol.heldout_cameras = 1;
  nvol.eval_every_s = std::max(10.0, minutes * 60 / 10);
  SplatOptions splat;
  splat.minutes = minutes;
  splat.image_width = width;
  splat.heldout_cameras = 1;
  splat.max_seed_points = seed_points;
  BothRuns runs;
  TrainBoth(take, root, "", nvol, splat, &runs);

  PrintSeries("Neural Volumes", runs.nvol_report);
  PrintSeries("splats", runs.splat_report);
  const double nvol_fps = PlaybackFps(root / "nvol", root / "play-nvol");
  const double splat_fps = PlaybackFps(root / "splat", root / "play-splat");
  std::printf("load after playback: %s\n", Load().c_str());

  std::printf("\nheld-out camera: %s (both)\n",
              runs.nvol.plan.value("heldout", nlohmann::json::array()).dump().c_str());
  std::printf("%-16s %10s %10s %10s %8s %9s %10s %9s\n", "method", "iters", "whole_dB",
              "subject_dB", "ssim", "MB", "count", "fps_512");
  std::printf("%-16s %10lld %10.2f %10.2f %8.4f %9s %10s %9.2f\n", "Neural Volumes",
              static_cast<long long>(runs.nvol.iterations), runs.nvol.heldout_psnr_db,
              runs.nvol.heldout_psnr_fg_db, runs.nvol.heldout_ssim, "-", "64^3 grid", nvol_fps);
  std::printf("%-16s %10lld %10.2f %10.2f %8.4f %9.2f %10lld %9.2f\n", "splats",
              static_cast<long long>(runs.splat.iterations), runs.splat.heldout_psnr_db,
              runs.splat.heldout_psnr_fg_db, runs.splat.heldout_ssim, runs.splat.megabytes,
              static_cast<long long>(runs.splat.gaussians), splat_fps);
  std::printf("background alone inside the silhouette: %.2f dB (nvol), %.2f dB (splat)\n",
              runs.nvol.background_psnr_fg_db, runs.splat.background_psnr_fg_db);
  std::printf("splat seed: %s, %.1f s before training (reconstruction and colouring)\n",
              runs.scene.seed.source.c_str(), runs.seed_s);
  std::printf("subject gain of splats over Neural Volumes: %+.2f dB\n",
              runs.splat.heldout_psnr_fg_db - runs.nvol.heldout_psnr_fg_db);
  std::printf("reports: %s, %s\n", (root / "nvol" / "report.json").c_str(),
              (root / "splat" / "report.json").c_str());
  return 0;
}
