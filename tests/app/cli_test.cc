// End-to-end tests of the holocap CLI on the simulated rig, and its bad-input contract: one
// clear error line and a non-zero exit.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <string>
#include <utility>
#include <vector>

#include "capture/drivers_built.h"
#include "capture/hal.h"
#include "capture/replay/replay_driver.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/report.h"
#include "core/take.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::RunCli;
using testing::TempDir;

using testing::ExpectOneLineError;

class SimulatedTake : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new TempDir("holocap-cli");
    auto result = RunCli("sim --rig single-rgbd --frames 3 --size 160x120 --no-noise --out " +
                         (dir_->path() / "take").string());
    ASSERT_EQ(result.exit_code, 0) << result.output;
  }
  static void TearDownTestSuite() { delete dir_; }
  static std::filesystem::path take() { return dir_->path() / "take"; }
  static TempDir* dir_;
};
TempDir* SimulatedTake::dir_ = nullptr;

TEST_F(SimulatedTake, InfoDescribesSensorsLensesAndGroundTruth) {
  auto result = RunCli("info --verify " + take().string());
  ASSERT_EQ(result.exit_code, 0) << result.output;
  EXPECT_NE(result.output.find("frame sets  3"), std::string::npos) << result.output;
  EXPECT_NE(result.output.find("ground truth yes"), std::string::npos) << result.output;
  EXPECT_NE(result.output.find("depth_m"), std::string::npos) << result.output;
  EXPECT_NE(result.output.find("true-lens=LENSMODEL_"), std::string::npos) << result.output;
  EXPECT_NE(result.output.find("sync spread"), std::string::npos) << result.output;
  EXPECT_NE(result.output.find("verified"), std::string::npos) << result.output;
}

TEST_F(SimulatedTake, ReplayReproducesEveryFrameBitExactly) {
  Take recorded = Take::Open(take());
  DriverRegistry registry;
  RegisterReplayDriver(registry);
  for (const auto& stream : recorded.streams()) {
    auto sensor = registry.Open(
        {.name = stream.name, .uri = "replay:" + take().string() + "#" + stream.name});
    sensor->Start();
    Frame frame;
    size_t count = 0;
    while (sensor->Grab(&frame, std::chrono::milliseconds(100))) {
      cv::Mat original = recorded.ReadFrame(count, stream.name);
      cv::Mat a = frame.image.reshape(1), b = original.reshape(1);
      ASSERT_EQ(a.size(), b.size());
      EXPECT_EQ(std::memcmp(a.data, b.data, a.total() * a.elemSize()), 0)
          << stream.name << " " << count;
      EXPECT_EQ(frame.timestamp_ns, recorded.entry(count).Find(stream.name)->timestamp_ns);
      ++count;
    }
    EXPECT_EQ(count, recorded.size()) << stream.name;
    // The take is not calibrated: its replay knows no model (the truth only when asked for).
    EXPECT_FALSE(sensor->known_model().has_value());
    auto truth = registry.Open({.name = stream.name,
                                .uri = "replay:" + take().string() + "#" + stream.name,
                                .options = {{"cameras", "truth"}}});
    ASSERT_TRUE(truth->known_model().has_value());
    EXPECT_TRUE(truth->known_model_is_truth());
  }
}

TEST_F(SimulatedTake, DevicesListsTheSimulatedRigsAndProbesASensor) {
  auto list = RunCli("devices");
  ASSERT_EQ(list.exit_code, 0) << list.output;
  EXPECT_NE(list.output.find("sim:studio8#cam0"), std::string::npos) << list.output;
  EXPECT_NE(list.output.find("sim:single-rgbd#depth0"), std::string::npos) << list.output;
  auto probe = RunCli("devices --probe 'replay:" + take().string() + "#cam0'");
  ASSERT_EQ(probe.exit_code, 0) << probe.output;
  EXPECT_NE(probe.output.find("160x120 bgr8"), std::string::npos) << probe.output;
}

