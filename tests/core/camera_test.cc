#include "core/camera.h"

#include <gtest/gtest.h>

#include <fstream>
#include <opencv2/calib3d.hpp>
#include <random>

#include "core/error.h"
#include "core/fs.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::SourceDir;
using testing::TempDir;

CameraModel RealWideLens() {
  return CameraModel::Read(testing::TestDataDir() / "lenses/wide-4000x2200.opencv8.cameramodel");
}

// Points spread over the field of view at 0.5..20 m.
Eigen::Matrix3Xd PointsInView(const CameraModel& camera, int count, uint64_t seed) {
  std::mt19937_64 random(seed);
  std::uniform_real_distribution<double> u(0.05, 0.95), depth(0.5, 20.0);
  Eigen::Matrix3Xd points(3, count);
  for (int i = 0; i < count; ++i) {
    Eigen::Vector2d pixel(u(random) * camera.width(), u(random) * camera.height());
    points.col(i) = camera.Unproject(pixel) * depth(random);
  }
  return points;
}

TEST(CameraModel, ReadsTheRealLensFile) {
  CameraModel lens = RealWideLens();
  EXPECT_EQ(lens.lensmodel(), "LENSMODEL_OPENCV8");
  EXPECT_EQ(lens.width(), 4000);
  EXPECT_EQ(lens.height(), 2200);
  EXPECT_NEAR(lens.intrinsics()[0], 1761.181055, 1e-9);
  EXPECT_NEAR(lens.cam_from_world().translation().y(), 2.0, 1e-12);
}

// OpenCV's projectPoints is an independent implementation of the OPENCV lens models.
TEST(CameraModel, OpenCvModelsProjectAsOpenCvDoes) {
  CameraModel lens = RealWideLens();
  for (int n : {4, 5, 8}) {
    std::vector<double> intrinsics(lens.intrinsics().begin(), lens.intrinsics().begin() + 4 + n);
    CameraModel camera("LENSMODEL_OPENCV" + std::to_string(n), intrinsics, lens.width(),
                       lens.height());
    Eigen::Matrix3Xd points = PointsInView(camera, 500, n);
    cv::Mat K = (cv::Mat_<double>(3, 3) << intrinsics[0], 0, intrinsics[2], 0, intrinsics[1],
                 intrinsics[3], 0, 0, 1);
    cv::Mat distortion(1, n, CV_64F, intrinsics.data() + 4);
    std::vector<cv::Point3d> cv_points;
    for (int i = 0; i < points.cols(); ++i)
      cv_points.emplace_back(points(0, i), points(1, i), points(2, i));
    std::vector<cv::Point2d> expected;
    cv::projectPoints(cv_points, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), K, distortion, expected);
    Eigen::Matrix2Xd pixels = camera.ProjectMany(points);
    double worst = 0;
    for (int i = 0; i < points.cols(); ++i) {
      Eigen::Vector2d single;
      ASSERT_TRUE(camera.Project(points.col(i), &single));
      worst = std::max(worst, (single - Eigen::Vector2d(expected[i].x, expected[i].y)).norm());
      EXPECT_EQ(single, pixels.col(i));
    }
    EXPECT_LT(worst, 1e-9) << "OPENCV" << n;
  }
}

