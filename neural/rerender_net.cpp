// The rerendering U-Net, its inputs and outputs, and rerendering models as AvatarModels.
#include "neural/internal/rerender_net.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <map>
#include <mutex>
#include <numeric>

#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/mesh.h"
#include "core/projector.h"
#include "core/threads.h"

namespace holocap {
namespace neural {

namespace {

int LevelChannels(const UNetConfig& config, int level) {
  return config.width << std::min(level, 3);
}

// Alpha of an uncovered pixel at the start, and 1 minus that of a fully covered one: sigmoid(-6).
const double kAlphaFloor = 1 / (1 + std::exp(6.0));

torch::nn::Sequential DoubleConv(int in, int out) {
  return torch::nn::Sequential(
      torch::nn::Conv2d(torch::nn::Conv2dOptions(in, out, 3).padding(1)),
      torch::nn::LeakyReLU(torch::nn::LeakyReLUOptions().negative_slope(0.2)),
      torch::nn::Conv2d(torch::nn::Conv2dOptions(out, out, 3).padding(1)),
      torch::nn::LeakyReLU(torch::nn::LeakyReLUOptions().negative_slope(0.2)));
}

}  // namespace

UNetImpl::UNetImpl(const UNetConfig& config) {
  for (int level = 0; level <= config.depth; ++level) {
    const int in = level == 0 ? kRerenderInputChannels : LevelChannels(config, level - 1);
    down_.push_back(register_module("down" + std::to_string(level),
                                    DoubleConv(in, LevelChannels(config, level))));
  }
  for (int level = config.depth - 1; level >= 0; --level) {
    const int in = LevelChannels(config, level + 1) + LevelChannels(config, level);
    up_.push_back(register_module("up" + std::to_string(level),
                                  DoubleConv(in, LevelChannels(config, level))));
  }
  head_ = register_module(
      "head", torch::nn::Conv2d(torch::nn::Conv2dOptions(LevelChannels(config, 0), 4, 1)));
  // The untrained network passes the raw render through (see DecodeRerender).
  torch::NoGradGuard no_grad;
  head_->weight.zero_();
  head_->bias.zero_();
}

torch::Tensor UNetImpl::forward(const torch::Tensor& features) {
  std::vector<torch::Tensor> skips;
  torch::Tensor x = features;
  for (size_t level = 0; level < down_.size(); ++level) {
    if (level > 0) x = torch::avg_pool2d(x, 2);
    x = down_[level]->forward(x);
    skips.push_back(x);
  }
  for (size_t i = 0; i < up_.size(); ++i) {
    const torch::Tensor& skip = skips[skips.size() - 2 - i];
    x = torch::upsample_bilinear2d(x, {skip.size(2), skip.size(3)}, false);
    x = up_[i]->forward(torch::cat({x, skip}, 1));
  }
  return head_->forward(x);
}

torch::Tensor ImageToTensor(const cv::Mat& image) {
  cv::Mat contiguous = image.isContinuous() ? image : image.clone();
  return torch::from_blob(contiguous.data,
                          {contiguous.rows, contiguous.cols, contiguous.channels()},
                          torch::kFloat32)
      .permute({2, 0, 1})
      .clone();
}

void LossEnds(const std::vector<double>& losses, double* first, double* last) {
  if (losses.empty()) return;
  const size_t window = std::max<size_t>(1, std::min<size_t>(20, losses.size() / 4));
  *first = std::accumulate(losses.begin(), losses.begin() + window, 0.0) / window;
  *last = std::accumulate(losses.end() - window, losses.end(), 0.0) / window;
}

cv::Mat TensorToImage(const torch::Tensor& chw) {
  torch::Tensor hwc = chw.detach().to(torch::kFloat32).permute({1, 2, 0}).contiguous();
  const int channels = static_cast<int>(hwc.size(2));
  cv::Mat image(static_cast<int>(hwc.size(0)), static_cast<int>(hwc.size(1)), CV_32FC(channels));
  std::memcpy(image.data, hwc.data_ptr<float>(), sizeof(float) * hwc.numel());
  return image;
}

torch::Tensor RerenderFeatures(const GBuffer& buffers) {
  const int height = buffers.color.rows, width = buffers.color.cols;
  cv::Mat depth = buffers.depth.clone();
  cv::Mat valid = buffers.mask.clone();
  // Depth about the subject's median: the network sees shape, not the camera's distance.
  std::vector<float> values;
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x) {
      const float z = depth.at<float>(y, x);
      if (!std::isfinite(z) || valid.at<uint8_t>(y, x) == 0) {
        valid.at<uint8_t>(y, x) = 0;
        depth.at<float>(y, x) = 0;
      } else {
        values.push_back(z);
      }
    }
  }
  float median = 0;
  if (!values.empty()) {
    std::nth_element(values.begin(), values.begin() + values.size() / 2, values.end());
    median = values[values.size() / 2];
  }
  cv::Mat relative(height, width, CV_32F, cv::Scalar(0));
  cv::Mat coverage(height, width, CV_32F, cv::Scalar(0));
  cv::Mat color(height, width, CV_32FC3, cv::Scalar::all(0)),
      normal(height, width, CV_32FC3, cv::Scalar::all(0));
  // World position about the per-axis median of the covered pixels: the body's layout
  // (legs below, head above) without the subject's place on the stage.
  const bool has_position =
      buffers.position.size() == buffers.color.size() && buffers.position.type() == CV_32FC3;
  cv::Mat position(height, width, CV_32FC3, cv::Scalar::all(0));
  cv::Vec3f position_median(0, 0, 0);
  if (has_position) {
    std::vector<float> axis;
    for (int k = 0; k < 3; ++k) {
      axis.clear();
      for (int y = 0; y < height; ++y) {
        for (int x = 0; x < width; ++x) {
          const float value = buffers.position.at<cv::Vec3f>(y, x)[k];
          if (valid.at<uint8_t>(y, x) && std::isfinite(value)) axis.push_back(value);
        }
      }
      if (axis.empty()) continue;
      std::nth_element(axis.begin(), axis.begin() + axis.size() / 2, axis.end());
      position_median[k] = axis[axis.size() / 2];
    }
  }
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x) {
      if (!valid.at<uint8_t>(y, x)) continue;
      relative.at<float>(y, x) = std::clamp(depth.at<float>(y, x) - median, -1.0f, 1.0f);
      coverage.at<float>(y, x) =
          valid.at<uint8_t>(y, x) / 255.0f;  // the covered fraction when supersampled
      cv::Vec3f c = buffers.color.at<cv::Vec3f>(y, x), n = buffers.normal.at<cv::Vec3f>(y, x);
      for (int k = 0; k < 3; ++k) {
        c[k] = std::isfinite(c[k]) ? std::clamp(c[k], 0.0f, 1.0f) : 0.0f;
        n[k] = std::isfinite(n[k]) ? std::clamp(n[k], -1.0f, 1.0f) : 0.0f;
      }
      color.at<cv::Vec3f>(y, x) = c;
      normal.at<cv::Vec3f>(y, x) = n;
      if (has_position) {
        cv::Vec3f p = buffers.position.at<cv::Vec3f>(y, x) - position_median;
        for (int k = 0; k < 3; ++k)
          p[k] = std::isfinite(p[k]) ? std::clamp(p[k], -1.5f, 1.5f) : 0.0f;
        position.at<cv::Vec3f>(y, x) = p;
      }
    }
  }
  return torch::cat({ImageToTensor(color), ImageToTensor(coverage), ImageToTensor(normal),
                     ImageToTensor(relative), ImageToTensor(position)},
                    0);
}

