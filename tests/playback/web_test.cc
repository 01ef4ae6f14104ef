// The web player: `holocap export web` on a small simulated take (3 frame sets, meshes, a
// dynamic Neural Volume and dynamic splats; exported as two shards), its stream decoded
// natively, `holocap view` serving it, and a real headless Chromium playing it
// (tests/playback/browser/drive.mjs): the page at a capture camera's pose and frame against the
// native renders, synthetic input, scrubbing across a splat key frame, a truncated chunk, a site of
// an unknown version, no console error.
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <random>

#include "avatar/image_metrics.h"
#include "core/error.h"
#include "core/fs.h"
#include "neural/neural.h"
#include "playback/internal/web_stream.h"
#include "playback/playback.h"
#include "splat/splat.h"
#include "tests/playback/view_server.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

// The avatar kinds these tests open.
const bool kAvatarKindsRegistered = [] {
  RegisterNeuralVolumeAvatarKind(AvatarKindRegistry::Global());
  RegisterSplatAvatarKind(AvatarKindRegistry::Global());
  return true;
}();

namespace fs = std::filesystem;
using testing::BrowserMissing;
using testing::RunCli;
using testing::RunShell;
using testing::TempDir;
using testing::ViewServer;

class WebTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new TempDir("holocap-web");
    auto sim = RunCli("sim --rig studio8 --frames 4 --clean-plate 1 --size 128 --seed 8 --out '" +
                      Take().string() + "'");
    ASSERT_EQ(sim.exit_code, 0) << sim.output;
    auto recon = RunCli("reconstruct '" + Take().string() +
                        "' --ground-truth-cameras --voxel 8mm --no-sweep");
    ASSERT_EQ(recon.exit_code, 0) << recon.output;
    NeuralVolumeOptions options;
    options.take.ground_truth_cameras = true;
    options.grid = 32;
    options.image_width = 64;
    options.latent_dim = 32;
    options.decoder_channels = 32;
    options.warp_grid = 16;
    options.rays_per_batch = 1024;
    options.iterations = 100;
    options.eval_every_s = 1000;
    // A short run may end DEGENERATE (the subject no better than the background in held-out
    // views); the model is kept and is what the page must draw like the native renderer.
    TrainNeuralVolume(Take(), Model(), options);
    ASSERT_TRUE(fs::exists(Model() / "model.json"));
    // Splats frame to frame, seeded from the take's reconstruction: few iterations, one thread
    // (a loaded machine's spinning OpenMP threads cost more than they give at this size).
    SplatOptions splats;
    splats.take.ground_truth_cameras = true;
    splats.recon_dir = (Take() / "recon").string();
    splats.image_width = 64;
    splats.max_seed_points = 4000;
    splats.iterations = 150;
    splats.sh_degree_every = 40;  // degree 3 by iteration 120: the page evaluates every degree
    splats.frame_iterations = 30;
    splats.minutes = splats.frame_minutes = 10;
    splats.eval_every_s = 1000;
    splats.threads = 1;
    TrainSplats(Take(), SplatModelDir(), splats);
    ASSERT_TRUE(fs::exists(SplatModelDir() / "deltas"));
    // Its first frame with strong view-dependent colour (every coefficient above degree 0
    // random in +-0.2), as a static model: what the page's spherical harmonics must match.
    SplatModel vivid = SplatModel::Load(SplatModelDir());
    vivid.frames = 1;
    std::mt19937 random(5);
    std::uniform_real_distribution<float> coefficient(-0.2f, 0.2f);
    const int k = vivid.gaussians.coefficients();
    for (size_t j = 0; j < vivid.gaussians.sh.size(); ++j)
      if ((j / 3) % k != 0) vivid.gaussians.sh[j] = coefficient(random);
    vivid.Save(VividModelDir());
    // Key frames every 2 frames: frame 1 is a delta of frame 0, frame 2 a key frame again. The
    // site is exported as two shards (groups {0, 1} and {2}), so the page plays a sharded site
    // (web_shard_test.cc checks that one is the bytes of one process's).
    for (const char* shard : {"0/2", "1/2"}) {
      auto exported =
          RunCli("export web '" + Take().string() + "' --ground-truth-cameras --model '" +
                 Model().string() + "' --model '" + SplatModelDir().string() + "' --model '" +
                 VividModelDir().string() +
                 "' --quality low,high,lossless --key-every 2 --ground-truth --out '" +
                 Site().string() + "' --shard " + shard);
      ASSERT_EQ(exported.exit_code, 0) << exported.output;
    }
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }
  static fs::path Take() { return dir_->path() / "take"; }
  static fs::path Model() { return dir_->path() / "nvol"; }
  static fs::path SplatModelDir() { return dir_->path() / "splat"; }
  static fs::path VividModelDir() { return dir_->path() / "vivid"; }
  static fs::path Site() { return dir_->path() / "site"; }
  static nlohmann::json Manifest() {
    return nlohmann::json::parse(ReadFileToString(Site() / "manifest.json"));
  }
  static TempDir* dir_;
};
TempDir* WebTest::dir_ = nullptr;

