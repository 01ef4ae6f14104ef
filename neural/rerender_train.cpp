// Training a rerendering U-Net on witness cameras that the reconstruction never saw.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <limits>
#include <map>
#include <numbers>
#include <numeric>
#include <opencv2/imgproc.hpp>
#include <random>
#include <set>
#include <tuple>

#include "avatar/image_metrics.h"
#include "avatar/training_data.h"
#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/image.h"
#include "core/progress.h"
#include "core/projector.h"
#include "core/take.h"
#include "core/take_plan.h"
#include "core/threads.h"
#include "neural/internal/rerender_net.h"

namespace holocap {

namespace {

using torch::indexing::Slice;

double Seconds(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - since).count();
}

// A copy of the take's manifest in which the named cameras are witnesses (reconstruction uses
// colour and depth sensors only); frames, index, calibration and ground truth are hard-linked.
void WriteWitnessView(const Take& take, const std::set<std::string>& witnesses,
                      const std::filesystem::path& dir) {
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  nlohmann::json manifest = nlohmann::json::parse(ReadFileToString(take.dir() / "take.json"));
  auto mark = [&](nlohmann::json& list) {
    for (auto& sensor : list) {
      if (sensor.contains("name") && witnesses.count(sensor["name"].get<std::string>()))
        sensor["role"] = "witness";
    }
  };
  if (manifest.contains("streams")) mark(manifest["streams"]);
  if (manifest.contains("rig") && manifest["rig"].contains("sensors"))
    mark(manifest["rig"]["sensors"]);
  WriteFileAtomic(dir / "take.json", manifest.dump(2));
  const std::string index = manifest.value("index", std::string("index.jsonl"));
  // Hard links (copies across file systems): a take's frames lie inside it, so a link out of
  // the view would be refused by every reader.
  for (const std::string& entry :
       {std::string("frames"), std::string("calib"), std::string("gt"), index}) {
    const auto target = take.dir() / entry;
    if (!std::filesystem::exists(target)) continue;
    std::error_code linked;
    std::filesystem::copy(
        target, dir / entry,
        std::filesystem::copy_options::recursive | std::filesystem::copy_options::create_hard_links,
        linked);
    if (linked) {
      std::filesystem::remove_all(dir / entry);
      std::filesystem::copy(target, dir / entry, std::filesystem::copy_options::recursive);
    }
  }
}

// SSIM with a 7x7 box window (torch), averaged over three scales.
torch::Tensor MultiScaleSsim(torch::Tensor a, torch::Tensor b) {
  const double c1 = 0.01 * 0.01, c2 = 0.03 * 0.03;
  torch::Tensor total = torch::zeros({}, a.options());
  int scales = 0;
  for (int scale = 0; scale < 3; ++scale) {
    if (std::min(a.size(2), a.size(3)) < 7) break;
    auto pool = [](const torch::Tensor& x) { return torch::avg_pool2d(x, 7, 1); };
    const torch::Tensor mu_a = pool(a), mu_b = pool(b);
    const torch::Tensor var_a = pool(a * a) - mu_a * mu_a, var_b = pool(b * b) - mu_b * mu_b;
    const torch::Tensor cov = pool(a * b) - mu_a * mu_b;
    const torch::Tensor ssim = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) /
                               ((mu_a * mu_a + mu_b * mu_b + c1) * (var_a + var_b + c2));
    total = total + ssim.mean();
    ++scales;
    a = torch::avg_pool2d(a, 2);
    b = torch::avg_pool2d(b, 2);
  }
  return scales > 0 ? total / scales : torch::ones({}, a.options());
}

// A PatchGAN discriminator (Isola et al. 2017): real/fake per 16x16 patch.
torch::nn::Sequential PatchDiscriminator() {
  auto lrelu = [] {
    return torch::nn::LeakyReLU(torch::nn::LeakyReLUOptions().negative_slope(0.2));
  };
  return torch::nn::Sequential(
      torch::nn::Conv2d(torch::nn::Conv2dOptions(3, 32, 4).stride(2).padding(1)), lrelu(),
      torch::nn::Conv2d(torch::nn::Conv2dOptions(32, 64, 4).stride(2).padding(1)), lrelu(),
      torch::nn::Conv2d(torch::nn::Conv2dOptions(64, 1, 3).padding(1)));
}

// Weight of neural::RawOutputPenalty: small, so that it is felt only once the output leaves its
// range, where every other term's gradient has vanished.
constexpr double kRawOutputPenaltyWeight = 0.01;
// A kept network whose held-out PSNR near the subject is within this of the background alone's
// draws no subject (a healthy one is several dB above it).
constexpr double kErasedMarginDb = 0.5;

// The held-out scores that tell whether the kept network draws the subject: near the rendered
// subject, or over the whole image where nothing is rendered.
struct SubjectScores {
  bool near = false;
  double shown = 0, background = 0, raw = 0;
  // Within kErasedMarginDb of the background alone: no more of the subject than no subject.
  bool shows_none() const {
    return std::isfinite(shown) && std::isfinite(background) &&
           shown <= background + kErasedMarginDb;
  }
};
SubjectScores ScoresNearSubject(const RerenderSummary& s) {
  SubjectScores scores;
  scores.near =
      std::isfinite(s.heldout_psnr_subject_db) && std::isfinite(s.background_psnr_subject_db);
  scores.shown = scores.near ? s.heldout_psnr_subject_db : s.heldout_psnr_db;
  scores.background = scores.near ? s.background_psnr_subject_db : s.background_psnr_db;
  scores.raw = scores.near ? s.raw_render_psnr_subject_db : s.raw_render_psnr_db;
  return scores;
}

// One camera at the training resolution, over every frame.
struct CameraData {
  std::string name;
  CameraModel camera;          // native
  CameraModel scaled;          // training resolution
  torch::Tensor features;      // [F, 8, Hp, Wp] padded
  torch::Tensor truth;         // [F, 3, Hp, Wp] BGR in [0, 1]
  torch::Tensor background;    // [1, 3, Hp, Wp]
  torch::Tensor weight;        // [F, 1, Hp, Wp] loss weights (subject favoured)
  torch::Tensor alpha_target;  // [F, 1, Hp, Wp] the camera's own silhouette (witnesses), or
                               // undefined without one
  std::vector<cv::Mat> truth_images, raw_images, subject_masks;  // unpadded
  cv::Mat background_image;                                      // unpadded
  std::vector<std::vector<int32_t>> subject_pixels;  // per frame, y * width + x near the subject
  int height = 0, width = 0;
  bool witness = false;  // trained on (else held out for measurement)
};

