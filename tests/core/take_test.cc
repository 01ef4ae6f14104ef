#include "core/take.h"

#include <gtest/gtest.h>
#include <signal.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <fstream>
#include <nlohmann/json.hpp>
#include <random>
#include <thread>

#include "core/error.h"
#include "core/fs.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::TempDir;

RigDescription TwoSensorRig() {
  RigDescription rig;
  rig.name = "test";
  rig.sensors = {{.name = "cam0", .uri = "sim:test#cam0"},
                 {.name = "depth0",
                  .uri = "sim:test#depth0",
                  .role = SensorRole::kDepth,
                  .paired_with = "cam0"}};
  return rig;
}

std::vector<StreamInfo> TwoStreams(ImageCodec color_codec = ImageCodec::kPng) {
  StreamInfo color{.name = "cam0",
                   .uri = "sim:test#cam0",
                   .width = 64,
                   .height = 48,
                   .pixel_format = "bgr8",
                   .codec = color_codec,
                   .clock = "sim"};
  StreamInfo depth{.name = "depth0",
                   .uri = "sim:test#depth0",
                   .role = SensorRole::kDepth,
                   .width = 32,
                   .height = 24,
                   .pixel_format = "depth_m",
                   .codec = ImageCodec::kExr,
                   .clock = "sim",
                   .paired_with = "cam0"};
  return {color, depth};
}

FrameSet RandomSet(int64_t index, uint64_t seed) {
  cv::RNG rng(seed);
  cv::Mat color(48, 64, CV_8UC3), depth(24, 32, CV_32FC1);
  rng.fill(color, cv::RNG::UNIFORM, 0, 256);
  rng.fill(depth, cv::RNG::UNIFORM, 0.3, 5.0);
  depth.at<float>(3, 4) = std::numeric_limits<float>::quiet_NaN();
  FrameSet set;
  set.index = index;
  set.frames.push_back({"cam0", color, 1000000 * index + 17, static_cast<uint64_t>(index)});
  set.frames.push_back({"depth0", depth, 1000000 * index + 250, static_cast<uint64_t>(index)});
  return set;
}

bool SameImage(const cv::Mat& a, const cv::Mat& b) {
  if (a.size() != b.size() || a.type() != b.type()) return false;
  cv::Mat a_bytes = a.reshape(1), b_bytes = b.reshape(1);
  if (a.depth() == CV_32F) {
    for (int r = 0; r < a_bytes.rows; ++r)
      for (int c = 0; c < a_bytes.cols; ++c) {
        float x = a_bytes.at<float>(r, c), y = b_bytes.at<float>(r, c);
        if (!(x == y || (std::isnan(x) && std::isnan(y)))) return false;
      }
    return true;
  }
  return cv::countNonZero(a_bytes != b_bytes) == 0;
}

TEST(Take, WritesAndReadsBackBitExactly) {
  for (ImageCodec codec : {ImageCodec::kPng, ImageCodec::kZstd}) {
    TempDir dir;
    {
      TakeWriter writer(dir / "take", TwoSensorRig(), TwoStreams(codec));
      for (int i = 0; i < 5; ++i) writer.Append(RandomSet(i, i));
      writer.CountDropped("cam0", 2);
      writer.Close();
    }
    Take take = Take::Open(dir / "take");
    EXPECT_EQ(take.state(), "complete");
    ASSERT_EQ(take.size(), 5u);
    EXPECT_EQ(take.dropped().at("cam0"), 2);
    EXPECT_EQ(take.rig().sensor("depth0").paired_with, "cam0");
    for (int i = 0; i < 5; ++i) {
      FrameSet expected = RandomSet(i, i);
      FrameSet got = take.Read(i);
      ASSERT_EQ(got.frames.size(), 2u);
      for (int k = 0; k < 2; ++k) {
        EXPECT_TRUE(SameImage(got.frames[k].image, expected.frames[k].image)) << i << " " << k;
        EXPECT_EQ(got.frames[k].timestamp_ns, expected.frames[k].timestamp_ns);
      }
      EXPECT_EQ(take.entry(i).spread_ns, 233);
    }
  }
}