const nlohmann::json& StreamNamed(const nlohmann::json& manifest, const std::string& name) {
  for (const auto& s : manifest.at("streams"))
    if (s.at("name") == name) return s;
  throw Error("no stream " + name);
}

// The capture camera as the page shows it: its pinhole core at its own size.
CameraModel PinholeOf(const nlohmann::json& camera) {
  const auto& m = camera.at("cam_from_world");
  Pose pose = Pose::Identity();
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) pose.matrix()(r, c) = m.at(4 * r + c).get<double>();
    pose.matrix()(r, 3) = m.at(4 * r + 3).get<double>();
  }
  return CameraModel("LENSMODEL_PINHOLE", camera.at("pinhole").get<std::vector<double>>(),
                     camera.at("width"), camera.at("height"), pose);
}

// The manifest's bounds as a box.
Box BoxOf(const nlohmann::json& bounds) {
  Box box;
  for (int a = 0; a < 3; ++a) {
    box.min[a] = bounds.at("min").at(a).get<double>();
    box.max[a] = bounds.at("max").at(a).get<double>();
  }
  return box;
}

TEST_F(WebTest, ExportStreamsEveryFrameAndMeasuresItsLoss) {
  const nlohmann::json manifest = Manifest();
  EXPECT_EQ(manifest.at("version"), kWebStreamFormatVersion);
  ASSERT_EQ(manifest.at("frames").size(), 3u);
  EXPECT_EQ(manifest.at("cameras").size(), 8u);
  const nlohmann::json report = nlohmann::json::parse(ReadFileToString(Site() / "report.json"));
  EXPECT_EQ(report.at("summary").at("termination"), "SUCCESS") << report.dump(1);
  for (const std::string name : {"mesh-high", "mesh-lossless", "nvol-high", "nvol-lossless",
                                 "splat-high", "splat-lossless"}) {
    const auto& stream = StreamNamed(manifest, name);
    ASSERT_EQ(stream.at("chunks").size(), 3u) << name;
    for (const auto& chunk : stream.at("chunks")) {
      ASSERT_FALSE(chunk.is_null()) << name;
      EXPECT_EQ(fs::file_size(Site() / stream.at("path").get<std::string>() /
                              chunk.at("file").get<std::string>()),
                chunk.at("bytes").get<uint64_t>());
    }
    const auto& metrics = report.at("metrics").at("streams").at(name);
    std::printf("%-14s %.4f MB/frame %.2f Mbps at %.0f fps, PSNR %.1f dB against uncompressed\n",
                name.c_str(), metrics.at("mb_per_frame").get<double>(),
                metrics.at("mbps").get<double>(), manifest.at("fps").get<double>(),
                metrics.at("psnr_db").get<double>());
    EXPECT_GT(metrics.at("psnr_db").get<double>(), name.ends_with("lossless") ? 98.0 : 38.0);
  }
  // The volume chunk decodes natively to a grid that marches like the model's own render.
  auto model = OpenModel(Model());
  const auto& nvol = StreamNamed(manifest, "nvol-high");
  const BakedFrame decoded = web::DecodeVolume(
      web::ParseChunk(ReadFileToString(Site() / nvol.at("path").get<std::string>() /
                                       nvol.at("chunks").at(1).at("file").get<std::string>())));
  const CameraModel camera = PinholeOf(manifest.at("cameras").at(2));
  const RenderedView native = model->Render(camera, 1, {});
  const RenderedView streamed = web::RenderBakedFrame(decoded, camera, 1e-3);
  const double psnr = PsnrDb(streamed.color, native.color);
  EXPECT_GT(psnr, 40.0);
  EXPECT_GT(cv::mean(native.alpha)[0], 0.01) << "the view shows too little of the volume";
}

