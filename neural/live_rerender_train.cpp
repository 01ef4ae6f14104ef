// Training a live-rerender U-Net on pairs of a scan take (neural/live_rerender.h).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <numbers>
#include <numeric>
#include <random>

#include "core/error.h"
#include "core/fs.h"
#include "core/image.h"
#include "core/progress.h"
#include "core/projector.h"
#include "core/threads.h"
#include "neural/internal/live_rerender.h"
#include "neural/internal/rerender_net.h"

namespace holocap {

namespace {

namespace fs = std::filesystem;
using torch::indexing::Slice;

// Weight of neural::RawOutputPenalty (as the witness trainer's): felt only once the output
// leaves its range.
constexpr double kRawOutputPenaltyWeight = 0.01;

double PooledPsnr(const neural::MaskedError& e) {
  return e.count > 0 && e.squared > 0 ? -10 * std::log10(e.squared / static_cast<double>(e.count))
                                      : std::numeric_limits<double>::quiet_NaN();
}

void Accumulate(const neural::MaskedError& e, neural::MaskedError* total) {
  total->squared += e.squared;
  total->count += e.count;
}

// The pairs, the training loop with its validation and kept weights, the model directory.
class LiveTrainer {
 public:
  LiveTrainer(const fs::path& scan_take, const fs::path& scan_dir, const fs::path& model_dir,
              const LiveRerenderOptions& options, Report* report)
      : scan_take_(scan_take),
        scan_dir_(scan_dir),
        model_dir_(model_dir),
        options_(options),
        report_(report),
        network_(options.net, options.seed) {}

  LiveRerenderSummary Run() {
    torch::set_num_threads(ResolveThreads(options_.threads));
    pairs_ = neural::MakeLivePairs(scan_take_, scan_dir_, options_);
    summary_.plan = pairs_.plan;
    summary_.plan["parameters"] = network_.parameter_count();
    summary_.composed_frames = pairs_.composed;
    summary_.refused_frames = pairs_.refused;
    summary_.train_pairs = static_cast<int64_t>(pairs_.train.size());
    summary_.validation_pairs = static_cast<int64_t>(pairs_.validation.size());
    if (report_) {
      report_->options() = options_.ToJson();
      report_->options()["scan_take"] = scan_take_.string();
      report_->options()["scan"] = scan_dir_.string();
      report_->plan() = summary_.plan;
    }
    if (pairs_.train.empty() || pairs_.validation.empty()) {
      summary_.End(
          Termination::kDegenerate,
          Cat("no training or validation pair: ", pairs_.composed,
              " frames of the scan take composed (", pairs_.refused, " refused), none turned ",
              options_.min_turn_deg, "-", options_.max_turn_deg, " degrees from another"));
      WriteReport();
      return summary_;
    }
    LoadTensors();
    summary_.raw_psnr_db = ValidationPsnr(/*raw=*/true);
    Train();
    KeepWeights();
    WriteModel();
    Summarise();
    WriteReport();
    return summary_;
  }

 private:
  void LoadTensors() {
    multiple_ = 1 << options_.net.depth;
    std::vector<torch::Tensor> features, targets, silhouettes;
    for (const neural::LivePair& pair : pairs_.train) {
      features.push_back(neural::RerenderFeatures(pair.buffers));
      targets.push_back(neural::ImageToTensor(pair.target));
      cv::Mat silhouette;
      pair.silhouette.convertTo(silhouette, CV_32F, 1.0 / 255);
      silhouettes.push_back(neural::ImageToTensor(silhouette));
      std::vector<int32_t> inside;
      for (int y = 0; y < pair.silhouette.rows; ++y)
        for (int x = 0; x < pair.silhouette.cols; ++x)
          if (pair.silhouette.at<uint8_t>(y, x)) inside.push_back(y * pair.silhouette.cols + x);
      subject_pixels_.push_back(std::move(inside));
    }
    features_ = neural::PadToMultiple(torch::stack(features), multiple_);
    targets_ = neural::PadToMultiple(torch::stack(targets), multiple_);
    silhouettes_ = neural::PadToMultiple(torch::stack(silhouettes), multiple_);
    width_ = pairs_.train[0].silhouette.cols;
    crop_w_ = features_.size(3), crop_h_ = features_.size(2);
    if (options_.crop_px > 0) {
      const int64_t crop = (options_.crop_px + multiple_ - 1) / multiple_ * multiple_;
      crop_w_ = std::min(crop_w_, crop);
      crop_h_ = std::min(crop_h_, crop);
    }
    summary_.plan["train_crop"] = options_.crop_px > 0
                                      ? Cat(crop_w_, "x", crop_h_, " in the target's silhouette")
                                      : std::string("whole images");
    if (report_) report_->plan() = summary_.plan;
  }

