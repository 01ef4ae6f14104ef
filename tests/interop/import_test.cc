// Import from foreign formats: the real Middlebury set, and files written here by hand after
// each format's documentation, checked against independent projections (OpenCV's
// projectPoints, K[R|t] evaluated directly).
#include <gtest/gtest.h>

#include <fstream>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <random>

#include "capture/replay/replay_driver.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/take.h"
#include "interop/interop.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::TempDir;

void WriteText(const std::filesystem::path& file, const std::string& text) {
  std::filesystem::create_directories(file.parent_path());
  std::ofstream(file) << text;
}

cv::Mat RandomImage(int width, int height, int type, uint64_t seed) {
  cv::Mat image(height, width, type);
  cv::RNG rng(seed);
  rng.fill(image, cv::RNG::UNIFORM, 0, type == CV_16UC3 ? 65536 : 256);
  return image;
}

bool SameImage(const cv::Mat& a, const cv::Mat& b) {
  return a.size() == b.size() && a.type() == b.type() &&
         cv::countNonZero(a.reshape(1) != b.reshape(1)) == 0;
}

// The pixel OpenCV's projectPoints gives for a world point, with the given principal-point
// shift (COLMAP's corner origin: -0.5 to holocap's).
Eigen::Vector2d OpenCvProject(const Eigen::Matrix3d& K, const std::vector<double>& distortion,
                              const Eigen::Matrix3d& R, const Eigen::Vector3d& t,
                              const Eigen::Vector3d& point) {
  cv::Mat k(3, 3, CV_64F), r(3, 3, CV_64F), rvec,
      tvec = (cv::Mat_<double>(3, 1) << t.x(), t.y(), t.z());
  for (int i = 0; i < 9; ++i) {
    k.at<double>(i / 3, i % 3) = K(i / 3, i % 3);
    r.at<double>(i / 3, i % 3) = R(i / 3, i % 3);
  }
  cv::Rodrigues(r, rvec);
  std::vector<cv::Point3d> points = {{point.x(), point.y(), point.z()}};
  std::vector<cv::Point2d> pixels;
  cv::projectPoints(points, rvec, tvec, k, distortion, pixels);
  return {pixels[0].x, pixels[0].y};
}

Eigen::Vector2d KrtProject(const KrtCamera& camera, const Eigen::Vector3d& point) {
  Eigen::Vector3d x = camera.K * (camera.R * point + camera.t);
  return x.head<2>() / x.z();
}

TEST(InteropImport, MiddleburyProjectsExactlyAsItsKRtAndReplaysItsPixels) {
  const auto source = testing::TestDataDir() / "middlebury" / "dinoSparseRing";
  ASSERT_TRUE(std::filesystem::exists(source / "dinoSR_par.txt")) << source;
  TempDir dir;
  ImportOptions options;
  options.format = InteropFormat::kMiddlebury;
  ImportSummary summary = ImportTake(source, dir / "take", options);
  EXPECT_EQ(summary.sensors, 16);
  EXPECT_EQ(summary.frame_sets, 1);
  // The file's rotations are non-orthonormal by ~1e-6 in one shared way.
  EXPECT_GT(summary.metrics["rotation_non_orthonormality"].get<double>(), 1e-7);
  EXPECT_LT(summary.metrics["rotation_residual"].get<double>(), 1e-12);

  Take take = Take::Open(dir / "take");
  std::vector<double> s =
      take.metadata()["interop"]["world_from_source"].get<std::vector<double>>();
  Eigen::Matrix3d world_from_source =
      Eigen::Map<Eigen::Matrix<double, 3, 3, Eigen::RowMajor>>(s.data());
  std::vector<KrtCamera> cameras =
      ParseMiddleburyPar(ReadFileToString(source / "dinoSR_par.txt"), "par");
  ASSERT_EQ(cameras.size(), 16u);
  // Points spread over the README's bounding box, corners included.
  const Eigen::Vector3d lo(-0.061897, -0.018874, -0.057845), hi(0.010897, 0.068227, 0.015495);
  double worst = 0;
  int points = 0;
  for (const auto& camera : cameras) {
    const std::string sensor = std::filesystem::path(camera.name).stem().string();
    CameraModel model = take.Camera(sensor);
    for (int i = 0; i <= 4; ++i)
      for (int j = 0; j <= 4; ++j)
        for (int k = 0; k <= 4; ++k) {
          Eigen::Vector3d point = lo + (hi - lo).cwiseProduct(Eigen::Vector3d(i, j, k) / 4.0);
          Eigen::Vector2d pixel;
          ASSERT_TRUE(model.ProjectWorld(world_from_source * point, &pixel));
          worst = std::max(worst, (pixel - KrtProject(camera, point)).norm());
          ++points;
        }
  }
  EXPECT_EQ(points, 16 * 125);
  EXPECT_LT(worst, 1e-9) << "largest projection difference " << worst << " px";
  std::printf("middlebury: %d points x cameras, largest difference to K[R|t] %.3g px\n", points,
              worst);

  // Without the shared non-orthonormal part the same cameras would be off by far more than that.
  double without = 0;
  CameraModel first = take.Camera("dinoSR0001");
  Eigen::Vector2d pixel;
  ASSERT_TRUE(first.ProjectWorld(lo, &pixel));
  without = (pixel - KrtProject(cameras[0], lo)).norm();
  EXPECT_GT(without, 1e-6);

  // Replay yields the original pixels.
  DriverRegistry registry;
  RegisterReplayDriver(registry);
  for (const std::string sensor : {"dinoSR0001", "dinoSR0016"}) {
    SensorSpec spec;
    spec.name = sensor;
    spec.uri = "replay:" + (dir / "take").string() + "#" + sensor;
    auto replay = registry.Open(spec);
    replay->Start();
    Frame frame;
    ASSERT_TRUE(replay->Grab(&frame, std::chrono::milliseconds(1000)));
    cv::Mat original = cv::imread((source / (sensor + ".png")).string(), cv::IMREAD_UNCHANGED);
    EXPECT_TRUE(SameImage(frame.image, original)) << sensor;
    EXPECT_FALSE(replay->Grab(&frame, std::chrono::milliseconds(10)));
  }
}

