// Scanning with one moving RGB-D sensor on small simulated takes: accuracy on an orbit, a
// hand-held walk and a turntable, and the stiff cases (a flat wall, a sensor too fast to follow, no
// depth).
#include <gtest/gtest.h>

#include <fstream>
#include <nlohmann/json.hpp>

#include "core/error.h"
#include "core/fs.h"
#include "core/mesh.h"
#include "core/report.h"
#include "core/take.h"
#include "core/trajectory.h"
#include "scan/scan.h"
#include "sim/sim.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::TempDir;

// A small scan take: 160x120 frames of the still subject.
SimOptions ScanSim(const std::string& trajectory, int64_t frames, int width = 160,
                   int height = 120) {
  SimOptions sim;
  sim.rig = "single-rgbd";
  sim.scene = "subject";
  sim.trajectory = trajectory;
  sim.frames = frames;
  sim.fps = 10;
  sim.image_width = width;
  sim.image_height = height;
  sim.antialias = 1;
  sim.motion_blur_samples = 3;
  sim.seed = 7;
  return sim;
}

ScanOptions SmallScan() {
  ScanOptions options;
  options.voxel_m = 0.02;
  options.write_glb = false;
  options.threads = 2;
  return options;
}

ScanSummary SimulateAndScan(const SimOptions& sim, const ScanOptions& options, const TempDir& dir) {
  EXPECT_TRUE(SimulateTake(sim, dir / "take").IsUsable());
  return ScanTake(dir / "take", testing::TrueCameras(), dir / "scan", options);
}

int64_t Count(const ScanSummary& summary, TrackingState state) {
  int64_t n = 0;
  for (const ScanFrame& f : summary.frames) n += f.state == state;
  return n;
}

TEST(ScanSimTest, TrajectoryGroundTruthStartsAtTheRigAndTurnsAtItsSpeed) {
  TempDir dir;
  SimOptions sim = ScanSim("orbit", 4);
  sim.image_width = 64;
  sim.image_height = 48;
  ASSERT_TRUE(SimulateTake(sim, dir / "take").IsUsable());
  const Take take = Take::Open(dir / "take");
  EXPECT_EQ(take.metadata().value("trajectory", ""), "orbit");
  const std::vector<StampedPose> truth =
      ParseTum(ReadFileToString(dir / "take" / "gt" / "trajectory" / "depth0.tum"), "depth0.tum");
  ASSERT_EQ(truth.size(), 4u);
  const CameraModel first = take.Camera("depth0", true);
  EXPECT_LT((truth[0].world_from_cam.translation() - first.center_in_world()).norm(), 1e-6);
  // 30 degrees per second at 10 frame sets per second: 3 degrees a frame about the vertical.
  const Pose step = truth[0].world_from_cam.inverse() * truth[3].world_from_cam;
  EXPECT_NEAR(RotationAngleDeg(step.linear()), 9.0, 0.05);
  // The scan's own reading of the ground truth agrees with the TUM file.
  const std::vector<StampedPose> read = TrueTrajectory(take, "depth0");
  ASSERT_EQ(read.size(), 4u);
  EXPECT_LT((read[3].world_from_cam.translation() - truth[3].world_from_cam.translation()).norm(),
            1e-6);
}

TEST(ScanSimTest, TurntableSubjectMovesAndTheSensorStays) {
  TempDir dir;
  SimOptions sim = ScanSim("turn", 3);
  sim.image_width = 64;
  sim.image_height = 48;
  ASSERT_TRUE(SimulateTake(sim, dir / "take").IsUsable());
  // The sensor is fixed in the room, so relative to the turning subject it orbits.
  const std::vector<StampedPose> truth =
      ParseTum(ReadFileToString(dir / "take" / "gt" / "trajectory" / "depth0.tum"), "depth0.tum");
  ASSERT_EQ(truth.size(), 3u);
  EXPECT_NEAR(
      RotationAngleDeg((truth[0].world_from_cam.inverse() * truth[2].world_from_cam).linear()), 6.0,
      0.05);
  const Mesh first = ReadPly(dir / "take" / "gt" / "meshes" / "000000.ply");
  const Mesh last = ReadPly(dir / "take" / "gt" / "meshes" / "000002.ply");
  // 6 degrees about the subject's axis moves its outer points by a few centimetres.
  float moved = 0;
  for (size_t i = 0; i < first.vertices.size(); ++i)
    moved = std::max(moved, (first.vertices[i] - last.vertices[i]).norm());
  EXPECT_GT(moved, 0.02f);
}

