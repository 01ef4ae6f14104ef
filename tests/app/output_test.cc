// "Nothing recorded is ever lost", through the CLI: no command writes into a
// take's recording or over its own input, a non-empty folder another command made is written
// into only with --overwrite (which removes nothing), a replaced take is put back when its
// replacement fails, and a take has one writer at a time.
#include <gtest/gtest.h>

#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "core/fs.h"
#include "core/output.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::ExpectOneLineError;
using testing::RunCli;
using testing::TempDir;
namespace fs = std::filesystem;

// Every file under `dir` (relative name -> hash of its bytes): two calls compare a folder.
std::map<std::string, size_t> Contents(const fs::path& dir) {
  std::map<std::string, size_t> files;
  for (const auto& entry : fs::recursive_directory_iterator(dir)) {
    if (!entry.is_regular_file()) continue;
    const std::string name = fs::relative(entry.path(), dir).string();
    if (name == kTakeLockFile) continue;  // the lock's note is not part of the recording
    files[name] = std::hash<std::string>{}(ReadFileToString(entry.path()));
  }
  return files;
}

class OutputSafety : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new TempDir("holocap-output");
    auto result =
        RunCli("sim --rig single-rgbd --frames 2 --size 96x72 --no-noise --out " + take().string());
    ASSERT_EQ(result.exit_code, 0) << result.output;
  }
  static void TearDownTestSuite() { delete dir_; }
  static fs::path take() { return dir_->path() / "take"; }
  static TempDir* dir_;
};
TempDir* OutputSafety::dir_ = nullptr;

// `render` (and every other writer) refuses the take's recorded data and the take itself;
// the refusal comes before any model is read, and the take's bytes do not change.
TEST_F(OutputSafety, NoCommandWritesIntoATakesRecording) {
  const auto before = Contents(take());
  const std::string t = take().string();
  ExpectOneLineError(RunCli("render " + t + " --model " + t + "/models/nvol --size 64 --views 2" +
                            " --out " + t + "/frames/cam0"),
                     "is part of the recorded take");
  ExpectOneLineError(RunCli("render " + t + " --size 64 --views 2 --out " + t + " --overwrite"),
                     "is a take's directory");
  ExpectOneLineError(RunCli("render " + t + " --size 64 --views 2 --out " + t + "/gt/orbit.mp4"),
                     "(gt)");
  ExpectOneLineError(RunCli("reconstruct " + t + " --out " + t + "/calib --overwrite"), "(calib)");
  ExpectOneLineError(RunCli("train nvol " + t + " --iterations 1 --out " + t + "/frames"),
                     "(frames)");
  ExpectOneLineError(RunCli("export colmap " + t + " --out " + t + "/frames/depth --overwrite"),
                     "(frames)");
  ExpectOneLineError(RunCli("report " + t + "/report.json --out " + t + "/report.json --overwrite"),
                     "(report.json)");
  ExpectOneLineError(RunCli("sim --rig single-rgbd --frames 1 --size 64x48 --overwrite --out " + t +
                            "/frames/cam0"),
                     "(frames)");
  EXPECT_EQ(Contents(take()), before);
}

// A folder another command made (or the user's own) is written into only with --overwrite, and
// then nothing in it is removed; a command's own output it reuses without the flag.
TEST_F(OutputSafety, AForeignFolderNeedsOverwriteAndKeepsWhatIsThere) {
  TempDir dir;
  fs::create_directories(dir / "mine");
  std::ofstream(dir / "mine/notes.txt") << "the user's";
  const std::string export_to =
      "export colmap " + take().string() + " --ground-truth --no-images --out ";
  ExpectOneLineError(RunCli(export_to + (dir / "mine").string()), "did not make it");
  auto result = RunCli(export_to + (dir / "mine").string() + " --overwrite");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  EXPECT_EQ(ReadFileToString(dir / "mine/notes.txt"), "the user's");
  result = RunCli(export_to + (dir / "exported").string());
  ASSERT_EQ(result.exit_code, 0) << result.output;
  result = RunCli(export_to + (dir / "exported").string());  // its own output: no flag needed
  ASSERT_EQ(result.exit_code, 0) << result.output;
  ExpectOneLineError(RunCli("reconstruct " + take().string() + " --ground-truth-cameras --out " +
                            (dir / "exported").string()),
                     "(holocap export)");
}

