// The web stream per kind and quality level: MB per frame, Mbps at 30 fps, PSNR of the page's
// picture against the uncompressed native render (Neural Volumes: `holocap render`'s marcher on
// the model; meshes: the reconstruction's own glTF rasterised natively), time to first frame on
// loopback and frames decoded per second in the page (headless Chromium, SwiftShader).
//
//   bench/web_bench [FRAMES] [WIDTH] [ITERATIONS] [VOXEL]
//     FRAMES      frame sets of the studio8 walk (30), after one clean plate
//     WIDTH       image width of the simulated cameras (640)
//     ITERATIONS  Neural Volumes training iterations (300)
//     VOXEL       the reconstruction's voxel (8mm)
// Needs chromium and tests/playback/browser/node_modules (scripts/setup.sh --tests).
#include <signal.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <string>

#include "core/fs.h"
#include "neural/neural.h"
#include "playback/playback.h"

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

double PsnrOver(const cv::Mat& shot, const RenderedView& native) {
  double squared = 0;
  for (int y = 0; y < shot.rows; ++y)
    for (int x = 0; x < shot.cols; ++x)
      for (int c = 0; c < 3; ++c) {
        const double d = shot.at<cv::Vec3b>(y, x)[c] / 255.0 -
                         std::clamp(native.color.at<cv::Vec3f>(y, x)[c], 0.0f, 1.0f);
        squared += d * d;
      }
  return 10 * std::log10(1.0 / std::max(squared / (3.0 * shot.total()), 1e-12));
}

CameraModel PinholeOf(const nlohmann::json& camera) {
  const auto& m = camera.at("cam_from_world");
  Pose pose = Pose::Identity();
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) pose.matrix()(r, c) = m.at(4 * r + c).get<double>();
  return CameraModel("LENSMODEL_PINHOLE", camera.at("pinhole").get<std::vector<double>>(),
                     camera.at("width"), camera.at("height"), pose);
}

}  // namespace

int main(int argc, char** argv) {
  const int frames = argc > 1 ? std::atoi(argv[1]) : 30;
  const int width = argc > 2 ? std::atoi(argv[2]) : 640;
  const int iterations = argc > 3 ? std::atoi(argv[3]) : 300;
  const std::string voxel = argc > 4 ? argv[4] : "8mm";
  const fs::path cli = HOLOCAP_BENCH_CLI;
  const fs::path driver = fs::path(HOLOCAP_BENCH_SOURCE_DIR) / "tests/playback/browser/drive.mjs";
  const fs::path dir =
      fs::temp_directory_path() / ("holocap-web-bench-" + std::to_string(getpid()));
  fs::create_directories(dir);
  const std::string q = "HOLOCAP_NO_PROGRESS=1 '" + cli.string() + "' ";
  const auto start = std::chrono::steady_clock::now();
  auto elapsed = [&] {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  };
  Run(q + "sim --rig studio8 --frames " + std::to_string(frames + 1) + " --clean-plate 1 --size " +
      std::to_string(width) + " --seed 3 --out '" + (dir / "take").string() + "'");
  std::printf("# simulated %d frame sets at %d px (%.0f s)\n", frames, width, elapsed());
  Run(q + "reconstruct '" + (dir / "take").string() + "' --voxel " + voxel + " --no-sweep");
  std::printf("# reconstructed at %s (%.0f s)\n", voxel.c_str(), elapsed());
  Run(q + "train nvol '" + (dir / "take").string() + "' --out '" + (dir / "nvol").string() +
      "' --iterations " + std::to_string(iterations) + " --eval-every 100000 || true");
  std::printf("# Neural Volumes: %d iterations (%.0f s)\n", iterations, elapsed());
  const std::string export_output =
      Run(q + "export web '" + (dir / "take").string() + "' --model '" + (dir / "nvol").string() +
          "' --quality low,medium,high,lossless --fps 30 --out '" + (dir / "site").string() + "'");
  std::printf("# exported (%.0f s)\n%s", elapsed(), export_output.c_str());
  const nlohmann::json manifest =
      nlohmann::json::parse(ReadFileToString(dir / "site" / "manifest.json"));

  // The server, on any free port, for the page.
  const std::string pid = Run("(" + q + "view '" + (dir / "site").string() + "' --port 0 > '" +
                              (dir / "view.log").string() + "' 2>&1 & echo $!)");
  std::string url;
  for (int i = 0; i < 100 && url.empty(); ++i) {
    usleep(100000);
    const std::string log = fs::exists(dir / "view.log") ? ReadFileToString(dir / "view.log") : "";
    const auto at = log.find("http://");
    if (at != std::string::npos) url = log.substr(at, log.find(' ', at) - at);
  }
  std::vector<std::string> names;
  for (const auto& s : manifest.at("streams")) names.push_back(s.at("name"));
  std::string list;
  for (const auto& n : names) list += " " + n;
  fs::create_directories(dir / "browser");
  Run("node '" + driver.string() + "' bench " + url + " '" + (dir / "browser").string() + "'" +
      list);
  const int camera_index = 1, frame = frames / 2;
  const CameraModel camera = PinholeOf(manifest.at("cameras").at(camera_index));
  Run("node '" + driver.string() + "' shots " + url + " '" + (dir / "browser").string() + "' " +
      std::to_string(camera.width()) + " " + std::to_string(camera.height()) + " " +
      std::to_string(frame) + " " + std::to_string(camera_index) + list);
  kill(std::stoi(pid), SIGTERM);
  const auto bench = nlohmann::json::parse(ReadFileToString(dir / "browser" / "bench.json"));

  auto model = OpenModel(dir / "nvol");
  const int64_t set = manifest.at("frames").at(frame).at("set");
  char glb[32];
  std::snprintf(glb, sizeof(glb), "%06lld.glb", static_cast<long long>(set));
  const RenderedView nvol_native = model->Render(camera, frame, {});
  const RenderedView mesh_native =
      RenderTexturedMesh(ReadTexturedGlb(dir / "take" / "recon" / glb), camera);
  std::printf("\n# load: %s", Run("uptime").c_str());
  std::printf("# page PSNR: capture camera %d (pinhole core, %dx%d), frame %d, whole picture\n",
              camera_index, camera.width(), camera.height(), frame);
  std::printf("%-15s %9s %10s %10s %10s %9s %10s\n", "stream", "MB/frame", "Mbps@30", "PSNR page",
              "PSNR exp.", "TTFF ms", "decoded/s");
  for (const auto& s : manifest.at("streams")) {
    const std::string name = s.at("name");
    const cv::Mat shot = cv::imread((dir / "browser" / (name + ".png")).string());
    const bool volume = s.at("kind") == "volume";
    const double page_psnr = PsnrOver(shot, volume ? nvol_native : mesh_native);
    const auto& b = bench.at(name);
    std::printf("%-15s %9.4f %10.2f %10.2f %10.2f %9.0f %10.1f\n", name.c_str(),
                s.at("mb_per_frame").get<double>(), s.at("mb_per_frame").get<double>() * 8 * 30,
                page_psnr, s.at("psnr_db").get<double>(), b.at("timeToFirstFrameMs").get<double>(),
                b.at("framesDecodedPerSecond").get<double>());
  }
  if (fs::exists(dir / "browser" / "player.png")) std::printf("# player picture kept\n");
  std::printf("# outputs under %s\n", dir.c_str());
  return 0;
}
