// The web stream per kind and quality level, scored against the camera: the page's picture
// (headless Chromium, SwiftShader) through a held-out capture camera, the stream's background
// behind the subject as a viewer sees it, against that camera's captured image inside the
// subject's true silhouette (avatar/camera_score.h), beside the native render's score on the same
// pixels (Neural Volumes and splats: `holocap render`'s renderer on the model; meshes: the
// reconstruction's own glTF rasterised natively; each over the same background), the background
// alone's, and the loss (native minus page). Also MB per frame, Mbps at 30 fps, the export's own
// figures (report.json: decoded against uncompressed, and its own score against the camera),
// time to first frame on loopback and frames decoded per second in the page.
//
//   bench/web_bench [FRAMES] [SIZE] [ITERATIONS] [VOXEL] [DIR] [SPLAT_ITERATIONS]
//     FRAMES      frame sets of the studio8 walk (10), after one clean plate
//     SIZE        the simulated cameras' size: a width (320; the sensors' own aspect ratio) or
//                 WIDTHxHEIGHT (e.g. 640x480: the sensor's centre at that size)
//     ITERATIONS  Neural Volumes training iterations (300)
//     VOXEL       the reconstruction's voxel (8mm)
//     DIR         work folder (default a new one under $TMP); a take, reconstruction and models
//                 already in it (DIR/take with recon/, DIR/nvol, DIR/splat) are used as they are
//     SPLAT_ITERATIONS  splat training iterations of frame 0 (1000; a tenth for each later
//                 frame), seeded from the take's reconstruction
//     SPLAT_MBPS  the splats exported again alone at `low` with `--splat-mbps SPLAT_MBPS` (10;
//                 0: not), served as a site of their own and measured the same way (the row
//                 splat-low@SPLAT_MBPS)
// Camera cam1 is held out of the reconstruction and the training: the scores are measured in it,
// at the middle frame of the timeline. The take is calibrated as a user's is: a board take of the
// rig (DIR/board, 48 frame sets at 640 px, or at SIZE where it is cropped) is solved and its models
// taken over
// (`calibrate TAKE --from DIR/board`); every stage, the page and the native renders use them,
// and the truth only scores (the subject's true silhouette).
// Needs chromium and tests/playback/browser/node_modules (scripts/setup.sh --tests).
#include <signal.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <exception>
#include <fstream>
#include <functional>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <string>

#include "avatar/camera_score.h"
#include "core/fs.h"
#include "core/take.h"
#include "neural/neural.h"
#include "playback/playback.h"
#include "splat/splat.h"

namespace fs = std::filesystem;
using namespace holocap;

namespace {

std::string Run(const std::string& command) {
  std::string output;
  FILE* pipe = popen((command + " 2>&1").c_str(), "r");
  char buffer[4096];
  while (pipe != nullptr && fgets(buffer, sizeof(buffer), pipe) != nullptr) output += buffer;
  const int status = pipe != nullptr ? pclose(pipe) : -1;
  if (status != 0) {
    std::fprintf(stderr, "web_bench: '%s' failed:\n%s\n", command.c_str(), output.c_str());
    std::exit(1);
  }
  return output;
}

CameraModel PinholeOf(const nlohmann::json& camera) {
  const auto& m = camera.at("cam_from_world");
  Pose pose = Pose::Identity();
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) pose.matrix()(r, c) = m.at(4 * r + c).get<double>();
  return CameraModel("LENSMODEL_PINHOLE", camera.at("pinhole").get<std::vector<double>>(),
                     camera.at("width"), camera.at("height"), pose);
}

// What the bench streams, made with the CLI unless DIR already holds it: the take, its
// calibration from a board take of the rig, the reconstruction and both models, each without the
// held-out camera.
struct BenchInputs {
  int frames;
  std::string size;  // --size of `holocap sim`
  int iterations;
  std::string voxel;
  int splat_iterations;
  fs::path dir;
  std::string heldout;
  std::string q;  // the CLI's command prefix
};

