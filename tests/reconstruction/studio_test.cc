// The studio8 simulated rig end to end: depth fusion, hull and stereo against the true
// meshes, the CLI's outputs, and bad takes.
#include <gtest/gtest.h>

#include <unistd.h>

#include <fstream>
#include <nlohmann/json.hpp>
#include <optional>

#include "core/error.h"
#include "core/mesh.h"
#include "core/take.h"
#include "reconstruction/reconstruction.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;
using testing::RunCli;
using testing::RunShell;
using testing::TempDir;

// A studio8 take (a clean plate, then the walking subject), simulated once and shared by the
// tests of this suite (ctest runs each in its own process).
const fs::path& StudioTake() {
  static const fs::path take = [] {
    fs::path dir = fs::temp_directory_path() / "holocap-recon-test-studio8-v1";
    if (fs::exists(dir / "take.json") && fs::exists(dir / "gt" / "meshes" / "000001.ply"))
      return dir;
    fs::path staging = dir.string() + ".staging-" + std::to_string(::getpid());
    auto result =
        RunCli("sim --rig studio8 --frames 2 --clean-plate 1 --seed 3 --overwrite --out '" +
               staging.string() + "'");
    if (result.exit_code != 0) throw Error("cannot simulate the studio take: " + result.output);
    std::error_code ignored;
    fs::rename(staging, dir, ignored);
    if (ignored) fs::remove_all(staging, ignored);  // another process won the race
    return dir;
  }();
  return take;
}

nlohmann::json RunPipeline(ReconstructionMethod method, double voxel, const fs::path& out) {
  ReconstructionOptions options;
  options.method = method;
  options.voxel_m = voxel;
  options.write_glb = false;
  options.texture.atlas = false;
  options.sweep_voxels_m.clear();
  Report report("reconstruct");
  ReconstructionSummary summary =
      ReconstructTake(StudioTake(), testing::TrueCameras(), out, options, &report);
  EXPECT_EQ(summary.termination, Termination::kSuccess) << summary.message;
  EXPECT_EQ(summary.plan["cameras"], "gt/cameras (asked for)")
      << "the test asks for the simulation's true cameras";
  return report.json();
}

TEST(StudioTest, TsdfFromTheDepthSensorsIsWithinFourMillimetres) {
  TempDir out;
  nlohmann::json report = RunPipeline(ReconstructionMethod::kTsdf, 0.004, out.path());
  ASSERT_TRUE(report["metrics"].contains("gt"));
  const auto& gt = report["metrics"]["gt"];
  const auto& frame = report["metrics"]["frames"][0]["metrics"];
  std::printf("tsdf 4 mm: %s\n", frame.dump().c_str());
  // Symmetric Chamfer against the subject's whole surface, also what neither depth sensor saw
  // (there the colour cameras' hull, carved by the sensors' free space, stands in). The
  // subject is a union of overlapping body parts: completeness is measured on its outer
  // surface, not on the faces buried inside other parts, which nothing can see.
  EXPECT_LE(gt["chamfer_mm"].get<double>(), 4.0);
  EXPECT_LE(gt["chamfer_with_buried_faces_mm"].get<double>(), 5.5);
  // The hull stands 5-10 mm outside the body where it cannot see into concavities.
  EXPECT_LE(gt["accuracy_mm"].get<double>(), 5.0);
  // On the surface the two depth sensors saw, their measurements decide.
  EXPECT_LE(frame["gt"]["observed"]["chamfer_mm"].get<double>(), 4.0);
  EXPECT_EQ(report["plan"]["skipped"], "stereo");
  EXPECT_GT(frame["completion"]["voxels_filled"].get<int64_t>(), 0);
  EXPECT_TRUE(frame["tsdf"].contains("valid_pixels")) << "the depth sensors were fused";
  EXPECT_FALSE(frame.contains("mvs")) << "no stereo ran";

  // Without completion only what the sensors saw is meshed, accurately; the plan skips the hull.
  ReconstructionOptions options;
  options.method = ReconstructionMethod::kTsdf;
  options.voxel_m = 0.004;
  options.write_glb = false;
  options.texture.atlas = false;
  options.sweep_voxels_m.clear();
  options.tsdf_hull_completion = false;
  TempDir plain_out;
  TakeSelection first_set = testing::TrueCameras();
  first_set.last_frame = 1;
  ReconstructionSummary plain =
      ReconstructTake(StudioTake(), first_set, plain_out.path(), options, nullptr);
  const auto& plain_gt = plain.frames[0].metrics["gt"];
  std::printf("tsdf 4 mm without completion: %s\n", plain_gt.dump().c_str());
  EXPECT_LE(plain_gt["accuracy_mm"].get<double>(), 3.0);
  EXPECT_GT(plain_gt["completeness_mm"].get<double>(), gt["completeness_mm"].get<double>() + 2.0);
  EXPECT_EQ(plain.plan["skipped"], "silhouettes, hull, stereo");
  EXPECT_FALSE(plain.frames[0].metrics.contains("hull")) << "no hull was computed";
}

