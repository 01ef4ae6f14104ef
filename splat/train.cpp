// Training splats: one random training view per iteration, L1 + D-SSIM, Adam with per-group
// rates, densification and pruning, held-out cameras evaluated against wall time, and the
// divergence guard (restore the last healthy state, halve the rates).
#include <omp.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <numeric>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <random>
#include <unordered_map>

#include "avatar/avatar.h"
#include "avatar/image_metrics.h"
#include "core/error.h"
#include "core/frame_tasks.h"
#include "core/fs.h"
#include "core/image.h"
#include "core/progress.h"
#include "core/threads.h"
#include "splat/splat.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;
using splat::Gaussians;

constexpr double kShC0 = 0.28209479177387814;
constexpr float kMaxOpacityLogit = 12.0f;

std::vector<float> ToFloat(const cv::Mat& bgr8) {
  cv::Mat f;
  bgr8.convertTo(f, CV_32FC3, 1.0 / 255.0);
  return std::vector<float>(f.ptr<float>(), f.ptr<float>() + f.total() * 3);
}

float Logit(double p) { return static_cast<float>(std::log(p / (1 - p))); }

// Adam's moments of every parameter, laid out as the Gaussians are.
struct Moments {
  Gaussians first, second;
};

// A later frame's translation field (SplatOptions::frame_motion_spacings): nodes `spacing` apart
// from `origin`, `dims` a side, each node's motion learned by Adam from the positional gradients
// of the Gaussians it blends (trilinear weights at each Gaussian's position; points outside the
// grid take its nearest face).
struct MotionField {
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  double spacing = 1;
  std::array<int64_t, 3> dims = {0, 0, 0};
  std::vector<float> first, second, gradient, move;  // 3 a node
  int64_t step = 0;

  bool on() const { return dims[0] > 0; }
  // The grid alone (spacing, origin, dims), nothing allocated.
  void Lay(const Box& box, double node_spacing) {
    const double longest = std::max(box.size().maxCoeff(), 1e-6);
    const Eigen::Vector3d padded = box.size().cwiseMax(longest / 256);
    spacing = std::max({node_spacing > 0 ? node_spacing : longest / 32, longest / 256,
                        std::cbrt(padded.prod() / 2e6)});
    origin = box.min;
    for (int a = 0; a < 3; ++a)
      dims[a] = static_cast<int64_t>(std::floor(box.size()[a] / spacing)) + 2;
  }
  // Nodes `node_spacing` apart covering `box`, the moments zero: at least a 256th of the box's
  // longest side and at most about 2 million nodes (a seed without a spacing: a 32nd).
  void Cover(const Box& box, double node_spacing) {
    Lay(box, node_spacing);
    const size_t values = 3 * static_cast<size_t>(dims[0] * dims[1] * dims[2]);
    first.assign(values, 0);
    second.assign(values, 0);
    gradient.assign(values, 0);
    move.assign(values, 0);
    step = 0;
  }
  // The eight nodes (index of node x, y, z: (x * dims[1] + y) * dims[2] + z) and weights of p.
  void Corners(const float* p, int64_t* node, float* weight) const {
    int64_t base[3];
    float f[3];
    for (int a = 0; a < 3; ++a) {
      const double u = std::clamp((p[a] - origin[a]) / spacing, 0.0, double(dims[a] - 1));
      base[a] = std::min<int64_t>(static_cast<int64_t>(u), dims[a] - 2);
      f[a] = static_cast<float>(u - static_cast<double>(base[a]));
    }
    for (int k = 0; k < 8; ++k) {
      const int64_t x = base[0] + (k & 1), y = base[1] + ((k >> 1) & 1), z = base[2] + (k >> 2);
      node[k] = (x * dims[1] + y) * dims[2] + z;
      weight[k] = ((k & 1) ? f[0] : 1 - f[0]) * (((k >> 1) & 1) ? f[1] : 1 - f[1]) *
                  ((k >> 2) ? f[2] : 1 - f[2]);
    }
  }
  // One Adam step of the nodes on the Gaussians' positional gradients at `rate`, each Gaussian
  // moved by its nodes' blended step.
  void Step(const Gaussians& gradients, float rate, Gaussians* gaussians) {
    std::fill(gradient.begin(), gradient.end(), 0.0f);
    const int64_t n = gaussians->size();
    int64_t node[8];
    float weight[8];
    for (int64_t i = 0; i < n; ++i) {
      Corners(&gaussians->position[3 * i], node, weight);
      for (int k = 0; k < 8; ++k)
        for (int a = 0; a < 3; ++a)
          gradient[3 * node[k] + a] += weight[k] * gradients.position[3 * i + a];
    }
    ++step;
    const float b1 = 0.9f, b2 = 0.999f;
    const float c1 = 1 / (1 - std::pow(b1, static_cast<float>(step)));
    const float c2 = 1 / (1 - std::pow(b2, static_cast<float>(step)));
    for (size_t k = 0; k < gradient.size(); ++k) {
      first[k] = b1 * first[k] + (1 - b1) * gradient[k];
      second[k] = b2 * second[k] + (1 - b2) * gradient[k] * gradient[k];
      move[k] = gradient[k] == 0 && first[k] == 0
                    ? 0.0f
                    : -rate * (first[k] * c1) / (std::sqrt(second[k] * c2) + 1e-15f);
    }
#pragma omp parallel for schedule(static)
    for (int64_t i = 0; i < n; ++i) {
      int64_t at[8];
      float w[8];
      Corners(&gaussians->position[3 * i], at, w);
      float shift[3] = {0, 0, 0};
      for (int k = 0; k < 8; ++k)
        for (int a = 0; a < 3; ++a) shift[a] += w[k] * move[3 * at[k] + a];
      for (int a = 0; a < 3; ++a) gaussians->position[3 * i + a] += shift[a];
    }
  }
};

// Everything the divergence guard restores.
struct Snapshot {
  Gaussians gaussians;
  Moments moments;
  int64_t iteration = 0;
  int64_t adam_step = 0;
  std::vector<int64_t> origin;
};

// The budget of one frame's training and what it may do.
struct FrameBudget {
  int64_t iterations = 0;     // > 0: stop after this many
  double seconds = 0;         // > 0: stop after this long
  bool first = true;          // frame 0: the degree raised progressively, the paper's densification
                              // schedule and opacity resets; later frames: full degree, higher
                              // harmonics frozen, densified every frame_densify_every
  double cpu_deadline_s = 0;  // > 0: stop when the run's CPU clock (Trainer::cpu_) reaches this
};

// Wall seconds of training's stages, summed over the iterations trained (the held-out scoring
// is no part of an iteration). The rasteriser's own stages come from the kernels.
struct StageProfile {
  splat::KernelTimes kernels;
  double projection = 0;     // ProjectGaussians
  double loss = 0;           // L1 + D-SSIM and its gradient
  double parameters = 0;     // ProjectBackward: projected gradients to the raw parameters
  double statistic = 0;      // densification's positional-gradient statistic
  double adam = 0;           // Adam, the parameters' bounds and the finite check
  double densification = 0;  // densify, prune, opacity reset
  double iteration = 0;      // the whole iteration (the rest: snapshots, bookkeeping)
  double pixels = 0;         // drawn, over the iterations (the resolution schedule's)
  int64_t iterations = 0;

  // {"iterations", "iterations_per_s", "stages": [{"stage", "ms_per_iteration", "share"}]}
  nlohmann::json ToJson() const {
    const double n = static_cast<double>(std::max<int64_t>(iterations, 1));
    const std::pair<const char*, double> stages[] = {{"projection", projection},
                                                     {"sort", kernels.sort},
                                                     {"binning", kernels.binning},
                                                     {"forward", kernels.forward},
                                                     {"loss_ssim", loss},
                                                     {"backward", kernels.backward},
                                                     {"reduction", kernels.reduction},
                                                     {"project_backward", parameters},
                                                     {"statistic", statistic},
                                                     {"adam", adam},
                                                     {"densification", densification}};
    nlohmann::json rows = nlohmann::json::array();
    double counted = 0;
    for (const auto& [name, seconds] : stages) {
      counted += seconds;
      rows.push_back({{"stage", name},
                      {"ms_per_iteration", 1e3 * seconds / n},
                      {"share", seconds / std::max(iteration, 1e-12)}});
    }
    rows.push_back({{"stage", "other"},
                    {"ms_per_iteration", 1e3 * std::max(0.0, iteration - counted) / n},
                    {"share", std::max(0.0, iteration - counted) / std::max(iteration, 1e-12)}});
    return {{"iterations", iterations},
            {"seconds", iteration},
            {"pixels_per_iteration", pixels / n},
            {"iterations_per_s", iterations / std::max(iteration, 1e-12)},
            {"stages", rows}};
  }
};

// The mean squared error of a held-out render composited on white against the captured image
// composited on white by its own alpha (`coverage`, 0-255), as alpha datasets are published:
// the render over `background` is its colour plus (1 - alpha) x background, so on white it is
// that plus (1 - alpha) x (1 - background).
double OnWhiteMse(const SplatRender& render, const cv::Mat& background, const cv::Mat& truth,
                  const cv::Mat& coverage) {
  cv::Mat clear, clear3, weight, weight3, on_white, truth_white;
  cv::subtract(cv::Scalar::all(1.0), render.alpha, clear);
  cv::cvtColor(clear, clear3, cv::COLOR_GRAY2BGR);
  on_white = render.color + clear3.mul(cv::Scalar::all(1.0) - background);
  cv::min(cv::max(on_white, 0.0), 1.0, on_white);
  coverage.convertTo(weight, CV_32F, 1.0 / 255.0);
  cv::cvtColor(weight, weight3, cv::COLOR_GRAY2BGR);
  truth_white = truth.mul(weight3) + (cv::Scalar::all(1.0) - weight3);
  return std::pow(10.0, -PsnrDb(on_white, truth_white) / 10.0);
}

// Seconds since `start`, and `start` moved to now.
double Lap(std::chrono::steady_clock::time_point* start) {
  const auto now = std::chrono::steady_clock::now();
  const double seconds = std::chrono::duration<double>(now - *start).count();
  *start = now;
  return seconds;
}

struct Evaluation {
  double psnr_db = 0, psnr_fg_db = 0, background_psnr_fg_db = 0, ssim = 0;
  double psnr_white_db = std::numeric_limits<double>::quiet_NaN();  // on white (alpha takes)
  bool subject_seen = false;  // a held-out silhouette holds any pixel
};

class Trainer {
 public:
  Trainer(const SplatScene& scene, const SplatOptions& options, const fs::path& model_dir)
      : scene_(scene),
        options_(options),
        model_dir_(model_dir),
        rng_(options.seed),
        cpu_(CpuSeconds() - scene.load_cpu_s) {
    for (size_t v = 0; v < scene.views.size(); ++v) {
      const SplatView& view = scene.views[v];
      (view.heldout ? heldout_ : training_).push_back(static_cast<int>(v));
      cameras_.push_back(ToPinhole(view.camera));
      targets_.push_back(ToFloat(view.image));
      backgrounds_.push_back(ToFloat(view.background));
      if (RandomBackground()) coverages_.push_back(CoverageOf(view.mask));
      images_.push_back(&view.image);
      masks_.push_back(&view.mask);
    }
    if (training_.empty()) Fail("no training view: every camera is held out");
    MeasureScene();
    levels_.resize(scene.views.size());
    const SplatView& first = scene.views.front();
    if (options.pixel_budget > 0) {
      while (static_cast<int64_t>(first.image.cols >> start_level_) *
                     (first.image.rows >> start_level_) >
                 options.pixel_budget &&
             (first.image.cols >> (start_level_ + 1)) >= splat::kTileSide)
        ++start_level_;
    }
  }