void MakeInputs(const BenchInputs& in, const std::function<double()>& elapsed) {
  const fs::path& dir = in.dir;
  const std::string& q = in.q;
  const std::string& heldout = in.heldout;
  const std::string& voxel = in.voxel;
  const int frames = in.frames, iterations = in.iterations;
  const int splat_iterations = in.splat_iterations;
  if (!fs::exists(dir / "take" / "take.json")) {
    Run(q + "sim --rig studio8 --frames " + std::to_string(frames + 1) +
        " --clean-plate 1 --size " + in.size + " --seed 3 --out '" + (dir / "take").string() + "'");
    std::printf("# simulated %d frame sets at %s px (%.0f s)\n", frames, in.size.c_str(),
                elapsed());
  }
  if (!fs::exists(dir / "take" / "calib" / "report.json")) {
    if (!fs::exists(dir / "board" / "calib" / "report.json")) {
      // A cropped size (WIDTHxHEIGHT) is another imager: its board take is filmed at that size.
      const std::string board_size =
          in.size.find('x') == std::string::npos ? std::string("640") : in.size;
      Run(q + "sim --rig studio8 --board --frames 48 --size " + board_size + " --seed 3 --out '" +
          (dir / "board").string() + "'");
      Run(q + "calibrate '" + (dir / "board").string() + "' --no-pictures");
    }
    Run(q + "calibrate '" + (dir / "take").string() + "' --from '" + (dir / "board").string() +
        "'");
    std::printf("# calibrated from a board take of the rig (%.0f s)\n", elapsed());
  }
  if (!fs::is_directory(dir / "take" / "recon")) {
    Run(q + "reconstruct '" + (dir / "take").string() + "' --voxel " + voxel +
        " --no-sweep --heldout-names " + heldout);
    std::printf("# reconstructed at %s without %s (%.0f s)\n", voxel.c_str(), heldout.c_str(),
                elapsed());
  }
  if (!fs::exists(dir / "nvol" / "model.json")) {
    Run(q + "train nvol '" + (dir / "take").string() + "' --out '" + (dir / "nvol").string() +
        "' --iterations " + std::to_string(iterations) + " --heldout-names " + heldout +
        " --eval-every 100000 || true");
    std::printf("# Neural Volumes: %d iterations without %s (%.0f s)\n", iterations,
                heldout.c_str(), elapsed());
  }
  if (!fs::exists(dir / "splat" / "model.json")) {
    Run(q + "train splat '" + (dir / "take").string() + "' --out '" + (dir / "splat").string() +
        "' --recon '" + (dir / "take" / "recon").string() + "' --iterations " +
        std::to_string(splat_iterations) + " --frame-iterations " +
        std::to_string(std::max(1, splat_iterations / 10)) +
        " --minutes 1000 --frame-minutes 1000 --heldout-names " + heldout +
        " --eval-every 100000 || true");
    std::printf("# splats: %d iterations (then %d a frame) without %s (%.0f s)\n", splat_iterations,
                std::max(1, splat_iterations / 10), heldout.c_str(), elapsed());
  }
}

// A site served on any free port, its streams timed and shot in the page: its manifest, the
// page's figures (bench.json) and the export's report.
struct PageRun {
  nlohmann::json manifest, bench, report;
};
PageRun MeasureInPage(const fs::path& dir, const std::string& site, const std::string& q,
                      const fs::path& driver, const CameraModel& camera, int frame,
                      int camera_index) {
  PageRun run;
  const fs::path browser = dir / (site == "site" ? "browser" : "browser-budget");
  const fs::path log_file = dir / (site + "-view.log");
  fs::remove(log_file);
  const std::string pid = Run("(" + q + "view '" + (dir / site).string() + "' --port 0 > '" +
                              log_file.string() + "' 2>&1 & echo $!)");
  std::string url;
  for (int i = 0; i < 100 && url.empty(); ++i) {
    usleep(100000);
    const std::string log = fs::exists(log_file) ? ReadFileToString(log_file) : "";
    const auto at = log.find("http://");
    if (at != std::string::npos) url = log.substr(at, log.find(' ', at) - at);
  }
  run.manifest = nlohmann::json::parse(ReadFileToString(dir / site / "manifest.json"));
  std::string list;
  for (const auto& s : run.manifest.at("streams")) {
    list += ' ';
    list += s.at("name").get<std::string>();
  }
  fs::create_directories(browser);
  // node drive.mjs MODE URL BROWSER [VIEW] STREAM...
  auto drive = [&](const std::string& mode, const std::string& view) {
    std::string command = "node '";
    command += driver.string();
    command += "' ";
    command += mode;
    command += " ";
    command += url;
    command += " '";
    command += browser.string();
    command += "' ";
    command += view;
    command += list;
    Run(command);
  };
  drive("bench", "");
  drive("camera", std::to_string(camera.width()) + " " + std::to_string(camera.height()) + " " +
                      std::to_string(frame) + " " + std::to_string(camera_index));
  kill(std::stoi(pid), SIGTERM);
  run.bench = nlohmann::json::parse(ReadFileToString(browser / "bench.json"));
  run.report = nlohmann::json::parse(ReadFileToString(dir / site / "report.json"));
  return run;
}