// `import --overwrite` never removes its own source, and replaces a take whole.
TEST(ImportOutput, OverwriteNeverRemovesTheSourceAndAFailedReplacementPutsTheTakeBack) {
  TempDir dir;
  const fs::path dino = dir / "dino";
  fs::copy(testing::TestDataDir() / "middlebury" / "dinoSparseRing", dino);
  const auto source = Contents(dino);
  ExpectOneLineError(
      RunCli("import middlebury " + dino.string() + " --out " + dino.string() + " --overwrite"),
      "holds the input");
  ExpectOneLineError(RunCli("import middlebury " + (dino / "dinoSR_par.txt").string() + " --out " +
                            dino.string() + " --overwrite"),
                     "holds the input");
  EXPECT_EQ(Contents(dino), source);

  // A take made by import, replaced by a new import (one image changed): the new take in its
  // place, nothing of the old one left beside it (core's take test covers a failed one).
  const fs::path take = dir / "take";
  auto result = RunCli("import middlebury " + dino.string() + " --out " + take.string());
  ASSERT_EQ(result.exit_code, 0) << result.output;
  const auto imported = Contents(take);
  cv::Mat image = cv::imread((dino / "dinoSR0009.png").string(), cv::IMREAD_UNCHANGED);
  cv::resize(image, image, cv::Size(320, 240));
  cv::imwrite((dino / "dinoSR0009.png").string(), image);
  ExpectOneLineError(RunCli("import middlebury " + dino.string() + " --out " + take.string()),
                     "not empty");
  EXPECT_EQ(Contents(take), imported);
  result =
      RunCli("import middlebury " + dino.string() + " --out " + take.string() + " --overwrite");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  EXPECT_NE(Contents(take), imported);
  EXPECT_EQ(std::distance(fs::directory_iterator(dir.path()), fs::directory_iterator()), 2)
      << "nothing left beside the take";

  // --overwrite replaces a take only: a folder of the user's is not one.
  fs::create_directories(dir / "photos");
  std::ofstream(dir / "photos/holiday.jpg") << "jpeg";
  fs::copy(testing::TestDataDir() / "middlebury" / "dinoSparseRing", dir / "dino2");
  ExpectOneLineError(RunCli("import middlebury " + (dir / "dino2").string() + " --out " +
                            (dir / "photos").string() + " --overwrite"),
                     "holds no take");
  EXPECT_TRUE(fs::exists(dir / "photos/holiday.jpg"));
}

// A recording made by holocap capture is never replaced, even with --overwrite.
TEST_F(OutputSafety, ARecordingIsNeverReplaced) {
  TempDir dir;
  fs::copy(take(), dir / "recorded", fs::copy_options::recursive);
  auto manifest = nlohmann::json::parse(ReadFileToString(dir / "recorded/take.json"));
  manifest["metadata"]["capture"] = {{"rig", "two cameras"}};
  WriteFileAtomic(dir / "recorded/take.json", manifest.dump(2));
  const auto before = Contents(dir / "recorded");
  ExpectOneLineError(RunCli("sim --rig single-rgbd --frames 1 --size 64x48 --overwrite --out " +
                            (dir / "recorded").string()),
                     "recording made by holocap capture");
  EXPECT_EQ(Contents(dir / "recorded"), before);
}

// A render size no frame buffer can hold is refused by name, not bad_alloc.
TEST_F(OutputSafety, AnImpossibleRenderSizeIsOneLine) {
  TempDir dir;
  ExpectOneLineError(
      RunCli("render " + take().string() + " --size 100000 --out " + (dir / "orbit").string()),
      "--size 100000 is outside 8..8192 pixels");
  EXPECT_FALSE(fs::exists(dir / "orbit"));
}

// A command ended by an error leaves its report where a finished one would be: FAILURE, the
// error line's text, and the options it ran with; a refused output receives nothing.
TEST_F(OutputSafety, AFailedRunLeavesItsReport) {
  TempDir dir;
  const fs::path out = dir / "recon";
  // The take has one colour camera: a hull needs two (refused once the output is claimed).
  ExpectOneLineError(RunCli("reconstruct " + take().string() +
                            " --ground-truth-cameras --method hull --out " + out.string()),
                     "at least two colour cameras");
  const auto report = nlohmann::json::parse(ReadFileToString(out / "report.json"));
  EXPECT_EQ(report["summary"]["termination"], "FAILURE");
  EXPECT_NE(report["summary"]["message"].get<std::string>().find("at least two colour cameras"),
            std::string::npos);
  EXPECT_EQ(report["command"], "reconstruct");
  fs::create_directories(dir / "mine");
  std::ofstream(dir / "mine/notes.txt") << "the user's";
  ExpectOneLineError(RunCli("reconstruct " + take().string() + " --ground-truth-cameras --out " +
                            (dir / "mine").string()),
                     "did not make it");
  EXPECT_FALSE(fs::exists(dir / "mine/report.json"));
}