  SplatSummary Run(Report* report);

  // Per-frame runs (splat.h): the trainer's state after frame 0 that later frames start with.
  nlohmann::json FirstFrameState() const {
    return {{"lr_scale", lr_scale_}, {"reset_done", reset_done_}};
  }
  // Trains later frame `frame` from `base` (its delta's base as decoded, after frame 0 ended in
  // `state`) for `iterations`, with a random stream of its own; its delta is written durably to
  // model_dir/deltas. The frame as decoded is left in gaussians(). FAILURE (no delta) when
  // training diverged more than max_divergences times.
  SplatSummary TrainFromBase(int64_t frame, const Gaussians& base, const nlohmann::json& state,
                             int64_t iterations);
  const Gaussians& gaussians() const { return gaussians_; }
  const StageProfile& profile() const { return profile_; }

 private:
  void TrainFrame(int64_t frame, const FrameBudget& budget, SplatSummary* summary, Report* report);
  void ShowFrame(int64_t frame);
  void ResetMoments();
  int64_t AddNewSurface(const SplatSeed& seed, int64_t* uncovered_count);
  void StoreDelta(int64_t frame, const Gaussians& previous, SplatFrameSummary* stored);
  bool TrainLaterFrame(int64_t frame, const FrameBudget& budget, SplatSummary* summary,
                       Report* report, SplatFrameSummary* scored);
  void TrainLaterFrames(SplatSummary* summary, Report* report);
  SplatFrameSummary ScoreFrame(int64_t frame, double seconds, int64_t iterations);
  void Record(const SplatFrameSummary& frame, SplatSummary* summary, Report* report);
  double Elapsed() const {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
  }
  void MeasureScene();
  double CpuDeadline(int64_t frame) const;
  void Seed(SplatSummary* summary);
  void SeedGaussian(int64_t i, const SplatSeed& seed, size_t s, float log_scale);
  double TrainStep(int active_degree, int view, int level);
  bool AdamStep(double progress, double* opacity_step);
  int64_t BoundGaussian(int64_t i);
  void BoundParameters();
  void ZeroGradient();
  void Densify(SplatSummary* summary);
  void Prune(bool prune_large, SplatSummary* summary);
  void Keep(const std::vector<int64_t>& indices);
  void ResetOpacity();
  Evaluation Evaluate(bool write_images);
  double TrainingPsnr();
  void DescribePlan(SplatSummary* summary) const;
  void Judge(int64_t iteration, SplatSummary* summary) const;
  void Finish(SplatSummary* summary);
  int ActiveDegree(int64_t iteration) const {
    return static_cast<int>(
        std::min<int64_t>(options_.sh_degree, iteration / std::max(1, options_.sh_degree_every)));
  }

  const SplatScene& scene_;
  SplatOptions options_;
  fs::path model_dir_;
  std::mt19937_64 rng_;
  std::vector<int> training_, heldout_;
  std::vector<splat::PinholeCamera> cameras_;
  std::vector<std::vector<float>> targets_, backgrounds_;
  // The views halved `level` times (index level - 1), made when first drawn; a frame shown
  // anew clears them. start_level_: the level training starts at (the pixel budget's).
  struct ViewLevel {
    splat::PinholeCamera camera;
    std::vector<float> target, background, coverage;  // coverage: alpha takes' (0-1)
  };
  bool RandomBackground() const { return scene_.alpha_masks && options_.random_background; }
  static std::vector<float> CoverageOf(const cv::Mat& alpha8) {
    cv::Mat f;
    alpha8.convertTo(f, CV_32F, 1.0 / 255.0);
    return std::vector<float>(f.ptr<float>(), f.ptr<float>() + f.total());
  }
  std::vector<std::vector<float>> coverages_;           // per view at full resolution (alpha takes)
  std::vector<float> mixed_target_, mixed_background_;  // RandomBackground's, per iteration
  std::vector<std::vector<ViewLevel>> levels_;
  int start_level_ = 0;
  const ViewLevel& Level(int v, int level);
  int LevelAt(double fraction) const;
  std::vector<const cv::Mat*> images_, masks_;  // the frame being trained, per view
  std::chrono::steady_clock::time_point start_ = std::chrono::steady_clock::now();
  CpuClock cpu_;                  // since LoadSplatScene began, held-out scoring excluded
  double train_cpu_start_ = 0;    // cpu_ when training began (after the seed)
  int64_t total_iterations_ = 0;  // over the frames before the one being trained
  bool temporal_ = false;         // training a later frame
  int64_t add_room_ = -1;         // Gaussians the frame may still add (-1: no limit but the cap)
  std::vector<int64_t> origin_;   // per Gaussian: its index in the frame before (-1: added)
  SplatModel stored_;             // frame 0 as saved, and the frames written
  bool per_frame_ = false;        // a later frame of a per-frame run (TrainFromBase): its delta
                                  // durable, no model.json or held-out images written
  double extent_ = 1;             // the paper's "cameras extent": 1.1 x the farthest camera from
                                  // their mean centre
  double pixel_m_ = 1e-3;         // a pixel's width at the scene's median distance (metres)
  double view_width_m_ = 1;       // the image's width there: the bounds' unit (SplatOptions)
  double min_log_scale_ = -20, max_log_scale_ = 0;
  Gaussians gaussians_, gradient_;
  Moments moments_;
  MotionField motion_;  // a later frame's (SplatOptions::frame_motion_spacings)
  int64_t adam_step_ = 0;
  double lr_scale_ = 1;
  std::vector<float> grad_accum_;  // densification's statistic, per Gaussian
  std::vector<int32_t> grad_count_;
  int64_t floored_ = 0;
  bool reset_done_ = false;
  bool subject_seen_ = false;  // by the last evaluation's held-out silhouettes
  StageProfile profile_;
  // Scratch of one iteration.
  splat::ProjectedArrays<float> projected_;
  splat::ProjectedGradients<float> projected_gradients_;
  splat::RasterState raster_;
  std::vector<float> image_, dloss_;
};

void Trainer::MeasureScene() {
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const auto& view : scene_.views) mean += view.camera.center_in_world();
  mean /= scene_.views.size();
  double farthest = 0;
  std::vector<double> distances;
  const Eigen::Vector3d subject = scene_.box.center();
  for (const auto& view : scene_.views) {
    farthest = std::max(farthest, (view.camera.center_in_world() - mean).norm());
    distances.push_back((view.camera.center_in_world() - subject).norm());
  }
  // One camera (or cameras at one place) has no spread: the subject's box stands in.
  extent_ = 1.1 * std::max(farthest, 0.5 * scene_.box.size().norm());
  std::nth_element(distances.begin(), distances.begin() + distances.size() / 2, distances.end());
  const double median_distance = distances[distances.size() / 2];
  const double focal = scene_.views.front().camera.intrinsics()[0];
  const int width = scene_.views.front().camera.width();
  pixel_m_ = median_distance / focal;
  view_width_m_ = width * pixel_m_;
  min_log_scale_ = std::log(options_.min_scale_px * pixel_m_);
  max_log_scale_ = std::log(options_.max_scale_view * view_width_m_);
}

// Gaussian i becomes seed point s: isotropic at `log_scale`, the seed's colour as the degree-0
// coefficient, the initial opacity.
void Trainer::SeedGaussian(int64_t i, const SplatSeed& seed, size_t s, float log_scale) {
  const int k = gaussians_.coefficients();
  for (int a = 0; a < 3; ++a) {
    gaussians_.position[3 * i + a] = seed.points[s][a];
    gaussians_.log_scale[3 * i + a] = log_scale;
    gaussians_.sh[(i * k) * 3 + a] = static_cast<float>((seed.colors[s][a] - 0.5) / kShC0);
  }
  gaussians_.rotation[4 * i] = 1;
  gaussians_.opacity[i] = Logit(options_.initial_opacity);
}

// One Gaussian per seed point: isotropic at the seeds' spacing, the seed's colour as the
// degree-0 coefficient, the paper's initial opacity.
void Trainer::Seed(SplatSummary* summary) {
  const SplatSeed& seed = scene_.seed;
  gaussians_.sh_degree = options_.sh_degree;
  const int64_t n = static_cast<int64_t>(seed.points.size());
  gaussians_.Resize(n);
  // Not clamped here: BoundParameters lifts (and counts) seeds below the floor.
  const float log_scale =
      static_cast<float>(std::log(options_.seed_scale_factor * std::max(seed.spacing_m, 1e-30)));
  for (int64_t i = 0; i < n; ++i) SeedGaussian(i, seed, i, log_scale);
  gradient_.sh_degree = moments_.first.sh_degree = moments_.second.sh_degree = options_.sh_degree;
  moments_.first.Resize(n);
  moments_.second.Resize(n);
  grad_accum_.assign(n, 0);
  grad_count_.assign(n, 0);
  summary->seed_points = n;
}

// The level an iteration at `fraction` of the budget draws at: start_level_ at the start, one
// level less at each equal step, 0 (full resolution) from options.full_resolution_at on.
int Trainer::LevelAt(double fraction) const {
  if (start_level_ == 0 || fraction >= options_.full_resolution_at) return 0;
  const double share = fraction / std::max(options_.full_resolution_at, 1e-12);
  return start_level_ - static_cast<int>(share * start_level_);
}

const Trainer::ViewLevel& Trainer::Level(int v, int level) {
  std::vector<ViewLevel>& made = levels_[v];
  if (made.size() < static_cast<size_t>(level)) made.resize(level);
  ViewLevel& out = made[level - 1];
  if (out.target.empty()) {
    const double scale = std::ldexp(1.0, -level);
    const CameraModel camera = scene_.views[v].camera.Scaled(scale);
    out.camera = ToPinhole(camera);
    const cv::Size size(camera.width(), camera.height());
    cv::Mat image, background;
    cv::resize(*images_[v], image, size, 0, 0, cv::INTER_AREA);
    cv::resize(scene_.views[v].background, background, size, 0, 0, cv::INTER_AREA);
    out.target = ToFloat(image);
    out.background = ToFloat(background);
    if (RandomBackground()) {
      cv::Mat coverage;
      cv::resize(*masks_[v], coverage, size, 0, 0, cv::INTER_AREA);
      out.coverage = CoverageOf(coverage);
    }
  }
  return out;
}

