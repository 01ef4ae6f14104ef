// Neural rerendering: the G-buffer rasteriser against analytic spheres and planes through
// distorted and wide lenses, the U-Net on empty, holed and NaN buffers, and the CLI end to
// end on a tiny simulated take (train rerender, render --model).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <iostream>
#include <limits>
#include <nlohmann/json.hpp>
#include <opencv2/imgproc.hpp>
#include <set>

#include "core/camera.h"
#include "core/error.h"
#include "core/image.h"
#include "core/mesh.h"
#include "core/pose.h"
#include "neural/rerender.h"
#include "tests/reconstruction/synthetic.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::Sphere;

int CountMismatch(const cv::Mat& a, const cv::Mat& b) {
  cv::Mat diff;
  cv::bitwise_xor(a, b, diff);
  return cv::countNonZero(diff);
}

TEST(RerenderRaster, SphereMatchesRayCastingThroughDistortedLenses) {
  const Sphere sphere;
  const Mesh mesh = testing::SphereMesh(sphere, 64, 128);
  for (const CameraModel& camera :
       testing::RingCameras(4, sphere, 1.4, 160, 120, /*distorted=*/true)) {
    const GBuffer buffers = RasteriseMesh(mesh, camera);
    cv::Mat depth, mask;
    testing::RenderSphere(camera, sphere, &depth, &mask);
    const int area = cv::countNonZero(mask);
    ASSERT_GT(area, 2000) << camera.lensmodel();
    // Only pixels on the rim may disagree (the mesh is a polygon inscribed in the sphere).
    EXPECT_LT(CountMismatch(buffers.mask, mask), 0.03 * area) << camera.lensmodel();
    double depth_error = 0, normal_error_deg = 0, position_error = 0;
    int count = 0;
    const Eigen::Vector3d centre_in_cam = camera.cam_from_world() * sphere.centre;
    for (int y = 0; y < mask.rows; ++y) {
      for (int x = 0; x < mask.cols; ++x) {
        if (!mask.at<uint8_t>(y, x) || !buffers.mask.at<uint8_t>(y, x)) continue;
        const float z = buffers.depth.at<float>(y, x);
        depth_error += std::abs(z - depth.at<float>(y, x));
        const Eigen::Vector3d ray = camera.Unproject(Eigen::Vector2d(x, y));
        const Eigen::Vector3d point = ray * (depth.at<float>(y, x) / ray.z());
        const Eigen::Vector3d truth = (point - centre_in_cam).normalized();
        const cv::Vec3f p = buffers.position.at<cv::Vec3f>(y, x);
        position_error +=
            (camera.cam_from_world().inverse() * point - Eigen::Vector3d(p[0], p[1], p[2])).norm();
        const cv::Vec3f n = buffers.normal.at<cv::Vec3f>(y, x);
        const double cosine = std::clamp(truth.dot(Eigen::Vector3d(n[0], n[1], n[2])), -1.0, 1.0);
        normal_error_deg += std::acos(cosine) * 180 / M_PI;
        ++count;
      }
    }
    ASSERT_GT(count, 0);
    EXPECT_LT(depth_error / count, 1e-3) << camera.lensmodel();  // metres
    EXPECT_LT(position_error / count, 2e-3) << camera.lensmodel();
    EXPECT_LT(normal_error_deg / count, 2.0) << camera.lensmodel();
    // Vertex colours default to mid grey where the mesh has none.
    EXPECT_NEAR(cv::mean(buffers.color, buffers.mask)[1], 0.5, 1e-3);
  }
}