TEST(Take, RefusesToOverwriteAndNamesBadFrames) {
  TempDir dir;
  {
    TakeWriter writer(dir / "take", TwoSensorRig(), TwoStreams());
    FrameSet wrong = RandomSet(0, 0);
    wrong.frames[0].image = cv::Mat(10, 10, CV_8UC3);
    EXPECT_THROW(writer.Append(wrong), Error);
    FrameSet stranger = RandomSet(0, 0);
    stranger.frames[0].sensor = "cam9";
    EXPECT_THROW(writer.Append(stranger), Error);
  }
  EXPECT_THROW(TakeWriter(dir / "take", TwoSensorRig(), TwoStreams()), Error);
}

// --overwrite replaces a take only with a complete one: a replacement abandoned by an exception
// puts the old take back whole; a completed one leaves nothing of the old beside it.
TEST(Take, AReplacementAbandonedByAnErrorPutsTheOldTakeBack) {
  TempDir dir;
  {
    TakeWriter writer(dir / "take", TwoSensorRig(), TwoStreams());
    writer.Append(RandomSet(0, 1));
    writer.Append(RandomSet(1, 2));
  }
  const std::string manifest = ReadFileToString(dir / "take/take.json");
  const cv::Mat frame = Take::Open(dir / "take").ReadFrame(1, "cam0");
  TakeWriterOptions replace;
  replace.overwrite = true;
  EXPECT_THROW(
      {
        TakeWriter writer(dir / "take", TwoSensorRig(), TwoStreams(), {}, replace);
        writer.Append(RandomSet(0, 7));
        FrameSet wrong = RandomSet(1, 8);
        wrong.frames[0].image = cv::Mat(10, 10, CV_8UC3);
        writer.Append(wrong);  // throws: the writer is abandoned mid-take
      },
      Error);
  EXPECT_EQ(ReadFileToString(dir / "take/take.json"), manifest);
  EXPECT_TRUE(SameImage(Take::Open(dir / "take").ReadFrame(1, "cam0"), frame));
  EXPECT_EQ(std::distance(fs::directory_iterator(dir.path()), fs::directory_iterator()), 1);
  {
    TakeWriter writer(dir / "take", TwoSensorRig(), TwoStreams(), {}, replace);
    writer.Append(RandomSet(0, 9));
    writer.Close();
  }
  EXPECT_EQ(Take::Open(dir / "take").size(), 1u);
  EXPECT_EQ(std::distance(fs::directory_iterator(dir.path()), fs::directory_iterator()), 1);
}

// A writer killed with SIGKILL mid-take leaves a take that opens with every complete set.
TEST(Take, SurvivesKillNineMidWrite) {
  TempDir dir;
  auto take_dir = dir / "take";
  pid_t child = fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    TakeWriter writer(take_dir, TwoSensorRig(), TwoStreams());
    for (int i = 0;; ++i) writer.Append(RandomSet(i, i));
  }
  // Wait until a few sets are in the index, then kill without warning.
  for (int tries = 0; tries < 2000; ++tries) {
    std::ifstream index(take_dir / "index.jsonl");
    int lines = std::count(std::istreambuf_iterator<char>(index), {}, '\n');
    if (lines >= 12) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  kill(child, SIGKILL);
  int status = 0;
  waitpid(child, &status, 0);
  ASSERT_TRUE(WIFSIGNALED(status));
  Take take = Take::Open(take_dir);
  EXPECT_EQ(take.state(), "recording");
  ASSERT_GE(take.size(), 12u);
  for (size_t i = 0; i < take.size(); ++i) {
    FrameSet set = take.Read(i);
    FrameSet expected = RandomSet(take.entry(i).index, take.entry(i).index);
    ASSERT_EQ(set.frames.size(), 2u);
    EXPECT_TRUE(SameImage(set.frames[0].image, expected.frames[0].image));
    EXPECT_TRUE(SameImage(set.frames[1].image, expected.frames[1].image));
  }
}

TEST(Take, SkipsATornIndexLineAndSetsWithMissingFrames) {
  TempDir dir;
  {
    TakeWriter writer(dir / "take", TwoSensorRig(), TwoStreams());
    for (int i = 0; i < 4; ++i) writer.Append(RandomSet(i, i));
  }
  std::filesystem::remove(dir / "take/frames/cam0/000002.png");
  {
    std::ofstream index(dir / "take/index.jsonl", std::ios::app);
    index << R"({"set": 4, "frames": [{"sensor": "cam0", "fi)";
  }
  Take take = Take::Open(dir / "take");
  EXPECT_EQ(take.size(), 3u);
  EXPECT_EQ(take.skipped_index_lines(), 2);
}

