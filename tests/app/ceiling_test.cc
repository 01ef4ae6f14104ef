// Every reader bounded: each hostile file below, given to the command that reads it under a
// 1 GB address-space ceiling (ulimit -v), ends in one error line and exit 1 within seconds: no
// abort on bad_alloc, no kill, no hang. Before, a frame linked to /dev/zero took 2-4 GB, a FIFO
// hung --verify, nested YAML aliases took 3.8 GB, a declared 30000x30000 frame 2.7 GB, and a
// model.json of 2000000000 Gaussians 22 GB.
#include <gtest/gtest.h>
#include <sys/stat.h>

#include <fstream>
#include <nlohmann/json.hpp>

#include "core/fs.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::ExpectOneLineError;
using testing::RunCli;
using testing::RunShell;
using testing::TempDir;
namespace fs = std::filesystem;

// `args` run by the CLI under a 1 GB ceiling, ended after 60 s at most (exit 124: a hang).
testing::CommandResult UnderCeiling(const std::string& args) {
  return RunShell("ulimit -v 1048576; timeout 60 '" + testing::CliPath() + "' " + args);
}

class ReaderCeiling : public ::testing::Test {
 protected:
  void SetUp() override {
    const auto sim = RunCli("sim --rig single-rgbd --frames 2 --size 96x72 --no-noise --out '" +
                            take().string() + "'");
    ASSERT_EQ(sim.exit_code, 0) << sim.output;
  }
  fs::path take() const { return dir_ / "take"; }
  fs::path Frame() const {
    const auto index = ReadFileToString(take() / "index.jsonl");
    const size_t at = index.find("\"file\":\"") + 8;
    return take() / index.substr(at, index.find('"', at) - at);
  }
  // DIR/model: a splat model.json declaring `declared` Gaussians of `degree`, beside a
  // gaussians.bin of `bytes` zero bytes and a finished training's report; returns the folder.
  fs::path SplatModel(int64_t declared, int degree, size_t bytes) const {
    fs::create_directories(dir_ / "model");
    WriteFileAtomic(dir_ / "model/model.json",
                    R"({"method": "splat", "gaussians": )" + std::to_string(declared) +
                        R"(, "sh_degree": )" + std::to_string(degree) +
                        R"(, "cameras": [], "box_min": [-1, -1, -1], "box_max": [1, 1, 1]})");
    WriteFileAtomic(dir_ / "model/gaussians.bin", std::string(bytes, '\0'));
    // A finished training's report, so that playback reads the model (and meets its sizes).
    WriteFileAtomic(dir_ / "model/report.json",
                    R"({"command": "train splat", "summary": {"termination": "CONVERGENCE",
                        "message": "written by hand"}})");
    return dir_ / "model";
  }
  void Verify(const std::string& needle) const {
    ExpectOneLineError(UnderCeiling("info '" + take().string() + "' --verify"), needle);
  }
  TempDir dir_;
};

TEST_F(ReaderCeiling, AFrameLinkedToDevZero) {
  fs::remove(Frame());
  fs::create_symlink("/dev/zero", Frame());
  Verify("is a symbolic link to '/dev/zero', outside the take");
}

TEST_F(ReaderCeiling, AFrameThatIsAFifo) {
  fs::remove(Frame());
  ASSERT_EQ(mkfifo(Frame().c_str(), 0644), 0);
  Verify("is not a regular file");
}

TEST_F(ReaderCeiling, ACameraModelLinkedToDevZero) {
  fs::create_directories(take() / "calib");
  const auto manifest = nlohmann::json::parse(ReadFileToString(take() / "take.json"));
  const std::string sensor = manifest["streams"][0]["name"];
  fs::create_symlink("/dev/zero", take() / "calib" / (sensor + ".cameramodel"));
  Verify("is not a regular file");
}

TEST_F(ReaderCeiling, AFrameSizeDeclaredPastThePixelLimit) {
  auto manifest = nlohmann::json::parse(ReadFileToString(take() / "take.json"));
  manifest["streams"][0]["width"] = 30000;
  manifest["streams"][0]["height"] = 30000;
  WriteFileAtomic(take() / "take.json", manifest.dump(2));
  Verify("declares 30000x30000 frames");
}

TEST_F(ReaderCeiling, ARigOfNestedAliases) {
  std::string laughs = "a: &a [x, x, x, x, x, x, x, x, x, x]\n";
  for (char c = 'b'; c <= 'i'; ++c) {
    laughs += std::string(1, c) + ": &" + std::string(1, c) + " [";
    for (int k = 0; k < 10; ++k) laughs += (k ? ", *" : "*") + std::string(1, c - 1);
    laughs += "]\n";
  }
  std::ofstream(dir_ / "laughs.yaml") << laughs << "sensors: [{name: a, uri: 'sim:x'}]\n";
  ExpectOneLineError(UnderCeiling("sim --rig '" + (dir_ / "laughs.yaml").string() +
                                  "' --frames 1 --size 64 --out '" + (dir_ / "out").string() + "'"),
                     "expands to more than 200000 values");
}

TEST_F(ReaderCeiling, ASplatModelDeclaringTwoBillionGaussians) {
  SplatModel(2000000000, 3, 236);  // one Gaussian's bytes at degree 3
  ExpectOneLineError(
      UnderCeiling("render '" + take().string() + "' --model '" + (dir_ / "model").string() +
                   "' --size 64 --views 1 --out '" + (dir_ / "renders").string() + "'"),
      "it declares 2000000000 Gaussians");
}

TEST_F(ReaderCeiling, ACameraPathOfTwoBillionViews) {
  SplatModel(1, 0, 56);  // one Gaussian at degree 0
  WriteFileAtomic(dir_ / "path.json",
                  R"({"views": 2000000000, "keys": [{"eye": [0, -3, 1], "look_at": [0, 0, 1]},
                                                   {"eye": [3, 0, 1], "look_at": [0, 0, 1]}]})");
  ExpectOneLineError(
      UnderCeiling("render '" + take().string() + "' --model '" + (dir_ / "model").string() +
                   "' --path '" + (dir_ / "path.json").string() + "' --size 64 --out '" +
                   (dir_ / "renders").string() + "'"),
      "\"views\" must be in [1, 1000000]");
}

TEST_F(ReaderCeiling, AReportOfAMillionNestedArrays) {
  WriteFileAtomic(dir_ / "report.json", std::string(1000000, '[') + std::string(1000000, ']'));
  ExpectOneLineError(UnderCeiling("report '" + (dir_ / "report.json").string() + "'"),
                     "is not valid JSON");
}

}  // namespace
}  // namespace holocap