// A slanted wall filling most of a real wide lens's view: its straight edges and its depth
// bend in the image, so big triangles must be split.
TEST(RerenderRaster, WideLensNeedsSplitTriangles) {
  CameraModel camera =
      CameraModel::Read(testing::TestDataDir() / "lenses" / "wide-4000x2200.opencv8.cameramodel")
          .Scaled(0.1);
  camera.set_cam_from_world(Pose::Identity());
  // The plane z = 2.2 + 0.6 x (camera coordinates): depth along a ray of direction d.
  auto plane_depth = [](const Eigen::Vector3d& d) { return 2.2 * d.z() / (d.z() - 0.6 * d.x()); };
  Mesh wall;
  for (const auto& [u, v] :
       {std::pair{0.1, 0.1}, std::pair{0.9, 0.1}, std::pair{0.9, 0.9}, std::pair{0.1, 0.9}}) {
    const Eigen::Vector3d ray =
        camera.Unproject(Eigen::Vector2d(u * camera.width(), v * camera.height()));
    wall.vertices.push_back((ray * (plane_depth(ray) / ray.z())).cast<float>());
  }
  wall.faces = {{0, 1, 2}, {0, 2, 3}};
  auto worst_depth_error = [&](const GBuffer& buffers) {
    double worst = 0;
    for (int y = 0; y < buffers.depth.rows; ++y) {
      for (int x = 0; x < buffers.depth.cols; ++x) {
        const float z = buffers.depth.at<float>(y, x);
        if (std::isfinite(z))
          worst =
              std::max(worst, std::abs(z - plane_depth(camera.Unproject(Eigen::Vector2d(x, y)))));
      }
    }
    return worst;
  };
  const GBuffer split = RasteriseMesh(wall, camera);
  MeshRasterOptions whole;
  whole.max_subdivisions = 0;
  const GBuffer unsplit = RasteriseMesh(wall, camera, whole);
  EXPECT_EQ(split.triangles_split, 2);
  EXPECT_GT(split.triangles_drawn, 100);
  EXPECT_EQ(unsplit.triangles_drawn, 2);
  std::cout << "wide lens wall: worst depth error " << worst_depth_error(split) * 1e3
            << " mm split, " << worst_depth_error(unsplit) * 1e3 << " mm unsplit\n";
  EXPECT_LT(worst_depth_error(split), 0.01);
  EXPECT_GT(worst_depth_error(unsplit), 3 * worst_depth_error(split));
}

TEST(RerenderRaster, CameraLookingAwaySeesNothing) {
  const Sphere sphere;
  const Mesh mesh = testing::SphereMesh(sphere, 16, 32);
  const CameraModel camera =
      CameraModel::Pinhole(80, 96, 64,
                           CamFromWorldLookAt(sphere.centre + Eigen::Vector3d(2, 0, 0),
                                              sphere.centre + Eigen::Vector3d(4, 0, 0)));
  const GBuffer buffers = RasteriseMesh(mesh, camera);
  EXPECT_EQ(buffers.triangles_drawn, 0);
  EXPECT_EQ(cv::countNonZero(buffers.mask), 0);
  EXPECT_EQ(cv::countNonZero(buffers.depth == buffers.depth), 0);  // all NaN
  const RenderedView view = RerenderNetwork(UNetConfig{.width = 8, .depth = 3}, 1).Apply(buffers);
  ASSERT_EQ(view.alpha.size(), cv::Size(camera.width(), camera.height()));
  double lo, hi;
  cv::minMaxLoc(view.alpha, &lo, &hi);
  EXPECT_LT(hi, 0.01);
  EXPECT_EQ(cv::checkRange(view.color), true);
}

// A plane's edge crossing pixel column 10 at x = 10.1: one sample at the pixel centre calls the
// column covered; 2x2 or 4x4 samples cover half of it, and the buffers average what they hit.
TEST(RerenderRaster, SupersamplingGivesTheCoveredFractionOfEdgePixels) {
  const CameraModel camera = CameraModel::Pinhole(40, 32, 16, Pose::Identity());
  // Pixel (u, v) sees x = (u - 15.5) z / 40, y = (v - 7.5) z / 40; the quad spans u from -0.4
  // to 10.1 and v from -0.4 to 15.4, its corners inside the image.
  const float z = 2, left = (-0.4f - 15.5f) * z / 40, right = (10.1f - 15.5f) * z / 40;
  const float top = (-0.4f - 7.5f) * z / 40, bottom = (15.4f - 7.5f) * z / 40;
  Mesh quad;
  quad.vertices = {{left, top, z}, {right, top, z}, {right, bottom, z}, {left, bottom, z}};
  quad.faces = {{0, 2, 1}, {0, 3, 2}};
  quad.colors.assign(4, Eigen::Matrix<uint8_t, 3, 1>(200, 100, 50));
  const cv::Mat white(camera.height(), camera.width(), CV_32FC3, cv::Scalar::all(1));
  for (int s : {1, 2, 4}) {
    SCOPED_TRACE(s);
    const GBuffer b =
        RasteriseMesh(quad, camera, MeshRasterOptions{.supersample = s, .threads = 1});
    ASSERT_EQ(b.mask.size(), cv::Size(32, 16));
    for (int y = 0; y < 16; ++y) {
      EXPECT_EQ(b.mask.at<uint8_t>(y, 9), 255);
      EXPECT_EQ(b.mask.at<uint8_t>(y, 10), s == 1 ? 255 : 128);
      EXPECT_EQ(b.mask.at<uint8_t>(y, 11), 0);
      EXPECT_NEAR(b.depth.at<float>(y, 10), z, 1e-4);
      const cv::Vec3f c = b.color.at<cv::Vec3f>(y, 10);  // BGR of the covered samples
      EXPECT_NEAR(c[0], 50 / 255.0, 1e-5);
      EXPECT_NEAR(c[2], 200 / 255.0, 1e-5);
      EXPECT_NEAR(b.normal.at<cv::Vec3f>(y, 10)[2], -1, 1e-4);  // facing the camera
    }
    EXPECT_TRUE(std::isnan(b.depth.at<float>(0, 11)));
    // The raw render blends the surface over the background by that fraction.
    const cv::Mat raw = CompositeRawRender(b, white);
    const double a = s == 1 ? 1.0 : 128 / 255.0;
    EXPECT_NEAR(raw.at<cv::Vec3f>(5, 10)[0], a * 50 / 255.0 + (1 - a), 1e-5);
    EXPECT_NEAR(raw.at<cv::Vec3f>(5, 11)[0], 1, 1e-6);
  }
  MeshRasterOptions bad;
  bad.supersample = 5;
  EXPECT_THROW(RasteriseMesh(quad, camera, bad), Error);
}