// mrcal's own Python reads the file holocap writes and projects the same points.
TEST(CameraModel, MatchesMrcalPythonThroughCameramodelFiles) {
  ASSERT_EQ(std::system("/usr/bin/python3 -c 'import mrcal' 2>/dev/null"), 0)
      << "python3-mrcal is missing: scripts/setup.sh --tests installs it";
  TempDir dir;
  std::vector<CameraModel> cameras = {
      RealWideLens(), CameraModel("LENSMODEL_PINHOLE", {800, 805, 319.5, 239.5}, 640, 480),
      CameraModel(
          "LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=8_Ny=6_fov_x_deg=150",
          [] {
            std::vector<double> v = {300, 300, 320, 240};
            std::mt19937_64 random(3);
            std::normal_distribution<double> knot(0, 0.02);
            for (int i = 0; i < 2 * 8 * 6; ++i) v.push_back(knot(random));
            return v;
          }(),
          640, 480)};
  for (size_t c = 0; c < cameras.size(); ++c) {
    const CameraModel& camera = cameras[c];
    auto model_file = dir / ("camera" + std::to_string(c) + ".cameramodel");
    camera.Write(model_file);
    Eigen::Matrix3Xd points = PointsInView(camera, 200, 10 + c);
    auto points_file = dir / "points.txt";
    {
      std::ofstream out(points_file);
      out.precision(17);
      for (int i = 0; i < points.cols(); ++i)
        out << points(0, i) << " " << points(1, i) << " " << points(2, i) << "\n";
    }
    auto result =
        testing::RunShell("/usr/bin/python3 -c \"import mrcal, numpy; m = mrcal.cameramodel('" +
                          model_file.string() + "'); p = numpy.loadtxt('" + points_file.string() +
                          "'); q = mrcal.project(p, *m.intrinsics()); numpy.savetxt('" +
                          (dir / "q.txt").string() + "', q, fmt='%.17g')\"");
    ASSERT_EQ(result.exit_code, 0) << result.output;
    std::ifstream in(dir / "q.txt");
    Eigen::Matrix2Xd ours = camera.ProjectMany(points);
    double worst = 0;
    for (int i = 0; i < points.cols(); ++i) {
      double x, y;
      in >> x >> y;
      worst = std::max(worst, (ours.col(i) - Eigen::Vector2d(x, y)).norm());
    }
    EXPECT_LT(worst, 1e-9) << camera.lensmodel();
  }
}

TEST(CameraModel, UnprojectRoundTrips) {
  CameraModel lens = RealWideLens().Scaled(0.16);
  std::mt19937_64 random(7);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  double worst = 0;
  for (int i = 0; i < 1000; ++i) {
    Eigen::Vector2d pixel(u(random) * (lens.width() - 1), u(random) * (lens.height() - 1));
    Eigen::Vector3d direction = lens.Unproject(pixel);
    EXPECT_NEAR(direction.norm(), 1.0, 1e-12);
    Eigen::Vector2d back;
    ASSERT_TRUE(lens.Project(direction * 3.0, &back));
    worst = std::max(worst, (back - pixel).norm());
  }
  EXPECT_LT(worst, 1e-6);
}

TEST(CameraModel, JacobiansMatchFiniteDifferences) {
  CameraModel lens = RealWideLens().Scaled(0.16);
  Eigen::Vector3d point(0.3, -0.2, 2.0);
  Eigen::Vector2d pixel;
  Eigen::Matrix<double, 2, 3> dpixel_dpoint;
  Eigen::MatrixXd dpixel_dintrinsics;
  ASSERT_TRUE(lens.Project(point, &pixel, &dpixel_dpoint, &dpixel_dintrinsics));
  const double h = 1e-6;
  for (int k = 0; k < 3; ++k) {
    Eigen::Vector3d plus = point, minus = point;
    plus[k] += h;
    minus[k] -= h;
    Eigen::Vector2d qp, qm;
    lens.Project(plus, &qp);
    lens.Project(minus, &qm);
    Eigen::Vector2d numeric = (qp - qm) / (2 * h);
    EXPECT_LT((numeric - dpixel_dpoint.col(k)).norm(), 1e-5 * (1 + numeric.norm()));
  }
  for (size_t k = 0; k < lens.intrinsics().size(); ++k) {
    CameraModel plus = lens, minus = lens;
    double step = h * std::max(1.0, std::abs(lens.intrinsics()[k]));
    plus.mutable_intrinsics()[k] += step;
    minus.mutable_intrinsics()[k] -= step;
    Eigen::Vector2d qp, qm;
    plus.Project(point, &qp);
    minus.Project(point, &qm);
    Eigen::Vector2d numeric = (qp - qm) / (2 * step);
    EXPECT_LT((numeric - dpixel_dintrinsics.col(k)).norm(), 1e-4 * (1 + numeric.norm())) << k;
  }
}

