// Splat training on synthetic scenes whose truth is itself a set of Gaussians, rendered into a
// ring of pinhole cameras: the stiff cases (one camera, an empty seed, an empty frame, a camera
// inside the cloud, Gaussians collapsing to a plane, a learning rate 100x too high, a subject
// leaving the volume). Budgets are in iterations: nothing depends on the machine's speed.
#include <gtest/gtest.h>

#include <unistd.h>
#include <array>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <opencv2/imgproc.hpp>
#include <random>

#include "avatar/image_metrics.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/report.h"
#include "neural/neural.h"
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
// `stripes`: the same Gaussians in colour bands a few of them wide (a motion that is seen).
splat::Gaussians Truth(int count, double radius = 0.3, bool planar = false, bool detailed = false,
                       bool stripes = false) {
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
      const double frequency = detailed ? 25 : 8;
      const double shade = detailed || stripes
                               ? 0.45 * std::copysign(1.0, std::sin(frequency * p[(a + 1) % 3]))
                               : 0.4 * p[(a + 1) % 3] / radius;
      g.sh[3 * i + a] = static_cast<float>(shade / 0.2820948);
    }
    g.rotation[4 * static_cast<size_t>(i)] = 1;
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
  bool stripes = false;        // the usual Gaussians in bands of colour
  double box_half_m = 0.5;     // the volume
  Eigen::Vector3d shift = Eigen::Vector3d::Zero();   // the truth and the seed moved by this
  int frames = 1;                                    // a dynamic take: frames after the first
  Eigen::Vector3d motion = Eigen::Vector3d::Zero();  // move the truth by this per frame
  double turn_rad = 0;                               // and turn it about z by this per frame
  double scale = 1;  // the whole scene (subject, cameras, volume, seed) this many times larger
};