double Trainer::TrainStep(int active_degree, int v, int level) {
  const ViewLevel* scaled = level > 0 ? &Level(v, level) : nullptr;
  const splat::PinholeCamera& camera = scaled != nullptr ? scaled->camera : cameras_[v];
  const std::vector<float>* target = scaled != nullptr ? &scaled->target : &targets_[v];
  const std::vector<float>* background = scaled != nullptr ? &scaled->background : &backgrounds_[v];
  const size_t pixels = static_cast<size_t>(camera.width) * camera.height;
  if (RandomBackground()) {
    // The target over a random colour by its alpha, rendered over the same colour: a Gaussian
    // outside the alpha is wrong against every colour, so only the subject is learned.
    const std::vector<float>& coverage = scaled != nullptr ? scaled->coverage : coverages_[v];
    std::uniform_real_distribution<float> unit(0.0f, 1.0f);
    const float colour[3] = {unit(rng_), unit(rng_), unit(rng_)};
    mixed_target_.resize(3 * pixels);
    mixed_background_.resize(3 * pixels);
    const float* captured = target->data();
    for (size_t p = 0; p < pixels; ++p) {
      const float a = coverage[p];
      for (int c = 0; c < 3; ++c) {
        mixed_target_[3 * p + c] = a * captured[3 * p + c] + (1 - a) * colour[c];
        mixed_background_[3 * p + c] = colour[c];
      }
    }
    target = &mixed_target_;
    background = &mixed_background_;
  }
  splat::RasterOptions raster;
  raster.active_sh_degree = active_degree;
  raster.times = &profile_.kernels;
  auto clock = std::chrono::steady_clock::now();
  splat::ProjectGaussians(gaussians_, camera, raster, &projected_);
  profile_.projection += Lap(&clock);
  image_.resize(3 * pixels);
  dloss_.resize(3 * pixels);
  profile_.pixels += static_cast<double>(pixels);
  splat::RasterizeForward(projected_, camera, raster, background->data(), image_.data(),
                          static_cast<float*>(nullptr), static_cast<float*>(nullptr), &raster_);
  Lap(&clock);
  const double loss = splat::PhotometricLoss(image_.data(), target->data(), camera.width,
                                             camera.height, options_.ssim_weight, dloss_.data());
  profile_.loss += Lap(&clock);
  if (!std::isfinite(loss)) return loss;
  splat::RasterizeBackward(projected_, camera, raster, raster_, background->data(), dloss_.data(),
                           static_cast<const float*>(nullptr), &projected_gradients_);
  Lap(&clock);
  ZeroGradient();
  splat::ProjectBackward(gaussians_, camera, raster, projected_, projected_gradients_, &gradient_);
  profile_.parameters += Lap(&clock);
  // The paper's statistic: the positional gradient in normalised device coordinates.
  const float half_w = 0.5f * camera.width, half_h = 0.5f * camera.height;
  for (int64_t i = 0; i < gaussians_.size(); ++i) {
    if (projected_.radius[i] <= 0) continue;
    const float gu = projected_gradients_.mean2d[2 * i] * half_w;
    const float gv = projected_gradients_.mean2d[2 * i + 1] * half_h;
    grad_accum_[i] += std::sqrt(gu * gu + gv * gv);
    ++grad_count_[i];
  }
  profile_.statistic += Lap(&clock);
  return loss;
}

// The gradient sized as the Gaussians and zero, without giving its memory back.
void Trainer::ZeroGradient() {
  gradient_.Resize(gaussians_.size());
  std::vector<float>* const fields[] = {&gradient_.position, &gradient_.rotation,
                                        &gradient_.log_scale, &gradient_.opacity, &gradient_.sh};
#pragma omp parallel
  for (std::vector<float>* field : fields) {
    float* values = field->data();
    const int64_t count = static_cast<int64_t>(field->size());
#pragma omp for schedule(static) nowait
    for (int64_t k = 0; k < count; ++k) values[k] = 0;
  }
}

// Adam on every group with its own rate; the position's decays exponentially to 1/100. Then
// the bounds (BoundParameters). One pass over the Gaussians, each Gaussian's groups in turn.
// opacity_step receives the mean |change| of the opacity logits that had a gradient; returns
// whether every position, scale, opacity and colour value is finite after the bounds.
bool Trainer::AdamStep(double progress, double* opacity_step) {
  ++adam_step_;
  const double beta1 = 0.9, beta2 = 0.999, epsilon = 1e-15;
  const double correction1 = 1 - std::pow(beta1, adam_step_);
  const double correction2 = 1 - std::pow(beta2, adam_step_);
  // A later frame's motion is learned at a higher rate, decaying to 1/10 over the frame.
  const double position_lr = temporal_
                                 ? options_.position_lr * extent_ *
                                       options_.frame_position_lr_scale * std::pow(0.1, progress)
                                 : options_.position_lr * extent_ * std::pow(0.01, progress);
  // With a motion field, the field learns at the later frame's rate and each Gaussian's own
  // position at frame_own_position_lr_scale x position_lr (decaying alike).
  const bool field = temporal_ && motion_.on();
  const double own_position_lr = field ? options_.position_lr * extent_ *
                                             options_.frame_own_position_lr_scale *
                                             std::pow(0.1, progress)
                                       : position_lr;
  const double scale = lr_scale_ * options_.learning_rate;
  const float b1 = static_cast<float>(beta1), b2 = static_cast<float>(beta2);
  const float c1 = static_cast<float>(1 / correction1), c2 = static_cast<float>(1 / correction2);
  const float eps = static_cast<float>(epsilon);
  // Adam on `count` values from `at`, the first `first_count` at `first`, the rest at `rest`.
  auto step = [&](std::vector<float>& p, const std::vector<float>& g, std::vector<float>& m,
                  std::vector<float>& s, size_t at, size_t count, size_t first_count, float first,
                  float rest) {
    for (size_t k = at; k < at + count; ++k) {
      const float rate = k - at < first_count ? first : rest;
      m[k] = b1 * m[k] + (1 - b1) * g[k];
      s[k] = b2 * s[k] + (1 - b2) * g[k] * g[k];
      p[k] -= rate * (m[k] * c1) / (std::sqrt(s[k] * c2) + eps);
    }
  };
  auto rate = [&](double lr) { return static_cast<float>(lr * scale); };
  if (field) motion_.Step(gradient_, rate(position_lr), &gaussians_);
  const float position_rate = rate(own_position_lr), rotation_rate = rate(options_.rotation_lr);
  const float scale_rate = rate(options_.scale_lr), opacity_rate = rate(options_.opacity_lr);
  // A later frame's delta holds no higher harmonics: they stay as the frame before left them.
  const float sh_first = rate(options_.sh_lr), sh_rest = rate(temporal_ ? 0 : options_.sh_lr / 20);
  const size_t sh_stride = size_t{3} * gaussians_.coefficients();
  Gaussians& p = gaussians_;
  const Gaussians& g = gradient_;
  Gaussians& m = moments_.first;
  Gaussians& s = moments_.second;
  const int64_t n = gaussians_.size();
  double moved = 0;
  int64_t moving = 0, floored = 0, not_finite = 0;
#pragma omp parallel for schedule(static) reduction(+ : moved, moving, floored, not_finite)
  for (int64_t i = 0; i < n; ++i) {
    const auto u = static_cast<size_t>(i);
    const float opacity_before = p.opacity[u];
    step(p.position, g.position, m.position, s.position, 3 * u, 3, 3, position_rate, 0);
    step(p.rotation, g.rotation, m.rotation, s.rotation, 4 * u, 4, 4, rotation_rate, 0);
    step(p.log_scale, g.log_scale, m.log_scale, s.log_scale, 3 * u, 3, 3, scale_rate, 0);
    step(p.opacity, g.opacity, m.opacity, s.opacity, u, 1, 1, opacity_rate, 0);
    step(p.sh, g.sh, m.sh, s.sh, sh_stride * u, sh_stride, 3, sh_first, sh_rest);
    if (g.opacity[u] != 0) {
      moved += std::abs(p.opacity[u] - opacity_before);
      ++moving;
    }
    floored += BoundGaussian(i);
    bool finite = std::isfinite(p.opacity[u]);
    for (size_t k = 3 * u; k < 3 * u + 3; ++k)
      finite = finite && std::isfinite(p.position[k]) && std::isfinite(p.log_scale[k]);
    for (size_t k = sh_stride * u; k < sh_stride * (u + 1); ++k)
      finite = finite && std::isfinite(p.sh[k]);
    not_finite += finite ? 0 : 1;
  }
  floored_ += floored;
  *opacity_step = moving > 0 ? moved / static_cast<double>(moving) : 0;
  return not_finite == 0;
}

// Gaussian i's scales between the floor and the cap, its opacity logit within +-12 and its
// quaternion reset when it lost its length; returns how many scale values it lifted.
int64_t Trainer::BoundGaussian(int64_t i) {
  const float lo = static_cast<float>(min_log_scale_), hi = static_cast<float>(max_log_scale_);
  int64_t floored = 0;
  for (int a = 0; a < 3; ++a) {
    float& s = gaussians_.log_scale[3 * i + a];
    if (s < lo) ++floored;
    s = std::clamp(s, lo, hi);
  }
  gaussians_.opacity[i] = std::clamp(gaussians_.opacity[i], -kMaxOpacityLogit, kMaxOpacityLogit);
  float* q = &gaussians_.rotation[4 * i];
  if (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3] < 1e-12f) {
    q[0] = 1;
    q[1] = q[2] = q[3] = 0;
  }
  return floored;
}

// Bounded activations: scales between the floor and the cap (the floor keeps every covariance
// positive definite; a Gaussian collapsing to a plane stops at it and is counted), opacity
// logits within +-12, quaternions that lost their length reset.
void Trainer::BoundParameters() {
  int64_t floored = 0;
#pragma omp parallel for schedule(static) reduction(+ : floored)
  for (int64_t i = 0; i < gaussians_.size(); ++i) floored += BoundGaussian(i);
  floored_ += floored;
}

// Keeps the Gaussians at `indices` (in that order, repeats allowed), parameters and moments.
void Trainer::Keep(const std::vector<int64_t>& indices) {
  auto select = [&](Gaussians& g) {
    Gaussians out;
    out.sh_degree = g.sh_degree;
    for (int64_t i : indices) out.AppendFrom(g, i);
    g = std::move(out);
  };
  select(gaussians_);
  select(moments_.first);
  select(moments_.second);
  std::vector<float> accum;
  std::vector<int32_t> count;
  for (int64_t i : indices) {
    accum.push_back(grad_accum_[i]);
    count.push_back(grad_count_[i]);
  }
  grad_accum_ = std::move(accum);
  grad_count_ = std::move(count);
  // A Gaussian continues the frame before's only once, in order; copies are added ones.
  std::vector<int64_t> origin;
  int64_t last = -1;
  for (int64_t i : indices) {
    const int64_t o = i < static_cast<int64_t>(origin_.size()) ? origin_[i] : -1;
    origin.push_back(o > last ? o : -1);
    if (o > last) last = o;
  }
  origin_ = std::move(origin);
}