TEST(ScanTest, HandheldTracksWithinAFewVoxels) {
  TempDir dir;
  const ScanSummary summary = SimulateAndScan(ScanSim("handheld", 24), SmallScan(), dir);
  ASSERT_EQ(summary.termination, Termination::kSuccess) << summary.message;
  EXPECT_EQ(summary.lost, 0);
  ASSERT_TRUE(summary.errors.has_value());
  EXPECT_LT(summary.errors->ate_rmse_m, 0.03);
  // A sensor carried through the room carries no light with it: none is looked for, and the
  // colours stay as seen.
  const nlohmann::json light =
      nlohmann::json::parse(ReadFileToString(dir / "scan" / "lighting.json"));
  EXPECT_FALSE(light["observed"].get<bool>());
  EXPECT_NE(light["why"].get<std::string>().find("the sensor moved"), std::string::npos)
      << light.dump();
  EXPECT_FALSE(std::filesystem::exists(dir / "scan" / "albedo.ply"));
}

TEST(ScanTest, TurntableTracksTheSubjectWithoutTheFloor) {
  TempDir dir;
  // 320x240: at 160x120 the sensor sees too little of the floor to find it.
  ASSERT_TRUE(SimulateTake(ScanSim("turn", 12, 320, 240), dir / "take").IsUsable());
  Report report("scan");
  ScanOptions options = SmallScan();
  options.subject_turns = true;  // the user says so (--turn); the take's metadata never does
  const ScanSummary summary =
      ScanTake(dir / "take", testing::TrueCameras(), dir / "scan", options, &report);
  ASSERT_EQ(summary.termination, Termination::kSuccess) << summary.message;
  EXPECT_EQ(summary.lost, 0);
  EXPECT_EQ(summary.fused, 12);
  // The floor stays while the subject turns: left in, it would hold the pose still.
  EXPECT_EQ(report.plan()["scan"]["subject_turns"], true);
  EXPECT_EQ(report.plan()["scan"]["floor_removed"], true);
  ASSERT_TRUE(summary.errors.has_value());
  EXPECT_EQ(summary.errors->matched, 12);
  // 12 frames at 3 degrees: the subject turns 33 degrees; the recovered orbit around it holds
  // to a voxel.
  EXPECT_LT(summary.errors->ate_rmse_m, 0.02);
  EXPECT_LT(summary.errors->rpe_rot_deg, 0.5);
  const std::vector<StampedPose> truth = TrueTrajectory(Take::Open(dir / "take"), "depth0");
  ASSERT_EQ(truth.size(), 12u);
  const double turned_deg = RotationAngleDeg(
      (truth.front().world_from_cam.inverse() * truth.back().world_from_cam).linear());
  const ScanFrame& last = summary.frames.back();
  const double scanned_deg = RotationAngleDeg(
      (summary.frames.front().world_from_cam.inverse() * last.world_from_cam).linear());
  EXPECT_NEAR(scanned_deg, turned_deg, 1.0);
}

// 40 frames: the constant-velocity prediction once compounded rounding in its rotation (an
// Isometry3d inverts by transposing) until, past the 36th frame of any trajectory, depths were
// scaled by a percent and every frame from there was lost.
TEST(ScanTest, FortyFrameOrbitLosesNoFrameAndTracksWithinAVoxel) {
  TempDir dir;
  const ScanSummary summary = SimulateAndScan(ScanSim("orbit", 40), SmallScan(), dir);
  ASSERT_EQ(summary.termination, Termination::kSuccess) << summary.message;
  EXPECT_EQ(summary.lost, 0);
  EXPECT_EQ(summary.fused, 40);
  ASSERT_TRUE(summary.errors.has_value());
  EXPECT_EQ(summary.errors->matched, 40);
  // 2 cm voxels at 160x120 (a pixel spans ~1.5 cm at 2.4 m): the pose holds to under a voxel.
  EXPECT_LT(summary.errors->ate_rmse_m, 0.02);
  EXPECT_LT(summary.errors->rpe_rot_deg, 0.5);
  EXPECT_TRUE(std::filesystem::exists(dir / "scan" / "trajectory.tum"));
  EXPECT_TRUE(std::filesystem::exists(dir / "scan" / "mesh.ply"));
  // Every keyframe but the first was checked against the final model and fits it to well
  // under the association gate (6 cm).
  EXPECT_GE(summary.metrics["keyframe_check"]["keyframes_checked"].get<int64_t>(), 3);
  EXPECT_EQ(summary.metrics["keyframe_check"]["keyframes_contradicted"].get<int64_t>(), 0);
  EXPECT_LT(summary.metrics["keyframe_check"]["largest_move_m"].get<double>(), 0.04);
}

