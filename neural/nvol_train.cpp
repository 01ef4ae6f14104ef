// Training a Neural Volume: random pixel batches across cameras and frames, Adam, held-out
// cameras evaluated against wall time, checkpoints, resume and a divergence guard.
#include <omp.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <deque>
#include <map>
#include <numbers>
#include <numeric>
#include <opencv2/imgproc.hpp>
#include <random>

#include "avatar/camera_score.h"
#include "avatar/image_metrics.h"
#include "avatar/training_data.h"
#include "core/error.h"
#include "core/frame_tasks.h"
#include "core/fs.h"
#include "core/image.h"
#include "core/progress.h"
#include "core/threads.h"
#include "neural/internal/nvol.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;
using neural::MarchContext;

constexpr int64_t kWarmupIterations = 20;  // of the learning rates (dynamic scenes)
using neural::NvolConfig;
using neural::NvolModel;

// Everything that must be saved and restored together.
struct Snapshot {
  std::vector<torch::Tensor> parameters;
  torch::Tensor backgrounds;
  int64_t iteration = 0;
};

Snapshot TakeSnapshot(NvolModel& model, const torch::Tensor& backgrounds, int64_t iteration) {
  torch::NoGradGuard no_grad;
  Snapshot s;
  for (const auto& p : model->parameters()) s.parameters.push_back(p.detach().clone());
  s.backgrounds = backgrounds.detach().clone();
  s.iteration = iteration;
  return s;
}

void RestoreSnapshot(const Snapshot& s, NvolModel& model, torch::Tensor& backgrounds) {
  torch::NoGradGuard no_grad;
  auto params = model->parameters();
  for (size_t i = 0; i < params.size(); ++i) params[i].copy_(s.parameters[i]);
  backgrounds.copy_(s.backgrounds);
}

struct Evaluation {
  double psnr_db = 0;
  double psnr_fg_db = 0;
  double background_psnr_fg_db = 0;  // the backgrounds alone, in the same pixels
  double psnr_white_db = std::numeric_limits<double>::quiet_NaN();  // on white (alpha takes)
  double ssim = 0;
  double alpha_outside = 0;  // mean alpha of held-out pixels that see the box outside the
                             // subject's grown silhouette: fog the training views cannot see
};

// The terms of one training step, logged as series of the report.
struct StepTerms {
  double photometric = 0, alpha_prior = 0, tv = 0, kl = 0, silhouette = 0;
  double alpha_inside = 0, alpha_outside = 0;  // mean ray alpha in / out of the silhouettes
  double gain_drift = 0, bias_drift = 0;       // largest |gain - 1|, |bias| over the cameras
  double warp_voxels = 0;                      // mean displacement of the warp, template voxels
};