int RunBench(int argc, char** argv) {
  holocap::RegisterNeuralVolumeAvatarKind(holocap::AvatarKindRegistry::Global());
  holocap::RegisterSplatAvatarKind(holocap::AvatarKindRegistry::Global());
  const int frames = argc > 1 ? std::atoi(argv[1]) : 10;
  const std::string size = argc > 2 ? argv[2] : "320";
  const int iterations = argc > 3 ? std::atoi(argv[3]) : 300;
  const std::string voxel = argc > 4 ? argv[4] : "8mm";
  const int splat_iterations = argc > 6 ? std::atoi(argv[6]) : 1000;
  const fs::path cli = HOLOCAP_BENCH_CLI;
  const fs::path driver = fs::path(HOLOCAP_BENCH_SOURCE_DIR) / "tests/playback/browser/drive.mjs";
  const fs::path dir =
      argc > 5 ? fs::path(argv[5])
               : fs::temp_directory_path() / ("holocap-web-bench-" + std::to_string(getpid()));
  const std::string heldout = "cam1";
  fs::create_directories(dir);
  const std::string q = "HOLOCAP_NO_PROGRESS=1 '" + cli.string() + "' ";
  const auto start = std::chrono::steady_clock::now();
  auto elapsed = [&] {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  };
  MakeInputs({frames, size, iterations, voxel, splat_iterations, dir, heldout, q}, elapsed);
  fs::remove_all(dir / "site");
  const std::string export_output =
      Run(q + "export web '" + (dir / "take").string() + "' --model '" + (dir / "nvol").string() +
          "' --model '" + (dir / "splat").string() +
          "' --quality low,medium,high,lossless --fps 30 --out '" + (dir / "site").string() + "'");
  std::printf("# exported (%.0f s)\n%s", elapsed(), export_output.c_str());
  const double splat_mbps = argc > 7 ? std::atof(argv[7]) : 10;
  std::vector<std::string> sites = {"site"};
  if (splat_mbps > 0) {
    fs::remove_all(dir / "site-budget");
    char budget[32];
    std::snprintf(budget, sizeof(budget), "%g", splat_mbps);
    const std::string budget_output =
        Run(q + "export web '" + (dir / "take").string() + "' --no-meshes --model '" +
            (dir / "splat").string() + "' --quality low --splat-mbps " + budget +
            " --fps 30 --out '" + (dir / "site-budget").string() + "'");
    std::printf("# exported the splats alone with --splat-mbps %s (%.0f s)\n%s", budget, elapsed(),
                budget_output.c_str());
    sites.push_back("site-budget");
  }
  const nlohmann::json manifest =
      nlohmann::json::parse(ReadFileToString(dir / "site" / "manifest.json"));
  int camera_index = 0;
  while (manifest.at("cameras").at(camera_index).at("name") != heldout) ++camera_index;
  const int frame = frames / 2;
  const CameraModel camera = PinholeOf(manifest.at("cameras").at(camera_index));

  // Each site served on any free port, its streams timed and shot in the page.
  nlohmann::json manifests, bench, report;
  for (const std::string& site : sites) {
    PageRun run = MeasureInPage(dir, site, q, driver, camera, frame, camera_index);
    manifests[site] = std::move(run.manifest);
    bench[site] = std::move(run.bench);
    report[site] = std::move(run.report);
  }

  // What the held-out camera captured at the frame, in its pinhole core, with the subject's true
  // silhouette; the native renders through that pinhole.
  const Take take = Take::Open(dir / "take");
  const int64_t set = manifest.at("frames").at(frame).at("set");
  const CameraTruth truth = ReadCameraTruth(take, heldout, take.Camera(heldout), set, 0);
  char glb[32];
  std::snprintf(glb, sizeof(glb), "%06lld.glb", static_cast<long long>(set));
  const RenderedView nvol_native = OpenModel(dir / "nvol")->Render(truth.pinhole, frame, {});
  const RenderedView splat_native = OpenModel(dir / "splat")->Render(truth.pinhole, frame, {});
  const RenderedView mesh_native =
      RenderTexturedMesh(ReadTexturedGlb(dir / "take" / "recon" / glb), truth.pinhole);
  std::printf("\n# load: %s", Run("uptime").c_str());
  std::printf(
      "# held-out camera %s (pinhole core, %dx%d), frame %d (set %lld): %lld subject pixels (%s, "
      "grown by 3 px)\n",
      heldout.c_str(), camera.width(), camera.height(), frame, static_cast<long long>(set),
      static_cast<long long>(cv::countNonZero(truth.subject)), truth.silhouette_source.c_str());
  std::printf(
      "# page, native, background: PSNR (dB) against the camera inside the silhouette; loss "
      "= native - page\n");
  std::printf(
      "# exp unc: the export's decoded chunks against uncompressed (2 capture cameras at "
      "160 px, every frame); exp cam: the export's own native / streamed score against "
      "the camera (its frames 0, 7, 14, ...)\n");
  std::printf("# faces: meshes' faces per frame, splats' Gaussians per frame\n");
  std::printf("%-15s %7s %9s %8s %6s %6s %6s %6s %7s %11s %8s %9s\n", "stream", "faces", "MB/frame",
              "Mbps@30", "page", "native", "loss", "bg", "exp unc", "exp cam", "TTFF ms",
              "decoded/s");
  for (const std::string& site : sites) {
    for (const auto& s : manifests[site].at("streams")) {
      const std::string name = s.at("name");
      const fs::path browser = dir / (site == "site" ? "browser" : "browser-budget");
      char budget_row[64];
      std::snprintf(budget_row, sizeof(budget_row), "%s@%g", name.c_str(), splat_mbps);
      const std::string row = site == "site" ? name : budget_row;
      const cv::Mat shot = cv::imread((browser / (name + ".png")).string());
      const std::string kind = s.at("kind");
      const RenderedView& native = kind == "volume"   ? nvol_native
                                   : kind == "splats" ? splat_native
                                                      : mesh_native;
      cv::Mat background(truth.image.size(), CV_8UC3, cv::Scalar::all(0));
      if (s.contains("backgrounds") && s.at("backgrounds").contains(heldout))
        background =
            cv::imread((dir / site / s.at("backgrounds").at(heldout).get<std::string>()).string());
      SquaredError page, native_error, background_error;
      page.Add(shot, truth.image, truth.subject);
      native_error.Add(OverBackground(native, background), truth.image, truth.subject);
      background_error.Add(background, truth.image, truth.subject);
      const auto& b = bench[site].at(name);
      const auto& metrics = report[site].at("metrics").at("streams").at(name);
      const auto& own = metrics.at("camera");
      auto db = [](const nlohmann::json& v) { return v.is_number() ? v.get<double>() : NAN; };
      char exp_cam[64];
      std::snprintf(exp_cam, sizeof(exp_cam), "%.2f/%.2f", db(own.at("native_psnr_db")),
                    db(own.at("streamed_psnr_db")));
      std::printf(
          "%-15s %7.0f %9.4f %8.2f %6.2f %6.2f %6.2f %6.2f %7.2f %11s %8.0f %9.1f\n", row.c_str(),
          metrics.value("mean_faces", 0.0) + metrics.value("mean_gaussians", 0.0),
          s.at("mb_per_frame").get<double>(), s.at("mb_per_frame").get<double>() * 8 * 30,
          page.PsnrDb(), native_error.PsnrDb(), native_error.PsnrDb() - page.PsnrDb(),
          background_error.PsnrDb(), s.at("psnr_db").get<double>(), exp_cam,
          b.at("timeToFirstFrameMs").get<double>(), b.at("framesDecodedPerSecond").get<double>());
    }
  }
  if (fs::exists(dir / "browser" / "player.png")) std::printf("# player picture kept\n");
  std::printf("# outputs under %s\n", dir.c_str());
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return RunBench(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "web_bench: error: %s\n", e.what());
    return 1;
  }
}