// The paper's densification: Gaussians whose mean view-space positional gradient exceeds the
// threshold are cloned (small ones: the copy moves apart under the gradient) or split in two
// (large ones: each sampled from the original, scales / 1.6). Stops at max_gaussians.
void Trainer::Densify(SplatSummary* summary) {
  const int64_t n = gaussians_.size();
  const double split_above = options_.split_scale_view * view_width_m_;
  std::vector<int64_t> keep, clones, splits;
  for (int64_t i = 0; i < n; ++i) {
    const bool hot = grad_count_[i] > 0 && grad_accum_[i] / grad_count_[i] >=
                                               static_cast<float>(options_.densify_gradient);
    const float* ls = &gaussians_.log_scale[3 * i];
    const double largest = std::exp(std::max({ls[0], ls[1], ls[2]}));
    if (hot && largest > split_above) {
      splits.push_back(i);
    } else {
      keep.push_back(i);
      if (hot) clones.push_back(i);
    }
  }
  // Each clone adds one Gaussian, each split one net: within the cap, the first ones win.
  int64_t room = std::max<int64_t>(0, options_.max_gaussians - n);
  if (add_room_ >= 0) room = std::min(room, add_room_);
  if (static_cast<int64_t>(clones.size() + splits.size()) > room) {
    summary->cap_reached = true;
    const int64_t clone_room = std::min<int64_t>(clones.size(), room);
    for (size_t k = room - clone_room; k < splits.size(); ++k) keep.push_back(splits[k]);
    splits.resize(room - clone_room);
    clones.resize(clone_room);
    std::sort(keep.begin(), keep.end());
  }
  // A split's first half takes the original's place (in a later frame it continues that
  // Gaussian: a delta changes it), its second half and the clones follow the rest (a delta adds
  // them): each clone and each split adds one Gaussian, as the cap counts.
  std::vector<int64_t> in_place = keep;
  in_place.insert(in_place.end(), splits.begin(), splits.end());
  std::sort(in_place.begin(), in_place.end());
  std::vector<int64_t> order = in_place;
  order.insert(order.end(), clones.begin(), clones.end());
  order.insert(order.end(), splits.begin(), splits.end());
  const Gaussians before = gaussians_;
  Keep(order);
  // The split pairs: positions drawn from the original Gaussian, scales shrunk.
  std::normal_distribution<float> normal(0.0f, 1.0f);
  const size_t second_halves = in_place.size() + clones.size();
  std::vector<int64_t> halves;
  for (size_t k = 0; k < splits.size(); ++k) {
    halves.push_back(std::lower_bound(in_place.begin(), in_place.end(), splits[k]) -
                     in_place.begin());
    halves.push_back(static_cast<int64_t>(second_halves + k));
  }
  for (size_t h = 0; h < halves.size(); ++h) {
    const int64_t i = splits[h / 2], j = halves[h];
    const float* q = &before.rotation[4 * i];
    const Eigen::Quaternionf rotation = Eigen::Quaternionf(q[0], q[1], q[2], q[3]).normalized();
    Eigen::Vector3f offset;
    for (int a = 0; a < 3; ++a) offset[a] = normal(rng_) * std::exp(before.log_scale[3 * i + a]);
    const Eigen::Vector3f moved = rotation * offset;
    for (int a = 0; a < 3; ++a) {
      gaussians_.position[3 * j + a] += moved[a];
      gaussians_.log_scale[3 * j + a] -= std::log(1.6f);
    }
  }
  summary->cloned += clones.size();
  summary->split += splits.size();
  if (add_room_ >= 0) add_room_ -= static_cast<int64_t>(clones.size() + splits.size());
  std::fill(grad_accum_.begin(), grad_accum_.end(), 0.0f);
  std::fill(grad_count_.begin(), grad_count_.end(), 0);
}

// Removes transparent Gaussians, too large ones (after the first opacity reset, as the paper),
// degenerate ones (a value not finite) and those that left the volume.
void Trainer::Prune(bool prune_large, SplatSummary* summary) {
  const float min_logit = Logit(options_.prune_opacity);
  const float max_log = static_cast<float>(std::log(options_.prune_scale_view * view_width_m_));
  const Eigen::Vector3d grow = Eigen::Vector3d::Constant(0.05 * scene_.box.size().norm());
  const Box volume{scene_.box.min - grow, scene_.box.max + grow};
  std::vector<int64_t> keep;
  for (int64_t i = 0; i < gaussians_.size(); ++i) {
    bool finite = std::isfinite(gaussians_.opacity[i]);
    for (int a = 0; a < 3; ++a) {
      finite = finite && std::isfinite(gaussians_.position[3 * i + a]) &&
               std::isfinite(gaussians_.log_scale[3 * i + a]);
    }
    for (int a = 0; a < 4; ++a) finite = finite && std::isfinite(gaussians_.rotation[4 * i + a]);
    if (!finite) {
      ++summary->pruned_degenerate;
      continue;
    }
    const Eigen::Vector3d p(gaussians_.position[3 * i], gaussians_.position[3 * i + 1],
                            gaussians_.position[3 * i + 2]);
    const float* ls = &gaussians_.log_scale[3 * i];
    if (gaussians_.opacity[i] < min_logit) {
      ++summary->pruned_transparent;
    } else if (!volume.Contains(p)) {
      ++summary->pruned_outside;
    } else if (prune_large && std::max({ls[0], ls[1], ls[2]}) > max_log) {
      ++summary->pruned_large;
    } else {
      keep.push_back(i);
    }
  }
  if (static_cast<int64_t>(keep.size()) != gaussians_.size()) Keep(keep);
}

// The paper's opacity reset: every opacity down to 0.01 (its moments cleared), so that the
// Gaussians that matter earn their opacity back and the rest are pruned.
void Trainer::ResetOpacity() {
  const float reset = Logit(0.01);
  for (int64_t i = 0; i < gaussians_.size(); ++i) {
    gaussians_.opacity[i] = std::min(gaussians_.opacity[i], reset);
    moments_.first.opacity[i] = moments_.second.opacity[i] = 0;
  }
  reset_done_ = true;
}

Evaluation Trainer::Evaluate(bool write_images) {
  Evaluation result;
  if (heldout_.empty()) return result;
  const CpuClock::Excluded scoring(&cpu_);
  double mse = 0, mse_fg = 0, mse_background = 0, ssim = 0, mse_white = 0;
  for (int v : heldout_) {
    const SplatView& view = scene_.views[v];
    cv::Mat background;
    view.background.convertTo(background, CV_32FC3, 1.0 / 255.0);
    SplatRender render = RenderSplats(gaussians_, view.camera, background, options_.sh_degree);
    cv::Mat predicted, truth;
    cv::min(cv::max(render.color, 0.0), 1.0, predicted);
    images_[v]->convertTo(truth, CV_32FC3, 1.0 / 255.0);
    // The subject's silhouette in the held-out view, grown by 3 pixels (as Neural Volumes').
    cv::Mat mask;
    cv::dilate(*masks_[v], mask, cv::Mat(), cv::Point(-1, -1), 3);
    result.subject_seen = result.subject_seen || cv::countNonZero(mask) > 0;
    mse += std::pow(10.0, -PsnrDb(predicted, truth) / 10.0);
    if (cv::countNonZero(mask) > 0) {
      mse_fg += std::pow(10.0, -PsnrDb(predicted, truth, mask) / 10.0);
      mse_background += std::pow(10.0, -PsnrDb(background, truth, mask) / 10.0);
    }
    ssim += Ssim(predicted, truth);
    if (scene_.alpha_masks) mse_white += OnWhiteMse(render, background, truth, *masks_[v]);
    if (write_images) {
      cv::Mat side_by_side, image8;
      cv::hconcat(predicted, truth, side_by_side);
      side_by_side.convertTo(image8, CV_8UC3, 255.0);
      CreateDirectories(model_dir_ / "heldout");
      WritePng(model_dir_ / "heldout" / (view.name + ".png"), image8);
    }
  }
  const double count = static_cast<double>(heldout_.size());
  result.psnr_db = -10.0 * std::log10(mse / count);
  result.psnr_fg_db = -10.0 * std::log10(mse_fg / count);
  result.background_psnr_fg_db = -10.0 * std::log10(mse_background / count);
  result.ssim = ssim / count;
  if (scene_.alpha_masks) result.psnr_white_db = -10.0 * std::log10(mse_white / count);
  return result;
}

double Trainer::TrainingPsnr() {
  const CpuClock::Excluded scoring(&cpu_);
  double mse = 0;
  for (int v : training_) {
    const SplatView& view = scene_.views[v];
    cv::Mat background, truth, predicted;
    view.background.convertTo(background, CV_32FC3, 1.0 / 255.0);
    images_[v]->convertTo(truth, CV_32FC3, 1.0 / 255.0);
    cv::min(
        cv::max(RenderSplats(gaussians_, view.camera, background, options_.sh_degree).color, 0.0),
        1.0, predicted);
    mse += std::pow(10.0, -PsnrDb(predicted, truth) / 10.0);
  }
  return -10.0 * std::log10(mse / training_.size());
}

void Trainer::DescribePlan(SplatSummary* summary) const {
  summary->plan = scene_.plan;
  summary->plan["method"] = "3D Gaussian splatting (Kerbl et al. 2023), CPU kernels";
  summary->plan["seed"] = {{"source", scene_.seed.source},
                           {"points", scene_.seed.points.size()},
                           {"spacing_m", scene_.seed.spacing_m}};
  summary->plan["training_cameras"] = nlohmann::json::array();
  for (int v : training_) summary->plan["training_cameras"].push_back(scene_.views[v].name);
  summary->plan["heldout"] = nlohmann::json::array();
  for (int v : heldout_) summary->plan["heldout"].push_back(scene_.views[v].name);
  summary->plan["extent_m"] = extent_;
  summary->plan["scale_bounds_m"] = {std::exp(min_log_scale_), std::exp(max_log_scale_)};
  // The bounds in the image: pixels at the median distance, the same for any subject's size.
  const double view_px = view_width_m_ / pixel_m_;
  summary->plan["view_width_m"] = view_width_m_;
  summary->plan["scale_bounds_px"] = {options_.min_scale_px, options_.max_scale_view * view_px};
  summary->plan["split_above_px"] = options_.split_scale_view * view_px;
  summary->plan["prune_above_px"] = options_.prune_scale_view * view_px;
  summary->plan["split_above_m"] = options_.split_scale_view * view_width_m_;
  summary->plan["prune_above_m"] = options_.prune_scale_view * view_width_m_;
  summary->plan["losses"] = {{"l1", 1 - options_.ssim_weight}, {"dssim", options_.ssim_weight}};
  summary->plan["device"] = "cpu (splat/kernels.h, OpenMP over 16x16 tiles)";
  if (!scene_.later_frames.empty()) {
    if (options_.frame_motion_spacings > 0) {
      MotionField grid;
      grid.Lay(scene_.box, options_.frame_motion_spacings * scene_.seed.spacing_m);
      summary->plan["later_frame_motion"] = {
          {"model",
           "a field of nodes over the subject's box, each Gaussian moved by its eight "
           "nodes' blend (--frame-motion-spacings)"},
          {"node_spacing_m", grid.spacing},
          {"nodes", grid.dims},
          {"own_position_lr_scale", options_.frame_own_position_lr_scale}};
    } else {
      summary->plan["later_frame_motion"] = {
          {"model", "each Gaussian its own (--frame-motion-spacings 0)"}};
    }
  }
  summary->plan["training_background"] =
      RandomBackground()
          ? "a random colour each iteration, the frames composited over it by their alpha: only "
            "the alpha's subject is learned (--no-random-background: the view's background)"
          : "the view's background (" + scene_.plan.value("background", std::string("given")) + ")";
  const SplatView& first = scene_.views.front();
  nlohmann::json levels = nlohmann::json::array();
  for (int level = start_level_; level >= 0; --level) {
    const double from = start_level_ == 0
                            ? 0.0
                            : options_.full_resolution_at * (start_level_ - level) / start_level_;
    const double scale = std::ldexp(1.0, -level);
    levels.push_back({{"width", std::lround(first.image.cols * scale)},
                      {"height", std::lround(first.image.rows * scale)},
                      {"from_fraction", from}});
  }
  summary->plan["resolution"] = {
      {"pixel_budget", options_.pixel_budget},
      {"full", {first.image.cols, first.image.rows}},
      {"schedule", levels},
      {"why", start_level_ == 0
                  ? "the views fit the pixel budget: every iteration at full resolution"
                  : Cat("the views exceed the pixel budget of ", options_.pixel_budget,
                        " pixels an iteration: halved ", start_level_,
                        " times at the start, full resolution from ", options_.full_resolution_at,
                        " of the budget on")}};
}