// The splat chunks of frames 0 and 1 (a key frame and a delta of it) decode, natively, to the
// model's frames: exactly at `lossless`, within the quantisation at `high`.
TEST_F(WebTest, SplatStreamDecodesKeyFramesAndDeltasToTheModelsFrames) {
  const nlohmann::json manifest = Manifest();
  const SplatModel model = SplatModel::Load(SplatModelDir());
  ASSERT_EQ(model.frames, 3);
  EXPECT_EQ(model.frame_sets, (std::vector<int64_t>{1, 2, 3}));
  auto chunk = [&](const nlohmann::json& stream, int frame) {
    return web::ParseChunk(
        ReadFileToString(Site() / stream.at("path").get<std::string>() /
                         stream.at("chunks").at(frame).at("file").get<std::string>()));
  };
  for (const std::string level : {"high", "lossless"}) {
    const auto& stream = StreamNamed(manifest, "splat-" + level);
    std::vector<bool> keys;
    for (const auto& c : stream.at("chunks")) keys.push_back(c.at("key").get<bool>());
    EXPECT_EQ(keys, (std::vector<bool>{true, false, true})) << level;
    const web::Chunk key = chunk(stream, 0), delta = chunk(stream, 1);
    const web::SplatCodes first = web::DecodeSplats(key, nullptr);
    EXPECT_THROW(web::DecodeSplats(delta, nullptr), Error);
    const web::SplatCodes second = web::DecodeSplats(delta, &first);
    const web::SplatEncoding encoding = web::SplatEncoding::FromJson(delta.header.at("encoding"));
    const splat::Gaussians decoded = web::SplatsFromCodes(second, encoding);
    const splat::Gaussians original = model.Frame(SplatModelDir(), 1);
    ASSERT_EQ(decoded.size(), original.size()) << level;
    std::printf(
        "splat-%s frame 1: a delta of %lld Gaussians (%lld removed, %lld added, %lld stored)\n",
        level.c_str(), static_cast<long long>(decoded.size()),
        delta.header.at("removed").get<long long>(), delta.header.at("added").get<long long>(),
        delta.header.at("stored").get<long long>());
    if (level == "lossless") {
      EXPECT_EQ(decoded.position, original.position);
      EXPECT_EQ(decoded.sh, original.sh);
      continue;
    }
    const CameraModel camera = PinholeOf(manifest.at("cameras").at(2));
    auto view = OpenModel(SplatModelDir())->Render(camera, 1, {});
    const double psnr = PsnrDb(RenderSplats(decoded, camera).color, view.color);
    std::printf("splat-high frame 1 decoded against holocap render, camera 2: %.2f dB\n", psnr);
    EXPECT_GT(psnr, 40.0);
    EXPECT_GT(cv::mean(view.alpha)[0], 0.01) << "the view shows too little of the splats";
  }
}

TEST_F(WebTest, SimplifiedMeshChunkDecodesToTheExportedMeshWithinItsBound) {
  const nlohmann::json manifest = Manifest();
  const auto& stream = StreamNamed(manifest, "mesh-low");
  const int frame = 1;
  const int64_t set = manifest.at("frames").at(frame).at("set");
  char glb[32];
  std::snprintf(glb, sizeof(glb), "%06lld.glb", static_cast<long long>(set));
  const TexturedMeshFrame original = ReadTexturedGlb(Take() / "recon" / glb);
  const web::Chunk chunk = web::ParseChunk(
      ReadFileToString(Site() / stream.at("path").get<std::string>() /
                       stream.at("chunks").at(frame).at("file").get<std::string>()));
  ASSERT_TRUE(chunk.header.contains("layout")) << chunk.header.dump(1);
  const TexturedMeshFrame decoded = web::DecodeMesh(chunk);
  // Fewer faces than the reconstruction, texture coordinates implied by the layout.
  EXPECT_GT(decoded.faces(), 50u);
  EXPECT_LT(decoded.faces(), original.faces());
  ASSERT_EQ(decoded.uvs.size(), decoded.positions.size());
  ASSERT_FALSE(decoded.atlas.empty());
  EXPECT_EQ(decoded.atlas.cols, chunk.header.at("layout").at("columns").get<int>() *
                                    chunk.header.at("layout").at("cell_px").get<int>());
  // What the export measured is what the chunk holds: encoding again gives the same corners.
  TexturedMeshFrame encoded;
  double max_error_m = 0;
  const std::string again =
      web::EncodeMesh(original, frame, web::QualityByName("low"), &encoded, &max_error_m)
          .Serialise();
  EXPECT_EQ(again.size(), stream.at("chunks").at(frame).at("bytes").get<size_t>());
  ASSERT_EQ(encoded.positions.size(), decoded.positions.size());
  for (size_t c = 0; c < decoded.positions.size(); ++c) {
    ASSERT_EQ(encoded.positions[c], decoded.positions[c]) << "corner " << c;
    ASSERT_EQ(encoded.uvs[c], decoded.uvs[c]) << "corner " << c;
  }
  // Every decoded vertex lies near the original surface: within the error the simplifier
  // reported plus the quantisation, checked against the nearest original vertex (one median
  // edge more, as vertices sample the surface that finely).
  const double edge_m = web::MedianEdgeM(original);
  double worst_m = 0;
  for (const auto& p : decoded.positions) {
    double nearest = std::numeric_limits<double>::infinity();
    for (const auto& q : original.positions) nearest = std::min(nearest, double((p - q).norm()));
    worst_m = std::max(worst_m, nearest);
  }
  std::printf(
      "mesh-low frame %d: %zu of %zu faces, vertices within %.2f mm of the original's "
      "(bound %.2f + %.2f mm), median edge %.2f mm\n",
      frame, decoded.faces(), original.faces(), 1e3 * worst_m, 1e3 * max_error_m, 1e3 * edge_m,
      1e3 * edge_m);
  EXPECT_LE(worst_m, max_error_m + edge_m);
  // Seen through a capture camera, the decoded frame looks like the exported mesh.
  const CameraModel camera = PinholeOf(manifest.at("cameras").at(3));
  const RenderedView a = RenderTexturedMesh(decoded, camera);
  const RenderedView b = RenderTexturedMesh(original, camera);
  int64_t pixels = 0;
  const double psnr =
      PsnrInsideBoxDb(a.color, b.color, camera, BoxOf(manifest.at("bounds")), &pixels);
  std::printf("mesh-low decoded against the exported mesh, camera 3: %.2f dB over %lld px\n", psnr,
              static_cast<long long>(pixels));
  EXPECT_GT(psnr, 30.0);
  EXPECT_GT(cv::mean(b.alpha)[0], 0.01) << "the view shows too little of the mesh";
}

