// The scanner's tracker alone: one simulated frame aligned to a raycast of a model fused from
// the take's true poses. From its own true pose it must stay there; from a pose moved by a
// known small motion it must come back to within a fraction of a voxel.
#include <gtest/gtest.h>

#include <cmath>

#include "core/projector.h"
#include "core/take.h"
#include "core/take_plan.h"
#include "scan/internal/track.h"
#include "scan/scan.h"
#include "sim/sim.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::TempDir;
using Vector6d = Eigen::Matrix<double, 6, 1>;

// A take of the orbit, the model fused from its first frames at their true poses, and what the
// tracker needs to align the last frame.
class TrackerFixture {
 public:
  TrackerFixture(int width, int height, double voxel_m, int fused_frames) {
    SimOptions sim;
    sim.rig = "single-rgbd";
    sim.scene = "subject";
    sim.trajectory = "orbit";
    sim.frames = fused_frames + 1;
    sim.fps = 10;
    sim.image_width = width;
    sim.image_height = height;
    sim.antialias = 1;
    sim.seed = 7;
    EXPECT_TRUE(SimulateTake(sim, dir_ / "take").IsUsable());
    take_ = std::make_unique<Take>(Take::Open(dir_ / "take"));
    plan_ = PlanTake(*take_, testing::TrueCameras());
    truth_ = TrueTrajectory(*take_, "depth0");
    depth_lens_ = plan_.cameras.at("depth0");
    color_lens_ = plan_.cameras.at(take_->stream("depth0").paired_with);
    color_from_depth_ = color_lens_.cam_from_world() * depth_lens_.world_from_cam();
    rays_ = NormalisedRays(depth_lens_);
    options_.voxel_m = voxel_m;
    options_.threads = 2;

    TsdfOptions tsdf;
    tsdf.voxel_m = voxel_m;
    tsdf.truncation_voxels = options_.truncation_voxels;
    const Eigen::Vector3d centre = truth_[0].world_from_cam * Eigen::Vector3d(0, 0, 2.4);
    bounds_ = {centre - Eigen::Vector3d::Constant(1.3), centre + Eigen::Vector3d::Constant(1.3)};
    tsdf.bounds = bounds_;
    tsdf.depth_min_m = options_.depth_min_m;
    tsdf.depth_max_m = options_.depth_max_m;
    tsdf.smoothing_radius_px = 2;
    tsdf.threads = 2;
    volume_ = std::make_unique<TsdfVolume>(tsdf);
    for (int i = 0; i < fused_frames; ++i) {
      CameraModel depth_camera = depth_lens_;
      depth_camera.set_cam_from_world(truth_[i].world_from_cam.inverse());
      CameraModel color_camera = color_lens_;
      color_camera.set_cam_from_world(color_from_depth_ * truth_[i].world_from_cam.inverse());
      volume_->Integrate(Depth(i), depth_camera, {}, take_->ReadFrame(i, "cam0"), &color_camera);
    }
    last_ = fused_frames;
  }

  // The depth the scanner keeps: in range and, at the true pose, inside the volume.
  cv::Mat Depth(int set) const {
    cv::Mat depth = take_->ReadFrame(static_cast<size_t>(set), "depth0").clone();
    for (int y = 0; y < depth.rows; ++y) {
      for (int x = 0; x < depth.cols; ++x) {
        float& d = depth.at<float>(y, x);
        const cv::Vec2f ray = rays_.at<cv::Vec2f>(y, x);
        const Eigen::Vector3d p =
            truth_[set].world_from_cam * Eigen::Vector3d(ray[0] * d, ray[1] * d, d);
        if (!(d >= options_.depth_min_m && d <= options_.depth_max_m) || !bounds_.Contains(p)) {
          d = std::numeric_limits<float>::quiet_NaN();
        }
      }
    }
    return depth;
  }

  // The last frame aligned to the model raycast from `start`; returns world_from_cam.
  scan::AlignResult Align(const Pose& start, const ScanOptions& options) const {
    const cv::Mat depth = Depth(last_);
    const cv::Mat gray = scan::RegisterIntensity(depth, rays_, take_->ReadFrame(last_, "cam0"),
                                                 color_lens_, color_from_depth_, 2);
    const scan::TrackFrame frame = scan::PrepareFrame(depth, rays_, gray, options.pyramid_levels,
                                                      options.depth_min_m, options.depth_max_m);
    const double window = 0.1 + 2 * volume_->volume().truncation_m();
    const scan::ModelView model =
        scan::RaycastModel(volume_->volume(), rays_, start, depth, window, 1, 2);
    return scan::AlignToReference(frame, model, depth_lens_, start, options, 2);
  }

  const Pose& TruePose() const { return truth_[last_].world_from_cam; }
  const ScanOptions& options() const { return options_; }