// A COLMAP model with every exactly-importable camera model, written by hand.
struct ColmapFixture {
  struct Camera {
    std::string model;
    std::vector<double> params;
    Eigen::Matrix3d K;               // holocap convention
    std::vector<double> distortion;  // OpenCV order
  };
  std::vector<Camera> cameras;
  std::vector<Eigen::Matrix3d> rotations;
  std::vector<Eigen::Vector3d> translations;
  std::vector<Eigen::Vector3d> points;
};

ColmapFixture MakeColmapFixture() {
  ColmapFixture f;
  auto k = [](double fx, double fy, double cx, double cy) {
    Eigen::Matrix3d K;
    K << fx, 0, cx - 0.5, 0, fy, cy - 0.5, 0, 0, 1;
    return K;
  };
  f.cameras.push_back({"SIMPLE_PINHOLE", {300, 80.25, 60.5}, k(300, 300, 80.25, 60.5), {}});
  f.cameras.push_back({"PINHOLE", {310, 305, 79.5, 61}, k(310, 305, 79.5, 61), {}});
  f.cameras.push_back(
      {"SIMPLE_RADIAL", {290, 81, 59, -0.12}, k(290, 290, 81, 59), {-0.12, 0, 0, 0}});
  f.cameras.push_back(
      {"RADIAL", {295, 80, 60, -0.1, 0.03}, k(295, 295, 80, 60), {-0.1, 0.03, 0, 0}});
  f.cameras.push_back({"OPENCV",
                       {300, 302, 80.7, 59.2, -0.2, 0.05, 0.001, -0.002},
                       k(300, 302, 80.7, 59.2),
                       {-0.2, 0.05, 0.001, -0.002}});
  f.cameras.push_back({"FULL_OPENCV",
                       {298, 299, 80.1, 60.3, -0.2, 0.05, 0.0005, -0.001, 0.01, 0.02, -0.01, 0.003},
                       k(298, 299, 80.1, 60.3),
                       {-0.2, 0.05, 0.0005, -0.001, 0.01, 0.02, -0.01, 0.003}});
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> unit(-1, 1);
  for (size_t i = 0; i < f.cameras.size(); ++i) {
    Eigen::Vector3d eye(3 * std::cos(i), 3 * std::sin(i), 0.5 * unit(rng));
    Pose cam_from_world =
        CamFromWorldLookAt(eye, Eigen::Vector3d(0.1 * unit(rng), 0.1 * unit(rng), 0));
    f.rotations.push_back(cam_from_world.linear());
    f.translations.push_back(cam_from_world.translation());
  }
  for (int i = 0; i < 40; ++i)
    f.points.emplace_back(0.4 * unit(rng), 0.4 * unit(rng), 0.4 * unit(rng));
  return f;
}

std::string QuaternionLine(const Eigen::Matrix3d& rotation, const Eigen::Vector3d& t) {
  Eigen::Quaterniond q(rotation);
  char line[512];
  std::snprintf(line, sizeof(line), "%.17g %.17g %.17g %.17g %.17g %.17g %.17g", q.w(), q.x(),
                q.y(), q.z(), t.x(), t.y(), t.z());
  return line;
}

