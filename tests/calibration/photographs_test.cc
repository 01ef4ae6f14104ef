// A user's path on real photographs: OpenCV's sample stereo pair (tests/data/opencv-stereo, 13
// pairs of 640x480 JPEGs of a 9 x 6 chessboard) imported and calibrated through the CLI, and the
// intrinsics held against OpenCV's own calibration of the same images.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <string>
#include <vector>

#include "core/fs.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::RunCli;
using testing::TempDir;
using testing::TestDataDir;

constexpr int kWidthN = 9;   // inner corners per row, as board.yaml says
constexpr int kHeightN = 6;  // inner corners per column
constexpr int kFrameSets = 13;

std::filesystem::path Data() { return TestDataDir() / "opencv-stereo"; }

// OpenCV's calibration of one camera from its own corners, the recipe of OpenCV's stereo_calib
// sample (findChessboardCorners, then cornerSubPix with an 11 x 11 half-window, shrunk to half
// the view's smallest corner spacing where squares are smaller, as holocap's --compare-detectors
// runs it), solved by calibrateCamera with the rational model (LENSMODEL_OPENCV8's eight
// distortion terms). Returns fx fy cx cy and their standard deviations.
struct OpenCvIntrinsics {
  int views = 0;
  double rms_px = 0;
  cv::Vec4d value;
  cv::Vec4d sigma;
};

OpenCvIntrinsics CalibrateWithOpenCv(const std::string& camera) {
  std::vector<cv::Point3f> board;
  for (int j = 0; j < kHeightN; ++j) {
    for (int i = 0; i < kWidthN; ++i) board.emplace_back(0.025F * i, 0.025F * j, 0.F);
  }
  std::vector<std::vector<cv::Point3f>> object_points;
  std::vector<std::vector<cv::Point2f>> image_points;
  cv::Size size;
  for (const auto& entry : std::filesystem::directory_iterator(Data())) {
    const std::string name = entry.path().filename().string();
    if (name.rfind(camera, 0) != 0 || entry.path().extension() != ".jpg") continue;
    const cv::Mat grey = cv::imread(entry.path().string(), cv::IMREAD_GRAYSCALE);
    size = grey.size();
    std::vector<cv::Point2f> corners;
    if (!cv::findChessboardCorners(grey, cv::Size(kWidthN, kHeightN), corners,
                                   cv::CALIB_CB_ADAPTIVE_THRESH | cv::CALIB_CB_NORMALIZE_IMAGE)) {
      continue;
    }
    double spacing = 1e9;
    for (int j = 0; j < kHeightN; ++j) {
      for (int i = 0; i < kWidthN; ++i) {
        const cv::Point2f& p = corners[j * kWidthN + i];
        if (i + 1 < kWidthN)
          spacing = std::min(spacing, cv::norm(corners[j * kWidthN + i + 1] - p));
        if (j + 1 < kHeightN) {
          spacing = std::min(spacing, cv::norm(corners[(j + 1) * kWidthN + i] - p));
        }
      }
    }
    const int half = std::clamp(static_cast<int>(0.5 * spacing), 2, 11);
    cv::cornerSubPix(grey, corners, cv::Size(half, half), cv::Size(-1, -1),
                     cv::TermCriteria(cv::TermCriteria::EPS + cv::TermCriteria::COUNT, 30, 0.01));
    object_points.push_back(board);
    image_points.push_back(corners);
  }
  OpenCvIntrinsics result;
  result.views = static_cast<int>(image_points.size());
  if (result.views < 3) return result;
  cv::Mat k;
  cv::Mat distortion;
  cv::Mat std_intrinsics;
  cv::Mat std_extrinsics;
  cv::Mat per_view_errors;
  std::vector<cv::Mat> rvecs;
  std::vector<cv::Mat> tvecs;
  result.rms_px = cv::calibrateCamera(object_points, image_points, size, k, distortion, rvecs,
                                      tvecs, std_intrinsics, std_extrinsics, per_view_errors,
                                      cv::CALIB_RATIONAL_MODEL);
  result.value = {k.at<double>(0, 0), k.at<double>(1, 1), k.at<double>(0, 2), k.at<double>(1, 2)};
  for (int i = 0; i < 4; ++i) result.sigma[i] = std_intrinsics.at<double>(i);
  return result;
}

