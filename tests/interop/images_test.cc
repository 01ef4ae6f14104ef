// Photographs and videos as takes (holocap import images) and a take's frames as images and
// videos (holocap export images), through the CLI: a simulated stereo board take calibrates
// from its JPEG folders and its MP4s as from the take itself; pairing rules, kept pixel
// formats, and every bad input's one error line with no take left behind.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "core/camera.h"
#include "core/fs.h"
#include "core/take.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::ExpectOneLineError;
using testing::RunCli;
using testing::TempDir;

// Two cameras 0.4 m apart looking at the board's stage, 640x480, OPENCV5 lenses.
constexpr const char* kStereoRig = R"(name: stereo
sync: hardware
fps: 30
sensors:
  - name: left
    uri: sim:stereo#left
    role: color
    options:
      lens: LENSMODEL_OPENCV5
      intrinsics: [520.0, 519.0, 322.0, 238.0, -0.12, 0.09, 0.0004, -0.0003, -0.02]
      size: [640, 480]
      position: [2.6, -0.2, 1.3]
      look_at: [0.0, -0.1, 1.1]
  - name: right
    uri: sim:stereo#right
    role: color
    options:
      lens: LENSMODEL_OPENCV5
      intrinsics: [515.0, 515.5, 318.0, 242.0, -0.10, 0.07, -0.0002, 0.0005, -0.01]
      size: [640, 480]
      position: [2.6, 0.2, 1.3]
      look_at: [0.0, 0.1, 1.1]
)";

// What a calibration says of the pair: per camera fx fy cx cy and their 1-sigma, the baseline
// (the right camera's centre from the left's) and its 1-sigma.
struct PairCalibration {
  std::map<std::string, std::vector<double>> intrinsics, sigma;
  double baseline_mm = 0;
  double baseline_sigma_mm = 0;
};

PairCalibration ReadCalibration(const std::filesystem::path& take) {
  const auto report = nlohmann::json::parse(ReadFileToString(take / "calib" / "report.json"));
  EXPECT_EQ(report["summary"]["termination"], "CONVERGENCE") << report["summary"].dump();
  PairCalibration out;
  const auto& cameras = report["metrics"]["cameras"];
  for (const std::string camera : {"left", "right"}) {
    const auto intrinsics = cameras[camera]["intrinsics"].get<std::vector<double>>();
    const auto sigma = cameras[camera]["intrinsics_sigma"].get<std::vector<double>>();
    out.intrinsics[camera].assign(intrinsics.begin(), intrinsics.begin() + 4);
    out.sigma[camera].assign(sigma.begin(), sigma.begin() + 4);
  }
  const auto rt = cameras["right"]["rt_cam_ref"].get<std::vector<double>>();
  out.baseline_mm = 1000 * std::sqrt(rt[3] * rt[3] + rt[4] * rt[4] + rt[5] * rt[5]);
  out.baseline_sigma_mm = cameras["right"]["center_sigma_mm"].get<double>();
  return out;
}

// Largest |difference| over fx fy cx cy of both cameras and the baseline, each divided by
// `sigma_scale` times the 1-sigma `reference` reports for it.
double WorstSigmas(const PairCalibration& a, const PairCalibration& b,
                   const PairCalibration& reference, double sigma_scale, std::string* where) {
  double worst = 0;
  const char* names[] = {"fx", "fy", "cx", "cy"};
  for (const std::string camera : {"left", "right"}) {
    for (int k = 0; k < 4; ++k) {
      const double ratio = std::abs(a.intrinsics.at(camera)[k] - b.intrinsics.at(camera)[k]) /
                           (sigma_scale * reference.sigma.at(camera)[k]);
      if (ratio > worst) {
        worst = ratio;
        *where = camera + " " + names[k];
      }
    }
  }
  const double ratio =
      std::abs(a.baseline_mm - b.baseline_mm) / (sigma_scale * reference.baseline_sigma_mm);
  if (ratio > worst) {
    worst = ratio;
    *where = "baseline";
  }
  return worst;
}

// The true pair (gt/cameras) in the same terms; no sigma.
PairCalibration TruePair(const std::filesystem::path& take) {
  PairCalibration out;
  std::map<std::string, CameraModel> cameras;
  for (const std::string camera : {"left", "right"}) {
    cameras.emplace(camera, CameraModel::Read(take / "gt" / "cameras" / (camera + ".cameramodel")));
    const auto& intrinsics = cameras.at(camera).intrinsics();
    out.intrinsics[camera].assign(intrinsics.begin(), intrinsics.begin() + 4);
  }
  out.baseline_mm =
      1000 * (cameras.at("right").center_in_world() - cameras.at("left").center_in_world()).norm();
  return out;
}

