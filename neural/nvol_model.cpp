// Neural Volumes' networks, the marcher as an autograd function, and the "nvol" model kind.
#include <omp.h>

#include <algorithm>
#include <chrono>
#include <cmath>

#include "core/error.h"
#include "core/fs.h"
#include "core/threads.h"
#include "neural/internal/nvol.h"

namespace holocap::neural {
namespace {

namespace F = torch::nn::functional;

int Log2(int value) {
  int n = 0;
  while ((1 << n) < value) ++n;
  return n;
}

Eigen::Vector3d VectorFromJson(const nlohmann::json& json) {
  return Eigen::Vector3d(json.at(0).get<double>(), json.at(1).get<double>(),
                         json.at(2).get<double>());
}

// Transposed 3D convolutions doubling the side from 4 to `side`, channels halving (at least
// 16) down to `out_channels`.
torch::nn::Sequential UpsamplingStack(int channels, int side, int out_channels) {
  torch::nn::Sequential stack;
  const int layers = Log2(side / 4);
  int in = channels;
  for (int i = 0; i < layers; ++i) {
    const bool last = i + 1 == layers;
    const int out = last ? out_channels : std::max(in / 2, 16);
    stack->push_back(torch::nn::ConvTranspose3d(
        torch::nn::ConvTranspose3dOptions(in, out, 4).stride(2).padding(1)));
    if (!last)
      stack->push_back(torch::nn::LeakyReLU(torch::nn::LeakyReLUOptions().negative_slope(0.2)));
    in = out;
  }
  return stack;
}

}  // namespace

double NvolConfig::density_scale() const {
  const Eigen::Vector3d extent = box_max - box_min;
  return grid / extent.minCoeff();
}

nlohmann::json NvolConfig::ToJson() const {
  return {{"dynamic", dynamic},
          {"grid", grid},
          {"latent_dim", latent_dim},
          {"warp_count", warp_count},
          {"warp_grid", warp_grid},
          {"encoder_views", encoder_views},
          {"encoder_width", encoder_width},
          {"encoder_height", encoder_height},
          {"decoder_channels", decoder_channels},
          {"cameras", cameras},
          {"frames", frames},
          {"box_min", {box_min.x(), box_min.y(), box_min.z()}},
          {"box_max", {box_max.x(), box_max.y(), box_max.z()}}};
}

NvolConfig NvolConfig::FromJson(const nlohmann::json& json) {
  NvolConfig c;
  c.dynamic = json.at("dynamic").get<bool>();
  c.grid = json.at("grid").get<int>();
  c.latent_dim = json.at("latent_dim").get<int>();
  c.warp_count = json.at("warp_count").get<int>();
  c.warp_grid = json.at("warp_grid").get<int>();
  c.encoder_views = json.at("encoder_views").get<int>();
  c.encoder_width = json.at("encoder_width").get<int>();
  c.encoder_height = json.at("encoder_height").get<int>();
  c.decoder_channels = json.at("decoder_channels").get<int>();
  c.cameras = json.at("cameras").get<int>();
  c.frames = json.value("frames", 0);
  c.box_min = VectorFromJson(json.at("box_min"));
  c.box_max = VectorFromJson(json.at("box_max"));
  return c;
}

EncoderImpl::EncoderImpl(int views, int width, int height, int latent_dim) {
  convs_ = torch::nn::Sequential();
  int in = 3 * views, w = width, h = height;
  for (int out : {32, 64, 128, 128}) {
    if (w < 8 || h < 8) break;
    convs_->push_back(torch::nn::Conv2d(torch::nn::Conv2dOptions(in, out, 4).stride(2).padding(1)));
    convs_->push_back(torch::nn::LeakyReLU(torch::nn::LeakyReLUOptions().negative_slope(0.2)));
    in = out;
    w /= 2;
    h /= 2;
  }
  register_module("convs", convs_);
  head_ = register_module("head", torch::nn::Linear(in * w * h, 2 * latent_dim));
  // A small initial log-sigma keeps the first latents informative.
  torch::NoGradGuard no_grad;
  head_->weight.mul_(0.1);
  head_->bias.zero_();
}

std::pair<torch::Tensor, torch::Tensor> EncoderImpl::forward(const torch::Tensor& images) {
  torch::Tensor x = convs_->forward(images).flatten(1);
  torch::Tensor out = head_->forward(x);
  auto halves = out.chunk(2, 1);
  return {halves[0], halves[1] - 3.0};
}

TemplateDecoderImpl::TemplateDecoderImpl(int latent_dim, int grid, int channels)
    : channels_(channels) {
  input_ = register_module("input", torch::nn::Linear(latent_dim, channels * 64));
  layers_ = register_module("layers", UpsamplingStack(channels, grid, 4));
}

torch::Tensor TemplateDecoderImpl::forward(const torch::Tensor& latent) {
  torch::Tensor x =
      F::leaky_relu(input_->forward(latent), F::LeakyReLUFuncOptions().negative_slope(0.2));
  return layers_->forward(x.view({latent.size(0), channels_, 4, 4, 4}));
}

WarpDecoderImpl::WarpDecoderImpl(int latent_dim, int warp_grid, int warp_count, int channels)
    : warp_grid_(warp_grid), warp_count_(warp_count), channels_(channels) {
  affine_ = register_module("affine", torch::nn::Linear(latent_dim, warp_count * 10));
  weight_input_ = register_module("weight_input", torch::nn::Linear(latent_dim, channels * 64));
  weight_layers_ =
      register_module("weight_layers", UpsamplingStack(channels, warp_grid, warp_count));
  // Start at the identity warp: every affine is the identity and the blend is uniform.
  torch::NoGradGuard no_grad;
  affine_->weight.mul_(0.01);
  affine_->bias.zero_();
}

torch::Tensor WarpDecoderImpl::BlendAffineWarps(const torch::Tensor& params,
                                                const torch::Tensor& weights) {
  const int64_t batch = params.size(0), count = params.size(1), side = weights.size(-1);
  torch::Tensor q = params.narrow(2, 0, 4);
  q = q / (q.norm(2, -1, true) + 1e-8);
  torch::Tensor w = q.select(2, 0), x = q.select(2, 1), y = q.select(2, 2), z = q.select(2, 3);
  torch::Tensor rotation =
      torch::stack({1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                    2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                    2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)},
                   -1)
          .view({batch, count, 3, 3});
  torch::Tensor translation = params.narrow(2, 4, 3);
  torch::Tensor scale = params.narrow(2, 7, 3).exp();
  // Voxel centres in grid_sample's [-1, 1] convention (align_corners = false), (x, y, z) for
  // the [z][y][x] layout.
  torch::Tensor axis = (torch::arange(side, params.options()) + 0.5) * (2.0 / side) - 1.0;
  auto mesh = torch::meshgrid({axis, axis, axis}, "ij");
  torch::Tensor points = torch::stack({mesh[2], mesh[1], mesh[0]}, -1).view({1, 1, -1, 3});
  torch::Tensor local =
      torch::matmul(points - translation.unsqueeze(2), rotation.transpose(-1, -2)) *
      scale.unsqueeze(2);  // [B, K, W³, 3]
  torch::Tensor sampled = F::grid_sample(weights.reshape({batch * count, 1, side, side, side}),
                                         local.reshape({batch * count, side, side, side, 3}),
                                         F::GridSampleFuncOptions()
                                             .mode(torch::kBilinear)
                                             .padding_mode(torch::kZeros)
                                             .align_corners(false));
  sampled = sampled.view({batch, count, -1, 1});
  torch::Tensor field = (sampled * local).sum(1) / (sampled.sum(1) + 1e-6);  // [B, W³, 3]
  return ((field + 1.0) * 0.5).view({batch, side, side, side, 3});
}