TEST(CalibratePhotographs, OpenCvsStereoPairConvergesAndAgreesWithOpenCv) {
  TempDir dir("holocap-opencv-stereo");
  const std::string take = (dir.path() / "cal").string();
  const auto import =
      RunCli("import images --camera left='" + (Data() / "left*.jpg").string() +
             "' --camera right='" + (Data() / "right*.jpg").string() + "' --out " + take);
  ASSERT_EQ(import.exit_code, 0) << import.output;
  const auto calibrate = RunCli("calibrate " + take + " --board " +
                                (Data() / "board.yaml").string() + " --no-pictures");
  ASSERT_EQ(calibrate.exit_code, 0) << calibrate.output;
  const auto report = nlohmann::json::parse(
      ReadFileToString(std::filesystem::path(take) / "calib" / "report.json"));
  EXPECT_EQ(report["summary"]["termination"], "CONVERGENCE") << report["summary"].dump();
  const auto& m = report["metrics"];

  // Every frame set's view of each camera is used, or counted with its reason (detection's
  // rejected views, the solve's dropped ones).
  EXPECT_EQ(m["detection"]["frames"].get<int>(), 2 * kFrameSets);
  for (const std::string camera : {"left", "right"}) {
    int counted = m["cameras"][camera]["views"].get<int>();
    for (const auto& list : {m["detection"]["rejected"], m["dropped_views"]}) {
      for (const auto& view : list) counted += view["sensor"] == camera ? 1 : 0;
    }
    EXPECT_EQ(counted, kFrameSets) << camera;
  }

  // The board's warp is solved only when asked for (mrcal's calobject_warp, --board-warp): a
  // bow of the printed sheet, well under a square.
  EXPECT_TRUE(m["board_warp_m"].is_null()) << m["board_warp_m"].dump();
  const auto warped = RunCli("calibrate " + take + " --board " + (Data() / "board.yaml").string() +
                             " --no-pictures --board-warp");
  ASSERT_EQ(warped.exit_code, 0) << warped.output;
  const auto warp_report = nlohmann::json::parse(
      ReadFileToString(std::filesystem::path(take) / "calib" / "report.json"));
  EXPECT_EQ(warp_report["summary"]["termination"], "CONVERGENCE");
  EXPECT_TRUE(warp_report["options"]["solve"]["solve_board_warp"].get<bool>());
  const auto& warp = warp_report["metrics"]["board_warp_m"];
  ASSERT_TRUE(warp.is_array() && warp.size() == 2) << warp.dump();
  for (const auto& w : warp) EXPECT_LT(std::abs(w.get<double>()), 0.025) << warp.dump();

  // fx fy cx cy against OpenCV's calibration of the same images from its own corners: two
  // estimates whose errors are independent up to the images they share differ by about
  // hypot(holocap's 1-sigma, OpenCV's standard deviation); 4 such sigmas (a Gaussian exceeds
  // it once in 16,000) leave room for what neither sigma holds (the finders' different
  // refinements, mrcal's regularisation) and none for a wrong lens.
  const char* names[] = {"fx", "fy", "cx", "cy"};
  for (const std::string camera : {"left", "right"}) {
    const OpenCvIntrinsics opencv = CalibrateWithOpenCv(camera);
    ASSERT_EQ(opencv.views, kFrameSets) << camera;
    const auto& intrinsics = m["cameras"][camera]["intrinsics"];
    const auto& sigma = m["cameras"][camera]["intrinsics_sigma"];
    for (int i = 0; i < 4; ++i) {
      const double holocap = intrinsics[i].get<double>();
      const double holocap_sigma = sigma[i].get<double>();
      ASSERT_GT(holocap_sigma, 0) << camera << " " << names[i];
      ASSERT_GT(opencv.sigma[i], 0) << camera << " " << names[i];
      const double combined = std::hypot(holocap_sigma, opencv.sigma[i]);
      EXPECT_LT(std::abs(holocap - opencv.value[i]), 4 * combined)
          << camera << " " << names[i] << ": holocap " << holocap << " +- " << holocap_sigma
          << ", OpenCV " << opencv.value[i] << " +- " << opencv.sigma[i] << " (its RMS "
          << opencv.rms_px << " px)";
    }
  }
}

}  // namespace
}  // namespace holocap