 private:
  TempDir dir_;
  std::unique_ptr<Take> take_;
  TakePlan plan_;
  std::vector<StampedPose> truth_;
  CameraModel depth_lens_, color_lens_;
  Pose color_from_depth_ = Pose::Identity();
  cv::Mat rays_;
  ScanOptions options_;
  Box bounds_;
  std::unique_ptr<TsdfVolume> volume_;
  int last_ = 0;
};

// Translation (metres) and rotation (degrees) between two world_from_cam poses.
std::pair<double, double> PoseError(const Pose& estimate, const Pose& truth) {
  const Pose error = truth.inverse() * estimate;
  return {error.translation().norm(), RotationAngleDeg(error.linear())};
}

// The camera moved by 2 cm and 1 degree, in its own frame (right multiplication).
Pose Perturbed(const Pose& world_from_cam) {
  Vector6d twist;
  twist << 0.012, -0.010, 0.012, 0.010, -0.008, 0.012;
  return world_from_cam * scan::ExpTwist(twist);
}

class ScanTrackTest : public ::testing::TestWithParam<double> {};

TEST_P(ScanTrackTest, AFrameAtItsTruePoseStaysThere) {
  const TrackerFixture fixture(160, 120, 0.02, 4);
  ScanOptions options = fixture.options();
  options.photometric_weight_m = GetParam();
  const scan::AlignResult aligned = fixture.Align(fixture.TruePose(), options);
  const auto [metres, degrees] = PoseError(aligned.world_from_cam, fixture.TruePose());
  std::printf("from the true pose: %.2f mm, %.3f deg; %.0f%% paired, RMS %.2f mm\n", 1e3 * metres,
              degrees, 100 * aligned.inlier_fraction, 1e3 * aligned.residual_m);
  // Most points pair (not all: the frame sees a little the model has not, and rays that graze
  // the model's edges find no normal there); the RMS is the depth noise (7 mm at 2.4 m) less
  // what the pyramid's averaging removes.
  EXPECT_GT(aligned.inlier_fraction, 0.6);
  EXPECT_LT(aligned.residual_m, 0.006);
  // An eighth of a voxel, a tenth of a degree (a pixel is 0.4 degree).
  EXPECT_LT(metres, 0.0025) << degrees << " deg";
  EXPECT_LT(degrees, 0.1) << metres << " m";
}

TEST_P(ScanTrackTest, AFrameMovedByASmallMotionComesBack) {
  const TrackerFixture fixture(160, 120, 0.02, 4);
  ScanOptions options = fixture.options();
  options.photometric_weight_m = GetParam();
  const Pose start = Perturbed(fixture.TruePose());
  const auto [start_m, start_deg] = PoseError(start, fixture.TruePose());
  ASSERT_GT(start_m, 0.015);
  ASSERT_GT(start_deg, 0.9);
  const scan::AlignResult aligned = fixture.Align(start, options);
  const auto [metres, degrees] = PoseError(aligned.world_from_cam, fixture.TruePose());
  std::printf("from %.1f mm, %.2f deg off: %.2f mm, %.3f deg; %.0f%% paired, RMS %.2f mm\n",
              1e3 * start_m, start_deg, 1e3 * metres, degrees, 100 * aligned.inlier_fraction,
              1e3 * aligned.residual_m);
  // The model is raycast from the wrong pose, so fewer of its pixels match the frame.
  EXPECT_GT(aligned.inlier_fraction, 0.55);
  EXPECT_LT(metres, 0.003) << degrees << " deg";
  EXPECT_LT(degrees, 0.1) << metres << " m";
}

// A start whose rotation carries rounding away from orthonormal (as a prediction composed of
// poses and their transposed inverses did, compounding frame after frame) comes back as a
// rotation: the tracker's pose is what the next prediction is made of.
TEST(ScanTrackOrthonormalTest, AlignedPoseIsARotationWhateverTheStartCarries) {
  const TrackerFixture fixture(160, 120, 0.02, 4);
  Pose start = fixture.TruePose();
  start.linear() *= 1 + 1e-6;
  const scan::AlignResult aligned = fixture.Align(start, fixture.options());
  const Eigen::Matrix3d rotation = aligned.world_from_cam.linear();
  EXPECT_LT((rotation.transpose() * rotation - Eigen::Matrix3d::Identity()).norm(), 1e-12);
  EXPECT_NEAR(rotation.determinant(), 1.0, 1e-12);
  const auto [metres, degrees] = PoseError(aligned.world_from_cam, fixture.TruePose());
  EXPECT_LT(metres, 0.0025) << degrees << " deg";
}

INSTANTIATE_TEST_SUITE_P(GeometryAndColour, ScanTrackTest, ::testing::Values(0.0, 0.02),
                         [](const ::testing::TestParamInfo<double>& info) {
                           return info.param > 0 ? std::string("Photometric")
                                                 : std::string("IcpOnly");
                         });

}  // namespace
}  // namespace holocap