TEST(Take, BadInputGivesOneClearError) {
  TempDir dir;
  try {
    Take::Open(dir.path());
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("take.json is missing"), std::string::npos) << e.what();
  }
  {
    TakeWriter writer(dir / "take", TwoSensorRig(), TwoStreams());
    writer.Append(RandomSet(0, 0));
  }
  // Truncate a frame file: reading it names the file.
  auto frame = dir / "take/frames/depth0/000000.exr";
  std::filesystem::resize_file(frame, std::filesystem::file_size(frame) / 2);
  Take take = Take::Open(dir / "take");
  try {
    take.Read(0);
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("000000.exr"), std::string::npos) << e.what();
  }
  auto png = dir / "take/frames/cam0/000000.png";
  std::filesystem::resize_file(png, std::filesystem::file_size(png) / 2);
  EXPECT_THROW(take.ReadFrame(0, "cam0"), Error);
  {
    std::ofstream manifest(dir / "take/take.json");
    manifest << "{\"format\": \"holocap-take\", \"format_version\": 99}";
  }
  EXPECT_THROW(Take::Open(dir / "take"), Error);
  EXPECT_THROW(TakeWriter("/proc/holocap-cannot-write", TwoSensorRig(), TwoStreams()), Error);
}

// Found by fuzz_take_json: a number JSON cannot hold escaped Open as nlohmann's out_of_range.
TEST(Take, ManifestNumbersJsonCannotHoldGiveOneClearError) {
  const auto exists = [](const std::string&) { return true; };
  try {
    Take::Parse("T", "6E12644", "", exists);
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("T/take.json' is corrupt"), std::string::npos) << e.what();
  }
  EXPECT_THROW(
      Take::Parse("T", R"({"format": "holocap-take", "format_version": 1e999})", "", exists),
      Error);
}

// nlohmann's get<int>() cast 1e100 to int (undefined behaviour: UBSan in fuzz_take_json stops
// on it) and wrapped -4294967295 to 1; integers out of range are refused in take.json and make
// an index line skipped.
TEST(Take, IntegersOutOfRangeAreRefused) {
  const auto exists = [](const std::string&) { return true; };
  const std::string head = R"({"format": "holocap-take", "rig": {"sensors": [{"name": "c",
    "uri": "sim:x#c"}]}, "streams": [{"name": "c", "pixel_format": "mono8", "height": 4, )";
  EXPECT_NO_THROW(Take::Parse("T", head + R"("width": 6.0}], "format_version": 1})", "", exists));
  for (const char* tail : {R"("width": 1e100}], "format_version": 1})",
                           R"("width": 6}], "format_version": -4294967295})",
                           R"("width": 6}], "format_version": 1.5})",
                           R"("width": 6}], "format_version": 1, "dropped": {"c": 1e300}})"}) {
    try {
      Take::Parse("T", head + tail, "", exists);
      ADD_FAILURE() << tail;
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find("must be an integer in"), std::string::npos) << e.what();
    }
  }
  const std::string manifest = head + R"("width": 6}], "format_version": 1})";
  Take take = Take::Parse("T", manifest,
                          R"({"set": 0, "frames": [{"sensor": "c", "file": "a", "t_ns": 1}]}
{"set": 1e100, "frames": []}
{"set": 2, "frames": [{"sensor": "c", "file": "b", "t_ns": 1e300}]}
{"set": 3, "frames": [{"sensor": "c", "file": "d", "t_ns": 1, "seq": -1}]}
)",
                          exists);
  EXPECT_EQ(take.size(), 1u);
  EXPECT_EQ(take.skipped_index_lines(), 3);
}

// An index line naming a file the file system refuses (a name too long) is skipped like a line
// naming a missing frame, not a std::filesystem error.
TEST(Take, IndexLineWithAnImpossibleFileNameIsSkipped) {
  TempDir dir;
  {
    TakeWriter writer(dir / "take", TwoSensorRig(), TwoStreams());
    writer.Append(RandomSet(0, 0));
  }
  {
    std::ofstream index(dir / "take/index.jsonl", std::ios::app);
    index << R"({"set": 1, "frames": [{"sensor": "cam0", "t_ns": 1, "file": ")"
          << std::string(5000, 'x') << "\"}]}\n";
  }
  Take take = Take::Open(dir / "take");
  EXPECT_EQ(take.size(), 1u);
  EXPECT_EQ(take.skipped_index_lines(), 1);
}

