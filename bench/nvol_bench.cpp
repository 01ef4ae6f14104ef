// Neural Volumes: held-out PSNR against training time on a simulated studio8 walking subject
// (and, with --dino, on Middlebury's dinoSparseRing as a static scene), then playback speed of
// the trained model at 512² with and without empty-space skipping. Prints tables; never
// passes or fails on time. Usage:
//   nvol_bench [--minutes 30] [--grid 64] [--frames 30] [--width 160] [--sim-width 320] [--rays
//   16384]
//              [--work /tmp/nvol-bench] [--dino] [--dino-only] [--dino-minutes 5]
//   nvol_bench --playback-only --model DIR [--work /tmp/nvol-bench]   (playback table of a trained
//   model)
#include <CLI/CLI.hpp>
#include <cstdio>
#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>
#include <string>

#include "avatar/image_metrics.h"
#include "bench/bench_data.h"
#include "bench/calibrated_sim.h"
#include "core/report.h"
#include "interop/interop.h"
#include "neural/neural.h"
#include "playback/playback.h"
#include "sim/sim.h"

namespace {

namespace fs = std::filesystem;
using namespace holocap;

void PrintSeries(const Report& report) {
  std::printf("%8s %7s %14s %14s %8s %10s\n", "t_s", "iter", "heldout_psnr", "subject_psnr", "ssim",
              "fog_alpha");
  const auto& series = report.json()["series"];
  for (size_t i = 0; i < series.size(); ++i) {
    if (series[i]["metric"] != "heldout_psnr_db") continue;
    double fg = 0, ssim = 0, fog = 0;
    for (size_t j = i + 1; j < series.size() && j < i + 4; ++j) {
      if (series[j]["metric"] == "heldout_psnr_fg_db") fg = series[j]["value"];
      if (series[j]["metric"] == "heldout_ssim") ssim = series[j]["value"];
      if (series[j]["metric"] == "heldout_alpha_outside") fog = series[j]["value"];
    }
    std::printf("%8.1f %7lld %11.2f dB %11.2f dB %8.4f %10.4f\n", series[i]["t_s"].get<double>(),
                static_cast<long long>(series[i]["iter"].get<int64_t>()),
                series[i]["value"].get<double>(), fg, ssim, fog);
  }
}

// The loss terms and drifts logged every 10 iterations, at about `rows` iterations.
void PrintTerms(const Report& report, int rows) {
  const char* names[] = {"loss",
                         "loss_alpha_prior",
                         "loss_tv",
                         "loss_silhouette",
                         "loss_kl",
                         "warp_voxels",
                         "train_alpha_inside",
                         "train_alpha_outside",
                         "gain_drift",
                         "bias_drift"};
  std::map<std::string, std::map<int64_t, double>> values;
  int64_t last = 0;
  for (const auto& point : report.json()["series"]) {
    const std::string metric = point["metric"];
    for (const char* name : names) {
      if (metric != name) continue;
      const int64_t iter = point["iter"].get<int64_t>();
      values[metric][iter] = point["value"].get<double>();
      last = std::max(last, iter);
    }
  }
  if (values["loss"].empty()) return;
  std::printf("%7s %10s %10s %10s %10s %10s %8s %8s %8s %8s %8s\n", "iter", "photo", "prior", "tv",
              "silhouette", "kl", "warp_vx", "a_in", "a_out", "gain_d", "bias_d");
  const int64_t stride = std::max<int64_t>(10, (last / rows + 9) / 10 * 10);
  for (const auto& [iter, photo] : values["loss"]) {
    if (iter % stride != 0 && iter != last) continue;
    auto at = [&](const char* name) {
      auto it = values[name].find(iter);
      return it == values[name].end() ? 0.0 : it->second;
    };
    std::printf("%7lld %10.5f %10.5f %10.6f %10.5f %10.3f %8.3f %8.3f %8.3f %8.3f %8.3f\n",
                static_cast<long long>(iter), photo, at("loss_alpha_prior"), at("loss_tv"),
                at("loss_silhouette"), at("loss_kl"), at("warp_voxels"), at("train_alpha_inside"),
                at("train_alpha_outside"), at("gain_drift"), at("bias_drift"));
  }
}

void PlaybackTable(const fs::path& model_dir, const fs::path& out) {
  auto model = OpenModel(model_dir);
  const int kViews = 24;
  std::printf("\nplayback of %s at 512x512, %d-view orbit (PNG writing excluded)\n",
              model_dir.c_str(), kViews);
  std::printf(
      "frame 0: decoded once before the orbit; sequence: frame i at view i, decoded (and baked) "
      "per view\n");
  std::printf("baked: bake_scale %.1f (the default)\n", ViewRenderOptions{}.bake_scale);
  std::printf("%-16s %-9s %-9s %8s %12s %9s\n", "sampling", "frames", "skipping", "fps",
              "samples/ray", "ms/view");
  struct Row {
    bool bake, sequence, skip;
  };
  const Row rows[] = {{true, false, true},  {true, false, false},  {true, true, true},
                      {false, false, true}, {false, false, false}, {false, true, true}};
  for (const Row& row : rows) {
    OrbitOptions orbit;
    orbit.views = kViews;
    orbit.width = 512;
    orbit.height = 512;
    orbit.advance_frames = row.sequence;
    CameraPath path = OrbitPath(*model, orbit);
    PlaybackOptions options;
    options.out = out / "frames";
    options.render.skip_empty = row.skip;
    options.render.bake = row.bake;
    options.write_frames = false;
    // The frame on show before the orbit starts: frame 0 for a fixed frame, the last one for a
    // sequence (so that its first view decodes too).
    model->Render(path.cameras[0], row.sequence ? model->frame_count() - 1 : 0, options.render);
    PlaybackSummary summary = RenderPath(*model, path, options);
    std::printf("%-16s %-9s %-9s %8.2f %12.1f %9.1f\n", row.bake ? "baked" : "warp+template",
                row.sequence ? "sequence" : "frame 0", row.skip ? "on" : "off", summary.render_fps,
                summary.samples_per_ray, 1000.0 / summary.render_fps);
  }
  // The baked grid against warp + template, on four views of the orbit (frame 0), for three
  // bake resolutions.
  OrbitOptions orbit;
  orbit.views = 4;
  orbit.width = 512;
  orbit.height = 512;
  orbit.advance_frames = false;
  const CameraPath path = OrbitPath(*model, orbit);
  ViewRenderOptions direct_options;
  direct_options.bake = false;
  std::vector<RenderedView> direct;
  for (size_t i = 0; i < path.size(); ++i)
    direct.push_back(model->Render(path.cameras[i], 0, direct_options));
  std::printf(
      "baked against warp+template, 4 views of frame 0 (colour and alpha where either covers):\n");
  std::printf("%-12s %10s %10s %16s\n", "bake_scale", "min PSNR", "max abs", "1st view ms (*)");
  for (double scale : {1.0, 1.5, 2.0}) {
    ViewRenderOptions options;
    options.bake_scale = scale;
    // Show another frame first, so that the first view at frame 0 decodes and bakes it again.
    if (model->frame_count() > 1) model->Render(path.cameras[0], model->frame_count() - 1, options);
    double worst_psnr = 1e9, worst_abs = 0, first_ms = 0;
    for (size_t i = 0; i < path.size(); ++i) {
      const RenderedView baked = model->Render(path.cameras[i], 0, options);
      if (i == 0) first_ms = 1000 * baked.seconds;  // a new bake resolution decodes and bakes again
      std::vector<cv::Mat> a = {baked.color, baked.alpha}, b = {direct[i].color, direct[i].alpha};
      cv::Mat rgba_baked, rgba_direct;
      cv::merge(a, rgba_baked);
      cv::merge(b, rgba_direct);
      const cv::Mat covered = (baked.alpha > 1.0 / 255) | (direct[i].alpha > 1.0 / 255);
      worst_psnr = std::min(worst_psnr, PsnrDb(rgba_baked, rgba_direct, covered));
      worst_abs = std::max(worst_abs, cv::norm(rgba_baked, rgba_direct, cv::NORM_INF));
    }
    std::printf("%-12.1f %7.1f dB %10.4f %16.0f\n", scale, worst_psnr, worst_abs, first_ms);
  }
  std::printf(
      "(*) the first view of frame 0 after another frame: decode, bake at that resolution, render "
      "(a one-frame model: render only)\n");
}

}  // namespace