class Trainer {
 public:
  // `cpu_origin`: the process's CPU seconds when the run began (before its data was loaded).
  Trainer(const TrainingData& data, const NeuralVolumeOptions& options, const fs::path& model_dir,
          double cpu_origin)
      : data_(data),
        options_(options),
        model_dir_(model_dir),
        rng_(options.seed),
        cpu_(cpu_origin) {
    config_.dynamic = data.dynamic;
    config_.grid = options.grid;
    config_.latent_dim = options.latent_dim;
    config_.warp_count = options.warp_count;
    config_.warp_grid = options.warp_grid;
    config_.encoder_views = static_cast<int>(data.encoder_views.size());
    config_.encoder_width = options.encoder_width;
    const auto& first = data.views.front().camera;
    config_.encoder_height = std::max(
        16, static_cast<int>(std::lround(options.encoder_width *
                                         static_cast<double>(first.height()) / first.width())));
    config_.decoder_channels = options.decoder_channels;
    config_.cameras = static_cast<int>(data.views.size());
    config_.frames = data.dynamic ? static_cast<int>(data.sets.size()) : 0;
    config_.box_min = data.box.min;
    config_.box_max = data.box.max;
    torch::manual_seed(options.seed);
    model_ = NvolModel(config_);
    step_m_ = options.step_voxels * data.box.size().minCoeff() / options.grid;

    training_ = data.TrainingViews();
    heldout_ = data.HeldoutViews();
    // Pixels of all views, concatenated: view v's pixel p is row offset_[v] + p.
    for (const auto& view : data.views) {
      offset_.push_back(total_pixels_);
      total_pixels_ += static_cast<int64_t>(view.camera.width()) * view.camera.height();
    }
    // Backgrounds [P, 3] BGR in [0, 1].
    std::vector<torch::Tensor> backgrounds;
    for (const auto& view : data.views)
      backgrounds.push_back(ImageTensor(view.background).view({-1, 3}));
    backgrounds_ = torch::cat(backgrounds).contiguous();
    if (options.learn_background) backgrounds_.set_requires_grad(true);
    // Rays of every pixel of every view, and the pixels whose rays meet the box.
    for (const auto& view : data.views) {
      all_rays_.push_back(CameraRaysAllPixels(view.camera, data.box_min_f(), data.box_max_f()));
      std::vector<int32_t> pixels;
      for (int64_t i = 0; i < all_rays_.back().size(); ++i) {
        if (all_rays_.back().t_far[i] > all_rays_.back().t_near[i])
          pixels.push_back(static_cast<int32_t>(i));
      }
      box_pixels_.push_back(std::move(pixels));
    }
    for (int v : heldout_) {
      const CameraModel& lens = data.views[v].camera;
      if (lens.lensmodel() == "LENSMODEL_PINHOLE") continue;
      PinholeScoring scoring{Undistortion(lens), {}, {}};
      scoring.rays =
          CameraRaysAllPixels(scoring.undistortion.pinhole, data.box_min_f(), data.box_max_f());
      for (int64_t i = 0; i < scoring.rays.size(); ++i) {
        if (scoring.rays.t_far[i] > scoring.rays.t_near[i])
          scoring.box_pixels.push_back(static_cast<int32_t>(i));
      }
      pinhole_scoring_.emplace(v, std::move(scoring));
    }
    // The backgrounds are refined only where no frame shows the subject (silhouettes grown by
    // 4 pixels): a per-pixel background would otherwise absorb a subject that moves little
    // (or not at all) and leave the volume empty, which held-out cameras then expose.
    if (options.learn_background) {
      std::vector<torch::Tensor> learnable;
      for (size_t v = 0; v < data.views.size(); ++v) {
        cv::Mat subject_anywhere = cv::Mat::zeros(data.views[v].background.size(), CV_8UC1);
        for (size_t f = 0; f < data.sets.size(); ++f) subject_anywhere |= data.masks[f][v];
        cv::dilate(subject_anywhere, subject_anywhere, cv::Mat(), cv::Point(-1, -1), 4);
        cv::Mat free;
        cv::compare(subject_anywhere, 0, free, cv::CmpTypes::CMP_EQ);
        free.convertTo(free, CV_32FC1, 1.0 / 255.0);
        learnable.push_back(torch::from_blob(free.data,
                                             {static_cast<int64_t>(free.rows) * free.cols, 1},
                                             torch::kFloat32)
                                .clone());
      }
      background_learnable_ = torch::cat(learnable).contiguous();
    }
    // Pixels of each frame's training silhouettes (grown by 4 pixels) that see the box: half
    // of every batch is drawn from them so that the subject, a small part of each image, is
    // fitted early.
    subject_pixels_.resize(data.sets.size());
    for (size_t f = 0; f < data.sets.size(); ++f) {
      for (int v : training_) {
        cv::Mat grown;
        cv::dilate(data.masks[f][v], grown, cv::Mat(), cv::Point(-1, -1), 4);
        for (int32_t p : box_pixels_[v]) {
          if (grown.data[p] != 0) subject_pixels_[f].emplace_back(v, p);
        }
      }
    }
    for (int v : training_) {
      if (box_pixels_[v].empty())
        Fail("training camera ", data.views[v].name, " does not see the volume's box");
    }
    // Frame images as float tensors [F, V, H, W, 3] and encoder inputs [F, 3E, eh, ew].
    std::vector<torch::Tensor> frames, encoder_inputs;
    for (size_t f = 0; f < data.images.size(); ++f) {
      std::vector<torch::Tensor> views, encoder_views;
      for (const auto& image : data.images[f]) views.push_back(ImageTensor(image).view({-1, 3}));
      frames.push_back(torch::cat(views));
      if (data.dynamic) {
        for (int v : data.encoder_views) {
          cv::Mat small;
          cv::resize(data.images[f][v], small,
                     cv::Size(config_.encoder_width, config_.encoder_height), 0, 0, cv::INTER_AREA);
          encoder_views.push_back(ImageTensor(small).permute({2, 0, 1}) - 0.5);
        }
        encoder_inputs.push_back(torch::cat(encoder_views, 0));
      }
    }
    images_ = torch::stack(frames).contiguous();
    if (data.dynamic) encoder_inputs_ = torch::stack(encoder_inputs).contiguous();
    // Evaluation frames, spread over the take.
    const int64_t count = std::min<int64_t>(options.eval_frames, data.sets.size());
    for (int64_t i = 0; i < count; ++i)
      eval_frames_.push_back(i * static_cast<int64_t>(data.sets.size()) / count);
    MakeOptimizer(1.0);
  }

  nlohmann::json Modules() const {
    nlohmann::json modules = nlohmann::json::array();
    for (const auto& child : model_->named_children()) modules.push_back(child.key());
    for (const auto& param : model_->named_parameters(false)) modules.push_back(param.key());
    return modules;
  }
  bool Has(const std::string& name) const {
    for (const auto& child : model_->named_children()) {
      if (child.key() == name) return true;
    }
    return false;
  }

  NeuralVolumeSummary Run(Report* report);
  void Judge(int64_t iteration, NeuralVolumeSummary* summary) const;

 private:
  // What the model is built of and trained with, into the summary's plan (the take's plan first).
  void DescribePlan(NeuralVolumeSummary* summary) const;
  torch::Tensor TotalVariation(const torch::Tensor& rgba) const;
  std::pair<double, double> MeanAlphaInsideOutside(const torch::Tensor& alpha, int64_t f,
                                                   const std::vector<int64_t>& camera,
                                                   const std::vector<int64_t>& pixel_index) const;
  static torch::Tensor ImageTensor(const cv::Mat& bgr8) {
    cv::Mat f;
    bgr8.convertTo(f, CV_32FC3, 1.0 / 255.0);
    return torch::from_blob(f.data, {f.rows, f.cols, 3}, torch::kFloat32).clone();
  }

  // Rates scaled by `scale` (the divergence guard lowers it).
  void MakeOptimizer(double scale) {
    const double network_lr = options_.learning_rate * scale;
    const double grid_lr =
        (data_.dynamic ? options_.template_learning_rate : options_.static_learning_rate) * scale;
    std::vector<torch::Tensor> network, grid, calibration;
    for (const auto& p : model_->named_parameters()) {
      if (p.key() == "gain" || p.key() == "bias")
        calibration.push_back(p.value());
      else if (p.key() == "grid")
        grid.push_back(p.value());
      else
        network.push_back(p.value());
    }
    std::vector<torch::optim::OptimizerParamGroup> groups;
    groups.emplace_back(grid, std::make_unique<torch::optim::AdamOptions>(grid_lr));
    if (!network.empty())
      groups.emplace_back(network, std::make_unique<torch::optim::AdamOptions>(network_lr));
    groups.emplace_back(calibration, std::make_unique<torch::optim::AdamOptions>(network_lr));
    if (backgrounds_.requires_grad()) {
      groups.emplace_back(std::vector<torch::Tensor>{backgrounds_},
                          std::make_unique<torch::optim::AdamOptions>(network_lr));
    }
    base_lrs_.clear();
    for (auto& group : groups)
      base_lrs_.push_back(static_cast<torch::optim::AdamOptions&>(group.options()).lr());
    optimizer_ = std::make_unique<torch::optim::Adam>(std::move(groups),
                                                      torch::optim::AdamOptions(network_lr));
  }

