// The take plan: one reading of a take (camera models, sensors, clean plate, frame sets) that
// every stage starts from.
#include "core/take_plan.h"

#include <gtest/gtest.h>

#include "core/error.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::TempDir;

// Three colour cameras on a ring and a depth sensor paired with cam1; `sets` frame sets, the
// first `plate` of them recorded as clean plate in the take's metadata; cam2 dropped in set 3.
std::filesystem::path WriteTake(const std::filesystem::path& dir, int sets, int plate) {
  RigDescription rig;
  rig.name = "plan";
  std::vector<StreamInfo> streams;
  for (const char* name : {"cam0", "cam1", "cam2"}) {
    rig.sensors.push_back({.name = name, .uri = std::string("sim:plan#") + name});
    streams.push_back({.name = name,
                       .uri = std::string("sim:plan#") + name,
                       .width = 32,
                       .height = 24,
                       .pixel_format = "bgr8",
                       .clock = "sim"});
  }
  rig.sensors.push_back({.name = "depth0",
                         .uri = "sim:plan#depth0",
                         .role = SensorRole::kDepth,
                         .paired_with = "cam1"});
  streams.push_back({.name = "depth0",
                     .uri = "sim:plan#depth0",
                     .role = SensorRole::kDepth,
                     .width = 16,
                     .height = 12,
                     .pixel_format = "depth_m",
                     .codec = ImageCodec::kExr,
                     .clock = "sim",
                     .paired_with = "cam1"});
  {
    TakeWriter writer(dir, rig, streams, {{"clean_plate_frames", plate}});
    for (int i = 0; i < sets; ++i) {
      FrameSet set;
      set.index = i;
      for (const char* name : {"cam0", "cam1", "cam2"}) {
        if (i == 3 && std::string(name) == "cam2") continue;
        set.frames.push_back({name, cv::Mat(24, 32, CV_8UC3, cv::Scalar::all(10 * i)),
                              int64_t{1000} * i, static_cast<uint64_t>(i)});
      }
      set.frames.push_back({"depth0", cv::Mat(12, 16, CV_32FC1, cv::Scalar(1.5f)),
                            int64_t{1000} * i, static_cast<uint64_t>(i)});
      writer.Append(set);
    }
    writer.Close();
  }
  return dir;
}

void WriteModels(const std::filesystem::path& folder) {
  const char* names[] = {"cam0", "cam1", "cam2", "depth0"};
  for (int i = 0; i < 4; ++i) {
    const double angle = 2 * 3.14159265358979 * i / 4;
    Pose cam_from_world = Pose::Identity();
    cam_from_world.translation() = Eigen::Vector3d(std::cos(angle), std::sin(angle), 3.0);
    CameraModel::Pinhole(30, i < 3 ? 32 : 16, i < 3 ? 24 : 12, cam_from_world)
        .Write(folder / (std::string(names[i]) + ".cameramodel"));
  }
}

// A simulated take is uncalibrated like any other: its true models (gt/cameras) are used only
// when asked for, never in place of a missing calibration.
TEST(TakePlan, NeedsACalibrationAndUsesTheTruthOnlyWhenAskedFor) {
  TempDir dir;
  const Take bare = Take::Open(WriteTake(dir.path() / "take", 3, 1));
  try {
    PlanTake(bare, TakeSelection{});
    FAIL() << "a take without calib/ or gt/cameras was planned";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("holocap calibrate"), std::string::npos) << e.what();
  }
  std::filesystem::create_directories(dir.path() / "take" / "gt" / "cameras");
  WriteModels(dir.path() / "take" / "gt" / "cameras");
  const Take simulated = Take::Open(dir.path() / "take");
  try {
    PlanTake(simulated, TakeSelection{});
    FAIL() << "a simulated take without calib/ was planned with its true cameras";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("run holocap calibrate first"), std::string::npos)
        << e.what();
    EXPECT_NE(std::string(e.what()).find("--ground-truth-cameras"), std::string::npos) << e.what();
  }
  TakeSelection asked;
  asked.ground_truth_cameras = true;
  const TakePlan truth = PlanTake(simulated, asked);
  EXPECT_TRUE(truth.ground_truth_cameras);
  EXPECT_EQ(truth.cameras_source, "gt/cameras (asked for)");
  EXPECT_EQ(truth.ToJson()["cameras"], "gt/cameras (asked for)");  // every report says which
  std::filesystem::create_directories(dir.path() / "take" / "calib");
  WriteModels(dir.path() / "take" / "calib");
  const Take calibrated = Take::Open(dir.path() / "take");
  EXPECT_EQ(PlanTake(calibrated, TakeSelection{}).cameras_source, "calib/");
  TakeSelection forced;
  forced.ground_truth_cameras = true;
  EXPECT_EQ(PlanTake(calibrated, forced).cameras_source, "gt/cameras (asked for)");
}