TEST(DevicesCli, NamesEveryHardwareDriverCompiledInOrLeftOut) {
  auto list = RunCli("devices");
  ASSERT_EQ(list.exit_code, 0) << list.output;
  for (const BuiltDriver& driver : kHardwareDrivers) {
    // One line per driver, at the start of a line: its description, or why it is missing.
    const std::string line = Cat("\n", driver.scheme, ":  ");
    const size_t at = ("\n" + list.output).find(line);
    ASSERT_NE(at, std::string::npos) << driver.scheme << "\n" << list.output;
    const std::string left_out = Cat("not compiled in (", driver.why_not, ")\n");
    EXPECT_EQ(list.output.compare(at + line.size() - 1, left_out.size(), left_out) == 0,
              !driver.compiled)
        << driver.scheme << "\n"
        << list.output;
  }
}

TEST_F(SimulatedTake, CorruptTakesGiveOneClearError) {
  TempDir dir;
  std::filesystem::copy(take(), dir / "copy", std::filesystem::copy_options::recursive);
  // A truncated frame file: named in the error.
  auto frame = dir / "copy/frames/cam0/000001.png";
  std::filesystem::resize_file(frame, std::filesystem::file_size(frame) / 3);
  ExpectOneLineError(RunCli("info --verify " + (dir / "copy").string()), "000001.png");
  // A missing manifest.
  std::filesystem::remove(dir / "copy/take.json");
  ExpectOneLineError(RunCli("info " + (dir / "copy").string()), "take.json is missing");
  ExpectOneLineError(RunCli("info " + (dir / "nothing-here").string()), "does not exist");
}

// Through the CLI: info --verify exited 0 on a take marked complete that had
// lost data; each damage now fails it with one line naming the file and line.
TEST_F(SimulatedTake, VerifyRefusesATakeThatLostDataInOneLine) {
  TempDir dir;
  const auto copy = dir / "copy";
  std::filesystem::copy(take(), copy, std::filesystem::copy_options::recursive);
  std::filesystem::remove(copy / "frames/cam0/000001.png");
  ExpectOneLineError(RunCli("info --verify " + copy.string()),
                     "index.jsonl' line 2: frame file 'frames/cam0/000001.png' is missing");
  std::filesystem::remove(copy / "index.jsonl");
  ExpectOneLineError(RunCli("info --verify " + copy.string()),
                     "take.json' counts 3 frame sets but '" + (copy / "index.jsonl").string() +
                         "' is missing or empty");
  const std::string index = ReadFileToString(take() / "index.jsonl");
  const size_t second = index.find('\n') + 1;
  std::ofstream(copy / "index.jsonl")
      << index << index.substr(second, index.find('\n', second) + 1 - second);
  std::filesystem::copy(take() / "frames/cam0/000001.png", copy / "frames/cam0/000001.png");
  ExpectOneLineError(RunCli("info --verify " + copy.string()),
                     "index.jsonl' line 4: frame set 1 is listed again (first on line 2)");
}

// Through the CLI: a model with a negative focal length in a take is refused by
// every command that reads it (info --verify reads them all), naming file and field.
TEST_F(SimulatedTake, VerifyRefusesANegativeFocalLength) {
  TempDir dir;
  const auto copy = dir / "copy";
  std::filesystem::copy(take(), copy, std::filesystem::copy_options::recursive);
  const auto model = copy / "gt/cameras/cam0.cameramodel";
  CameraModel camera = CameraModel::Read(model);
  std::string text = camera.ToString();
  text.replace(text.find("'intrinsics': [ "), 16, "'intrinsics': [ -");
  std::ofstream(model) << text;
  ExpectOneLineError(RunCli("info --verify " + copy.string()),
                     "cam0.cameramodel': camera model: intrinsics[0] (fx) is -");
}

