// Options, the registry of model kinds and image metrics: the parts without LibTorch.
#include <cmath>
#include <map>
#include <mutex>
#include <opencv2/imgproc.hpp>

#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"
#include "neural/neural.h"

namespace holocap {

namespace neural {
std::unique_ptr<AvatarModel> OpenNeuralVolume(const std::filesystem::path& dir,
                                              const nlohmann::json& model_json);
}  // namespace neural

namespace {

bool IsPowerOfTwo(int value) { return value > 0 && (value & (value - 1)) == 0; }

struct ModelRegistry {
  std::mutex mutex;
  std::map<std::string, ModelOpener> openers{{"nvol", neural::OpenNeuralVolume}};
};
ModelRegistry& Registry() {
  static ModelRegistry registry;
  return registry;
}

}  // namespace

const char* ToString(VolumeBoundsSource source) {
  switch (source) {
    case VolumeBoundsSource::kAuto:
      return "auto";
    case VolumeBoundsSource::kHull:
      return "hull";
    case VolumeBoundsSource::kGroundTruth:
      return "gt";
    case VolumeBoundsSource::kStage:
      return "stage";
  }
  return "?";
}

VolumeBoundsSource VolumeBoundsSourceFromString(const std::string& text) {
  for (auto source : {VolumeBoundsSource::kAuto, VolumeBoundsSource::kHull,
                      VolumeBoundsSource::kGroundTruth, VolumeBoundsSource::kStage}) {
    if (text == ToString(source)) return source;
  }
  Fail("unknown volume bounds source '", text, "' (auto, hull, gt, stage)");
}

void NeuralVolumeOptions::Check() const {
  HOLOCAP_CHECK_OPTION_IN(grid, 16, 128);
  HOLOCAP_CHECK_OPTION(IsPowerOfTwo(grid), grid);
  HOLOCAP_CHECK_OPTION_GE(latent_dim, 1);
  HOLOCAP_CHECK_OPTION_GE(warp_count, 1);
  HOLOCAP_CHECK_OPTION_IN(warp_grid, 8, 64);
  HOLOCAP_CHECK_OPTION(IsPowerOfTwo(warp_grid), warp_grid);
  HOLOCAP_CHECK_OPTION_GE(encoder_views, 1);
  HOLOCAP_CHECK_OPTION_GE(encoder_width, 16, "pixels");
  HOLOCAP_CHECK_OPTION_GE(decoder_channels, 16);
  HOLOCAP_CHECK_OPTION(IsOneOf(scene, {"auto", "static", "dynamic"}), scene);
  HOLOCAP_CHECK_OPTION_GE(image_width, 0, "0: native");
  HOLOCAP_CHECK_OPTION_GE(heldout_cameras, 0);
  take.Check();
  HOLOCAP_CHECK_OPTION_GE(bounds_margin_m, 0);
  HOLOCAP_CHECK_OPTION_GE(occupancy_cells, 0);
  HOLOCAP_CHECK_OPTION(minutes > 0 || iterations > 0, minutes,
                       "give a positive minutes budget or a number of iterations");
  HOLOCAP_CHECK_OPTION_GE(iterations, 0);
  HOLOCAP_CHECK_OPTION_GE(rays_per_batch, 16);
  HOLOCAP_CHECK_OPTION_GE(frames_per_batch, 1);
  HOLOCAP_CHECK_OPTION_GT(learning_rate, 0);
  HOLOCAP_CHECK_OPTION_GT(static_learning_rate, 0);
  HOLOCAP_CHECK_OPTION_GT(template_learning_rate, 0);
  HOLOCAP_CHECK_OPTION_GE(kl_weight, 0);
  HOLOCAP_CHECK_OPTION_GE(alpha_prior_weight, 0);
  HOLOCAP_CHECK_OPTION_GE(tv_weight, 0);
  HOLOCAP_CHECK_OPTION_GE(silhouette_weight, 0);
  HOLOCAP_CHECK_OPTION_GE(warp_prior_weight, 0);
  HOLOCAP_CHECK_OPTION_GT(step_voxels, 0);
  HOLOCAP_CHECK_OPTION_GE(min_transmittance, 0);
  HOLOCAP_CHECK_OPTION_LT(min_transmittance, 1);
  HOLOCAP_CHECK_OPTION_GT(eval_every_s, 0);
  HOLOCAP_CHECK_OPTION_GE(eval_every_iterations, 0);
  HOLOCAP_CHECK_OPTION_GE(eval_frames, 1);
  HOLOCAP_CHECK_OPTION_GT(checkpoint_every_s, 0);
  HOLOCAP_CHECK_OPTION_GT(divergence_factor, 1);
  HOLOCAP_CHECK_OPTION_GE(max_divergences, 0);
  HOLOCAP_CHECK_OPTION_GE(threads, 0);
}

nlohmann::json NeuralVolumeOptions::ToJson() const {
  return {{"grid", grid},
          {"latent_dim", latent_dim},
          {"warp_count", warp_count},
          {"warp_grid", warp_grid},
          {"encoder_views", encoder_views},
          {"encoder_width", encoder_width},
          {"decoder_channels", decoder_channels},
          {"scene", scene},
          {"image_width", image_width},
          {"heldout_cameras", heldout_cameras},
          {"heldout", heldout},
          {"take", take.ToJson()},
          {"bounds", ToString(bounds)},
          {"bounds_margin_m", bounds_margin_m},
          {"occupancy_cells", occupancy_cells},
          {"minutes", minutes},
          {"iterations", iterations},
          {"rays_per_batch", rays_per_batch},
          {"frames_per_batch", frames_per_batch},
          {"learning_rate", learning_rate},
          {"static_learning_rate", static_learning_rate},
          {"template_learning_rate", template_learning_rate},
          {"kl_weight", kl_weight},
          {"alpha_prior_weight", alpha_prior_weight},
          {"tv_weight", tv_weight},
          {"silhouette_weight", silhouette_weight},
          {"warp_prior_weight", warp_prior_weight},
          {"learn_background", learn_background},
          {"step_voxels", step_voxels},
          {"jitter", jitter},
          {"min_transmittance", min_transmittance},
          {"seed", seed},
          {"eval_every_s", eval_every_s},
          {"eval_every_iterations", eval_every_iterations},
          {"eval_frames", eval_frames},
          {"checkpoint_every_s", checkpoint_every_s},
          {"resume", resume},
          {"divergence_factor", divergence_factor},
          {"max_divergences", max_divergences},
          {"threads", threads}};
}

void RegisterModelKind(const std::string& method, ModelOpener opener) {
  auto& registry = Registry();
  std::lock_guard lock(registry.mutex);
  registry.openers[method] = std::move(opener);
}

std::vector<std::string> ModelKinds() {
  auto& registry = Registry();
  std::lock_guard lock(registry.mutex);
  std::vector<std::string> kinds;
  for (const auto& [name, opener] : registry.openers) kinds.push_back(name);
  return kinds;
}

std::unique_ptr<AvatarModel> OpenModel(const std::filesystem::path& dir) {
  const auto file = dir / "model.json";
  if (!std::filesystem::exists(file)) Fail("no model in ", dir.string(), ": model.json is missing");
  nlohmann::json json;
  try {
    json = nlohmann::json::parse(ReadFileToString(file));
  } catch (const nlohmann::json::exception& e) {
    Fail(file.string(), " is not valid JSON: ", e.what());
  }
  if (!json.contains("method") || !json["method"].is_string())
    Fail(file.string(), " names no \"method\"");
  const std::string method = json["method"].get<std::string>();
  ModelOpener opener;
  {
    auto& registry = Registry();
    std::lock_guard lock(registry.mutex);
    auto it = registry.openers.find(method);
    if (it != registry.openers.end()) opener = it->second;
  }
  if (!opener) {
    std::string known;
    for (const auto& kind : ModelKinds()) known += (known.empty() ? "" : ", ") + kind;
    if (method == "live-rerender") {
      Fail(file.string(), ": a live rerender model renders `holocap live` meshes: holocap render ",
           "TAKE --model ", dir.string(), " --recon TAKE/live/recon --cameras NAMES");
    }
    Fail(file.string(), ": unknown model method '", method, "' (known: ", known, ")");
  }
  return opener(dir, json);
}

namespace {
cv::Mat AsFloat(const cv::Mat& image) {
  cv::Mat out;
  image.convertTo(out, CV_MAKETYPE(CV_64F, image.channels()),
                  image.depth() == CV_8U ? 1.0 / 255.0 : 1.0);
  return out;
}
}  // namespace

double PsnrDb(const cv::Mat& image, const cv::Mat& reference, const cv::Mat& mask) {
  if (image.size() != reference.size() || image.type() != reference.type())
    Fail("PSNR needs images of one size and type");
  cv::Mat a = AsFloat(image), b = AsFloat(reference), diff;
  cv::subtract(a, b, diff);
  diff = diff.mul(diff);
  double sum = 0;
  int64_t count = 0;
  for (int y = 0; y < diff.rows; ++y) {
    const double* row = diff.ptr<double>(y);
    for (int x = 0; x < diff.cols; ++x) {
      if (!mask.empty() && mask.at<uint8_t>(y, x) == 0) continue;
      for (int c = 0; c < diff.channels(); ++c) sum += row[x * diff.channels() + c];
      count += diff.channels();
    }
  }
  if (count == 0) return std::numeric_limits<double>::quiet_NaN();
  const double mse = sum / count;
  return mse > 0 ? -10.0 * std::log10(mse) : std::numeric_limits<double>::infinity();
}

double Ssim(const cv::Mat& image, const cv::Mat& reference) {
  // Wang et al. 2004: Gaussian window sigma 1.5, on each channel, averaged.
  if (image.size() != reference.size() || image.type() != reference.type())
    Fail("SSIM needs images of one size and type");
  const double c1 = 0.01 * 0.01, c2 = 0.03 * 0.03;
  cv::Mat a = AsFloat(image), b = AsFloat(reference);
  std::vector<cv::Mat> ca, cb;
  cv::split(a, ca);
  cv::split(b, cb);
  double total = 0;
  for (size_t c = 0; c < ca.size(); ++c) {
    cv::Mat mu_a, mu_b, aa, bb, ab;
    const cv::Size window(11, 11);
    cv::GaussianBlur(ca[c], mu_a, window, 1.5);
    cv::GaussianBlur(cb[c], mu_b, window, 1.5);
    cv::GaussianBlur(ca[c].mul(ca[c]), aa, window, 1.5);
    cv::GaussianBlur(cb[c].mul(cb[c]), bb, window, 1.5);
    cv::GaussianBlur(ca[c].mul(cb[c]), ab, window, 1.5);
    cv::Mat var_a = aa - mu_a.mul(mu_a), var_b = bb - mu_b.mul(mu_b), cov = ab - mu_a.mul(mu_b);
    cv::Mat num = (2 * mu_a.mul(mu_b) + c1).mul(2 * cov + c2);
    cv::Mat den = (mu_a.mul(mu_a) + mu_b.mul(mu_b) + c1).mul(var_a + var_b + c2);
    cv::Mat ratio;
    cv::divide(num, den, ratio);
    total += cv::mean(ratio)[0];
  }
  return total / ca.size();
}

}  // namespace holocap