TEST(TakePlan, ChoosesSensorsPlateAndFrameSetsOnce) {
  TempDir dir;
  WriteTake(dir.path() / "take", 6, 1);
  std::filesystem::create_directories(dir.path() / "take" / "calib");
  WriteModels(dir.path() / "take" / "calib");
  const Take take = Take::Open(dir.path() / "take");
  TakePlan plan = PlanTake(take, TakeSelection{});
  EXPECT_EQ(plan.color_sensors, (std::vector<std::string>{"cam0", "cam1", "cam2"}));
  EXPECT_EQ(plan.depth_sensors, (std::vector<std::string>{"depth0"}));
  EXPECT_EQ(plan.paired_color, (std::set<std::string>{"cam1"}));
  EXPECT_EQ(plan.cameras.size(), 4u);
  EXPECT_EQ(plan.clean_plate_frames, 1);  // from the take's metadata
  EXPECT_EQ(plan.plate_set(), 0);
  EXPECT_EQ(plan.sets, (std::vector<int64_t>{1, 2, 3, 4, 5}));

  TakeSelection range;
  range.first_frame = 1;
  range.last_frame = 3;
  range.clean_plate_frames = 2;  // the user's word beats the metadata
  plan = PlanTake(take, range);
  EXPECT_EQ(plan.clean_plate_frames, 2);
  EXPECT_EQ(plan.sets, (std::vector<int64_t>{3, 4}));
  // Set 3 lacks cam2: a stage that reads cam2 is told which set and sensor, one that does not is
  // not.
  try {
    plan.RequireFrames(take, {"cam0", "cam2"});
    FAIL() << "a dropped frame went unnoticed";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("frame set 3"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("'cam2'"), std::string::npos) << e.what();
  }
  EXPECT_NO_THROW(plan.RequireFrames(take, {"cam0", "depth0"}));

  plan.heldout = {"cam2"};
  plan.LeaveOut("depth sensors", "colour alone");
  const nlohmann::json json = plan.ToJson();
  EXPECT_EQ(json.at("frame_sets"), nlohmann::json({3, 4}));
  EXPECT_EQ(json.at("heldout"), nlohmann::json({"cam2"}));
  EXPECT_EQ(json.at("left_out").at("depth sensors"), "colour alone");
  EXPECT_EQ(plan.ColorIndex("cam2", "held-out"), 2);
  EXPECT_THROW(plan.ColorIndex("depth0", "held-out"), Error);
}

TEST(TakePlan, NoDepthLeavesTheDepthSensorsOutOfEverything) {
  TempDir dir;
  WriteTake(dir.path() / "take", 6, 1);
  std::filesystem::create_directories(dir.path() / "take" / "calib");
  WriteModels(dir.path() / "take" / "calib");
  const Take take = Take::Open(dir.path() / "take");
  TakeSelection colour;
  colour.color_only = true;
  const TakePlan plan = PlanTake(take, colour);
  EXPECT_EQ(plan.color_sensors, (std::vector<std::string>{"cam0", "cam1", "cam2"}));
  EXPECT_TRUE(plan.depth_sensors.empty());
  EXPECT_TRUE(plan.paired_color.empty());
  EXPECT_EQ(plan.cameras.count("depth0"), 0u);  // no stage can reach its model
  EXPECT_EQ(plan.ToJson().at("left_out").at("depth sensors"),
            "colour cameras only, asked for (--no-depth)");
  EXPECT_EQ(colour.ToJson().at("color_only"), true);
}

TEST(TakePlan, RefusesSelectionsThatSelectNothing) {
  TempDir dir;
  WriteTake(dir.path() / "take", 3, 1);
  std::filesystem::create_directories(dir.path() / "take" / "calib");
  WriteModels(dir.path() / "take" / "calib");
  const Take take = Take::Open(dir.path() / "take");
  TakeSelection past_the_end;
  past_the_end.first_frame = 2;  // two sets after the plate: 0 and 1
  EXPECT_THROW(PlanTake(take, past_the_end), Error);
  TakeSelection all_plate;
  all_plate.clean_plate_frames = 3;
  EXPECT_THROW(PlanTake(take, all_plate), Error);
  TakeSelection empty;
  empty.first_frame = 1;
  empty.last_frame = 1;
  EXPECT_THROW(empty.Check(), Error);
  TakeSelection negative;
  negative.first_frame = -1;
  EXPECT_THROW(negative.Check(), Error);
}