// Writes the model with observations offset by known amounts, and each point's ERROR computed
// with OpenCV, as COLMAP would have it.
void WriteColmapModel(const ColmapFixture& f, const std::filesystem::path& dir) {
  std::string cameras = "# Camera list with one line of data per camera:\n";
  std::string images = "# Image list with two lines of data per image:\n";
  for (size_t c = 0; c < f.cameras.size(); ++c) {
    cameras += Cat(c + 1, " ", f.cameras[c].model, " 160 120");
    for (double p : f.cameras[c].params) cameras += Cat(" ", p);
    cameras += "\n";
  }
  std::vector<std::vector<std::pair<int64_t, int64_t>>> tracks(f.points.size());
  std::vector<double> errors(f.points.size(), 0);
  for (size_t c = 0; c < f.cameras.size(); ++c) {
    images += Cat(c + 1, " ", QuaternionLine(f.rotations[c], f.translations[c]), " ", c + 1,
                  " view", c, ".png\n");
    std::string line;
    for (size_t p = 0; p < f.points.size(); ++p) {
      Eigen::Vector2d pixel = OpenCvProject(f.cameras[c].K, f.cameras[c].distortion, f.rotations[c],
                                            f.translations[c], f.points[p]);
      // A known observation error, different per observation.
      Eigen::Vector2d offset(0.01 * ((p + c) % 5), -0.02 * ((p * c) % 3));
      Eigen::Vector2d observed = pixel + offset + Eigen::Vector2d::Constant(0.5);
      char observation[100];
      std::snprintf(observation, sizeof(observation), "%s%.17g %.17g %zu", line.empty() ? "" : " ",
                    observed.x(), observed.y(), p + 1);
      line += observation;
      tracks[p].emplace_back(c + 1, p);
      errors[p] += offset.norm() / f.cameras.size();
    }
    images += line + "\n";
  }
  std::string points = "# 3D point list with one line of data per point:\n";
  for (size_t p = 0; p < f.points.size(); ++p) {
    char xyz[200];
    std::snprintf(xyz, sizeof(xyz), "%.17g %.17g %.17g", f.points[p].x(), f.points[p].y(),
                  f.points[p].z());
    char error[40];
    std::snprintf(error, sizeof(error), "%.17g", errors[p]);
    points += Cat(p + 1, " ", xyz, " 128 64 32 ", error);
    for (const auto& [image, index] : tracks[p]) points += Cat(" ", image, " ", index);
    points += "\n";
  }
  WriteText(dir / "sparse" / "0" / "cameras.txt", cameras);
  WriteText(dir / "sparse" / "0" / "images.txt", images);
  WriteText(dir / "sparse" / "0" / "points3D.txt", points);
  std::filesystem::create_directories(dir / "images");
  for (size_t c = 0; c < f.cameras.size(); ++c) {
    cv::imwrite((dir / "images" / Cat("view", c, ".png")).string(),
                RandomImage(160, 120, CV_8UC3, c));
  }
}

TEST(InteropImport, ColmapCamerasMatchOpenCvAndPointErrorsMatchTheFile) {
  TempDir dir;
  ColmapFixture f = MakeColmapFixture();
  WriteColmapModel(f, dir.path());
  ImportOptions options;
  options.format = InteropFormat::kColmap;
  ImportSummary summary = ImportTake(dir.path(), dir / "take", options);
  ASSERT_EQ(summary.sensors, 6);
  EXPECT_EQ(summary.frame_sets, 1);
  Take take = Take::Open(dir / "take");
  const char* expected_lens[] = {"LENSMODEL_PINHOLE", "LENSMODEL_PINHOLE", "LENSMODEL_OPENCV4",
                                 "LENSMODEL_OPENCV4", "LENSMODEL_OPENCV4", "LENSMODEL_OPENCV8"};
  double worst = 0;
  for (size_t c = 0; c < f.cameras.size(); ++c) {
    CameraModel model = take.Camera(Cat("view", c));
    EXPECT_EQ(model.lensmodel(), expected_lens[c]) << f.cameras[c].model;
    for (const auto& point : f.points) {
      Eigen::Vector2d pixel;
      ASSERT_TRUE(model.ProjectWorld(point, &pixel));
      Eigen::Vector2d reference = OpenCvProject(f.cameras[c].K, f.cameras[c].distortion,
                                                f.rotations[c], f.translations[c], point);
      worst = std::max(worst, (pixel - reference).norm());
    }
    EXPECT_TRUE(SameImage(take.ReadFrame(0, Cat("view", c)), RandomImage(160, 120, CV_8UC3, c)));
  }
  EXPECT_LT(worst, 1e-9) << worst;
  const auto& points = summary.metrics["colmap_points"];
  EXPECT_EQ(points["count"].get<int>(), 40);
  EXPECT_EQ(points["observations"].get<int>(), 240);
  EXPECT_GT(points["file_mean_reprojection_error_px"].get<double>(), 0.005);
  EXPECT_NEAR(points["mean_reprojection_error_px"].get<double>(),
              points["file_mean_reprojection_error_px"].get<double>(), 1e-9);
  EXPECT_LT(points["max_per_point_difference_px"].get<double>(), 1e-9);
  std::printf("colmap: cameras vs OpenCV %.3g px; points3D mean error %.9f px, file %.9f px\n",
              worst, points["mean_reprojection_error_px"].get<double>(),
              points["file_mean_reprojection_error_px"].get<double>());
}

