// Neural rerendering: held-out PSNR/SSIM of the U-Net against the raw textured-mesh render and
// against training time, temporal flicker on a fixed held-out camera, on a simulated studio8
// walking subject and (with --dino) on Middlebury's dinoSparseRing; then inference time per
// 512² frame (rasterising and the network apart). Prints tables; never passes or fails on time.
// Usage:
//   rerender_bench [--minutes 10] [--frames 30] [--width 160] [--sim-width 320]
//                  [--unet-width 24] [--unet-depth 4] [--crop 64] [--batch-pairs 2] [--lr 3e-4]
//                  [--subject-weight 4] [--alpha-weight 1] [--seed 1] [--supersample 2]
//                  [--witness-scales 1]
//                  [--recon-voxel 0.004] [--recon-method auto] [--recon-no-completion]
//                  [--gan-weight 0] [--temporal-weight 8] [--threads 2] [--train-threads 0]
//                  [--work /tmp/rerender-bench] [--model-name model-studio8] [--recon DIR]
//                  [--witness-folds 3] [--witness-names A,B] [--fold-witnesses C,D ...]
//                  [--fold-recon DIR ...] [--validation-witnesses -1] [--eval-every S]
//                  [--dino] [--dino-only] [--dino-minutes 5]
//   rerender_bench --inference-only MODEL_DIR [--threads 2]
#include <CLI/CLI.hpp>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <string>

#include "bench/bench_data.h"
#include "bench/calibrated_sim.h"
#include "core/mesh.h"
#include "core/report.h"
#include "interop/interop.h"
#include "neural/rerender.h"
#include "playback/playback.h"
#include "sim/sim.h"