  // The network's (or the raw composition's) view of a pair, over black.
  cv::Mat View(const neural::LivePair& pair, bool raw) const {
    if (raw) return CompositeRawRender(pair.buffers, cv::Mat());
    return network_.Apply(pair.buffers, options_.threads).color;
  }

  double ValidationPsnr(bool raw) const {
    neural::MaskedError total;
    for (const neural::LivePair& pair : pairs_.validation)
      Accumulate(neural::ErrorInSilhouette(View(pair, raw), pair), &total);
    return PooledPsnr(total);
  }

  void EvaluateAndKeep(int64_t iteration) {
    const double psnr = ValidationPsnr(false);
    if (report_) report_->AddPoint("validation_psnr_db", psnr, iteration);
    if (psnr > best_) {
      best_ = psnr;
      summary_.kept_iteration = iteration;
      network_.Save(model_dir_ / "unet.pt");
    }
  }

  // A batch of crops centred on pixels of the targets' silhouettes.
  double TrainStep(torch::optim::Adam& optimizer) {
    std::vector<torch::Tensor> xs, truths, silhouettes;
    for (int b = 0; b < options_.batch; ++b) {
      const int64_t p = std::uniform_int_distribution<int64_t>(0, features_.size(0) - 1)(rng_);
      const std::vector<int32_t>& inside = subject_pixels_[p];
      const int64_t pixel =
          inside.empty()
              ? 0
              : inside[std::uniform_int_distribution<size_t>(0, inside.size() - 1)(rng_)];
      const int64_t x0 =
          std::clamp<int64_t>(pixel % width_ - crop_w_ / 2, 0, features_.size(3) - crop_w_);
      const int64_t y0 =
          std::clamp<int64_t>(pixel / width_ - crop_h_ / 2, 0, features_.size(2) - crop_h_);
      const auto window = [&](const torch::Tensor& all) {
        return all.index(
            {Slice(p, p + 1), Slice(), Slice(y0, y0 + crop_h_), Slice(x0, x0 + crop_w_)});
      };
      xs.push_back(window(features_));
      truths.push_back(window(targets_));
      silhouettes.push_back(window(silhouettes_));
    }
    const torch::Tensor x = torch::cat(xs), truth = torch::cat(truths),
                        silhouette = torch::cat(silhouettes);
    // The subject: the target's silhouette and what the composition covers.
    const torch::Tensor coverage = x.index({Slice(), Slice(3, 4)});
    const torch::Tensor weight = 1 + (options_.subject_weight - 1) *
                                         torch::max(silhouette, (coverage > 0).to(torch::kFloat));
    const torch::Tensor raw_output = network_.state().net->forward(x);
    auto [rgb, alpha] = neural::DecodeRerender(raw_output, x);
    const torch::Tensor out = rgb * alpha;
    torch::Tensor loss = (weight * (out - truth).abs()).mean() / weight.mean();
    loss =
        loss + options_.alpha_weight * (weight * (alpha - silhouette).abs()).mean() / weight.mean();
    loss = loss + kRawOutputPenaltyWeight * neural::RawOutputPenalty(raw_output);
    const double value = loss.item<double>();
    if (!std::isfinite(value)) return value;
    optimizer.zero_grad();
    loss.backward();
    optimizer.step();
    return value;
  }

  void Train() {
    torch::optim::Adam optimizer(network_.state().net->parameters(),
                                 torch::optim::AdamOptions(options_.learning_rate));
    rng_.seed(options_.seed);
    const auto start = std::chrono::steady_clock::now();
    const auto elapsed = [&] {
      return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    };
    Progress progress("live rerender", options_.iterations > 0
                                           ? options_.iterations
                                           : static_cast<int64_t>(options_.minutes * 60));
    int64_t iteration = 0;
    for (;; ++iteration) {
      const bool done = (options_.iterations > 0 && iteration >= options_.iterations) ||
                        (options_.minutes > 0 && elapsed() >= options_.minutes * 60);
      if (done || iteration % options_.eval_every == 0) EvaluateAndKeep(iteration);
      if (done) break;
      const double spent = std::max(
          options_.minutes > 0 ? elapsed() / (options_.minutes * 60) : 0.0,
          options_.iterations > 0 ? static_cast<double>(iteration) / options_.iterations : 0.0);
      static_cast<torch::optim::AdamOptions&>(optimizer.param_groups()[0].options())
          .lr(options_.learning_rate *
              (0.1 + 0.45 * (1 + std::cos(std::numbers::pi * std::min(spent, 1.0)))));
      const double value = TrainStep(optimizer);
      if (!std::isfinite(value)) {
        diverged_ = true;
        break;
      }
      losses_.push_back(value);
      if (report_ && iteration % 10 == 0) report_->AddPoint("loss", value, iteration);
      progress.Update(options_.iterations > 0 ? iteration : static_cast<int64_t>(elapsed()),
                      Cat(best_, " dB"));
    }
    progress.Finish();
    summary_.iterations = iteration;
    summary_.seconds = elapsed();
  }