TEST(InteropImport, ColmapFisheyeIsRefusedByName) {
  TempDir dir;
  WriteText(dir / "cameras.txt", "1 OPENCV_FISHEYE 100 80 90 90 50 40 0.1 0.01 0 0\n");
  WriteText(dir / "images.txt", "1 1 0 0 0 0 0 0 1 a.png\n\n");
  WriteText(dir / "points3D.txt", "");
  cv::imwrite((dir / "a.png").string(), RandomImage(100, 80, CV_8UC3, 1));
  ImportOptions options;
  options.format = InteropFormat::kColmap;
  options.images = dir.path();
  try {
    ReadForeignRig(dir.path(), options);
    FAIL() << "a fisheye model was imported";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("OPENCV_FISHEYE"), std::string::npos) << e.what();
  }
}

TEST(InteropImport, BlenderTransformsUseOpenGlAxesAndTheImageCentre) {
  TempDir dir;
  // Blender synthetic layout: camera_angle_x only, file paths without extension, RGBA frames.
  const double angle = 0.6911112070083618;
  Eigen::Matrix4d c2w = Eigen::Matrix4d::Identity();
  c2w.topLeftCorner<3, 3>() = (Eigen::AngleAxisd(3.1, Eigen::Vector3d::UnitZ()) *
                               Eigen::AngleAxisd(1.27, Eigen::Vector3d::UnitX()))
                                  .toRotationMatrix();
  c2w.topRightCorner<3, 1>() = Eigen::Vector3d(-0.05, 3.85, 1.21);
  nlohmann::json json;
  json["camera_angle_x"] = angle;
  for (int i = 0; i < 2; ++i) {
    nlohmann::json frame;
    frame["file_path"] = Cat("./train/r_", i);
    Eigen::Matrix4d m = c2w;
    m(2, 3) += i;  // the second camera one unit higher
    for (int r = 0; r < 4; ++r)
      frame["transform_matrix"].push_back({m(r, 0), m(r, 1), m(r, 2), m(r, 3)});
    json["frames"].push_back(frame);
    cv::Mat rgba = RandomImage(40, 40, CV_8UC4, 10 + i);
    std::filesystem::create_directories(dir / "train");
    cv::imwrite((dir / "train" / Cat("r_", i, ".png")).string(), rgba);
  }
  WriteText(dir / "transforms.json", json.dump());
  ImportOptions options;
  options.format = InteropFormat::kNerf;
  ImportSummary summary = ImportTake(dir / "transforms.json", dir / "take", options);
  EXPECT_EQ(summary.sensors, 2);
  EXPECT_EQ(summary.metrics["alpha_channels_dropped"].get<int>(), 0);
  EXPECT_EQ(summary.metrics["alpha_channels_kept"].get<int>(), 2);
  Take take = Take::Open(dir / "take");
  CameraModel camera = take.Camera("r_0");
  const double f = 20 / std::tan(angle / 2);
  EXPECT_NEAR(camera.intrinsics()[0], f, 1e-12);
  EXPECT_NEAR(camera.intrinsics()[2], 19.5, 1e-12);  // the centre of a 40-pixel-wide image
  // The camera looks down its -z (OpenGL): a point ahead of it lands on the principal point,
  // and a point up its +y lands above it (smaller row).
  Eigen::Vector3d eye = c2w.topRightCorner<3, 1>();
  Eigen::Vector3d ahead = eye - 2 * c2w.block<3, 1>(0, 2);
  Eigen::Vector3d up = ahead + 0.1 * c2w.block<3, 1>(0, 1);
  Eigen::Vector2d pixel;
  ASSERT_TRUE(camera.ProjectWorld(ahead, &pixel));
  EXPECT_LT((pixel - Eigen::Vector2d(19.5, 19.5)).norm(), 1e-9);
  ASSERT_TRUE(camera.ProjectWorld(up, &pixel));
  EXPECT_NEAR(pixel.y(), 19.5 - f * 0.05, 1e-9);
  EXPECT_NEAR(pixel.x(), 19.5, 1e-9);
  // Alpha is kept: the frame is the RGBA image exactly, its stream bgra8.
  EXPECT_EQ(take.stream("r_1").pixel_format, "bgra8");
  EXPECT_TRUE(SameImage(take.ReadFrame(0, "r_1"), RandomImage(40, 40, CV_8UC4, 11)));
}