  // Cosine decay of every group's rate to a tenth over the run (`progress` in [0, 1]): the
  // early steps move the volume fast, the late ones refine it without the noise of a full
  // rate. Dynamic scenes first warm up linearly over `steps` iterations: Adam's first steps
  // move every weight of the decoder's transposed convolutions by the full rate at once, and
  // their product threw the density out by orders of magnitude within three steps.
  void ScheduleLearningRate(double progress, int64_t steps) {
    double factor =
        0.1 + 0.45 * (1.0 + std::cos(std::numbers::pi * std::clamp(progress, 0.0, 1.0)));
    if (data_.dynamic && steps < kWarmupIterations)
      factor *= static_cast<double>(steps + 1) / (kWarmupIterations + 1);
    auto& groups = optimizer_->param_groups();
    for (size_t i = 0; i < groups.size() && i < base_lrs_.size(); ++i) {
      static_cast<torch::optim::AdamOptions&>(groups[i].options()).lr(base_lrs_[i] * factor);
    }
  }

  // The latent of frame f: sampled (training) or the mean (evaluation); adds its KL.
  torch::Tensor Latent(int64_t f, bool sample, torch::Tensor* kl) {
    if (!data_.dynamic) return {};
    auto [mu, log_sigma] = model_->encoder->forward(encoder_inputs_.narrow(0, f, 1));
    if (kl != nullptr) {
      *kl = 0.5 * (mu.pow(2) + (2 * log_sigma).exp() - 1 - 2 * log_sigma).sum(1).mean();
    }
    if (model_->frame_codes.defined()) mu = mu + model_->frame_codes.narrow(0, f, 1);
    if (!sample) return mu;
    return mu + log_sigma.exp() * torch::randn_like(mu);
  }

  double TrainStep(int64_t iteration, double* photometric, double* samples_per_ray);
  // Template coordinates of the identity warp [W, W, W, 3] (voxel centres, x y z).
  static torch::Tensor IdentityWarp(int64_t side) {
    torch::Tensor axis = (torch::arange(side, torch::kFloat32) + 0.5) / side;
    auto mesh = torch::meshgrid({axis, axis, axis}, "ij");
    return torch::stack({mesh[2], mesh[1], mesh[0]}, -1);
  }
  // Held-out PSNR/SSIM; with `write_images`, each held-out view is also written to
  // model_dir/heldout/ as the rendering beside the truth, for a person to look at.
  Evaluation Evaluate(bool write_images = false);
  void SaveCheckpoint(int64_t iteration);
  bool LoadCheckpoint(int64_t* iteration);
  void SaveModel(const nlohmann::json& plan);

  const TrainingData& data_;
  NeuralVolumeOptions options_;
  fs::path model_dir_;
  std::mt19937_64 rng_;
  NvolConfig config_;
  NvolModel model_{nullptr};
  double step_m_ = 0;
  std::vector<int> training_, heldout_;
  std::vector<int64_t> offset_;
  int64_t total_pixels_ = 0;
  torch::Tensor backgrounds_, images_, encoder_inputs_;
  torch::Tensor background_learnable_;  // [P, 1]: 1 where no frame's silhouette reaches
  std::vector<RayBatch> all_rays_;
  std::vector<std::vector<int32_t>> box_pixels_;
  // A held-out camera with a distorting lens is scored in the pinhole of its intrinsics core,
  // as the splats and `holocap export web` score it: its rays there, the pixels of them that
  // meet the box, and the resampling of its images (keyed by view).
  struct PinholeScoring {
    Undistortion undistortion;
    RayBatch rays;
    std::vector<int32_t> box_pixels;
  };
  std::map<int, PinholeScoring> pinhole_scoring_;
  std::vector<std::vector<std::pair<int, int32_t>>> subject_pixels_;  // [frame] (view, pixel)
  std::vector<int64_t> eval_frames_;
  CpuClock cpu_;  // since the run began, held-out scoring excluded
  std::unique_ptr<torch::optim::Adam> optimizer_;
  std::vector<double> base_lrs_;  // of each group, before the schedule
  double lr_scale_ = 1;
  StepTerms last_terms_;
};

// Total variation of colour and of density in optical depth per voxel.
torch::Tensor Trainer::TotalVariation(const torch::Tensor& rgba) const {
  const torch::Tensor normalised =
      rgba / torch::tensor({1.0f, 1.0f, 1.0f, static_cast<float>(config_.density_scale())});
  const auto along = [&](int axis) {
    return (normalised.narrow(axis, 1, config_.grid - 1) -
            normalised.narrow(axis, 0, config_.grid - 1))
        .pow(2)
        .mean();
  };
  // One expression, as the autograd graph's shape sets the order gradients are summed in.
  return along(0) + along(1) + along(2);
}

// Mean ray alpha of a batch's pixels inside and outside their training silhouettes.
std::pair<double, double> Trainer::MeanAlphaInsideOutside(
    const torch::Tensor& alpha, int64_t f, const std::vector<int64_t>& camera,
    const std::vector<int64_t>& pixel_index) const {
  const float* a = alpha.contiguous().data_ptr<float>();
  double in_sum = 0, out_sum = 0;
  int64_t in_count = 0, out_count = 0;
  for (size_t i = 0; i < camera.size(); ++i) {
    const int32_t p = static_cast<int32_t>(pixel_index[i] - f * total_pixels_ - offset_[camera[i]]);
    if (data_.masks[f][camera[i]].data[p] != 0) {
      in_sum += a[i];
      ++in_count;
    } else {
      out_sum += a[i];
      ++out_count;
    }
  }
  return {in_count > 0 ? in_sum / in_count : 0.0, out_count > 0 ? out_sum / out_count : 0.0};
}