// `info --verify` passed a take marked complete that had lost data. Each damage
// is refused by Take::Verify (what info --verify runs), or by Open where no writer could have
// left it, with one message naming the file and line.
class DamagedTake : public ::testing::Test {
 protected:
  void SetUp() override {
    TakeWriter writer(dir_ / "take", TwoSensorRig(), TwoStreams());
    for (int i = 0; i < 3; ++i) writer.Append(RandomSet(i, i));
    writer.Close();
    index_ = ReadFileToString(dir_ / "take/index.jsonl");
  }
  std::filesystem::path take() const { return dir_ / "take"; }
  void WriteIndex(const std::string& text) const { std::ofstream(take() / "index.jsonl") << text; }
  std::string Line(int n) const {  // 1-based, with its '\n'
    size_t at = 0;
    for (int i = 1; i < n; ++i) at = index_.find('\n', at) + 1;
    return index_.substr(at, index_.find('\n', at) + 1 - at);
  }
  // The message of the Error `call` throws ("" when none).
  static std::string ErrorOf(const std::function<void()>& call) {
    try {
      call();
    } catch (const Error& e) {
      return e.what();
    }
    return "";
  }
  TempDir dir_;
  std::string index_;
};

TEST_F(DamagedTake, AnIntactTakeVerifies) {
  Take opened = Take::Open(take());
  EXPECT_EQ(opened.manifest_frame_sets(), 3);
  EXPECT_NO_THROW(opened.Verify());
}

TEST_F(DamagedTake, AMissingFrameFileIsNamedWithItsIndexLine) {
  std::filesystem::remove(take() / "frames/depth0/000001.exr");
  Take opened = Take::Open(take());  // a take cut short still opens...
  EXPECT_EQ(opened.size(), 2u);
  const std::string error = ErrorOf([&] { opened.Verify(); });  // ...but does not verify
  EXPECT_NE(error.find("index.jsonl' line 2: frame file 'frames/depth0/000001.exr' is missing"),
            std::string::npos)
      << error;
}

TEST_F(DamagedTake, AnEmptyOrMissingIndexDoesNotHoldWhatTakeJsonCounts) {
  for (bool remove : {false, true}) {
    if (remove) {
      std::filesystem::remove(take() / "index.jsonl");
    } else {
      WriteIndex("");
    }
    const std::string error = ErrorOf([&] { Take::Open(take()).Verify(); });
    EXPECT_NE(error.find("take.json' counts 3 frame sets but '"), std::string::npos) << error;
    EXPECT_NE(error.find("index.jsonl' is missing or empty"), std::string::npos) << error;
  }
  WriteIndex(Line(1) + Line(3));
  const std::string error = ErrorOf([&] { Take::Open(take()).Verify(); });
  EXPECT_NE(
      error.find("counts 3 frame sets but '" + (take() / "index.jsonl").string() + "' lists 2"),
      std::string::npos)
      << error;
}

TEST_F(DamagedTake, ADuplicatedIndexLineIsRefused) {
  WriteIndex(Line(1) + Line(2) + Line(3) + Line(2));
  const std::string error = ErrorOf([&] { Take::Open(take()); });
  EXPECT_NE(error.find("index.jsonl' line 4: frame set 1 is listed again (first on line 2)"),
            std::string::npos)
      << error;
}

TEST_F(DamagedTake, AFrameFileOutsideTheTakeIsRefused) {
  std::filesystem::create_directories(dir_ / "other/frames/cam0");
  std::filesystem::copy(take() / "frames/cam0/000002.png", dir_ / "other/frames/cam0/000002.png");
  for (const std::string& file : {std::string("../other/frames/cam0/000002.png"),
                                  (dir_ / "other/frames/cam0/000002.png").string(),
                                  std::string("frames/../../other/frames/cam0/000002.png")}) {
    std::string line = Line(3);
    const std::string original = "frames/cam0/000002.png";
    line.replace(line.find(original), original.size(), file);
    WriteIndex(Line(1) + Line(2) + line);
    const std::string error = ErrorOf([&] { Take::Open(take()); });
    EXPECT_NE(error.find("index.jsonl' line 3: frame file '" + file + "'"), std::string::npos)
        << error;
    EXPECT_NE(error.find("frames must lie inside the take"), std::string::npos) << error;
  }
}