TEST(RerenderRaster, PointsWithoutFacesAreSplatted) {
  const Sphere sphere;
  Mesh points = testing::SphereMesh(sphere, 32, 64);
  points.faces.clear();
  const CameraModel camera = testing::RingCameras(1, sphere, 1.4, 120, 90, false)[0];
  const GBuffer buffers = RasteriseMesh(points, camera);
  cv::Mat mask;
  testing::RenderSphere(camera, sphere, nullptr, &mask);
  EXPECT_GT(cv::countNonZero(buffers.mask & mask), 0.9 * cv::countNonZero(mask));
  // 1.5 px splats spill about that far past the rim.
  EXPECT_LT(cv::countNonZero(buffers.mask & ~mask), 0.2 * cv::countNonZero(mask));
}

TEST(RerenderRaster, RejectsBadInput) {
  Mesh mesh;
  mesh.vertices = {{0, 0, 1}, {1, 0, 1}, {0, 1, 1}};
  mesh.faces = {{0, 1, 3}};
  const CameraModel camera = CameraModel::Pinhole(50, 64, 48);
  EXPECT_THROW(RasteriseMesh(mesh, camera), Error);
  mesh.faces = {{0, 1, 2}};
  MeshRasterOptions bad;
  bad.max_edge_px = 0;
  EXPECT_THROW(RasteriseMesh(mesh, camera, bad), Error);
}

// The untrained network returns the raw render: colour where covered, no alpha elsewhere.
TEST(RerenderNet, StartsAsTheRawRender) {
  const Sphere sphere;
  Mesh mesh = testing::SphereMesh(sphere, 32, 64);
  for (size_t i = 0; i < mesh.vertices.size(); ++i)
    mesh.colors.push_back({static_cast<uint8_t>(i % 200 + 20), 90, 160});
  const CameraModel camera = testing::RingCameras(1, sphere, 1.4, 100, 70, false)[0];
  const GBuffer buffers = RasteriseMesh(mesh, camera);
  const RerenderNetwork network(UNetConfig{.width = 8, .depth = 3}, 3);
  const RenderedView view = network.Apply(buffers);
  const cv::Mat raw = CompositeRawRender(buffers, {});
  cv::Mat alpha3;
  cv::cvtColor(view.alpha, alpha3, cv::COLOR_GRAY2BGR);
  cv::Mat straight = view.color / cv::max(alpha3, 1e-6);
  double worst = 0;
  for (int y = 0; y < raw.rows; ++y) {
    for (int x = 0; x < raw.cols; ++x) {
      if (!buffers.mask.at<uint8_t>(y, x)) {
        EXPECT_LT(view.alpha.at<float>(y, x), 0.01f);
        continue;
      }
      EXPECT_GT(view.alpha.at<float>(y, x), 0.99f);
      const cv::Vec3f d = straight.at<cv::Vec3f>(y, x) - raw.at<cv::Vec3f>(y, x);
      worst =
          std::max({worst, std::abs<double>(d[0]), std::abs<double>(d[1]), std::abs<double>(d[2])});
    }
  }
  EXPECT_LT(worst, 0.021);  // colours are clamped to [0.02, 0.98] before the logit
}