// Third-party stderr, binary bytes and allocation failures all end as the one
// error line.
TEST(Cli, ErrorsStayOneEscapedLine) {
  TempDir dir;
  // A garbage cameras.txt: its bytes are quoted escaped, never sent raw to the terminal.
  std::filesystem::create_directories(dir / "colmap/images");
  std::ofstream(dir / "colmap/cameras.txt", std::ios::binary)
      << std::string("1 \x1b[2J\xff\xfe\x01PINHOLE 10 10 1 1 5 5\n", 29);
  std::ofstream(dir / "colmap/images.txt") << "";
  std::ofstream(dir / "colmap/points3D.txt") << "";
  auto garbage =
      RunCli("import colmap " + (dir / "colmap").string() + " --out " + (dir / "t1").string());
  ExpectOneLineError(garbage, "unknown COLMAP camera model '\\x1b[2J\\xff\\xfe\\x01PINHOLE'");
  for (size_t i = 0; i + 1 < garbage.output.size(); ++i) {
    const unsigned char c = garbage.output[i];
    EXPECT_TRUE(c >= 0x20 && c < 0x7f) << "byte " << int{c} << " at " << i;
  }
  // libmrcal's own complaint is part of the line, not a line of its own.
  std::filesystem::create_directories(dir / "mrcal/left");
  cv::imwrite((dir / "mrcal/left/0.png").string(), cv::Mat(24, 32, CV_8UC3, cv::Scalar(1, 2, 3)));
  std::ofstream(dir / "mrcal/left.cameramodel")
      << "{ 'lensmodel': 'LENSMODEL_PINHOLE', 'intrinsics': [40, 40, 15.5, nan], "
         "'extrinsics': [0, 0, 0, 0, 0, 0], 'imagersize': [32, 24] }\n";
  ExpectOneLineError(
      RunCli("import mrcal " + (dir / "mrcal").string() + " --out " + (dir / "t2").string()),
      "left.cameramodel' is not a valid mrcal .cameramodel: libmrcal says: ");
  // An allocation that fails says so and what was asked (address space capped: no host has it).
  const std::string asked =
      "sim --rig single-rgbd --frames 1 --size 60000x60000 --no-noise --out " +
      (dir / "t3").string();
  auto huge = testing::RunShell("ulimit -v 1000000; HOLOCAP_NO_PROGRESS=1 '" + testing::CliPath() +
                                "' " + asked + " 2>&1");
  ExpectOneLineError(huge, "out of memory");
  EXPECT_NE(huge.output.find("(asked: holocap " + asked + ")"), std::string::npos) << huge.output;
}

TEST(Cli, BadInputGivesOneClearError) {
  TempDir dir;
  ExpectOneLineError(RunCli("devices --probe gopro:cam1"), "unknown URI scheme 'gopro'");
  ExpectOneLineError(RunCli("devices --probe nocolon"), "malformed sensor URI");
  std::ofstream(dir / "bad.yaml") << "name: x\nsensors: [ {name: cam0, uri: 'sim:x#cam0' ";
  ExpectOneLineError(RunCli("sim --frames 1 --rig " + (dir / "bad.yaml").string() + " --out " +
                            (dir / "t").string()),
                     "not valid YAML");
  ExpectOneLineError(RunCli("sim --rig studio9 --frames 1 --out " + (dir / "t2").string()),
                     "studio9");
  ExpectOneLineError(
      RunCli("sim --rig single-rgbd --frames 1 --size 64x48 --out /proc/holocap-denied/take"),
      "/proc/holocap-denied");
  std::filesystem::create_directories(dir / "full");
  std::ofstream(dir / "full/keep.txt") << "recorded";
  ExpectOneLineError(
      RunCli("sim --rig single-rgbd --frames 1 --size 64x48 --out " + (dir / "full").string()),
      "not empty");
  EXPECT_TRUE(std::filesystem::exists(dir / "full/keep.txt"));  // nothing already there is lost
}