namespace {

namespace fs = std::filesystem;
using namespace holocap;

void PrintSeries(const Report& report) {
  // One row per evaluation: held-out PSNR and SSIM, and the validation witnesses' PSNR when
  // early stopping is on.
  std::map<int64_t, std::map<std::string, double>> rows;
  std::map<int64_t, double> time_of;
  const auto& series = report.json()["series"];
  for (const auto& point : series) {
    const std::string metric = point["metric"];
    if (metric != "heldout_psnr_db" && metric != "heldout_ssim" && metric != "validation_psnr_db")
      continue;
    const int64_t iter = point["iter"].get<int64_t>();
    rows[iter][metric] = point["value"].get<double>();
    if (!time_of.count(iter)) time_of[iter] = point["t_s"].get<double>();
  }
  std::printf("%8s %7s %14s %8s %16s\n", "t_s", "iter", "heldout_psnr", "ssim", "validation_psnr");
  for (const auto& [iter, row] : rows) {
    std::printf("%8.1f %7lld", time_of[iter], static_cast<long long>(iter));
    if (row.count("heldout_psnr_db")) {
      std::printf(" %11.2f dB %8.4f", row.at("heldout_psnr_db"),
                  row.count("heldout_ssim") ? row.at("heldout_ssim") : 0.0);
    } else {
      std::printf(" %14s %8s", "", "");
    }
    if (row.count("validation_psnr_db")) std::printf(" %13.2f dB", row.at("validation_psnr_db"));
    std::printf("\n");
  }
}

void PrintComparison(const RerenderSummary& s) {
  std::printf("\n%-22s %12s %12s %12s %10s\n", "held-out", "background", "raw render", "rerendered",
              "gain");
  std::printf("%-22s %9.2f dB %9.2f dB %9.2f dB %+7.2f dB\n", "PSNR (whole image)",
              s.background_psnr_db, s.raw_render_psnr_db, s.heldout_psnr_db,
              s.heldout_psnr_db - s.raw_render_psnr_db);
  std::printf("%-22s %9.2f dB %9.2f dB %9.2f dB %+7.2f dB\n", "PSNR (near subject)",
              s.background_psnr_subject_db, s.raw_render_psnr_subject_db, s.heldout_psnr_subject_db,
              s.heldout_psnr_subject_db - s.raw_render_psnr_subject_db);
  std::printf("%-22s %12.4f %12.4f %12.4f %+10.4f\n", "SSIM", s.background_ssim, s.raw_render_ssim,
              s.heldout_ssim, s.heldout_ssim - s.raw_render_ssim);
  std::printf("%-22s %12s %12.3f %12.3f\n", "flicker / truth's", "", s.raw_flicker_ratio,
              s.flicker_ratio);
  std::printf("%-22s %12s %12.4f %12.4f\n", "flicker excess", "", s.raw_flicker_excess,
              s.flicker_excess);
  std::printf("rerendered over background only: %+.2f dB whole, %+.2f dB near the subject\n",
              s.heldout_psnr_db - s.background_psnr_db,
              s.heldout_psnr_subject_db - s.background_psnr_subject_db);
  if (s.kept_iteration >= 0) {
    std::printf(
        "validation witnesses: raw render %.2f dB, best %.2f dB (%+.2f dB) at iteration %lld, "
        "whose weights are kept\n",
        s.validation_raw_psnr_db, s.validation_psnr_db,
        s.validation_psnr_db - s.validation_raw_psnr_db, static_cast<long long>(s.kept_iteration));
  }
  std::printf("%s: %s\nloss %.5f -> %.5f, %lld iterations in %.0f s\n", ToString(s.termination),
              s.message.c_str(), s.first_loss, s.last_loss, static_cast<long long>(s.iterations),
              s.seconds);
}

void InferenceTable(const fs::path& model_dir, int threads) {
  auto model = OpenModel(model_dir);
  const nlohmann::json json = nlohmann::json::parse(std::ifstream(model_dir / "model.json"));
  const RerenderNetwork network =
      RerenderNetwork::Load(model_dir / "unet.pt", UNetConfig::FromJson(json["net"]));
  fs::path mesh_file = json["meshes"][0].get<std::string>();
  if (mesh_file.is_relative()) mesh_file = model_dir / mesh_file;
  const Mesh mesh = ReadPly(mesh_file);
  OrbitOptions orbit;
  orbit.views = 8;
  orbit.width = 512;
  orbit.height = 512;
  orbit.advance_frames = false;
  const CameraPath path = OrbitPath(*model, orbit);
  std::printf(
      "\ninference at 512x512, %zu orbit views, U-Net width %d depth %d (%lld parameters), mesh "
      "%zu triangles, "
      "%d raster sample(s) per pixel\n",
      path.size(), network.config().width, network.config().depth,
      static_cast<long long>(network.parameter_count()), mesh.faces.size(),
      json.value("supersample", 1) * json.value("supersample", 1));
  std::printf("%8s %14s %14s %14s %8s\n", "threads", "rasterise ms", "U-Net ms", "total ms", "fps");
  for (int t : {1, threads}) {
    MeshRasterOptions raster;
    raster.threads = t;
    raster.supersample = json.value("supersample", 1);  // as playback does
    double raster_s = 0, net_s = 0;
    network.Apply(RasteriseMesh(mesh, path.cameras[0], raster), t);  // warm-up
    for (const CameraModel& camera : path.cameras) {
      auto t0 = std::chrono::steady_clock::now();
      GBuffer buffers = RasteriseMesh(mesh, camera, raster);
      auto t1 = std::chrono::steady_clock::now();
      network.Apply(buffers, t);
      auto t2 = std::chrono::steady_clock::now();
      raster_s += std::chrono::duration<double>(t1 - t0).count();
      net_s += std::chrono::duration<double>(t2 - t1).count();
    }
    const double n = static_cast<double>(path.size());
    std::printf("%8d %14.1f %14.1f %14.1f %8.2f\n", t, 1e3 * raster_s / n, 1e3 * net_s / n,
                1e3 * (raster_s + net_s) / n, n / (raster_s + net_s));
    if (t == threads) break;
  }
}

// The command line: the training options shared by both cases, and which cases to run.
struct BenchArgs {
  double minutes = 10, dino_minutes = 5;
  int frames = 30, width = 160, sim_width = 320, threads = 2, train_threads = 0;
  RerenderOptions base;
  std::string work = "/tmp/rerender-bench", model_name = "model-studio8";
  std::string recon_method = "auto", inference_only;
  bool dino = false, dino_only = false, no_completion = false;
  double eval_every = 0;
};

void AddFlags(CLI::App* app, BenchArgs& args) {
  app->add_option("--minutes", args.minutes, "Training budget on studio8");
  app->add_option("--frames", args.frames, "Frame sets of the simulated take");
  app->add_option("--width", args.width, "Training image width");
  app->add_option("--sim-width", args.sim_width, "Simulated image width");
  app->add_option("--unet-width", args.base.net.width, "U-Net channels of the first level");
  app->add_option("--unet-depth", args.base.net.depth, "U-Net levels");
  app->add_option("--gan-weight", args.base.gan_weight, "PatchGAN weight (0: none)");
  app->add_option("--temporal-weight", args.base.temporal_weight, "Temporal-consistency weight");
  app->add_option("--crop", args.base.crop_px,
                  "Training crop size near the subject (0: whole images)");
  app->add_option("--batch-pairs", args.base.batch_pairs, "Pairs of consecutive frames per step");
  app->add_option("--subject-weight", args.base.subject_weight,
                  "Loss weight of pixels near the subject");
  app->add_option("--alpha-weight", args.base.alpha_weight,
                  "Weight of alpha against the witnesses' silhouettes (0: off)");
  app->add_option("--seed", args.base.seed,
                  "Seed of the network's initial weights and of the batches");
  app->add_option("--lr", args.base.learning_rate,
                  "Adam learning rate (decayed to a tenth over the budget)");
  app->add_option("--threads", args.threads,
                  "Threads for inference (and training unless --train-threads)");
  app->add_option("--train-threads", args.train_threads,
                  "Threads for reconstruction and training (0: --threads)");
  app->add_option("--work", args.work, "Working directory (takes and models are kept)");
  app->add_option("--model-name", args.model_name, "Model directory under --work for studio8");
  app->add_option("--recon", args.base.recon_dir,
                  "studio8: reuse this reconstruction (built without the same witnesses)");
  app->add_option("--supersample", args.base.supersample,
                  "Raster samples per pixel along each axis");
  app->add_option("--witness-scales", args.base.witness_scales,
                  "Fractions of the training width the witnesses also train at")
      ->delimiter(',');
  app->add_option("--recon-voxel", args.base.reconstruction.voxel_m,
                  "studio8: reconstruction voxel in metres");
  app->add_option("--recon-method", args.recon_method,
                  "studio8: reconstruction method (auto, hull, tsdf, mvs)");
  app->add_flag("--recon-no-completion", args.no_completion,
                "studio8: fuse the depth sensors alone (holes where they saw nothing), as a live "
                "fusion system does");
  app->add_option("--witness-folds", args.base.witness_folds,
                  "Witness sets, each with a reconstruction built without them");
  app->add_option("--witness-names", args.base.witness,
                  "studio8: the first fold's witnesses (names)")
      ->delimiter(',');
  app->add_option("--heldout-names", args.base.heldout,
                  "studio8: the held-out cameras (names; default: one spread around the rig)")
      ->delimiter(',');
  app->add_option("--fold-witnesses", args.base.fold_witness,
                  "studio8: a further fold's witnesses, comma-separated (once per fold)")
      ->delimiter(',');
  app->add_option("--fold-recon", args.base.fold_recon_dirs,
                  "studio8: reuse these reconstructions of the further folds");
  app->add_option("--validation-witnesses", args.base.validation_witnesses,
                  "Witnesses that choose the weights (early stopping)");
  app->add_option("--eval-every", args.eval_every,
                  "Seconds between evaluations (0: a fifth of the budget, at least 10)");
  app->add_flag("--dino", args.dino, "Also train on Middlebury dinoSparseRing");
  app->add_flag("--dino-only", args.dino_only, "Only the dinoSparseRing case");
  app->add_option("--dino-minutes", args.dino_minutes, "Training budget on dinoSparseRing");
  app->add_option("--inference-only", args.inference_only,
                  "Only time playback of this trained rerendering model at 512x512");
}

// studio8: a simulated walking subject (simulated once and kept under --work).
void RunStudio8(const BenchArgs& args, const fs::path& root) {
  const fs::path take =
      root / ("studio8-" + std::to_string(args.frames) + "-" + std::to_string(args.sim_width));
  if (!fs::exists(take / "take.json")) {
    SimOptions sim;
    sim.rig = "studio8";
    sim.frames = args.frames + 1;
    sim.scene = "subject";
    sim.clean_plate_frames = 1;
    sim.image_width = args.sim_width;
    sim.overwrite = true;
    SimSummary s = SimulateTake(sim, take);
    std::printf("simulated %s: %lld frame sets in %.1f s; %s\n", take.c_str(),
                static_cast<long long>(s.frame_sets), s.seconds,
                bench::CalibrateFromBoardTake(sim, take).c_str());
  }
  RerenderOptions options = args.base;
  options.minutes = args.minutes;
  options.image_width = args.width;
  options.eval_every_s =
      args.eval_every > 0
          ? args.eval_every
          : std::max(10.0, args.minutes * 60 / 5);  // an evaluation costs many steps
  Report report("rerender_bench");
  const fs::path model = root / args.model_name;
  RerenderSummary summary = TrainRerender(take, model, options, &report);
  std::printf("\nstudio8 walking subject, %d frame(s), %dpx wide, U-Net width %d depth %d\n",
              args.frames, args.width, options.net.width, options.net.depth);
  std::printf("plan: %s\n", summary.plan.dump().c_str());
  PrintSeries(report);
  PrintComparison(summary);
  InferenceTable(model, args.threads);
}

// Middlebury dinoSparseRing: one frame of 16 views, the hull recipe of the README.
void RunDino(const BenchArgs& args, const fs::path& root) {
  const fs::path take = bench::ImportDinoOnce(root);
  RerenderOptions options = args.base;
  options.minutes = args.dino_minutes;
  options.recon_dir.clear();
  options.fold_recon_dirs.clear();
  options.image_width = 320;
  options.witness_cameras = 4;
  options.heldout_cameras = 1;
  options.eval_every_s =
      args.eval_every > 0 ? args.eval_every : std::max(10.0, args.dino_minutes * 60 / 4);
  // The Middlebury recipe: a hull from thresholded silhouettes inside the README's box.
  ReconstructionOptions& r = options.reconstruction;
  r.method = ReconstructionMethod::kHull;
  r.voxel_m = 0.001;
  r.bounds = Box{};
  r.bounds->min = Eigen::Vector3d(-0.072, -0.029, -0.068);
  r.bounds->max = Eigen::Vector3d(0.021, 0.079, 0.026);
  r.silhouette.mode = SilhouetteMode::kThreshold;
  r.silhouette.open_px = 0;
  r.silhouette.dilate_px = 10;
  r.silhouette.erode_px = 7;
  r.hull.min_views = 3;
  Report report("rerender_bench_dino");
  RerenderSummary summary = TrainRerender(take, root / "model-dino", options, &report);
  std::printf("\ndinoSparseRing (one frame), 320px wide, %s\n", summary.plan.dump().c_str());
  PrintSeries(report);
  PrintComparison(summary);
}

}  // namespace

int main(int argc, char** argv) {
  holocap::RegisterRerenderAvatarKind(holocap::AvatarKindRegistry::Global());
  CLI::App app{"Neural rerendering benchmark"};
  BenchArgs args;
  AddFlags(&app, args);
  CLI11_PARSE(app, argc, argv);
  std::setvbuf(stdout, nullptr, _IOLBF, 0);  // tables reach a redirected log as they are printed
  try {
    if (!args.inference_only.empty()) {
      InferenceTable(args.inference_only, args.threads);
      return 0;
    }
    args.base.threads = args.train_threads > 0 ? args.train_threads : args.threads;
    if (args.no_completion) args.base.reconstruction.tsdf_hull_completion = false;
    args.base.reconstruction.method = ReconstructionMethodFromString(args.recon_method);
    const fs::path root = args.work;
    fs::create_directories(root);
    if (!args.dino_only) RunStudio8(args, root);
    if (args.dino || args.dino_only) RunDino(args, root);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  }
  return 0;
}
