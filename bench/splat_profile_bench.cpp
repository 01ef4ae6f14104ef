// One splat training iteration by stage (projection, sort, binning, forward, loss and SSIM,
// backward, reduction, the gradient to the raw parameters, the densification statistic, Adam,
// densification): trains a few iterations of one scene at one size and prints the wall time of
// each stage per iteration, as `holocap train splat --profile` reports it (metrics.profile).
// Scenes: "synthetic" (a sphere of --gaussians Gaussians, 100k by default, seen by a ring of 16
// pinholes, seeded with one Gaussian per true one, so the count is known), "dino" (Middlebury
// dinoSparseRing, real, 16 views, native 640x480), "studio8" (the simulator's walk, frame 0,
// 8 cameras, its true cameras) and "object-ring" (the simulator's `--color-only --world-scale
// 0.05 --dark`: a 9 cm subject seen from 15 cm). Simulated takes are made once under --work at
// --sim-size and trained at --width. The model starts from the seed: the full degree-3 colour
// from the fourth iteration (sh_degree_every 1) and densification every 10 iterations
// (ten times the paper's rate, so that its cost shows in a short run; max_gaussians = the seed's
// count, so the count stays). Never passes or fails on time. Usage:
//   splat_profile_bench --scene synthetic|dino|studio8|object-ring [--width 640]
//                       [--iterations 20] [--threads 2] [--work /tmp/splat-profile]
//                       [--holocap build/app/holocap] [--sim-size 1280] [--gaussians 100000]
//                       [--pixel-budget 0]
#include <CLI/CLI.hpp>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <filesystem>
#include <fstream>
#include <random>
#include <string>

#include "bench/bench_data.h"
#include "core/error.h"
#include "core/pose.h"
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

// A pinhole of `width` x 3/4 width at `center` looking at the origin, z up.
CameraModel Ring(const Eigen::Vector3d& center, int width) {
  return CameraModel::Pinhole(0.9 * width, width, width * 3 / 4,
                              CamFromWorldLookAt(center, Eigen::Vector3d::Zero()));
}

// `count` opaque Gaussians on a sphere of 0.3 m (colour bands), 16 views 1.2 m away, the seed
// one point per Gaussian 5 mm off.
SplatScene Synthetic(int64_t count, int width) {
  std::mt19937_64 rng(7);
  std::normal_distribution<double> normal(0, 1);
  splat::Gaussians truth;
  truth.sh_degree = 0;
  truth.Resize(count);
  const double radius = 0.3;
  const double spacing = std::sqrt(4 * M_PI * radius * radius / static_cast<double>(count));
  SplatScene scene;
  for (int64_t i = 0; i < count; ++i) {
    Eigen::Vector3d p(normal(rng), normal(rng), normal(rng));
    p = radius * p.normalized();
    for (int a = 0; a < 3; ++a) {
      truth.position[3 * i + a] = static_cast<float>(p[a]);
      truth.log_scale[3 * i + a] = static_cast<float>(std::log(spacing));
      truth.sh[3 * i + a] =
          static_cast<float>(0.45 * std::copysign(1.0, std::sin(12 * p[(a + 1) % 3])) / 0.2820948);
    }
    truth.rotation[4 * i] = 1;
    truth.opacity[i] = 3;
    scene.seed.points.emplace_back(p.cast<float>() + 0.005f * Eigen::Vector3f::Random());
    scene.seed.colors.emplace_back(0.5f, 0.5f, 0.5f);
  }
  scene.seed.spacing_m = spacing;
  scene.seed.source = Cat("synthetic, ", count, " points");
  scene.box = Box{Eigen::Vector3d::Constant(-0.5), Eigen::Vector3d::Constant(0.5)};
  const int height = width * 3 / 4;
  const cv::Mat background(height, width, CV_32FC3, cv::Scalar(0.2, 0.25, 0.15));
  for (int c = 0; c < 16; ++c) {
    const double angle = 2 * M_PI * c / 16;
    SplatView view;
    view.name = Cat("cam", c);
    view.camera = Ring(
        Eigen::Vector3d(1.2 * std::cos(angle), 1.2 * std::sin(angle), 0.3 * std::sin(3 * angle)),
        width);
    const SplatRender render = RenderSplats(truth, view.camera, background, 0);
    render.color.convertTo(view.image, CV_8UC3, 255.0);
    background.convertTo(view.background, CV_8UC3, 255.0);
    view.mask = render.alpha > 0.5;
    view.heldout = c % 8 == 7;
    scene.views.push_back(view);
  }
  return scene;
}