// A take has one writer at a time; the second gets one line naming the first, and the
// take is free again once the first has ended.
TEST_F(OutputSafety, ASecondWriterOfATakeIsRefusedNamingTheFirst) {
  const auto before = Contents(take());
  {
    const TakeLock held = TakeLock::Acquire(take(), "reconstruct");
    ExpectOneLineError(
        RunCli("reconstruct " + take().string() + " --ground-truth-cameras --method hull"),
        "is being written by pid " + std::to_string(::getpid()));
    ExpectOneLineError(RunCli("export nerf " + take().string() +
                              " --ground-truth --no-images --out " + (take() / "nerf").string()),
                       "one command writes into a take at a time");
    ExpectOneLineError(RunCli("calibrate " + take().string()), "is being written by");
  }
  auto result = RunCli("export nerf " + take().string() + " --ground-truth --no-images --out " +
                       (take() / "nerf").string());
  EXPECT_EQ(result.exit_code, 0) << result.output;
  fs::remove_all(take() / "nerf");
  EXPECT_EQ(Contents(take()), before);
}

// `sim --overwrite` into a folder holding any JSON take.json removed everything else there (a
// source tree, a take's recon/ and models/). A take is replaced only when this command made it
// and it holds nothing but what a take writer makes; the folder's bytes stay as they were.
TEST_F(OutputSafety, OverwriteReplacesOnlyATakeItMadeHoldingNothingElse) {
  TempDir dir;
  const std::string sim = "sim --rig single-rgbd --frames 1 --size 64x48 --overwrite --out ";
  fs::create_directories(dir / "proj/src");
  std::ofstream(dir / "proj/src/main.c") << "int main() {}\n";
  std::ofstream(dir / "proj/take.json") << R"({"name": "cfg"})";
  auto before = Contents(dir / "proj");
  ExpectOneLineError(RunCli(sim + (dir / "proj").string()), "not a holocap take's");
  EXPECT_EQ(Contents(dir / "proj"), before);

  fs::copy(take(), dir / "made", fs::copy_options::recursive);
  fs::create_directories(dir / "made/recon");
  std::ofstream(dir / "made/recon/mesh.ply") << "ply";
  std::ofstream(dir / "made/notes.txt") << "the user's";
  before = Contents(dir / "made");
  ExpectOneLineError(RunCli(sim + (dir / "made").string()),
                     "holds notes.txt, recon, which holocap sim did not make");
  EXPECT_EQ(Contents(dir / "made"), before);

  fs::remove_all(dir / "made/recon");
  fs::remove(dir / "made/notes.txt");
  auto manifest = nlohmann::json::parse(ReadFileToString(dir / "made/take.json"));
  EXPECT_EQ(manifest["made_by"], "sim");
  manifest["made_by"] = "import";
  WriteFileAtomic(dir / "made/take.json", manifest.dump(2));
  before = Contents(dir / "made");
  ExpectOneLineError(RunCli(sim + (dir / "made").string()), "holds a take made by holocap import");
  EXPECT_EQ(Contents(dir / "made"), before);

  manifest["made_by"] = "sim";
  WriteFileAtomic(dir / "made/take.json", manifest.dump(2));
  const auto result = RunCli(sim + (dir / "made").string());
  ASSERT_EQ(result.exit_code, 0) << result.output;
  EXPECT_NE(result.output.find("holocap sim: replacing the take '" + (dir / "made").string() +
                               "' (made by holocap sim, 2 frame sets)"),
            std::string::npos)
      << result.output;
}

// A calibration that fails kept nothing of the take's previous good report: its FAILURE
// replaced calib/report.json. It now goes beside it, as calib/report.failed.json.
TEST_F(OutputSafety, AFailedCalibrationLeavesThePreviousGoodReport) {
  TempDir dir;
  fs::copy(take(), dir / "take", fs::copy_options::recursive);
  fs::create_directories(dir / "take/calib");
  WriteFileAtomic(dir / "take/calib/report.json",
                  R"({"command": "calibrate", "summary": {"termination": "SUCCESS"}})");
  const auto before = Contents(dir / "take/calib");
  const auto result = RunCli("calibrate " + (dir / "take").string());
  EXPECT_NE(result.exit_code, 0) << result.output;
  auto after = Contents(dir / "take/calib");
  ASSERT_EQ(after.count("report.failed.json"), 1u) << result.output;
  after.erase("report.failed.json");
  EXPECT_EQ(after, before);
  const auto failed =
      nlohmann::json::parse(ReadFileToString(dir / "take/calib/report.failed.json"));
  EXPECT_EQ(failed["summary"]["termination"], "FAILURE");
}