TEST_F(WebTest, PagePlaysTheStreamLikeTheNativeRenderer) {
  const fs::path driver = testing::SourceDir() / "tests/playback/browser";
  if (const std::string why = BrowserMissing(driver); !why.empty()) GTEST_SKIP() << why;
  const nlohmann::json manifest = Manifest();
  // A chunk cut short: the page must name it and play on.
  const auto& broken = StreamNamed(manifest, "mesh-lossless");
  const fs::path broken_file = Site() / broken.at("path").get<std::string>() /
                               broken.at("chunks").at(1).at("file").get<std::string>();
  const std::string bytes = ReadFileToString(broken_file);
  WriteFileAtomic(broken_file, bytes.substr(0, bytes.size() / 2));

  ViewServer server(Site());
  ASSERT_FALSE(server.url().empty()) << server.first_line();
  const fs::path out = dir_->path() / "browser";
  fs::create_directories(out);
  const int camera_index = 2, frame = 1;
  const CameraModel camera = PinholeOf(manifest.at("cameras").at(camera_index));
  auto shots =
      RunShell("node '" + (driver / "drive.mjs").string() + "' shots " + server.url() + " '" +
               out.string() + "' " + std::to_string(camera.width()) + " " +
               std::to_string(camera.height()) + " " + std::to_string(frame) + " " +
               std::to_string(camera_index) + " nvol-high mesh-high splat-high vivid-high");
  const auto shot_results = nlohmann::json::parse(ReadFileToString(out / "shots.json"));
  ASSERT_TRUE(shot_results.at("ok").get<bool>()) << shots.output;
  EXPECT_TRUE(shot_results.at("consoleErrors").empty()) << shot_results.dump(1);

  int64_t pixels = 0;
  auto model = OpenModel(Model());
  const double nvol_psnr = PsnrInsideBoxDb(cv::imread((out / "nvol-high.png").string()),
                                           model->Render(camera, frame, {}).color, camera,
                                           BoxOf(manifest.at("bounds")), &pixels);
  std::printf("Neural Volumes stream in the page against holocap render: %.2f dB over %lld px\n",
              nvol_psnr, static_cast<long long>(pixels));
  EXPECT_GE(nvol_psnr, 35.0);
  EXPECT_GT(pixels, 500);
  const int64_t set = manifest.at("frames").at(frame).at("set");
  char glb[32];
  std::snprintf(glb, sizeof(glb), "%06lld.glb", static_cast<long long>(set));
  const double mesh_psnr =
      PsnrInsideBoxDb(cv::imread((out / "mesh-high.png").string()),
                      RenderTexturedMesh(ReadTexturedGlb(Take() / "recon" / glb), camera).color,
                      camera, BoxOf(manifest.at("bounds")), &pixels);
  std::printf("mesh stream in the page against the native textured render: %.2f dB over %lld px\n",
              mesh_psnr, static_cast<long long>(pixels));
  EXPECT_GE(mesh_psnr, 30.0);

  // Splats: the page against holocap render of the splat model, then scrubbed from frame 2 (a key
  // frame) to frame 1 (a delta of frame 0, which the page fetches and decodes first) and 0.
  auto splats = OpenModel(SplatModelDir());
  const double splat_psnr = PsnrInsideBoxDb(cv::imread((out / "splat-high.png").string()),
                                            splats->Render(camera, frame, {}).color, camera,
                                            BoxOf(manifest.at("bounds")), &pixels);
  std::printf("splat stream in the page against holocap render: %.2f dB over %lld px\n", splat_psnr,
              static_cast<long long>(pixels));
  EXPECT_GE(splat_psnr, 30.0);
  const RenderedView vivid = OpenModel(VividModelDir())->Render(camera, frame, {});
  const cv::Mat vivid_page = cv::imread((out / "vivid-high.png").string());
  const double vivid_psnr =
      PsnrInsideBoxDb(vivid_page, vivid.color, camera, BoxOf(manifest.at("bounds")), &pixels);
  // Where the splats cover the picture, the page's 8-bit colour against the native float one.
  cv::Mat native_8u, covered;
  vivid.color.convertTo(native_8u, CV_8UC3, 255.0);
  cv::compare(vivid.alpha, 0.5, covered, cv::CMP_GT);
  const double vivid_covered_psnr = PsnrDb(vivid_page, native_8u, covered);
  std::printf(
      "splats of strong view-dependent colour (degree 3) in the page: %.2f dB inside the box, "
      "%.2f dB over the %d px they cover\n",
      vivid_psnr, vivid_covered_psnr, cv::countNonZero(covered));
  EXPECT_GE(vivid_psnr, 30.0);
  // 42 dB measured; one basis term of the wrong sign in the page gives 34 dB here.
  EXPECT_GE(vivid_covered_psnr, 38.0);
  EXPECT_GT(cv::countNonZero(covered), 200);
  auto scrub = RunShell("node '" + (driver / "drive.mjs").string() + "' scrub " + server.url() +
                        " '" + out.string() + "' " + std::to_string(camera.width()) + " " +
                        std::to_string(camera.height()) + " " + std::to_string(camera_index) +
                        " splat-high 2 1 0");
  const auto scrubbed = nlohmann::json::parse(ReadFileToString(out / "scrub.json"));
  ASSERT_TRUE(scrubbed.at("ok").get<bool>()) << scrub.output;
  EXPECT_TRUE(scrubbed.at("consoleErrors").empty()) << scrubbed.dump(1);
  for (const auto& step : scrubbed.at("frames")) {
    const int target = step.at("target");
    EXPECT_EQ(step.at("drawnFrame"), target);
    EXPECT_TRUE(step.at("messages").empty()) << step.dump();
    const double psnr = PsnrInsideBoxDb(
        cv::imread((out / ("scrub-" + std::to_string(target) + ".png")).string()),
        splats->Render(camera, target, {}).color, camera, BoxOf(manifest.at("bounds")));
    std::printf("splat stream scrubbed to frame %d: %.2f dB against holocap render\n", target,
                psnr);
    EXPECT_GE(psnr, 30.0);
  }

  auto interact = RunShell("node '" + (driver / "drive.mjs").string() + "' interact " +
                           server.url() + " '" + out.string() + "' 1 mesh-lossless");
  const auto r = nlohmann::json::parse(ReadFileToString(out / "interact.json"));
  ASSERT_TRUE(r.at("ok").get<bool>()) << interact.output;
  EXPECT_NE(r.at("drag").at("hashBefore"), r.at("drag").at("hashAfter"));
  EXPECT_TRUE(r.at("drag").at("pictureChanged").get<bool>());
  EXPECT_NE(r.at("zoom").at("hashBefore"), r.at("zoom").at("hashAfter"));
  EXPECT_TRUE(r.at("zoom").at("pictureChanged").get<bool>());
  EXPECT_NE(r.at("play").at("frameAfter"), 0);
  EXPECT_EQ(r.at("scrub").at("frame"), 2);
  EXPECT_EQ(r.at("scrub").at("drawnFrame"), 2);
  EXPECT_GT(r.at("broken").at("frame").get<int>(), 1);
  const std::string messages = r.at("broken").at("messages").dump();
  EXPECT_NE(messages.find("truncated"), std::string::npos) << messages;
  EXPECT_NE(r.at("unknownVersion").get<std::string>().find("version 99"), std::string::npos)
      << r.at("unknownVersion");
  EXPECT_TRUE(r.at("consoleErrors").empty()) << r.at("consoleErrors").dump(1);
  // The player's picture, kept for the bench folder by whoever wants it.
  std::printf("player screenshot: %s\n", (out / "player.png").c_str());
  if (const char* keep = std::getenv("HOLOCAP_KEEP_PLAYER_PNG"))
    fs::copy_file(out / "player.png", keep, fs::copy_options::overwrite_existing);
}