// One table row per figure: the route's difference to the direct solve and to the truth, the
// direct solve's 1-sigma and the route's own (bench/images_calibration.sh keeps them).
void PrintAgreement(const std::string& route, const PairCalibration& a,
                    const PairCalibration& direct, const PairCalibration& truth) {
  const char* names[] = {"fx", "fy", "cx", "cy"};
  const auto row = [&](const std::string& figure, double value, double to_direct, double to_truth,
                       double sigma_direct, double sigma_own) {
    std::printf("%-5s %-12s %10.4f %+9.4f %+9.4f %8.4f %8.4f %6.2f\n", route.c_str(),
                figure.c_str(), value, to_direct, to_truth, sigma_direct, sigma_own,
                std::abs(to_direct) / sigma_direct);
  };
  for (const std::string camera : {"left", "right"}) {
    for (int k = 0; k < 4; ++k) {
      const double v = a.intrinsics.at(camera)[k];
      row(camera + " " + names[k], v, v - direct.intrinsics.at(camera)[k],
          v - truth.intrinsics.at(camera)[k], direct.sigma.at(camera)[k], a.sigma.at(camera)[k]);
    }
  }
  row("baseline_mm", a.baseline_mm, a.baseline_mm - direct.baseline_mm,
      a.baseline_mm - truth.baseline_mm, direct.baseline_sigma_mm, a.baseline_sigma_mm);
}

std::string Calibrate(const std::filesystem::path& take, const std::filesystem::path& board) {
  return "calibrate " + take.string() + " --no-pictures --lens-model LENSMODEL_OPENCV5" +
         (board.empty() ? std::string() : " --board " + board.string());
}

