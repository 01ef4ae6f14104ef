// The splat stream's rate against its loss, by rung and by attribute group: a trained dynamic
// splat model's frames encoded as `holocap export web` encodes them (a key frame, then deltas
// of the frame before as decoded), each chunk decoded as the page decodes it and rendered through
// a held-out camera at its own size, against the native render of the same frame inside the
// subject's silhouette (the loss a viewer sees) and against the camera's own image there (what
// bench/web_bench scores), each drawn over the take's clean plate as the page draws it (where
// the model trained over one).
//
//   bench/splat_stream_bench TAKE MODEL CAMERA [FRAMES] [FPS] [KEY_RUNGS] [DELTA_RUNGS] [FIRST]
//     TAKE, MODEL  a calibrated take and a splat model trained on it (`holocap train splat`)
//     CAMERA       the held-out camera scored (its silhouette as web_bench reads it)
//     FRAMES       the model frames streamed from frame FIRST (0), one key frame then deltas
//                  (10)
//     FPS          the rate's frames a second (30)
//     KEY_RUNGS, DELTA_RUNGS  comma lists of rungs (web::SplatRung; 0 the level "low" itself,
//                  11 the coarsest): every pair with delta >= key (0,3,6,9 and 0,3,6,9)
//
// Rows: the pair as the export would stream it (`as is`), then the same pair with one part made
// exact, to show where the loss comes from: `exact motion` (the deltas' positions at motion step
// 1 and no dead zone), `no hold` (every other group sent again whenever a code changed), `no
// prune` (no Gaussian left out). Columns: Mbps at FPS over the segment, the key frame's and the
// deltas' mean kB, each section's share of the deltas' bytes, PSNR (dB) against the native render
// and against the camera inside the silhouette, each the mean of the frames' squared errors.
#include <cstdio>
#include <exception>
#include <map>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <vector>

#include "avatar/camera_score.h"
#include "core/fs.h"
#include "core/take.h"
#include "playback/internal/web_stream.h"
#include "splat/splat.h"

namespace fs = std::filesystem;
using namespace holocap;