// Frame sets 0-11, then 30-37 of a 38-set take: the sensor jumps 1.8 s ahead.
TakeSelection JumpingSelection() {
  TakeSelection selection = testing::TrueCameras();
  for (int64_t set = 0; set < 12; ++set) selection.frame_list.push_back(set);
  for (int64_t set = 30; set < 38; ++set) selection.frame_list.push_back(set);
  return selection;
}

// The hand-held sensor jumps 1.8 s ahead between the 12th and the 13th frame scanned: the
// frames after the jump are lost, fewer than max_lost_frames in a row, so tracking never
// stops; such a scan once ended SUCCESS with a third of its frames missing.
TEST(ScanTest, ScanWithManyLostFramesIsDegenerateNotSuccess) {
  TempDir dir;
  ASSERT_TRUE(SimulateTake(ScanSim("handheld", 38), dir / "take").IsUsable());
  const TakeSelection selection = JumpingSelection();
  const ScanSummary summary = ScanTake(dir / "take", selection, dir / "scan", SmallScan());
  EXPECT_EQ(summary.termination, Termination::kDegenerate) << summary.message;
  EXPECT_GE(summary.lost, 3);
  EXPECT_LT(summary.lost, SmallScan().max_lost_frames);  // never stopped: judged at the end
  EXPECT_NE(summary.message.find("frames lost (more than 10%)"), std::string::npos)
      << summary.message;
  for (const ScanFrame& f : summary.frames) {
    if (f.state == TrackingState::kLost) EXPECT_FALSE(f.fused) << "set " << f.set;
  }
}

// The same jump with tracking tests that accept anything: no frame is lost, the frames after
// the jump are fused wherever the alignment left them, and only the keyframes' check against
// the final model can tell that the trajectory broke.
TEST(ScanTest, KeyframeContradictingTheFinalModelIsDegenerate) {
  TempDir dir;
  ASSERT_TRUE(SimulateTake(ScanSim("handheld", 38), dir / "take").IsUsable());
  const TakeSelection selection = JumpingSelection();
  ScanOptions options = SmallScan();
  options.min_inlier_fraction = 0;
  options.max_residual_m = 1;
  options.max_step_m = 10;
  options.max_step_deg = 180;
  options.keyframe_every = 4;
  const ScanSummary summary = ScanTake(dir / "take", selection, dir / "scan", options);
  EXPECT_EQ(summary.lost, 0);
  EXPECT_EQ(summary.termination, Termination::kDegenerate) << summary.message;
  EXPECT_NE(summary.message.find("contradicts the final model"), std::string::npos)
      << summary.message;
  EXPECT_GE(summary.metrics["keyframe_check"]["keyframes_contradicted"].get<int64_t>(), 1);
  ASSERT_TRUE(summary.errors.has_value());
  EXPECT_GT(summary.errors->ate_rmse_m, 0.05);  // the trajectory did break
}