TEST(StudioTest, MvsFromColourAloneIsWithinEightMillimetres) {
  TempDir out;
  nlohmann::json report = RunPipeline(ReconstructionMethod::kMvs, 0.004, out.path());
  const auto& gt = report["metrics"]["gt"];
  std::printf("mvs 4 mm: %s\n", report["metrics"]["frames"][0]["metrics"].dump().c_str());
  EXPECT_LE(gt["chamfer_mm"].get<double>(), 8.0);
  EXPECT_LE(gt["accuracy_mm"].get<double>(), 6.0);
  EXPECT_FALSE(report["metrics"]["frames"][0]["metrics"].contains("tsdf") &&
               report["metrics"]["frames"][0]["metrics"]["tsdf"].contains("valid_pixels"))
      << "no depth sensor was fused";
}

TEST(StudioTest, HullContainsTheTrueSurface) {
  const Take take = Take::Open(StudioTake());
  std::vector<View> views;
  for (const StreamInfo& stream : take.streams()) {
    if (stream.role != SensorRole::kColor) continue;
    View view{stream.name, take.Camera(stream.name, true), take.ReadFrame(1, stream.name), {}};
    view.mask = ExtractSilhouette(view.image, take.ReadFrame(0, stream.name), SilhouetteOptions{});
    views.push_back(view);
  }
  const Mesh truth = ReadPly(StudioTake() / "gt" / "meshes" / "000001.ply");
  const auto points = truth.SampleSurface(20000, 5);
  double fraction[2];
  for (int tolerated = 0; tolerated < 2; ++tolerated) {
    HullOptions options;
    options.voxel_m = 0.008;
    options.tolerated_bad_views = tolerated;
    HullSummary summary;
    VisualHull hull = ComputeVisualHull(views, options, &summary);
    ASSERT_EQ(summary.termination, Termination::kSuccess) << summary.message;
    int64_t inside = 0;
    for (const auto& p : points) inside += hull.Contains(p, 0.5 * options.voxel_m);
    fraction[tolerated] = static_cast<double>(inside) / points.size();
    std::printf("hull (%s): %.4f of true surface points within half a voxel; %.1f litres\n",
                tolerated ? "conservative, one bad view tolerated" : "strict", fraction[tolerated],
                summary.volume_m3 * 1e3);
  }
  // The strict hull carves whatever any one silhouette misses; hysteresis keeps skin and hair
  // that are close to the wall's colour (without it: 95.1% strict, 98.6% conservative).
  EXPECT_GE(fraction[0], 0.99);
  EXPECT_GE(fraction[1], 0.995);
  // Masks from background subtraction against the true silhouettes: few true pixels lost.
  for (const View& view : views) {
    cv::Mat truth_mask = ReadImage(StudioTake() / "gt" / "masks" / view.name / "000001.png");
    EXPECT_GT(MaskIoU(view.mask, truth_mask), 0.9) << view.name;
    const double lost = cv::countNonZero(truth_mask & ~view.mask) /
                        static_cast<double>(cv::countNonZero(truth_mask));
    EXPECT_LT(lost, 0.02) << view.name;  // 6% in cam6 without hysteresis
  }
}