double Trainer::TrainStep(int64_t iteration, double* photometric, double* samples_per_ray) {
  optimizer_->zero_grad();
  const int64_t frames = static_cast<int64_t>(data_.sets.size());
  const int per_frame = options_.rays_per_batch / options_.frames_per_batch;
  std::uniform_int_distribution<int64_t> pick_frame(0, frames - 1);
  std::uniform_real_distribution<float> unit(0.0f, 1.0f);
  int64_t total_pixels = 0;
  for (int v : training_) total_pixels += box_pixels_[v].size();
  torch::Tensor loss = torch::zeros({});
  double photo_sum = 0, samples = 0;
  StepTerms terms;
  std::vector<std::unique_ptr<MarchContext>> contexts;
  for (int b = 0; b < options_.frames_per_batch; ++b) {
    const int64_t f = data_.dynamic ? pick_frame(rng_) : 0;
    auto context = std::make_unique<MarchContext>();
    context->box_min = data_.box_min_f();
    context->box_max = data_.box_max_f();
    context->occupancy = &data_.occupancy[f];
    context->options.step_m = static_cast<float>(step_m_);
    context->options.min_transmittance = static_cast<float>(options_.min_transmittance);
    context->rays.Resize(per_frame);
    std::vector<int64_t> camera(per_frame), pixel_index(per_frame);
    std::uniform_int_distribution<int64_t> pick_pixel(0, total_pixels - 1);
    const auto& subject = subject_pixels_[f];
    for (int i = 0; i < per_frame; ++i) {
      int v = training_.front();
      int32_t p = 0;
      if (i % 2 == 0 && !subject.empty()) {
        const auto& pick =
            subject[std::uniform_int_distribution<size_t>(0, subject.size() - 1)(rng_)];
        v = pick.first;
        p = pick.second;
      } else {
        // Uniform over the pixels of all training cameras that see the box.
        int64_t k = pick_pixel(rng_);
        for (int candidate : training_) {
          if (k < static_cast<int64_t>(box_pixels_[candidate].size())) {
            v = candidate;
            break;
          }
          k -= box_pixels_[candidate].size();
        }
        p = box_pixels_[v][k];
      }
      const auto& source = all_rays_[v];
      for (int a = 0; a < 3; ++a) {
        context->rays.origin[3 * i + a] = source.origin[3 * p + a];
        context->rays.direction[3 * i + a] = source.direction[3 * p + a];
      }
      context->rays.t_near[i] = source.t_near[p];
      context->rays.t_far[i] = source.t_far[p];
      context->rays.jitter[i] = options_.jitter ? unit(rng_) : 0.0f;
      camera[i] = v;
      pixel_index[i] = f * total_pixels_ + offset_[v] + p;
    }
    torch::Tensor kl;
    torch::Tensor latent = Latent(f, /*sample=*/true, data_.dynamic ? &kl : nullptr);
    torch::Tensor rgba = model_->DecodeRgba(latent);
    torch::Tensor warp = model_->DecodeWarp(latent);
    auto marched = neural::MarchRays(rgba, warp, context.get());
    torch::Tensor rgb = marched[0], alpha = marched[1].unsqueeze(1);
    torch::Tensor cameras = torch::from_blob(camera.data(), {per_frame}, torch::kInt64).clone();
    torch::Tensor pixels = torch::from_blob(pixel_index.data(), {per_frame}, torch::kInt64).clone();
    torch::Tensor target = images_.view({-1, 3}).index_select(0, pixels);
    torch::Tensor background = backgrounds_.index_select(0, pixels.remainder(total_pixels_));
    torch::Tensor prediction = model_->gain.index_select(0, cameras) * rgb +
                               model_->bias.index_select(0, cameras) * alpha +
                               (1 - alpha) * background;
    torch::Tensor photo = (prediction - target).pow(2).mean();
    // The beta prior of the paper on ray alpha, zero at alpha 0 and 1.
    torch::Tensor prior =
        (torch::log(0.1 + alpha) + torch::log(0.1 + 1 - alpha) - std::log(0.1) - std::log(1.1))
            .mean();
    torch::Tensor tv = TotalVariation(rgba);
    torch::Tensor frame_loss =
        photo + options_.alpha_prior_weight * prior + options_.tv_weight * tv;
    torch::Tensor silhouette_term, warp_term;
    if (data_.dynamic) frame_loss = frame_loss + options_.kl_weight * kl;
    if (options_.silhouette_weight > 0) {
      // The silhouettes of the training views (alpha, else the clean plate, else gt/masks, else a
      // threshold: the plan names the source): opaque inside, empty outside.
      std::vector<float> inside(per_frame);
      for (int i = 0; i < per_frame; ++i) {
        const int32_t p =
            static_cast<int32_t>(pixel_index[i] - f * total_pixels_ - offset_[camera[i]]);
        inside[i] = data_.masks[f][camera[i]].data[p] != 0 ? 1.0f : 0.0f;
      }
      torch::Tensor silhouette =
          torch::from_blob(inside.data(), {per_frame, 1}, torch::kFloat32).clone();
      silhouette_term = (alpha - silhouette).pow(2).mean();
      frame_loss = frame_loss + options_.silhouette_weight * silhouette_term;
    }
    if (warp.defined() && options_.warp_prior_weight > 0) {
      warp_term = (warp - IdentityWarp(warp.size(0))).pow(2).sum(-1).mean();
      frame_loss = frame_loss + options_.warp_prior_weight * warp_term;
    }
    loss = loss + frame_loss / options_.frames_per_batch;
    photo_sum += photo.item<double>();
    {
      torch::NoGradGuard no_grad;
      const double share = 1.0 / options_.frames_per_batch;
      terms.alpha_prior += share * prior.item<double>();
      terms.tv += share * tv.item<double>();
      if (kl.defined()) terms.kl += share * kl.item<double>();
      if (silhouette_term.defined()) terms.silhouette += share * silhouette_term.item<double>();
      const auto [inside, outside] = MeanAlphaInsideOutside(alpha, f, camera, pixel_index);
      terms.alpha_inside += share * inside;
      terms.alpha_outside += share * outside;
      if (warp.defined())
        terms.warp_voxels += share *
                             (warp - IdentityWarp(warp.size(0))).norm(2, -1).mean().item<double>() *
                             config_.grid;
    }
    samples += context->outputs.MeanSamples();
    contexts.push_back(std::move(context));
  }
  const double value = loss.item<double>();
  if (std::isfinite(value)) {
    loss.backward();
    if (backgrounds_.requires_grad() && backgrounds_.grad().defined())
      backgrounds_.mutable_grad().mul_(background_learnable_);
    optimizer_->step();
    // The first training camera is the colour reference: its calibration stays the identity
    // (gain and bias are otherwise ambiguous with the volume's colours). Held-out cameras
    // never receive a gradient and stay at the identity too.
    torch::NoGradGuard no_grad;
    model_->gain[training_.front()].fill_(1.0);
    model_->bias[training_.front()].fill_(0.0);
  }
  *photometric = photo_sum / options_.frames_per_batch;
  *samples_per_ray = samples / options_.frames_per_batch;
  terms.photometric = *photometric;
  {
    torch::NoGradGuard no_grad;
    terms.gain_drift = (model_->gain - 1).abs().max().item<double>();
    terms.bias_drift = model_->bias.abs().max().item<double>();
  }
  last_terms_ = terms;
  return value;
}