TEST(ScanTest, SensorFasterThanTrackingIsLostAndNotFused) {
  TempDir dir;
  SimOptions sim = ScanSim("orbit", 8);
  sim.trajectory_deg_per_s = 400;  // 40 degrees between frames
  ScanOptions options = SmallScan();
  options.max_lost_frames = 3;
  const ScanSummary summary = SimulateAndScan(sim, options, dir);
  EXPECT_EQ(summary.termination, Termination::kDegenerate) << summary.message;
  EXPECT_NE(summary.message.find("tracking lost"), std::string::npos) << summary.message;
  EXPECT_GE(summary.lost, 3);
  for (const ScanFrame& f : summary.frames) {
    if (f.state == TrackingState::kLost) EXPECT_FALSE(f.fused) << "set " << f.set;
  }
  // Only the first frame made it into the model; the model so far is still written.
  EXPECT_EQ(summary.fused, 1);
  EXPECT_TRUE(std::filesystem::exists(dir / "scan" / "mesh.ply"));
}

TEST(ScanTest, FlatWallIsReportedDegenerate) {
  TempDir dir;
  // One sensor 1.2 m before a wall of the room, sliding along it: ICP sees only a plane.
  const std::filesystem::path rig = dir / "wall.json";
  std::ofstream(rig) << R"({"name": "wall", "fps": 10, "sensors": [
    {"name": "cam0", "uri": "sim:wall#cam0", "role": "color",
     "options": {"lens": "LENSMODEL_OPENCV4", "intrinsics": [140, 140, 79.5, 59.5, 0, 0, 0, 0],
                 "size": [160, 120], "position": [3.8, 0, 1.6], "look_at": [5, 0, 1.6]}},
    {"name": "depth0", "uri": "sim:wall#depth0", "role": "depth", "paired_with": "cam0",
     "options": {"lens": "LENSMODEL_OPENCV4", "intrinsics": [140, 140, 79.5, 59.5, 0, 0, 0, 0],
                 "size": [160, 120], "depth_from_color": [0, 0, 0, -0.03, 0, 0]}}]})";
  SimOptions sim = ScanSim("orbit", 10);
  sim.rig = rig.string();
  sim.scene = "object";
  sim.image_width = 0;
  sim.image_height = 0;
  sim.trajectory_deg_per_s = 4;  // about 2.7 cm a frame along the wall
  ScanOptions options = SmallScan();
  options.photometric_weight_m = 0;  // geometry alone
  options.volume_side_m = 3;
  const ScanSummary summary = SimulateAndScan(sim, options, dir);
  EXPECT_EQ(summary.termination, Termination::kDegenerate) << summary.message;
  EXPECT_NE(summary.message.find("degenerate"), std::string::npos) << summary.message;
  EXPECT_GE(Count(summary, TrackingState::kDegenerate), 5);
  // The weak direction lies in the wall (the wall's normal is the world's x).
  for (const ScanFrame& f : summary.frames) {
    if (f.state != TrackingState::kDegenerate) continue;
    EXPECT_LT(std::abs(f.weak_direction.normalized().x()), 0.3) << "set " << f.set;
  }
}

TEST(ScanTest, NoValidDepthIsDegenerateWithAReason) {
  TempDir dir;
  SimOptions sim = ScanSim("orbit", 3);
  sim.depth_max_m = 0.31;  // nothing in the room is this close: every pixel NaN
  const ScanSummary summary = SimulateAndScan(sim, SmallScan(), dir);
  EXPECT_EQ(summary.termination, Termination::kDegenerate);
  EXPECT_NE(summary.message.find("no frame had enough valid depth"), std::string::npos)
      << summary.message;
  EXPECT_EQ(summary.fused, 0);
  // The CLI says so in one line and fails, with the report written.
  const testing::CommandResult cli =
      testing::RunCli("scan " + (dir / "take").string() + " --ground-truth-cameras --out " +
                      (dir / "cli").string());
  testing::ExpectOneLineError(cli, "no frame had enough valid depth");
  const auto report = nlohmann::json::parse(ReadFileToString(dir / "cli" / "report.json"));
  EXPECT_EQ(report["summary"]["termination"], "DEGENERATE");
}

TEST(ScanTest, TakeWithoutOneDepthSensorIsRefused) {
  TempDir dir;
  SimOptions sim = ScanSim("orbit", 2);
  sim.color_only = true;
  ASSERT_TRUE(SimulateTake(sim, dir / "take").IsUsable());
  EXPECT_THROW(ScanTake(dir / "take", testing::TrueCameras(), dir / "scan", SmallScan()), Error);
}

}  // namespace
}  // namespace holocap
