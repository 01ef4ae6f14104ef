// Neural Volumes' networks and the ray marcher as an autograd function. Internal to
// holocap_neural: only neural/*.cpp include LibTorch.
#pragma once

#include <torch/torch.h>

#include <Eigen/Core>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "avatar/raymarch.h"
#include "neural/neural.h"

namespace holocap::neural {

// What a model is built of; stored in model.json so that playback rebuilds the same networks.
struct NvolConfig {
  bool dynamic = false;
  int grid = 64;
  int latent_dim = 256;
  int warp_count = 16;
  int warp_grid = 32;
  int encoder_views = 3;
  int encoder_width = 64;
  int encoder_height = 48;
  int decoder_channels = 128;
  int cameras = 0;
  int frames = 0;  // dynamic: frames with a learnt code of their own
  Eigen::Vector3d box_min = Eigen::Vector3d::Zero();
  Eigen::Vector3d box_max = Eigen::Vector3d::Ones();

  double density_scale() const;  // 1/m: unit raw density = optical depth 1 per voxel
  nlohmann::json ToJson() const;
  static NvolConfig FromJson(const nlohmann::json& json);
};

// Views of a frame -> (mean, log sigma) of its latent code.
class EncoderImpl : public torch::nn::Module {
 public:
  EncoderImpl(int views, int width, int height, int latent_dim);
  std::pair<torch::Tensor, torch::Tensor> forward(const torch::Tensor& images);  // [B,3V,H,W]

 private:
  torch::nn::Sequential convs_{nullptr};
  torch::nn::Linear head_{nullptr};
};
TORCH_MODULE(Encoder);

// Latent -> raw RGBA template [B, 4, D, D, D] by transposed 3D convolutions from 4³.
class TemplateDecoderImpl : public torch::nn::Module {
 public:
  TemplateDecoderImpl(int latent_dim, int grid, int channels);
  torch::Tensor forward(const torch::Tensor& latent);

 private:
  int channels_;
  torch::nn::Linear input_{nullptr};
  torch::nn::Sequential layers_{nullptr};
};
TORCH_MODULE(TemplateDecoder);

// Latent -> a mixture of affine warps blended on a W³ grid -> the warp field [B, W, W, W, 3]
// of template coordinates in [0, 1] (channels last, as the marcher reads it).
class WarpDecoderImpl : public torch::nn::Module {
 public:
  WarpDecoderImpl(int latent_dim, int warp_grid, int warp_count, int channels);
  torch::Tensor forward(const torch::Tensor& latent);
  // The field for given affine parameters and blend weights (exposed for gradient checks):
  // params [B, K, 10] (quaternion, translation, log scale), weights [B, K, W, W, W] > 0.
  static torch::Tensor BlendAffineWarps(const torch::Tensor& params, const torch::Tensor& weights);

 private:
  int warp_grid_, warp_count_, channels_;
  torch::nn::Linear affine_{nullptr};
  torch::nn::Linear weight_input_{nullptr};
  torch::nn::Sequential weight_layers_{nullptr};
};
TORCH_MODULE(WarpDecoder);

// The whole model. A static model holds only `grid` (the raw RGBA grid itself is optimised);
// a dynamic one the encoder, the template decoder (plus `grid`, a directly optimised
// residual), per-frame codes and the warp decoder. Both hold per-camera
// colour calibration.
class NvolModelImpl : public torch::nn::Module {
 public:
  explicit NvolModelImpl(const NvolConfig& config);
  const NvolConfig& config() const { return config_; }

  // Activated RGBA, channels last [D, D, D, 4]: colour in [0, 1], density in 1/m.
  torch::Tensor DecodeRgba(const torch::Tensor& latent);  // latent [1, L], undefined: static
  torch::Tensor DecodeWarp(const torch::Tensor& latent);  // [W, W, W, 3] or undefined (static)

  Encoder encoder{nullptr};
  TemplateDecoder decoder{nullptr};
  WarpDecoder warp{nullptr};
  torch::Tensor
      grid;  // raw [1, 4, D, D, D]: the volume (static), the template's residual (dynamic)
  // Dynamic: a learnt code per frame [frames, L], added to the encoder's mean. The encoder
  // sees the subject small in a few low-resolution views, so its means barely tell frames
  // apart at first; the codes let each frame's volume separate from the others early.
  torch::Tensor frame_codes;
  torch::Tensor gain;  // [cameras, 3], around 1
  torch::Tensor bias;  // [cameras, 3], around 0

 private:
  NvolConfig config_;
};
TORCH_MODULE(NvolModel);

// raw [1, 4, D, D, D] -> activated channels last [D, D, D, 4].
torch::Tensor ActivateRgba(const torch::Tensor& raw, double density_scale);

// Everything the marcher needs besides the differentiable grids; must outlive backward().
struct MarchContext {
  RayBatch rays;
  Eigen::Vector3f box_min, box_max;
  const OccupancyGrid* occupancy = nullptr;
  MarchOptions options;
  MarchOutputs outputs;  // filled by the forward pass (samples per ray, depth)
};

// Differentiable marching: rgba [D, D, D, 4] float, warp [W, W, W, 3] or undefined. Returns
// {rgb [N, 3] premultiplied, alpha [N]}.
std::vector<torch::Tensor> MarchRays(const torch::Tensor& rgba, const torch::Tensor& warp,
                                     MarchContext* context);

// Opens an "nvol" model directory for rendering.
std::unique_ptr<AvatarModel> OpenNeuralVolume(const std::filesystem::path& dir,
                                              const nlohmann::json& model_json);

}  // namespace holocap::neural