cv::Mat ToFloatImage(const cv::Mat& image, const cv::Size& size) {
  cv::Mat color = image;
  if (color.channels() == 1) cv::cvtColor(color, color, cv::COLOR_GRAY2BGR);
  if (color.channels() == 4) cv::cvtColor(color, color, cv::COLOR_BGRA2BGR);
  cv::Mat scaled;
  if (color.size() != size) {
    cv::resize(color, scaled, size, 0, 0, cv::INTER_AREA);
  } else {
    scaled = color;
  }
  cv::Mat out;
  scaled.convertTo(out, CV_32FC3, color.depth() == CV_16U ? 1.0 / 65535 : 1.0 / 255);
  return out;
}

// 8-bit BGR at native size (what silhouette extraction takes).
cv::Mat ToEightBitColor(const cv::Mat& image) {
  cv::Mat color = image;
  if (color.depth() == CV_16U) color.convertTo(color, CV_8U, 1.0 / 257.0);
  if (color.channels() == 1) cv::cvtColor(color, color, cv::COLOR_GRAY2BGR);
  return color;
}

// The composite over the background [B, 3, H, W].
torch::Tensor Composite(const torch::Tensor& rgb, const torch::Tensor& alpha,
                        const torch::Tensor& background) {
  return rgb * alpha + background * (1 - alpha);
}

struct Evaluation {
  double psnr_db = 0, ssim = 0, psnr_subject_db = 0;
  double flicker_ratio = 0, flicker_excess = 0;
};

// Mean |frame-to-frame change| relative to the truth's, and mean |change - truth's change|.
void Flicker(const std::vector<cv::Mat>& images, const std::vector<cv::Mat>& truth,
             Evaluation* evaluation) {
  double change = 0, truth_change = 0, excess = 0;
  for (size_t f = 1; f < images.size(); ++f) {
    const cv::Mat d = images[f] - images[f - 1], t = truth[f] - truth[f - 1];
    change += cv::norm(d, cv::NORM_L1);
    truth_change += cv::norm(t, cv::NORM_L1);
    excess += cv::norm(d - t, cv::NORM_L1);
  }
  const double pixels =
      images.empty()
          ? 1.0
          : static_cast<double>(images[0].total() * 3 * std::max<size_t>(1, images.size() - 1));
  evaluation->flicker_ratio =
      truth_change > 0 ? change / truth_change : std::numeric_limits<double>::quiet_NaN();
  evaluation->flicker_excess = excess / pixels;
}

Evaluation Score(const std::vector<std::vector<cv::Mat>>& images,
                 const std::vector<CameraData*>& cameras) {
  Evaluation e;
  double mse = 0, mse_subject = 0;
  int64_t count = 0, count_subject = 0, views = 0;
  for (size_t c = 0; c < cameras.size(); ++c) {
    for (size_t f = 0; f < images[c].size(); ++f) {
      cv::Mat diff = images[c][f] - cameras[c]->truth_images[f];
      diff = diff.mul(diff);
      mse += cv::sum(diff).dot(cv::Scalar::all(1));
      count += static_cast<int64_t>(diff.total()) * 3;
      mse_subject +=
          cv::sum(diff.setTo(0, cameras[c]->subject_masks[f] == 0)).dot(cv::Scalar::all(1));
      count_subject += static_cast<int64_t>(cv::countNonZero(cameras[c]->subject_masks[f])) * 3;
      e.ssim += Ssim(images[c][f], cameras[c]->truth_images[f]);
      ++views;
    }
  }
  auto psnr = [](double sum, int64_t n) {
    return n > 0 && sum > 0 ? -10 * std::log10(sum / n) : std::numeric_limits<double>::quiet_NaN();
  };
  e.psnr_db = psnr(mse, count);
  e.psnr_subject_db = psnr(mse_subject, count_subject);
  e.ssim /= std::max<int64_t>(1, views);
  if (!cameras.empty()) Flicker(images[0], cameras[0]->truth_images, &e);
  return e;
}

}  // namespace

void RerenderOptions::Check() const {
  net.Check();
  HOLOCAP_CHECK_OPTION(witness_cameras >= 1 || !witness.empty(), witness_cameras,
                       "rerender needs at least one witness camera");
  HOLOCAP_CHECK_OPTION_GE(heldout_cameras, 0);
  HOLOCAP_CHECK_OPTION_GE(validation_witnesses, -1, "-1: automatic");
  MeshRasterOptions{.supersample = supersample}.Check();
  HOLOCAP_CHECK_OPTION(!witness_scales.empty(), witness_scales, "1: the training width only");
  for (double scale : witness_scales) {
    HOLOCAP_CHECK_OPTION(scale >= 0.25 && scale <= 2, witness_scales, "each in [0.25, 2]");
  }
  HOLOCAP_CHECK_OPTION(std::ranges::find(witness_scales, 1.0) != witness_scales.end(),
                       witness_scales,
                       "1 is the training width, where validation and held-out cameras are "
                       "scored");
  HOLOCAP_CHECK_OPTION_IN(witness_folds, 1, 16);
  for (const auto& fold : fold_witness) {
    HOLOCAP_CHECK_OPTION(!fold.empty(), fold_witness, "a fold of witnesses cannot be empty");
  }
  HOLOCAP_CHECK_OPTION(
      !fold_witness.empty() || fold_recon_dirs.size() <= static_cast<size_t>(witness_folds - 1),
      fold_recon_dirs,
      Cat(fold_recon_dirs.size(), " fold reconstructions given for ", witness_folds - 1,
          " further fold(s)"));
  HOLOCAP_CHECK_OPTION(image_width == 0 || image_width >= 32, image_width,
                       "0: native, else at least 32 px");
  take.Check();
  HOLOCAP_CHECK_OPTION(std::isfinite(minutes), minutes, "a budget must end");
  HOLOCAP_CHECK_OPTION(minutes > 0 || iterations > 0, minutes,
                       "give a positive time budget (minutes) or an iteration count");
  HOLOCAP_CHECK_OPTION_GE(iterations, 0);
  HOLOCAP_CHECK_OPTION_IN(batch_pairs, 1, 64);
  HOLOCAP_CHECK_OPTION(crop_px == 0 || crop_px >= 16, crop_px, "0: whole images, else at least 16");
  HOLOCAP_CHECK_OPTION_GT(learning_rate, 0);
  HOLOCAP_CHECK_OPTION_LT(learning_rate, 1);
  HOLOCAP_CHECK_OPTION(l1_weight >= 0 && std::isfinite(l1_weight), l1_weight);
  HOLOCAP_CHECK_OPTION(ssim_weight >= 0 && std::isfinite(ssim_weight), ssim_weight);
  HOLOCAP_CHECK_OPTION(temporal_weight >= 0 && std::isfinite(temporal_weight), temporal_weight);
  HOLOCAP_CHECK_OPTION(gan_weight >= 0 && std::isfinite(gan_weight), gan_weight);
  HOLOCAP_CHECK_OPTION(l1_weight + ssim_weight > 0, l1_weight,
                       "l1_weight and ssim_weight cannot both be 0");
  HOLOCAP_CHECK_OPTION_IN(subject_weight, 1, 100);
  HOLOCAP_CHECK_OPTION_IN(alpha_weight, 0, 100);
  HOLOCAP_CHECK_OPTION_GT(eval_every_s, 0);
  HOLOCAP_CHECK_OPTION_GE(threads, 0, "0: all cores");
  reconstruction.Check();
}