// An option out of its bound ends in one line naming the flag as the user typed it, what
// followed it, and the bound, in every command (`live` and `scan` included). The checks run
// before anything is written (reconstruct claims its output first).
TEST_F(SimulatedTake, OptionErrorsNameTheFlagTypedItsValueAndTheBound) {
  TempDir dir;
  const std::string take_dir = take().string();
  // calibrate's failure report goes into the take's calib/: it gets a take of its own.
  std::filesystem::copy(take(), dir / "copy", std::filesystem::copy_options::recursive);
  const std::string scan = " --scan " + (dir / "scan").string();
  // " --out DIR/name"; every output but reconstruct's must still be missing at the end.
  std::vector<std::filesystem::path> unwritten;
  auto out = [&](const std::string& name, bool written = false) {
    if (!written) unwritten.push_back(dir / name);
    return " --out " + (dir / name).string();
  };
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"train nvol " + take_dir + out("nvol") + " --kl-weight -1",
       "--kl-weight -1 violates kl_weight >= 0"},
      {"live " + take_dir + scan + out("live") + " --gate -1", "--gate -1 violates gate_m > 0"},
      {"scan " + take_dir + out("scan0") + " --voxel 0", "--voxel must be > 0, got '0'"},
      {"scan " + take_dir + out("scan20") + " --voxel 20cm",
       "--voxel 20cm violates voxel_m <= 0.1"},
      {"reconstruct " + take_dir + out("recon", true) + " --voxel 2m",
       "--voxel 2m violates voxel_m < 1 (in (0, 1) m, or 0 for the plan's)"},
      {"train splat " + take_dir + out("splat") + " --iterations -5",
       "--iterations -5 violates iterations >= 0"},
      {"sim --rig single-rgbd --frames 0" + out("sim0"), "--frames 0 violates frames >= 1"},
      {"calibrate " + (dir / "copy").string() + " --threads -1",
       "--threads -1 violates threads >= 0"},
      {"merge " + take_dir + out("merged") + " --writers 0",
       "--writers 0 violates writer_threads in [1, 64]"},
      {"capture --rig " + (dir / "rig.yaml").string() + out("captured") +
           " --frames 5 --lost-after-periods 0",
       "--lost-after-periods 0 violates lost_after_periods in [1, 1000]"},
      // Flags of other names than their fields: the command's table, or the take selection's.
      {"train rerender " + take_dir + out("rerender") + " --width 64 --unet-width 2",
       "--unet-width 2 violates width in [4, 128] (channels)"},
      {"live " + take_dir + scan + out("live2") + " --min-inliers 1.5",
       "--min-inliers 1.5 violates min_inlier_fraction in [0, 1]"},
      {"sim --rig single-rgbd --frames 1 --size 4" + out("sim4"),
       "--size 4 violates image_width == 0 || image_width >= 8"},
      {"train nvol " + take_dir + out("nvol2") + " --frames 5:3",
       "--frames 5:3 violates last_frame < 0 || last_frame > first_frame (the range 5:3 is "
       "empty)"},
      // A budget must end, and a number is read whole.
      {"train splat " + take_dir + out("splat3") + " --minutes inf",
       "--minutes inf violates std::isfinite(minutes) (a budget must end)"},
      {"train nvol " + take_dir + out("nvol4") + " --minutes inf",
       "--minutes inf violates std::isfinite(minutes) (a budget must end)"},
      {"sim --rig single-rgbd --frames 1 --size 1e9" + out("sim1e9"),
       "--size must be WIDTH or WIDTHxHEIGHT in whole pixels (at most 999999), got '1e9'"},
      // A method's options are its own: another method's flag is refused by name.
      {"train splat " + take_dir + out("splat2") + " --witness 2",
       "train splat has no option '--witness'"},
      {"train nvol " + take_dir + out("nvol3") + " --seed-points 10",
       "train nvol has no option '--seed-points'"},
      // A field no flag fills: the line is the check's own, naming the struct and the field.
      {"export middlebury " + take_dir + out("exported"),
       "ExportOptions::format = middlebury violates "},
  };
  for (const auto& [args, line] : cases) {
    SCOPED_TRACE(args);
    ExpectOneLineError(RunCli(args), "holocap: error: " + line);
  }
  for (const auto& path : unwritten) EXPECT_FALSE(std::filesystem::exists(path)) << path;
}