TEST(TakePlan, SpreadsPicksAroundTheCentre) {
  std::vector<CameraModel> ring;
  for (int i = 0; i < 8; ++i) {
    const double angle = 2 * 3.14159265358979 * i / 8;
    Pose cam_from_world = Pose::Identity();
    cam_from_world.translation() = Eigen::Vector3d(3 * std::cos(angle), 3 * std::sin(angle), 0);
    ring.push_back(CameraModel::Pinhole(100, 64, 48, cam_from_world));
  }
  // world_from_cam's translation is the centre; these cameras sit at -translation.
  const std::vector<int> all = {0, 1, 2, 3, 4, 5, 6, 7};
  const std::vector<int> two = SpreadAround(ring, all, 2, Eigen::Vector3d::Zero());
  EXPECT_EQ(two, (std::vector<int>{0, 4})) << "opposite cameras are farthest apart";
  EXPECT_EQ(SpreadAround(ring, all, 4, Eigen::Vector3d::Zero()), (std::vector<int>{0, 2, 4, 6}));
  EXPECT_TRUE(SpreadAround(ring, all, 0, Eigen::Vector3d::Zero()).empty());
  EXPECT_EQ(SpreadAround(ring, {3, 5}, 5, Eigen::Vector3d::Zero()).size(), 2u);
}

}  // namespace
}  // namespace holocap