  void KeepWeights() {
    neural::LossEnds(losses_, &summary_.first_loss, &summary_.last_loss);
    network_ = RerenderNetwork::Load(model_dir_ / "unet.pt", options_.net);
    summary_.validation_psnr_db = best_;
  }

  // model.json and validation.png (truth, raw composition, network: the middle validation pair).
  void WriteModel() {
    const neural::LivePair& pair = pairs_.validation[pairs_.validation.size() / 2];
    cv::Mat strip, eight_bit;
    cv::hconcat(std::vector<cv::Mat>{pair.target, View(pair, true), View(pair, false)}, strip);
    strip.convertTo(eight_bit, CV_8UC3, 255);
    WritePng(model_dir_ / "validation.png", eight_bit);
    const nlohmann::json model = {{"method", "live-rerender"},
                                  {"net", options_.net.ToJson()},
                                  {"supersample", options_.supersample},
                                  {"image_width", options_.image_width},
                                  {"scan_take", fs::absolute(scan_take_).string()},
                                  {"scan", fs::absolute(scan_dir_).string()},
                                  {"color_sensor", summary_.plan.value("color_sensor", "")}};
    WriteFileAtomic(model_dir_ / "model.json", model.dump(2));
  }

  void Summarise() {
    const std::string scores =
        Cat(summary_.validation_psnr_db, " dB inside the targets' silhouettes on ",
            summary_.validation_pairs, " validation pairs against the raw composition's ",
            summary_.raw_psnr_db, " dB");
    if (diverged_) {
      summary_.End(Termination::kFailure,
                   Cat("the loss became non-finite at iteration ", summary_.iterations,
                       "; kept the weights of iteration ", summary_.kept_iteration));
    } else if (!(summary_.validation_psnr_db > summary_.raw_psnr_db)) {
      summary_.End(Termination::kDegenerate,
                   Cat("the network is no better than the raw composition: ", scores));
    } else if (summary_.kept_iteration == 0) {
      // The untrained network starts as the raw composition: no step improved on it.
      summary_.End(Termination::kDegenerate,
                   Cat("no training step improved on the untrained network (the raw composition ",
                       "rendered as it is) in ", summary_.iterations, " iterations: ", scores));
    } else {
      summary_.End(summary_.kept_iteration < summary_.iterations ? Termination::kConvergence
                                                                 : Termination::kNoConvergence,
                   Cat("trained ", summary_.iterations, " iterations in ", summary_.seconds,
                       " s; kept iteration ", summary_.kept_iteration, ": ", scores));
    }
  }

  void WriteReport() {
    if (!report_) return;
    report_->plan() = summary_.plan;
    report_->metrics() = {{"validation_psnr_db", summary_.validation_psnr_db},
                          {"raw_psnr_db", summary_.raw_psnr_db},
                          {"kept_iteration", summary_.kept_iteration},
                          {"composed_frames", summary_.composed_frames},
                          {"refused_frames", summary_.refused_frames},
                          {"train_pairs", summary_.train_pairs},
                          {"validation_pairs", summary_.validation_pairs},
                          {"iterations", summary_.iterations},
                          {"seconds", summary_.seconds},
                          {"first_loss", summary_.first_loss},
                          {"last_loss", summary_.last_loss}};
    report_->SetSummary(summary_);
    report_->Write(model_dir_ / "report.json");
  }

  const fs::path scan_take_, scan_dir_, model_dir_;
  const LiveRerenderOptions& options_;
  Report* report_;
  LiveRerenderSummary summary_;
  neural::LivePairs pairs_;
  RerenderNetwork network_;
  int multiple_ = 1;
  torch::Tensor features_, targets_, silhouettes_;
  std::vector<std::vector<int32_t>> subject_pixels_;
  int width_ = 0;
  int64_t crop_w_ = 0, crop_h_ = 0;
  std::mt19937_64 rng_;
  double best_ = -std::numeric_limits<double>::infinity();
  std::vector<double> losses_;
  bool diverged_ = false;
};

}  // namespace

LiveRerenderSummary TrainLiveRerender(const fs::path& scan_take, const fs::path& scan_dir,
                                      const fs::path& model_dir, const LiveRerenderOptions& options,
                                      Report* report) {
  options.Check();
  CreateDirectories(model_dir);
  return LiveTrainer(scan_take, scan_dir, model_dir, options, report).Run();
}

}  // namespace holocap
