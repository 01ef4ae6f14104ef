// A splat ladder of budgets: a dynamic splat model trained on a 20-frame simulated take (budgets
// in iterations), exported at its `low` level held to two `--splat-mbps` budgets and at its own
// encoding, is one ladder of three streams, and a real headless Chromium
// (tests/playback/browser/drive.mjs ladder) plays it adaptively: up on the open link, down when
// Chromium's network emulation throttles it, back up when it is freed, switching at key frames.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <nlohmann/json.hpp>
#include <string>

#include "core/fs.h"
#include "tests/playback/view_server.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;
using testing::BrowserMissing;
using testing::RunCli;
using testing::RunShell;
using testing::TempDir;
using testing::ViewServer;

// 20 frame sets (19 after the clean plate): more than the page keeps decoded at buffer=5 (15), so
// that a looping stream is fetched again and again, through whatever the link allows; a key
// frame every 5 (where the page may switch).
constexpr int kFrames = 20;
constexpr int kBuffer = 5;

class WebSplatLadderTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new TempDir("holocap-splat-ladder");
    auto sim = RunCli("sim --rig studio8 --frames " + std::to_string(kFrames) +
                      " --clean-plate 1 --size 96 --seed 8 --out '" + Take().string() + "'");
    ASSERT_EQ(sim.exit_code, 0) << sim.output;
    auto trained = RunCli("train splat '" + Take().string() + "' --ground-truth-cameras --out '" +
                          Model().string() +
                          "' --width 64 --iterations 100 --frame-iterations 20 --seed-points "
                          "4000 --sh-degree 1 --eval-every 1000 --threads 1");
    ASSERT_TRUE(fs::exists(Model() / "deltas")) << trained.output;
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }
  static fs::path Take() { return dir_->path() / "take"; }
  static fs::path Model() { return dir_->path() / "splat"; }
  static testing::CommandResult Export(const fs::path& out, const std::string& flags) {
    return RunCli("export web '" + Take().string() +
                  "' --ground-truth-cameras --no-meshes --model '" + Model().string() +
                  "' --quality low --key-every 5" + flags + " --out '" + out.string() + "'");
  }
  static TempDir* dir_;
};
TempDir* WebSplatLadderTest::dir_ = nullptr;

const nlohmann::json& StreamNamed(const nlohmann::json& manifest, const std::string& name) {
  for (const auto& s : manifest.at("streams"))
    if (s.at("name") == name) return s;
  throw std::runtime_error("no stream " + name);
}