int main(int argc, char** argv) {
  holocap::RegisterNeuralVolumeAvatarKind(holocap::AvatarKindRegistry::Global());
  CLI::App app{"Neural Volumes benchmark"};
  double minutes = 30, dino_minutes = 5;
  int grid = 64, frames = 30, width = 160, sim_width = 320, rays = 16384;
  NeuralVolumeOptions defaults;
  int latent = defaults.latent_dim, channels = defaults.decoder_channels,
      warp_grid = defaults.warp_grid;
  double lr = defaults.learning_rate, tv = defaults.tv_weight,
         template_lr = defaults.template_learning_rate;
  bool playback = true;
  std::string work = "/tmp/nvol-bench", take_option;
  bool dino = false, dino_only = false;
  std::string scene = "subject";
  app.add_option("--minutes", minutes, "Training budget of the dynamic take");
  app.add_option("--grid", grid, "RGBA grid side");
  app.add_option("--frames", frames, "Frame sets of the simulated take");
  app.add_option("--width", width, "Training image width");
  app.add_option(
      "--rays", rays,
      "Rays per batch of the dynamic take (the decoder, not the marcher, sets the step time)");
  app.add_option("--sim-width", sim_width, "Simulated image width");
  app.add_option("--work", work, "Working directory (takes and models are kept)");
  app.add_flag("--dino", dino, "Also train on Middlebury dinoSparseRing");
  app.add_flag("--dino-only", dino_only, "Only the dinoSparseRing case");
  app.add_option("--scene", scene, "Simulated scene: subject (dynamic) or object (static)");
  app.add_option("--dino-minutes", dino_minutes, "Training budget of dinoSparseRing");
  app.add_option("--take", take_option, "Train on this take instead of simulating one");
  app.add_option("--latent", latent, "Latent code size");
  app.add_option("--channels", channels, "Decoder channels after its first layer");
  app.add_option("--warp-grid", warp_grid, "Warp field voxels per axis");
  app.add_option("--lr", lr, "Adam learning rate of the networks");
  app.add_option("--tv", tv, "Total-variation weight of the grid");
  double kl = defaults.kl_weight;
  app.add_option("--kl", kl, "KL weight of the latent");
  app.add_option("--template-lr", template_lr,
                 "Adam learning rate of the template's residual grid");
  app.add_flag("!--no-playback", playback, "Skip the playback table");
  bool playback_only = false;
  std::string model_option;
  app.add_flag("--playback-only", playback_only,
               "Only the playback table of the model given by --model");
  app.add_option("--model", model_option, "Trained model directory (with --playback-only)");
  CLI11_PARSE(app, argc, argv);
  const fs::path root = work;
  fs::create_directories(root);
  if (playback_only) {
    if (model_option.empty()) {
      std::fprintf(stderr, "nvol_bench: --playback-only needs --model DIR\n");
      return 1;
    }
    try {
      PlaybackTable(model_option, root / "playback");
    } catch (const std::exception& e) {
      std::fprintf(stderr, "nvol_bench: %s\n", e.what());
      return 1;
    }
    return 0;
  }

  if (!dino_only) {
    if (scene == "object") frames = 1;
    const fs::path take = take_option.empty()
                              ? root / ("studio8-" + scene + "-" + std::to_string(frames) + "-" +
                                        std::to_string(sim_width))
                              : fs::path(take_option);
    if (!fs::exists(take / "take.json")) {
      SimOptions sim;
      sim.rig = "studio8";
      sim.frames = frames + 1;
      sim.scene = scene;
      sim.clean_plate_frames = 1;
      sim.image_width = sim_width;
      sim.overwrite = true;
      SimSummary s = SimulateTake(sim, take);
      std::printf("simulated %s: %lld frame sets in %.1f s; %s\n", take.c_str(),
                  static_cast<long long>(s.frame_sets), s.seconds,
                  bench::CalibrateFromBoardTake(sim, take).c_str());
    }
    NeuralVolumeOptions options;
    options.grid = grid;
    options.minutes = minutes;
    options.image_width = width;
    options.rays_per_batch = rays;
    options.latent_dim = latent;
    options.decoder_channels = channels;
    options.warp_grid = warp_grid;
    options.learning_rate = lr;
    options.tv_weight = tv;
    options.kl_weight = kl;
    options.template_learning_rate = template_lr;
    options.eval_every_s = std::max(10.0, minutes * 60 / 20);
    Report report("nvol_bench");
    const fs::path model = root / ("model-" + scene + "-grid" + std::to_string(grid));
    NeuralVolumeSummary summary = TrainNeuralVolume(take, model, options, &report);
    std::printf("\nstudio8 %s, %d frame(s), grid %d³, %dpx wide, 2 held-out cameras\n",
                scene == "object" ? "static object" : "walking subject", frames, grid, width);
    std::printf("plan: %s\n", summary.plan.dump().c_str());
    PrintSeries(report);
    PrintTerms(report, 20);
    std::printf("%s: %s\nloss %.5f -> %.5f, %lld iterations, %.1f samples/ray (skipping on)\n",
                ToString(summary.termination), summary.message.c_str(), summary.first_loss,
                summary.last_loss, static_cast<long long>(summary.iterations),
                summary.samples_per_ray);
    if (playback) PlaybackTable(model, root / "playback");
  }

  if (dino || dino_only) {
    const fs::path take = bench::ImportDinoOnce(root);
    NeuralVolumeOptions options;
    options.grid = grid;
    options.minutes = dino_minutes;
    options.image_width = 320;
    options.heldout_cameras = 1;
    options.eval_every_s = std::max(10.0, dino_minutes * 60 / 10);
    Report report("nvol_bench_dino");
    const fs::path model = root / "model-dino";
    NeuralVolumeSummary summary = TrainNeuralVolume(take, model, options, &report);
    std::printf("\ndinoSparseRing (static), 15 views trained, 1 held out, grid %d³, 320px wide\n",
                grid);
    std::printf("plan: %s\n", summary.plan.dump().c_str());
    PrintSeries(report);
    std::printf("%s: %s\n", ToString(summary.termination), summary.message.c_str());
  }
  return 0;
}