TEST(CameraModel, FileRoundTripIsExact) {
  TempDir dir;
  CameraModel lens = RealWideLens();
  Pose pose = PoseFromRt({0.1234567890123, -0.3, 0.7, 1000.25, -2.5, 3.0});
  lens.set_cam_from_world(pose);
  lens.Write(dir / "a.cameramodel");
  CameraModel back = CameraModel::Read(dir / "a.cameramodel");
  EXPECT_EQ(back.lensmodel(), lens.lensmodel());
  EXPECT_EQ(back.intrinsics(), lens.intrinsics());
  EXPECT_EQ(back.width(), lens.width());
  EXPECT_EQ(back.height(), lens.height());
  EXPECT_LT((back.cam_from_world().matrix() - pose.matrix()).cwiseAbs().maxCoeff(), 1e-12);
}

TEST(CameraModel, ScalingKeepsThePixelCentreConvention) {
  CameraModel camera("LENSMODEL_PINHOLE", {500, 500, 319.5, 239.5}, 640, 480);
  CameraModel half = camera.Scaled(0.5);
  EXPECT_EQ(half.width(), 320);
  EXPECT_DOUBLE_EQ(half.intrinsics()[2], 159.5);  // still the imager centre
  Eigen::Vector2d q, q_half;
  camera.Project({0.2, 0.1, 1.0}, &q);
  half.Project({0.2, 0.1, 1.0}, &q_half);
  EXPECT_NEAR(q_half.x(), (q.x() + 0.5) * 0.5 - 0.5, 1e-12);
}

TEST(CameraModel, RejectsBadInput) {
  EXPECT_THROW(CameraModel("LENSMODEL_NOPE", {1, 2, 3, 4}, 10, 10), Error);
  EXPECT_THROW(CameraModel("LENSMODEL_OPENCV8", {1, 2, 3, 4}, 10, 10), Error);
  EXPECT_THROW(CameraModel("LENSMODEL_PINHOLE", {1, 2, 3, NAN}, 10, 10), Error);
  EXPECT_THROW(CameraModel::Parse("{ 'lensmodel': ", "broken"), Error);
  EXPECT_THROW(CameraModel::Read("/nonexistent/x.cameramodel"), Error);
  CameraModel pinhole = CameraModel::Pinhole(500, 640, 480);
  Eigen::Vector2d q;
  EXPECT_FALSE(pinhole.Project({0, 0, -1}, &q));
  EXPECT_FALSE(pinhole.Project({NAN, 0, 1}, &q));
}

// Every truncation of a valid file, and the inputs on which libmrcal's own parser reads out of
// bounds (in the fuzz corpus, bench/fuzz/corpus/cameramodel/), give an Error, never a crash.
TEST(CameraModel, TruncatedAndMalformedFilesGiveAnError) {
  TempDir dir;
  RealWideLens().Write(dir / "a.cameramodel");
  const std::string text = ReadFileToString(dir / "a.cameramodel");
  ASSERT_NO_THROW(CameraModel::Parse(text, "whole"));
  // mrcal's tools store their optimisation inputs as a Python bytes literal.
  std::string with_bytes = text;
  with_bytes.insert(with_bytes.find('{') + 1, "\n    'optimization_inputs': b'P)h>@6aWAK2',");
  EXPECT_NO_THROW(CameraModel::Parse(with_bytes, "bytes"));
  size_t last_brace = text.rfind('}');
  for (size_t size = 0; size < last_brace; size += 7) {
    EXPECT_THROW(CameraModel::Parse(text.substr(0, size), "cut"), Error) << size;
  }
  for (const char* file :
       {"mrcal-parser-oob-1.cameramodel", "mrcal-parser-oob-truncated.cameramodel"}) {
    EXPECT_THROW(CameraModel::Read(SourceDir() / "bench/fuzz/corpus/cameramodel" / file), Error)
        << file;
  }
  for (const char* bad :
       {"{ 'lensmodel': 'LENSMODEL_PINHOLE' # x", "{ 'el': 'LEN{P# INHd", "{ 'a': [1, 2 }",
        "{ 'a': 1 } trailing", "{ 'a' 1 }", "[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[["}) {
    EXPECT_THROW(CameraModel::Parse(bad, "bad"), Error) << bad;
  }
}

