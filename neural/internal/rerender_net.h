// The rerendering U-Net and the tensors around it. Internal to holocap_neural: only
// neural/*.cpp include LibTorch.
#pragma once

#include <torch/torch.h>

#include <utility>
#include <vector>

#include "neural/rerender.h"

namespace holocap::neural {

// Colour (3), coverage (1), camera-frame normal (3), depth about the subject's median (1),
// world position about the subject's median (3).
inline constexpr int kRerenderInputChannels = 11;

class UNetImpl : public torch::nn::Module {
 public:
  explicit UNetImpl(const UNetConfig& config);
  // features [B, 11, H, W], H and W multiples of 2^depth -> raw [B, 4, H, W] (0 at start).
  torch::Tensor forward(const torch::Tensor& features);

 private:
  std::vector<torch::nn::Sequential> down_;
  std::vector<torch::nn::Sequential> up_;
  torch::nn::Conv2d head_{nullptr};
};
TORCH_MODULE(UNet);

// G-buffers -> [11, H, W] inputs. NaN or infinite depth counts as empty.
torch::Tensor RerenderFeatures(const GBuffer& buffers);
// Zero-pads [B, C, H, W] on the right and bottom to multiples of `multiple`.
torch::Tensor PadToMultiple(const torch::Tensor& x, int multiple);
// Raw network output and the inputs -> {rgb [B, 3, H, W] in (0, 1), alpha [B, 1, H, W]}:
// corrections on top of the raw render's colour and coverage.
std::pair<torch::Tensor, torch::Tensor> DecodeRerender(const torch::Tensor& raw,
                                                       const torch::Tensor& features);
// A penalty that keeps the raw output where DecodeRerender's sigmoids and bound still pass a
// gradient (|raw| <= kRawOutputRange): without it, a loss that pushes every pixel one way (a
// reconstruction mostly phantom volume asks for alpha 0 nearly everywhere) lets Adam's momentum
// compound through the unnormalised layers, the output runs to 1e5 within ten steps and the
// network is stuck erasing the subject for good. 0 while the output stays in range.
inline constexpr double kRawOutputRange = 20;
torch::Tensor RawOutputPenalty(const torch::Tensor& raw);
// CV_32FC3 / CV_32FC1 <-> [C, H, W] float tensors.
torch::Tensor ImageToTensor(const cv::Mat& image);
cv::Mat TensorToImage(const torch::Tensor& chw);
// The mean loss over a run's first and over its last iterations (windows of a quarter of the
// run, 1 to 20 iterations); both stay as they are when there was no iteration.
void LossEnds(const std::vector<double>& losses, double* first, double* last);

}  // namespace holocap::neural

namespace holocap {
struct RerenderNetwork::State {
  UNetConfig config;
  neural::UNet net{nullptr};
};
}  // namespace holocap