TEST_F(DamagedTake, ACutShortTakeStillVerifiesWithItsTornLastLine) {
  auto set_state = [&](const std::string& from, const std::string& to) {
    std::string manifest = ReadFileToString(take() / "take.json");
    manifest.replace(manifest.find(from), from.size(), to);
    std::ofstream(take() / "take.json") << manifest;
  };
  set_state("\"complete\"", "\"recording\"");
  WriteIndex(index_ + R"({"set": 3, "frames": [{"sensor": "cam0", "fi)");
  EXPECT_NO_THROW(Take::Open(take()).Verify());
  // A torn line in a take marked complete is lost data.
  set_state("\"recording\"", "\"complete\"");
  const std::string error = ErrorOf([&] { Take::Open(take()).Verify(); });
  EXPECT_NE(error.find("index.jsonl' line 4: torn"), std::string::npos) << error;
}

// A small PNG whose header claims 20000x20000x16-bit was decoded whole (2.5 GB)
// before its size was compared with its stream's. The header is now checked first.
TEST_F(DamagedTake, AFrameWhoseHeaderClaimsAHugeImageIsRefusedBeforeDecoding) {
  // A valid PNG of a header alone: IHDR 20000x20000, 16-bit RGB, then IEND (CRCs correct).
  auto chunk = [](const std::string& type, const std::string& data) {
    auto be32 = [](uint32_t v) {
      return std::string{static_cast<char>(v >> 24), static_cast<char>(v >> 16),
                         static_cast<char>(v >> 8), static_cast<char>(v)};
    };
    std::string body = type + data;
    uint32_t crc = 0xffffffffu;
    for (unsigned char c : body) {
      crc ^= c;
      for (int k = 0; k < 8; ++k) crc = (crc >> 1) ^ (0xedb88320u & (0u - (crc & 1)));
    }
    return be32(static_cast<uint32_t>(data.size())) + body + be32(~crc);
  };
  const std::string ihdr{0, 0, 0x4e, 0x20, 0, 0, 0x4e, 0x20, 16, 2, 0, 0, 0};
  const std::string png =
      std::string("\x89PNG\r\n\x1a\n", 8) + chunk("IHDR", ihdr) + chunk("IEND", "");
  std::ofstream(take() / "frames/cam0/000001.png", std::ios::binary) << png;
  const std::string error = ErrorOf([&] { Take::Open(take()).Verify(); });
  EXPECT_NE(error.find("000001.png': its PNG header says 20000x20000 16-bit but its stream's "
                       "frames are 64x48 8-bit"),
            std::string::npos)
      << error;
  // Read with no declared size, the pixel budget refuses it.
  const std::string alone = ErrorOf([&] { ReadImage(take() / "frames/cam0/000001.png"); });
  EXPECT_NE(alone.find("more than the 134217728 pixels"), std::string::npos) << alone;
}

// The index claims what --verify now checks: each stream once, sets and times counted from 0
// and never going back, each frame file named once, nothing after an image's end, frames that
// are regular files inside the take. Each of these passed info --verify before.
TEST_F(DamagedTake, AStreamListedTwiceIsRefused) {
  std::string manifest = ReadFileToString(take() / "take.json");
  nlohmann::json json = nlohmann::json::parse(manifest);
  json["streams"].push_back(json["streams"][0]);
  std::ofstream(take() / "take.json") << json.dump(2);
  const std::string error = ErrorOf([&] { Take::Open(take()); });
  EXPECT_NE(error.find("take.json': stream 'cam0' is listed twice"), std::string::npos) << error;
}

TEST_F(DamagedTake, ANegativeSetOrTimeIsRefused) {
  std::string line = Line(3);
  line.replace(line.find("\"set\":2"), 7, "\"set\":-5");
  WriteIndex(Line(1) + Line(2) + line);
  std::string error = ErrorOf([&] { Take::Open(take()); });
  EXPECT_NE(error.find("line 3: frame set -5 is negative"), std::string::npos) << error;
  line = Line(3);
  const size_t at = line.find("\"t_ns\":");
  line.replace(at, line.find_first_of(",}", at) - at, "\"t_ns\":-9223372036854775808");
  WriteIndex(Line(1) + Line(2) + line);
  error = ErrorOf([&] { Take::Open(take()); });
  EXPECT_NE(error.find("line 3: frame of 'cam0' in set 2 has time -9223372036854775808 ns"),
            std::string::npos)
      << error;
}