// A thread count past the machine runs on the machine's limit (core/threads.h): each stage ends
// in a state and a report, as with any count (it once ended in a segmentation fault).
TEST_F(SimulatedTake, ThreadCountsPastTheMachineEndInAStateAndAReport) {
  TempDir dir;
  const std::string take_dir = take().string();
  const std::vector<std::pair<std::string, std::filesystem::path>> runs = {
      {"reconstruct " + take_dir + " --ground-truth-cameras --voxel 20mm --no-sweep --no-glb",
       dir / "recon"},
      {"train splat " + take_dir + " --ground-truth-cameras --iterations 2 --width 32",
       dir / "splat"},
  };
  for (const auto& [args, out] : runs) {
    SCOPED_TRACE(args);
    const auto result = RunCli(args + " --threads 100000 --out " + out.string());
    EXPECT_TRUE(result.exit_code == 0 || result.exit_code == 1)
        << "exit " << result.exit_code << "\n"
        << result.output;
    EXPECT_TRUE(std::filesystem::exists(out / "report.json")) << result.output;
  }
}

// holocap report reads what a run wrote: its outcome, metrics and series as text, the series
// as a plot; a directory is searched for reports.
TEST(Cli, ReportShowsOutcomeMetricsAndTheErrorAgainstTime) {
  TempDir dir;
  Report report("train");
  report.metrics()["heldout_psnr_db"] = 27.25;
  for (int i = 0; i < 20; ++i) report.AddPoint("loss", std::pow(0.5, i), i);
  report.SetSummary({Termination::kNoConvergence, "ran out of time"});
  report.Write(dir / "run/a/report.json");
  auto shown = RunCli("report " + (dir / "run/a/report.json").string() + " --rows 3 --out " +
                      (dir / "loss.png").string());
  ASSERT_EQ(shown.exit_code, 0) << shown.output;
  EXPECT_NE(shown.output.find("NO_CONVERGENCE: ran out of time"), std::string::npos)
      << shown.output;
  EXPECT_NE(shown.output.find("heldout_psnr_db"), std::string::npos) << shown.output;
  EXPECT_NE(shown.output.find("loss against time (20 points)"), std::string::npos) << shown.output;
  EXPECT_NE(shown.output.find("1.90735e-06"), std::string::npos)
      << "the last point is always shown";
  cv::Mat plot = cv::imread((dir / "loss.png").string());
  ASSERT_FALSE(plot.empty());
  EXPECT_GT(plot.rows, 200);

  auto all = RunCli("report " + (dir / "run").string() + " --out " + (dir / "plots").string());
  ASSERT_EQ(all.exit_code, 0) << all.output;
  EXPECT_TRUE(std::filesystem::exists(dir / "plots/a.png")) << all.output;

  std::ofstream(dir / "bad.json") << "{ \"command\": ";
  ExpectOneLineError(RunCli("report " + (dir / "bad.json").string()), "not valid JSON");
  ExpectOneLineError(RunCli("report " + (dir / "empty").string()), "does not exist");
}

