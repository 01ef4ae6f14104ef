// Splats against Neural Volumes on Middlebury's dinoSparseRing (real, static): both trained in
// the same run for the same wall-clock budget at the same width with the same held-out camera
// (both read the take through neural/data.h's loader, which chooses it), their held-out PSNR
// against time, then native playback speed of each model at 512x512. Prints tables; never
// passes or fails on time. Usage:
//   splat_bench [--minutes 3] [--width 320] [--seed-points 20000] [--work /tmp/splat-bench]
#include <CLI/CLI.hpp>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>

#include "bench/bench_data.h"
#include "core/report.h"
#include "neural/neural.h"
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

// Views per second of a 24-view orbit at 512x512 (frame 0, nothing written), after one view
// that loads and warms the model.
double PlaybackFps(const fs::path& model_dir, const fs::path& out) {
  auto model = OpenModel(model_dir);
  OrbitOptions orbit;
  orbit.views = 24;
  orbit.advance_frames = false;
  const CameraPath path = OrbitPath(*model, orbit);
  PlaybackOptions options;
  options.out = out;
  options.write_frames = false;
  model->Render(path.cameras[0], 0, options.render);
  return RenderPath(*model, path, options).render_fps;
}

}  // namespace

int main(int argc, char** argv) {
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
  CLI11_PARSE(app, argc, argv);
  RegisterSplatModelKind();
  const fs::path root(work);
  fs::create_directories(root);
  const fs::path take = bench::ImportDinoOnce(root);
  std::printf("dinoSparseRing (static): 15 views trained, 1 held out, %d px wide, %.1f min each\n",
              width, minutes);

  NeuralVolumeOptions nvol;
  nvol.minutes = minutes;
  nvol.image_width = width;
  nvol.heldout_cameras = 1;
  nvol.eval_every_s = std::max(10.0, minutes * 60 / 10);
  std::printf("load before Neural Volumes: %s\n", Load().c_str());
  Report nvol_report("train nvol");
  fs::remove_all(root / "nvol");
  const NeuralVolumeSummary nvol_summary =
      TrainNeuralVolume(take, root / "nvol", nvol, &nvol_report);
  std::printf("nvol: %s\n", nvol_summary.message.c_str());

  SplatOptions splat;
  splat.minutes = minutes;
  splat.image_width = width;
  splat.heldout_cameras = 1;
  splat.max_seed_points = seed_points;
  splat.eval_every_s = nvol.eval_every_s;
  std::printf("load before splats: %s\n", Load().c_str());
  fs::remove_all(root / "splat");
  const auto seed_start = std::chrono::steady_clock::now();
  const SplatScene scene = LoadSplatScene(take, root / "splat", splat);
  const double seed_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - seed_start).count();
  Report splat_report("train splat");
  const SplatSummary splat_summary = TrainSplatsOn(scene, root / "splat", splat, &splat_report);
  std::printf("splat: %s\n", splat_summary.message.c_str());
  std::printf("load after training: %s\n", Load().c_str());

  PrintSeries("Neural Volumes", nvol_report);
  PrintSeries("splats", splat_report);
  const double nvol_fps = PlaybackFps(root / "nvol", root / "play-nvol");
  const double splat_fps = PlaybackFps(root / "splat", root / "play-splat");
  std::printf("load after playback: %s\n", Load().c_str());

  std::printf("\nheld-out camera: %s (both)\n",
              nvol_summary.plan.value("heldout", nlohmann::json::array()).dump().c_str());
  std::printf("%-16s %10s %10s %10s %8s %9s %10s %9s\n", "method", "iters", "whole_dB",
              "subject_dB", "ssim", "MB", "count", "fps_512");
  std::printf("%-16s %10lld %10.2f %10.2f %8.4f %9s %10s %9.2f\n", "Neural Volumes",
              static_cast<long long>(nvol_summary.iterations), nvol_summary.heldout_psnr_db,
              nvol_summary.heldout_psnr_fg_db, nvol_summary.heldout_ssim, "-", "64^3 grid",
              nvol_fps);
  std::printf("%-16s %10lld %10.2f %10.2f %8.4f %9.2f %10lld %9.2f\n", "splats",
              static_cast<long long>(splat_summary.iterations), splat_summary.heldout_psnr_db,
              splat_summary.heldout_psnr_fg_db, splat_summary.heldout_ssim, splat_summary.megabytes,
              static_cast<long long>(splat_summary.gaussians), splat_fps);
  std::printf("background alone inside the silhouette: %.2f dB (nvol), %.2f dB (splat)\n",
              nvol_summary.background_psnr_fg_db, splat_summary.background_psnr_fg_db);
  std::printf("splat seed: %s, %.1f s before training (reconstruction and colouring)\n",
              scene.seed.source.c_str(), seed_s);
  std::printf("subject gain of splats over Neural Volumes: %+.2f dB\n",
              splat_summary.heldout_psnr_fg_db - nvol_summary.heldout_psnr_fg_db);
  std::printf("reports: %s, %s\n", (root / "nvol" / "report.json").c_str(),
              (root / "splat" / "report.json").c_str());
  return 0;
}