TEST(StudioTest, CliWritesMeshesThatOpen3dReads) {
  TempDir out;
  auto result = RunCli("reconstruct '" + StudioTake().string() +
                       "' --ground-truth-cameras --frames 0:1 --voxel 8mm --no-sweep --out '" +
                       out.path().string() + "'");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  EXPECT_NE(result.output.find("gt/ (not calibrated)"), std::string::npos) << result.output;
  ASSERT_TRUE(fs::exists(out / "000001.ply"));
  ASSERT_TRUE(fs::exists(out / "000001.glb"));
  nlohmann::json report = nlohmann::json::parse(std::ifstream(out / "report.json"));
  EXPECT_EQ(report["metrics"]["timing"]["per_frame_s"].size(), 1u);
  // The true cameras and an 8 mm volume: the surface lies within half a voxel of the truth on
  // average (2.8 mm here; 3.1 mm even at 16 mm), and most of it within 5 mm (F-score 0.87). A
  // mesh written a few millimetres off (another world, a half-voxel shift) fails both.
  EXPECT_LE(report["metrics"]["gt"]["chamfer_mm"].get<double>(), 4.0);
  EXPECT_GT(report["metrics"]["gt"]["fscore_5mm"].get<double>(), 0.6);
  EXPECT_EQ(report["plan"]["method"], "tsdf");
  Mesh ply = ReadPly(out / "000001.ply");
  auto open3d =
      RunShell("/usr/bin/python3 -c \"import open3d as o3d; m = o3d.io.read_triangle_mesh('" +
               (out / "000001.glb").string() +
               "', enable_post_processing=True); print('glb', len(m.vertices), len(m.triangles), "
               "m.has_textures())\"");
  ASSERT_EQ(open3d.exit_code, 0) << open3d.output;
  long vertices = 0, triangles = 0;
  char textured[16] = {};
  auto at = open3d.output.find("glb ");
  ASSERT_NE(at, std::string::npos) << open3d.output;
  ASSERT_EQ(
      std::sscanf(open3d.output.c_str() + at, "glb %ld %ld %15s", &vertices, &triangles, textured),
      3);
  EXPECT_EQ(static_cast<size_t>(triangles), ply.faces.size());
  EXPECT_GT(vertices, 0);
  EXPECT_STREQ(textured, "True");
}

// A take with calib/ is reconstructed through those models even when gt/ is there too: a
// calibration whose world is shifted by 10 cm moves the mesh by 10 cm.
TEST(StudioTest, CalibratedTakePrefersCalib) {
  TempDir dir;
  const fs::path take_dir = dir / "take";
  auto copy = RunShell("cp -r '" + StudioTake().string() + "' '" + take_dir.string() + "'");
  ASSERT_EQ(copy.exit_code, 0) << copy.output;
  const Eigen::Vector3d shift(0.1, 0, 0);  // point_in_calib = point_in_gt + shift
  Pose gt_from_calib = Pose::Identity();
  gt_from_calib.translation() = -shift;
  const Take take = Take::Open(take_dir);
  fs::create_directories(take.calib_dir());
  for (const StreamInfo& stream : take.streams()) {
    CameraModel model = take.Camera(stream.name, true);
    model.set_cam_from_world(model.cam_from_world() * gt_from_calib);
    model.Write(take.calib_dir() / (stream.name + ".cameramodel"));
  }
  ASSERT_TRUE(Take::Open(take_dir).has_calibration());
  auto centroid = [](const fs::path& ply) {
    Mesh mesh = ReadPly(ply);
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    for (const auto& v : mesh.vertices) sum += v.cast<double>();
    return Eigen::Vector3d(sum / std::max<size_t>(1, mesh.vertices.size()));
  };
  ReconstructionOptions options;
  options.method = ReconstructionMethod::kTsdf;
  options.voxel_m = 0.008;
  options.write_glb = false;
  options.sweep_voxels_m.clear();
  TakeSelection first_set;
  first_set.last_frame = 1;
  TempDir calibrated_out, truth_out;
  ReconstructionSummary calibrated =
      ReconstructTake(take_dir, first_set, calibrated_out.path(), options, nullptr);
  EXPECT_EQ(calibrated.plan["cameras"], "calib/");
  TakeSelection truth_cameras = testing::TrueCameras();
  truth_cameras.last_frame = 1;
  ReconstructionSummary truth =
      ReconstructTake(StudioTake(), truth_cameras, truth_out.path(), options, nullptr);
  EXPECT_EQ(truth.plan["cameras"], "gt/cameras (asked for)");
  const Eigen::Vector3d moved =
      centroid(calibrated_out / "000001.ply") - centroid(truth_out / "000001.ply");
  EXPECT_LT((moved - shift).norm(), 0.005) << moved.transpose();
}

