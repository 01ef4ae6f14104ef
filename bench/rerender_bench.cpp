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
  RegisterRerenderModelKind();
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
    RasterOptions raster;
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

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Neural rerendering benchmark"};
  double minutes = 10, dino_minutes = 5;
  int frames = 30, width = 160, sim_width = 320, threads = 2;
  RerenderOptions base;
  std::string work = "/tmp/rerender-bench";
  bool dino = false, dino_only = false;
  app.add_option("--minutes", minutes, "Training budget on studio8");
  app.add_option("--frames", frames, "Frame sets of the simulated take");
  app.add_option("--width", width, "Training image width");
  app.add_option("--sim-width", sim_width, "Simulated image width");
  app.add_option("--unet-width", base.net.width, "U-Net channels of the first level");
  app.add_option("--unet-depth", base.net.depth, "U-Net levels");
  app.add_option("--gan-weight", base.gan_weight, "PatchGAN weight (0: none)");
  app.add_option("--temporal-weight", base.temporal_weight, "Temporal-consistency weight");
  app.add_option("--crop", base.crop_px, "Training crop size near the subject (0: whole images)");
  app.add_option("--batch-pairs", base.batch_pairs, "Pairs of consecutive frames per step");
  app.add_option("--subject-weight", base.subject_weight, "Loss weight of pixels near the subject");
  app.add_option("--alpha-weight", base.alpha_weight,
                 "Weight of alpha against the witnesses' silhouettes (0: off)");
  app.add_option("--seed", base.seed, "Seed of the network's initial weights and of the batches");
  app.add_option("--lr", base.learning_rate,
                 "Adam learning rate (decayed to a tenth over the budget)");
  int train_threads = 0;
  app.add_option("--threads", threads,
                 "Threads for inference (and training unless --train-threads)");
  app.add_option("--train-threads", train_threads,
                 "Threads for reconstruction and training (0: --threads)");
  app.add_option("--work", work, "Working directory (takes and models are kept)");
  std::string model_name = "model-studio8";
  app.add_option("--model-name", model_name, "Model directory under --work for studio8");
  app.add_option("--recon", base.recon_dir,
                 "studio8: reuse this reconstruction (built without the same witnesses)");
  app.add_option("--supersample", base.supersample, "Raster samples per pixel along each axis");
  app.add_option("--witness-scales", base.witness_scales,
                 "Fractions of the training width the witnesses also train at")
      ->delimiter(',');
  app.add_option("--recon-voxel", base.reconstruction.voxel_m,
                 "studio8: reconstruction voxel in metres");
  std::string recon_method = "auto";
  app.add_option("--recon-method", recon_method,
                 "studio8: reconstruction method (auto, hull, tsdf, mvs)");
  bool no_completion = false;
  app.add_flag("--recon-no-completion", no_completion,
               "studio8: fuse the depth sensors alone (holes where they saw nothing), as a live "
               "fusion system does");
  app.add_option("--witness-folds", base.witness_folds,
                 "Witness sets, each with a reconstruction built without them");
  app.add_option("--witness-names", base.witness, "studio8: the first fold's witnesses (names)")
      ->delimiter(',');
  app.add_option("--heldout-names", base.heldout,
                 "studio8: the held-out cameras (names; default: one spread around the rig)")
      ->delimiter(',');
  app.add_option("--fold-witnesses", base.fold_witness,
                 "studio8: a further fold's witnesses, comma-separated (once per fold)")
      ->delimiter(',');
  app.add_option("--fold-recon", base.fold_recon_dirs,
                 "studio8: reuse these reconstructions of the further folds");
  app.add_option("--validation-witnesses", base.validation_witnesses,
                 "Witnesses that choose the weights (early stopping)");
  double eval_every = 0;
  app.add_option("--eval-every", eval_every,
                 "Seconds between evaluations (0: a fifth of the budget, at least 10)");
  app.add_flag("--dino", dino, "Also train on Middlebury dinoSparseRing");
  app.add_flag("--dino-only", dino_only, "Only the dinoSparseRing case");
  app.add_option("--dino-minutes", dino_minutes, "Training budget on dinoSparseRing");
  std::string inference_only;
  app.add_option("--inference-only", inference_only,
                 "Only time playback of this trained rerendering model at 512x512");
  CLI11_PARSE(app, argc, argv);
  std::setvbuf(stdout, nullptr, _IOLBF, 0);  // tables reach a redirected log as they are printed
  if (!inference_only.empty()) {
    try {
      InferenceTable(inference_only, threads);
    } catch (const std::exception& e) {
      std::fprintf(stderr, "error: %s\n", e.what());
      return 1;
    }
    return 0;
  }
  const fs::path root = work;
  fs::create_directories(root);
  base.threads = train_threads > 0 ? train_threads : threads;
  if (no_completion) base.reconstruction.tsdf_hull_completion = false;
  try {
    base.reconstruction.method = ReconstructionMethodFromString(recon_method);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  }
  if (!dino_only) {
    const fs::path take =
        root / ("studio8-" + std::to_string(frames) + "-" + std::to_string(sim_width));
    if (!fs::exists(take / "take.json")) {
      SimOptions sim;
      sim.rig = "studio8";
      sim.frames = frames + 1;
      sim.scene = "subject";
      sim.clean_plate_frames = 1;
      sim.image_width = sim_width;
      sim.overwrite = true;
      SimSummary s = SimulateTake(sim, take);
      std::printf("simulated %s: %lld frame sets in %.1f s\n", take.c_str(),
                  static_cast<long long>(s.frame_sets), s.seconds);
    }
    RerenderOptions options = base;
    options.minutes = minutes;
    options.image_width = width;
    options.eval_every_s =
        eval_every > 0 ? eval_every
                       : std::max(10.0, minutes * 60 / 5);  // an evaluation costs many steps
    Report report("rerender_bench");
    const fs::path model = root / model_name;
    RerenderSummary summary = TrainRerender(take, model, options, &report);
    std::printf("\nstudio8 walking subject, %d frame(s), %dpx wide, U-Net width %d depth %d\n",
                frames, width, options.net.width, options.net.depth);
    std::printf("plan: %s\n", summary.plan.dump().c_str());
    PrintSeries(report);
    PrintComparison(summary);
    InferenceTable(model, threads);
  }
  if (dino || dino_only) {
    const fs::path source =
        fs::path(HOLOCAP_TEST_DATA_DIR) / "middlebury" / "dinoSparseRing" / "dinoSR_par.txt";
    const fs::path take = root / "dino";
    if (!fs::exists(take / "take.json")) {
      ImportOptions import;
      import.format = InteropFormat::kMiddlebury;
      import.overwrite = true;
      ImportTake(source, take, import);
    }
    RerenderOptions options = base;
    options.minutes = dino_minutes;
    options.recon_dir.clear();
    options.fold_recon_dirs.clear();
    options.image_width = 320;
    options.witness_cameras = 4;
    options.heldout_cameras = 1;
    options.eval_every_s = eval_every > 0 ? eval_every : std::max(10.0, dino_minutes * 60 / 4);
    // The Middlebury recipe: a hull from thresholded silhouettes inside the README's box.
    ReconstructionOptions& r = options.reconstruction;
    r.method = ReconstructionMethod::kHull;
    r.voxel_m = 0.001;
    r.bounds.min = Eigen::Vector3d(-0.072, -0.029, -0.068);
    r.bounds.max = Eigen::Vector3d(0.021, 0.079, 0.026);
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
  return 0;
}