torch::Tensor PadToMultiple(const torch::Tensor& x, int multiple) {
  const int64_t h = x.size(-2), w = x.size(-1);
  const int64_t pad_h = (multiple - h % multiple) % multiple,
                pad_w = (multiple - w % multiple) % multiple;
  if (pad_h == 0 && pad_w == 0) return x;
  return torch::constant_pad_nd(x, {0, pad_w, 0, pad_h}, 0);
}

std::pair<torch::Tensor, torch::Tensor> DecodeRerender(const torch::Tensor& raw,
                                                       const torch::Tensor& features) {
  using torch::indexing::Slice;
  const torch::Tensor color = features.index({Slice(), Slice(0, 3)}).clamp(0.02, 0.98);
  const torch::Tensor coverage = features.index({Slice(), Slice(3, 4)});
  torch::Tensor rgb =
      torch::sigmoid(raw.index({Slice(), Slice(0, 3)}) + torch::log(color / (1 - color)));
  // Alpha starts as the coverage (the covered fraction of a supersampled pixel, as the raw render
  // composites it; kept off 0 and 1 by sigmoid(+-6)). The correction is bounded (tanh): alpha can
  // be overruled, but never pushed so far into the sigmoid's flat tails that its gradient vanishes.
  const torch::Tensor start = coverage.clamp(kAlphaFloor, 1 - kAlphaFloor);
  torch::Tensor alpha = torch::sigmoid(10 * torch::tanh(raw.index({Slice(), Slice(3, 4)}) / 10) +
                                       torch::log(start / (1 - start)));
  return {rgb, alpha};
}

