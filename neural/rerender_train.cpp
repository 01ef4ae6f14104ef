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

#include "core/error.h"
#include "core/fs.h"
#include "core/image.h"
#include "core/progress.h"
#include "core/take.h"
#include "neural/data.h"
#include "neural/rerender_net.h"
#include "reconstruction/projector.h"

namespace holocap {

namespace {

using torch::indexing::Slice;

double Seconds(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - since).count();
}

// A copy of the take's manifest in which the named cameras are witnesses (reconstruction uses
// colour and depth sensors only); frames, index, calibration and ground truth are linked.
void WriteWitnessView(const Take& take, const std::set<std::string>& witnesses, const std::filesystem::path& dir) {
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  nlohmann::json manifest = nlohmann::json::parse(ReadFileToString(take.dir() / "take.json"));
  auto mark = [&](nlohmann::json& list) {
    for (auto& sensor : list) {
      if (sensor.contains("name") && witnesses.count(sensor["name"].get<std::string>())) sensor["role"] = "witness";
    }
  };
  if (manifest.contains("streams")) mark(manifest["streams"]);
  if (manifest.contains("rig") && manifest["rig"].contains("sensors")) mark(manifest["rig"]["sensors"]);
  WriteFileAtomic(dir / "take.json", manifest.dump(2));
  const std::string index = manifest.value("index", std::string("index.jsonl"));
  for (const std::string& entry : {std::string("frames"), std::string("calib"), std::string("gt"), index}) {
    const auto target = std::filesystem::absolute(take.dir() / entry);
    if (std::filesystem::exists(target)) std::filesystem::create_symlink(target, dir / entry);
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
  auto lrelu = [] { return torch::nn::LeakyReLU(torch::nn::LeakyReLUOptions().negative_slope(0.2)); };
  return torch::nn::Sequential(torch::nn::Conv2d(torch::nn::Conv2dOptions(3, 32, 4).stride(2).padding(1)), lrelu(),
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
  bool shows_none() const { return std::isfinite(shown) && std::isfinite(background) && shown <= background + kErasedMarginDb; }
};
SubjectScores ScoresNearSubject(const RerenderSummary& s) {
  SubjectScores scores;
  scores.near = std::isfinite(s.heldout_psnr_subject_db) && std::isfinite(s.background_psnr_subject_db);
  scores.shown = scores.near ? s.heldout_psnr_subject_db : s.heldout_psnr_db;
  scores.background = scores.near ? s.background_psnr_subject_db : s.background_psnr_db;
  scores.raw = scores.near ? s.raw_render_psnr_subject_db : s.raw_render_psnr_db;
  return scores;
}

// One camera at the training resolution, over every frame.
struct CameraData {
  std::string name;
  CameraModel camera;             // native
  CameraModel scaled;             // training resolution
  torch::Tensor features;         // [F, 8, Hp, Wp] padded
  torch::Tensor truth;            // [F, 3, Hp, Wp] BGR in [0, 1]
  torch::Tensor background;       // [1, 3, Hp, Wp]
  torch::Tensor weight;           // [F, 1, Hp, Wp] loss weights (subject favoured)
  torch::Tensor alpha_target;     // [F, 1, Hp, Wp] the camera's own silhouette (witnesses), or
                                  // undefined without one
  std::vector<cv::Mat> truth_images, raw_images, subject_masks;  // unpadded
  cv::Mat background_image;                                       // unpadded
  std::vector<std::vector<int32_t>> subject_pixels;  // per frame, y * width + x near the subject
  int height = 0, width = 0;
  bool witness = false;           // trained on (else held out for measurement)
};

cv::Mat ToFloatImage(const cv::Mat& image, const cv::Size& size) {
  cv::Mat color = image;
  if (color.channels() == 1) cv::cvtColor(color, color, cv::COLOR_GRAY2BGR);
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
torch::Tensor Composite(const torch::Tensor& rgb, const torch::Tensor& alpha, const torch::Tensor& background) {
  return rgb * alpha + background * (1 - alpha);
}

struct Evaluation {
  double psnr_db = 0, ssim = 0, psnr_subject_db = 0;
  double flicker_ratio = 0, flicker_excess = 0;
};

// Mean |frame-to-frame change| relative to the truth's, and mean |change - truth's change|.
void Flicker(const std::vector<cv::Mat>& images, const std::vector<cv::Mat>& truth, Evaluation* evaluation) {
  double change = 0, truth_change = 0, excess = 0;
  for (size_t f = 1; f < images.size(); ++f) {
    const cv::Mat d = images[f] - images[f - 1], t = truth[f] - truth[f - 1];
    change += cv::norm(d, cv::NORM_L1);
    truth_change += cv::norm(t, cv::NORM_L1);
    excess += cv::norm(d - t, cv::NORM_L1);
  }
  const double pixels = images.empty() ? 1.0 : static_cast<double>(images[0].total() * 3 * std::max<size_t>(1, images.size() - 1));
  evaluation->flicker_ratio = truth_change > 0 ? change / truth_change : std::numeric_limits<double>::quiet_NaN();
  evaluation->flicker_excess = excess / pixels;
}

Evaluation Score(const std::vector<std::vector<cv::Mat>>& images, const std::vector<CameraData*>& cameras) {
  Evaluation e;
  double mse = 0, mse_subject = 0;
  int64_t count = 0, count_subject = 0, views = 0;
  for (size_t c = 0; c < cameras.size(); ++c) {
    for (size_t f = 0; f < images[c].size(); ++f) {
      cv::Mat diff = images[c][f] - cameras[c]->truth_images[f];
      diff = diff.mul(diff);
      mse += cv::sum(diff).dot(cv::Scalar::all(1));
      count += static_cast<int64_t>(diff.total()) * 3;
      mse_subject += cv::sum(diff.setTo(0, cameras[c]->subject_masks[f] == 0)).dot(cv::Scalar::all(1));
      count_subject += cv::countNonZero(cameras[c]->subject_masks[f]) * 3;
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
  if (witness_cameras < 1 && witness.empty()) Fail("rerender needs at least one witness camera");
  if (heldout_cameras < 0) Fail("heldout_cameras must be >= 0");
  if (validation_witnesses < -1) Fail("validation_witnesses must be >= 0 (or -1: automatic)");
  RasterOptions{.supersample = supersample}.Check();
  if (witness_scales.empty()) Fail("witness_scales cannot be empty (1: the training width only)");
  for (double s : witness_scales) {
    if (!(s >= 0.25 && s <= 2)) Fail("witness scales must be in [0.25, 2] (got ", s, ")");
  }
  if (std::find(witness_scales.begin(), witness_scales.end(), 1.0) == witness_scales.end()) {
    Fail("witness_scales must include 1 (the training width, where validation and held-out cameras are scored)");
  }
  if (witness_folds < 1 || witness_folds > 16) Fail("witness_folds must be in [1, 16] (got ", witness_folds, ")");
  for (const auto& fold : fold_witness) if (fold.empty()) Fail("a fold of witnesses cannot be empty");
  if (fold_witness.empty() && fold_recon_dirs.size() > static_cast<size_t>(witness_folds - 1)) {
    Fail(fold_recon_dirs.size(), " fold reconstructions given for ", witness_folds - 1, " further fold(s)");
  }
  if (image_width < 0 || (image_width > 0 && image_width < 32)) Fail("image_width must be 0 (native) or >= 32 px (got ", image_width, ")");
  if (first_frame < 0) Fail("first_frame must be >= 0");
  if (last_frame >= 0 && last_frame <= first_frame) Fail("last_frame must be -1 or > first_frame");
  if (!(minutes > 0) && iterations <= 0) Fail("give a positive time budget (minutes) or an iteration count");
  if (iterations < 0) Fail("iterations must be >= 0");
  if (batch_pairs < 1 || batch_pairs > 64) Fail("batch_pairs must be in [1, 64] (got ", batch_pairs, ")");
  if (crop_px < 0 || (crop_px > 0 && crop_px < 16)) Fail("crop_px must be 0 (whole images) or >= 16 (got ", crop_px, ")");
  if (!(learning_rate > 0 && learning_rate < 1)) Fail("learning_rate must be in (0, 1) (got ", learning_rate, ")");
  for (double w : {l1_weight, ssim_weight, temporal_weight, gan_weight}) {
    if (!(w >= 0 && std::isfinite(w))) Fail("loss weights must be finite and >= 0");
  }
  if (!(l1_weight + ssim_weight > 0)) Fail("l1_weight and ssim_weight cannot both be 0");
  if (!(subject_weight >= 1 && subject_weight <= 100)) Fail("subject_weight must be in [1, 100] (got ", subject_weight, ")");
  if (!(alpha_weight >= 0 && alpha_weight <= 100)) Fail("alpha_weight must be in [0, 100] (got ", alpha_weight, ")");
  if (!(eval_every_s > 0)) Fail("eval_every_s must be > 0");
  if (threads < 0) Fail("threads must be >= 0 (0: all cores)");
  reconstruction.Check();
}

nlohmann::json RerenderOptions::ToJson() const {
  return {{"net", net.ToJson()}, {"witness_cameras", witness_cameras}, {"heldout_cameras", heldout_cameras},
          {"witness", witness}, {"heldout", heldout}, {"ground_truth_cameras", ground_truth_cameras},
          {"recon_dir", recon_dir.string()}, {"witness_folds", witness_folds}, {"validation_witnesses", validation_witnesses}, {"fold_witness", fold_witness},
          {"fold_recon_dirs", [&] { std::vector<std::string> d; for (const auto& p : fold_recon_dirs) d.push_back(p.string()); return d; }()},
          {"reconstruction", reconstruction.ToJson()},
          {"image_width", image_width}, {"supersample", supersample}, {"witness_scales", witness_scales}, {"first_frame", first_frame}, {"last_frame", last_frame},
          {"minutes", minutes}, {"iterations", iterations}, {"batch_pairs", batch_pairs},
          {"crop_px", crop_px},           {"learning_rate", learning_rate}, {"l1_weight", l1_weight}, {"ssim_weight", ssim_weight},
          {"subject_weight", subject_weight}, {"alpha_weight", alpha_weight}, {"temporal_weight", temporal_weight}, {"gan_weight", gan_weight},
          {"seed", seed}, {"eval_every_s", eval_every_s}, {"threads", threads}};
}

RerenderSummary TrainRerender(const std::filesystem::path& take_dir, const std::filesystem::path& model_dir,
                              const RerenderOptions& options, Report* report) {
  options.Check();
  const Take take = Take::Open(take_dir);
  RerenderSummary summary;
  nlohmann::json& plan = summary.plan;

  // Cameras and the three-way split.
  const bool ground_truth = options.ground_truth_cameras || !take.has_calibration();
  if (ground_truth && !std::filesystem::is_directory(take.gt_dir() / "cameras")) {
    Fail("take '", take_dir.string(), "' is not calibrated (no calib/ for every sensor, no gt/cameras)");
  }
  std::vector<std::string> names;
  std::set<std::string> paired;
  for (const auto& s : take.streams()) {
    if (s.role == SensorRole::kColor) names.push_back(s.name);
    if (!s.paired_with.empty()) paired.insert(s.paired_with);
  }
  std::vector<CameraModel> cameras;
  for (const auto& n : names) cameras.push_back(take.Camera(n, ground_truth));
  auto by_name = [&](const std::vector<std::string>& wanted, const char* what) {
    std::vector<int> out;
    for (const auto& w : wanted) {
      auto it = std::find(names.begin(), names.end(), w);
      if (it == names.end()) Fail("the ", what, " camera '", w, "' is not a colour camera of the take");
      out.push_back(static_cast<int>(it - names.begin()));
    }
    return out;
  };
  Eigen::Vector3d center = Eigen::Vector3d::Zero();
  for (const auto& c : cameras) center += c.center_in_world() / static_cast<double>(cameras.size());
  // Cameras that colour the depth sensors' fusion stay with the reconstruction when possible.
  std::vector<int> candidates, fallback;
  for (int i = 0; i < static_cast<int>(names.size()); ++i) (paired.count(names[i]) ? fallback : candidates).push_back(i);
  const int wanted_out = (options.heldout.empty() ? options.heldout_cameras : static_cast<int>(options.heldout.size())) +
                         (options.witness.empty() ? options.witness_cameras : static_cast<int>(options.witness.size()));
  if (static_cast<int>(candidates.size()) < wanted_out) candidates.insert(candidates.end(), fallback.begin(), fallback.end());
  std::vector<int> heldout = options.heldout.empty()
      ? neural::SpreadAround(cameras, candidates, options.heldout_cameras, center) : by_name(options.heldout, "held-out");
  std::vector<int> rest;
  for (int c : candidates) if (std::find(heldout.begin(), heldout.end(), c) == heldout.end()) rest.push_back(c);
  std::vector<int> witness = options.witness.empty() ? neural::SpreadAround(cameras, rest, options.witness_cameras, center)
                                                     : by_name(options.witness, "witness");
  for (int w : witness) {
    if (std::find(heldout.begin(), heldout.end(), w) != heldout.end()) Fail("camera '", names[w], "' cannot be both witness and held out");
  }
  const int recon_count = static_cast<int>(names.size() - witness.size() - heldout.size());
  if (witness.empty() || recon_count < 2) {
    Fail("take '", take_dir.string(), "' has ", names.size(), " colour cameras: ", witness.size(), " witness and ",
         heldout.size(), " held-out ones leave ", recon_count, " for the reconstruction (it needs 2)");
  }
  // Further folds: other witness sets, each with its own reconstruction.
  std::vector<std::vector<int>> folds = {witness};
  auto is_witness_yet = [&](int c) {
    for (const auto& f : folds) if (std::find(f.begin(), f.end(), c) != f.end()) return true;
    return false;
  };
  if (!options.fold_witness.empty()) {
    for (const auto& named : options.fold_witness) {
      std::vector<int> fold = by_name(named, "witness");
      for (int c : fold) {
        if (std::find(heldout.begin(), heldout.end(), c) != heldout.end()) Fail("camera '", names[c], "' cannot be both witness and held out");
        if (is_witness_yet(c)) Fail("camera '", names[c], "' is a witness of two folds");
      }
      folds.push_back(fold);
    }
  } else {
    for (int k = 1; k < options.witness_folds; ++k) {
      std::vector<int> pool;
      for (int c : rest) if (!is_witness_yet(c)) pool.push_back(c);
      if (pool.empty()) break;
      folds.push_back(neural::SpreadAround(cameras, pool, std::min<int>(static_cast<int>(witness.size()), static_cast<int>(pool.size())), center));
    }
  }
  for (const auto& fold : folds) {
    const int left = static_cast<int>(names.size() - fold.size() - heldout.size());
    if (fold.empty() || left < 2) Fail("a fold of ", fold.size(), " witnesses leaves ", left, " cameras for its reconstruction (it needs 2)");
  }
  if (options.fold_recon_dirs.size() > folds.size() - 1) {
    Fail(options.fold_recon_dirs.size(), " fold reconstructions given for ", folds.size() - 1, " further fold(s)");
  }
  std::vector<std::string> witness_names, heldout_names;
  for (const auto& fold : folds) for (int w : fold) witness_names.push_back(names[w]);
  for (int h : heldout) heldout_names.push_back(names[h]);
  const int validation_count = options.validation_witnesses >= 0 ? options.validation_witnesses
                               : witness_names.size() >= 3 ? std::max(1, static_cast<int>(witness_names.size()) / 5) : 0;
  if (validation_count >= static_cast<int>(witness_names.size())) {
    Fail(validation_count, " validation witness(es) leave no witness to train on (", witness_names.size(),
         " in all): ask for more witnesses or folds");
  }
  plan["cameras"] = ground_truth ? "gt/cameras" : "calib/";
  plan["witness"] = witness_names;
  plan["heldout"] = heldout_names;
  plan["reconstruction_cameras"] = recon_count;

  // The reconstructions, each from the cameras that are neither its fold's witnesses nor held out.
  std::filesystem::create_directories(model_dir);
  const auto start_all = std::chrono::steady_clock::now();
  auto reconstruct = [&](size_t k, nlohmann::json& fold_plan) {
    std::set<std::string> left_out;
    for (int w : folds[k]) left_out.insert(names[w]);
    for (int h : heldout) left_out.insert(names[h]);
    std::filesystem::path recon_dir = k == 0 ? options.recon_dir
                                      : k - 1 < options.fold_recon_dirs.size() ? options.fold_recon_dirs[k - 1]
                                                                               : std::filesystem::path();
    std::map<int64_t, std::filesystem::path> meshes;
    const auto start_fold = std::chrono::steady_clock::now();
    if (recon_dir.empty()) {
      recon_dir = k == 0 ? model_dir / "recon" : model_dir / Cat("recon-", k);
      const std::filesystem::path view = model_dir / "witness_take";
      WriteWitnessView(take, left_out, view);
      ReconstructionOptions recon = options.reconstruction;
      recon.first_frame = options.first_frame;
      recon.last_frame = options.last_frame;
      recon.write_glb = false;
      recon.sweep_voxels_m.clear();
      recon.threads = options.threads;
      Report recon_report("reconstruct");
      ReconstructionSummary built = ReconstructTake(view, recon_dir, recon, &recon_report);
      for (const auto& f : built.frames) {
        char file[32];
        std::snprintf(file, sizeof(file), "%06lld.ply", static_cast<long long>(f.set));
        if (IsUsable(f.termination) && f.faces > 0) meshes[f.set] = recon_dir / file;
      }
      fold_plan["reconstruction"] = Cat(ToString(built.termination), ": ", built.message);
      std::filesystem::remove_all(view);
    } else {
      if (!std::filesystem::is_directory(recon_dir)) Fail("reconstruction directory ", recon_dir.string(), " does not exist");
      // A reconstruction that saw a witness or a held-out camera would score the network on
      // views it was coloured from: refused when its report names the cameras it used.
      const std::filesystem::path built_report = recon_dir / "report.json";
      std::string cameras_used = "cameras not recorded";
      if (std::filesystem::exists(built_report)) {
        nlohmann::json built;
        try {
          built = nlohmann::json::parse(std::ifstream(built_report));
        } catch (const std::exception& e) {
          Fail("reconstruction report ", built_report.string(), " is unreadable: ", e.what());
        }
        const nlohmann::json used = built.contains("plan") ? built["plan"].value("color_sensors", nlohmann::json()) : nlohmann::json();
        if (used.is_array()) {
          for (const auto& name : used) {
            const std::string camera = name.get<std::string>();
            if (!left_out.count(camera)) continue;
            const bool is_heldout = std::any_of(heldout.begin(), heldout.end(), [&](int h) { return names[h] == camera; });
            Fail("reconstruction ", recon_dir.string(), " was built with camera '", camera, "', ",
                 is_heldout ? "held out" : "a witness of its fold", ": build it without that camera");
          }
          cameras_used = Cat(used.size(), " colour cameras, none of this fold's witnesses or held-out");
        }
      }
      for (const auto& entry : std::filesystem::directory_iterator(recon_dir)) {
        if (entry.path().extension() != ".ply") continue;
        try {
          meshes[std::stoll(entry.path().stem().string())] = entry.path();
        } catch (const std::exception&) {
        }
      }
      fold_plan["reconstruction"] = Cat("given: ", recon_dir.string(), " (", cameras_used, ")");
    }
    fold_plan["reconstruction_seconds"] = Seconds(start_fold);
    return meshes;
  };
  std::vector<std::map<int64_t, std::filesystem::path>> fold_meshes;
  nlohmann::json fold_plans = nlohmann::json::array();
  for (size_t k = 0; k < folds.size(); ++k) {
    nlohmann::json fold_plan;
    std::vector<std::string> fold_names;
    for (int w : folds[k]) fold_names.push_back(names[w]);
    fold_plan["witness"] = fold_names;
    fold_plan["reconstruction_cameras"] = static_cast<int>(names.size() - folds[k].size() - heldout.size());
    fold_meshes.push_back(reconstruct(k, fold_plan));
    if (k == 0) plan["reconstruction"] = fold_plan["reconstruction"];
    fold_plans.push_back(fold_plan);
  }
  std::map<int64_t, std::filesystem::path>& meshes = fold_meshes[0];
  if (folds.size() > 1) plan["folds"] = fold_plans;
  if (options.fold_witness.empty() && static_cast<int>(folds.size()) < options.witness_folds) {
    plan["witness_folds"] = Cat(options.witness_folds, " asked, ", folds.size(),
                                " possible: every other camera is a witness, held out or colours a depth sensor");
  }
  plan["reconstruction_seconds"] = Seconds(start_all);
  std::map<int64_t, size_t> entry_of_set;
  for (size_t i = 0; i < take.size(); ++i) entry_of_set[take.entry(i).index] = i;
  std::vector<int64_t> sets;
  for (const auto& [set, file] : meshes) {
    bool everywhere = entry_of_set.count(set) > 0;
    for (const auto& other : fold_meshes) everywhere = everywhere && other.count(set) > 0;
    if (everywhere) sets.push_back(set);
  }
  plan["frames"] = sets.size();
  if (sets.empty()) {
    summary.termination = Termination::kDegenerate;
    summary.message = "the reconstruction gave no mesh to rerender";
    if (report) {
      report->plan() = plan;
      report->SetSummary({summary.termination, summary.message});
      report->Write(model_dir / "report.json");
    }
    return summary;
  }

  // Data at the training resolution (and, for the witnesses, at the further scales asked for).
  const std::set<std::string> validation_names(witness_names.end() - validation_count, witness_names.end());
  const int threads = recon::ResolveThreads(options.threads);
  torch::set_num_threads(threads);
  const int64_t clean_plates = take.metadata().value("clean_plate_frames", int64_t{0});
  const int multiple = 1 << options.net.depth;
  std::vector<CameraData> data;
  Eigen::Vector3d box_min = Eigen::Vector3d::Constant(1e30), box_max = Eigen::Vector3d::Constant(-1e30);
  auto load_camera = [&](int index, const std::vector<Mesh>& mesh_cache, bool is_witness, double extra_scale) {
    CameraData d;
    d.name = names[index];
    d.witness = is_witness;
    d.camera = cameras[index];
    const double scale = (options.image_width > 0 ? static_cast<double>(options.image_width) / d.camera.width() : 1.0) * extra_scale;
    d.scaled = scale == 1.0 ? d.camera : d.camera.Scaled(scale);
    d.width = d.scaled.width();
    d.height = d.scaled.height();
    const cv::Size size(d.width, d.height);
    cv::Mat background = clean_plates > 0 ? ToFloatImage(take.ReadFrame(0, d.name), size)
                                          : cv::Mat(size, CV_32FC3, cv::Scalar::all(0));
    d.background = neural::PadToMultiple(neural::ImageToTensor(background).unsqueeze(0), multiple);
    d.background_image = background;
    const bool silhouettes = is_witness && options.alpha_weight > 0 &&
                             (options.reconstruction.silhouette.mode == SilhouetteMode::kThreshold || clean_plates > 0);
    cv::Mat plate;
    if (silhouettes && clean_plates > 0) plate = ToEightBitColor(take.ReadFrame(0, d.name));
    std::vector<torch::Tensor> features, truth, weight, alpha_target;
    const int dilate = std::max(2, d.width / 40);
    const cv::Mat kernel = cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * dilate + 1, 2 * dilate + 1));
    for (size_t f = 0; f < sets.size(); ++f) {
      GBuffer buffers = RasteriseMesh(mesh_cache[f], d.scaled, RasterOptions{.supersample = options.supersample, .threads = threads});
      const cv::Mat native = take.ReadFrame(entry_of_set[sets[f]], d.name);
      cv::Mat image = ToFloatImage(native, size);
      if (silhouettes) {
        // The witness's silhouette at the training resolution (area-averaged: soft edges).
        cv::Mat mask = ExtractSilhouette(ToEightBitColor(native), plate, options.reconstruction.silhouette), soft;
        mask.convertTo(mask, CV_32F, 1.0 / 255);
        cv::resize(mask, soft, size, 0, 0, cv::INTER_AREA);
        alpha_target.push_back(neural::ImageToTensor(soft));
      }
      cv::Mat subject;
      cv::dilate(buffers.mask, subject, kernel);
      features.push_back(neural::RerenderFeatures(buffers));
      truth.push_back(neural::ImageToTensor(image));
      cv::Mat w;
      subject.convertTo(w, CV_32F, (options.subject_weight - 1) / 255.0, 1.0);
      weight.push_back(neural::ImageToTensor(w));
      d.truth_images.push_back(image);
      d.raw_images.push_back(CompositeRawRender(buffers, background));
      d.subject_masks.push_back(subject);
      std::vector<cv::Point> near;
      cv::findNonZero(subject, near);
      d.subject_pixels.emplace_back();
      for (const cv::Point& p : near) d.subject_pixels.back().push_back(p.y * d.width + p.x);
    }
    d.features = neural::PadToMultiple(torch::stack(features), multiple);
    d.truth = neural::PadToMultiple(torch::stack(truth), multiple);
    d.weight = neural::PadToMultiple(torch::stack(weight), multiple);
    if (!alpha_target.empty()) d.alpha_target = neural::PadToMultiple(torch::stack(alpha_target), multiple);
    data.push_back(std::move(d));
  };
  for (size_t k = 0; k < folds.size(); ++k) {
    // One fold's meshes in memory at a time.
    std::vector<Mesh> mesh_cache;
    for (int64_t set : sets) mesh_cache.push_back(ReadPly(fold_meshes[k][set]));
    if (k == 0) {
      for (const Mesh& m : mesh_cache) {
        for (const auto& v : m.vertices) box_min = box_min.cwiseMin(v.cast<double>()), box_max = box_max.cwiseMax(v.cast<double>());
      }
      for (int h : heldout) load_camera(h, mesh_cache, false, 1.0);
    }
    for (int w : folds[k]) {
      load_camera(w, mesh_cache, true, 1.0);
      // Validation witnesses are scored at the training width only; the others train at every
      // scale asked for.
      if (validation_names.count(names[w])) continue;
      for (double s : options.witness_scales) if (s != 1.0) load_camera(w, mesh_cache, true, s);
    }
  }
  // Validation witnesses: the last ones (the last fold's), at the training width.
  std::vector<CameraData*> train_cameras, eval_cameras, validation_cameras;
  for (CameraData& d : data) {
    if (!d.witness) eval_cameras.push_back(&d);
    else if (validation_names.count(d.name)) validation_cameras.push_back(&d);
    else train_cameras.push_back(&d);
  }
  if (!validation_cameras.empty()) {
    std::vector<std::string> validation_list;
    for (const CameraData* d : validation_cameras) validation_list.push_back(d->name);
    plan["validation"] = validation_list;
  }
  const bool temporal = sets.size() >= 2 && options.temporal_weight > 0;
  plan["temporal_term"] = temporal ? "on" : (sets.size() < 2 ? "off: one frame" : "off: weight 0");
  plan["patch_gan"] = options.gan_weight > 0 ? "on" : "off";
  plan["alpha_target"] = options.alpha_weight <= 0 ? std::string("off: weight 0")
                         : train_cameras[0]->alpha_target.defined()
                             ? std::string("the witnesses' silhouettes")
                             : std::string("off: background subtraction without a clean plate");
  if (options.witness_scales.size() > 1 || options.witness_scales[0] != 1.0) plan["witness_scales"] = options.witness_scales;
  plan["trained_views"] = train_cameras.size();  // witness cameras trained on, once per scale
  plan["train_resolution"] = Cat(train_cameras[0]->width, "x", train_cameras[0]->height, " (", train_cameras[0]->name, ")");
  plan["raster_samples"] = options.supersample == 1
      ? std::string("1 per pixel (its centre)")
      : Cat(options.supersample, "x", options.supersample, " per pixel, averaged (the raw render too)");
  // Crops share one size across the witnesses: the requested one rounded up to the network's
  // multiple, at most the smallest padded image.
  int64_t crop_w = std::numeric_limits<int64_t>::max(), crop_h = crop_w;
  for (const CameraData* d : train_cameras) {
    crop_w = std::min(crop_w, d->features.size(3));
    crop_h = std::min(crop_h, d->features.size(2));
  }
  if (options.crop_px > 0) {
    const int64_t crop = (options.crop_px + multiple - 1) / multiple * multiple;
    crop_w = std::min(crop_w, crop);
    crop_h = std::min(crop_h, crop);
  }
  plan["train_crop"] = options.crop_px > 0 ? Cat(crop_w, "x", crop_h, " near the subject") : std::string("whole images");

  RerenderNetwork network(options.net, options.seed);
  neural::UNet& net = network.state().net;
  plan["parameters"] = network.parameter_count();
  torch::optim::Adam optimizer(net->parameters(), torch::optim::AdamOptions(options.learning_rate));
  torch::nn::Sequential discriminator{nullptr};
  std::unique_ptr<torch::optim::Adam> d_optimizer;
  if (options.gan_weight > 0) {
    discriminator = PatchDiscriminator();
    d_optimizer = std::make_unique<torch::optim::Adam>(discriminator->parameters(), torch::optim::AdamOptions(options.learning_rate).betas({0.5, 0.999}));
  }

  enum class Output { kNetwork, kRaw, kBackground };
  auto evaluate = [&](Output what, const std::vector<CameraData*>& on) {
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
        images[c].push_back(neural::TensorToImage(out[0].index({Slice(), Slice(0, d.height), Slice(0, d.width)})));
      }
    }
    net->train();
    return std::make_pair(Score(images, on), images);
  };

  if (report) {
    report->options() = options.ToJson();
    report->plan() = plan;
  }
  const Evaluation raw = evaluate(Output::kRaw, eval_cameras).first;
  const Evaluation background_only = evaluate(Output::kBackground, eval_cameras).first;
  if (!validation_cameras.empty()) summary.validation_raw_psnr_db = evaluate(Output::kRaw, validation_cameras).first.psnr_db;
  double best_validation = -std::numeric_limits<double>::infinity();
  summary.background_psnr_db = background_only.psnr_db;
  summary.background_psnr_subject_db = background_only.psnr_subject_db;
  summary.background_ssim = background_only.ssim;
  summary.raw_render_psnr_db = raw.psnr_db;
  summary.raw_render_ssim = raw.ssim;
  summary.raw_render_psnr_subject_db = raw.psnr_subject_db;
  summary.raw_flicker_ratio = raw.flicker_ratio;
  summary.raw_flicker_excess = raw.flicker_excess;

  std::mt19937_64 rng(options.seed);
  const auto start = std::chrono::steady_clock::now();
  double next_eval = 0;
  Evaluation last;
  std::vector<std::vector<cv::Mat>> last_images;
  std::vector<double> losses;
  Progress progress("rerender", options.iterations > 0 ? options.iterations : static_cast<int64_t>(options.minutes * 60));
  const std::filesystem::path weights = model_dir / "unet.pt";
  bool diverged = false;
  int64_t iteration = 0;
  for (;; ++iteration) {
    const double elapsed = Seconds(start);
    const bool done = (options.iterations > 0 && iteration >= options.iterations) ||
                      (options.minutes > 0 && elapsed >= options.minutes * 60);
    if ((!eval_cameras.empty() || !validation_cameras.empty()) && (elapsed >= next_eval || done)) {
      bool keep = true;
      if (!validation_cameras.empty()) {
        const double psnr = evaluate(Output::kNetwork, validation_cameras).first.psnr_db;
        if (report) report->AddPoint("validation_psnr_db", psnr, iteration);
        keep = psnr > best_validation;
        if (keep) best_validation = psnr, summary.kept_iteration = iteration;
      }
      if (!eval_cameras.empty()) {
        Evaluation now;
        std::vector<std::vector<cv::Mat>> now_images;
        std::tie(now, now_images) = evaluate(Output::kNetwork, eval_cameras);
        if (report) {
          report->AddPoint("heldout_psnr_db", now.psnr_db, iteration);
          report->AddPoint("heldout_ssim", now.ssim, iteration);
        }
        if (keep) last = now, last_images = std::move(now_images);
      }
      if (keep) network.Save(weights);
      next_eval = elapsed + options.eval_every_s;
    }
    if (done) break;
    // Cosine decay of the rate to a tenth over the budget: large steps first, then refinement
    // without their noise.
    const double spent = std::max(options.minutes > 0 ? elapsed / (options.minutes * 60) : 0.0,
                                  options.iterations > 0 ? static_cast<double>(iteration) / options.iterations : 0.0);
    static_cast<torch::optim::AdamOptions&>(optimizer.param_groups()[0].options())
        .lr(options.learning_rate * (0.1 + 0.45 * (1 + std::cos(std::numbers::pi * std::min(spent, 1.0)))));

    // A batch: pairs of consecutive frames of a witness camera, each pair cropped alike around
    // a pixel near the subject (whole images when crops are off).
    std::vector<torch::Tensor> xs, truths, weights, backgrounds, alpha_targets;
    int64_t samples = 0;
    for (int p = 0; p < options.batch_pairs; ++p) {
      const CameraData& d = *train_cameras[std::uniform_int_distribution<size_t>(0, train_cameras.size() - 1)(rng)];
      const int64_t frames = d.features.size(0);
      const int64_t t = std::uniform_int_distribution<int64_t>(0, std::max<int64_t>(0, frames - (temporal ? 2 : 1)))(rng);
      const int64_t count = temporal ? 2 : 1;
      int64_t x0 = 0, y0 = 0;
      if (options.crop_px > 0) {
        const std::vector<int32_t>& near = d.subject_pixels[t];
        const int64_t pixel = near.empty() ? std::uniform_int_distribution<int64_t>(0, int64_t{d.width} * d.height - 1)(rng)
                                           : near[std::uniform_int_distribution<size_t>(0, near.size() - 1)(rng)];
        x0 = std::clamp<int64_t>(pixel % d.width - crop_w / 2, 0, d.features.size(3) - crop_w);
        y0 = std::clamp<int64_t>(pixel / d.width - crop_h / 2, 0, d.features.size(2) - crop_h);
      }
      const auto window = [&](const torch::Tensor& all, int64_t first, int64_t n) {
        return all.index({Slice(first, first + n), Slice(), Slice(y0, y0 + crop_h), Slice(x0, x0 + crop_w)});
      };
      xs.push_back(window(d.features, t, count));
      truths.push_back(window(d.truth, t, count));
      weights.push_back(window(d.weight, t, count));
      backgrounds.push_back(window(d.background, 0, 1).expand({count, 3, crop_h, crop_w}));
      if (d.alpha_target.defined()) alpha_targets.push_back(window(d.alpha_target, t, count));
      samples += count;
    }
    const torch::Tensor x = torch::cat(xs), truth = torch::cat(truths), weight = torch::cat(weights);
    const torch::Tensor background = torch::cat(backgrounds);
    const torch::Tensor raw_output = net->forward(x);
    auto [rgb, alpha] = neural::DecodeRerender(raw_output, x);
    const torch::Tensor out = Composite(rgb, alpha, background);
    torch::Tensor loss = options.l1_weight * (weight * (out - truth).abs()).mean() / weight.mean();
    loss = loss + kRawOutputPenaltyWeight * neural::RawOutputPenalty(raw_output);
    if (options.ssim_weight > 0) loss = loss + options.ssim_weight * (1 - MultiScaleSsim(out, truth));
    if (alpha_targets.size() == xs.size()) {
      loss = loss + options.alpha_weight * (weight * (alpha - torch::cat(alpha_targets)).abs()).mean() / weight.mean();
    }
    if (temporal) {
      const torch::Tensor even = torch::arange(0, samples, 2), odd = even + 1;
      const torch::Tensor change = out.index_select(0, odd) - out.index_select(0, even);
      const torch::Tensor truth_change = truth.index_select(0, odd) - truth.index_select(0, even);
      loss = loss + options.temporal_weight * (change - truth_change).abs().mean();
    }
    if (discriminator) {
      torch::Tensor fake_score = discriminator->forward(out);
      loss = loss + options.gan_weight * (fake_score - 1).pow(2).mean();
    }
    const double value = loss.item<double>();
    if (!std::isfinite(value)) {
      diverged = true;
      break;
    }
    optimizer.zero_grad();
    loss.backward();
    optimizer.step();
    if (discriminator) {
      d_optimizer->zero_grad();
      const torch::Tensor d_loss = (discriminator->forward(truth) - 1).pow(2).mean() + discriminator->forward(out.detach()).pow(2).mean();
      d_loss.backward();
      d_optimizer->step();
    }
    losses.push_back(value);
    if (report && iteration % 10 == 0) report->AddPoint("loss", value, iteration);
    progress.Update(options.iterations > 0 ? iteration : static_cast<int64_t>(elapsed), Cat(last.psnr_db, " dB"));
  }
  progress.Finish();
  summary.iterations = iteration;
  summary.seconds = Seconds(start);
  const size_t window = std::max<size_t>(1, std::min<size_t>(20, losses.size() / 4));
  if (!losses.empty()) {
    summary.first_loss = std::accumulate(losses.begin(), losses.begin() + window, 0.0) / window;
    summary.last_loss = std::accumulate(losses.end() - window, losses.end(), 0.0) / window;
  }
  summary.validation_psnr_db = validation_cameras.empty() ? 0 : best_validation;
  if (diverged || !validation_cameras.empty()) {
    // The weights on disk are those of the last evaluation before the loss broke down, or
    // those where the validation witnesses peaked; `last` holds their held-out scores.
    network = RerenderNetwork::Load(weights, options.net);
  } else {
    network.Save(weights);
  }
  summary.heldout_psnr_db = last.psnr_db;
  summary.heldout_ssim = last.ssim;
  summary.heldout_psnr_subject_db = last.psnr_subject_db;
  summary.flicker_ratio = last.flicker_ratio;
  summary.flicker_excess = last.flicker_excess;

  if (!eval_cameras.empty() && !last_images[0].empty()) {
    const size_t f = last_images[0].size() / 2;
    cv::Mat strip, eight_bit;
    cv::hconcat(std::vector<cv::Mat>{eval_cameras[0]->truth_images[f], eval_cameras[0]->raw_images[f], last_images[0][f]}, strip);
    strip.convertTo(eight_bit, CV_8UC3, 255);
    WritePng(model_dir / "heldout.png", eight_bit);
  }

  // The model directory.
  std::filesystem::create_directories(model_dir / "cameras");
  nlohmann::json model = {{"method", "rerender"}, {"net", options.net.ToJson()}, {"cameras", nlohmann::json::array()},
                          {"meshes", nlohmann::json::array()}, {"image_width", options.image_width},
                          {"supersample", options.supersample},
                          {"box_min", {box_min.x(), box_min.y(), box_min.z()}},
                          {"box_max", {box_max.x(), box_max.y(), box_max.z()}}, {"frame_sets", sets}};
  for (size_t i = 0; i < names.size(); ++i) {
    cameras[i].Write(model_dir / "cameras" / (names[i] + ".cameramodel"));
    model["cameras"].push_back(names[i]);
  }
  for (int64_t set : sets) {
    const auto file = meshes[set];
    const auto relative = std::filesystem::relative(file, model_dir);
    model["meshes"].push_back(!relative.empty() && *relative.begin() != ".." ? relative.string() : std::filesystem::absolute(file).string());
  }
  WriteFileAtomic(model_dir / "model.json", model.dump(2));

  if (diverged) {
    summary.termination = Termination::kFailure;
    summary.message = Cat("the loss became non-finite at iteration ", iteration, "; kept the weights of the last evaluation");
  } else if (const SubjectScores scores = ScoresNearSubject(summary); !eval_cameras.empty() && scores.shows_none()) {
    // The kept network shows the held-out cameras the background and hardly anything of the
    // subject (it erased it, or the raw render it started from shows no more): a better PSNR
    // than a poor raw render is no model of the subject.
    summary.termination = Termination::kDegenerate;
    summary.message = Cat("the network's output shows the held-out cameras no more of the subject than the background alone: ",
                          scores.near ? "near the subject" : "over the whole image (the reconstruction draws nothing there)",
                          " they score ", scores.shown, " dB, the background alone ", scores.background, " dB and the raw render ",
                          scores.raw, " dB",
                          scores.raw < scores.background - kErasedMarginDb
                              ? Cat(" (the reconstruction, built from ", recon_count,
                                    " colour cameras, renders worse than no subject at all: give it more cameras or depth)")
                              : std::string());
  } else if (eval_cameras.empty()) {
    summary.termination = Termination::kNoConvergence;
    summary.message = Cat("trained ", iteration, " iterations in ", summary.seconds, " s; no held-out camera to measure on");
  } else {
    summary.termination = Termination::kNoConvergence;
    summary.message = Cat("trained ", iteration, " iterations in ", summary.seconds, " s (budget spent); held-out PSNR ",
                          summary.heldout_psnr_db, " dB against the raw render's ", summary.raw_render_psnr_db, " dB");
  }
  if (!validation_cameras.empty() && !diverged) {
    summary.message += Cat("; kept the weights of iteration ", summary.kept_iteration, ", where the validation witnesses peaked at ",
                           summary.validation_psnr_db, " dB (raw render ", summary.validation_raw_psnr_db, " dB)");
  }
  if (report) {
    report->plan() = plan;
    auto& m = report->metrics();
    m["heldout_psnr_db"] = summary.heldout_psnr_db;
    m["raw_render_psnr_db"] = summary.raw_render_psnr_db;
    m["background_psnr_db"] = summary.background_psnr_db;
    m["background_psnr_subject_db"] = summary.background_psnr_subject_db;
    m["background_ssim"] = summary.background_ssim;
    m["heldout_ssim"] = summary.heldout_ssim;
    m["raw_render_ssim"] = summary.raw_render_ssim;
    m["heldout_psnr_subject_db"] = summary.heldout_psnr_subject_db;
    m["raw_render_psnr_subject_db"] = summary.raw_render_psnr_subject_db;
    m["flicker_ratio"] = summary.flicker_ratio;
    m["raw_flicker_ratio"] = summary.raw_flicker_ratio;
    m["flicker_excess"] = summary.flicker_excess;
    m["raw_flicker_excess"] = summary.raw_flicker_excess;
    if (!validation_cameras.empty()) {
      m["validation_psnr_db"] = summary.validation_psnr_db;
      m["validation_raw_psnr_db"] = summary.validation_raw_psnr_db;
      m["kept_iteration"] = summary.kept_iteration;
    }
    m["iterations"] = summary.iterations;
    m["seconds"] = summary.seconds;
    m["first_loss"] = summary.first_loss;
    m["last_loss"] = summary.last_loss;
    report->SetSummary({summary.termination, summary.message});
    report->Write(model_dir / "report.json");
  }
  return summary;
}

}  // namespace holocap