TEST_F(DamagedTake, AFrameFileNamedTwiceIsRefused) {
  // Set 2's line naming set 1's files: two frame sets read from one pair of files.
  std::string line = Line(2);
  line.replace(line.find("\"set\":1"), 7, "\"set\":2");
  WriteIndex(Line(1) + Line(2) + line);
  const std::string error = ErrorOf([&] { Take::Open(take()); });
  EXPECT_NE(error.find("line 3: frame file 'frames/cam0/000001.png' is listed again (first on "
                       "line 2)"),
            std::string::npos)
      << error;
}

TEST_F(DamagedTake, TimesGoingBackAreRefused) {
  std::string line = Line(3);
  const size_t at = line.find("\"t_ns\":");
  line.replace(at, line.find_first_of(",}", at) - at, "\"t_ns\":5");
  WriteIndex(Line(1) + Line(2) + line);
  const std::string error = ErrorOf([&] { Take::Open(take()).Verify(); });
  EXPECT_NE(error.find("the frame of 'cam0' in set 2 has time 5 ns, before set 1's 1000017 ns"),
            std::string::npos)
      << error;
}

TEST_F(DamagedTake, BytesAfterAnImagesEndAreRefused) {
  std::ofstream(take() / "frames/cam0/000001.png", std::ios::binary | std::ios::app)
      << std::string(4096, 'x');
  const std::string error = ErrorOf([&] { Take::Open(take()).Verify(); });
  EXPECT_NE(error.find("000001.png' has 4096 bytes after the end of its image"), std::string::npos)
      << error;
}

TEST_F(DamagedTake, AFrameLinkedOutsideTheTakeIsRefused) {
  std::filesystem::create_directories(dir_ / "other");
  std::filesystem::rename(take() / "frames/cam0/000001.png", dir_ / "other/000001.png");
  std::filesystem::create_symlink(dir_ / "other/000001.png", take() / "frames/cam0/000001.png");
  const std::string error = ErrorOf([&] { Take::Open(take()).Verify(); });
  EXPECT_NE(error.find("000001.png' is a symbolic link to '" + (dir_ / "other").string()),
            std::string::npos)
      << error;
  EXPECT_NE(error.find("outside the take"), std::string::npos) << error;
  // A link that stays inside the take is a frame like any other.
  std::filesystem::rename(dir_ / "other/000001.png", take() / "frames/cam0/kept.png");
  std::filesystem::remove(take() / "frames/cam0/000001.png");
  std::filesystem::create_symlink("kept.png", take() / "frames/cam0/000001.png");
  EXPECT_NO_THROW(Take::Open(take()).Verify());
}

TEST_F(DamagedTake, AFrameThatIsAFifoOrADeviceIsRefusedWithoutWaiting) {
  const auto frame = take() / "frames/cam0/000001.png";
  std::filesystem::remove(frame);
  ASSERT_EQ(mkfifo(frame.c_str(), 0644), 0);
  std::string error = ErrorOf([&] { Take::Open(take()).Verify(); });  // no writer: would hang
  EXPECT_NE(error.find("000001.png' is not a regular file"), std::string::npos) << error;
  std::filesystem::remove(frame);
  // /dev/zero inside the take's own tree is still no frame: it never ends.
  std::filesystem::create_symlink("/dev/zero", frame);
  error = ErrorOf([&] { Take::Open(take()).Verify(); });
  EXPECT_FALSE(error.empty());
  error = ErrorOf([&] { ReadFileToString("/dev/zero"); });
  EXPECT_NE(error.find("'/dev/zero' is not a regular file"), std::string::npos) << error;
}

TEST_F(DamagedTake, AStreamDeclaringFramesPastThePixelLimitIsRefused) {
  nlohmann::json json = nlohmann::json::parse(ReadFileToString(take() / "take.json"));
  json["streams"][0]["width"] = 30000;
  json["streams"][0]["height"] = 30000;
  std::ofstream(take() / "take.json") << json.dump(2);
  const std::string error = ErrorOf([&] { Take::Open(take()); });
  EXPECT_NE(error.find("stream 'cam0' declares 30000x30000 frames; a frame has 1 to 134217728 "
                       "pixels"),
            std::string::npos)
      << error;
}

}  // namespace
}  // namespace holocap