torch::Tensor WarpDecoderImpl::forward(const torch::Tensor& latent) {
  const int64_t batch = latent.size(0);
  torch::Tensor params = affine_->forward(latent).view({batch, warp_count_, 10});
  torch::Tensor identity = torch::zeros({10}, latent.options());
  identity[0] = 1.0;
  params = params + identity;
  torch::Tensor x =
      F::leaky_relu(weight_input_->forward(latent), F::LeakyReLUFuncOptions().negative_slope(0.2));
  torch::Tensor weights = weight_layers_->forward(x.view({batch, channels_, 4, 4, 4}));
  weights = torch::exp(weights.clamp(-10.0, 10.0));
  return BlendAffineWarps(params, weights);
}

NvolModelImpl::NvolModelImpl(const NvolConfig& config) : config_(config) {
  if (config.dynamic) {
    encoder = register_module("encoder", Encoder(config.encoder_views, config.encoder_width,
                                                 config.encoder_height, config.latent_dim));
    decoder = register_module(
        "decoder", TemplateDecoder(config.latent_dim, config.grid, config.decoder_channels));
    warp =
        register_module("warp", WarpDecoder(config.latent_dim, config.warp_grid, config.warp_count,
                                            std::max(config.decoder_channels / 2, 16)));
    // The template's fine detail, optimised directly (as a static grid is) and added to the
    // decoder's output: a per-voxel parameter follows the images within tens of steps, while
    // the decoder and the warp learn what changes from frame to frame.
    // Nearly empty at first, as a static grid: an initial fog over the whole box is removed
    // fastest by warping every sample out of the template, after which no sample reaches a
    // density and nothing receives a gradient again.
    torch::Tensor initial = torch::zeros({1, 4, config.grid, config.grid, config.grid});
    initial.narrow(1, 3, 1).fill_(-3.0);
    grid = register_parameter("grid", initial);
    if (config.frames > 0)
      frame_codes =
          register_parameter("frame_codes", torch::zeros({config.frames, config.latent_dim}));
  } else {
    // Grey and nearly empty (optical depth softplus(-5) = 0.007 per voxel): Adam moves each
    // voxel by about the learning rate per step, so density appears within tens of steps
    // where the views need it, and unobserved fog stays faint.
    torch::Tensor initial = torch::zeros({1, 4, config.grid, config.grid, config.grid});
    initial.narrow(1, 3, 1).fill_(-3.0);
    grid = register_parameter("grid", initial);
  }
  gain = register_parameter("gain", torch::ones({std::max(config.cameras, 1), 3}));
  bias = register_parameter("bias", torch::zeros({std::max(config.cameras, 1), 3}));
}

