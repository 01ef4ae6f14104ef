// Splat training on synthetic scenes whose truth is itself a set of Gaussians, rendered into a
// ring of pinhole cameras: the stiff cases (one camera, an empty seed, an empty frame, a camera
// inside the cloud, Gaussians collapsing to a plane, a learning rate 100x too high, a subject
// leaving the volume). Budgets are in iterations: nothing depends on the machine's speed.
#include <gtest/gtest.h>

#include <unistd.h>
#include <cmath>
#include <filesystem>
#include <random>

#include "core/error.h"
#include "core/report.h"
#include "splat/splat.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;

constexpr int kSide = 64;

// A camera at `center` looking at `target`, y roughly down the world's -z.
CameraModel LookAt(const Eigen::Vector3d& center, const Eigen::Vector3d& target) {
  const Eigen::Vector3d z = (target - center).normalized();
  Eigen::Vector3d x = z.cross(Eigen::Vector3d::UnitZ());
  if (x.norm() < 1e-6) x = Eigen::Vector3d::UnitX();
  x.normalize();
  const Eigen::Vector3d y = z.cross(x);
  Eigen::Matrix3d world_from_cam;
  world_from_cam << x, y, z;
  Pose cam_from_world = Pose::Identity();
  cam_from_world.linear() = world_from_cam.transpose();
  cam_from_world.translation() = -world_from_cam.transpose() * center;
  return CameraModel::Pinhole(70, kSide, kSide, cam_from_world);
}

// The truth: opaque Gaussians on a sphere of radius 0.3 m, coloured by where they sit.
splat::Gaussians Truth(int count, double radius = 0.3, bool planar = false, bool detailed = false) {
  std::mt19937_64 rng(7);
  std::normal_distribution<double> normal(0, 1);
  splat::Gaussians g;
  g.sh_degree = 0;
  g.Resize(count);
  for (int i = 0; i < count; ++i) {
    Eigen::Vector3d p(normal(rng), normal(rng), planar ? 0.0 : normal(rng));
    p = radius * p.normalized();
    if (planar) p *= std::sqrt(std::abs(normal(rng)) + 0.1);
    for (int a = 0; a < 3; ++a) {
      g.position[3 * i + a] = static_cast<float>(p[a]);
      g.log_scale[3 * i + a] = std::log(planar && a == 2 ? 1e-4f : (detailed ? 0.025f : 0.06f));
      const double shade = detailed ? 0.45 * std::copysign(1.0, std::sin(25 * p[(a + 1) % 3]))
                                    : 0.4 * p[(a + 1) % 3] / radius;
      g.sh[3 * i + a] = static_cast<float>(shade / 0.2820948);
    }
    g.rotation[4 * i] = 1;
    g.opacity[i] = 3;
  }
  return g;
}

struct SceneSpec {
  int cameras = 8;
  int heldout = 2;
  bool empty_frame = false;    // the subject is absent from every image
  bool camera_inside = false;  // the first training camera sits at the cloud's centre
  bool planar = false;         // the subject is a flat disc
  bool detailed = false;       // small Gaussians in sharply changing colours
  double box_half_m = 0.5;     // the volume
  Eigen::Vector3d shift = Eigen::Vector3d::Zero();  // the truth and the seed moved by this
};

SplatScene MakeScene(const SceneSpec& spec) {
  splat::Gaussians truth = Truth(spec.detailed ? 1600 : 400, 0.3, spec.planar, spec.detailed);
  for (int64_t i = 0; i < truth.size(); ++i)
    for (int a = 0; a < 3; ++a) truth.position[3 * i + a] += static_cast<float>(spec.shift[a]);
  SplatScene scene;
  scene.box = Eigen::AlignedBox3d(Eigen::Vector3d::Constant(-spec.box_half_m),
                                  Eigen::Vector3d::Constant(spec.box_half_m));
  const cv::Mat background(kSide, kSide, CV_32FC3, cv::Scalar(0.2, 0.25, 0.15));
  for (int c = 0; c < spec.cameras; ++c) {
    const double angle = 2 * M_PI * c / spec.cameras;
    const Eigen::Vector3d center(2.0 * std::cos(angle), 2.0 * std::sin(angle),
                                 spec.planar ? 1.2 : 0.4 * std::sin(3 * angle));
    SplatView view;
    view.name = Cat("cam", c);
    view.camera = spec.camera_inside && c == 0 ? LookAt(Eigen::Vector3d::Zero(), center)
                                               : LookAt(center, Eigen::Vector3d::Zero());
    SplatRender render = RenderSplats(truth, view.camera, background, 0);
    const cv::Mat shown = spec.empty_frame ? background : render.color;
    shown.convertTo(view.image, CV_8UC3, 255.0);
    background.convertTo(view.background, CV_8UC3, 255.0);
    view.mask = spec.empty_frame ? cv::Mat::zeros(kSide, kSide, CV_8UC1) : render.alpha > 0.5;
    view.heldout = c >= spec.cameras - spec.heldout;
    scene.views.push_back(view);
  }
  // The seed: the truth's positions, off by a few centimetres, in grey.
  std::mt19937_64 rng(3);
  std::normal_distribution<float> noise(0.0f, 0.02f);
  for (int64_t i = 0; i < truth.size(); i += 2) {
    scene.seed.points.emplace_back(truth.position[3 * i] + noise(rng),
                                   truth.position[3 * i + 1] + noise(rng),
                                   truth.position[3 * i + 2] + noise(rng));
    scene.seed.colors.emplace_back(0.5f, 0.5f, 0.5f);
  }
  scene.seed.spacing_m = 0.05;
  scene.seed.source = "test";
  return scene;
}