// A simulated take is uncalibrated like any other until it is calibrated: its truth only
// measures. Without calib/ (with its gt/ or without) reconstruct stops with the calibrate line,
// before anything is written.
TEST(StudioTest, TakeWithoutCalibrationIsAClearError) {
  TempDir dir;
  auto simulated = RunCli("reconstruct '" + StudioTake().string() + "' --out '" +
                          (dir / "simulated").string() + "'");
  testing::ExpectOneLineError(simulated, "is not calibrated");
  EXPECT_NE(simulated.output.find("run holocap calibrate first"), std::string::npos)
      << simulated.output;
  EXPECT_FALSE(fs::exists(dir / "simulated" / "000001.ply"));
  auto copy = RunShell("cp -r '" + StudioTake().string() + "' '" + (dir / "take").string() +
                       "' && rm -rf '" + (dir / "take" / "gt").string() + "'");
  ASSERT_EQ(copy.exit_code, 0) << copy.output;
  auto result = RunCli("reconstruct '" + (dir / "take").string() + "'");
  testing::ExpectOneLineError(result, "is not calibrated");
}

TEST(StudioTest, MissingFramesAreAClearError) {
  TempDir dir;
  // Small frames and frequent drops: some set after the clean plate lacks a camera.
  auto sim =
      RunCli("sim --rig studio8 --frames 4 --clean-plate 1 --size 160 --drop 0.3 --seed 2 --out '" +
             (dir / "take").string() + "'");
  ASSERT_EQ(sim.exit_code, 0) << sim.output;
  auto result = RunCli("reconstruct '" + (dir / "take").string() +
                       "' --ground-truth-cameras --method hull --no-sweep");
  EXPECT_NE(result.exit_code, 0);
  EXPECT_NE(result.output.find("holocap: error: "), std::string::npos) << result.output;
  EXPECT_TRUE(result.output.find("has no frame from") != std::string::npos ||
              result.output.find("clean plate") != std::string::npos)
      << result.output;
}

// A run is SUCCESS only when every frame set gave a surface: with the subject gone from one
// frame set (its frames are the clean plate's), that set's hull is empty and the run is
// DEGENERATE, naming the set, while the other set's mesh is still written.
TEST(StudioTest, AFrameSetWithoutASurfaceMakesTheRunDegenerate) {
  TempDir dir;
  const fs::path take = dir / "take";
  ASSERT_EQ(RunCli("sim --rig studio8 --frames 3 --clean-plate 1 --size 160 --seed 3 --no-noise "
                   "--out '" +
                   take.string() + "'")
                .exit_code,
            0);
  for (const auto& camera : fs::directory_iterator(take / "frames")) {
    if (camera.path().filename().string().rfind("cam", 0) != 0) continue;
    fs::copy_file(camera.path() / "000000.png", camera.path() / "000002.png",
                  fs::copy_options::overwrite_existing);
  }
  auto result = RunCli("reconstruct '" + take.string() +
                       "' --ground-truth-cameras --method hull --no-sweep --no-glb --no-atlas");
  EXPECT_EQ(result.exit_code, 1) << result.output;
  EXPECT_NE(result.output.find("DEGENERATE: 1 of 2 frame sets gave no surface (set(s) 2)"),
            std::string::npos)
      << result.output;
  EXPECT_NE(result.output.find("the hull is empty"), std::string::npos) << result.output;
  EXPECT_TRUE(fs::exists(take / "recon" / "000001.ply"));
  std::ifstream file(take / "recon" / "report.json");
  const nlohmann::json report = nlohmann::json::parse(file);
  EXPECT_EQ(report["summary"]["termination"], "DEGENERATE");
  EXPECT_EQ(report["metrics"]["frames"][0]["termination"], "SUCCESS");
}