namespace {

std::vector<int> Rungs(const std::string& list) {
  std::vector<int> rungs;
  std::stringstream in(list);
  std::string item;
  while (std::getline(in, item, ',')) rungs.push_back(std::stoi(item));
  return rungs;
}

struct Frames {
  std::vector<splat::Gaussians> gaussians;
  std::vector<std::vector<int64_t>> origin;  // empty for frame 0
  std::vector<CameraTruth> truth;
  std::vector<cv::Mat> native;
  cv::Mat background;  // the camera's clean plate, CV_32FC3 (what the page draws behind)
};

struct Row {
  double key_bytes = 0, delta_bytes = 0;
  std::map<std::string, double> delta_sections;
  SquaredError native, camera;
};

Row Stream(const Frames& frames, const web::SplatEncoding& key, const web::SplatEncoding& delta) {
  Row row;
  web::SplatCodes decoded;
  for (size_t f = 0; f < frames.gaussians.size(); ++f) {
    const bool is_key = f == 0;
    const web::SplatEncoding& encoding = is_key ? key : delta;
    web::SplatCodes codes;
    const web::Chunk chunk =
        web::EncodeSplats(frames.gaussians[f], static_cast<int64_t>(f), encoding,
                          is_key ? nullptr : &decoded, frames.origin[f], &codes);
    const std::string bytes = chunk.Serialise();
    (is_key ? row.key_bytes : row.delta_bytes) += static_cast<double>(bytes.size());
    if (!is_key)
      for (const auto& section : chunk.header.at("sections"))
        row.delta_sections[section.at("name")] += section.at("bytes").get<double>();
    decoded = web::DecodeSplats(web::ParseChunk(bytes), is_key ? nullptr : &decoded);
    decoded.order = std::move(codes.order);
    const splat::Gaussians drawn = web::SplatsFromCodes(decoded, encoding);
    const CameraTruth& truth = frames.truth[f];
    const cv::Mat picture = RenderSplats(drawn, truth.pinhole, frames.background).color;
    row.native.Add(picture, frames.native[f], truth.subject);
    row.camera.Add(picture, truth.image, truth.subject);
  }
  return row;
}

int RunBench(int argc, char** argv) {
  if (argc < 4) {
    std::fprintf(stderr,
                 "usage: splat_stream_bench TAKE MODEL CAMERA [FRAMES] [FPS] [KEY_RUNGS] "
                 "[DELTA_RUNGS] [FIRST]\n");
    return 2;
  }
  const fs::path take_dir = argv[1], model_dir = argv[2];
  const std::string camera = argv[3];
  const int64_t count = argc > 4 ? std::stoll(argv[4]) : 10;
  const double fps = argc > 5 ? std::stod(argv[5]) : 30;
  const std::vector<int> key_rungs = Rungs(argc > 6 ? argv[6] : "0,3,6,9");
  const std::vector<int> delta_rungs = Rungs(argc > 7 ? argv[7] : "0,3,6,9");
  const int64_t first = argc > 8 ? std::stoll(argv[8]) : 0;

  const Take take = Take::Open(take_dir);
  const SplatModel model = SplatModel::Load(model_dir);
  const nlohmann::json model_json =
      nlohmann::json::parse(ReadFileToString(model_dir / "model.json"));
  const auto sets = model_json.at("frame_sets").get<std::vector<int64_t>>();
  Frames frames;
  // The page draws a splat stream over the take's clean plate where the model trained over one
  // (its plan's background: "clean plate (frame set N)"), as the export's backgrounds hold it;
  // else over black.
  const std::string behind = model_json.at("plan").value("background", "");
  const auto plate_at = behind.find("frame set ");
  if (behind.starts_with("clean plate") && plate_at != std::string::npos) {
    const int64_t plate_set = std::stoll(behind.substr(plate_at + 10));
    ReadCameraTruth(take, camera, take.Camera(camera), plate_set, -1)
        .image.convertTo(frames.background, CV_32FC3, 1.0 / 255);
  }
  splat::Gaussians current;
  const int64_t last = std::min<int64_t>({first + count, model.frames, std::ssize(sets)});
  for (int64_t f = 0; f < last; ++f) {
    if (f > first && model.Base(f) != f - 1) break;  // a per-frame run's segment starts again
    current = f == 0 ? model.Frame(model_dir, 0) : model.Frame(model_dir, f, &current, f - 1);
    if (f < first) continue;
    frames.gaussians.push_back(current);
    frames.origin.push_back(
        f == first ? std::vector<int64_t>{}
                   : SplatDeltaOrigins(ReadFileToString(SplatDeltaFile(model_dir, f))));
    frames.truth.push_back(ReadCameraTruth(take, camera, take.Camera(camera), sets[f], 0));
    if (frames.truth.back().subject.empty())
      Fail("no silhouette of ", camera, ": ", frames.truth.back().silhouette_source);
    frames.native.push_back(
        RenderSplats(frames.gaussians.back(), frames.truth.back().pinhole, frames.background)
            .color);
  }
  if (frames.gaussians.empty()) Fail("the model has no frame ", first);
  web::SplatEncoding level =
      web::SplatEncoding::For(web::QualityByName("low"), frames.gaussians[0].sh_degree);
  for (const auto& g : frames.gaussians) level.Include(g);
  const double seconds = static_cast<double>(frames.gaussians.size()) / fps;
  SquaredError native_camera;
  for (size_t f = 0; f < frames.native.size(); ++f)
    native_camera.Add(frames.native[f], frames.truth[f].image, frames.truth[f].subject);

  std::printf("# bench/splat_stream_bench");
  for (int a = 1; a < argc; ++a) std::printf(" %s", argv[a]);
  std::printf("\n# %zu frames of %s (%lld Gaussians in frame 0) through %s at %dx%d; %g fps\n",
              frames.gaussians.size(), model_dir.c_str(),
              static_cast<long long>(frames.gaussians[0].size()), camera.c_str(),
              frames.truth[0].pinhole.width(), frames.truth[0].pinhole.height(), fps);
  std::printf(
      "# drawn over %s; the native render against the camera inside the silhouette: %.2f dB "
      "(loss: that minus the stream's `camera`)\n",
      frames.background.empty() ? "black" : behind.c_str(), native_camera.PsnrDb());
  std::printf("%-4s %-5s %-13s %7s %8s %8s %6s %6s %6s %6s %6s %6s %6s %7s %7s %6s\n", "key",
              "delta", "variant", "Mbps", "key kB", "delta kB", "masks", "motion", "pos", "rot",
              "scale", "opac", "color", "native", "camera", "loss");
  for (int k : key_rungs) {
    for (int d : delta_rungs) {
      if (d < k) continue;
      const web::SplatEncoding key = web::SplatRung(level, k);
      const web::SplatEncoding delta = web::SplatDeltaRung(level, k, d);
      for (const char* variant : {"as is", "exact motion", "no hold", "no prune"}) {
        web::SplatEncoding key_variant = key, delta_variant = delta;
        const std::string v = variant;
        if (v == "exact motion") {
          delta_variant.motion_step = 1;
          delta_variant.dead_zone = 0;
        } else if (v == "no hold") {
          delta_variant.hold = 0;
        } else if (v == "no prune") {
          key_variant.prune_opacity = delta_variant.prune_opacity = 0;
        }
        const Row row = Stream(frames, key_variant, delta_variant);
        const double deltas = std::max<double>(1, static_cast<double>(frames.gaussians.size()) - 1);
        auto share = [&](const char* name) {
          // No delta (one frame): no share.
          return row.delta_bytes > 0 ? 100 * row.delta_sections.at(name) / row.delta_bytes : 0.0;
        };
        std::printf(
            "%-4d %-5d %-13s %7.2f %8.1f %8.1f %5.1f%% %5.1f%% %5.1f%% %5.1f%% %5.1f%% %5.1f%% "
            "%5.1f%% %7.2f %7.2f %6.2f\n",
            k, d, variant, (row.key_bytes + row.delta_bytes) * 8 / seconds / 1e6,
            row.key_bytes / 1e3, row.delta_bytes / deltas / 1e3, share("masks"), share("motion"),
            share("position"), share("rotation"), share("scale"), share("opacity"), share("color"),
            row.native.PsnrDb(), row.camera.PsnrDb(), native_camera.PsnrDb() - row.camera.PsnrDb());
        std::fflush(stdout);
      }
    }
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return RunBench(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "splat_stream_bench: error: %s\n", e.what());
    return 1;
  }
}