nlohmann::json RerenderOptions::ToJson() const {
  return {{"net", net.ToJson()},
          {"witness_cameras", witness_cameras},
          {"heldout_cameras", heldout_cameras},
          {"witness", witness},
          {"heldout", heldout},
          {"take", take.ToJson()},
          {"recon_dir", recon_dir.string()},
          {"witness_folds", witness_folds},
          {"validation_witnesses", validation_witnesses},
          {"fold_witness", fold_witness},
          {"fold_recon_dirs",
           [&] {
             std::vector<std::string> d;
             for (const auto& p : fold_recon_dirs) d.push_back(p.string());
             return d;
           }()},
          {"reconstruction", reconstruction.ToJson()},
          {"image_width", image_width},
          {"supersample", supersample},
          {"witness_scales", witness_scales},
          {"minutes", minutes},
          {"iterations", iterations},
          {"batch_pairs", batch_pairs},
          {"crop_px", crop_px},
          {"learning_rate", learning_rate},
          {"l1_weight", l1_weight},
          {"ssim_weight", ssim_weight},
          {"subject_weight", subject_weight},
          {"alpha_weight", alpha_weight},
          {"temporal_weight", temporal_weight},
          {"gan_weight", gan_weight},
          {"seed", seed},
          {"eval_every_s", eval_every_s},
          {"threads", threads}};
}

namespace {

// Trains one rerendering model: the take's plan and the three-way camera split, a
// reconstruction per witness fold, the data at the training resolution, the training loop
// with early stopping, then the model directory and the summary. Each step is a method; the
// state they share lives in members.
class RerenderTrainer {
 public:
  RerenderTrainer(const std::filesystem::path& take_dir, const std::filesystem::path& model_dir,
                  const RerenderOptions& options, Report* report)
      : take_(Take::Open(take_dir)),
        model_dir_(model_dir),
        options_(options),
        report_(report),
        plan_(summary_.plan),
        network_(options.net, options.seed) {}

  RerenderSummary Run() {
    PlanCameras();
    ChooseFolds();
    ReconstructFolds();
    if (!ChooseFrameSets()) return summary_;
    LoadData();
    DescribeTraining();
    MeasureBaselines();
    Train();
    KeepWeights();
    WriteModel();
    Summarise();
    return summary_;
  }

 private:
  enum class Output { kNetwork, kRaw, kBackground };

  bool is_heldout(int c) const {
    return std::find(heldout_.begin(), heldout_.end(), c) != heldout_.end();
  }
  bool is_witness_yet(int c) const {
    for (const auto& fold : folds_) {
      if (std::find(fold.begin(), fold.end(), c) != fold.end()) return true;
    }
    return false;
  }

  // The take's plan; held-out cameras and the first witnesses, spread around the rig.
  void PlanCameras() {
    take_plan_ = PlanTake(take_, options_.take);
    names_ = take_plan_.color_sensors;
    cameras_ = take_plan_.Cameras(names_);
    Eigen::Vector3d center = Eigen::Vector3d::Zero();
    for (const auto& c : cameras_)
      center += c.center_in_world() / static_cast<double>(cameras_.size());
    center_ = center;
    // Cameras that colour the depth sensors' fusion stay with the reconstruction when possible.
    std::vector<int> candidates, fallback;
    for (int i = 0; i < static_cast<int>(names_.size()); ++i) {
      (take_plan_.paired_color.count(names_[i]) ? fallback : candidates).push_back(i);
    }
    const int wanted_out = (options_.heldout.empty() ? options_.heldout_cameras
                                                     : static_cast<int>(options_.heldout.size())) +
                           (options_.witness.empty() ? options_.witness_cameras
                                                     : static_cast<int>(options_.witness.size()));
    if (static_cast<int>(candidates.size()) < wanted_out)
      candidates.insert(candidates.end(), fallback.begin(), fallback.end());
    heldout_ = options_.heldout.empty()
                   ? SpreadAround(cameras_, candidates, options_.heldout_cameras, center_)
                   : take_plan_.ColorIndices(options_.heldout, "held-out");
    for (int c : candidates) {
      if (!is_heldout(c)) rest_.push_back(c);
    }
    const std::vector<int> witness =
        options_.witness.empty() ? SpreadAround(cameras_, rest_, options_.witness_cameras, center_)
                                 : take_plan_.ColorIndices(options_.witness, "witness");
    for (int w : witness) {
      if (is_heldout(w)) Fail("camera '", names_[w], "' cannot be both witness and held out");
    }
    recon_count_ = static_cast<int>(names_.size() - witness.size() - heldout_.size());
    if (witness.empty() || recon_count_ < 2) {
      Fail("take '", take_.dir().string(), "' has ", names_.size(),
           " colour cameras: ", witness.size(), " witness and ", heldout_.size(),
           " held-out ones leave ", recon_count_, " for the reconstruction (it needs 2)");
    }
    folds_ = {witness};
  }

  // Further folds: other witness sets, each with its own reconstruction.
  void ChooseFolds() {
    if (!options_.fold_witness.empty()) {
      for (const auto& named : options_.fold_witness) {
        std::vector<int> fold = take_plan_.ColorIndices(named, "witness");
        for (int c : fold) {
          if (is_heldout(c)) Fail("camera '", names_[c], "' cannot be both witness and held out");
          if (is_witness_yet(c)) Fail("camera '", names_[c], "' is a witness of two folds");
        }
        folds_.push_back(fold);
      }
    } else {
      const int fold_size = static_cast<int>(folds_[0].size());
      for (int k = 1; k < options_.witness_folds; ++k) {
        std::vector<int> pool;
        for (int c : rest_) {
          if (!is_witness_yet(c)) pool.push_back(c);
        }
        if (pool.empty()) break;
        folds_.push_back(SpreadAround(
            cameras_, pool, std::min<int>(fold_size, static_cast<int>(pool.size())), center_));
      }
    }
    for (const auto& fold : folds_) {
      const int left = static_cast<int>(names_.size() - fold.size() - heldout_.size());
      if (fold.empty() || left < 2)
        Fail("a fold of ", fold.size(), " witnesses leaves ", left,
             " cameras for its reconstruction (it needs 2)");
    }
    if (options_.fold_recon_dirs.size() > folds_.size() - 1) {
      Fail(options_.fold_recon_dirs.size(), " fold reconstructions given for ", folds_.size() - 1,
           " further fold(s)");
    }
    for (const auto& fold : folds_) {
      for (int w : fold) witness_names_.push_back(names_[w]);
    }
    for (int h : heldout_) take_plan_.heldout.push_back(names_[h]);
    take_plan_.witness = witness_names_;
    validation_count_ = options_.validation_witnesses >= 0 ? options_.validation_witnesses
                        : witness_names_.size() >= 3
                            ? std::max(1, static_cast<int>(witness_names_.size()) / 5)
                            : 0;
    if (validation_count_ >= static_cast<int>(witness_names_.size())) {
      Fail(validation_count_, " validation witness(es) leave no witness to train on (",
           witness_names_.size(), " in all): ask for more witnesses or folds");
    }
    if (!take_plan_.depth_sensors.empty() &&
        options_.reconstruction.method == ReconstructionMethod::kHull) {
      take_plan_.LeaveOut("depth sensors", "the folds' reconstruction is a visual hull");
    }
    plan_ = take_plan_.ToJson();
    plan_["reconstruction_cameras"] = recon_count_;
  }