// Supersampled, edge pixels are partly covered: the untrained network's alpha is that fraction,
// so composited over a background it gives the raw render there too.
TEST(RerenderNet, StartsAsTheSupersampledRawRenderAtPartlyCoveredEdges) {
  const Sphere sphere;
  Mesh mesh = testing::SphereMesh(sphere, 32, 64);
  mesh.colors.assign(mesh.vertices.size(), Eigen::Matrix<uint8_t, 3, 1>(200, 90, 40));
  const CameraModel camera = testing::RingCameras(1, sphere, 1.4, 100, 70, false)[0];
  const GBuffer buffers =
      RasteriseMesh(mesh, camera, MeshRasterOptions{.supersample = 4, .threads = 1});
  const RenderedView view =
      RerenderNetwork(UNetConfig{.width = 8, .depth = 3}, 3).Apply(buffers, 1);
  const cv::Mat background(buffers.color.size(), CV_32FC3, cv::Scalar(0.1, 0.8, 0.5));
  const cv::Mat raw = CompositeRawRender(buffers, background);
  int partial = 0;
  double worst = 0;
  for (int y = 0; y < raw.rows; ++y) {
    for (int x = 0; x < raw.cols; ++x) {
      const uint8_t m = buffers.mask.at<uint8_t>(y, x);
      const float a = view.alpha.at<float>(y, x);
      if (m > 0 && m < 255) ++partial;
      EXPECT_NEAR(a, std::clamp(m / 255.0, 0.0025, 0.9975), 1e-3) << x << "," << y;
      const cv::Vec3f composited =
          view.color.at<cv::Vec3f>(y, x) + (1 - a) * background.at<cv::Vec3f>(y, x);
      const cv::Vec3f d = composited - raw.at<cv::Vec3f>(y, x);
      worst =
          std::max({worst, std::abs<double>(d[0]), std::abs<double>(d[1]), std::abs<double>(d[2])});
    }
  }
  EXPECT_GT(partial, 50);   // the sphere's outline
  EXPECT_LT(worst, 0.021);  // the colour clamp, and alpha's +-0.0025 against a far background
}

// Holes in the coverage and NaN where depth or colour should be never reach the output.
TEST(RerenderNet, HolesAndNanBuffersGiveFiniteOutput) {
  const Sphere sphere;
  const CameraModel camera = testing::RingCameras(1, sphere, 1.4, 96, 64, false)[0];
  GBuffer buffers = RasteriseMesh(testing::SphereMesh(sphere, 24, 48), camera);
  const float nan = std::numeric_limits<float>::quiet_NaN();
  buffers.mask(cv::Rect(40, 20, 10, 10)).setTo(0);
  buffers.depth(cv::Rect(40, 20, 10, 10)).setTo(nan);
  buffers.depth(cv::Rect(30, 30, 6, 6)).setTo(nan);  // covered, but no depth
  buffers.color(cv::Rect(50, 30, 4, 4)).setTo(cv::Scalar::all(nan));
  buffers.normal(cv::Rect(50, 30, 4, 4))
      .setTo(cv::Scalar::all(std::numeric_limits<float>::infinity()));
  const RenderedView view = RerenderNetwork(UNetConfig{.width = 8, .depth = 2}, 5).Apply(buffers);
  EXPECT_TRUE(cv::checkRange(view.color));
  EXPECT_TRUE(cv::checkRange(view.alpha));
  EXPECT_LT(view.alpha.at<float>(25, 45), 0.01f);  // the hole is empty
  EXPECT_LT(view.alpha.at<float>(33, 33), 0.01f);  // covered without depth counts as empty
}