// NeRF-synthetic's layout: a folder with transforms_{train,val,test}.json and no
// transforms.json. The folder imports its training split and says what it left out.
TEST(InteropImport, NerfFolderWithSplitsImportsTheTrainingSplitAndSaysSo) {
  TempDir dir;
  auto write_split = [&](const std::string& split, int count) {
    nlohmann::json json;
    json["camera_angle_x"] = 0.69;
    for (int i = 0; i < count; ++i) {
      nlohmann::json frame;
      frame["file_path"] = Cat("./", split, "/r_", i);
      Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
      m(0, 3) = i;
      for (int r = 0; r < 4; ++r)
        frame["transform_matrix"].push_back({m(r, 0), m(r, 1), m(r, 2), m(r, 3)});
      json["frames"].push_back(frame);
      std::filesystem::create_directories(dir / split);
      cv::imwrite((dir / split / Cat("r_", i, ".png")).string(),
                  RandomImage(24, 24, CV_8UC4, 30 + i));
    }
    WriteText(dir / Cat("transforms_", split, ".json"), json.dump());
  };
  write_split("train", 3);
  write_split("test", 2);
  ImportOptions options;
  options.format = InteropFormat::kNerf;
  ImportSummary summary = ImportTake(dir.path(), dir / "take", options);
  EXPECT_EQ(summary.sensors, 3);
  EXPECT_NE(summary.message.find("training split (transforms_train.json) without "
                                 "transforms_test.json"),
            std::string::npos)
      << summary.message;
  // A folder with neither name says which names it looked for.
  TempDir empty;
  try {
    ReadForeignRig(empty.path(), options);
    FAIL() << "an empty folder imported";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("transforms.json, transforms_train.json"),
              std::string::npos)
        << e.what();
  }
  // A split named as a file imports that split.
  ImportSummary test = ImportTake(dir / "transforms_test.json", dir / "test-take", options);
  EXPECT_EQ(test.sensors, 2);
}

TEST(InteropImport, NeuralVolumesKrtAlignsNumberedFramesAcrossCameras) {
  TempDir dir;
  std::vector<KrtCamera> cameras(2);
  cameras[0].name = "400001";
  cameras[0].K << 500, 0, 31.5, 0, 505, 23.5, 0, 0, 1;
  cameras[0].distortion = {-0.1, 0.02, 0.001, 0.0005, 0.004};
  cameras[0].R = CamFromWorldLookAt({2, 0, 0.3}, {0, 0, 0}).linear();
  cameras[0].t = CamFromWorldLookAt({2, 0, 0.3}, {0, 0, 0}).translation();
  cameras[1].name = "400002";
  cameras[1].K << 480, 0, 32, 0, 480, 24, 0, 0, 1;
  cameras[1].distortion = {0, 0, 0, 0, 0};
  cameras[1].R = CamFromWorldLookAt({0, 2, 0.3}, {0, 0, 0}).linear();
  cameras[1].t = CamFromWorldLookAt({0, 2, 0.3}, {0, 0, 0}).translation();
  WriteText(dir / "KRT", FormatNeuralVolumesKrt(cameras));
  // Camera 400002 lost frame 1.
  for (int frame : {0, 1, 2}) {
    std::filesystem::create_directories(dir / "cam400001");
    std::filesystem::create_directories(dir / "cam400002");
    cv::imwrite((dir / "cam400001" / Cat("image000", frame, ".png")).string(),
                RandomImage(64, 48, CV_8UC3, frame));
    if (frame != 1)
      cv::imwrite((dir / "cam400002" / Cat("image000", frame, ".png")).string(),
                  RandomImage(64, 48, CV_8UC3, 50 + frame));
  }
  ImportOptions options;
  options.format = InteropFormat::kKrt;
  ImportSummary summary = ImportTake(dir.path(), dir / "take", options);
  EXPECT_EQ(summary.frame_sets, 3);
  EXPECT_EQ(summary.frames, 5);
  Take take = Take::Open(dir / "take");
  EXPECT_EQ(take.entry(1).Find("cam400002"), nullptr);
  EXPECT_TRUE(SameImage(take.ReadFrame(2, "cam400002"), RandomImage(64, 48, CV_8UC3, 52)));
  EXPECT_EQ(take.Camera("cam400001").lensmodel(), "LENSMODEL_OPENCV5");
  EXPECT_EQ(take.Camera("cam400002").lensmodel(), "LENSMODEL_PINHOLE");
  double worst = 0;
  for (int c = 0; c < 2; ++c) {
    CameraModel model = take.Camera(Cat("cam40000", c + 1));
    for (double x : {-0.3, 0.0, 0.3})
      for (double z : {-0.2, 0.25}) {
        Eigen::Vector3d point(x, 0.1 * x, z);
        Eigen::Vector2d pixel;
        ASSERT_TRUE(model.ProjectWorld(point, &pixel));
        worst = std::max(worst, (pixel - OpenCvProject(cameras[c].K, cameras[c].distortion,
                                                       cameras[c].R, cameras[c].t, point))
                                    .norm());
      }
  }
  EXPECT_LT(worst, 1e-9);
}