torch::Tensor ActivateRgba(const torch::Tensor& raw, double density_scale) {
  // Raw density 0 is an optical depth of softplus(-2) = 0.13 per voxel: faint enough that the
  // backgrounds show through an untrained volume, steep enough (slope 0.12) that density grows
  // within tens of iterations where the images ask for it.
  torch::Tensor colour = torch::sigmoid(raw.narrow(1, 0, 3));
  torch::Tensor density = F::softplus(raw.narrow(1, 3, 1) - 2.0) * density_scale;
  return torch::cat({colour, density}, 1).squeeze(0).permute({1, 2, 3, 0});
}

torch::Tensor NvolModelImpl::DecodeRgba(const torch::Tensor& latent) {
  torch::Tensor raw = config_.dynamic ? decoder->forward(latent) + grid : grid;
  return ActivateRgba(raw, config_.density_scale());
}

torch::Tensor NvolModelImpl::DecodeWarp(const torch::Tensor& latent) {
  if (!config_.dynamic) return {};
  return warp->forward(latent).squeeze(0);
}

// ---------------------------------------------------------------------------------------------

namespace {

MarchVolume VolumeOf(const torch::Tensor& rgba, const torch::Tensor& warp,
                     const MarchContext& context) {
  MarchVolume volume;
  volume.box_min = context.box_min;
  volume.box_max = context.box_max;
  volume.rgba = rgba.data_ptr<float>();
  volume.grid = static_cast<int>(rgba.size(0));
  if (warp.defined()) {
    volume.warp = warp.data_ptr<float>();
    volume.warp_grid = static_cast<int>(warp.size(0));
  }
  volume.occupancy = context.occupancy;
  return volume;
}

class MarchFunction : public torch::autograd::Function<MarchFunction> {
 public:
  static torch::autograd::variable_list forward(torch::autograd::AutogradContext* ctx,
                                                const torch::Tensor& rgba,
                                                const torch::Tensor& warp,
                                                int64_t context_address) {
    // The autograd node carries the march context as its address (an int64 is what it stores).
    // NOLINTNEXTLINE(performance-no-int-to-ptr)
    auto* context = reinterpret_cast<MarchContext*>(context_address);
    const bool has_warp = warp.numel() > 0;
    torch::Tensor rgba_c = rgba.contiguous();
    torch::Tensor warp_c = has_warp ? warp.contiguous() : torch::Tensor();
    MarchForward(VolumeOf(rgba_c, warp_c, *context), context->rays, context->options,
                 &context->outputs);
    const int64_t n = context->rays.size();
    torch::Tensor rgb =
        torch::from_blob(context->outputs.rgb.data(), {n, 3}, torch::kFloat32).clone();
    torch::Tensor alpha =
        torch::from_blob(context->outputs.alpha.data(), {n}, torch::kFloat32).clone();
    ctx->saved_data["context"] = context_address;
    ctx->saved_data["has_warp"] = has_warp;
    ctx->save_for_backward({rgba_c, has_warp ? warp_c : warp});
    return {rgb, alpha};
  }