// How a run that did not diverge ended: not finite, no subject to judge, or a subject no better
// than the background alone (DEGENERATE), or the budget spent.
void Trainer::Judge(int64_t iteration, SplatSummary* summary) const {
  if (!heldout_.empty() && !subject_seen_) {
    summary->End(Termination::kDegenerate,
                 "the held-out views show no subject (empty silhouettes): nothing to judge the "
                 "splats by (an empty frame?)");
  } else if (!std::isfinite(summary->last_loss) ||
             (!heldout_.empty() && !std::isfinite(summary->heldout_psnr_db))) {
    summary->End(Termination::kFailure, "the loss or the held-out PSNR is not finite");
  } else if (!heldout_.empty() && summary->heldout_psnr_fg_db <= summary->background_psnr_fg_db) {
    summary->End(Termination::kDegenerate,
                 Cat("the subject in the held-out views (", summary->heldout_psnr_fg_db,
                     " dB) is no better than the background alone (",
                     summary->background_psnr_fg_db, " dB) after ", iteration, " iterations"));
  } else {
    summary->End(
        Termination::kNoConvergence,
        heldout_.empty()
            ? Cat("trained ", iteration, " iterations in ", summary->seconds,
                  " s (no held-out camera); training views ", summary->train_psnr_db, " dB")
            : Cat("trained ", iteration, " iterations in ", summary->seconds, " s; held-out PSNR ",
                  summary->heldout_psnr_db, " dB (subject ", summary->heldout_psnr_fg_db,
                  " dB, background alone ", summary->background_psnr_fg_db, " dB",
                  OnWhiteClause(summary->heldout_psnr_white_db), "), ", summary->gaussians,
                  " Gaussians"));
  }
}

SplatSummary Trainer::Run(Report* report) {
  SplatSummary summary;
  DescribePlan(&summary);
  if (report != nullptr) report->plan() = summary.plan;
  if (scene_.seed.points.empty()) {
    summary.End(Termination::kDegenerate,
                Cat("the reconstruction seed is empty (", scene_.seed.source,
                    "): no surface to start the Gaussians from (an empty frame, or silhouettes "
                    "that hold no subject)"));
    return summary;
  }
  Seed(&summary);
  BoundParameters();
  start_ = std::chrono::steady_clock::now();
  train_cpu_start_ = cpu_.Now();
  const bool cpu_budget = options_.cpu_minutes > 0;
  TrainFrame(0,
             FrameBudget{options_.iterations, cpu_budget ? 0.0 : options_.minutes * 60.0, true,
                         cpu_budget ? CpuDeadline(0) : 0.0},
             &summary, report);
  summary.seconds = Elapsed();
  summary.iterations = total_iterations_;
  Finish(&summary);
  SplatFrameSummary first = ScoreFrame(0, summary.seconds, summary.iterations);
  first.megabytes = summary.megabytes;
  Record(first, &summary, report);
  if (summary.divergences <= options_.max_divergences) TrainLaterFrames(&summary, report);
  summary.profile = profile_.ToJson();
  summary.cpu_s_seed = scene_.load_cpu_s;
  summary.cpu_s_training = cpu_.Now() - scene_.load_cpu_s;
  summary.cpu_s_scoring = cpu_.excluded();
  if (summary.divergences <= options_.max_divergences) Judge(summary.iterations, &summary);
  return summary;
}

// Where frame `frame`'s training ends on the CPU clock: what the seed left of the budget, shared
// as minutes (frame 0) : frame_minutes (each later frame), a frame's unspent share passing on.
double Trainer::CpuDeadline(int64_t frame) const {
  const double later = static_cast<double>(scene_.later_frames.size());
  const double share = (options_.minutes + static_cast<double>(frame) * options_.frame_minutes) /
                       (options_.minutes + later * options_.frame_minutes);
  return train_cpu_start_ + std::max(0.0, options_.cpu_minutes * 60 - train_cpu_start_) * share;
}

// The views show frame `frame` (0: the scene's views, else a later frame's images).
void Trainer::ShowFrame(int64_t frame) {
  for (size_t v = 0; v < scene_.views.size(); ++v) {
    const SplatView& view = scene_.views[v];
    images_[v] = frame == 0 ? &view.image : &scene_.later_frames[frame - 1].images[v];
    masks_[v] = frame == 0 ? &view.mask : &scene_.later_frames[frame - 1].masks[v];
    if (!view.heldout) targets_[v] = ToFloat(*images_[v]);
    if (RandomBackground() && !view.heldout) coverages_[v] = CoverageOf(*masks_[v]);
    levels_[v].clear();
  }
}

void Trainer::ResetMoments() {
  moments_.first.Resize(0);
  moments_.second.Resize(0);
  moments_.first.Resize(gaussians_.size());
  moments_.second.Resize(gaussians_.size());
  adam_step_ = 0;
  grad_accum_.assign(gaussians_.size(), 0);
  grad_count_.assign(gaussians_.size(), 0);
  if (temporal_ && options_.frame_motion_spacings > 0)
    motion_.Cover(scene_.box, options_.frame_motion_spacings * scene_.seed.spacing_m);
}

// Seeds a Gaussian at each of the new frame's surface samples that lies farther than
// new_surface_spacings x the spacing from every Gaussian (a hash grid of that cell size), within
// the frame's room. Returns how many were added; `uncovered_count` receives how many samples
// asked.
int64_t Trainer::AddNewSurface(const SplatSeed& seed, int64_t* uncovered_count) {
  *uncovered_count = 0;
  if (seed.points.empty() || add_room_ == 0) return 0;
  const double cell = options_.new_surface_spacings * std::max(seed.spacing_m, 1e-6);
  auto key = [&](const Eigen::Vector3f& p, int dx, int dy, int dz) {
    const int64_t x = static_cast<int64_t>(std::floor(p.x() / cell)) + dx;
    const int64_t y = static_cast<int64_t>(std::floor(p.y() / cell)) + dy;
    const int64_t z = static_cast<int64_t>(std::floor(p.z() / cell)) + dz;
    return (x * 73856093) ^ (y * 19349663) ^ (z * 83492791);
  };
  std::unordered_multimap<int64_t, int64_t> grid;
  auto position = [&](int64_t i) {
    return Eigen::Vector3f(gaussians_.position[3 * i], gaussians_.position[3 * i + 1],
                           gaussians_.position[3 * i + 2]);
  };
  for (int64_t i = 0; i < gaussians_.size(); ++i) grid.emplace(key(position(i), 0, 0, 0), i);
  std::vector<size_t> uncovered;
  for (size_t s = 0; s < seed.points.size(); ++s) {
    bool covered = false;
    for (int d = 0; d < 27 && !covered; ++d) {
      auto [from, to] = grid.equal_range(key(seed.points[s], d % 3 - 1, d / 3 % 3 - 1, d / 9 - 1));
      for (auto it = from; it != to && !covered; ++it)
        covered = (position(it->second) - seed.points[s]).norm() <= cell;
    }
    if (!covered) uncovered.push_back(s);
  }
  int64_t count = static_cast<int64_t>(uncovered.size());
  *uncovered_count = count;
  count = std::min(count, std::max<int64_t>(0, options_.max_gaussians - gaussians_.size()));
  if (add_room_ >= 0) count = std::min(count, add_room_);
  const int64_t n = gaussians_.size();
  const float log_scale = static_cast<float>(std::log(std::max(seed.spacing_m, 1e-30)));
  gaussians_.Resize(n + count);
  for (int64_t j = 0; j < count; ++j) {
    // Spread over the uncovered samples when the room is smaller than they are.
    const size_t s = uncovered[j * uncovered.size() / std::max<int64_t>(count, 1)];
    SeedGaussian(n + j, seed, s, log_scale);
  }
  origin_.resize(n + count, -1);
  if (add_room_ >= 0) add_room_ -= count;
  return count;
}

// The frame's delta of the frame before, coarsened until it fits max_frame_megabytes (and, were
// the added Gaussians alone over it, without them); the trainer continues from the frame as
// decoded, so that playback and training never drift apart.
void Trainer::StoreDelta(int64_t frame, const Gaussians& previous, SplatFrameSummary* stored) {
  SplatDeltaSteps steps;
  steps.position_m = static_cast<float>(options_.delta_position_step_m);
  steps.rotation = static_cast<float>(options_.delta_rotation_step);
  steps.log_scale = static_cast<float>(options_.delta_scale_step);
  steps.opacity = static_cast<float>(options_.delta_opacity_step);
  steps.color = static_cast<float>(options_.delta_color_step / kShC0);
  const double max_bytes = options_.max_frame_megabytes * 1e6;
  std::string delta = EncodeSplatDelta(previous, gaussians_, origin_, steps);
  while (static_cast<double>(delta.size()) > max_bytes) {
    if (stored->coarsened >= 16) {
      std::vector<int64_t> survivors;
      for (int64_t i = 0; i < gaussians_.size(); ++i)
        if (origin_[i] >= 0) survivors.push_back(i);
      Keep(survivors);
    }
    steps = steps.Doubled();
    ++stored->coarsened;
    delta = EncodeSplatDelta(previous, gaussians_, origin_, steps);
    if (stored->coarsened > 40) Fail("a splat delta does not fit ", max_bytes, " bytes");
  }
  gaussians_ = ApplySplatDelta(previous, delta);
  CreateDirectories(model_dir_ / "deltas");
  WriteFileAtomic(SplatDeltaFile(model_dir_, frame), delta, /*durable=*/per_frame_);
  if (!per_frame_) {
    stored_.frames = frame + 1;
    stored_.Save(model_dir_, /*write_gaussians=*/false);
  }
  const SplatDeltaCounts counts = CountSplatDelta(delta);
  stored->added = counts.added;
  stored->removed = counts.removed;
  stored->changed = counts.changed;
  stored->megabytes = static_cast<double>(delta.size()) / 1e6;
}

SplatFrameSummary Trainer::ScoreFrame(int64_t frame, double seconds, int64_t iterations) {
  // The tasks of a per-frame run would write one folder of held-out images at once.
  const Evaluation eval = Evaluate(!per_frame_);
  subject_seen_ = eval.subject_seen;
  SplatFrameSummary scored;
  scored.frame = frame;
  scored.set =
      frame == 0 ? scene_.plan.value("frame_set", int64_t{0}) : scene_.later_frames[frame - 1].set;
  scored.iterations = iterations;
  scored.seconds = seconds;
  scored.elapsed_s = Elapsed();
  scored.heldout_psnr_db = eval.psnr_db;
  scored.heldout_psnr_fg_db = eval.psnr_fg_db;
  scored.background_psnr_fg_db = eval.background_psnr_fg_db;
  scored.heldout_ssim = eval.ssim;
  scored.heldout_psnr_white_db = eval.psnr_white_db;
  scored.gaussians = gaussians_.size();
  return scored;
}