torch::Tensor RawOutputPenalty(const torch::Tensor& raw) {
  return torch::relu(raw.abs() - kRawOutputRange).pow(2).mean();
}

namespace {

// A rerendering model on disk: model.json, unet.pt, cameras/*.cameramodel and the meshes.
class RerenderModel : public AvatarModel {
 public:
  RerenderModel(const std::filesystem::path& dir, const nlohmann::json& json)
      : network_(RerenderNetwork::Load(dir / "unet.pt", UNetConfig::FromJson(json.at("net")))),
        supersample_(json.value("supersample", 1)) {
    for (const auto& entry : json.at("meshes")) {
      std::filesystem::path file = entry.get<std::string>();
      meshes_.push_back(file.is_absolute() ? file : dir / file);
    }
    if (meshes_.empty()) Fail(dir.string(), "/model.json lists no meshes");
    for (const auto& name : json.at("cameras"))
      cameras_.push_back(
          CameraModel::Read(dir / "cameras" / (name.get<std::string>() + ".cameramodel")));
    box_min_ = Eigen::Vector3d(json.at("box_min")[0], json.at("box_min")[1], json.at("box_min")[2]);
    box_max_ = Eigen::Vector3d(json.at("box_max")[0], json.at("box_max")[1], json.at("box_max")[2]);
  }
  std::string method() const override { return "rerender"; }
  int64_t frame_count() const override { return static_cast<int64_t>(meshes_.size()); }
  Box box() const override { return {box_min_, box_max_}; }
  std::vector<CameraModel> cameras() const override { return cameras_; }

  RenderedView Render(const CameraModel& camera, int64_t frame,
                      const ViewRenderOptions& options) override {
    const auto start = std::chrono::steady_clock::now();
    frame = std::clamp<int64_t>(frame, 0, frame_count() - 1);
    if (frame != cached_frame_) {
      mesh_ = ReadPly(meshes_[frame]);
      cached_frame_ = frame;
    }
    MeshRasterOptions raster;
    raster.threads = options.threads;
    raster.supersample = supersample_;  // as the network was trained
    RenderedView view = network_.Apply(RasteriseMesh(mesh_, camera, raster), options.threads);
    view.depth.setTo(std::numeric_limits<float>::quiet_NaN(), view.alpha < options.depth_min_alpha);
    view.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    return view;
  }

 private:
  RerenderNetwork network_;
  int supersample_ = 1;
  std::vector<std::filesystem::path> meshes_;
  std::vector<CameraModel> cameras_;
  Eigen::Vector3d box_min_, box_max_;
  Mesh mesh_;
  int64_t cached_frame_ = -1;
};

}  // namespace
}  // namespace neural