Evaluation Trainer::Evaluate(bool write_images) {
  torch::NoGradGuard no_grad;
  Evaluation result;
  if (heldout_.empty()) return result;
  const CpuClock::Excluded scoring(&cpu_);
  double mse_sum = 0, mse_fg_sum = 0, mse_background_sum = 0, ssim_sum = 0, alpha_outside_sum = 0;
  // A take whose silhouettes are its alpha is also scored as its dataset publishes (on white).
  const bool alpha_take = data_.alpha_masks;
  double mse_white_sum = 0;
  int count = 0;
  for (int64_t f : eval_frames_) {
    torch::Tensor latent = Latent(f, /*sample=*/false, nullptr);
    torch::Tensor rgba = model_->DecodeRgba(latent).contiguous();
    torch::Tensor warp = model_->DecodeWarp(latent);
    if (warp.defined()) warp = warp.contiguous();
    for (int v : heldout_) {
      const int h = data_.views[v].camera.height(), w = data_.views[v].camera.width();
      const auto pinhole = pinhole_scoring_.find(v);
      const PinholeScoring* scoring =
          pinhole == pinhole_scoring_.end() ? nullptr : &pinhole->second;
      MarchContext context;
      context.box_min = data_.box_min_f();
      context.box_max = data_.box_max_f();
      context.occupancy = &data_.occupancy[f];
      context.options.step_m = static_cast<float>(step_m_);
      context.options.min_transmittance = static_cast<float>(options_.min_transmittance);
      context.rays = scoring != nullptr ? scoring->rays : all_rays_[v];
      auto out = neural::MarchRays(rgba, warp, &context);
      torch::Tensor alpha = out[1].unsqueeze(1);
      // The view's background (learned where training cameras see it), in the scored geometry.
      cv::Mat background(h, w, CV_32FC3);
      std::memcpy(background.data,
                  backgrounds_.narrow(0, offset_[v], static_cast<int64_t>(h) * w)
                      .detach()
                      .contiguous()
                      .data_ptr<float>(),
                  sizeof(float) * h * w * 3);
      cv::Mat truth, silhouette = data_.masks[f][v];
      if (scoring != nullptr) {
        background = scoring->undistortion.Color(background);
        scoring->undistortion.Color(data_.images[f][v]).convertTo(truth, CV_32FC3, 1.0 / 255.0);
        silhouette = scoring->undistortion.Mask(silhouette);
      } else {
        data_.images[f][v].convertTo(truth, CV_32FC3, 1.0 / 255.0);
      }
      const torch::Tensor background_tensor =
          torch::from_blob(background.data, {static_cast<int64_t>(h) * w, 3}, torch::kFloat32);
      torch::Tensor prediction = (out[0] + (1 - alpha) * background_tensor).clamp(0, 1);
      cv::Mat predicted(h, w, CV_32FC3);
      std::memcpy(predicted.data, prediction.contiguous().data_ptr<float>(),
                  sizeof(float) * h * w * 3);
      // The subject's silhouette in the held-out view, grown by 3 pixels.
      cv::Mat mask;
      cv::dilate(silhouette, mask, cv::Mat(), cv::Point(-1, -1), 3);
      mse_sum += std::pow(10.0, -PsnrDb(predicted, truth) / 10.0);
      mse_fg_sum += std::pow(10.0, -PsnrDb(predicted, truth, mask) / 10.0);
      if (alpha_take) {
        cv::Mat on_white(h, w, CV_32FC3), coverage, truth_white;
        const torch::Tensor white = (out[0] + (1 - alpha)).clamp(0, 1).contiguous();
        std::memcpy(on_white.data, white.data_ptr<float>(), sizeof(float) * h * w * 3);
        silhouette.convertTo(coverage, CV_32F, 1.0 / 255.0);
        cv::cvtColor(coverage, coverage, cv::COLOR_GRAY2BGR);
        truth_white = truth.mul(coverage) + (cv::Scalar::all(1.0) - coverage);
        mse_white_sum += std::pow(10.0, -PsnrDb(on_white, truth_white) / 10.0);
      }
      {
        const float* a = out[1].contiguous().data_ptr<float>();
        double sum = 0;
        int64_t n = 0;
        for (int32_t p : scoring != nullptr ? scoring->box_pixels : box_pixels_[v]) {
          if (mask.data[p] != 0) continue;
          sum += a[p];
          ++n;
        }
        if (n > 0) alpha_outside_sum += sum / n;
      }
      cv::Mat plain = data_.views[v].background;
      if (scoring != nullptr) plain = scoring->undistortion.Color(plain);
      plain.convertTo(plain, CV_32FC3, 1.0 / 255.0);
      mse_background_sum += std::pow(10.0, -PsnrDb(plain, truth, mask) / 10.0);
      ssim_sum += Ssim(predicted, truth);
      ++count;
      if (write_images) {
        cv::Mat side_by_side, image8;
        cv::hconcat(predicted, truth, side_by_side);
        side_by_side.convertTo(image8, CV_8UC3, 255.0);
        CreateDirectories(model_dir_ / "heldout");
        WritePng(model_dir_ / "heldout" / Cat(data_.views[v].name, "_frame", data_.sets[f], ".png"),
                 image8);
      }
    }
  }
  // PSNR of the mean squared error over every evaluated image (not the mean of PSNRs).
  result.psnr_db = -10.0 * std::log10(mse_sum / count);
  result.psnr_fg_db = -10.0 * std::log10(mse_fg_sum / count);
  result.background_psnr_fg_db = -10.0 * std::log10(mse_background_sum / count);
  if (alpha_take) result.psnr_white_db = -10.0 * std::log10(mse_white_sum / count);
  result.ssim = ssim_sum / count;
  result.alpha_outside = alpha_outside_sum / count;
  return result;
}