// The frame's scores become the summary's (the last frame's stand at the end) and the report's.
void Trainer::Record(const SplatFrameSummary& frame, SplatSummary* summary, Report* report) {
  summary->frames.push_back(frame);
  summary->heldout_psnr_db = frame.heldout_psnr_db;
  summary->heldout_psnr_fg_db = frame.heldout_psnr_fg_db;
  summary->background_psnr_fg_db = frame.background_psnr_fg_db;
  summary->heldout_ssim = frame.heldout_ssim;
  summary->heldout_psnr_white_db = frame.heldout_psnr_white_db;
  summary->gaussians = gaussians_.size();
  if (report == nullptr) return;
  if (!heldout_.empty()) {
    // The training series ends each frame with its score (the curve runs on across frames).
    report->AddPoint("heldout_psnr_db", frame.heldout_psnr_db, total_iterations_);
    report->AddPoint("heldout_psnr_fg_db", frame.heldout_psnr_fg_db, total_iterations_);
    report->AddPoint("heldout_ssim", frame.heldout_ssim, total_iterations_);
    report->AddPoint("cpu_s", cpu_.Now(), total_iterations_);
    report->AddPoint("frame_heldout_psnr_db", frame.heldout_psnr_db, frame.frame);
    report->AddPoint("frame_heldout_psnr_fg_db", frame.heldout_psnr_fg_db, frame.frame);
  }
  report->AddPoint("frame_megabytes", frame.megabytes, frame.frame);
  report->metrics()["frames"] = nlohmann::json::array();
  for (const auto& f : summary->frames) report->metrics()["frames"].push_back(f.ToJson());
  report->Write(model_dir_ / "report.json");
}

// Frame `frame` from the Gaussians held now (its delta's base): new surface seeded, trained for
// the budget, stored as a delta and scored into `scored`. False when training diverged too often
// (nothing stored).
bool Trainer::TrainLaterFrame(int64_t frame, const FrameBudget& budget, SplatSummary* summary,
                              Report* report, SplatFrameSummary* scored) {
  const double frame_start = Elapsed();
  const int64_t iterations_before = total_iterations_;
  const int divergences_before = summary->divergences;
  ShowFrame(frame);
  const Gaussians previous = gaussians_;
  origin_.resize(gaussians_.size());
  std::iota(origin_.begin(), origin_.end(), int64_t{0});
  add_room_ = options_.max_added_per_frame;
  int64_t uncovered = 0;
  const int64_t surface = AddNewSurface(scene_.later_frames[frame - 1].seed, &uncovered);
  BoundParameters();
  ResetMoments();
  TrainFrame(frame, budget, summary, report);
  add_room_ = -1;
  if (summary->divergences > options_.max_divergences) return false;
  SplatFrameSummary stored;
  StoreDelta(frame, previous, &stored);
  *scored = ScoreFrame(frame, Elapsed() - frame_start, total_iterations_ - iterations_before);
  scored->added = stored.added;
  scored->added_surface = surface;
  scored->surface_uncovered = uncovered;
  scored->add_cap_reached = stored.added >= options_.max_added_per_frame;
  scored->removed = stored.removed;
  scored->changed = stored.changed;
  scored->coarsened = stored.coarsened;
  scored->megabytes = stored.megabytes;
  scored->divergences = summary->divergences - divergences_before;
  Record(*scored, summary, report);
  std::printf(
      "splat: frame %lld (set %lld): %.1f s, held-out %.2f dB (subject %.2f dB), %lld "
      "Gaussians, %.3f MB; added %lld (%lld on new surface: %lld samples lay beyond %.3g "
      "spacings of the frame before's Gaussians%s)\n",
      static_cast<long long>(frame), static_cast<long long>(scored->set), scored->seconds,
      scored->heldout_psnr_db, scored->heldout_psnr_fg_db,
      static_cast<long long>(scored->gaussians), scored->megabytes,
      static_cast<long long>(scored->added), static_cast<long long>(surface),
      static_cast<long long>(uncovered), options_.new_surface_spacings,
      scored->add_cap_reached ? "; the per-frame cap bit" : "");
  return true;
}

// Frames 1, 2, ...: each from the frame before, trained for the frame's budget.
void Trainer::TrainLaterFrames(SplatSummary* summary, Report* report) {
  temporal_ = true;
  summary->temporal = !scene_.later_frames.empty();
  for (size_t f = 0; f < scene_.later_frames.size(); ++f) {
    SplatFrameSummary scored;
    const bool cpu_budget = options_.cpu_minutes > 0;
    const FrameBudget budget{options_.frame_iterations,
                             cpu_budget ? 0.0 : options_.frame_minutes * 60.0, false,
                             cpu_budget ? CpuDeadline(static_cast<int64_t>(f) + 1) : 0.0};
    if (!TrainLaterFrame(static_cast<int64_t>(f) + 1, budget, summary, report, &scored)) return;
  }
  summary->seconds = Elapsed();
  summary->iterations = total_iterations_;
  if (summary->temporal) summary->train_psnr_db = TrainingPsnr();
}

SplatSummary Trainer::TrainFromBase(int64_t frame, const Gaussians& base,
                                    const nlohmann::json& state, int64_t iterations) {
  per_frame_ = temporal_ = true;
  // Everything the frame's bytes depend on comes from its base, its own data and frame 0's
  // end state: never from the frames this task happened to train before.
  std::seed_seq stream{options_.seed, static_cast<uint64_t>(frame)};
  rng_.seed(stream);
  lr_scale_ = state.at("lr_scale").get<double>();
  reset_done_ = state.at("reset_done").get<bool>();
  gaussians_ = base;
  gradient_.sh_degree = moments_.first.sh_degree = moments_.second.sh_degree = base.sh_degree;
  SplatSummary summary;
  summary.temporal = true;
  SplatFrameSummary scored;
  if (!TrainLaterFrame(frame, FrameBudget{iterations, 0, false}, &summary, nullptr, &scored))
    return summary;
  summary.seconds = scored.seconds;
  Judge(scored.iterations, &summary);
  // The frame's record holds what decides its bytes and its scores, never its time.
  if (summary.termination == Termination::kNoConvergence) {
    summary.End(
        Termination::kNoConvergence,
        Cat("trained ", scored.iterations, " iterations; held-out PSNR ", scored.heldout_psnr_db,
            " dB (subject ", scored.heldout_psnr_fg_db, " dB, background alone ",
            scored.background_psnr_fg_db, " dB), ", scored.gaussians, " Gaussians"));
  }
  return summary;
}

// Trains the Gaussians on the frame the views show, for the budget; the divergence guard
// restores the last snapshot and halves the rates.
void Trainer::TrainFrame(int64_t frame, const FrameBudget& budget, SplatSummary* summary,
                         Report* report) {
  Snapshot snapshot{gaussians_, moments_, 0, adam_step_, origin_};
  const double frame_start = Elapsed();
  auto elapsed = [&] { return Elapsed() - frame_start; };
  const double cpu_start = cpu_.Now();
  const bool cpu_budget = budget.cpu_deadline_s > 0;
  const double cpu_span = std::max(budget.cpu_deadline_s - cpu_start, 1e-9);
  Progress progress(frame == 0 ? "splat train" : Cat("splat frame ", frame),
                    budget.iterations > 0 ? budget.iterations
                    : cpu_budget          ? static_cast<int64_t>(cpu_span)
                                          : static_cast<int64_t>(budget.seconds));
  std::vector<double> reference(scene_.views.size(), -1), losses;
  std::vector<int> order;
  size_t cursor = 0;
  double next_eval = 0;
  Evaluation last_eval;
  auto log_eval = [&](int64_t it) {
    last_eval = Evaluate(false);
    subject_seen_ = last_eval.subject_seen;
    if (report == nullptr || heldout_.empty()) return;
    report->AddPoint("heldout_psnr_db", last_eval.psnr_db, total_iterations_ + it);
    report->AddPoint("heldout_psnr_fg_db", last_eval.psnr_fg_db, total_iterations_ + it);
    report->AddPoint("heldout_ssim", last_eval.ssim, total_iterations_ + it);
    report->AddPoint("gaussians", static_cast<double>(gaussians_.size()), total_iterations_ + it);
    report->AddPoint("cpu_s", cpu_.Now(), total_iterations_ + it);
    report->Write(model_dir_ / "report.json");
  };
  int64_t iteration = 0;
  while (true) {
    const double t = elapsed();
    const double cpu_t = cpu_budget ? cpu_.Now() - cpu_start : 0.0;
    if (budget.iterations > 0 && iteration >= budget.iterations) break;
    if (budget.seconds > 0 && t >= budget.seconds) break;
    if (cpu_budget && cpu_t >= cpu_span) break;
    // Later frames are scored once, when trained.
    const bool eval_due = budget.first && (options_.eval_every_iterations > 0
                                               ? iteration % options_.eval_every_iterations == 0
                                               : t >= next_eval);
    if (eval_due) {
      log_eval(iteration);
      next_eval = elapsed() + options_.eval_every_s;
    }
    double fraction = 0;
    if (budget.iterations > 0) fraction = static_cast<double>(iteration) / budget.iterations;
    if (budget.seconds > 0) fraction = std::max(fraction, t / budget.seconds);
    if (cpu_budget) fraction = std::max(fraction, cpu_t / cpu_span);
    if (cursor == order.size()) {
      order = training_;
      std::shuffle(order.begin(), order.end(), rng_);
      cursor = 0;
    }
    const int v = order[cursor++];
    auto iteration_start = std::chrono::steady_clock::now();
    auto clock = iteration_start;
    const double loss = TrainStep(budget.first ? ActiveDegree(iteration) : options_.sh_degree, v,
                                  budget.first ? LevelAt(fraction) : 0);
    bool diverged = !std::isfinite(loss) ||
                    (reference[v] > 0 && loss > options_.divergence_factor * reference[v]);
    double opacity_step = 0;
    Lap(&clock);
    if (!diverged) {
      const bool finite = AdamStep(std::min(fraction, 1.0), &opacity_step);
      // A step that flips opacities (a rate far too high) diverges even while the loss, noisy
      // from the start, has not yet doubled.
      diverged = !finite || opacity_step > options_.max_opacity_step;
    }
    profile_.adam += Lap(&clock);
    if (diverged) {
      ++summary->divergences;
      gaussians_ = snapshot.gaussians;
      moments_ = snapshot.moments;
      adam_step_ = snapshot.adam_step;
      origin_ = snapshot.origin;
      if (motion_.on())
        motion_.Cover(scene_.box, options_.frame_motion_spacings * scene_.seed.spacing_m);
      grad_accum_.assign(gaussians_.size(), 0);
      grad_count_.assign(gaussians_.size(), 0);
      lr_scale_ *= 0.5;
      std::fprintf(stderr,
                   "splat: frame %lld iteration %lld: loss %g (view %s, %g before), opacity "
                   "step %g; restored iteration %lld, learning rates x%.3g\n",
                   static_cast<long long>(frame), static_cast<long long>(iteration), loss,
                   scene_.views[v].name.c_str(), reference[v], opacity_step,
                   static_cast<long long>(snapshot.iteration), lr_scale_);
      if (report != nullptr)
        report->AddPoint("divergence_lr_scale", lr_scale_, total_iterations_ + iteration);
      iteration = snapshot.iteration;
      std::fill(reference.begin(), reference.end(), -1.0);
      if (summary->divergences > options_.max_divergences) {
        summary->End(Termination::kFailure,
                     Cat("training diverged ", summary->divergences, " times; stopped"));
        break;
      }
      continue;
    }
    // The view's best loss since the model last changed shape: a run that drifts away from
    // it step by step is caught as surely as one that jumps.
    reference[v] = reference[v] < 0 ? loss : std::min(reference[v], loss);
    losses.push_back(loss);
    ++iteration;
    bool changed = false;
    const bool densify = budget.first ? iteration >= options_.densify_from &&
                                            iteration <= options_.densify_until &&
                                            iteration % options_.densify_every == 0
                                      : iteration % options_.frame_densify_every == 0;
    Lap(&clock);
    if (densify) {
      Densify(summary);
      Prune(reset_done_, summary);
      changed = true;
    }
    if (budget.first && options_.opacity_reset_every > 0 &&
        iteration % options_.opacity_reset_every == 0 && iteration <= options_.densify_until) {
      ResetOpacity();
      changed = true;
    }
    profile_.densification += Lap(&clock);
    // A changed model renders differently: each view's reference starts again.
    if (changed) std::fill(reference.begin(), reference.end(), -1.0);
    if (iteration % options_.snapshot_every == 0)
      snapshot = Snapshot{gaussians_, moments_, iteration, adam_step_, origin_};
    profile_.iteration += Lap(&iteration_start);
    ++profile_.iterations;
    if (report != nullptr && iteration % 10 == 0) {
      report->AddPoint("loss", loss, total_iterations_ + iteration);
      report->AddPoint("gaussians", static_cast<double>(gaussians_.size()),
                       total_iterations_ + iteration);
    }
    progress.Update(budget.iterations > 0 ? iteration
                    : cpu_budget          ? static_cast<int64_t>(cpu_t)
                                          : static_cast<int64_t>(t),
                    Cat("it ", iteration, " loss ", loss, " held-out ", last_eval.psnr_db, " dB, ",
                        gaussians_.size(), " Gaussians"));
  }
  progress.Finish();
  total_iterations_ += iteration;
  const size_t window = std::max<size_t>(1, std::min<size_t>(10, losses.size() / 4));
  if (!losses.empty()) {
    if (frame == 0)
      summary->first_loss = std::accumulate(losses.begin(), losses.begin() + window, 0.0) / window;
    summary->last_loss = std::accumulate(losses.end() - window, losses.end(), 0.0) / window;
  }
}