// With no bounds given, the plan takes them from the rig: the box the cameras share, cut at the
// floor the depth sensors see and tightened to a coarse hull. The hull in it is the hull in the
// old hand-set stage box: the same Chamfer against the truth.
TEST(StudioTest, BoundsFromTheRigGiveTheSameHullAsTheStageBox) {
  TempDir dir;
  auto run = [&](const std::optional<Box>& bounds, const std::string& name) {
    ReconstructionOptions options;
    options.method = ReconstructionMethod::kHull;
    options.voxel_m = 0.008;
    options.write_glb = false;
    options.texture.atlas = false;
    options.sweep_voxels_m.clear();
    TakeSelection selection = testing::TrueCameras();
    selection.bounds = bounds;
    Report report("reconstruct");
    ReconstructionSummary summary =
        ReconstructTake(StudioTake(), selection, dir / name, options, &report);
    EXPECT_EQ(summary.termination, Termination::kSuccess) << summary.message;
    return report.json();
  };
  const nlohmann::json stage =
      run(Box{Eigen::Vector3d(-1.5, -1.5, 0), Eigen::Vector3d(1.5, 1.5, 2.5)}, "stage");
  const nlohmann::json rig = run(std::nullopt, "rig");
  const nlohmann::json& plan = rig["plan"];
  EXPECT_EQ(plan["bounds"]["source"].get<std::string>().rfind("cameras + coarse hull", 0), 0u)
      << plan["bounds"];
  EXPECT_EQ(plan["up"]["axis"], nlohmann::json({0.0, 0.0, 1.0})) << plan["up"];
  ASSERT_TRUE(plan["floor_m"].is_number()) << plan["up"];
  EXPECT_NEAR(plan["floor_m"].get<double>(), -0.032, 0.01);  // the floor less 1% of 3.2 m
  EXPECT_EQ(stage["plan"]["bounds"]["source"], "user (--bounds)");
  // The subject (1.8 m tall, walking) fits; the stage box around it is not kept.
  const Mesh truth = ReadPly(StudioTake() / "gt" / "meshes" / "000001.ply");
  const Box box{Eigen::Vector3d(plan["bounds"]["box"]["min"][0].get<double>(),
                                plan["bounds"]["box"]["min"][1].get<double>(),
                                plan["bounds"]["box"]["min"][2].get<double>()),
                Eigen::Vector3d(plan["bounds"]["box"]["max"][0].get<double>(),
                                plan["bounds"]["box"]["max"][1].get<double>(),
                                plan["bounds"]["box"]["max"][2].get<double>())};
  int outside = 0;
  for (const auto& v : truth.vertices) outside += !box.Contains(v.cast<double>());
  EXPECT_EQ(outside, 0);
  EXPECT_LT(box.Volume(), 0.5 * 3 * 3 * 2.5);
  const double chamfer_stage = stage["metrics"]["gt"]["chamfer_mm"].get<double>();
  const double chamfer_rig = rig["metrics"]["gt"]["chamfer_mm"].get<double>();
  std::printf("hull at 8 mm: chamfer %.3f mm in the stage box, %.3f mm in the rig's bounds\n",
              chamfer_stage, chamfer_rig);
  EXPECT_NEAR(chamfer_rig, chamfer_stage, 0.02 * chamfer_stage);
}

// Silhouettes that do not separate a subject (a threshold below the lit studio's walls) give a
// hull that fills the cameras' shared view: DEGENERATE with the reason, never a "success"; so
// do bounds that no camera looks at.
TEST(StudioTest, AHullFillingItsBoundsOrUnseenBoundsAreDegenerate) {
  TempDir dir;
  const std::string take = "'" + StudioTake().string() + "' --ground-truth-cameras";
  auto filled = RunCli("reconstruct " + take +
                       " --method hull --silhouette-threshold 0.01 --voxel 16mm --no-sweep "
                       "--no-glb --out '" +
                       (dir / "filled").string() + "'");
  EXPECT_EQ(filled.exit_code, 1) << filled.output;
  EXPECT_NE(filled.output.find("holocap: error: reconstruction ended DEGENERATE"),
            std::string::npos)
      << filled.output;
  EXPECT_NE(filled.output.find("the silhouettes do not separate a subject"), std::string::npos)
      << filled.output;
  std::ifstream file(dir / "filled" / "report.json");
  const nlohmann::json report = nlohmann::json::parse(file);
  EXPECT_EQ(report["summary"]["termination"], "DEGENERATE") << report["summary"];
  EXPECT_EQ(report["plan"]["silhouettes"]["source"], "threshold");

  auto unseen = RunCli("reconstruct " + take +
                       " --method hull --bounds 40,40,40,41,41,41 --no-sweep --no-glb --out '" +
                       (dir / "unseen").string() + "'");
  EXPECT_EQ(unseen.exit_code, 1) << unseen.output;
  EXPECT_NE(unseen.output.find("the cameras do not see the bounds: 0 of 8"), std::string::npos)
      << unseen.output;
}

}  // namespace
}  // namespace holocap