// A stream's chunks as written under `site`.
std::vector<web::Chunk> ChunksOf(const fs::path& site, const nlohmann::json& stream) {
  std::vector<web::Chunk> chunks;
  for (const auto& c : stream.at("chunks"))
    chunks.push_back(web::ParseChunk(ReadFileToString(site / stream.at("path").get<std::string>() /
                                                      c.at("file").get<std::string>())));
  return chunks;
}

// `--splat-mbps`: the splats exported to half of splat-low's own rate fit it (a coarser rung than
// the level's), their last frame (a delta of a delta) drawn by the page like the native
// rasteriser draws what the C++ decoder reads from the same chunks; a version-3 splat chunk is
// refused by name.
TEST_F(WebTest, BudgetedSplatStreamFitsAndThePageDecodesItAsNatively) {
  const nlohmann::json manifest = Manifest();
  const double fps = manifest.at("fps").get<double>();
  const auto& low = StreamNamed(manifest, "splat-low");
  double bytes = 0;
  for (const auto& chunk : low.at("chunks")) bytes += chunk.at("bytes").get<double>();
  const double budget = 0.5 * bytes / 3 * 8 * fps / 1e6;
  const fs::path site = dir_->path() / "budget";
  auto exported =
      RunCli("export web '" + Take().string() + "' --ground-truth-cameras --no-meshes --model '" +
             SplatModelDir().string() + "' --quality low --key-every 3 --splat-mbps " +
             std::to_string(budget) + " --out '" + site.string() + "'");
  ASSERT_EQ(exported.exit_code, 0) << exported.output;
  const nlohmann::json budget_manifest =
      nlohmann::json::parse(ReadFileToString(site / "manifest.json"));
  const nlohmann::json report = nlohmann::json::parse(ReadFileToString(site / "report.json"));
  const double mbps = report.at("metrics").at("streams").at("splat-low").at("mbps");
  std::printf("splat-low at its level %.3f Mbps, with --splat-mbps %.3f: %.3f Mbps\n", 2 * budget,
              budget, mbps);
  EXPECT_LE(mbps, budget);
  const auto& stream = StreamNamed(budget_manifest, "splat-low");
  const std::vector<web::Chunk> chunks = ChunksOf(site, stream);
  ASSERT_EQ(chunks.size(), 3u);
  const web::SplatEncoding e = web::SplatEncoding::FromJson(chunks[2].header.at("encoding"));
  EXPECT_GT(e.motion_step, 1) << "the level's own encoding does not fit half its rate";
  web::SplatCodes codes = web::DecodeSplats(chunks[0], nullptr);
  for (size_t f = 1; f < chunks.size(); ++f) {
    ASSERT_FALSE(chunks[f].header.at("key").get<bool>());
    codes = web::DecodeSplats(chunks[f], &codes);
  }
  const fs::path driver = testing::SourceDir() / "tests/playback/browser";
  if (const std::string why = BrowserMissing(driver); !why.empty()) GTEST_SKIP() << why;
  // A copy of the site whose first splat chunk says version 3.
  const fs::path old_site = dir_->path() / "budget-v3";
  fs::copy(site, old_site, fs::copy_options::recursive);
  const fs::path first = old_site / stream.at("path").get<std::string>() /
                         stream.at("chunks").at(0).at("file").get<std::string>();
  std::string first_bytes = ReadFileToString(first);
  first_bytes[8] = 3;
  WriteFileAtomic(first, first_bytes);
  const int camera_index = 2, frame = 2;
  const CameraModel camera = PinholeOf(budget_manifest.at("cameras").at(camera_index));
  const fs::path out = dir_->path() / "budget-browser";
  fs::create_directories(out);
  nlohmann::json results[2];
  for (int s = 0; s < 2; ++s) {
    ViewServer server(s == 0 ? site : old_site);
    ASSERT_FALSE(server.url().empty()) << server.first_line();
    const std::string mode = s == 0 ? "shots" : "refused";
    const std::string view = s == 0 ? std::to_string(camera.width()) + " " +
                                          std::to_string(camera.height()) + " " +
                                          std::to_string(frame) + " " + std::to_string(camera_index)
                                    : "0";
    std::string command = "node '";
    command += (driver / "drive.mjs").string();
    command += "' " + mode + " ";
    command += server.url();
    command += " '" + out.string() + "' ";
    command += view;
    command += " splat-low";
    auto run = RunShell(command);
    results[s] = nlohmann::json::parse(ReadFileToString(out / (mode + ".json")));
    ASSERT_TRUE(results[s].at("ok").get<bool>()) << run.output;
  }
  EXPECT_TRUE(results[0].at("consoleErrors").empty()) << results[0].dump(1);
  const SplatRender native = RenderSplats(web::SplatsFromCodes(codes, e), camera);
  int64_t pixels = 0;
  const double psnr = PsnrInsideBoxDb(cv::imread((out / "splat-low.png").string()), native.color,
                                      camera, BoxOf(budget_manifest.at("bounds")), &pixels);
  std::printf(
      "budgeted splat stream, frame %d, in the page against the native render of the C++ "
      "decoder's Gaussians: %.2f dB over %lld px\n",
      frame, psnr, static_cast<long long>(pixels));
  // 52 dB measured (the page's 8-bit picture against the float one).
  EXPECT_GE(psnr, 45.0);
  EXPECT_GT(pixels, 500);
  EXPECT_GT(cv::mean(native.alpha)[0], 0.01) << "the view shows too little of the splats";
  const std::string messages = results[1].at("messages").dump();
  EXPECT_NE(messages.find("splat chunk of stream format version 3"), std::string::npos) << messages;
}