// The model on disk, its size, the training views' PSNR and the playback speed.
void Trainer::Finish(SplatSummary* summary) {
  summary->gaussians = gaussians_.size();
  summary->floored_scales = floored_;
  summary->train_psnr_db = TrainingPsnr();
  stored_.gaussians = gaussians_;
  stored_.cameras.clear();
  for (const auto& view : scene_.views) stored_.cameras.push_back(view.camera);
  stored_.box = scene_.box;
  stored_.plan = summary->plan;
  stored_.frame_sets = {scene_.plan.value("frame_set", int64_t{0})};
  for (const SplatFrame& later : scene_.later_frames) stored_.frame_sets.push_back(later.set);
  stored_.Save(model_dir_);
  summary->megabytes = static_cast<double>(fs::file_size(model_dir_ / "gaussians.bin")) / 1e6;
  const SplatView& view = scene_.views[heldout_.empty() ? training_.front() : heldout_.front()];
  const CpuClock::Excluded timing(&cpu_);
  const auto start = std::chrono::steady_clock::now();
  const int renders = 3;
  for (int k = 0; k < renders; ++k) RenderSplats(gaussians_, view.camera, {}, options_.sh_degree);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  summary->render_fps = renders / std::max(seconds, 1e-9);
}

}  // namespace

std::string FormatSplatProfile(const nlohmann::json& profile) {
  if (!profile.is_object() || !profile.contains("stages")) return "no iteration profiled\n";
  std::string table = Cat(profile.at("iterations").get<int64_t>(), " iterations, ",
                          profile.at("iterations_per_s").get<double>(), " per second\n");
  char line[96];
  for (const nlohmann::json& row : profile.at("stages")) {
    std::snprintf(line, sizeof(line), "  %-17s %9.2f ms %5.1f %%\n",
                  row.at("stage").get<std::string>().c_str(),
                  row.at("ms_per_iteration").get<double>(), 100 * row.at("share").get<double>());
    table += line;
  }
  return table;
}

SplatSummary TrainSplatsOn(const SplatScene& scene, const fs::path& model_dir,
                           const SplatOptions& options, Report* report) {
  options.Check();
  if (options.threads > 0) omp_set_num_threads(ResolveThreads(options.threads));
  CreateDirectories(model_dir);
  if (report != nullptr) report->options() = options.ToJson();
  Trainer trainer(scene, options, model_dir);
  SplatSummary summary = trainer.Run(report);
  if (report != nullptr) {
    report->plan() = summary.plan;
    report->metrics() = TrainingMetrics(summary);
    report->metrics().update({{"train_psnr_db", summary.train_psnr_db},
                              {"gaussians", summary.gaussians},
                              {"seed_points", summary.seed_points},
                              {"cap_reached", summary.cap_reached},
                              {"max_gaussians", options.max_gaussians},
                              {"cloned", summary.cloned},
                              {"split", summary.split},
                              {"pruned_transparent", summary.pruned_transparent},
                              {"pruned_large", summary.pruned_large},
                              {"pruned_degenerate", summary.pruned_degenerate},
                              {"pruned_outside", summary.pruned_outside},
                              {"floored_scales", summary.floored_scales},
                              {"megabytes", summary.megabytes},
                              {"render_fps", summary.render_fps},
                              {"temporal", summary.temporal},
                              {"cpu_s_seed", summary.cpu_s_seed},
                              {"cpu_s_training", summary.cpu_s_training},
                              {"cpu_s_scoring", summary.cpu_s_scoring},
                              {"profile", summary.profile}});
    if (options.cpu_minutes > 0) report->metrics()["cpu_s_budget"] = options.cpu_minutes * 60;
    if (std::isfinite(summary.heldout_psnr_white_db))
      report->metrics()["heldout_psnr_white_db"] = summary.heldout_psnr_white_db;
    nlohmann::json frames = nlohmann::json::array();
    double largest_mb = 0;
    for (const auto& frame : summary.frames) {
      frames.push_back(frame.ToJson());
      if (frame.frame > 0) largest_mb = std::max(largest_mb, frame.megabytes);
    }
    report->metrics()["frames"] = frames;
    if (summary.temporal) report->metrics()["largest_delta_megabytes"] = largest_mb;
    report->SetSummary(summary);
    report->Write(model_dir / "report.json");
  }
  return summary;
}

SplatSummary TrainSplats(const fs::path& take_dir, const fs::path& model_dir,
                         const SplatOptions& options, Report* report) {
  options.Check();
  if (options.segment_frames > 0) return TrainSplatFrames(take_dir, model_dir, options, report);
  if (options.threads > 0) omp_set_num_threads(ResolveThreads(options.threads));
  CreateDirectories(model_dir);
  const SplatScene scene = LoadSplatScene(take_dir, model_dir, options);
  return TrainSplatsOn(scene, model_dir, options, report);
}

// ---------------------------------------------------------------------------------------------
// Per-frame runs (splat.h, core/frame_tasks.h).

namespace {

constexpr const char* kFramesCommand = "train splat";

Termination TerminationNamed(const std::string& name) {
  for (Termination t :
       {Termination::kSuccess, Termination::kConvergence, Termination::kNoConvergence,
        Termination::kDegenerate, Termination::kFailure}) {
    if (name == ToString(t)) return t;
  }
  return Termination::kFailure;
}

// The frame a later frame's delta applies to: frame 0 where a segment starts, else the one before.
int64_t SegmentBase(int64_t frame, int64_t segment_frames) {
  return (frame - 1) % segment_frames == 0 ? 0 : frame - 1;
}

// A delta's name relative to the model directory, as its record lists it.
std::string DeltaName(int64_t frame) { return SplatDeltaFile("", frame).string(); }

// The options that decide a frame's bytes (less threads and how the task runs).
nlohmann::json IdentityOptions(const SplatOptions& options) {
  nlohmann::json json = options.ToJson();
  json.erase("threads");
  json.erase("tasks");
  return json;
}

// The take's recording and camera models as one hash: a re-recorded or recalibrated take is
// another run.
std::string TakeFingerprint(const fs::path& take_dir) {
  std::string bytes = ReadFileToString(take_dir / "take.json");
  std::error_code ec;
  if (fs::exists(take_dir / "index.jsonl", ec)) bytes += ReadFileToString(take_dir / "index.jsonl");
  std::vector<fs::path> models;
  if (fs::is_directory(take_dir / "calib", ec)) {
    for (const auto& entry : fs::directory_iterator(take_dir / "calib", ec))
      if (entry.is_regular_file()) models.push_back(entry.path());
  }
  std::sort(models.begin(), models.end());
  for (const fs::path& file : models) bytes += file.filename().string() + ReadFileToString(file);
  return HashBytes(bytes);
}

// One task of a per-frame run: frame 0 from the run's plan, then the task's segments.
class FrameRun {
 public:
  FrameRun(fs::path take_dir, fs::path out, const SplatOptions& options, Report* report)
      : take_dir_(std::move(take_dir)), out_(std::move(out)), options_(options), report_(report) {}

  SplatSummary Run() {
    PlanFirstFrame();
    if (!scene_) scene_.emplace(LoadSplatScene(take_dir_, out_, options_, TaskFrames()));
    StartRecords();
    const Termination first = TerminationNamed(plan_.at("termination").get<std::string>());
    if (IsUsable(first)) {
      frame0_ = SplatModel::Load(out_ / kPlanDir).gaussians;
      trainer_.emplace(*scene_, options_, out_);
      for (int64_t segment : TaskSegments()) TrainSegment(segment);
    } else {
      failed_ = Cat("frame 0: ", plan_.at("message").get<std::string>());
    }
    return FinishTask(first);
  }

 private:
  // Frame 0, trained once for every task of the run (PlanOnce) into OUT/plan.
  void PlanFirstFrame() {
    const std::string fingerprint = HashBytes(nlohmann::json{
        {"options", IdentityOptions(options_)},
        {"take", TakeFingerprint(take_dir_)}}.dump());
    const StoredPlan stored =
        PlanOnce(out_, kFramesCommand, fingerprint, task_, [this](std::vector<std::string>* files) {
          scene_.emplace(LoadSplatScene(take_dir_, out_, options_, TaskFrames()));
          return TrainFirstFrame(files);
        });
    plan_ = stored.plan;
    plan_origin_ = stored.made ? Cat("made by this task (", stored.why, ")")
                               : Cat("read from ", (out_ / kPlanDir).string(), " (made by ",
                                     stored.made_by, ")");
    std::printf("splat: frame 0 (the run's plan): %s\n", plan_origin_.c_str());
  }

  nlohmann::json TrainFirstFrame(std::vector<std::string>* files) {
    SplatScene first = *scene_;
    first.later_frames.clear();
    SplatOptions options = options_;
    options.minutes = 0;  // iterations alone decide frame 0's bytes
    const fs::path dir = out_ / kPlanDir;
    Trainer trainer(first, options, dir);
    const SplatSummary summary = trainer.Run(nullptr);
    std::error_code ec;
    if (fs::exists(dir / "gaussians.bin", ec)) {
      files->push_back("model.json");
      files->push_back("gaussians.bin");
      for (const auto& entry : fs::directory_iterator(dir / "cameras", ec))
        files->push_back((fs::path("cameras") / entry.path().filename()).string());
      std::sort(files->begin(), files->end());
    }
    std::vector<int64_t> sets = {scene_->plan.value("frame_set", int64_t{0})};
    for (const SplatFrame& later : scene_->later_frames) sets.push_back(later.set);
    return {{"sets", sets},
            {"termination", ToString(summary.termination)},
            {"message", summary.message},
            {"frame0", summary.frames.empty() ? nlohmann::json() : summary.frames.front().ToJson()},
            {"state", trainer.FirstFrameState()},
            {"plan", summary.plan},
            {"seed_points", summary.seed_points},
            {"cloned", summary.cloned},
            {"split", summary.split},
            {"floored_scales", summary.floored_scales},
            {"train_psnr_db", summary.train_psnr_db}};
  }