TEST(RerenderOptions, ChecksExplainBadValues) {
  RerenderOptions options;
  options.take.ground_truth_cameras = true;
  options.net.depth = 9;
  EXPECT_THROW(options.Check(), Error);
  options = {};
  options.subject_weight = 0.5;
  EXPECT_THROW(options.Check(), Error);
  options = {};
  options.image_width = 8;
  EXPECT_THROW(options.Check(), Error);
  options = {};
  options.crop_px = 8;
  EXPECT_THROW(options.Check(), Error);
  options = {};
  options.alpha_weight = -1;
  EXPECT_THROW(options.Check(), Error);
  options = {};
  options.witness_folds = 0;
  EXPECT_THROW(options.Check(), Error);
  options = {};
  options.fold_witness = {{}};
  EXPECT_THROW(options.Check(), Error);
  options = {};
  options.witness_folds = 1;
  options.fold_recon_dirs = {"a"};  // one further reconstruction for no further fold
  EXPECT_THROW(options.Check(), Error);
  options = {};
  options.validation_witnesses = -2;
  EXPECT_THROW(options.Check(), Error);
  options = {};
  options.supersample = 0;
  EXPECT_THROW(options.Check(), Error);
  options = {};
  options.witness_scales = {0.5};  // the training width itself is where views are scored
  EXPECT_THROW(options.Check(), Error);
  options = {};
  options.witness_scales = {1, 0.1};
  EXPECT_THROW(options.Check(), Error);
  options = {};
  options.witness_scales = {1, 0.5};
  EXPECT_NO_THROW(options.Check());
  EXPECT_NO_THROW(RerenderOptions{}.Check());
}

// End to end: a 3-frame simulated take, the reconstruction from the other cameras, a short
// training, then playback through the model.
TEST(RerenderCli, TrainsAndRendersATinyTake) {
  testing::TempDir dir("rerender-cli");
  const auto take = dir / "take";
  auto sim = testing::RunCli(
      "sim --rig studio8 --frames 4 --clean-plate 1 --size 128 --no-noise --out " + take.string());
  ASSERT_EQ(sim.exit_code, 0) << sim.output;
  const auto model = dir / "model";
  auto too_many =
      testing::RunCli("train rerender " + take.string() + " --ground-truth-cameras --out " +
                      model.string() + " --witness 6");
  EXPECT_NE(too_many.exit_code, 0);
  EXPECT_NE(too_many.output.find("for the reconstruction"), std::string::npos) << too_many.output;
  auto bad_bounds =
      testing::RunCli("train rerender " + take.string() + " --ground-truth-cameras --out " +
                      model.string() + " --recon-bounds 1,2,3");
  EXPECT_NE(bad_bounds.exit_code, 0);
  EXPECT_NE(bad_bounds.output.find("--recon-bounds must be six numbers"), std::string::npos)
      << bad_bounds.output;
  auto bad_method =
      testing::RunCli("train rerender " + take.string() + " --ground-truth-cameras --out " +
                      model.string() + " --recon-method sculpt");
  EXPECT_NE(bad_method.exit_code, 0);
  EXPECT_NE(bad_method.output.find("sculpt"), std::string::npos) << bad_method.output;

  auto train = testing::RunCli(
      "train rerender " + take.string() + " --ground-truth-cameras --out " + model.string() +
      " --witness-folds 1 --iterations 60 --width 64 --crop 0 --unet-width 8 "
      "--unet-depth 3 --recon-voxel 0.012 --eval-every 1000 --threads 1");
  ASSERT_EQ(train.exit_code, 0) << train.output;
  std::ifstream file(model / "report.json");
  const nlohmann::json report = nlohmann::json::parse(file);
  const auto& m = report.at("metrics");
  EXPECT_EQ(m.at("iterations").get<int>(), 60);
  EXPECT_TRUE(std::isfinite(m.at("last_loss").get<double>()));
  EXPECT_GT(m.at("raw_render_psnr_db").get<double>(), 10);
  // What rerendering promises: the network repairs the raw render on a camera it never trained
  // on (near the subject, where both are scored; a run that does not is DEGENERATE).
  EXPECT_EQ(report.at("summary").at("termination"), "NO_CONVERGENCE");
  EXPECT_GT(m.at("heldout_psnr_subject_db").get<double>(),
            m.at("raw_render_psnr_subject_db").get<double>());
  EXPECT_EQ(report.at("plan").at("witness").size(), 2u);
  EXPECT_EQ(report.at("plan").at("temporal_term"), "on");
  // The take has a clean plate: alpha learns from the witnesses' silhouettes, and the
  // background alone is scored beside the raw render.
  EXPECT_EQ(report.at("plan").at("alpha_target"), "the witnesses' silhouettes");
  EXPECT_GT(m.at("background_psnr_db").get<double>(), 10);
  EXPECT_GT(m.at("background_psnr_subject_db").get<double>(), 5);

  // A reconstruction that draws nothing: the held-out cameras see no more of the subject than
  // the background alone, which training reports as DEGENERATE (exit status 1), not as a model.
  const auto empty = dir / "empty-recon";
  std::filesystem::create_directories(empty);
  for (const auto& entry : std::filesystem::directory_iterator(model / "recon")) {
    if (entry.path().extension() == ".ply") {
      WritePly(empty / entry.path().filename(), Mesh{});
    } else if (entry.is_regular_file()) {
      std::filesystem::copy_file(entry.path(), empty / entry.path().filename());
    }
  }
  const auto nothing = dir / "nothing";
  auto degenerate =
      testing::RunCli("train rerender " + take.string() + " --ground-truth-cameras --out " +
                      nothing.string() + " --recon " + empty.string() +
                      " --witness-folds 1 --iterations 10 --width 64 --crop 0 "
                      "--unet-width 8 --unet-depth 3 --eval-every 1000 --threads 1");
  EXPECT_NE(degenerate.exit_code, 0);
  EXPECT_NE(degenerate.output.find("DEGENERATE"), std::string::npos) << degenerate.output;
  EXPECT_NE(degenerate.output.find("no more of the subject than the background alone"),
            std::string::npos)
      << degenerate.output;
  EXPECT_TRUE(std::filesystem::exists(nothing / "report.json")) << degenerate.output;

  // A step far too large scrambles the network: finite, but the held-out camera scores below
  // the raw render it started from, which training reports as DEGENERATE, not as a model.
  const auto scrambled = dir / "scrambled";
  auto worse =
      testing::RunCli("train rerender " + take.string() + " --ground-truth-cameras --out " +
                      scrambled.string() + " --recon " + (model / "recon").string() +
                      " --witness-folds 1 --iterations 1 --lr 0.3 --width 64 --crop 0 "
                      "--unet-width 8 --unet-depth 3 --eval-every 1000 --threads 1");
  EXPECT_EQ(worse.exit_code, 1) << worse.output;
  EXPECT_NE(worse.output.find("DEGENERATE: the network's output is no better than the raw render"),
            std::string::npos)
      << worse.output;
  const nlohmann::json worse_report =
      nlohmann::json::parse(std::ifstream(scrambled / "report.json"));
  EXPECT_LT(worse_report.at("metrics").at("heldout_psnr_subject_db").get<double>(),
            worse_report.at("metrics").at("raw_render_psnr_subject_db").get<double>());

  const auto frames = dir / "frames";
  auto render = testing::RunCli("render " + take.string() + " --model " + model.string() +
                                " --views 3 --size 64 --no-exr --out " + frames.string());
  ASSERT_EQ(render.exit_code, 0) << render.output;
  EXPECT_TRUE(std::filesystem::exists(frames / "000002.png")) << render.output;
  const cv::Mat first = ReadImage(frames / "000000.png");
  EXPECT_EQ(first.channels(), 4);
  EXPECT_EQ(first.cols, 64);
  EXPECT_EQ(first.rows, 64);
}