namespace holocap {
namespace {

// A pinhole camera at `center` looking at `target`, its image "up" (-y) as close to `up` as the
// view allows.
CameraModel LookAt(const Eigen::Vector3d& center, const Eigen::Vector3d& target,
                   const Eigen::Vector3d& up, double focal_px = 1000) {
  const Eigen::Vector3d z = (target - center).normalized();
  const Eigen::Vector3d x = z.cross(up).normalized();
  const Eigen::Vector3d y = z.cross(x);
  Eigen::Matrix3d world_from_cam_rotation;
  world_from_cam_rotation << x, y, z;
  Pose world_from_cam = Pose::Identity();
  world_from_cam.linear() = world_from_cam_rotation;
  world_from_cam.translation() = center;
  return CameraModel::Pinhole(focal_px, 640, 480, world_from_cam.inverse());
}

// `count` cameras on a ring of `radius` around `target`, `height` above it along `up` (y-up
// here: no world axis but y is vertical), each aimed at the target.
std::vector<CameraModel> Ring(int count, double radius, double height,
                              const Eigen::Vector3d& target) {
  std::vector<CameraModel> cameras;
  const Eigen::Vector3d up = Eigen::Vector3d::UnitY();
  for (int i = 0; i < count; ++i) {
    const double angle = 2 * M_PI * i / count;
    const Eigen::Vector3d center =
        target + Eigen::Vector3d(radius * std::cos(angle), height, radius * std::sin(angle));
    cameras.push_back(LookAt(center, target, up));
  }
  return cameras;
}

TEST(SceneFromRig, BoundsUpAndVoxelFollowTheCamerasAtAnyScale) {
  const Eigen::Vector3d target(0.3, -0.2, 1.0);
  for (double scale : {1.0, 0.05}) {
    SCOPED_TRACE(scale);
    const auto cameras = Ring(12, 3.0 * scale, 1.0 * scale, target * scale);
    const RigView view = ViewOfRig(cameras);
    ASSERT_TRUE(view.converges) << view.why;
    EXPECT_LT((view.center - target * scale).norm(), 1e-6 * scale) << view.why;
    EXPECT_NEAR(view.median_distance_m, std::hypot(3.0, 1.0) * scale, 1e-9);
    EXPECT_EQ(view.min_cameras, 6);
    EXPECT_TRUE(view.shared.Contains(target * scale));
    // f = 1000 px over 640 px sees 2 x 0.32 x 3.16 m = 2.0 m across at the target: the box that
    // half the ring sees is about that wide, never the ring itself.
    const Eigen::Vector3d size = view.shared.size() / scale;
    EXPECT_GT(size.minCoeff(), 1.0) << size.transpose();
    EXPECT_LT(size.maxCoeff(), 4.0) << size.transpose();
    std::string why;
    EXPECT_EQ(UpFromCameras(cameras, &why), Eigen::Vector3d::UnitY()) << why;
    // A pixel at 3.16 m is 3.16 mm (2/3 of it 2.1 mm) at scale 1; whichever rule wins, the
    // voxel is a power of two in millimetres and shrinks with the scene.
    const double voxel = ImpliedVoxel(view.shared, cameras, &why);
    const double log2_mm = std::log2(voxel * 1e3);
    EXPECT_NEAR(log2_mm, std::round(log2_mm), 1e-9) << why;
    EXPECT_GE(voxel / scale, 0.002) << why;
    EXPECT_LE(voxel / scale, 0.008) << why;
  }
}

TEST(SceneFromRig, OneCameraOrParallelAxesDoNotConverge) {
  const auto ring = Ring(4, 3.0, 1.0, Eigen::Vector3d::Zero());
  EXPECT_FALSE(ViewOfRig({ring[0]}).converges);
  std::vector<CameraModel> parallel;
  parallel.reserve(3);
  for (int i = 0; i < 3; ++i) {
    parallel.push_back(
        LookAt(Eigen::Vector3d(i, 0, 0), Eigen::Vector3d(i, 0, 5), -Eigen::Vector3d::UnitY()));
  }
  const RigView view = ViewOfRig(parallel);
  EXPECT_FALSE(view.converges);
  EXPECT_NE(view.why.find("do not meet"), std::string::npos) << view.why;
  // Cameras rolled 30 degrees about their axes give an up axis no world axis is close to.
  std::vector<CameraModel> tilted;
  for (const auto& camera : ring) {
    Pose cam_from_world = camera.cam_from_world();
    cam_from_world.linear() =
        Eigen::AngleAxisd(M_PI / 6, Eigen::Vector3d::UnitZ()).toRotationMatrix() *
        cam_from_world.linear();
    tilted.push_back(CameraModel::Pinhole(1000, 640, 480, cam_from_world));
  }
  std::string why;
  const Eigen::Vector3d up = UpFromCameras(tilted, &why);
  EXPECT_GT(std::acos(up.dot(Eigen::Vector3d::UnitY())), 10 * M_PI / 180) << why;
  EXPECT_NE(why.find("no world axis"), std::string::npos) << why;
}

TEST(SceneFromRig, ThePlanRecordsTheUsersSceneAndSilhouettesOrTheTakes) {
  TempDir dir;
  WriteTake(dir.path() / "take", 4, 0);
  std::filesystem::create_directories(dir.path() / "take" / "calib");
  WriteModels(dir.path() / "take" / "calib");
  const Take take = Take::Open(dir.path() / "take");
  TakePlan plan = PlanTake(take, TakeSelection{});
  EXPECT_EQ(plan.silhouettes, SilhouetteSource::kOtsu) << plan.silhouette_reason;
  EXPECT_FALSE(plan.bounds_source.empty());
  EXPECT_GT(plan.voxel_m, 0);
  EXPECT_TRUE(plan.bounds.Contains(plan.bounds.center()));

  TakeSelection selection;
  selection.bounds = Box{Eigen::Vector3d(-1, -2, -3), Eigen::Vector3d(1, 2, 3)};
  selection.up = Eigen::Vector3d(0, -2, 0);
  selection.silhouette_threshold = 0.3;
  selection.heldout = {"cam2"};
  plan = PlanTake(take, selection);
  EXPECT_EQ(plan.bounds_source, "user (--bounds)");
  EXPECT_EQ(plan.bounds.max, Eigen::Vector3d(1, 2, 3));
  EXPECT_EQ(plan.up, -Eigen::Vector3d::UnitY());
  EXPECT_EQ(plan.up_source.rfind("user (--up)", 0), 0u) << plan.up_source;
  EXPECT_EQ(plan.silhouettes, SilhouetteSource::kThreshold);
  EXPECT_DOUBLE_EQ(plan.silhouette_threshold, 0.3);
  EXPECT_EQ(plan.ReconstructionSensors(), (std::vector<std::string>{"cam0", "cam1"}));
  const nlohmann::json json = plan.ToJson();
  EXPECT_EQ(json.at("bounds").at("source"), "user (--bounds)");
  EXPECT_EQ(json.at("silhouettes").at("source"), "threshold");
  EXPECT_EQ(json.at("voxel").at("m"), plan.voxel_m);

  // A clean plate asked for where there is none: the error names every source.
  TakeSelection plate;
  plate.silhouettes = "plate";
  try {
    PlanTake(take, plate);
    FAIL() << "silhouettes from a plate the take lacks";
  } catch (const Error& e) {
    for (const char* option : {"--clean-plate", "--silhouettes otsu", "--silhouette-threshold",
                               "alpha", "background model"}) {
      EXPECT_NE(std::string(e.what()).find(option), std::string::npos) << e.what();
    }
  }
  // Alpha asked for by name on a take without it: the error names the streams that lack it.
  TakeSelection alpha;
  alpha.silhouettes = "alpha";
  try {
    PlanTake(take, alpha);
    FAIL() << "silhouettes from alpha the take lacks";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("colour streams without alpha: cam0 (bgr8)"),
              std::string::npos)
        << e.what();
  }
  alpha.silhouette_threshold = 0.2;
  EXPECT_THROW(alpha.Check(), Error);
  selection.heldout = {"depth0"};
  EXPECT_THROW(PlanTake(take, selection), Error);
}

}  // namespace
}  // namespace holocap