// A negative focal length in a .cameramodel was accepted, and reconstruct
// reported SUCCESS on a meaningless surface. Every model is validated where it is made; a file's
// error names the file and the field.
TEST(CameraModel, RefusesAModelNoCameraCanHaveNamingFileAndField) {
  const std::string good = CameraModel::Pinhole(500, 640, 480).ToString();
  ASSERT_NO_THROW(CameraModel::Parse(good, "good"));
  auto with_intrinsics = [&](const std::string& intrinsics) {
    std::string text = good;
    const size_t from = text.find("'intrinsics': [") + 15;
    text.replace(from, text.find(']', from) - from, intrinsics);
    return text;
  };
  struct Case {
    std::string intrinsics;
    std::string expected;
  };
  for (const Case& c :
       {Case{"-500, 500, 319.5, 239.5", "intrinsics[0] (fx) is -500"},
        Case{"500, 0, 319.5, 239.5", "intrinsics[1] (fy) is 0"},
        Case{"500, 500, 1281, 239.5", "intrinsics[2] (cx) is 1281, outside [-640"},
        Case{"500, 500, 319.5, -481", "intrinsics[3] (cy) is -481, outside [-480"}}) {
    try {
      CameraModel::Parse(with_intrinsics(c.intrinsics), "calib/cam0.cameramodel");
      ADD_FAILURE() << c.intrinsics;
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find("'calib/cam0.cameramodel'"), std::string::npos)
          << e.what();
      EXPECT_NE(std::string(e.what()).find(c.expected), std::string::npos) << e.what();
    }
  }
  // The margin is one image size on each side: its ends are still accepted.
  EXPECT_NO_THROW(CameraModel("LENSMODEL_PINHOLE", {500, 500, -640, 960}, 640, 480));
  try {
    CameraModel("LENSMODEL_OPENCV4", {500, 500, 320, 240, 0.1, INFINITY, 0, 0}, 640, 480);
    ADD_FAILURE();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("intrinsics[5] is inf, not a finite number"),
              std::string::npos)
        << e.what();
  }
}

// A translation of 1e300 m is finite, and was accepted: every projection through it is
// rounding noise. A camera farther than kMaxCameraTranslationM from the rig's origin is refused,
// naming the file.
TEST(CameraModel, RefusesACameraFartherThanARigCanReach) {
  const std::string good = CameraModel::Pinhole(500, 640, 480).ToString();
  std::string text = good;
  const size_t from = text.find("'extrinsics': [") + 15;
  text.replace(from, text.find(']', from) - from, "0, 0, 0, 1e300, 0, 0");
  try {
    CameraModel::Parse(text, "calib/cam0.cameramodel");
    ADD_FAILURE();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("'calib/cam0.cameramodel': camera model: its translation "
                                         "reaches 1e+300 m, more than the 1e+06 m"),
              std::string::npos)
        << e.what();
  }
  text = good;
  text.replace(from, text.find(']', from) - from, "0, 0, 0, 999999, 0, 0");
  EXPECT_NO_THROW(CameraModel::Parse(text, "calib/cam0.cameramodel"));
}

// libmrcal printed its own line on stderr and holocap's error gave no reason.
// Its words now are part of the one error, and nothing reaches stderr.
TEST(CameraModel, LibmrcalsComplaintIsFoldedIntoTheOneError) {
  const std::string text =
      "{ 'lensmodel': 'LENSMODEL_PINHOLE', 'intrinsics': [500, 500, 319.5, nan], "
      "'extrinsics': [0, 0, 0, 0, 0, 0], 'imagersize': [640, 480] }";
  ::testing::internal::CaptureStderr();
  std::string message;
  try {
    CameraModel::Parse(text, "odd.cameramodel");
  } catch (const Error& e) {
    message = e.what();
  }
  const std::string printed = ::testing::internal::GetCapturedStderr();
  ASSERT_FALSE(message.empty()) << "libmrcal accepted a NaN";
  EXPECT_EQ(printed, "");
  EXPECT_NE(message.find("'odd.cameramodel' is not a valid mrcal .cameramodel: libmrcal says: "
                         "cameramodel-parser.re("),
            std::string::npos)
      << message;
  EXPECT_EQ(message.find('\n'), std::string::npos) << message;
}