// A simulated take under `work`, made once with `flags`.
fs::path SimulateOnce(const fs::path& work, const std::string& name, const std::string& holocap,
                      int size, const std::string& flags) {
  fs::path take = work / Cat(name, "-", size);
  if (fs::exists(take / "take.json")) return take;
  fs::create_directories(work);
  const std::string command =
      Cat(holocap, " sim --rig studio8 --frames 1 --size ", size, " ", flags, " --out ",
          take.string(), " --overwrite > ", (work / Cat(name, "-sim.log")).string(), " 2>&1");
  if (std::system(command.c_str()) != 0) Fail("'", command, "' failed");
  return take;
}

int Run(const std::string& name, int width, int64_t iterations, int threads, const fs::path& work,
        const std::string& holocap, int sim_size, int64_t gaussians, int64_t pixel_budget) {
  SplatOptions options;
  options.minutes = 0;
  options.iterations = iterations;
  options.threads = threads;
  options.image_width = width;
  options.sh_degree = 3;
  options.sh_degree_every = 1;
  options.densify_from = 10;
  options.densify_every = 10;
  options.opacity_reset_every = 0;
  options.eval_every_s = 1e9;  // scored once before the first iteration and at the end
  options.seed_method = "hull";
  options.heldout_cameras = 1;
  options.pixel_budget = pixel_budget;
  const fs::path model = work / "runs" / Cat(name, "-", width);
  fs::remove_all(model);
  SplatScene scene;
  if (name == "synthetic") {
    scene = Synthetic(gaussians, width);
  } else {
    fs::path take;
    if (name == "dino") {
      take = bench::ImportDinoOnce(work);
    } else if (name == "studio8") {
      take = SimulateOnce(work, name, holocap, sim_size, "");
      options.take.ground_truth_cameras = true;
    } else if (name == "object-ring") {
      take = SimulateOnce(work, name, holocap, sim_size, "--color-only --world-scale 0.05 --dark");
      options.take.ground_truth_cameras = true;
    } else {
      Fail("unknown scene '", name, "' (synthetic, dino, studio8, object-ring)");
    }
    scene = LoadSplatScene(take, model, options);
  }
  options.max_gaussians = static_cast<int64_t>(scene.seed.points.size());
  const cv::Size size = scene.views.front().image.size();
  const SplatSummary summary = TrainSplatsOn(scene, model, options);
  if (summary.profile.is_null()) Fail(name, ": ", summary.message);
  std::printf("%s %dx%d, %lld Gaussians, %d threads, load %s: %s", name.c_str(), size.width,
              size.height, static_cast<long long>(summary.gaussians), threads, Load().c_str(),
              FormatSplatProfile(summary.profile).c_str());
  // One line for tables: scene, size, Gaussians, it/s, then each stage's ms in order.
  std::printf("ROW %s %dx%d %lld %.3f", name.c_str(), size.width, size.height,
              static_cast<long long>(summary.gaussians),
              summary.profile.at("iterations_per_s").get<double>());
  for (const auto& row : summary.profile.at("stages"))
    std::printf(" %.1f", row.at("ms_per_iteration").get<double>());
  std::printf("\n");
  return 0;
}

int Main(int argc, char** argv) {
  CLI::App app("The wall time of one splat training iteration by stage");
  std::string scene = "synthetic", holocap = "build/app/holocap";
  std::string work = "/tmp/splat-profile";
  int width = 640, threads = 2, sim_size = 1280;
  int64_t iterations = 20, gaussians = 100000, pixel_budget = 0;
  app.add_option("--scene", scene, "synthetic, dino, studio8 or object-ring")
      ->capture_default_str();
  app.add_option("--width", width, "Training width (height 3/4 of it)")->capture_default_str();
  app.add_option("--iterations", iterations, "Iterations profiled")->capture_default_str();
  app.add_option("--threads", threads, "OpenMP threads")->capture_default_str();
  app.add_option("--work", work, "Where takes and models go")->capture_default_str();
  app.add_option("--holocap", holocap, "The holocap binary that simulates takes")
      ->capture_default_str();
  app.add_option("--sim-size", sim_size, "Width simulated takes are rendered at")
      ->capture_default_str();
  app.add_option("--gaussians", gaussians, "Gaussians of the synthetic scene")
      ->capture_default_str();
  app.add_option("--pixel-budget", pixel_budget,
                 "Pixels an iteration draws at the start (0: every iteration at --width; the "
                 "stages then compare size for size)")
      ->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  return Run(scene, width, iterations, threads, fs::absolute(work), holocap, sim_size, gaussians,
             pixel_budget);
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return Main(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "splat_profile_bench: error: %s\n", e.what());
  } catch (...) {
    std::fprintf(stderr, "splat_profile_bench: error: an unknown exception\n");
  }
  return 1;
}