  // Builds fold k's reconstruction from the cameras that are neither its witnesses nor held out.
  std::map<int64_t, std::filesystem::path> BuildReconstruction(
      size_t k, const std::set<std::string>& left_out, nlohmann::json& fold_plan) {
    std::map<int64_t, std::filesystem::path> meshes;
    const std::filesystem::path recon_dir =
        k == 0 ? model_dir_ / "recon" : model_dir_ / Cat("recon-", k);
    const std::filesystem::path view = model_dir_ / "witness_take";
    WriteWitnessView(take_, left_out, view);
    ReconstructionOptions recon = options_.reconstruction;
    recon.write_glb = false;
    recon.sweep_voxels_m.clear();
    recon.threads = options_.threads;
    Report recon_report("reconstruct");
    ReconstructionSummary built =
        ReconstructTake(view, options_.take, recon_dir, recon, &recon_report);
    for (const auto& f : built.frames) {
      char file[32];
      std::snprintf(file, sizeof(file), "%06lld.ply", static_cast<long long>(f.set));
      if (f.IsUsable() && f.faces > 0) meshes[f.set] = recon_dir / file;
    }
    fold_plan["reconstruction"] = Cat(ToString(built.termination), ": ", built.message);
    std::filesystem::remove_all(view);
    return meshes;
  }

  // A given reconstruction; refused when its report says it saw a witness or held-out camera
  // (it would score the network on views it was coloured from).
  std::map<int64_t, std::filesystem::path> GivenReconstruction(
      const std::filesystem::path& recon_dir, const std::set<std::string>& left_out,
      nlohmann::json& fold_plan) {
    if (!std::filesystem::is_directory(recon_dir))
      Fail("reconstruction directory ", recon_dir.string(), " does not exist");
    const std::filesystem::path built_report = recon_dir / "report.json";
    std::string cameras_used = "cameras not recorded";
    if (std::filesystem::exists(built_report)) {
      nlohmann::json built;
      try {
        built = nlohmann::json::parse(std::ifstream(built_report));
      } catch (const std::exception& e) {
        Fail("reconstruction report ", built_report.string(), " is unreadable: ", e.what());
      }
      const nlohmann::json used = built.contains("plan")
                                      ? built["plan"].value("color_sensors", nlohmann::json())
                                      : nlohmann::json();
      if (used.is_array()) {
        for (const auto& name : used) {
          const std::string camera = name.get<std::string>();
          if (!left_out.count(camera)) continue;
          const bool was_heldout = std::any_of(heldout_.begin(), heldout_.end(),
                                               [&](int h) { return names_[h] == camera; });
          Fail("reconstruction ", recon_dir.string(), " was built with camera '", camera, "', ",
               was_heldout ? "held out" : "a witness of its fold",
               ": build it without that camera");
        }
        cameras_used =
            Cat(used.size(), " colour cameras, none of this fold's witnesses or held-out");
      }
    }
    std::map<int64_t, std::filesystem::path> meshes;
    for (const auto& entry : std::filesystem::directory_iterator(recon_dir)) {
      if (entry.path().extension() != ".ply") continue;
      try {
        meshes[std::stoll(entry.path().stem().string())] = entry.path();
      } catch (const std::exception&) {
      }
    }
    fold_plan["reconstruction"] = Cat("given: ", recon_dir.string(), " (", cameras_used, ")");
    return meshes;
  }

  void ReconstructFolds() {
    std::filesystem::create_directories(model_dir_);
    const auto start_all = std::chrono::steady_clock::now();
    nlohmann::json fold_plans = nlohmann::json::array();
    for (size_t k = 0; k < folds_.size(); ++k) {
      nlohmann::json fold_plan;
      std::vector<std::string> fold_names;
      for (int w : folds_[k]) fold_names.push_back(names_[w]);
      fold_plan["witness"] = fold_names;
      fold_plan["reconstruction_cameras"] =
          static_cast<int>(names_.size() - folds_[k].size() - heldout_.size());
      std::set<std::string> left_out;
      for (int w : folds_[k]) left_out.insert(names_[w]);
      for (int h : heldout_) left_out.insert(names_[h]);
      const std::filesystem::path given = k == 0 ? options_.recon_dir
                                          : k - 1 < options_.fold_recon_dirs.size()
                                              ? options_.fold_recon_dirs[k - 1]
                                              : std::filesystem::path();
      const auto start_fold = std::chrono::steady_clock::now();
      fold_meshes_.push_back(given.empty() ? BuildReconstruction(k, left_out, fold_plan)
                                           : GivenReconstruction(given, left_out, fold_plan));
      fold_plan["reconstruction_seconds"] = Seconds(start_fold);
      if (k == 0) plan_["reconstruction"] = fold_plan["reconstruction"];
      fold_plans.push_back(fold_plan);
    }
    if (folds_.size() > 1) plan_["folds"] = fold_plans;
    if (options_.fold_witness.empty() && static_cast<int>(folds_.size()) < options_.witness_folds) {
      plan_["witness_folds"] =
          Cat(options_.witness_folds, " asked, ", folds_.size(),
              " possible: every other camera is a witness, held out or colours a depth sensor");
    }
    plan_["reconstruction_seconds"] = Seconds(start_all);
  }

  // The frame sets every fold reconstructed; false (DEGENERATE, reported) when there are none.
  bool ChooseFrameSets() {
    for (size_t i = 0; i < take_.size(); ++i) entry_of_set_[take_.entry(i).index] = i;
    for (const auto& [set, file] : fold_meshes_[0]) {
      bool everywhere = entry_of_set_.count(set) > 0;
      for (const auto& other : fold_meshes_) everywhere = everywhere && other.count(set) > 0;
      if (everywhere) sets_.push_back(set);
    }
    plan_["frames"] = sets_.size();
    if (!sets_.empty()) return true;
    summary_.End(Termination::kDegenerate, "the reconstruction gave no mesh to rerender");
    if (report_) {
      report_->plan() = plan_;
      report_->SetSummary(summary_);
      report_->Write(model_dir_ / "report.json");
    }
    return false;
  }