void Trainer::SaveCheckpoint(int64_t iteration) {
  CreateDirectories(model_dir_);
  const fs::path tmp = model_dir_ / "checkpoint.pt.tmp";
  {
    torch::serialize::OutputArchive archive;
    model_->save(archive);
    archive.write("backgrounds", backgrounds_.detach());
    archive.write("iteration", torch::tensor(iteration));
    archive.write("lr_scale", torch::tensor(lr_scale_));
    torch::serialize::OutputArchive optimizer_archive;
    optimizer_->save(optimizer_archive);
    archive.write("optimizer", optimizer_archive);
    archive.save_to(tmp.string());
  }
  fs::rename(tmp, model_dir_ / "checkpoint.pt");
}

bool Trainer::LoadCheckpoint(int64_t* iteration) {
  const fs::path file = model_dir_ / "checkpoint.pt";
  if (!fs::exists(file)) return false;
  try {
    torch::serialize::InputArchive archive;
    archive.load_from(file.string());
    model_->load(archive);
    torch::Tensor backgrounds, it, scale;
    archive.read("backgrounds", backgrounds);
    archive.read("iteration", it);
    archive.read("lr_scale", scale);
    {
      torch::NoGradGuard no_grad;
      backgrounds_.copy_(backgrounds);
    }
    lr_scale_ = scale.item<double>();
    MakeOptimizer(lr_scale_);
    torch::serialize::InputArchive optimizer_archive;
    archive.read("optimizer", optimizer_archive);
    optimizer_->load(optimizer_archive);
    *iteration = it.item<int64_t>();
  } catch (const c10::Error& e) {
    Fail("cannot resume from ", file.string(),
         " (a checkpoint of another configuration?): ", e.what_without_backtrace());
  }
  return true;
}

void Trainer::SaveModel(const nlohmann::json& plan) {
  torch::NoGradGuard no_grad;
  CreateDirectories(model_dir_ / "cameras");
  CreateDirectories(model_dir_ / "backgrounds");
  torch::save(model_, (model_dir_ / "model.pt").string());
  if (!data_.occupancy.empty() && !data_.occupancy.front().empty()) {
    // Training never sampled outside these cells: playback must skip them too.
    const int64_t cells = data_.occupancy.front().size;
    torch::Tensor occupancy = torch::zeros(
        {static_cast<int64_t>(data_.occupancy.size()), cells * cells * cells}, torch::kUInt8);
    for (size_t f = 0; f < data_.occupancy.size(); ++f) {
      std::memcpy(occupancy[f].data_ptr<uint8_t>(), data_.occupancy[f].occupied.data(),
                  cells * cells * cells);
    }
    torch::save(occupancy, (model_dir_ / "occupancy.pt").string());
  }
  if (data_.dynamic) {
    std::vector<torch::Tensor> latents;
    for (int64_t f = 0; f < static_cast<int64_t>(data_.sets.size()); ++f)
      latents.push_back(Latent(f, false, nullptr));
    torch::save(torch::cat(latents, 0), (model_dir_ / "latents.pt").string());
  }
  nlohmann::json cameras = nlohmann::json::array();
  for (size_t v = 0; v < data_.views.size(); ++v) {
    const auto& view = data_.views[v];
    view.camera.Write(model_dir_ / "cameras" / (view.name + ".cameramodel"));
    cameras.push_back(view.name);
    const int h = view.camera.height(), w = view.camera.width();
    torch::Tensor bg =
        (backgrounds_.narrow(0, offset_[v], static_cast<int64_t>(h) * w).clamp(0, 1) * 255)
            .round()
            .to(torch::kUInt8)
            .contiguous();
    cv::Mat image(h, w, CV_8UC3, bg.data_ptr<uint8_t>());
    WritePng(model_dir_ / "backgrounds" / (view.name + ".png"), image.clone());
  }
  nlohmann::json json = {{"method", "nvol"},     {"config", config_.ToJson()},
                         {"cameras", cameras},   {"frame_sets", data_.sets},
                         {"modules", Modules()}, {"plan", plan}};
  WriteFileAtomic(model_dir_ / "model.json", json.dump(2) + "\n");
}

void Trainer::DescribePlan(NeuralVolumeSummary* out) const {
  NeuralVolumeSummary& summary = *out;
  summary.plan = data_.plan;
  summary.built_encoder = Has("encoder");
  summary.built_warp = Has("warp");
  summary.plan["modules"] = Modules();
  if (!data_.dynamic) {
    nlohmann::json& left_out = summary.plan["left_out"];
    left_out["encoder"] = "one static frame: no latent to infer";
    left_out["warp field"] = "nothing moves";
    left_out["template decoder"] = "the RGBA grid itself is optimised";
  }
  summary.plan["device"] = "cpu (the ray marcher is CPU code)";
  nlohmann::json losses = {{"photometric", 1.0},
                           {"alpha_prior", options_.alpha_prior_weight},
                           {"total_variation", options_.tv_weight}};
  if (options_.silhouette_weight > 0) losses["silhouette"] = options_.silhouette_weight;
  if (data_.dynamic) {
    losses["kl"] = options_.kl_weight;
    losses["warp_prior"] = options_.warp_prior_weight;
  }
  summary.plan["losses"] = losses;
  summary.plan["step_m"] = step_m_;
  if (!pinhole_scoring_.empty()) {
    summary.plan["heldout_scoring"] =
        Cat(pinhole_scoring_.size(),
            " held-out camera(s) with a distorting lens scored in the pinhole of the lens's "
            "intrinsics core (images, silhouettes and backgrounds resampled there), as splats "
            "and `holocap export web` score them");
  }
}