// Further witness folds: every fold's witnesses are seen through a reconstruction built without
// them (and without the held-out camera), and the network trains on all of them.
// A run of a step or two, made to check the plan: it trains and ends with its report, either
// short of convergence or DEGENERATE because two steps have not yet made a network better than
// the raw render (or, through folds that never saw the held-out camera, than its background).
void ExpectPlanOnlyEnding(const std::filesystem::path& model, const testing::CommandResult& run) {
  ASSERT_TRUE(std::filesystem::exists(model / "report.json")) << run.output;
  const nlohmann::json summary =
      nlohmann::json::parse(std::ifstream(model / "report.json")).at("summary");
  const std::string termination = summary.at("termination");
  if (termination == "DEGENERATE") {
    EXPECT_EQ(run.exit_code, 1) << run.output;
    EXPECT_NE(run.output.find("training ended DEGENERATE: the network's output"), std::string::npos)
        << run.output;
  } else {
    EXPECT_EQ(termination, "NO_CONVERGENCE") << run.output;
    EXPECT_EQ(run.exit_code, 0) << run.output;
  }
}

TEST(RerenderCli, WitnessFoldsTrainThroughReconstructionsThatNeverSawThem) {
  testing::TempDir dir("rerender-folds");
  const auto take = dir / "take";
  auto sim = testing::RunCli(
      "sim --rig studio8 --frames 3 --clean-plate 1 --size 96 --no-noise --out " + take.string());
  ASSERT_EQ(sim.exit_code, 0) << sim.output;
  const auto model = dir / "model";
  auto no_trainer = testing::RunCli(
      "train rerender " + take.string() + " --ground-truth-cameras --out " + model.string() +
      " --witness 1 --witness-folds 1 --validation-witnesses 1 --iterations 1");
  EXPECT_NE(no_trainer.exit_code, 0);
  EXPECT_NE(no_trainer.output.find("leave no witness to train on"), std::string::npos)
      << no_trainer.output;
  auto train = testing::RunCli(
      "train rerender " + take.string() + " --ground-truth-cameras --out " + model.string() +
      " --heldout 1 --witness-folds 3 --validation-witnesses 1 --supersample 3 "
      "--iterations 60 --lr 0.003 --width 48 --crop 0 --unet-width 8 --unet-depth 3"
      " --recon-method hull --recon-voxel 0.016 --eval-every 1000 --threads 1");
  ASSERT_EQ(train.exit_code, 0) << train.output;
  const nlohmann::json report = nlohmann::json::parse(std::ifstream(model / "report.json"));
  const auto& plan = report.at("plan");
  ASSERT_TRUE(plan.contains("folds")) << plan.dump();
  const auto& folds = plan.at("folds");
  ASSERT_EQ(folds.size(),
            3u);  // cam0 held out; {cam1, cam5}, then two of cam3, cam4, cam7, then the last
  const std::string heldout = plan.at("heldout").at(0);
  std::set<std::string> all_witnesses;
  size_t witnesses = 0;
  for (size_t k = 0; k < folds.size(); ++k) {
    const auto recon = model / (k == 0 ? std::string("recon") : "recon-" + std::to_string(k));
    ASSERT_TRUE(std::filesystem::exists(recon / "report.json")) << recon;
    const nlohmann::json built = nlohmann::json::parse(std::ifstream(recon / "report.json"));
    std::set<std::string> used;
    for (const auto& name : built.at("plan").at("color_sensors"))
      used.insert(name.get<std::string>());
    EXPECT_EQ(used.count(heldout), 0u) << "fold " << k;
    EXPECT_GE(used.size(), 2u);
    for (const auto& w : folds[k].at("witness")) {
      EXPECT_EQ(used.count(w.get<std::string>()), 0u)
          << "fold " << k << " reconstruction used its witness " << w;
      EXPECT_NE(w.get<std::string>(), heldout);
      all_witnesses.insert(w.get<std::string>());
      ++witnesses;
    }
  }
  // No camera is a witness twice, and every witness of every fold is trained on.
  EXPECT_EQ(all_witnesses.size(), witnesses);
  EXPECT_EQ(plan.at("witness").size(), witnesses);
  EXPECT_GT(witnesses, 4u);
  EXPECT_EQ(report.at("metrics").at("iterations").get<int>(), 60);
  // Early stopping: the last fold's witness is scored, not trained on, and the weights kept are
  // those of an evaluation after training (iteration 0 is the raw render itself: a run that
  // keeps it is DEGENERATE). The hulls of five or six cameras keep phantom volume that the
  // network learns to remove, so it scores the validation witness and the held-out camera
  // above the raw render.
  ASSERT_EQ(plan.at("validation").size(), 1u);
  EXPECT_EQ(plan.at("validation").at(0), folds.back().at("witness").back());
  const auto& metrics = report.at("metrics");
  EXPECT_EQ(metrics.at("kept_iteration").get<int>(), 60);
  EXPECT_GT(metrics.at("validation_psnr_db").get<double>(),
            metrics.at("validation_raw_psnr_db").get<double>());
  EXPECT_GT(metrics.at("heldout_psnr_subject_db").get<double>(),
            metrics.at("raw_render_psnr_subject_db").get<double>());
  // More folds than cameras to spare: as many as there are, and the plan says so.
  const auto fewer = dir / "fewer";
  auto again = testing::RunCli(
      "train rerender " + take.string() + " --ground-truth-cameras --out " + fewer.string() +
      " --heldout 1 --witness-folds 5 --recon " + (model / "recon").string() +
      " --iterations 2 --width 48 --crop 0 --unet-width 8 --unet-depth 3"
      " --recon-voxel 0.016 --eval-every 1000 --threads 1");
  // Two steps rarely lift the network above the raw render: this run checks the plan only.
  ExpectPlanOnlyEnding(fewer, again);
  const nlohmann::json fewer_report = nlohmann::json::parse(std::ifstream(fewer / "report.json"));
  EXPECT_EQ(fewer_report.at("plan").at("folds").size(), 3u);
  EXPECT_NE(
      fewer_report.at("plan").at("witness_folds").get<std::string>().find("5 asked, 3 possible"),
      std::string::npos)
      << fewer_report.at("plan").dump();
  // By default a fifth of the witnesses validate, at least one once there are three.
  const size_t fewer_witnesses = fewer_report.at("plan").at("witness").size();
  ASSERT_GE(fewer_witnesses, 3u);
  EXPECT_EQ(fewer_report.at("plan").at("validation").size(),
            std::max<size_t>(1, fewer_witnesses / 5))
      << fewer_report.at("plan").dump();
  // Playback uses the first fold's reconstruction.
  const nlohmann::json model_json = nlohmann::json::parse(std::ifstream(model / "model.json"));
  EXPECT_EQ(model_json.at("meshes").at(0).get<std::string>().rfind("recon/", 0), 0u)
      << model_json.at("meshes").dump();
  // The model keeps its raster sampling, and playback rasterises alike.
  EXPECT_EQ(model_json.at("supersample").get<int>(), 3);
  EXPECT_EQ(report.at("plan").at("raster_samples").get<std::string>().rfind("3x3 per pixel", 0), 0u)
      << report.at("plan").dump();
  const auto frames = dir / "frames";
  auto render = testing::RunCli("render " + take.string() + " --model " + model.string() +
                                " --views 1 --size 48 --no-exr --out " + frames.string());
  ASSERT_EQ(render.exit_code, 0) << render.output;
  EXPECT_TRUE(std::filesystem::exists(frames / "000000.png")) << render.output;

  // Folds named on the command line, their reconstructions reused, and the witnesses trained
  // at a second scale too: the last fold's witness validates at the training width only.
  auto names = [](const nlohmann::json& list) {
    std::string joined;
    for (const auto& n : list) joined += (joined.empty() ? "" : ",") + n.get<std::string>();
    return joined;
  };
  const auto named = dir / "named";
  // The first fold's reconstruction saw the second fold's witnesses: refused for that fold.
  auto leaked = testing::RunCli(
      "train rerender " + take.string() + " --ground-truth-cameras --out " + named.string() +
      " --heldout-names " + heldout + " --witness-names " + names(folds[0].at("witness")) +
      " --fold-witnesses " + names(folds[1].at("witness")) + " --recon " +
      (model / "recon").string() + " --fold-recon " + (model / "recon").string() +
      " --iterations 1 --width 48 --threads 1");
  EXPECT_NE(leaked.exit_code, 0);
  EXPECT_NE(leaked.output.find("was built with camera"), std::string::npos) << leaked.output;
  auto by_name = testing::RunCli(
      "train rerender " + take.string() + " --ground-truth-cameras --out " + named.string() +
      " --heldout-names " + heldout + " --witness-names " + names(folds[0].at("witness")) +
      " --fold-witnesses " + names(folds[1].at("witness")) + " --recon " +
      (model / "recon").string() + " --fold-recon " + (model / "recon-1").string() +
      " --witness-scales 1,0.5 --validation-witnesses 1"
      " --iterations 2 --width 48 --crop 0 --unet-width 8 --unet-depth 3 --eval-every 1000 "
      "--threads 1");
  ExpectPlanOnlyEnding(named, by_name);
  const nlohmann::json named_plan =
      nlohmann::json::parse(std::ifstream(named / "report.json")).at("plan");
  ASSERT_EQ(named_plan.at("folds").size(), 2u) << named_plan.dump();
  EXPECT_EQ(named_plan.at("folds").at(1).at("witness"), folds[1].at("witness"));
  EXPECT_EQ(named_plan.at("validation").at(0), folds[1].at("witness").back());
  EXPECT_EQ(named_plan.at("witness_scales"), nlohmann::json({1.0, 0.5}));
  const size_t named_witnesses = named_plan.at("witness").size();
  EXPECT_EQ(named_plan.at("trained_views").get<size_t>(), 2 * (named_witnesses - 1))
      << named_plan.dump();
}

}  // namespace
}  // namespace holocap