// `--splat-mbps` holds every segment (a key frame and its deltas, up to the next key frame) to
// the budget over its playing time, the peak segment rate HLS calls BANDWIDTH: not the stream's
// mean (a key frame alone at the end of the timeline can be far above it), nor each chunk (a
// key frame is larger than one frame's share by nature; holding it there would coarsen a
// segment that fits). Key frames every 2 of the 3 frames: segments {key, delta} and {key}. The
// budget lies between the stream's mean at the level's own encoding and its largest segment's
// rate: the segment that fits keeps the level's encoding, the other is coarsened to fit, and
// the chunks decode in turn, each by the encoding in its header. A budget no rung can meet
// ends the export DEGENERATE, naming the stream.
TEST_F(WebTest, BudgetHoldsEverySegmentOfASplatStream) {
  const fs::path own = dir_->path() / "own-rate", held = dir_->path() / "held",
                 starved = dir_->path() / "starved";
  auto export_at = [&](const fs::path& site, const std::string& budget) {
    return RunCli("export web '" + Take().string() +
                  "' --ground-truth-cameras --no-meshes --model '" + SplatModelDir().string() +
                  "' --quality low --key-every 2" + budget + " --out '" + site.string() + "'");
  };
  auto exported = export_at(own, "");
  ASSERT_EQ(exported.exit_code, 0) << exported.output;
  const nlohmann::json own_manifest =
      nlohmann::json::parse(ReadFileToString(own / "manifest.json"));
  const double fps = own_manifest.at("fps").get<double>();
  // Each segment's rate (Mbps over its frames) and its chunks' sizes.
  struct Segment {
    double mbps = 0;
    std::vector<double> bytes;
  };
  auto segments_of = [&](const nlohmann::json& stream) {
    std::vector<Segment> segments;
    for (const auto& chunk : stream.at("chunks")) {
      if (chunk.at("key").get<bool>()) segments.emplace_back();
      segments.back().bytes.push_back(chunk.at("bytes").get<double>());
    }
    for (Segment& segment : segments) {
      double sum = 0;
      for (double b : segment.bytes) sum += b;
      segment.mbps = sum * 8 * fps / 1e6 / static_cast<double>(segment.bytes.size());
    }
    return segments;
  };
  const auto& level = StreamNamed(own_manifest, "splat-low");
  ASSERT_EQ(level.at("chunks").size(), 3u);
  const std::vector<Segment> own_segments = segments_of(level);
  ASSERT_EQ(own_segments.size(), 2u);
  const double mean = level.at("mbps").get<double>();
  const double largest = std::max(own_segments[0].mbps, own_segments[1].mbps);
  ASSERT_GT(largest, mean * 1.01) << "a segment above the mean";
  const double budget = (mean + largest) / 2;
  exported = export_at(held, " --splat-mbps " + std::to_string(budget));
  ASSERT_EQ(exported.exit_code, 0) << exported.output;
  std::printf(
      "splat-low at its own encoding: mean %.3f Mbps, segments %.3f and %.3f; budget %.3f\n%s",
      mean, own_segments[0].mbps, own_segments[1].mbps, budget, exported.output.c_str());
  const nlohmann::json manifest = nlohmann::json::parse(ReadFileToString(held / "manifest.json"));
  const auto& stream = StreamNamed(manifest, "splat-low");
  const std::vector<Segment> segments = segments_of(stream);
  ASSERT_EQ(segments.size(), 2u);
  double held_largest = 0;
  int kept = 0, coarsened = 0;
  for (size_t k = 0; k < segments.size(); ++k) {
    EXPECT_LE(segments[k].mbps, budget) << "segment " << k;
    held_largest = std::max(held_largest, segments[k].mbps);
    if (own_segments[k].mbps <= budget) {
      EXPECT_EQ(segments[k].bytes, own_segments[k].bytes) << "segment " << k << " fits as it is";
      ++kept;
    } else {
      EXPECT_LT(segments[k].mbps, own_segments[k].mbps) << "segment " << k;
      ++coarsened;
    }
  }
  EXPECT_EQ(kept, 1);
  EXPECT_EQ(coarsened, 1);
  const nlohmann::json report = nlohmann::json::parse(ReadFileToString(held / "report.json"));
  const auto& metrics = report.at("metrics").at("streams").at("splat-low");
  EXPECT_NEAR(metrics.at("max_segment_mbps").get<double>(), held_largest, 1e-6 * held_largest);
  EXPECT_LE(metrics.at("mbps").get<double>(), metrics.at("max_chunk_mbps").get<double>());
  EXPECT_NE(exported.output.find("largest segment"), std::string::npos) << exported.output;
  const std::vector<web::Chunk> chunks = ChunksOf(held, stream);
  ASSERT_EQ(chunks.size(), 3u);
  web::SplatCodes codes;
  for (size_t f = 0; f < chunks.size(); ++f) {
    const bool key = chunks[f].header.at("key").get<bool>();
    EXPECT_EQ(key, f % 2 == 0) << f;
    codes = web::DecodeSplats(chunks[f], key ? nullptr : &codes);
    EXPECT_EQ(codes.count, chunks[f].header.at("count").get<int64_t>());
  }
  // A budget the coarsest rung cannot meet: the site is written, and the export says so.
  exported = export_at(starved, " --splat-mbps 0.001");
  EXPECT_NE(exported.exit_code, 0) << exported.output;
  EXPECT_NE(exported.output.find("DEGENERATE"), std::string::npos) << exported.output;
  EXPECT_NE(exported.output.find("over its budget"), std::string::npos) << exported.output;
  EXPECT_TRUE(fs::exists(starved / "report.json"));
}