// How a run that did not diverge ended: not finite, a subject no better than the background
// alone (DEGENERATE), or the budget spent while the loss still fell.
void Trainer::Judge(int64_t iteration, NeuralVolumeSummary* summary) const {
  if (!std::isfinite(summary->last_loss) ||
      (!heldout_.empty() && !std::isfinite(summary->heldout_psnr_db))) {
    summary->End(Termination::kFailure, "the loss or the held-out PSNR is not finite");
  } else if (!heldout_.empty() && std::isfinite(summary->background_psnr_fg_db) &&
             summary->heldout_psnr_fg_db <= summary->background_psnr_fg_db) {
    // The model's subject is no closer to the held-out views than the empty background is:
    // it renders fog or nothing where the subject stands, whatever the whole-image PSNR says.
    summary->End(Termination::kDegenerate,
                 Cat("the subject in the held-out views (", summary->heldout_psnr_fg_db,
                     " dB) is no better than the background alone (",
                     summary->background_psnr_fg_db, " dB) after ", iteration,
                     " iterations: the volume does not hold the subject (bounds, silhouettes "
                     "or too short a run)"));
  } else {
    summary->End(Termination::kNoConvergence,
                 heldout_.empty() ? Cat("trained ", iteration, " iterations in ", summary->seconds,
                                        " s (no held-out camera)")
                                  : Cat("trained ", iteration, " iterations in ", summary->seconds,
                                        " s; held-out PSNR ", summary->heldout_psnr_db,
                                        " dB (subject ", summary->heldout_psnr_fg_db,
                                        " dB, background alone ", summary->background_psnr_fg_db,
                                        " dB", OnWhiteClause(summary->heldout_psnr_white_db), ")"));
  }
}