// Rotations are checked where they are read (finite, entries in [-1, 1],
// det +1, orthonormal to 1e-6); a nearly orthonormal one becomes the nearest rotation.
TEST(Pose, CheckRotationRefusesNonRotationsAndReorthonormalisesNearOnes) {
  const Eigen::Matrix3d rotation = CamFromWorldLookAt({1, 2, 3}, {0, 0, 0}).linear();
  CheckedRotation exact = CheckRotation(rotation, "here");
  EXPECT_FALSE(exact.reorthonormalised());
  EXPECT_EQ(exact.rotation, rotation);  // kept bit for bit
  Eigen::Matrix3d near = rotation;
  near(0, 1) += 5.7e-11;
  CheckedRotation fixed = CheckRotation(near, "here");
  EXPECT_TRUE(fixed.reorthonormalised());
  EXPECT_GT(fixed.residual, 1e-11);
  EXPECT_LT(fixed.residual, 1e-10);
  EXPECT_LT((fixed.rotation.transpose() * fixed.rotation - Eigen::Matrix3d::Identity())
                .cwiseAbs()
                .maxCoeff(),
            1e-15);
  EXPECT_NEAR(fixed.rotation.determinant(), 1, 1e-15);
  EXPECT_LT((fixed.rotation - rotation).cwiseAbs().maxCoeff(), 1e-10);
  auto expect_refused = [](const Eigen::Matrix3d& matrix, const std::string& expected) {
    try {
      CheckRotation(matrix, "f.txt:3");
      ADD_FAILURE() << expected;
    } catch (const Error& e) {
      EXPECT_EQ(std::string(e.what()).rfind("f.txt:3: ", 0), 0u) << e.what();
      EXPECT_NE(std::string(e.what()).find(expected), std::string::npos) << e.what();
    }
  };
  Eigen::Matrix3d huge = rotation;
  huge(1, 2) = 1e308;
  expect_refused(huge, "R[1][2] is 1e+308, outside [-1, 1]");
  Eigen::Matrix3d not_finite = rotation;
  not_finite(2, 0) = NAN;
  expect_refused(not_finite, "R[2][0] is nan, not finite");
  expect_refused(-rotation, "determinant -1");
  Eigen::Matrix3d skewed = rotation;
  skewed(0, 1) += 1e-4;
  expect_refused(skewed, "not orthonormal");
}

TEST(Pose, LookAtUsesOpenCvAxesInAZUpWorld) {
  Pose cam_from_world = CamFromWorldLookAt({3, 0, 1.5}, {0, 0, 1.5});
  Eigen::Vector3d target = cam_from_world * Eigen::Vector3d(0, 0, 1.5);
  EXPECT_NEAR(target.x(), 0, 1e-12);
  EXPECT_NEAR(target.y(), 0, 1e-12);
  EXPECT_NEAR(target.z(), 3, 1e-12);
  Eigen::Vector3d above = cam_from_world * Eigen::Vector3d(0, 0, 2.5);
  EXPECT_LT(above.y(), 0);  // up in the world is up (negative y) in the image
  EXPECT_THROW(CamFromWorldLookAt({0, 0, 0}, {0, 0, 1}), Error);
  Rt rt = {0.1, 0.2, -0.3, 1, 2, 3};
  Rt back = RtFromPose(PoseFromRt(rt));
  for (int i = 0; i < 6; ++i) EXPECT_NEAR(back[i], rt[i], 1e-14);
  EXPECT_NEAR(RotationAngleDeg(PoseFromRt({1e-9, 0, 0, 0, 0, 0}).linear()), 1e-9 * 180 / M_PI,
              1e-20);
}

}  // namespace
}  // namespace holocap