TEST(InteropImport, PanopticCentimetresBecomeMetresAndUnrecordedCamerasAreSkipped) {
  TempDir dir;
  Pose pose = CamFromWorldLookAt({150, -200, 120}, {0, 0, 90});
  nlohmann::json json;
  for (const std::string name : {"00_00", "00_01"}) {
    nlohmann::json camera;
    camera["name"] = name;
    camera["type"] = "hd";
    camera["resolution"] = {32, 24};
    camera["K"] = {{1400.5, 0, 15.2}, {0, 1401.25, 11.9}, {0, 0, 1}};
    camera["distCoef"] = {-0.21, 0.15, 0.0004, -0.0003, -0.02};
    for (int r = 0; r < 3; ++r)
      camera["R"].push_back({pose.linear()(r, 0), pose.linear()(r, 1), pose.linear()(r, 2)});
    for (int r = 0; r < 3; ++r) camera["t"].push_back({pose.translation()(r)});
    json["cameras"].push_back(camera);
  }
  WriteText(dir / "calibration_171026_pose1.json", json.dump());
  std::filesystem::create_directories(dir / "hdImgs" / "00_00");
  cv::imwrite((dir / "hdImgs" / "00_00" / "00_00_00000123.jpg").string(),
              RandomImage(32, 24, CV_8UC3, 3));
  ImportOptions options;
  options.format = InteropFormat::kPanoptic;
  ImportSummary summary = ImportTake(dir.path(), dir / "take", options);
  EXPECT_EQ(summary.sensors, 1);
  EXPECT_EQ(summary.metrics["cameras_skipped_without_images"].get<int>(), 1);
  Take take = Take::Open(dir / "take");
  CameraModel model = take.Camera("00_00");
  EXPECT_NEAR(model.center_in_world().x(), 1.5, 1e-12);  // 150 cm
  // The JPEG's decoded pixels are what the take holds.
  cv::Mat decoded =
      cv::imread((dir / "hdImgs" / "00_00" / "00_00_00000123.jpg").string(), cv::IMREAD_UNCHANGED);
  EXPECT_TRUE(SameImage(take.ReadFrame(0, "00_00"), decoded));
  Eigen::Matrix3d K;
  K << 1400.5, 0, 15.2, 0, 1401.25, 11.9, 0, 0, 1;
  Eigen::Vector3d point_cm(10, -5, 100);
  Eigen::Vector2d pixel;
  ASSERT_TRUE(model.ProjectWorld(point_cm / 100, &pixel));
  Eigen::Vector2d reference = OpenCvProject(K, {-0.21, 0.15, 0.0004, -0.0003, -0.02}, pose.linear(),
                                            pose.translation(), point_cm);
  EXPECT_LT((pixel - reference).norm(), 1e-9);
  // The same calibration named camera_parameters.json is found in its folder too; a folder
  // holding both names asks which one.
  std::filesystem::rename(dir / "calibration_171026_pose1.json", dir / "camera_parameters.json");
  ImportSummary renamed = ImportTake(dir.path(), dir / "take2", options);
  EXPECT_EQ(renamed.sensors, 1);
  EXPECT_NEAR(Take::Open(dir / "take2").Camera("00_00").center_in_world().x(), 1.5, 1e-12);
  WriteText(dir / "calibration_other.json", "{}");
  try {
    ImportTake(dir.path(), dir / "take3", options);
    FAIL() << "a folder with two calibrations imported";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("holds both camera_parameters.json and a "
                                         "calibration_*.json"),
              std::string::npos)
        << e.what();
  }
}

TEST(InteropImport, MrcalFoldersKeepTheModels) {
  TempDir dir;
  CameraModel lens =
      CameraModel::Read(testing::TestDataDir() / "lenses" / "wide-4000x2200.opencv8.cameramodel")
          .Scaled(0.02);
  lens.set_cam_from_world(CamFromWorldLookAt({1, 2, 1.5}, {0, 0, 1}));
  lens.Write(dir / "left.cameramodel");
  std::filesystem::create_directories(dir / "left");
  for (int i = 0; i < 2; ++i) {
    cv::imwrite((dir / "left" / Cat("frame", i, ".png")).string(),
                RandomImage(lens.width(), lens.height(), CV_16UC3, i));
  }
  ImportOptions options;
  options.format = InteropFormat::kMrcal;
  ImportSummary summary = ImportTake(dir.path(), dir / "take", options);
  EXPECT_EQ(summary.frame_sets, 2);
  Take take = Take::Open(dir / "take");
  EXPECT_EQ(take.stream("left").pixel_format, "bgr16");
  CameraModel back = take.Camera("left");
  EXPECT_EQ(back.lensmodel(), lens.lensmodel());
  EXPECT_EQ(back.intrinsics(), lens.intrinsics());
  EXPECT_LT((back.cam_from_world().matrix() - lens.cam_from_world().matrix()).cwiseAbs().maxCoeff(),
            1e-15);
  EXPECT_TRUE(
      SameImage(take.ReadFrame(1, "left"), RandomImage(lens.width(), lens.height(), CV_16UC3, 1)));
}