SplatOptions TestOptions(int64_t iterations) {
  SplatOptions options;
  options.minutes = 0;
  options.iterations = iterations;
  options.sh_degree = 1;
  options.sh_degree_every = 100;
  options.eval_every_iterations = 50;
  options.densify_from = 50;
  options.densify_every = 50;
  options.opacity_reset_every = 0;
  options.max_gaussians = 2000;
  options.threads = 2;
  return options;
}

fs::path Path(const std::string& name) {
  return fs::temp_directory_path() / Cat("holocap_splat_test_", ::getpid()) / name;
}
// Removes every test's output once the suite is done.
class RemoveOutputs : public ::testing::Environment {
 public:
  void TearDown() override { fs::remove_all(Path("").parent_path()); }
};
const ::testing::Environment* const kRemoveOutputs =
    ::testing::AddGlobalTestEnvironment(new RemoveOutputs);

// A fresh output directory.
fs::path Dir(const std::string& name) {
  fs::remove_all(Path(name));
  return Path(name);
}

TEST(SplatTrain, LearnsTheSubjectAndBeatsTheBackground) {
  const SplatScene scene = MakeScene({});
  Report report("train splat");
  const SplatSummary start = TrainSplatsOn(scene, Dir("start"), TestOptions(1));
  const SplatSummary summary = TrainSplatsOn(scene, Dir("trained"), TestOptions(200), &report);
  ASSERT_TRUE(summary.IsUsable()) << summary.message;
  EXPECT_EQ(summary.termination, Termination::kNoConvergence);
  EXPECT_GT(summary.heldout_psnr_fg_db, start.heldout_psnr_fg_db + 3) << summary.message;
  EXPECT_GT(summary.heldout_psnr_fg_db, summary.background_psnr_fg_db + 5) << summary.message;
  EXPECT_GT(summary.heldout_ssim, start.heldout_ssim);
  EXPECT_GT(summary.cloned + summary.split, 0) << "densification never ran";
  EXPECT_GT(summary.megabytes, 0);
  // The series of the report, as Neural Volumes writes them.
  int psnr_points = 0;
  for (const auto& point : report.json()["series"])
    psnr_points += point["metric"] == "heldout_psnr_fg_db";
  EXPECT_GE(psnr_points, 5);
  // The saved model renders as the trainer's last state did.
  const SplatModel model = SplatModel::Load(Path("trained"));
  EXPECT_EQ(model.gaussians.size(), summary.gaussians);
}

TEST(SplatTrain, OneCameraTrainsWithoutHeldOutViews) {
  SceneSpec spec;
  spec.cameras = 1;
  spec.heldout = 0;
  const SplatScene scene = MakeScene(spec);
  const SplatSummary start = TrainSplatsOn(scene, Dir("one_start"), TestOptions(1));
  const SplatSummary summary = TrainSplatsOn(scene, Dir("one"), TestOptions(200));
  ASSERT_EQ(summary.termination, Termination::kNoConvergence) << summary.message;
  EXPECT_NE(summary.message.find("no held-out camera"), std::string::npos) << summary.message;
  EXPECT_GT(summary.train_psnr_db, start.train_psnr_db + 3);
}

TEST(SplatTrain, EmptyReconstructionSeedIsDegenerate) {
  SplatScene scene = MakeScene({});
  scene.seed = SplatSeed{};
  scene.seed.source = "hull of set 0: no surface";
  const SplatSummary summary = TrainSplatsOn(scene, Dir("empty_seed"), TestOptions(50));
  EXPECT_EQ(summary.termination, Termination::kDegenerate);
  EXPECT_NE(summary.message.find("seed is empty"), std::string::npos) << summary.message;
  EXPECT_EQ(ExitStatus(summary.termination), 1);
}

TEST(SplatTrain, EmptyFrameIsDegenerate) {
  SceneSpec spec;
  spec.empty_frame = true;
  const SplatSummary summary = TrainSplatsOn(MakeScene(spec), Dir("empty_frame"), TestOptions(50));
  EXPECT_EQ(summary.termination, Termination::kDegenerate) << summary.message;
  EXPECT_NE(summary.message.find("no subject"), std::string::npos) << summary.message;
}