NeuralVolumeSummary Trainer::Run(Report* report) {
  NeuralVolumeSummary summary;
  DescribePlan(&summary);
  if (report != nullptr) {
    report->plan() = summary.plan;
    report->Write(model_dir_ / "report.json");
  }
  int64_t iteration = 0;
  if (options_.resume && LoadCheckpoint(&iteration)) {
    summary.plan["resumed_from_iteration"] = iteration;
    if (report != nullptr) report->plan()["resumed_from_iteration"] = iteration;
  }
  Snapshot snapshot = TakeSnapshot(model_, backgrounds_, iteration);
  const auto start = std::chrono::steady_clock::now();
  auto elapsed = [&] {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  };
  // A CPU budget replaces the wall clock; what loading the data spent of it is gone.
  const bool cpu_budget = options_.cpu_minutes > 0;
  const double budget_s = cpu_budget ? 0.0 : options_.minutes * 60.0;
  const double cpu_start = cpu_.Now();
  const double cpu_span = std::max(options_.cpu_minutes * 60.0 - cpu_start, 1e-9);
  const int64_t first_iteration = iteration;
  Progress progress("nvol train", options_.iterations > 0 ? options_.iterations
                                  : cpu_budget            ? static_cast<int64_t>(cpu_span)
                                                          : static_cast<int64_t>(budget_s));
  std::deque<double> recent;
  std::vector<double> photo_history;
  double running = 0, first_finite_loss = -1;
  double next_eval = 0, next_checkpoint = options_.checkpoint_every_s;
  Evaluation last_eval;
  auto log_eval = [&](int64_t it, bool write_images = false) {
    last_eval = Evaluate(write_images);
    if (report != nullptr && !heldout_.empty()) {
      report->AddPoint("heldout_psnr_db", last_eval.psnr_db, it);
      report->AddPoint("heldout_psnr_fg_db", last_eval.psnr_fg_db, it);
      report->AddPoint("heldout_ssim", last_eval.ssim, it);
      report->AddPoint("heldout_alpha_outside", last_eval.alpha_outside, it);
      report->AddPoint("cpu_s", cpu_.Now(), it);
      report->Write(model_dir_ / "report.json");
    }
  };
  while (true) {
    const double t = elapsed();
    const double cpu_t = cpu_budget ? cpu_.Now() - cpu_start : 0.0;
    if (options_.iterations > 0 && iteration - first_iteration >= options_.iterations) break;
    if (budget_s > 0 && t >= budget_s) break;
    if (cpu_budget && cpu_t >= cpu_span) break;
    const bool eval_due = options_.eval_every_iterations > 0
                              ? (iteration - first_iteration) % options_.eval_every_iterations == 0
                              : t >= next_eval;
    if (eval_due) {
      log_eval(iteration);
      next_eval = t + options_.eval_every_s;
    }
    double photo = 0, samples = 0;
    // Training ends at whichever budget runs out first, and so does the schedule.
    double progress_fraction = 0;
    if (options_.iterations > 0)
      progress_fraction = static_cast<double>(iteration - first_iteration) / options_.iterations;
    if (budget_s > 0) progress_fraction = std::max(progress_fraction, t / budget_s);
    if (cpu_budget) progress_fraction = std::max(progress_fraction, cpu_t / cpu_span);
    ScheduleLearningRate(progress_fraction, iteration);
    const double loss = TrainStep(iteration, &photo, &samples);
    // Against the running mean, or the first loss until there is one: an explosion in the
    // very first steps must not become the reference itself.
    if (first_finite_loss < 0 && std::isfinite(loss)) first_finite_loss = loss;
    const double reference = recent.size() >= 10 ? running : first_finite_loss;
    const bool exploded = reference > 0 && loss > options_.divergence_factor * reference;
    if (!std::isfinite(loss) || exploded) {
      ++summary.divergences;
      RestoreSnapshot(snapshot, model_, backgrounds_);
      lr_scale_ *= 0.5;
      MakeOptimizer(lr_scale_);
      std::fprintf(stderr,
                   "nvol: iteration %lld: loss %g %s; restored the checkpoint of iteration %lld, "
                   "learning rate x%.3g\n",
                   static_cast<long long>(iteration), loss,
                   std::isfinite(loss) ? "exploded" : "is not finite",
                   static_cast<long long>(snapshot.iteration), lr_scale_);
      if (report != nullptr) report->AddPoint("divergence_lr_scale", lr_scale_, iteration);
      iteration = snapshot.iteration;
      recent.clear();
      if (summary.divergences > options_.max_divergences) {
        summary.End(Termination::kFailure,
                    Cat("training diverged ", summary.divergences, " times; stopped"));
        break;
      }
      continue;
    }
    recent.push_back(loss);
    if (recent.size() > 50) recent.pop_front();
    running = std::accumulate(recent.begin(), recent.end(), 0.0) / recent.size();
    photo_history.push_back(photo);
    summary.samples_per_ray = samples;
    ++iteration;
    if (report != nullptr && iteration % 10 == 0) {
      const StepTerms& terms = last_terms_;
      report->AddPoint("loss", photo, iteration);
      report->AddPoint("loss_alpha_prior", terms.alpha_prior, iteration);
      report->AddPoint("loss_tv", terms.tv, iteration);
      report->AddPoint("loss_silhouette", terms.silhouette, iteration);
      if (data_.dynamic) {
        report->AddPoint("loss_kl", terms.kl, iteration);
        report->AddPoint("warp_voxels", terms.warp_voxels, iteration);
      }
      report->AddPoint("train_alpha_inside", terms.alpha_inside, iteration);
      report->AddPoint("train_alpha_outside", terms.alpha_outside, iteration);
      report->AddPoint("gain_drift", terms.gain_drift, iteration);
      report->AddPoint("bias_drift", terms.bias_drift, iteration);
    }
    progress.Update(options_.iterations > 0 ? iteration - first_iteration
                    : cpu_budget            ? static_cast<int64_t>(cpu_t)
                                            : static_cast<int64_t>(t),
                    Cat("it ", iteration, " loss ", photo, " held-out ", last_eval.psnr_db, " dB"));
    if (elapsed() >= next_checkpoint) {
      snapshot = TakeSnapshot(model_, backgrounds_, iteration);
      SaveCheckpoint(iteration);
      next_checkpoint = elapsed() + options_.checkpoint_every_s;
    }
  }
  progress.Finish();
  summary.seconds = elapsed();
  summary.iterations = iteration;
  SaveCheckpoint(iteration);
  log_eval(iteration, /*write_images=*/true);
  const size_t window = std::max<size_t>(1, std::min<size_t>(10, photo_history.size() / 4));
  if (!photo_history.empty()) {
    summary.first_loss =
        std::accumulate(photo_history.begin(), photo_history.begin() + window, 0.0) / window;
    summary.last_loss =
        std::accumulate(photo_history.end() - window, photo_history.end(), 0.0) / window;
  }
  summary.heldout_psnr_db = last_eval.psnr_db;
  summary.heldout_psnr_fg_db = last_eval.psnr_fg_db;
  summary.heldout_psnr_white_db = last_eval.psnr_white_db;
  summary.background_psnr_fg_db = last_eval.background_psnr_fg_db;
  summary.heldout_ssim = last_eval.ssim;
  summary.cpu_s_loading = cpu_start;
  summary.cpu_s_training = cpu_.Now() - cpu_start;
  summary.cpu_s_scoring = cpu_.excluded();
  if (summary.divergences <= options_.max_divergences) Judge(iteration, &summary);
  SaveModel(summary.plan);
  return summary;
}

}  // namespace

NeuralVolumeSummary TrainNeuralVolume(const fs::path& take_dir, const fs::path& model_dir,
                                      const NeuralVolumeOptions& options, Report* report) {
  options.Check();
  if (options.threads > 0) {
    torch::set_num_threads(ResolveThreads(options.threads));
    omp_set_num_threads(ResolveThreads(options.threads));
  }
  const double cpu_origin = CpuSeconds();
  CreateDirectories(model_dir);
  if (report != nullptr) report->options() = options.ToJson();
  TrainingData data = LoadTrainingData(take_dir, options.data_options());
  NeuralVolumeSummary summary;
  try {
    Trainer trainer(data, options, model_dir, cpu_origin);
    summary = trainer.Run(report);
  } catch (const c10::Error& e) {
    // LibTorch reports broken preconditions (shapes, devices) with a backtrace: one line here.
    Fail("neural volume training: ", e.what_without_backtrace());
  }
  if (report != nullptr) {
    report->plan() = summary.plan;
    report->metrics() = TrainingMetrics(summary);
    report->metrics()["samples_per_ray"] = summary.samples_per_ray;
    report->metrics()["cpu_s_loading"] = summary.cpu_s_loading;
    report->metrics()["cpu_s_training"] = summary.cpu_s_training;
    report->metrics()["cpu_s_scoring"] = summary.cpu_s_scoring;
    if (options.cpu_minutes > 0) report->metrics()["cpu_s_budget"] = options.cpu_minutes * 60;
    if (std::isfinite(summary.heldout_psnr_white_db)) {
      report->metrics()["heldout_psnr_white_db"] = summary.heldout_psnr_white_db;
      report->metrics()["heldout_psnr_white_convention"] =
          "composited on white by alpha: NeRF-synthetic's published scores";
    }
    report->SetSummary(summary);
    report->Write(model_dir / "report.json");
  }
  return summary;
}

}  // namespace holocap