  static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx,
                                                 torch::autograd::variable_list grads) {
    // NOLINTNEXTLINE(performance-no-int-to-ptr): the address forward() saved
    auto* context = reinterpret_cast<MarchContext*>(ctx->saved_data["context"].toInt());
    const bool has_warp = ctx->saved_data["has_warp"].toBool();
    auto saved = ctx->get_saved_variables();
    torch::Tensor rgba = saved[0];
    torch::Tensor warp = has_warp ? saved[1] : torch::Tensor();
    const int64_t n = context->rays.size();
    torch::Tensor g_rgb = grads[0].defined() ? grads[0].contiguous() : torch::zeros({n, 3});
    torch::Tensor g_alpha = grads[1].defined() ? grads[1].contiguous() : torch::zeros({n});
    torch::Tensor g_rgba = torch::zeros_like(rgba);
    torch::Tensor g_warp = has_warp ? torch::zeros_like(warp) : torch::zeros({0});
    MarchBackward(VolumeOf(rgba, warp, *context), context->rays, context->options,
                  g_rgb.data_ptr<float>(), g_alpha.data_ptr<float>(), g_rgba.data_ptr<float>(),
                  has_warp ? g_warp.data_ptr<float>() : nullptr);
    return {g_rgba, g_warp, torch::Tensor()};
  }
};

}  // namespace

std::vector<torch::Tensor> MarchRays(const torch::Tensor& rgba, const torch::Tensor& warp,
                                     MarchContext* context) {
  // Autograd functions take no undefined input: an empty tensor stands for "no warp".
  return MarchFunction::apply(rgba, warp.defined() ? warp : torch::zeros({0}),
                              reinterpret_cast<int64_t>(context));
}

// ---------------------------------------------------------------------------------------------
// The "nvol" model kind for playback.

namespace {

class NeuralVolumeAvatar : public AvatarModel {
 public:
  NeuralVolumeAvatar(const std::filesystem::path& dir, const nlohmann::json& json)
      : config_(NvolConfig::FromJson(json.at("config"))), model_(config_) {
    torch::load(model_, (dir / "model.pt").string());
    model_->eval();
    if (config_.dynamic) torch::load(latents_, (dir / "latents.pt").string());
    for (const auto& name : json.at("cameras")) {
      cameras_.push_back(
          CameraModel::Read(dir / "cameras" / (name.get<std::string>() + ".cameramodel")));
    }
    frames_ = config_.dynamic ? latents_.size(0) : 1;
    if (std::filesystem::exists(dir / "occupancy.pt"))
      torch::load(hull_occupancy_, (dir / "occupancy.pt").string());
  }

  std::string method() const override { return "nvol"; }
  int64_t frame_count() const override { return frames_; }
  Box box() const override { return {config_.box_min, config_.box_max}; }
  std::vector<CameraModel> cameras() const override { return cameras_; }

  RenderedView Render(const CameraModel& camera, int64_t frame,
                      const ViewRenderOptions& options) override {
    if (options.threads > 0) omp_set_num_threads(ResolveThreads(options.threads));
    const auto start = std::chrono::steady_clock::now();
    frame = std::clamp<int64_t>(frame, 0, frames_ - 1);
    Decode(frame, options.bake_scale);
    MarchContext context;
    context.box_min = config_.box_min.cast<float>();
    context.box_max = config_.box_max.cast<float>();
    // Without skipping every sample is evaluated, but the cells training never fitted still
    // add nothing, so both modes render the same image.
    context.occupancy = &occupancy_;
    context.options.evaluate_empty_cells = !options.skip_empty;
    context.options.step_m = static_cast<float>(StepMetres(options.step_voxels));
    context.options.min_transmittance = static_cast<float>(options.min_transmittance);
    context.rays = CameraRaysAllPixels(camera, context.box_min, context.box_max);
    MarchPlayback(options.bake ? baked_.View(context.occupancy) : VolumeOf(rgba_, warp_, context),
                  context.rays, context.options, &context.outputs);

    RenderedView view;
    const int w = camera.width(), h = camera.height();
    view.color.create(h, w, CV_32FC3);
    view.alpha.create(h, w, CV_32FC1);
    view.depth.create(h, w, CV_32FC1);
    const Eigen::Vector3d axis = camera.world_from_cam().rotation().col(2);
    double samples = 0;
    int64_t in_volume = 0;
#pragma omp parallel for schedule(static) reduction(+ : samples, in_volume)
    for (int y = 0; y < h; ++y) {
      for (int x = 0, i = y * w; x < w; ++x, ++i) {
        const float alpha = context.outputs.alpha[i];
        for (int c = 0; c < 3; ++c)
          view.color.at<cv::Vec3f>(y, x)[c] = context.outputs.rgb[3 * i + c];
        view.alpha.at<float>(y, x) = alpha;
        float depth = std::numeric_limits<float>::quiet_NaN();
        if (alpha >= options.depth_min_alpha && alpha > 0) {
          const double t = context.outputs.depth[i] / alpha;
          const float* direction = &context.rays.direction[3 * static_cast<size_t>(i)];
          const Eigen::Vector3d d(direction[0], direction[1], direction[2]);
          depth = static_cast<float>(t * d.dot(axis));
        }
        view.depth.at<float>(y, x) = depth;
        if (context.rays.t_far[i] > context.rays.t_near[i]) {
          samples += context.outputs.samples[i];
          ++in_volume;
        }
      }
    }
    view.rays_in_volume = in_volume;
    view.samples_per_ray = in_volume > 0 ? samples / in_volume : 0;
    view.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    return view;
  }