  void StartRecords() {
    if (scene_->later_frames.empty())
      Fail("--segment-frames splits the frames after the first; the run has one frame set");
    std::vector<int64_t> sets;
    for (const SplatFrame& later : scene_->later_frames) sets.push_back(later.set);
    records_.emplace(out_, kFramesCommand,
                     nlohmann::json{{"options", IdentityOptions(options_)},
                                    {"take", TakeFingerprint(take_dir_)}},
                     sets);
    nlohmann::json options = IdentityOptions(options_);
    options["take_dir"] = take_dir_.string();
    options["out"] = out_.string();
    records_->WriteRun({{"options", options}, {"plan", plan_.at("plan")}});
  }

  // Whether the task trains a frame of a run of `frames` (frame 0 and its segments' frames): the
  // others' images and seeds are not loaded.
  SplatFramesNeeded TaskFrames() const {
    return [this](int64_t frame, int64_t frames) {
      const std::vector<int64_t> mine = SegmentsOf(frames);
      return frame == 0 || std::find(mine.begin(), mine.end(),
                                     (frame - 1) / options_.segment_frames) != mine.end();
    };
  }

  // The task's segments of a run of `frames`.
  std::vector<int64_t> SegmentsOf(int64_t frames) const {
    std::vector<int64_t> segments((frames - 1 + options_.segment_frames - 1) /
                                  options_.segment_frames);
    std::iota(segments.begin(), segments.end(), int64_t{0});
    return options_.tasks.shard.Of(segments);
  }

  std::vector<int64_t> TaskSegments() {
    const int64_t frames = 1 + static_cast<int64_t>(scene_->later_frames.size());
    segment_count_ = (frames - 1 + options_.segment_frames - 1) / options_.segment_frames;
    return SegmentsOf(frames);
  }

  // The segment's frames in order: each decoded when complete, else trained from its base.
  void TrainSegment(int64_t segment) {
    const int64_t frames = 1 + static_cast<int64_t>(scene_->later_frames.size());
    const int64_t first = 1 + segment * options_.segment_frames;
    const int64_t end = std::min(frames, first + options_.segment_frames);
    Gaussians current;
    for (int64_t f = first; f < end; ++f) {
      const Gaussians& base = f == first ? frame0_ : current;
      const int64_t set = scene_->later_frames[f - 1].set;
      if (!options_.tasks.redo) {
        if (const auto record = records_->Complete(set)) {
          current = ApplySplatDeltaFile(base, SplatDeltaFile(out_, f));
          results_.push_back((*record)["result"]);
          ++skipped_;
          continue;
        }
      }
      const double started = UnixSeconds();
      const int64_t iterations =
          f == first ? options_.SegmentStartIterations() : options_.frame_iterations;
      const SplatSummary trained = trainer_->TrainFromBase(f, base, plan_.at("state"), iterations);
      if (trained.frames.empty()) {
        failed_ = Cat("frame ", f, " (set ", set, "): ", trained.message);
        return;  // the segment's later frames start from this one
      }
      nlohmann::json result = trained.frames.back().ToJson();
      result["base"] = SegmentBase(f, options_.segment_frames);
      result["termination"] = ToString(trained.termination);
      result["message"] = trained.message;
      records_->Record(set, result, {DeltaName(f)}, started, task_);
      results_.push_back(result);
      current = trainer_->gaussians();
    }
  }

  SplatSummary FinishTask(Termination first) {
    const RunState run = ReadRunState(out_);
    const Shard& shard = options_.tasks.shard;
    if (!failed_.empty()) std::printf("splat: not trained: %s\n", failed_.c_str());
    if (shard.whole()) {
      Report local(kFramesCommand);
      return MergeSplatFrames(out_, report_ != nullptr ? report_ : &local);
    }
    const int64_t done = static_cast<int64_t>(results_.size()) - skipped_;
    std::printf(
        "splat: shard %s trained %lld and skipped %lld frame(s) of its segments; the run: %s\n",
        shard.ToString().c_str(), static_cast<long long>(done), static_cast<long long>(skipped_),
        run.Describe().c_str());
    if (run.done()) {
      Report merged(kFramesCommand);
      const SplatSummary all = MergeSplatFrames(out_, &merged);
      std::printf("splat: the run is complete: %s (%s)\n", (out_ / "report.json").c_str(),
                  ToString(all.termination));
    }
    SplatSummary summary;
    if (!failed_.empty()) {
      summary.End(IsUsable(first) ? Termination::kFailure : first, failed_);
    } else {
      summary.End(
          Termination::kSuccess,
          Cat("shard ", shard.ToString(), ": ", done, " frame(s) trained, ", skipped_,
              " complete from an earlier run (", segment_count_, " segment(s) in the run)"));
      for (const nlohmann::json& result : results_) {
        const Termination t = TerminationNamed(result.value("termination", ""));
        if (!IsUsable(t)) summary.End(t, Cat("frame ", result["frame"], ": ", result["message"]));
      }
    }
    if (report_ == nullptr) return summary;
    report_->options() = options_.ToJson();
    report_->plan() = plan_.at("plan");
    report_->metrics()["frames"] = results_;
    report_->metrics()["plan"] = plan_origin_;
    report_->metrics()["run"] = run.Describe();
    const double wall_s = report_->ElapsedSeconds();
    report_->metrics()["timing"] = {{"frames_done", done},
                                    {"frames_skipped", skipped_},
                                    {"wall_s", wall_s},
                                    {"frames_per_minute", 60.0 * done / std::max(wall_s, 1e-9)}};
    report_->metrics()["peak_rss_mb"] = PeakRssMb();
    report_->SetSummary(summary);
    report_->Write(TaskReportPath(out_, shard));
    return summary;
  }

  const fs::path take_dir_, out_;
  const SplatOptions& options_;
  Report* report_;
  const std::string task_ = DescribeTask(options_.tasks.shard);
  std::optional<SplatScene> scene_;
  nlohmann::json plan_;
  std::string plan_origin_;
  std::optional<FrameRecords> records_;
  std::optional<Trainer> trainer_;
  Gaussians frame0_;
  int64_t segment_count_ = 0;
  std::vector<nlohmann::json> results_;  // this task's frames, trained or complete
  int64_t skipped_ = 0;
  std::string failed_;  // the frame that could not be trained, and why
};

// The merged report's frames, series and end state (the model is written by the caller).
void SummariseFrames(const RunState& run, const nlohmann::json& plan, SplatSummary* summary,
                     Report* report) {
  nlohmann::json frames = nlohmann::json::array();
  if (plan.at("frame0").is_object()) frames.push_back(plan.at("frame0"));  // none: no seed
  double largest_mb = 0;
  for (int64_t set : run.sets) {
    const auto record = run.complete.find(set);
    if (record == run.complete.end()) continue;
    frames.push_back(record->second["result"]);
    largest_mb = std::max(largest_mb, record->second["result"].value("megabytes", 0.0));
  }
  for (const nlohmann::json& frame : frames) {
    const int64_t f = frame.value("frame", int64_t{0});
    report->AddPointAt("frame_heldout_psnr_db", frame.value("heldout_psnr_db", 0.0), f, 0);
    report->AddPointAt("frame_heldout_psnr_fg_db", frame.value("heldout_psnr_fg_db", 0.0), f, 0);
    report->AddPointAt("frame_megabytes", frame.value("megabytes", 0.0), f, 0);
  }
  const nlohmann::json last = frames.empty() ? nlohmann::json::object() : frames.back();
  summary->temporal = true;
  summary->heldout_psnr_db = last.value("heldout_psnr_db", 0.0);
  summary->heldout_psnr_fg_db = last.value("heldout_psnr_fg_db", 0.0);
  summary->background_psnr_fg_db = last.value("background_psnr_fg_db", 0.0);
  summary->heldout_ssim = last.value("heldout_ssim", 0.0);
  summary->gaussians = last.value("gaussians", int64_t{0});
  report->metrics() = {{"frames", frames},
                       {"temporal", true},
                       {"largest_delta_megabytes", largest_mb},
                       {"seed_points", plan.at("seed_points")},
                       {"cloned", plan.at("cloned")},
                       {"split", plan.at("split")},
                       {"floored_scales", plan.at("floored_scales")},
                       {"train_psnr_db", plan.at("train_psnr_db")},
                       {"run", run.Describe()},
                       {"timing", {{"frames_by_task", run.frames_by_task}}}};
  if (!run.done()) {
    summary->End(Termination::kFailure, Cat("the run is incomplete: ", run.Describe()));
    return;
  }
  summary->End(TerminationNamed(plan.at("termination").get<std::string>()),
               Cat("frame 0: ", plan.at("message").get<std::string>()));
  if (!summary->IsUsable()) return;
  for (const nlohmann::json& frame : frames) {
    const Termination t =
        TerminationNamed(frame.value("termination", ToString(summary->termination)));
    if (!IsUsable(t)) {
      summary->End(t, Cat("frame ", frame["frame"], ": ", frame["message"]));
      return;
    }
  }
  summary->End(Termination::kNoConvergence,
               Cat(frames.size(), " frames trained for their iterations (frame 0: ",
                   plan.at("frame0").value("iterations", int64_t{0}),
                   "); last frame held-out PSNR ", summary->heldout_psnr_db, " dB (subject ",
                   summary->heldout_psnr_fg_db, " dB, background alone ",
                   summary->background_psnr_fg_db, " dB), ", summary->gaussians, " Gaussians"));
}

}  // namespace

SplatSummary TrainSplatFrames(const fs::path& take_dir, const fs::path& model_dir,
                              const SplatOptions& options, Report* report) {
  options.Check();
  if (options.segment_frames <= 0) Fail("a per-frame splat run needs --segment-frames");
  if (options.threads > 0) omp_set_num_threads(ResolveThreads(options.threads));
  CreateDirectories(model_dir);
  return FrameRun(take_dir, model_dir, options, report).Run();
}

SplatSummary MergeSplatFrames(const fs::path& model_dir, Report* report) {
  const RunState run = ReadRunState(model_dir);
  if (run.command != kFramesCommand) {
    Fail("'", model_dir.string(), "' holds a run of holocap ", run.command, ", not of ",
         kFramesCommand);
  }
  const fs::path plan_file = model_dir / kPlanDir / "plan.json";
  nlohmann::json plan;
  try {
    plan = nlohmann::json::parse(ReadFileToString(plan_file)).at("plan");
  } catch (const nlohmann::json::exception& e) {
    Fail("cannot read the run's plan ", plan_file.string(), ": ", e.what());
  }
  SplatSummary summary;
  summary.plan = run.header.value("plan", nlohmann::json::object());
  report->options() = run.header.value("options", nlohmann::json::object());
  report->plan() = summary.plan;
  SummariseFrames(run, plan, &summary, report);
  if (run.done() && summary.IsUsable()) {
    SplatModel model = SplatModel::Load(model_dir / kPlanDir);
    const int64_t segment_frames = report->options().at("segment_frames").get<int64_t>();
    model.frame_sets = plan.at("sets").get<std::vector<int64_t>>();
    model.frames = static_cast<int64_t>(model.frame_sets.size());
    model.bases = {-1};
    for (int64_t f = 1; f < model.frames; ++f)
      model.bases.push_back(SegmentBase(f, segment_frames));
    model.plan = summary.plan;
    model.Save(model_dir);
    summary.megabytes = static_cast<double>(fs::file_size(model_dir / "gaussians.bin")) / 1e6;
  }
  report->SetSummary(summary);
  report->Write(model_dir / "report.json");
  return summary;
}

}  // namespace holocap