TEST_F(WebTest, ViewOfATakeRemovesItsTemporarySiteWhenStopped) {
  ViewServer server(
      ViewServer::Start{{Take().string(), "--ground-truth-cameras", "--port", "0"}, {}, {}});
  server.WaitForUrl();
  ASSERT_FALSE(server.url().empty()) << server.printed();
  const std::string& printed = server.printed();
  const auto at = printed.find(" to ");
  ASSERT_NE(at, std::string::npos) << printed;
  const fs::path temporary = printed.substr(at + 4, printed.find(" (", at) - at - 4);
  EXPECT_TRUE(fs::exists(temporary / "manifest.json")) << temporary;
  const int status = server.Stop();
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << status;
  EXPECT_FALSE(fs::exists(temporary)) << temporary << " is left after SIGTERM";
}

TEST(WebViewTest, RefusesAFolderThatIsNotASiteAndAPortInUse) {
  TempDir dir("holocap-web-view");
  fs::create_directories(dir.path() / "empty");
  fs::create_directories(dir.path() / "site");
  testing::ExpectOneLineError(RunCli("view '" + (dir.path() / "empty").string() + "'"),
                              "is not a site made by holocap export web");
  testing::ExpectOneLineError(RunCli("view '" + (dir.path() / "missing").string() + "'"),
                              "is not a site");
  // A site of another version is refused too.
  WriteFileAtomic(dir.path() / "site" / "index.html", "<!doctype html>");
  WriteFileAtomic(dir.path() / "site" / "manifest.json",
                  R"({"format": "holocap-stream", "version": 99})");
  testing::ExpectOneLineError(RunCli("view '" + (dir.path() / "site").string() + "'"),
                              "version 99");
  // So is a site of version 1 (its mesh chunks are laid out differently); version 2 (before
  // the splat stream) still plays.
  WriteFileAtomic(dir.path() / "site" / "manifest.json",
                  R"({"format": "holocap-stream", "version": 1})");
  testing::ExpectOneLineError(RunCli("view '" + (dir.path() / "site").string() + "'"),
                              "version 1; this holocap plays versions " +
                                  std::to_string(kOldestWebStreamFormatVersion) + " to " +
                                  std::to_string(kWebStreamFormatVersion));
  WriteFileAtomic(dir.path() / "site" / "manifest.json",
                  R"({"format": "holocap-stream", "version": 2})");
  ViewServer first(dir.path() / "site");
  ASSERT_FALSE(first.url().empty()) << first.first_line();
  const std::string port = first.url().substr(first.url().rfind(':') + 1,
                                              first.url().size() - first.url().rfind(':') - 2);
  testing::ExpectOneLineError(
      RunCli("view '" + (dir.path() / "site").string() + "' --port " + port), "is in use");
}

}  // namespace
}  // namespace holocap