// `--splat-mbps B1,B2,0` (0.5 and 0.75 of the level's largest segment's rate, and its own
// encoding): one ladder of three streams in rate order, each budgeted stream's every segment (a
// key frame and its deltas) within its budget over its playing time; then played at 0.1x (software
// WebGL sorts and draws the splats in time on a loaded host), 5 frames fetched ahead: up to the
// level's own encoding on the open link, down when the link is throttled to a rate the lowest level
// climbs to and the top one does not keep, no climb back while throttled, back up once freed, every
// switch at a key frame.
TEST_F(WebSplatLadderTest, BudgetLadderPlaysAdaptively) {
  const fs::path own = dir_->path() / "own", site = dir_->path() / "site";
  auto exported = Export(own, "");
  ASSERT_EQ(exported.exit_code, 0) << exported.output;
  // The level's largest segment at its own encoding, as the export's report gives it.
  const double largest = nlohmann::json::parse(ReadFileToString(own / "report.json"))
                             .at("metrics")
                             .at("streams")
                             .at("splat-low")
                             .at("max_segment_mbps");
  const double budgets[2] = {std::round(50 * largest) / 100, std::round(75 * largest) / 100};
  char flag[64];
  std::snprintf(flag, sizeof(flag), " --splat-mbps %g,%g,0", budgets[0], budgets[1]);
  exported = Export(site, flag);
  ASSERT_EQ(exported.exit_code, 0) << exported.output;
  std::printf("%s\n%s", flag, exported.output.c_str());
  const nlohmann::json manifest = nlohmann::json::parse(ReadFileToString(site / "manifest.json"));
  const double fps = manifest.at("fps").get<double>();
  ASSERT_EQ(manifest.at("ladders").size(), 1u) << manifest.at("ladders").dump(1);
  const auto& ladder = manifest.at("ladders").at(0);
  EXPECT_EQ(ladder.at("name"), "splat");
  EXPECT_EQ(ladder.at("kind"), "splats");
  const auto& levels = ladder.at("levels");
  ASSERT_EQ(levels.size(), 3u) << levels.dump(1);
  for (size_t i = 1; i < levels.size(); ++i)
    EXPECT_GT(levels[i].at("mbps").get<double>(), levels[i - 1].at("mbps").get<double>());
  EXPECT_EQ(levels[2].at("stream"), "splat-low");
  for (int b = 0; b < 2; ++b) {
    char name[64];
    std::snprintf(name, sizeof(name), "splat-low-%gmbps", budgets[b]);
    EXPECT_EQ(levels[b].at("stream"), name);
    // Each segment's bytes over its frames (a frame without a chunk plays in it too).
    double bytes = 0;
    int frames = 0, segments = 0;
    auto close = [&] {
      if (frames > 0) EXPECT_LE(bytes * 8 * fps / 1e6 / frames, budgets[b]) << name;
      segments += frames > 0;
      bytes = 0;
      frames = 0;
    };
    for (const auto& chunk : StreamNamed(manifest, name).at("chunks")) {
      if (!chunk.is_null() && chunk.at("key").get<bool>()) close();
      ++frames;
      if (!chunk.is_null()) bytes += chunk.at("bytes").get<double>();
    }
    close();
    EXPECT_GE(segments, 4) << name;
  }
  const fs::path driver = testing::SourceDir() / "tests/playback/browser";
  if (const std::string why = BrowserMissing(driver); !why.empty()) GTEST_SKIP() << why;
  // At 0.1x: a throttle the lowest level climbs to (within 0.7 of it, with a tenth to spare) and
  // the top one does not keep (above 0.9 of it).
  const double speed = 0.1, lowest = speed * levels[0].at("mbps").get<double>();
  const double top = speed * levels[2].at("mbps").get<double>(), throttle = 1.1 * lowest / 0.7;
  ASSERT_GT(top, 0.9 * throttle) << "the top level fits the throttled link";
  ViewServer server(site);
  ASSERT_FALSE(server.url().empty()) << server.first_line();
  const fs::path out = dir_->path() / "browser";
  fs::create_directories(out);
  auto run = RunShell("node '" + (driver / "drive.mjs").string() + "' ladder " + server.url() +
                      " '" + out.string() + "' splat " + std::to_string(speed) + " " +
                      std::to_string(throttle) + " 20 " + std::to_string(kBuffer));
  const auto r = nlohmann::json::parse(ReadFileToString(out / "ladder.json"));
  ASSERT_TRUE(r.at("ok").get<bool>()) << run.output;
  std::printf("%s\n", r.dump(1).c_str());
  EXPECT_TRUE(r.at("consoleErrors").empty()) << r.dump(1);
  EXPECT_EQ(r.at("open").at("stream"), "splat-low");
  EXPECT_NE(r.at("down").at("stream"), "splat-low");
  EXPECT_LT(r.at("held").at("highestMbps").get<double>(), levels[2].at("mbps").get<double>());
  EXPECT_EQ(r.at("up").at("stream"), "splat-low");
  for (const auto& s : r.at("switches")) {
    EXPECT_TRUE(s.at("key").get<bool>()) << s.dump();
    EXPECT_TRUE(s.at("auto").get<bool>()) << s.dump();
  }
}

}  // namespace
}  // namespace holocap