// A number CLI11 cannot read as the flag's type ("1e9" for a count, "2.5" threads) printed
// CLI11's two lines; it is one error line like every other, and the number is never cut short.
TEST(Cli, NumbersAreReadWholeOrRefusedInOneLine) {
  ExpectOneLineError(RunCli("sim --rig studio8 --frames 1e9 --out /nonexistent/x"),
                     "Could not convert: --frames = 1e9 (holocap sim --help lists the options)");
  ExpectOneLineError(RunCli("reconstruct /nonexistent --threads 2.5"),
                     "Could not convert: --threads = 2.5");
  ExpectOneLineError(RunCli("sim --rig studio8 --size 1e9 --out /nonexistent/x"), "--size");
  ExpectOneLineError(RunCli(""), "A subcommand is required (holocap --help lists the options)");
  const auto help = RunCli("sim --help");
  EXPECT_EQ(help.exit_code, 0) << help.output;
}

// report printed a report.json's escape sequences raw (a file could retitle or clear the
// terminal) and ended wrong JSON types with nlohmann's bare "[json.exception.type_error.306]".
TEST(Cli, ReportPrintsNoEscapeSequenceAndNamesAFileOfWrongTypes) {
  TempDir dir;
  Report report("train");
  report.metrics()["psnr\x1b[2J"] = "\x1b]0;owned\x07";
  report.AddPoint("loss\x1b[31m", 1.0, 0);
  report.SetSummary({Termination::kSuccess, "done\x1b[2J\x1b]0;owned\x07"});
  report.Write(dir / "run/report.json");
  auto shown = RunCli("report " + (dir / "run/report.json").string());
  ASSERT_EQ(shown.exit_code, 0) << shown.output;
  EXPECT_EQ(shown.output.find('\x1b'), std::string::npos) << shown.output;
  EXPECT_EQ(shown.output.find('\x07'), std::string::npos) << shown.output;
  EXPECT_NE(shown.output.find("SUCCESS: done"), std::string::npos) << shown.output;
  std::ofstream(dir / "types.json") << R"({"command": "x", "summary": {"termination": 5}})";
  ExpectOneLineError(RunCli("report " + (dir / "types.json").string()),
                     "'" + (dir / "types.json").string() + "' is not a holocap report");
  std::ofstream(dir / "series.json")
      << R"({"command": "x", "summary": {}, "series": [{"metric": 5, "value": 1}]})";
  ExpectOneLineError(RunCli("report " + (dir / "series.json").string()),
                     "'" + (dir / "series.json").string() + "' holds a field of the wrong type");
}

// Several reports given at once share one plot: the series they all have, one line per run
// (two methods' held-out PSNR against time, say), each in its own colour.
TEST(Cli, ReportsGivenTogetherShareOnePlot) {
  TempDir dir;
  for (const std::string method : {"nvol", "splat"}) {
    Report report("train " + method);
    for (int i = 0; i < 10; ++i)
      report.AddPoint("heldout_psnr_db", 20 + i * (method == "splat" ? 1.0 : 0.5), i);
    report.AddPoint(method + "_only", 1, 0);
    report.SetSummary({Termination::kNoConvergence, "ran out of time"});
    report.Write(dir / method / "report.json");
  }
  auto shown =
      RunCli("report " + (dir / "nvol/report.json").string() + " " +
             (dir / "splat/report.json").string() + " --out " + (dir / "both.png").string());
  ASSERT_EQ(shown.exit_code, 0) << shown.output;
  EXPECT_NE(shown.output.find("plot: " + (dir / "both.png").string()), std::string::npos)
      << shown.output;
  EXPECT_FALSE(std::filesystem::exists(dir / "nvol.png"));
  const cv::Mat plot = cv::imread((dir / "both.png").string());
  ASSERT_FALSE(plot.empty());
  // One panel (heldout_psnr_db; the series only one run has are left out) below a legend of two.
  EXPECT_LT(plot.rows, 2 * 260);
  auto pixels_of = [&](const cv::Scalar& bgr) {
    cv::Mat match;
    cv::inRange(plot, bgr, bgr, match);
    return cv::countNonZero(match);
  };
  EXPECT_GT(pixels_of({180, 90, 20}), 100);   // the first run's line
  EXPECT_GT(pixels_of({30, 120, 230}), 100);  // the second's
}

}  // namespace
}  // namespace holocap