// The message of the Error `call` throws ("" when none).
std::string ErrorOf(const std::function<void()>& call) {
  try {
    call();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

// A rotation entry of 1e308 in a Middlebury _par.txt or a KRT file imported as
// SUCCESS (take.json held nulls, the camera turned by pi). It is refused naming file, line and
// entry, and nothing is written.
TEST(InteropImport, RotationEntriesNoRotationHasAreRefusedNamingFileLineAndEntry) {
  TempDir dir;
  const auto dino = testing::TestDataDir() / "middlebury" / "dinoSparseRing";
  std::string par = ReadFileToString(dino / "dinoSR_par.txt");
  const std::string r12 = "0.96422332027030622000";  // R[0][1] of dinoSR0002.png, line 3
  ASSERT_NE(par.find(r12), std::string::npos);
  par.replace(par.find(r12), r12.size(), "1e308");
  WriteText(dir / "dino/dinoSR_par.txt", par);
  ImportOptions options;
  options.format = InteropFormat::kMiddlebury;
  options.images = dino;
  std::string error = ErrorOf([&] { ImportTake(dir / "dino", dir / "take", options); });
  EXPECT_NE(error.find("dinoSR_par.txt:3 (r11..r33): camera 'dinoSR0002.png': rotation entry "
                       "R[0][1] is 1e+308, outside [-1, 1]"),
            std::string::npos)
      << error;
  EXPECT_FALSE(std::filesystem::exists(dir / "take"));

  std::vector<KrtCamera> cameras(1);
  cameras[0].name = "400001";
  cameras[0].K << 500, 0, 31.5, 0, 505, 23.5, 0, 0, 1;
  cameras[0].R(2, 2) = 1e308;
  WriteText(dir / "nv/KRT", FormatNeuralVolumesKrt(cameras));
  std::filesystem::create_directories(dir / "nv/cam400001");
  cv::imwrite((dir / "nv/cam400001/image0000.png").string(), RandomImage(64, 48, CV_8UC3, 1));
  options.format = InteropFormat::kKrt;
  options.images.clear();
  error = ErrorOf([&] { ImportTake(dir / "nv", dir / "take", options); });
  EXPECT_NE(error.find("KRT:6-8 ([R|t]): camera '400001': rotation entry R[2][2] is 1e+308"),
            std::string::npos)
      << error;
  EXPECT_FALSE(std::filesystem::exists(dir / "take"));
}

// Real calibrations print rotations to ~1e-11 (CMU Panoptic's are 5.7e-11 from orthonormal, each
// in its own way) and were refused at the old 1e-12; they now import with no option, each camera
// given its nearest rotation and the report saying so.
TEST(InteropImport, NearlyOrthonormalRotationsAreReorthonormalisedAndSaidSo) {
  TempDir dir;
  nlohmann::json json;
  const std::vector<Eigen::Vector3d> eyes = {{150, -200, 120}, {-180, -150, 110}};
  for (int c = 0; c < 2; ++c) {
    Pose pose = CamFromWorldLookAt(eyes[c], {0, 0, 90});
    Eigen::Matrix3d R = pose.linear();
    R(c, 1 - c) += 5.7e-11;  // differently in each camera
    nlohmann::json camera;
    camera["name"] = Cat("00_0", c);
    camera["resolution"] = {32, 24};
    camera["K"] = {{1400.5, 0, 15.2}, {0, 1401.25, 11.9}, {0, 0, 1}};
    for (int r = 0; r < 3; ++r) camera["R"].push_back({R(r, 0), R(r, 1), R(r, 2)});
    for (int r = 0; r < 3; ++r) camera["t"].push_back({pose.translation()(r)});
    json["cameras"].push_back(camera);
    std::filesystem::create_directories(dir / "hdImgs" / Cat("00_0", c));
    cv::imwrite((dir / "hdImgs" / Cat("00_0", c) / "00_00000001.png").string(),
                RandomImage(32, 24, CV_8UC3, c));
  }
  WriteText(dir / "calibration_x.json", json.dump());
  ImportOptions options;
  options.format = InteropFormat::kPanoptic;
  ImportSummary summary = ImportTake(dir.path(), dir / "take", options);
  EXPECT_EQ(summary.termination, Termination::kSuccess) << summary.message;
  EXPECT_GT(summary.metrics["rotation_residual"].get<double>(), 1e-12);
  for (const char* camera : {"camera 00_00: rotation re-orthonormalised (residual ",
                             "camera 00_01: rotation re-orthonormalised (residual "}) {
    EXPECT_NE(summary.message.find(camera), std::string::npos) << summary.message;
  }
  Take take = Take::Open(dir / "take");
  for (int c = 0; c < 2; ++c) {
    const Eigen::Matrix3d R = take.Camera(Cat("00_0", c)).cam_from_world().linear();
    EXPECT_LT((R.transpose() * R - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff(), 1e-15);
    EXPECT_LT((R - CamFromWorldLookAt(eyes[c], {0, 0, 90}).linear()).cwiseAbs().maxCoeff(), 1e-10);
  }
}

// `import mrcal` accepted a negative focal length. Refused, naming file and field.
TEST(InteropImport, MrcalModelWithANegativeFocalLengthIsRefused) {
  TempDir dir;
  std::string model = CameraModel::Pinhole(40, 32, 24).ToString();
  model.replace(model.find("'intrinsics': [ 40"), 18, "'intrinsics': [ -40");
  WriteText(dir / "left.cameramodel", model);
  std::filesystem::create_directories(dir / "left");
  cv::imwrite((dir / "left/frame0.png").string(), RandomImage(32, 24, CV_8UC3, 0));
  ImportOptions options;
  options.format = InteropFormat::kMrcal;
  const std::string error = ErrorOf([&] { ImportTake(dir.path(), dir / "take", options); });
  EXPECT_NE(error.find("left.cameramodel': camera model: intrinsics[0] (fx) is -40: a focal "
                       "length must be positive"),
            std::string::npos)
      << error;
  EXPECT_FALSE(std::filesystem::exists(dir / "take"));
}

// Each malformed file gives one Error naming the file; none crashes or imports something.
TEST(InteropImport, MalformedFilesGiveOneClearError) {
  struct Case {
    const char* what;
    std::function<void()> parse;
    const char* expected;
  };
  std::vector<Case> cases = {
      {"par count",
       [] {
         ParseMiddleburyPar("3\na.png 1 0 0 0 1 0 0 0 1 1 0 0 0 1 0 0 0 1 0 0 1\n", "x_par.txt");
       },
       "announces 3"},
      {"par field",
       [] {
         ParseMiddleburyPar("1\na.png 1 0 0 0 1 0 0 0 1 1 0 0 0 1 0 0 0 1 0 0 nan\n", "x_par.txt");
       },
       "not a finite"},
      {"par short", [] { ParseMiddleburyPar("1\na.png 1 0 0\n", "x_par.txt"); }, "22 fields"},
      {"krt short", [] { ParseNeuralVolumesKrt("cam\n1 0 0\n0 1 0\n", "KRT"); }, "ends early"},
      {"krt row",
       [] { ParseNeuralVolumesKrt("cam\n1 0 0\n0 1 0\n0 0 1\n0 0 0 0 0\n1 0 0\n", "KRT"); },
       "[R|t]"},
      {"colmap model", [] { ParseColmapCameras("1 WEIRD 10 10 1 2 3\n", "cameras.txt"); },
       "unknown COLMAP camera model"},
      {"colmap params", [] { ParseColmapCameras("1 PINHOLE 10 10 1 2 3\n", "cameras.txt"); },
       "takes 4 parameters"},
      {"colmap size", [] { ParseColmapCameras("1 PINHOLE -10 10 1 2 3 4\n", "cameras.txt"); },
       "out of range"},
      {"colmap quaternion", [] { ParseColmapImages("1 2 0 0 0 0 0 0 1 a.png\n\n", "images.txt"); },
       "unit length"},
      {"colmap points2d", [] { ParseColmapImages("1 1 0 0 0 0 0 0 1 a.png\n1 2\n", "images.txt"); },
       "triples"},
      {"colmap point", [] { ParseColmapPoints("1 0 0 0 300 0 0 0.5\n", "points3D.txt"); },
       "outside 0..255"},
      {"nerf json", [] { ParseNerfTransforms("{\"frames\": [", "transforms.json"); },
       "not valid JSON"},
      {"nerf matrix",
       [] {
         ParseNerfTransforms(R"({"frames": [{"file_path": "a", "transform_matrix": [[1,0]]}]})",
                             "transforms.json");
       },
       "transform_matrix"},
      {"nerf k4",
       [] {
         NerfIntrinsics intrinsics;
         intrinsics.fl_x = 10;
         intrinsics.distortion["k4"] = 0.1;
         CameraFromNerf(intrinsics, Eigen::Matrix4d::Identity(), 8, 8, "t");
       },
       "k4"},
      {"panoptic",
       [] {
         ParsePanopticCalibration(R"({"cameras": [{"name": "a", "K": [[1]], "R": [], "t": []}]})",
                                  "calibration_x.json");
       },
       "K must be"},
      {"skew",
       [] {
         KrtCamera camera;
         camera.K << 100, 1, 5, 0, 100, 5, 0, 0, 1;
         camera.width = camera.height = 10;
         CameraFromKrt(camera, Pose::Identity());
       },
       "skew"},
  };
  for (const auto& test : cases) {
    try {
      test.parse();
      ADD_FAILURE() << test.what << ": accepted";
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find(test.expected), std::string::npos)
          << test.what << ": " << e.what();
      EXPECT_EQ(std::string(e.what()).find('\n'), std::string::npos)
          << test.what << ": " << e.what();
    }
  }
}

}  // namespace
}  // namespace holocap