// The truth of frame `frame`: moved and turned as the spec says.
splat::Gaussians Moved(const splat::Gaussians& truth, const SceneSpec& spec, int frame) {
  splat::Gaussians moved = truth;
  const Eigen::Matrix3d turn =
      Eigen::AngleAxisd(spec.turn_rad * frame, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  for (int64_t i = 0; i < truth.size(); ++i) {
    const Eigen::Vector3d p(truth.position[3 * i], truth.position[3 * i + 1],
                            truth.position[3 * i + 2]);
    const Eigen::Vector3d q = turn * p + spec.shift + frame * spec.motion;
    for (int a = 0; a < 3; ++a) moved.position[3 * i + a] = static_cast<float>(q[a]);
  }
  return moved;
}

// The seed: the truth's positions, off by a few centimetres, in grey.
SplatSeed SeedOf(const splat::Gaussians& truth, uint64_t seed, double scale = 1) {
  SplatSeed out;
  std::mt19937_64 rng(seed);
  std::normal_distribution<float> noise(0.0f, static_cast<float>(0.02 * scale));
  for (int64_t i = 0; i < truth.size(); i += 2) {
    out.points.emplace_back(truth.position[3 * i] + noise(rng),
                            truth.position[3 * i + 1] + noise(rng),
                            truth.position[3 * i + 2] + noise(rng));
    out.colors.emplace_back(0.5f, 0.5f, 0.5f);
  }
  out.spacing_m = 0.05 * scale;
  out.source = "test";
  return out;
}

SplatScene MakeScene(const SceneSpec& spec) {
  splat::Gaussians still =
      Truth(spec.detailed ? 1600 : 400, 0.3, spec.planar, spec.detailed, spec.stripes);
  for (float& p : still.position) p = static_cast<float>(p * spec.scale);
  for (float& s : still.log_scale) s += static_cast<float>(std::log(spec.scale));
  const splat::Gaussians truth = Moved(still, spec, 0);
  SplatScene scene;
  const double box_half_m = spec.box_half_m * spec.scale;
  scene.box = Box{Eigen::Vector3d::Constant(-box_half_m), Eigen::Vector3d::Constant(box_half_m)};
  const cv::Mat background(kSide, kSide, CV_32FC3, cv::Scalar(0.2, 0.25, 0.15));
  scene.later_frames.resize(spec.frames - 1);
  for (int c = 0; c < spec.cameras; ++c) {
    const double angle = 2 * M_PI * c / spec.cameras;
    const Eigen::Vector3d center =
        spec.scale * Eigen::Vector3d(2.0 * std::cos(angle), 2.0 * std::sin(angle),
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
    for (int f = 1; f < spec.frames; ++f) {
      SplatFrame& frame = scene.later_frames[f - 1];
      const SplatRender moved = RenderSplats(Moved(still, spec, f), view.camera, background, 0);
      frame.set = f;
      frame.images.emplace_back();
      moved.color.convertTo(frame.images.back(), CV_8UC3, 255.0);
      frame.masks.push_back(moved.alpha > 0.5);
    }
    scene.views.push_back(view);
  }
  scene.seed = SeedOf(truth, 3, spec.scale);
  for (int f = 1; f < spec.frames; ++f)
    scene.later_frames[f - 1].seed = SeedOf(Moved(still, spec, f), 3 + f);
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

// A take whose silhouettes are the frames' own alpha is also scored on white, as alpha datasets
// publish: the held-out render composited on white against the captured image composited on
// white by its alpha. Computed here from the saved model rendered over white; a take without
// alpha has no such score.
TEST(SplatTrain, AlphaTakeIsScoredOnWhite) {
  SplatScene scene = MakeScene({});
  const cv::Mat dark(kSide, kSide, CV_32FC3, cv::Scalar(0.2, 0.25, 0.15));
  const splat::Gaussians truth = Truth(400);
  for (auto& view : scene.views) {
    RenderSplats(truth, view.camera, dark, 0).alpha.convertTo(view.mask, CV_8U, 255.0);
  }
  scene.alpha_masks = true;
  Report report("train splat");
  const SplatSummary summary = TrainSplatsOn(scene, Dir("on_white"), TestOptions(100), &report);
  ASSERT_TRUE(summary.IsUsable()) << summary.message;
  ASSERT_TRUE(std::isfinite(summary.heldout_psnr_white_db)) << summary.message;
  EXPECT_EQ(report.json()["metrics"]["heldout_psnr_white_db"], summary.heldout_psnr_white_db);
  EXPECT_NE(summary.message.find("on white"), std::string::npos) << summary.message;
  const SplatModel model = SplatModel::Load(Path("on_white"));
  const cv::Mat white(kSide, kSide, CV_32FC3, cv::Scalar::all(1.0));
  double mse = 0;
  int heldout = 0;
  for (const auto& view : scene.views) {
    if (!view.heldout) continue;
    cv::Mat predicted, truth_image, coverage, coverage3, truth_white;
    cv::min(
        cv::max(RenderSplats(model.gaussians, view.camera, white, model.gaussians.sh_degree).color,
                0.0),
        1.0, predicted);
    view.image.convertTo(truth_image, CV_32FC3, 1.0 / 255.0);
    view.mask.convertTo(coverage, CV_32F, 1.0 / 255.0);
    cv::cvtColor(coverage, coverage3, cv::COLOR_GRAY2BGR);
    truth_white = truth_image.mul(coverage3) + (cv::Scalar::all(1.0) - coverage3);
    mse += std::pow(10.0, -PsnrDb(predicted, truth_white) / 10.0);
    ++heldout;
  }
  ASSERT_GT(heldout, 0);
  EXPECT_NEAR(summary.heldout_psnr_white_db, -10.0 * std::log10(mse / heldout), 0.01);
  const SplatSummary plain = TrainSplatsOn(MakeScene({}), Dir("not_alpha"), TestOptions(1));
  EXPECT_FALSE(std::isfinite(plain.heldout_psnr_white_db));
  EXPECT_EQ(plain.message.find("on white"), std::string::npos) << plain.message;
}

// An alpha take whose frames also show their surroundings (bands of colour that the view's
// uniform background does not hold), as a render or a matted capture does. Trained over a
// random colour each iteration, composited by the alpha, the splats learn what the alpha holds
// and nothing else: a Gaussian outside it is wrong against every colour, so the held-out
// coverage outside the alpha stays near zero and the subject on white is as good as the alpha
// allows. Trained over the view's background, Gaussians grow to stand for the surroundings
// and show on white.
TEST(SplatTrain, AlphaTakeLearnsOnlyWhatTheAlphaHolds) {
  const splat::Gaussians truth = Truth(400);
  SplatScene scene = MakeScene({});
  for (auto& view : scene.views) {
    cv::Mat surroundings(kSide, kSide, CV_32FC3);
    for (int y = 0; y < kSide; ++y) {
      for (int x = 0; x < kSide; ++x) {
        surroundings.at<cv::Vec3f>(y, x) =
            cv::Vec3f(0.5f + 0.4f * std::sin(0.4f * x), 0.5f + 0.4f * std::cos(0.3f * y),
                      0.5f + 0.4f * std::sin(0.25f * (x + y)));
      }
    }
    const SplatRender render = RenderSplats(truth, view.camera, surroundings, 0);
    render.color.convertTo(view.image, CV_8UC3, 255.0);
    render.alpha.convertTo(view.mask, CV_8U, 255.0);
  }
  scene.alpha_masks = true;
  // Held-out coverage outside the alpha: the mean rendered alpha where the frame's is zero.
  auto outside = [&](const std::string& name) {
    const SplatModel model = SplatModel::Load(Path(name));
    double sum = 0;
    int count = 0;
    for (const auto& view : scene.views) {
      if (!view.heldout) continue;
      const cv::Mat alpha =
          RenderSplats(model.gaussians, view.camera, cv::Mat(kSide, kSide, CV_32FC3, 0.0), 1).alpha;
      for (int y = 0; y < kSide; ++y) {
        for (int x = 0; x < kSide; ++x) {
          if (view.mask.at<uint8_t>(y, x) != 0) continue;
          sum += alpha.at<float>(y, x);
          ++count;
        }
      }
    }
    return sum / std::max(count, 1);
  };
  SplatOptions options = TestOptions(300);
  Report report("train splat");
  const SplatSummary random = TrainSplatsOn(scene, Dir("random_background"), options, &report);
  ASSERT_TRUE(random.IsUsable()) << random.message;
  EXPECT_NE(report.json()["plan"]["training_background"].get<std::string>().find("random"),
            std::string::npos);
  options.random_background = false;
  const SplatSummary captured = TrainSplatsOn(scene, Dir("view_background"), options);
  ASSERT_TRUE(captured.IsUsable()) << captured.message;
  const double random_outside = outside("random_background");
  const double captured_outside = outside("view_background");
  std::printf(
      "coverage outside the alpha %.4f (random) %.4f (view's background); on white %.2f "
      "and %.2f dB\n",
      random_outside, captured_outside, random.heldout_psnr_white_db,
      captured.heldout_psnr_white_db);
  EXPECT_LT(random_outside, 0.01) << "captured: " << captured_outside;
  EXPECT_GT(random.heldout_psnr_white_db, captured.heldout_psnr_white_db + 1)
      << "coverage outside " << random_outside << " against " << captured_outside;
}

// The same scene 20 times smaller (a 3 cm subject seen from 10 cm, the seed's spacing and
// noise, the volume and the cameras alike): the scale bounds and the split and prune sizes
// follow the view (pixels), so it trains as the full-size scene does in the same iterations,
// to the same held-out PSNR within 0.3 dB (what float rounding of the smaller coordinates
// leaves after 200 iterations), with the same bounds in pixels.
TEST(SplatTrain, SceneTwentyTimesSmallerTrainsAlike) {
  SceneSpec small;
  small.scale = 0.05;
  const SplatSummary full = TrainSplatsOn(MakeScene({}), Dir("full_size"), TestOptions(200));
  const SplatSummary scaled = TrainSplatsOn(MakeScene(small), Dir("small"), TestOptions(200));
  ASSERT_TRUE(full.IsUsable()) << full.message;
  ASSERT_TRUE(scaled.IsUsable()) << scaled.message;
  std::printf("full size: %s\n1/20: %s\n", full.message.c_str(), scaled.message.c_str());
  EXPECT_NEAR(scaled.heldout_psnr_fg_db, full.heldout_psnr_fg_db, 0.3);
  EXPECT_NEAR(scaled.heldout_psnr_db, full.heldout_psnr_db, 0.3);
  EXPECT_GT(scaled.heldout_psnr_fg_db, scaled.background_psnr_fg_db + 5);
  for (int k = 0; k < 2; ++k) {
    EXPECT_NEAR(scaled.plan["scale_bounds_px"][k].get<double>(),
                full.plan["scale_bounds_px"][k].get<double>(), 1e-6);
    EXPECT_NEAR(scaled.plan["scale_bounds_m"][k].get<double>(),
                0.05 * full.plan["scale_bounds_m"][k].get<double>(),
                1e-6 * full.plan["scale_bounds_m"][k].get<double>());
  }
  EXPECT_NEAR(scaled.plan["split_above_px"].get<double>(),
              full.plan["split_above_px"].get<double>(), 1e-6);
}

// A pixel budget of a quarter of the views: the first half of the iterations draw them halved
// (32 x 32), the rest at full size, as the plan's schedule says; the subject is still learned.
TEST(SplatTrain, PixelBudgetDrawsHalvedViewsFirst) {
  SplatOptions options = TestOptions(200);
  options.pixel_budget = kSide * kSide / 4;
  const SplatSummary summary = TrainSplatsOn(MakeScene({}), Dir("budget"), options);
  ASSERT_TRUE(summary.IsUsable()) << summary.message;
  const nlohmann::json& schedule = summary.plan["resolution"]["schedule"];
  ASSERT_EQ(schedule.size(), 2u) << summary.plan["resolution"].dump();
  EXPECT_EQ(schedule[0]["width"].get<int>(), kSide / 2);
  EXPECT_EQ(schedule[1]["width"].get<int>(), kSide);
  EXPECT_DOUBLE_EQ(schedule[1]["from_fraction"].get<double>(), 0.5);
  // 100 iterations of 32 x 32 pixels and 100 of 64 x 64.
  EXPECT_NEAR(summary.profile["pixels_per_iteration"].get<double>(),
              0.5 * (kSide * kSide / 4.0 + kSide * kSide), 1e-6);
  EXPECT_EQ(summary.profile["iterations"].get<int64_t>(), 200);
  EXPECT_GT(summary.heldout_psnr_fg_db, summary.background_psnr_fg_db + 5) << summary.message;
}

// A CPU budget counts what loading and seeding spent: a seed that took it all leaves frame 0
// no iteration (the iteration cap only stops a run that ignores it), and the seconds are
// reported apart.
TEST(SplatTrain, CpuBudgetIncludesTheSeed) {
  SplatScene scene = MakeScene({});
  scene.load_cpu_s = 1000;
  SplatOptions options = TestOptions(200);
  options.minutes = 1;
  options.cpu_minutes = 10;  // far more than 200 iterations of this scene take on any host
  Report report("train splat");
  const SplatSummary spent = TrainSplatsOn(scene, Dir("cpu_spent"), options, &report);
  EXPECT_EQ(spent.iterations, 0) << spent.message;
  EXPECT_EQ(spent.cpu_s_seed, 1000);
  EXPECT_EQ(report.json()["metrics"]["cpu_s_budget"], 600.0);
  // The same budget with a seed that spent nothing trains until the cap.
  scene.load_cpu_s = 0;
  const SplatSummary trained = TrainSplatsOn(scene, Dir("cpu_left"), options);
  EXPECT_EQ(trained.iterations, 200) << trained.message;
  EXPECT_GT(trained.cpu_s_training, 0);
  EXPECT_LT(trained.cpu_s_seed + trained.cpu_s_training, 600) << "the budget was not the bound";
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

// A rate 100x too high flips opacities at every step (Adam moves each parameter by about its
// rate) while the loss, high from the start, need not double: the guard catches the step, restores
// the last snapshot and halves the rates until a step is sane, and the run ends usable, close to
// one at the right rate. A rate 10^4 x too high never ends as a usable result.
TEST(SplatTrain, LearningRateFarTooHighIsCaughtByTheGuard) {
  SceneSpec spec;
  spec.detailed = true;
  const SplatScene scene = MakeScene(spec);
  SplatOptions options = TestOptions(120);
  const SplatSummary right = TrainSplatsOn(scene, Dir("lr1"), options);
  ASSERT_TRUE(right.IsUsable()) << right.message;
  EXPECT_EQ(right.divergences, 0) << right.message;
  options.max_divergences = 30;
  options.learning_rate = 100;
  Report report("train splat");
  const SplatSummary high = TrainSplatsOn(scene, Dir("lr100"), options, &report);
  ASSERT_TRUE(high.IsUsable()) << high.message;
  // 100 x 0.05 = 5 logits a step: three halvings bring it under 1.
  EXPECT_GE(high.divergences, 3) << high.message;
  double last_scale = 1;
  for (const auto& point : report.json()["series"])
    if (point["metric"] == "divergence_lr_scale") last_scale = point["value"];
  EXPECT_LE(last_scale, 0.125);
  EXPECT_TRUE(std::isfinite(high.heldout_psnr_db));
  EXPECT_EQ(high.pruned_degenerate, 0);
  EXPECT_GT(high.heldout_psnr_fg_db, high.background_psnr_fg_db + 1) << high.message;
  EXPECT_GT(high.heldout_psnr_db, right.heldout_psnr_db - 2)
      << "rate 100x: " << high.heldout_psnr_db << " dB, right rate " << right.heldout_psnr_db;
  options.learning_rate = 1e4;
  options.max_divergences = 5;
  const SplatSummary runaway = TrainSplatsOn(scene, Dir("lr10000"), options);
  EXPECT_GE(runaway.divergences, 1) << runaway.message;
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
  const double grow = 0.05 * scene.box.size().norm();
  for (int64_t i = 0; i < model.gaussians.size(); ++i)
    EXPECT_LE(model.gaussians.position[3 * i], 0.5 + grow + 0.05) << "Gaussian " << i;
}

// A dynamic take: the subject moves 3 cm and turns 0.06 rad per frame.
SceneSpec Moving(int frames) {
  SceneSpec spec;
  spec.frames = frames;
  spec.motion = Eigen::Vector3d(0.05, 0.03, 0);
  spec.turn_rad = 0.1;
  return spec;
}

// The held-out PSNR (as the trainer scores it: the whole image, or inside the silhouettes grown
// by 3 pixels) of `gaussians` against frame `frame`'s images.
double HeldoutPsnr(const splat::Gaussians& gaussians, const SplatScene& scene, int frame,
                   bool subject = false) {
  double mse = 0;
  int heldout = 0;
  for (size_t v = 0; v < scene.views.size(); ++v) {
    const SplatView& view = scene.views[v];
    if (!view.heldout) continue;
    cv::Mat background, predicted, truth;
    view.background.convertTo(background, CV_32FC3, 1.0 / 255.0);
    cv::min(cv::max(RenderSplats(gaussians, view.camera, background, 1).color, 0.0), 1.0,
            predicted);
    (frame == 0 ? view.image : scene.later_frames[frame - 1].images[v])
        .convertTo(truth, CV_32FC3, 1.0 / 255.0);
    cv::Mat mask;
    if (subject) {
      cv::dilate(frame == 0 ? view.mask : scene.later_frames[frame - 1].masks[v], mask, cv::Mat(),
                 cv::Point(-1, -1), 3);
    }
    mse += std::pow(10.0, -PsnrDb(predicted, truth, mask) / 10.0);
    ++heldout;
  }
  return -10 * std::log10(mse / heldout);
}

TEST(SplatDynamic, LaterFrameFromThePreviousNearsScratchInFewerIterations) {
  const SplatScene moving = MakeScene(Moving(2));
  SplatOptions options = TestOptions(150);
  options.frame_iterations = 100;
  options.frame_minutes = 0;
  Report report("train splat");
  const SplatSummary dynamic = TrainSplatsOn(moving, Dir("dynamic"), options, &report);
  ASSERT_TRUE(dynamic.IsUsable()) << dynamic.message;
  ASSERT_TRUE(dynamic.temporal);
  ASSERT_EQ(dynamic.frames.size(), 2u);
  const SplatFrameSummary& later = dynamic.frames[1];
  EXPECT_EQ(later.iterations, 100);
  // New surface is added only where it asked (lay beyond the frame before's Gaussians), within
  // the cap, and the report says whether the cap bit.
  EXPECT_LE(later.added_surface, later.surface_uncovered);
  EXPECT_LE(later.added, options.max_added_per_frame);
  EXPECT_EQ(later.add_cap_reached, later.added >= options.max_added_per_frame);
  // Frame 1 from scratch: its own seed, the whole frame-0 budget.
  SplatScene scratch_scene = moving;
  scratch_scene.seed = moving.later_frames[0].seed;
  for (size_t v = 0; v < scratch_scene.views.size(); ++v) {
    scratch_scene.views[v].image = moving.later_frames[0].images[v];
    scratch_scene.views[v].mask = moving.later_frames[0].masks[v];
  }
  scratch_scene.later_frames.clear();
  const SplatSummary scratch = TrainSplatsOn(scratch_scene, Dir("scratch"), TestOptions(150));
  ASSERT_TRUE(scratch.IsUsable()) << scratch.message;
  EXPECT_LT(later.iterations, scratch.iterations);
  EXPECT_GT(later.heldout_psnr_db, scratch.heldout_psnr_db - 1.0)
      << "from the previous frame " << later.heldout_psnr_db << " dB, from scratch "
      << scratch.heldout_psnr_db << " dB";
  // The motion was learned: the Gaussians' opacity-weighted centre moved with the subject, and
  // frame 0's Gaussians as they were score lower on frame 1.
  const SplatModel model = SplatModel::Load(Path("dynamic"));
  auto centre = [](const splat::Gaussians& g) {
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    double weight = 0;
    for (int64_t i = 0; i < g.size(); ++i) {
      const double w = 1 / (1 + std::exp(-g.opacity[i]));
      sum += w * Eigen::Vector3d(g.position[3 * i], g.position[3 * i + 1], g.position[3 * i + 2]);
      weight += w;
    }
    return Eigen::Vector3d(sum / weight);
  };
  const Eigen::Vector3d moved = centre(model.Frame(Path("dynamic"), 1)) - centre(model.gaussians);
  const Eigen::Vector3d motion = Moving(2).motion;
  EXPECT_GT(moved.dot(motion) / motion.squaredNorm(), 0.6) << moved.transpose();
  EXPECT_LT((moved - motion).norm(), 0.5 * motion.norm()) << moved.transpose();
  const double unmoved = HeldoutPsnr(model.gaussians, moving, 1);
  EXPECT_GT(later.heldout_psnr_db, unmoved + 0.5)
      << "trained " << later.heldout_psnr_db << " dB, frame 0 as it was " << unmoved << " dB";
  // Scored at once, in the report.
  ASSERT_EQ(report.json()["metrics"]["frames"].size(), 2u);
  int per_frame = 0;
  for (const auto& point : report.json()["series"])
    per_frame += point["metric"] == "frame_heldout_psnr_db";
  EXPECT_EQ(per_frame, 2);
}

// How far each surviving Gaussian's motion from frame 0 to frame 1 strays from the mean motion
// of the survivors near it (cells of a tenth of the scene's box a side): RMS, metres.
double MotionStray(const fs::path& dir, const Box& box) {
  const SplatModel model = SplatModel::Load(dir);
  const splat::Gaussians& before = model.gaussians;
  const splat::Gaussians after = model.Frame(dir, 1);
  const std::vector<int64_t> origin = SplatDeltaOrigins(ReadFileToString(SplatDeltaFile(dir, 1)));
  std::map<std::array<int, 3>, std::pair<Eigen::Vector3d, int>> cells;
  std::vector<std::pair<std::array<int, 3>, Eigen::Vector3d>> moves;
  for (int64_t i = 0; i < after.size(); ++i) {
    const int64_t from = origin[i];
    if (from < 0) continue;
    const Eigen::Vector3d p0(before.position[3 * from], before.position[3 * from + 1],
                             before.position[3 * from + 2]);
    const Eigen::Vector3d p1(after.position[3 * i], after.position[3 * i + 1],
                             after.position[3 * i + 2]);
    std::array<int, 3> cell;
    for (int a = 0; a < 3; ++a)
      cell[a] = static_cast<int>(std::floor(10 * (p0[a] - box.min[a]) / box.size()[a]));
    auto& [sum, count] = cells[cell];
    if (count == 0) sum.setZero();
    sum += p1 - p0;
    ++count;
    moves.emplace_back(cell, p1 - p0);
  }
  double squared = 0;
  for (const auto& [cell, move] : moves) {
    const auto& [sum, count] = cells.at(cell);
    squared += (move - sum / count).squaredNorm();
  }
  return std::sqrt(squared / static_cast<double>(std::max<size_t>(1, moves.size())));
}

// A later frame's motion is a field over the box (3DGStream's deformation): the Gaussians of a
// neighbourhood move together, where each learning its own motion at the later frame's rate
// wanders on its own; the field follows the subject as well.
TEST(SplatDynamic, LaterFramesMoveTheGaussiansTogetherByAField) {
  const SplatScene moving = MakeScene(Moving(2));
  SplatOptions options = TestOptions(150);
  options.frame_iterations = 100;
  options.frame_minutes = 0;
  // No densification in frame 1: a split Gaussian's half jumps by its size, whatever moved it.
  options.frame_densify_every = 1000;
  const SplatSummary field = TrainSplatsOn(moving, Dir("field"), options);
  ASSERT_TRUE(field.IsUsable()) << field.message;
  options.frame_motion_spacings = 0;
  const SplatSummary own = TrainSplatsOn(moving, Dir("own"), options);
  ASSERT_TRUE(own.IsUsable()) << own.message;
  // The plan says which motion the later frames learned.
  ASSERT_TRUE(field.plan.contains("later_frame_motion")) << field.plan.dump();
  EXPECT_GT(field.plan["later_frame_motion"]["node_spacing_m"].get<double>(), 0);
  EXPECT_EQ(own.plan["later_frame_motion"]["model"],
            "each Gaussian its own (--frame-motion-spacings 0)");
  const double field_stray = MotionStray(Path("field"), moving.box);
  const double own_stray = MotionStray(Path("own"), moving.box);
  EXPECT_LT(field_stray, 0.5 * own_stray)
      << "field " << 1e3 * field_stray << " mm, each its own " << 1e3 * own_stray << " mm";
  EXPECT_GT(field.frames[1].heldout_psnr_db, own.frames[1].heldout_psnr_db - 1.0)
      << "field " << field.frames[1].heldout_psnr_db << " dB, each its own "
      << own.frames[1].heldout_psnr_db << " dB";
  const double unmoved = HeldoutPsnr(SplatModel::Load(Path("field")).gaussians, moving, 1);
  EXPECT_GT(field.frames[1].heldout_psnr_db, unmoved + 0.5)
      << "trained " << field.frames[1].heldout_psnr_db << " dB, frame 0 as it was " << unmoved;
}

TEST(SplatDynamic, DeltasStayWithinTheirBoundAndPlayBackAsTrained) {
  const SplatScene moving = MakeScene(Moving(3));
  SplatOptions options = TestOptions(120);
  options.frame_iterations = 30;
  options.frame_minutes = 0;
  options.max_frame_megabytes = 0.004;  // 4 kB: far below the raw delta
  const SplatSummary summary = TrainSplatsOn(moving, Dir("bounded"), options);
  ASSERT_TRUE(summary.IsUsable()) << summary.message;
  ASSERT_EQ(summary.frames.size(), 3u);
  int coarsened = 0;
  for (size_t f = 1; f < summary.frames.size(); ++f) {
    EXPECT_LE(summary.frames[f].megabytes, options.max_frame_megabytes) << "frame " << f;
    EXPECT_GT(summary.frames[f].megabytes, 0) << "frame " << f;
    EXPECT_LE(fs::file_size(SplatDeltaFile(Path("bounded"), static_cast<int64_t>(f))), 4000u);
    coarsened += summary.frames[f].coarsened;
  }
  EXPECT_GT(coarsened, 0) << "the bound never bit";
  // The last frame rebuilt from frame 0 and the deltas scores what training scored.
  const SplatModel model = SplatModel::Load(Path("bounded"));
  ASSERT_EQ(model.frames, 3);
  EXPECT_EQ(model.frame_sets.size(), 3u);  // the take's frame set of each frame
  const splat::Gaussians last = model.Frame(Path("bounded"), 2);
  EXPECT_EQ(last.size(), summary.frames[2].gaussians);
  EXPECT_NEAR(HeldoutPsnr(last, moving, 2), summary.frames[2].heldout_psnr_db, 1e-3);
  // Frame by frame from the one before, as playback applies them, gives the same frame.
  const splat::Gaussians first = model.Frame(Path("bounded"), 1);
  EXPECT_EQ(model.Frame(Path("bounded"), 2, &first, 1).position, last.position);
}

// A dynamic scene's later frames get their minutes : frame_minutes share of what seeding left
// of a CPU budget: nothing when seeding spent it all.
TEST(SplatDynamic, CpuBudgetSpentLeavesLaterFramesNoIteration) {
  SplatScene scene = MakeScene(Moving(3));
  scene.load_cpu_s = 1000;
  SplatOptions options = TestOptions(100);
  options.minutes = 1;
  options.frame_minutes = 1;
  options.frame_iterations = 100;
  options.cpu_minutes = 1;
  const SplatSummary summary = TrainSplatsOn(scene, Dir("cpu_dynamic"), options);
  ASSERT_EQ(summary.frames.size(), 3u) << summary.message;
  for (const SplatFrameSummary& frame : summary.frames) EXPECT_EQ(frame.iterations, 0);
}

TEST(SplatDynamic, StaticSceneTrainsNothingTemporal) {
  const SplatSummary summary = TrainSplatsOn(MakeScene({}), Dir("static"), TestOptions(30));
  ASSERT_TRUE(summary.IsUsable()) << summary.message;
  EXPECT_FALSE(summary.temporal);
  EXPECT_EQ(summary.frames.size(), 1u);
  EXPECT_FALSE(fs::exists(Path("static") / "deltas"));
  EXPECT_EQ(SplatModel::Load(Path("static")).frames, 1);
}

TEST(SplatDynamic, CorruptDeltaIsRefused) {
  splat::Gaussians previous = Truth(20);
  std::vector<int64_t> origin(20);
  for (int i = 0; i < 20; ++i) origin[i] = i;
  splat::Gaussians next = previous;
  next.position[0] += 0.01f;
  const std::string delta = EncodeSplatDelta(previous, next, origin, SplatDeltaSteps{});
  const splat::Gaussians decoded = ApplySplatDelta(previous, delta);
  EXPECT_NEAR(decoded.position[0], next.position[0], 2.5e-4);
  EXPECT_EQ(CountSplatDelta(delta).changed, 1);
  splat::Gaussians shorter = previous;
  shorter.Resize(19);
  EXPECT_THROW(ApplySplatDelta(shorter, delta), Error);
  EXPECT_THROW(ApplySplatDelta(previous, delta.substr(0, delta.size() / 2)), Error);
}

TEST(SplatDynamic, DeltaNamesWhereEachGaussianComesFrom) {
  const splat::Gaussians previous = Truth(20);
  splat::Gaussians next;
  next.sh_degree = previous.sh_degree;
  std::vector<int64_t> origin;
  for (int64_t i : {1, 2, 5, 19}) {
    next.AppendFrom(previous, i);
    origin.push_back(i);
  }
  next.AppendFrom(previous, 0);  // added again, in full
  origin.push_back(-1);
  const std::string delta = EncodeSplatDelta(previous, next, origin, SplatDeltaSteps{});
  EXPECT_EQ(SplatDeltaOrigins(delta), origin);
  EXPECT_EQ(CountSplatDelta(delta).removed, 16);
  EXPECT_THROW(SplatDeltaOrigins(delta.substr(0, delta.size() / 2)), Error);
}

// A 68 KB delta decompressed to 2.1 GB: what a delta may expand to now follows from its header
// (the previous frame's count, its added Gaussians) and its own size, checked before anything
// is allocated; the error names the file.
TEST(SplatDynamic, ADeltaThatWouldExpandPastItsBytesIsRefusedNamingItsFile) {
  const splat::Gaussians previous = Truth(20);
  splat::Gaussians next = previous;
  std::vector<int64_t> origin(20);
  for (int i = 0; i < 20; ++i) origin[i] = i;
  for (int k = 0; k < 300000; ++k) {  // one Gaussian added 300000 times: zstd folds it away
    next.AppendFrom(previous, 0);
    origin.push_back(-1);
  }
  const std::string delta = EncodeSplatDelta(previous, next, origin, SplatDeltaSteps{});
  ASSERT_LT(delta.size(), 64u << 10);
  const fs::path file = fs::temp_directory_path() / ("holocap-bomb-" + std::to_string(getpid()));
  WriteFileAtomic(file, delta);
  try {
    ApplySplatDeltaFile(previous, file);
    ADD_FAILURE();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("'" + file.string() + "': a splat delta of " +
                                         std::to_string(delta.size()) +
                                         " bytes declares 300000 added Gaussians, more than its "
                                         "bytes can hold"),
              std::string::npos)
        << e.what();
  }
  fs::remove(file);
  // Twenty added Gaussians of trained values are what a frame adds: they decode.
  next = previous;
  origin.resize(20);
  const splat::Gaussians more = Truth(40);
  for (int k = 20; k < 40; ++k) {
    next.AppendFrom(more, k);
    origin.push_back(-1);
  }
  EXPECT_EQ(ApplySplatDelta(previous, EncodeSplatDelta(previous, next, origin, {})).size(), 40);
}

// model.json declaring 2000000000 Gaussians made render take 22 GB: the count is checked
// against gaussians.bin's real size first, and every error names the file.
TEST(SplatModelFile, ACountThatGaussiansBinCannotHoldIsRefusedBeforeAllocating) {
  const fs::path dir = fs::temp_directory_path() / ("holocap-model-" + std::to_string(getpid()));
  SplatModel model;
  model.gaussians = Truth(20);
  model.cameras = {LookAt(Eigen::Vector3d(0, -2, 0), Eigen::Vector3d::Zero())};
  model.box = Box{Eigen::Vector3d::Constant(-1), Eigen::Vector3d::Constant(1)};
  model.Save(dir);
  ASSERT_EQ(SplatModel::Load(dir).gaussians.size(), 20);
  const std::string saved = ReadFileToString(dir / "model.json");
  auto with = [&](const std::string& from, const std::string& to) {
    std::string text = saved;
    text.replace(text.find(from), from.size(), to);
    WriteFileAtomic(dir / "model.json", text);
  };
  auto error = [&] {
    try {
      SplatModel::Load(dir);
    } catch (const Error& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  with("\"gaussians\": 20", "\"gaussians\": 2000000000");
  EXPECT_NE(error().find("model.json: it declares 2000000000 Gaussians"), std::string::npos)
      << error();
  with("\"gaussians\": 20", "\"gaussians\": \"many\"");
  EXPECT_NE(error().find((dir / "model.json").string() + ": [json.exception.type_error"),
            std::string::npos)
      << error();
  fs::remove_all(dir);
}

}  // namespace
}  // namespace holocap