nlohmann::json UNetConfig::ToJson() const { return {{"width", width}, {"depth", depth}}; }

UNetConfig UNetConfig::FromJson(const nlohmann::json& json) {
  UNetConfig config;
  config.width = json.value("width", config.width);
  config.depth = json.value("depth", config.depth);
  config.Check();
  return config;
}

void UNetConfig::Check() const {
  HOLOCAP_CHECK_OPTION_IN(width, 4, 128, "channels");
  HOLOCAP_CHECK_OPTION_IN(depth, 1, 6, "levels");
}

RerenderNetwork::RerenderNetwork(std::unique_ptr<State> state) : state_(std::move(state)) {}

RerenderNetwork::RerenderNetwork(const UNetConfig& config, uint64_t seed)
    : state_(std::make_unique<State>()) {
  config.Check();
  torch::manual_seed(seed);
  state_->config = config;
  state_->net = neural::UNet(config);
}

RerenderNetwork::~RerenderNetwork() = default;
RerenderNetwork::RerenderNetwork(RerenderNetwork&&) noexcept = default;
RerenderNetwork& RerenderNetwork::operator=(RerenderNetwork&&) noexcept = default;

const UNetConfig& RerenderNetwork::config() const { return state_->config; }

int64_t RerenderNetwork::parameter_count() const {
  int64_t count = 0;
  for (const auto& p : state_->net->parameters()) count += p.numel();
  return count;
}

RerenderNetwork RerenderNetwork::Load(const std::filesystem::path& weights,
                                      const UNetConfig& config) {
  if (!std::filesystem::exists(weights))
    Fail("rerender weights ", weights.string(), " are missing");
  RerenderNetwork network(config, 0);
  try {
    torch::serialize::InputArchive archive;
    archive.load_from(weights.string());
    network.state_->net->load(archive);
  } catch (const c10::Error& e) {
    Fail("cannot read rerender weights ", weights.string(), " (", e.what_without_backtrace(), ")");
  }
  return network;
}

void RerenderNetwork::Save(const std::filesystem::path& weights) const {
  const std::filesystem::path temporary = weights.string() + ".tmp";
  torch::serialize::OutputArchive archive;
  state_->net->save(archive);
  archive.save_to(temporary.string());
  std::filesystem::rename(temporary, weights);
}

RenderedView RerenderNetwork::Apply(const GBuffer& buffers, int threads) const {
  torch::NoGradGuard no_grad;
  torch::set_num_threads(ResolveThreads(threads));
  state_->net->eval();
  const int height = buffers.color.rows, width = buffers.color.cols;
  const torch::Tensor features =
      neural::PadToMultiple(neural::RerenderFeatures(buffers).unsqueeze(0), 1 << config().depth);
  auto [rgb, alpha] = neural::DecodeRerender(state_->net->forward(features), features);
  using torch::indexing::Slice;
  rgb = rgb.index({0, Slice(), Slice(0, height), Slice(0, width)});
  alpha = alpha.index({0, Slice(), Slice(0, height), Slice(0, width)});
  RenderedView view;
  view.color = neural::TensorToImage(rgb * alpha);
  view.alpha = neural::TensorToImage(alpha);
  view.depth = buffers.depth.clone();
  return view;
}

void RegisterRerenderAvatarKind(AvatarKindRegistry& registry) {
  registry.Register({"rerender", "a reconstruction rasterised and refined by a U-Net",
                     [](const std::filesystem::path& dir, const nlohmann::json& json) {
                       try {
                         return std::unique_ptr<AvatarModel>(new neural::RerenderModel(dir, json));
                       } catch (const nlohmann::json::exception& e) {
                         Fail(dir.string(), "/model.json is not a rerendering model: ", e.what());
                       }
                     }});
}

}  // namespace holocap