  // One camera at the training resolution (times `extra_scale`), over every frame set.
  void LoadCamera(int index, const std::vector<Mesh>& mesh_cache, bool is_witness,
                  double extra_scale) {
    CameraData d;
    d.name = names_[index];
    d.witness = is_witness;
    d.camera = cameras_[index];
    const double scale =
        (options_.image_width > 0 ? static_cast<double>(options_.image_width) / d.camera.width()
                                  : 1.0) *
        extra_scale;
    d.scaled = scale == 1.0 ? d.camera : d.camera.Scaled(scale);
    d.width = d.scaled.width();
    d.height = d.scaled.height();
    const cv::Size size(d.width, d.height);
    const bool has_plate = take_plan_.has_clean_plate();
    const size_t plate_set = static_cast<size_t>(std::max<int64_t>(0, take_plan_.plate_set()));
    cv::Mat background = has_plate ? ToFloatImage(take_.ReadFrame(plate_set, d.name), size)
                                   : cv::Mat(size, CV_32FC3, cv::Scalar::all(0));
    d.background = neural::PadToMultiple(neural::ImageToTensor(background).unsqueeze(0), multiple_);
    d.background_image = background;
    // Alpha first (exact), as the take plan orders the sources; else the plate or a threshold.
    const bool alpha = take_plan_.silhouettes == SilhouetteSource::kAlpha;
    SilhouetteOptions witness_silhouette = options_.reconstruction.silhouette;
    if (alpha) witness_silhouette.mode = SilhouetteMode::kAlpha;
    const bool silhouettes =
        is_witness && options_.alpha_weight > 0 &&
        (alpha || options_.reconstruction.silhouette.mode == SilhouetteMode::kThreshold ||
         has_plate);
    cv::Mat plate;
    if (silhouettes && has_plate) plate = ToEightBitColor(take_.ReadFrame(plate_set, d.name));
    std::vector<torch::Tensor> features, truth, weight, alpha_target;
    const int dilate = std::max(2, d.width / 40);
    const cv::Mat kernel =
        cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * dilate + 1, 2 * dilate + 1));
    for (size_t f = 0; f < sets_.size(); ++f) {
      GBuffer buffers = RasteriseMesh(
          mesh_cache[f], d.scaled,
          MeshRasterOptions{.supersample = options_.supersample, .threads = threads_});
      const cv::Mat native = take_.ReadFrame(entry_of_set_[sets_[f]], d.name);
      cv::Mat image = ToFloatImage(native, size);
      if (silhouettes) {
        // The witness's silhouette at the training resolution (area-averaged: soft edges).
        cv::Mat mask = alpha
                           ? ExtractSilhouette(native, cv::Mat(), witness_silhouette)
                           : ExtractSilhouette(ToEightBitColor(native), plate, witness_silhouette),
                soft;
        mask.convertTo(mask, CV_32F, 1.0 / 255);
        cv::resize(mask, soft, size, 0, 0, cv::INTER_AREA);
        alpha_target.push_back(neural::ImageToTensor(soft));
      }
      cv::Mat subject;
      cv::dilate(buffers.mask, subject, kernel);
      features.push_back(neural::RerenderFeatures(buffers));
      truth.push_back(neural::ImageToTensor(image));
      cv::Mat w;
      subject.convertTo(w, CV_32F, (options_.subject_weight - 1) / 255.0, 1.0);
      weight.push_back(neural::ImageToTensor(w));
      d.truth_images.push_back(image);
      d.raw_images.push_back(CompositeRawRender(buffers, background));
      d.subject_masks.push_back(subject);
      std::vector<cv::Point> near;
      cv::findNonZero(subject, near);
      d.subject_pixels.emplace_back();
      for (const cv::Point& p : near) d.subject_pixels.back().push_back(p.y * d.width + p.x);
    }
    d.features = neural::PadToMultiple(torch::stack(features), multiple_);
    d.truth = neural::PadToMultiple(torch::stack(truth), multiple_);
    d.weight = neural::PadToMultiple(torch::stack(weight), multiple_);
    if (!alpha_target.empty())
      d.alpha_target = neural::PadToMultiple(torch::stack(alpha_target), multiple_);
    data_.push_back(std::move(d));
  }

  // Data at the training resolution (and, for the witnesses, at the further scales asked for),
  // one fold's meshes in memory at a time; then the split into trained, validation and
  // held-out cameras.
  void LoadData() {
    validation_names_ =
        std::set<std::string>(witness_names_.end() - validation_count_, witness_names_.end());
    threads_ = ResolveThreads(options_.threads);
    torch::set_num_threads(threads_);
    multiple_ = 1 << options_.net.depth;
    for (size_t k = 0; k < folds_.size(); ++k) {
      std::vector<Mesh> mesh_cache;
      for (int64_t set : sets_) mesh_cache.push_back(ReadPly(fold_meshes_[k][set]));
      if (k == 0) {
        for (const Mesh& m : mesh_cache) {
          for (const auto& v : m.vertices) {
            box_min_ = box_min_.cwiseMin(v.cast<double>());
            box_max_ = box_max_.cwiseMax(v.cast<double>());
          }
        }
        for (int h : heldout_) LoadCamera(h, mesh_cache, false, 1.0);
      }
      for (int w : folds_[k]) {
        LoadCamera(w, mesh_cache, true, 1.0);
        // Validation witnesses are scored at the training width only; the others train at every
        // scale asked for.
        if (validation_names_.count(names_[w])) continue;
        for (double s : options_.witness_scales) {
          if (s != 1.0) LoadCamera(w, mesh_cache, true, s);
        }
      }
    }
    for (CameraData& d : data_) {
      if (!d.witness)
        eval_cameras_.push_back(&d);
      else if (validation_names_.count(d.name))
        validation_cameras_.push_back(&d);
      else
        train_cameras_.push_back(&d);
    }
    temporal_ = sets_.size() >= 2 && options_.temporal_weight > 0;
  }

  void DescribeTraining() {
    if (!validation_cameras_.empty()) {
      std::vector<std::string> validation_list;
      for (const CameraData* d : validation_cameras_) validation_list.push_back(d->name);
      plan_["validation"] = validation_list;
    }
    plan_["temporal_term"] =
        temporal_ ? "on" : (sets_.size() < 2 ? "off: one frame" : "off: weight 0");
    plan_["patch_gan"] = options_.gan_weight > 0 ? "on" : "off";
    plan_["alpha_target"] = options_.alpha_weight <= 0 ? std::string("off: weight 0")
                            : train_cameras_[0]->alpha_target.defined()
                                ? std::string("the witnesses' silhouettes")
                                : std::string("off: background subtraction without a clean plate");
    if (options_.witness_scales.size() > 1 || options_.witness_scales[0] != 1.0)
      plan_["witness_scales"] = options_.witness_scales;
    plan_["trained_views"] = train_cameras_.size();  // witness cameras trained on, once per scale
    plan_["train_resolution"] = Cat(train_cameras_[0]->width, "x", train_cameras_[0]->height, " (",
                                    train_cameras_[0]->name, ")");
    plan_["raster_samples"] = options_.supersample == 1
                                  ? std::string("1 per pixel (its centre)")
                                  : Cat(options_.supersample, "x", options_.supersample,
                                        " per pixel, averaged (the raw render too)");
    // Crops share one size across the witnesses: the requested one rounded up to the network's
    // multiple, at most the smallest padded image.
    crop_w_ = crop_h_ = std::numeric_limits<int64_t>::max();
    for (const CameraData* d : train_cameras_) {
      crop_w_ = std::min(crop_w_, d->features.size(3));
      crop_h_ = std::min(crop_h_, d->features.size(2));
    }
    if (options_.crop_px > 0) {
      const int64_t crop =
          static_cast<int64_t>((options_.crop_px + multiple_ - 1) / multiple_) * multiple_;
      crop_w_ = std::min(crop_w_, crop);
      crop_h_ = std::min(crop_h_, crop);
    }
    plan_["train_crop"] = options_.crop_px > 0 ? Cat(crop_w_, "x", crop_h_, " near the subject")
                                               : std::string("whole images");
    plan_["parameters"] = network_.parameter_count();
    if (report_) {
      report_->options() = options_.ToJson();
      report_->plan() = plan_;
    }
  }

  std::pair<Evaluation, std::vector<std::vector<cv::Mat>>> Evaluate(
      Output what, const std::vector<CameraData*>& on) {
    neural::UNet& net = network_.state().net;
    std::vector<std::vector<cv::Mat>> images(on.size());
    torch::NoGradGuard no_grad;
    net->eval();
    for (size_t c = 0; c < on.size(); ++c) {
      CameraData& d = *on[c];
      for (int64_t f = 0; f < d.features.size(0); ++f) {
        if (what != Output::kNetwork) {
          images[c].push_back(what == Output::kRaw ? d.raw_images[f] : d.background_image);
          continue;
        }
        const torch::Tensor x = d.features.index({Slice(f, f + 1)});
        auto [rgb, alpha] = neural::DecodeRerender(net->forward(x), x);
        const torch::Tensor out = Composite(rgb, alpha, d.background).clamp(0, 1);
        images[c].push_back(
            neural::TensorToImage(out[0].index({Slice(), Slice(0, d.height), Slice(0, d.width)})));
      }
    }
    net->train();
    return std::make_pair(Score(images, on), images);
  }

  // The raw render and the background alone on the held-out cameras: what training must beat.
  void MeasureBaselines() {
    const Evaluation raw = Evaluate(Output::kRaw, eval_cameras_).first;
    const Evaluation background_only = Evaluate(Output::kBackground, eval_cameras_).first;
    if (!validation_cameras_.empty())
      summary_.validation_raw_psnr_db = Evaluate(Output::kRaw, validation_cameras_).first.psnr_db;
    summary_.background_psnr_db = background_only.psnr_db;
    summary_.background_psnr_subject_db = background_only.psnr_subject_db;
    summary_.background_ssim = background_only.ssim;
    summary_.raw_render_psnr_db = raw.psnr_db;
    summary_.raw_render_ssim = raw.ssim;
    summary_.raw_render_psnr_subject_db = raw.psnr_subject_db;
    summary_.raw_flicker_ratio = raw.flicker_ratio;
    summary_.raw_flicker_excess = raw.flicker_excess;
  }

  // Scores the validation and held-out cameras; saves the weights when validation improved.
  void EvaluateAndKeep(int64_t iteration) {
    bool keep = true;
    if (!validation_cameras_.empty()) {
      const double psnr = Evaluate(Output::kNetwork, validation_cameras_).first.psnr_db;
      if (report_) report_->AddPoint("validation_psnr_db", psnr, iteration);
      keep = psnr > best_validation_;
      if (keep) best_validation_ = psnr, summary_.kept_iteration = iteration;
    }
    if (!eval_cameras_.empty()) {
      auto [now, now_images] = Evaluate(Output::kNetwork, eval_cameras_);
      if (report_) {
        report_->AddPoint("heldout_psnr_db", now.psnr_db, iteration);
        report_->AddPoint("heldout_ssim", now.ssim, iteration);
      }
      if (keep) last_ = now, last_images_ = std::move(now_images);
    }
    if (keep) network_.Save(weights_file());
  }

  std::filesystem::path weights_file() const { return model_dir_ / "unet.pt"; }

  // A batch: pairs of consecutive frames of a witness camera, each pair cropped alike around a
  // pixel near the subject (whole images when crops are off). Returns the loss before the step.
  double TrainStep(torch::optim::Adam& optimizer, torch::nn::Sequential& discriminator,
                   torch::optim::Adam* d_optimizer) {
    neural::UNet& net = network_.state().net;
    std::vector<torch::Tensor> xs, truths, weights, backgrounds, alpha_targets;
    int64_t samples = 0;
    for (int p = 0; p < options_.batch_pairs; ++p) {
      const CameraData& d = *train_cameras_[std::uniform_int_distribution<size_t>(
          0, train_cameras_.size() - 1)(rng_)];
      const int64_t frames = d.features.size(0);
      const int64_t t = std::uniform_int_distribution<int64_t>(
          0, std::max<int64_t>(0, frames - (temporal_ ? 2 : 1)))(rng_);
      const int64_t count = temporal_ ? 2 : 1;
      int64_t x0 = 0, y0 = 0;
      if (options_.crop_px > 0) {
        const std::vector<int32_t>& near = d.subject_pixels[t];
        const int64_t pixel =
            near.empty()
                ? std::uniform_int_distribution<int64_t>(0, int64_t{d.width} * d.height - 1)(rng_)
                : near[std::uniform_int_distribution<size_t>(0, near.size() - 1)(rng_)];
        x0 = std::clamp<int64_t>(pixel % d.width - crop_w_ / 2, 0, d.features.size(3) - crop_w_);
        y0 = std::clamp<int64_t>(pixel / d.width - crop_h_ / 2, 0, d.features.size(2) - crop_h_);
      }
      const auto window = [&](const torch::Tensor& all, int64_t first, int64_t n) {
        return all.index(
            {Slice(first, first + n), Slice(), Slice(y0, y0 + crop_h_), Slice(x0, x0 + crop_w_)});
      };
      xs.push_back(window(d.features, t, count));
      truths.push_back(window(d.truth, t, count));
      weights.push_back(window(d.weight, t, count));
      backgrounds.push_back(window(d.background, 0, 1).expand({count, 3, crop_h_, crop_w_}));
      if (d.alpha_target.defined()) alpha_targets.push_back(window(d.alpha_target, t, count));
      samples += count;
    }
    const torch::Tensor x = torch::cat(xs), truth = torch::cat(truths),
                        weight = torch::cat(weights);
    const torch::Tensor background = torch::cat(backgrounds);
    const torch::Tensor raw_output = net->forward(x);
    auto [rgb, alpha] = neural::DecodeRerender(raw_output, x);
    const torch::Tensor out = Composite(rgb, alpha, background);
    torch::Tensor loss = options_.l1_weight * (weight * (out - truth).abs()).mean() / weight.mean();
    loss = loss + kRawOutputPenaltyWeight * neural::RawOutputPenalty(raw_output);
    if (options_.ssim_weight > 0)
      loss = loss + options_.ssim_weight * (1 - MultiScaleSsim(out, truth));
    if (alpha_targets.size() == xs.size()) {
      loss = loss + options_.alpha_weight *
                        (weight * (alpha - torch::cat(alpha_targets)).abs()).mean() / weight.mean();
    }
    if (temporal_) {
      const torch::Tensor even = torch::arange(0, samples, 2), odd = even + 1;
      const torch::Tensor change = out.index_select(0, odd) - out.index_select(0, even);
      const torch::Tensor truth_change = truth.index_select(0, odd) - truth.index_select(0, even);
      loss = loss + options_.temporal_weight * (change - truth_change).abs().mean();
    }
    if (discriminator) {
      torch::Tensor fake_score = discriminator->forward(out);
      loss = loss + options_.gan_weight * (fake_score - 1).pow(2).mean();
    }
    const double value = loss.item<double>();
    if (!std::isfinite(value)) return value;
    optimizer.zero_grad();
    loss.backward();
    optimizer.step();
    if (discriminator) {
      d_optimizer->zero_grad();
      const torch::Tensor d_loss = (discriminator->forward(truth) - 1).pow(2).mean() +
                                   discriminator->forward(out.detach()).pow(2).mean();
      d_loss.backward();
      d_optimizer->step();
    }
    return value;
  }

  void Train() {
    neural::UNet& net = network_.state().net;
    torch::optim::Adam optimizer(net->parameters(),
                                 torch::optim::AdamOptions(options_.learning_rate));
    torch::nn::Sequential discriminator{nullptr};
    std::unique_ptr<torch::optim::Adam> d_optimizer;
    if (options_.gan_weight > 0) {
      discriminator = PatchDiscriminator();
      d_optimizer = std::make_unique<torch::optim::Adam>(
          discriminator->parameters(),
          torch::optim::AdamOptions(options_.learning_rate).betas({0.5, 0.999}));
    }
    rng_.seed(options_.seed);
    const auto start = std::chrono::steady_clock::now();
    double next_eval = 0;
    Progress progress("rerender", options_.iterations > 0
                                      ? options_.iterations
                                      : static_cast<int64_t>(options_.minutes * 60));
    int64_t iteration = 0;
    for (;; ++iteration) {
      const double elapsed = Seconds(start);
      const bool done = (options_.iterations > 0 && iteration >= options_.iterations) ||
                        (options_.minutes > 0 && elapsed >= options_.minutes * 60);
      if ((!eval_cameras_.empty() || !validation_cameras_.empty()) &&
          (elapsed >= next_eval || done)) {
        EvaluateAndKeep(iteration);
        next_eval = elapsed + options_.eval_every_s;
      }
      if (done) break;
      // Cosine decay of the rate to a tenth over the budget: large steps first, then refinement
      // without their noise.
      const double spent = std::max(
          options_.minutes > 0 ? elapsed / (options_.minutes * 60) : 0.0,
          options_.iterations > 0 ? static_cast<double>(iteration) / options_.iterations : 0.0);
      static_cast<torch::optim::AdamOptions&>(optimizer.param_groups()[0].options())
          .lr(options_.learning_rate *
              (0.1 + 0.45 * (1 + std::cos(std::numbers::pi * std::min(spent, 1.0)))));
      const double value = TrainStep(optimizer, discriminator, d_optimizer.get());
      if (!std::isfinite(value)) {
        diverged_ = true;
        break;
      }
      losses_.push_back(value);
      if (report_ && iteration % 10 == 0) report_->AddPoint("loss", value, iteration);
      progress.Update(options_.iterations > 0 ? iteration : static_cast<int64_t>(elapsed),
                      Cat(last_.psnr_db, " dB"));
    }
    progress.Finish();
    summary_.iterations = iteration;
    summary_.seconds = Seconds(start);
  }

  // The weights on disk are those of the last evaluation before the loss broke down, or those
  // where the validation witnesses peaked; `last_` holds their held-out scores.
  void KeepWeights() {
    neural::LossEnds(losses_, &summary_.first_loss, &summary_.last_loss);
    summary_.validation_psnr_db = validation_cameras_.empty() ? 0 : best_validation_;
    if (diverged_ || !validation_cameras_.empty()) {
      network_ = RerenderNetwork::Load(weights_file(), options_.net);
    } else {
      network_.Save(weights_file());
    }
    summary_.heldout_psnr_db = last_.psnr_db;
    summary_.heldout_ssim = last_.ssim;
    summary_.heldout_psnr_subject_db = last_.psnr_subject_db;
    summary_.flicker_ratio = last_.flicker_ratio;
    summary_.flicker_excess = last_.flicker_excess;
  }

  // model.json, the cameras, and heldout.png (truth, raw render, rerendered, side by side).
  void WriteModel() {
    if (!eval_cameras_.empty() && !last_images_[0].empty()) {
      const size_t f = last_images_[0].size() / 2;
      cv::Mat strip, eight_bit;
      cv::hconcat(std::vector<cv::Mat>{eval_cameras_[0]->truth_images[f],
                                       eval_cameras_[0]->raw_images[f], last_images_[0][f]},
                  strip);
      strip.convertTo(eight_bit, CV_8UC3, 255);
      WritePng(model_dir_ / "heldout.png", eight_bit);
    }
    std::filesystem::create_directories(model_dir_ / "cameras");
    nlohmann::json model = {{"method", "rerender"},
                            {"net", options_.net.ToJson()},
                            {"cameras", nlohmann::json::array()},
                            {"meshes", nlohmann::json::array()},
                            {"image_width", options_.image_width},
                            {"supersample", options_.supersample},
                            {"box_min", {box_min_.x(), box_min_.y(), box_min_.z()}},
                            {"box_max", {box_max_.x(), box_max_.y(), box_max_.z()}},
                            {"frame_sets", sets_}};
    for (size_t i = 0; i < names_.size(); ++i) {
      cameras_[i].Write(model_dir_ / "cameras" / (names_[i] + ".cameramodel"));
      model["cameras"].push_back(names_[i]);
    }
    for (int64_t set : sets_) {
      const auto file = fold_meshes_[0][set];
      const auto relative = std::filesystem::relative(file, model_dir_);
      model["meshes"].push_back(!relative.empty() && *relative.begin() != ".."
                                    ? relative.string()
                                    : std::filesystem::absolute(file).string());
    }
    WriteFileAtomic(model_dir_ / "model.json", model.dump(2));
  }

  // FAILURE on a non-finite loss; DEGENERATE when the kept network shows the held-out cameras
  // no more of the subject than the background alone, or scores them no better than the raw
  // render (near the subject where both are measured), or the weights kept are the untrained
  // network's (validation peaked at iteration 0); CONVERGENCE when the validation
  // witnesses peaked before the budget ran out (those weights are kept); else NO_CONVERGENCE.
  void Summarise() {
    const int64_t iteration = summary_.iterations;
    const SubjectScores scores = ScoresNearSubject(summary_);
    if (diverged_) {
      summary_.End(Termination::kFailure, Cat("the loss became non-finite at iteration ", iteration,
                                              "; kept the weights of the last evaluation"));
    } else if (!eval_cameras_.empty() && scores.shows_none()) {
      // It erased the subject, or the raw render it started from shows no more: a better PSNR
      // than a poor raw render is no model of the subject.
      summary_.End(
          Termination::kDegenerate,
          Cat("the network's output shows the held-out cameras no more of the subject than the "
              "background alone: ",
              scores.near ? "near the subject"
                          : "over the whole image (the reconstruction draws nothing there)",
              " they score ", scores.shown, " dB, the background alone ", scores.background,
              " dB and the raw render ", scores.raw, " dB",
              scores.raw < scores.background - kErasedMarginDb
                  ? Cat(" (the reconstruction, built from ", recon_count_,
                        " colour cameras, renders worse than no subject at all: give it more "
                        "cameras or depth)")
                  : std::string()));
    } else if (!eval_cameras_.empty() &&
               (!(scores.shown > scores.raw) ||
                (!validation_cameras_.empty() && summary_.kept_iteration == 0))) {
      // Rerendering exists to repair the raw render: a network that leaves the held-out
      // cameras no better (or kept the untrained weights, the raw render itself) is no result.
      summary_.End(Termination::kDegenerate,
                   Cat("the network's output is no better than the raw render on the held-out "
                       "cameras: ",
                       scores.near ? "near the subject" : "over the whole image", " they score ",
                       scores.shown, " dB, the raw render ", scores.raw, " dB",
                       summary_.kept_iteration == 0 && !validation_cameras_.empty()
                           ? " (the validation witnesses peaked at iteration 0: the weights kept "
                             "are the untrained network's)"
                           : ""));
    } else {
      const bool peaked_early = !validation_cameras_.empty() && summary_.kept_iteration < iteration;
      summary_.End(peaked_early ? Termination::kConvergence : Termination::kNoConvergence,
                   eval_cameras_.empty()
                       ? Cat("trained ", iteration, " iterations in ", summary_.seconds,
                             " s; no held-out camera to measure on")
                       : Cat("trained ", iteration, " iterations in ", summary_.seconds,
                             " s (budget spent); held-out PSNR ", summary_.heldout_psnr_db,
                             " dB against the raw render's ", summary_.raw_render_psnr_db, " dB"));
    }
    if (!validation_cameras_.empty() && !diverged_) {
      summary_.message +=
          Cat("; kept the weights of iteration ", summary_.kept_iteration,
              ", where the validation witnesses peaked at ", summary_.validation_psnr_db,
              " dB (raw render ", summary_.validation_raw_psnr_db, " dB)");
    }
    if (report_) WriteReport();
  }

  void WriteReport() {
    report_->plan() = plan_;
    auto& m = report_->metrics();
    m["heldout_psnr_db"] = summary_.heldout_psnr_db;
    m["raw_render_psnr_db"] = summary_.raw_render_psnr_db;
    m["background_psnr_db"] = summary_.background_psnr_db;
    m["background_psnr_subject_db"] = summary_.background_psnr_subject_db;
    m["background_ssim"] = summary_.background_ssim;
    m["heldout_ssim"] = summary_.heldout_ssim;
    m["raw_render_ssim"] = summary_.raw_render_ssim;
    m["heldout_psnr_subject_db"] = summary_.heldout_psnr_subject_db;
    m["raw_render_psnr_subject_db"] = summary_.raw_render_psnr_subject_db;
    m["flicker_ratio"] = summary_.flicker_ratio;
    m["raw_flicker_ratio"] = summary_.raw_flicker_ratio;
    m["flicker_excess"] = summary_.flicker_excess;
    m["raw_flicker_excess"] = summary_.raw_flicker_excess;
    if (!validation_cameras_.empty()) {
      m["validation_psnr_db"] = summary_.validation_psnr_db;
      m["validation_raw_psnr_db"] = summary_.validation_raw_psnr_db;
      m["kept_iteration"] = summary_.kept_iteration;
    }
    m["iterations"] = summary_.iterations;
    m["seconds"] = summary_.seconds;
    m["first_loss"] = summary_.first_loss;
    m["last_loss"] = summary_.last_loss;
    report_->SetSummary(summary_);
    report_->Write(model_dir_ / "report.json");
  }

  const Take take_;
  const std::filesystem::path model_dir_;
  const RerenderOptions& options_;
  Report* report_;
  RerenderSummary summary_;
  nlohmann::json& plan_;
  TakePlan take_plan_;
  // The colour cameras, and the split (indices into names_).
  std::vector<std::string> names_;
  std::vector<CameraModel> cameras_;
  Eigen::Vector3d center_ = Eigen::Vector3d::Zero();
  std::vector<int> heldout_, rest_;
  std::vector<std::vector<int>> folds_;
  std::vector<std::string> witness_names_;
  int validation_count_ = 0;
  int recon_count_ = 0;
  // Reconstructions and frames.
  std::vector<std::map<int64_t, std::filesystem::path>> fold_meshes_;
  std::map<int64_t, size_t> entry_of_set_;
  std::vector<int64_t> sets_;
  // Data.
  std::set<std::string> validation_names_;
  int threads_ = 1;
  int multiple_ = 1;
  std::vector<CameraData> data_;
  std::vector<CameraData*> train_cameras_, eval_cameras_, validation_cameras_;
  Eigen::Vector3d box_min_ = Eigen::Vector3d::Constant(1e30),
                  box_max_ = Eigen::Vector3d::Constant(-1e30);
  bool temporal_ = false;
  int64_t crop_w_ = 0, crop_h_ = 0;
  // Training.
  RerenderNetwork network_;
  std::mt19937_64 rng_;
  double best_validation_ = -std::numeric_limits<double>::infinity();
  Evaluation last_;
  std::vector<std::vector<cv::Mat>> last_images_;
  std::vector<double> losses_;
  bool diverged_ = false;
};

}  // namespace

RerenderSummary TrainRerender(const std::filesystem::path& take_dir,
                              const std::filesystem::path& model_dir,
                              const RerenderOptions& options, Report* report) {
  options.Check();
  return RerenderTrainer(take_dir, model_dir, options, report).Run();
}

}  // namespace holocap