// calibrate wrote through a calib/ that was a symbolic link into another take.
TEST_F(OutputSafety, CalibrateNeverWritesThroughALinkedCalibFolder) {
  TempDir dir;
  fs::copy(take(), dir / "a", fs::copy_options::recursive);
  fs::copy(take(), dir / "b", fs::copy_options::recursive);
  fs::create_directories(dir / "b/calib");
  std::ofstream(dir / "b/calib/report.json") << "{}";
  fs::create_directory_symlink(dir / "b/calib", dir / "a/calib");
  const auto before = Contents(dir / "b");
  ExpectOneLineError(RunCli("calibrate " + (dir / "a").string()), "is a symbolic link");
  EXPECT_EQ(Contents(dir / "b"), before);
}

// reconstruct A --out B/recon replaced some of B's sets: a mix of two takes, SUCCESS. The
// marker names its source; another take's results are written into only with --overwrite, and a
// link leading out of the take the path names is refused.
TEST_F(OutputSafety, AnotherTakesResultsAreNotMixedIn) {
  TempDir dir;
  fs::copy(take(), dir / "b", fs::copy_options::recursive);
  auto result = RunCli("reconstruct " + (dir / "b").string() + " --ground-truth-cameras");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  const auto before = Contents(dir / "b");
  ExpectOneLineError(RunCli("reconstruct " + take().string() + " --ground-truth-cameras --out " +
                            (dir / "b/recon").string()),
                     "holds holocap reconstruct's results of '" +
                         fs::canonical(dir / "b").string() + "', not of '" +
                         fs::canonical(take()).string() + "'");
  EXPECT_EQ(Contents(dir / "b"), before);
  // b/elsewhere, a link into another folder: where it leads is no part of take b.
  fs::create_directories(dir / "outside");
  fs::create_directory_symlink(dir / "outside", dir / "b/elsewhere");
  ExpectOneLineError(RunCli("reconstruct " + (dir / "b").string() +
                            " --ground-truth-cameras --out " + (dir / "b/elsewhere").string()),
                     "but a symbolic link leads it to");
  EXPECT_TRUE(fs::is_empty(dir / "outside"));
}

// Two train splat into one --out outside a take both ended SUCCESS, the later one replacing the
// first's model: an output outside a take now holds a lock like a take's.
TEST_F(OutputSafety, AnOutputOutsideATakeHasOneWriterAtATime) {
  TempDir dir;
  const fs::path out = dir / "model";
  const auto held = OutputDirectory::Claim(out, {"train splat", false, {}, false, take()});
  ExpectOneLineError(RunCli("train splat " + take().string() +
                            " --ground-truth-cameras --iterations 1 --out " + out.string()),
                     "is being written by pid " + std::to_string(::getpid()) + " (");
  ExpectOneLineError(RunCli("train splat " + take().string() +
                            " --ground-truth-cameras --iterations 1 --out " + out.string()),
                     "one command writes into an output at a time");
  EXPECT_FALSE(fs::exists(out / "model.json"));
}

// A frame that was a symbolic link to a file outside the take passed --verify and was copied
// out by export colmap; a rig sensor named ".." made sim write frames into the take's root.
TEST_F(OutputSafety, NoFrameIsReadThroughALinkOutOfItsTakeAndNoSensorIsAPath) {
  TempDir dir;
  fs::copy(take(), dir / "take", fs::copy_options::recursive);
  const auto index = ReadFileToString(dir / "take/index.jsonl");
  const size_t at = index.find("\"file\":\"") + 8;
  const fs::path frame = dir / "take" / index.substr(at, index.find('"', at) - at);
  std::ofstream(dir / "secret.png") << "not the take's";
  fs::remove(frame);
  fs::create_symlink(dir / "secret.png", frame);
  ExpectOneLineError(RunCli("export colmap " + (dir / "take").string() + " --ground-truth --out " +
                            (dir / "colmap").string()),
                     "outside the take: a take's frames lie inside it");
  if (fs::exists(dir / "colmap/images")) {
    for (const auto& entry : fs::recursive_directory_iterator(dir / "colmap/images"))
      EXPECT_FALSE(entry.is_regular_file()) << entry.path() << ": no frame is copied out";
  }
  std::ofstream(dir / "dots.yaml")
      << "name: dots\nsensors:\n  - {name: \"..\", uri: \"sim:x#a\"}\n";
  ExpectOneLineError(RunCli("sim --rig " + (dir / "dots.yaml").string() +
                            " --frames 1 --size 64 --out " + (dir / "dots").string()),
                     "sensor name '..' may not be '.' or '..'");
  EXPECT_FALSE(fs::exists(dir / "dots"));
}

}  // namespace
}  // namespace holocap