// 24 frame sets of the stereo rig filming the board; the take is calibrated directly, then
// through JPEG folders (one frame of the right camera deleted: pairing by number must keep the
// later frames together) and through MP4s.
TEST(ImportImages, BoardTakeCalibratesFromJpegFoldersAndMp4sAsFromTheTake) {
  TempDir dir("holocap-images");
  { std::ofstream(dir / "stereo.yaml") << kStereoRig; }
  const auto take = dir / "board";
  auto r = RunCli("sim --rig " + (dir / "stereo.yaml").string() + " --board --frames 24 --out " +
                  take.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  // The board a user would have printed: the simulated board's layout.
  const auto gt_board = nlohmann::json::parse(ReadFileToString(take / "gt" / "board.json"));
  const auto board = dir / "board.json";
  { std::ofstream(board) << gt_board["layout"].dump(); }
  r = RunCli(Calibrate(take, ""));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const PairCalibration direct = ReadCalibration(take);
  const PairCalibration truth = TruePair(take);
  std::printf("%-5s %-12s %10s %9s %9s %8s %8s %6s\n", "route", "figure", "value", "-direct",
              "-truth", "sigma", "own_sig", "/sigma");
  PrintAgreement("take", direct, direct, truth);

  // JPEG folders: left/000000.jpg ..., right/ without 000005.jpg.
  r = RunCli("export images " + take.string() + " --out " + (dir / "jpg").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  ASSERT_TRUE(std::filesystem::remove(dir / "jpg" / "right" / "000005.jpg"));
  r = RunCli("import images " + (dir / "jpg").string() + " --out " + (dir / "from-jpg").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("paired by number"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("1 frame(s) unpaired: " + (dir / "jpg" / "left" / "000005.jpg").string()),
            std::string::npos)
      << r.output;
  r = RunCli("info " + (dir / "from-jpg").string());
  EXPECT_NE(r.output.find("uncalibrated"), std::string::npos) << r.output;
  EXPECT_FALSE(std::filesystem::exists(dir / "from-jpg" / "calib"));
  r = RunCli(Calibrate(dir / "from-jpg", board));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const PairCalibration jpeg = ReadCalibration(dir / "from-jpg");
  PrintAgreement("jpeg", jpeg, direct, truth);
  // The JPEG frames hold the take's pixels up to quality-95 rounding, and the same noise: the
  // two solves differ by far less than the direct solve's 1-sigma (measured: at most 0.5).
  std::string where;
  EXPECT_LT(WorstSigmas(jpeg, direct, direct, 1.0, &where), 1.0) << where;

  // MP4s (H.264, crf 18, 4:2:0).
  r = RunCli("export images " + take.string() + " --video mp4 --out " + (dir / "mp4").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = RunCli("import images --camera left=" + (dir / "mp4" / "left.mp4").string() +
             " --camera right=" + (dir / "mp4" / "right.mp4").string() + " --out " +
             (dir / "from-mp4").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("24 frame set(s) of 2 camera(s); 0 frame(s) unpaired"), std::string::npos)
      << r.output;
  r = RunCli(Calibrate(dir / "from-mp4", board));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const PairCalibration video = ReadCalibration(dir / "from-mp4");
  PrintAgreement("mp4", video, direct, truth);
  // Lossy video adds an error of its own, independent of the take's noise (the corners' RMS
  // residual grows about 5 times), so the difference is a draw of the video solve's own error,
  // whose 1-sigma that solve reports from the residuals it saw: held to 3 of those sigmas over
  // the 9 figures (measured: at most 1.8).
  EXPECT_LT(WorstSigmas(video, direct, video, 3.0, &where), 1.0) << where;
  for (const std::string camera : {"left", "right"}) {
    EXPECT_GT(video.sigma.at(camera)[0], direct.sigma.at(camera)[0]) << camera;
  }
}

cv::Mat Pattern(int width, int height, int type, int seed) {
  cv::Mat image(height, width, type);
  cv::randu(image, 0, CV_MAT_DEPTH(type) == CV_16U ? 65535 : 255);
  image.at<uint8_t>(0, 0) = static_cast<uint8_t>(seed);
  return image;
}

// Each image's first pixel in the take, by set and camera.
std::map<std::pair<int64_t, std::string>, cv::Mat> TakeFrames(const std::filesystem::path& dir) {
  const Take take = Take::Open(dir);
  std::map<std::pair<int64_t, std::string>, cv::Mat> frames;
  for (size_t i = 0; i < take.size(); ++i) {
    for (const auto& item : take.entry(i).items)
      frames[{take.entry(i).index, item.sensor}] = take.ReadFrame(i, item.sensor);
  }
  return frames;
}

bool Same(const cv::Mat& a, const cv::Mat& b) {
  return a.size() == b.size() && a.type() == b.type() && cv::norm(a, b, cv::NORM_INF) == 0;
}

// left01..left06 and right01..right06 without right04: by number, right05 stays with left05,
// and left04 is unpaired, counted and named in the line and report.json; grey and 16-bit PNGs
// stay as they are.
TEST(ImportImages, PairsByNumberAndNamesTheUnpaired) {
  TempDir dir("holocap-images");
  std::filesystem::create_directories(dir / "calib");
  std::map<std::string, cv::Mat> written;
  for (int i = 1; i <= 6; ++i) {
    const std::string n = "0" + std::to_string(i);
    written["left" + n] = Pattern(64, 48, CV_8UC1, i);
    cv::imwrite((dir / "calib" / ("left" + n + ".png")).string(), written["left" + n]);
    if (i == 4) continue;
    written["right" + n] = Pattern(40, 30, CV_16UC3, 10 + i);
    cv::imwrite((dir / "calib" / ("right" + n + ".png")).string(), written["right" + n]);
  }
  const auto out = dir / "cal";
  const auto r = RunCli("import images --camera left='" + (dir / "calib").string() +
                        "/left*.png' --camera right='" + (dir / "calib").string() +
                        "/right*.png' --out " + out.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("paired by number"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("6 frame set(s) of 2 camera(s); 1 frame(s) unpaired: " +
                          (dir / "calib" / "left04.png").string()),
            std::string::npos)
      << r.output;
  const auto report = nlohmann::json::parse(ReadFileToString(out / "report.json"));
  EXPECT_EQ(report["plan"]["pair_by"], "number");
  EXPECT_EQ(report["plan"]["unpaired"].size(), 1u);
  EXPECT_EQ(report["metrics"]["unpaired_frames"], 1);
  const Take take = Take::Open(out);
  EXPECT_EQ(take.stream("left").pixel_format, "mono8");
  EXPECT_EQ(take.stream("right").pixel_format, "bgr16");
  EXPECT_EQ(take.stream("right").width, 40);
  EXPECT_FALSE(take.has_calibration());
  const auto frames = TakeFrames(out);
  ASSERT_EQ(frames.size(), 11u);
  for (int i = 1; i <= 6; ++i) {
    const std::string n = "0" + std::to_string(i);
    EXPECT_TRUE(Same(frames.at({i - 1, "left"}), written["left" + n])) << i;
    if (i != 4) EXPECT_TRUE(Same(frames.at({i - 1, "right"}), written["right" + n])) << i;
  }
  EXPECT_EQ(frames.count({3, "right"}), 0u);
}

// Names without numbers: timestamps.txt pairs them (the right camera 5 ms late, one extra
// frame); without it they pair by order, and --pair-by number is refused naming a file.
TEST(ImportImages, PairsByTimestampsBesideTheImagesElseByOrder) {
  TempDir temp("holocap-images");
  const auto root = temp / "photos";
  for (const std::string camera : {"a", "b"}) std::filesystem::create_directories(root / camera);
  const char* names[] = {"first", "second", "third"};
  std::ofstream a_times(root / "a" / "timestamps.txt"), b_times(root / "b" / "timestamps.txt");
  a_times << "# file seconds\n";
  for (int i = 0; i < 3; ++i) {
    cv::imwrite((root / "a" / (std::string(names[i]) + ".png")).string(),
                Pattern(32, 32, CV_8UC3, i));
    a_times << names[i] << ".png " << 100 + i * 0.5 << "\n";
  }
  // b: "early" at 99.0 has no partner; the others are 5 ms after a's.
  const char* b_names[] = {"early", "x", "y", "z"};
  const double b_times_s[] = {99.0, 100.005, 100.505, 101.005};
  for (int i = 0; i < 4; ++i) {
    cv::imwrite((root / "b" / (std::string(b_names[i]) + ".png")).string(),
                Pattern(32, 32, CV_8UC3, 10 + i));
    b_times << b_names[i] << ".png " << b_times_s[i] << "\n";
  }
  a_times.close();
  b_times.close();
  auto r = RunCli("import images " + root.string() + " --out " + (temp / "t").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("paired by time"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("4 frame set(s) of 2 camera(s); 1 frame(s) unpaired: " +
                          (root / "b" / "early.png").string()),
            std::string::npos)
      << r.output;
  Take take = Take::Open(temp / "t");
  ASSERT_EQ(take.size(), 4u);
  // Set 1 holds a/first and b/x, 5 ms apart.
  EXPECT_EQ(take.entry(1).items.size(), 2u);
  EXPECT_EQ(take.entry(1).spread_ns, 5000000);
  EXPECT_EQ(take.ReadFrame(1, "a").at<cv::Vec3b>(0, 0)[0], 0);
  EXPECT_EQ(take.ReadFrame(1, "b").at<cv::Vec3b>(0, 0)[0], 11);

  std::filesystem::remove(root / "a" / "timestamps.txt");
  r = RunCli("import images " + root.string() + " --out " + (temp / "o").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("paired by order"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("1 frame(s) unpaired: " + (root / "b" / "z.png").string()),
            std::string::npos)
      << r.output;
  ExpectOneLineError(
      RunCli("import images " + root.string() + " --pair-by number --out " + (temp / "n").string()),
      "has no number in its name");
  EXPECT_FALSE(std::filesystem::exists(temp / "n"));
}

// Every bad input: one error line, non-zero exit, and no take folder.
TEST(ImportImages, BadInputGivesOneErrorAndNoTake) {
  TempDir dir("holocap-images");
  const auto out = dir / "out";
  const auto expect_refused = [&](const std::string& args, const std::string& needle) {
    ExpectOneLineError(RunCli("import images " + args + " --out " + out.string()), needle);
    EXPECT_FALSE(std::filesystem::exists(out)) << args;
  };
  std::filesystem::create_directories(dir / "empty");
  expect_refused((dir / "empty").string(), "holds no camera");
  expect_refused("--camera left=" + (dir / "empty").string(), "holds no images");
  expect_refused("--camera left='" + (dir / "none*.jpg").string() + "'", "matches no image file");
  expect_refused("--camera left=" + (dir / "missing").string(), "does not exist");

  std::filesystem::create_directories(dir / "good");
  for (int i = 0; i < 3; ++i)
    cv::imwrite((dir / "good" / ("g" + std::to_string(i) + ".jpg")).string(),
                Pattern(64, 48, CV_8UC3, i));
  expect_refused(
      "--camera left=" + (dir / "good").string() + " --camera left=" + (dir / "good").string(),
      "camera 'left' is given twice");

  // A JPEG cut in half decodes with grey in libjpeg; it must be refused.
  std::filesystem::create_directories(dir / "cut");
  std::filesystem::copy_file(dir / "good" / "g0.jpg", dir / "cut" / "c0.jpg");
  const std::string bytes = ReadFileToString(dir / "good" / "g1.jpg");
  { std::ofstream(dir / "cut" / "c1.jpg", std::ios::binary) << bytes.substr(0, bytes.size() / 2); }
  expect_refused("--camera left=" + (dir / "cut").string(), "c1.jpg' is truncated");
  std::filesystem::create_directories(dir / "junk");
  { std::ofstream(dir / "junk" / "j0.png") << "not an image"; }
  expect_refused("--camera left=" + (dir / "junk").string(), "j0.png' is truncated or not a PNG");

  std::filesystem::create_directories(dir / "sizes");
  cv::imwrite((dir / "sizes" / "s0.png").string(), Pattern(64, 48, CV_8UC3, 0));
  cv::imwrite((dir / "sizes" / "s1.png").string(), Pattern(80, 48, CV_8UC3, 1));
  expect_refused("--camera left=" + (dir / "sizes").string(),
                 "s1.png' is 80x48 but '" + (dir / "sizes" / "s0.png").string() + "' is 64x48");

  // A file that no FFmpeg demuxer reads.
  { std::ofstream(dir / "clip.mp4") << "not a video"; }
  expect_refused("--camera left=" + (dir / "clip.mp4").string(), "cannot be opened");
}

}  // namespace
}  // namespace holocap