  bool Bake(int64_t frame, const ViewRenderOptions& options, BakedFrame* out) override {
    Decode(std::clamp<int64_t>(frame, 0, frames_ - 1), options.bake_scale);
    out->box = {config_.box_min, config_.box_max};
    out->grid = baked_.grid;
    out->rgba = baked_.rgba;
    out->clamped = baked_.clamped;
    out->occupancy_cells = occupancy_.size;
    out->occupied = occupancy_.occupied;
    out->step_m = StepMetres(options.step_voxels);
    return true;
  }

 private:
  double StepMetres(double step_voxels) const {
    return step_voxels * (config_.box_max - config_.box_min).minCoeff() / config_.grid;
  }

  void Decode(int64_t frame, double bake_scale) {
    if (!(bake_scale >= 1)) Fail("bake_scale must be at least 1, got ", bake_scale);
    // A static volume has no warp: its grid is sampled as it is.
    const int bake_grid =
        config_.dynamic ? static_cast<int>(std::lround(bake_scale * config_.grid)) : config_.grid;
    if (frame == decoded_frame_ && bake_grid == baked_.grid) return;
    torch::NoGradGuard no_grad;
    torch::Tensor latent = config_.dynamic ? latents_.narrow(0, frame, 1) : torch::Tensor();
    rgba_ = model_->DecodeRgba(latent).contiguous();
    warp_ = config_.dynamic ? model_->DecodeWarp(latent).contiguous() : torch::Tensor();
    MarchContext context;
    context.box_min = config_.box_min.cast<float>();
    context.box_max = config_.box_max.cast<float>();
    // A cell matters once a step through it absorbs 0.1% of the light.
    const float min_density = static_cast<float>(1e-3 / StepMetres(1.0));
    const bool has_hull = hull_occupancy_.defined();
    const int cells =
        has_hull
            ? static_cast<int>(std::lround(std::cbrt(static_cast<double>(hull_occupancy_.size(1)))))
            : std::max(config_.grid / 4, 4);
    baked_ = BakeVolume(VolumeOf(rgba_, warp_, context), bake_grid);
    occupancy_ = OccupancyFromVolume(baked_.View(), cells, min_density);
    occupancy_.Dilate(1);
    if (has_hull) {
      // Training sampled only the hull's cells; density elsewhere was never fitted.
      const uint8_t* hull = hull_occupancy_[std::min<int64_t>(frame, hull_occupancy_.size(0) - 1)]
                                .data_ptr<uint8_t>();
      for (size_t i = 0; i < occupancy_.occupied.size(); ++i) occupancy_.occupied[i] &= hull[i];
    }
    decoded_frame_ = frame;
  }

  NvolConfig config_;
  NvolModel model_;
  torch::Tensor latents_;
  torch::Tensor hull_occupancy_;  // [frames, cells³] uint8, or undefined
  std::vector<CameraModel> cameras_;
  int64_t frames_ = 1;
  int64_t decoded_frame_ = -1;
  torch::Tensor rgba_, warp_;
  BakedVolume baked_;
  OccupancyGrid occupancy_;
};

}  // namespace

std::unique_ptr<AvatarModel> OpenNeuralVolume(const std::filesystem::path& dir,
                                              const nlohmann::json& model_json) {
  try {
    return std::make_unique<NeuralVolumeAvatar>(dir, model_json);
  } catch (const c10::Error& e) {
    Fail("cannot load the neural volume in ", dir.string(), ": ", e.what_without_backtrace());
  } catch (const nlohmann::json::exception& e) {
    Fail("model.json in ", dir.string(), " is malformed: ", e.what());
  }
}

}  // namespace holocap::neural

namespace holocap {

void RegisterNeuralVolumeAvatarKind(AvatarKindRegistry& registry) {
  registry.Register(
      {"nvol", "Neural Volumes: a learned RGBA volume and warp field", neural::OpenNeuralVolume});
}

}  // namespace holocap