TEST(SplatTrain, CameraInsideTheCloud) {
  SceneSpec spec;
  spec.camera_inside = true;
  const SplatScene scene = MakeScene(spec);
  const SplatSummary summary = TrainSplatsOn(scene, Dir("inside"), TestOptions(200));
  ASSERT_TRUE(summary.IsUsable()) << summary.message;
  EXPECT_GT(summary.heldout_psnr_fg_db, summary.background_psnr_fg_db + 3) << summary.message;
  // The camera at the centre sees Gaussians on every side, half of them behind it.
  splat::ProjectedArrays<float> projected;
  splat::ProjectGaussians(SplatModel::Load(Path("inside")).gaussians,
                          ToPinhole(scene.views[0].camera), splat::RasterOptions{}, &projected);
  EXPECT_GT(projected.culled_near, 0);
}

TEST(SplatTrain, GaussiansCollapsingToAPlaneStopAtTheScaleFloor) {
  SceneSpec spec;
  spec.planar = true;
  const SplatScene scene = MakeScene(spec);
  SplatOptions options = TestOptions(200);
  options.seed_scale_factor = 1e-9;  // every seed starts flat on every axis
  options.min_scale_px = 0.3;
  const SplatSummary summary = TrainSplatsOn(scene, Dir("planar"), options);
  ASSERT_TRUE(summary.IsUsable()) << summary.message;
  EXPECT_GT(summary.floored_scales, 0);
  EXPECT_EQ(summary.pruned_degenerate, 0);
  EXPECT_GT(summary.heldout_psnr_fg_db, summary.background_psnr_fg_db) << summary.message;
  // A flat Gaussian seen exactly edge-on still has a positive definite footprint (the
  // low-pass filter), so nothing is culled as degenerate.
  splat::Gaussians flat;
  flat.sh_degree = 0;
  flat.Resize(1);
  flat.rotation[0] = 1;
  flat.log_scale[0] = flat.log_scale[1] = std::log(0.1f);
  flat.log_scale[2] = -80;
  flat.opacity[0] = 2;
  const CameraModel edge_on = LookAt(Eigen::Vector3d(2, 0, 0), Eigen::Vector3d::Zero());
  splat::ProjectedArrays<float> projected;
  splat::ProjectGaussians(flat, ToPinhole(edge_on), splat::RasterOptions{}, &projected);
  EXPECT_EQ(projected.culled_degenerate, 0);
  EXPECT_GT(projected.radius[0], 0);
  const SplatRender render = RenderSplats(flat, edge_on);
  EXPECT_TRUE(cv::checkRange(render.color));
}

// With Adam and bounded activations a rate 100x too high does not blow the training loss up
// (each step moves a parameter by about its rate; scales and opacities stay inside their
// bounds): the run stays finite, bounded and usable. A rate 10^4 x too high empties the model
// (every opacity driven to its floor and pruned): that run must never end as a usable result,
// whether the guard catches it or the judgement against the background does.
TEST(SplatTrain, LearningRateFarTooHighNeverEndsAsSuccess) {
  SceneSpec spec;
  spec.detailed = true;
  const SplatScene scene = MakeScene(spec);
  SplatOptions options = TestOptions(120);
  options.max_divergences = 30;
  options.learning_rate = 100;
  const SplatSummary high = TrainSplatsOn(scene, Dir("lr100"), options);
  ASSERT_TRUE(high.IsUsable()) << high.message;
  EXPECT_TRUE(std::isfinite(high.heldout_psnr_db));
  EXPECT_EQ(high.pruned_degenerate, 0);
  options.learning_rate = 1e4;
  const SplatSummary runaway = TrainSplatsOn(scene, Dir("lr10000"), options);
  EXPECT_TRUE(runaway.divergences >= 1 || runaway.termination == Termination::kDegenerate)
      << runaway.message;
  EXPECT_FALSE(runaway.divergences == 0 && runaway.IsUsable()) << runaway.message;
}

TEST(SplatTrain, SubjectLeavingTheVolumeIsPrunedAtItsEdge) {
  SceneSpec spec;
  spec.shift = Eigen::Vector3d(0.45, 0, 0);  // half the subject beyond x = 0.5
  const SplatScene scene = MakeScene(spec);
  const SplatSummary summary = TrainSplatsOn(scene, Dir("leaving"), TestOptions(150));
  ASSERT_TRUE(summary.IsUsable()) << summary.message;
  EXPECT_GT(summary.pruned_outside, 0);
  const SplatModel model = SplatModel::Load(Path("leaving"));
  const double grow = 0.05 * scene.box.diagonal().norm();
  for (int64_t i = 0; i < model.gaussians.size(); ++i)
    EXPECT_LE(model.gaussians.position[3 * i], 0.5 + grow + 0.05) << "Gaussian " << i;
}

}  // namespace
}  // namespace holocap
