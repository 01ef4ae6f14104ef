// Options, rendering through a holocap camera, the model on disk and its playback kind.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <mutex>

#include "avatar/avatar.h"
#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"
#include "splat/splat.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;

// gaussians.bin holds these fields one after the other, float32 little-endian.
struct Field {
  const char* name;
  std::vector<float> splat::Gaussians::*member;
  int per_gaussian;  // 0: 3 x coefficients
};
const Field kFields[] = {{"position", &splat::Gaussians::position, 3},
                         {"rotation", &splat::Gaussians::rotation, 4},
                         {"log_scale", &splat::Gaussians::log_scale, 3},
                         {"opacity", &splat::Gaussians::opacity, 1},
                         {"sh", &splat::Gaussians::sh, 0}};

}  // namespace

void SplatOptions::Check() const {
  HOLOCAP_CHECK_OPTION_IN(sh_degree, 0, splat::kMaxShDegree);
  HOLOCAP_CHECK_OPTION_GE(sh_degree_every, 1);
  HOLOCAP_CHECK_OPTION_GE(max_gaussians, 1);
  HOLOCAP_CHECK_OPTION_GE(max_seed_points, 1);
  HOLOCAP_CHECK_OPTION_GT(seed_scale_factor, 0);
  HOLOCAP_CHECK_OPTION_GT(initial_opacity, 0);
  HOLOCAP_CHECK_OPTION_LT(initial_opacity, 1);
  HOLOCAP_CHECK_OPTION_GE(image_width, 0, "0: native");
  HOLOCAP_CHECK_OPTION_GE(heldout_cameras, 0);
  take.Check();
  HOLOCAP_CHECK_OPTION_GE(minutes, 0);
  HOLOCAP_CHECK_OPTION(std::isfinite(minutes), minutes, "a budget must end");
  HOLOCAP_CHECK_OPTION(minutes > 0 || iterations > 0, minutes,
                       "give a positive minutes budget or a number of iterations");
  HOLOCAP_CHECK_OPTION_GE(iterations, 0);
  HOLOCAP_CHECK_OPTION_GT(learning_rate, 0);
  HOLOCAP_CHECK_OPTION_GT(position_lr, 0);
  HOLOCAP_CHECK_OPTION_GT(sh_lr, 0);
  HOLOCAP_CHECK_OPTION_GT(opacity_lr, 0);
  HOLOCAP_CHECK_OPTION_GT(scale_lr, 0);
  HOLOCAP_CHECK_OPTION_GT(rotation_lr, 0);
  HOLOCAP_CHECK_OPTION_IN(ssim_weight, 0, 1);
  HOLOCAP_CHECK_OPTION_GT(min_scale_px, 0);
  HOLOCAP_CHECK_OPTION_GT(max_scale_extent, 0);
  HOLOCAP_CHECK_OPTION_GE(densify_every, 1);
  HOLOCAP_CHECK_OPTION_GT(densify_gradient, 0);
  HOLOCAP_CHECK_OPTION_GT(percent_dense, 0);
  HOLOCAP_CHECK_OPTION_GT(prune_opacity, 0);
  HOLOCAP_CHECK_OPTION_LT(prune_opacity, 1);
  HOLOCAP_CHECK_OPTION_GT(prune_extent, 0);
  HOLOCAP_CHECK_OPTION_GE(opacity_reset_every, 0);
  HOLOCAP_CHECK_OPTION_GT(eval_every_s, 0);
  HOLOCAP_CHECK_OPTION_GE(eval_every_iterations, 0);
  HOLOCAP_CHECK_OPTION_GT(divergence_factor, 1);
  HOLOCAP_CHECK_OPTION_GT(max_opacity_step, 0);
  HOLOCAP_CHECK_OPTION_GE(max_divergences, 0);
  HOLOCAP_CHECK_OPTION_GE(snapshot_every, 1);
  HOLOCAP_CHECK_OPTION_GE(threads, 0);
  HOLOCAP_CHECK_OPTION(IsOneOf(scene, {"auto", "static", "dynamic"}), scene);
  HOLOCAP_CHECK_OPTION_GE(frame_minutes, 0);
  HOLOCAP_CHECK_OPTION(std::isfinite(frame_minutes), frame_minutes, "a budget must end");
  HOLOCAP_CHECK_OPTION(frame_minutes > 0 || frame_iterations > 0, frame_minutes,
                       "give later frames a positive frame_minutes budget or frame_iterations");
  HOLOCAP_CHECK_OPTION_GE(frame_iterations, 0);
  HOLOCAP_CHECK_OPTION_GE(frame_densify_every, 1);
  HOLOCAP_CHECK_OPTION_GT(frame_position_lr_scale, 0);
  HOLOCAP_CHECK_OPTION_GE(max_added_per_frame, 0);
  HOLOCAP_CHECK_OPTION_GT(new_surface_spacings, 0);
  HOLOCAP_CHECK_OPTION_GT(max_frame_megabytes, 0);
  HOLOCAP_CHECK_OPTION_GT(delta_position_step_m, 0);
  HOLOCAP_CHECK_OPTION_GT(delta_rotation_step, 0);
  HOLOCAP_CHECK_OPTION_GT(delta_scale_step, 0);
  HOLOCAP_CHECK_OPTION_GT(delta_opacity_step, 0);
  HOLOCAP_CHECK_OPTION_GT(delta_color_step, 0);
  HOLOCAP_CHECK_OPTION_GE(segment_frames, 0);
  HOLOCAP_CHECK_OPTION_GE(segment_start_iterations, 0);
  tasks.Check();
  HOLOCAP_CHECK_OPTION(segment_frames > 0 || tasks.shard.whole(), tasks.shard,
                       "--shard splits a per-frame run: give --segment-frames too");
  HOLOCAP_CHECK_OPTION(segment_frames == 0 || (iterations > 0 && frame_iterations > 0),
                       segment_frames,
                       "a per-frame run trains every frame for a number of iterations, so that "
                       "its bytes do not depend on the machine's speed: give iterations and "
                       "frame_iterations");
  HOLOCAP_CHECK_OPTION(segment_frames == 0 || scene != "static", segment_frames,
                       "a per-frame run splits the frames of a dynamic scene; scene is static");
}

int64_t SplatOptions::SegmentStartIterations() const {
  return segment_start_iterations > 0 ? segment_start_iterations : 4 * frame_iterations;
}

nlohmann::json SplatFrameSummary::ToJson() const {
  return {{"frame", frame},
          {"set", set},
          {"iterations", iterations},
          {"seconds", seconds},
          {"elapsed_s", elapsed_s},
          {"heldout_psnr_db", heldout_psnr_db},
          {"heldout_psnr_fg_db", heldout_psnr_fg_db},
          {"background_psnr_fg_db", background_psnr_fg_db},
          {"heldout_ssim", heldout_ssim},
          {"gaussians", gaussians},
          {"added", added},
          {"added_surface", added_surface},
          {"surface_uncovered", surface_uncovered},
          {"add_cap_reached", add_cap_reached},
          {"removed", removed},
          {"changed", changed},
          {"coarsened", coarsened},
          {"megabytes", megabytes},
          {"divergences", divergences}};
}

nlohmann::json SplatOptions::ToJson() const {
  return {{"sh_degree", sh_degree},
          {"sh_degree_every", sh_degree_every},
          {"max_gaussians", max_gaussians},
          {"max_seed_points", max_seed_points},
          {"seed_scale_factor", seed_scale_factor},
          {"initial_opacity", initial_opacity},
          {"image_width", image_width},
          {"heldout_cameras", heldout_cameras},
          {"heldout", heldout},
          {"take", take.ToJson()},
          {"recon_dir", recon_dir},
          {"minutes", minutes},
          {"iterations", iterations},
          {"learning_rate", learning_rate},
          {"position_lr", position_lr},
          {"sh_lr", sh_lr},
          {"opacity_lr", opacity_lr},
          {"scale_lr", scale_lr},
          {"rotation_lr", rotation_lr},
          {"ssim_weight", ssim_weight},
          {"min_scale_px", min_scale_px},
          {"max_scale_extent", max_scale_extent},
          {"seed", seed},
          {"densify_from", densify_from},
          {"densify_until", densify_until},
          {"densify_every", densify_every},
          {"densify_gradient", densify_gradient},
          {"percent_dense", percent_dense},
          {"prune_opacity", prune_opacity},
          {"prune_extent", prune_extent},
          {"opacity_reset_every", opacity_reset_every},
          {"eval_every_s", eval_every_s},
          {"eval_every_iterations", eval_every_iterations},
          {"divergence_factor", divergence_factor},
          {"max_opacity_step", max_opacity_step},
          {"max_divergences", max_divergences},
          {"snapshot_every", snapshot_every},
          {"threads", threads},
          {"scene", scene},
          {"frame_minutes", frame_minutes},
          {"frame_iterations", frame_iterations},
          {"frame_densify_every", frame_densify_every},
          {"frame_position_lr_scale", frame_position_lr_scale},
          {"max_added_per_frame", max_added_per_frame},
          {"new_surface_spacings", new_surface_spacings},
          {"max_frame_megabytes", max_frame_megabytes},
          {"delta_position_step_m", delta_position_step_m},
          {"delta_rotation_step", delta_rotation_step},
          {"delta_scale_step", delta_scale_step},
          {"delta_opacity_step", delta_opacity_step},
          {"delta_color_step", delta_color_step},
          {"segment_frames", segment_frames},
          {"segment_start_iterations", segment_start_iterations},
          {"tasks", tasks.ToJson()}};
}

splat::PinholeCamera ToPinhole(const CameraModel& camera) {
  if (!camera.has_core())
    Fail("splats render through a pinhole; lens model ", camera.lensmodel(), " has no core");
  splat::PinholeCamera pinhole;
  const auto& k = camera.intrinsics();
  pinhole.fx = k[0];
  pinhole.fy = k[1];
  pinhole.cx = k[2];
  pinhole.cy = k[3];
  pinhole.width = camera.width();
  pinhole.height = camera.height();
  const Eigen::Matrix3d r = camera.cam_from_world().rotation();
  for (int row = 0; row < 3; ++row) {
    for (int col = 0; col < 3; ++col) pinhole.cam_from_world_rotation[3 * row + col] = r(row, col);
    pinhole.cam_from_world_translation[row] = camera.cam_from_world().translation()[row];
  }
  return pinhole;
}

SplatRender RenderSplats(const splat::Gaussians& gaussians, const CameraModel& camera,
                         const cv::Mat& background, int sh_degree) {
  splat::RasterOptions options;
  options.active_sh_degree = sh_degree;
  return RenderSplats(gaussians, camera, background, options, nullptr);
}

SplatRender RenderSplats(const splat::Gaussians& gaussians, const CameraModel& camera,
                         const cv::Mat& background, const splat::RasterOptions& options,
                         SplatRenderScratch* scratch) {
  const splat::PinholeCamera pinhole = ToPinhole(camera);
  SplatRenderScratch local;
  if (scratch == nullptr) scratch = &local;
  splat::ProjectGaussians(gaussians, pinhole, options, &scratch->projected);
  SplatRender out;
  out.color.create(camera.height(), camera.width(), CV_32FC3);
  out.alpha.create(camera.height(), camera.width(), CV_32FC1);
  out.depth.create(camera.height(), camera.width(), CV_32FC1);
  cv::Mat bg;
  if (!background.empty()) {
    bg = background.isContinuous() ? background : background.clone();
    if (bg.type() != CV_32FC3 || bg.size() != out.color.size())
      Fail("a splat render's background must be CV_32FC3 at the camera's size");
  }
  splat::RasterizeForward(scratch->projected, pinhole, options,
                          bg.empty() ? static_cast<const float*>(nullptr) : bg.ptr<float>(),
                          out.color.ptr<float>(), out.alpha.ptr<float>(), out.depth.ptr<float>(),
                          &scratch->state);
  return out;
}

void SplatModel::Save(const fs::path& dir, bool write_gaussians) const {
  CreateDirectories(dir / "cameras");
  std::string bytes;
  nlohmann::json fields = nlohmann::json::array();
  for (const Field& field : kFields) {
    const std::vector<float>& values = gaussians.*field.member;
    if (write_gaussians)
      bytes.append(reinterpret_cast<const char*>(values.data()), values.size() * sizeof(float));
    fields.push_back(field.name);
  }
  if (write_gaussians) WriteFileAtomic(dir / "gaussians.bin", bytes);
  nlohmann::json names = nlohmann::json::array();
  for (size_t k = 0; k < cameras.size(); ++k) {
    const std::string name = Cat("view", k);
    if (write_gaussians) cameras[k].Write(dir / "cameras" / (name + ".cameramodel"));
    names.push_back(name);
  }
  const Eigen::Vector3d lo = box.min, hi = box.max;
  nlohmann::json json = {
      {"method", "splat"},
      {"format_version", bases.empty() ? 1 : 2},
      {"gaussians", gaussians.size()},
      {"frames", frames},
      {"frame_sets",
       std::vector<int64_t>(frame_sets.begin(),
                            frame_sets.begin() + std::min<int64_t>(frames, frame_sets.size()))},
      {"deltas", "deltas/<frame, 6 digits>.bin (splat/splat.h)"},
      {"sh_degree", gaussians.sh_degree},
      {"fields", fields},
      {"format", "float32 little-endian, each field for every Gaussian in turn"},
      {"cameras", names},
      {"box_min", {lo.x(), lo.y(), lo.z()}},
      {"box_max", {hi.x(), hi.y(), hi.z()}},
      {"plan", plan}};
  if (!bases.empty()) {
    json["delta_bases"] = std::vector<int64_t>(
        bases.begin(), bases.begin() + std::min<int64_t>(frames, bases.size()));
  }
  WriteFileAtomic(dir / "model.json", json.dump(2) + "\n");
}

SplatModel SplatModel::Load(const fs::path& dir) {
  const fs::path file = dir / "model.json";
  const fs::path binary = dir / "gaussians.bin";
  nlohmann::json json;
  try {
    json = nlohmann::json::parse(ReadFileToString(file));
  } catch (const nlohmann::json::exception& e) {
    Fail("cannot read ", file.string(), ": ", e.what());
  }
  SplatModel model;
  std::vector<std::string> camera_names;
  if (!json.is_object() || json.value("method", "") != "splat")
    Fail(dir.string(), " does not hold a splat model");
  try {
    const int64_t count = json.at("gaussians").get<int64_t>();
    model.gaussians.sh_degree = json.at("sh_degree").get<int>();
    if (count < 0 || model.gaussians.sh_degree < 0 ||
        model.gaussians.sh_degree > splat::kMaxShDegree) {
      Fail("bad count or degree");
    }
    // The count is checked against gaussians.bin's real size before anything is allocated.
    const uint64_t per_gaussian =
        sizeof(float) *
        (11 + 3 * static_cast<uint64_t>(splat::ShCoefficients(model.gaussians.sh_degree)));
    const std::string bytes = ReadFileToString(binary);
    if (static_cast<uint64_t>(count) != bytes.size() / per_gaussian ||
        bytes.size() % per_gaussian != 0) {
      Fail("it declares ", count, " Gaussians of degree ", model.gaussians.sh_degree, " (",
           per_gaussian, " bytes each) but '", binary.string(), "' holds ", bytes.size(), " bytes");
    }
    model.gaussians.Resize(count);
    size_t offset = 0;
    for (const Field& field : kFields) {
      std::vector<float>& values = model.gaussians.*field.member;
      const size_t size = values.size() * sizeof(float);
      std::memcpy(values.data(), bytes.data() + offset, size);
      offset += size;
    }
    for (const auto& name : json.at("cameras")) {
      camera_names.push_back(name.get<std::string>());
      const std::string& text = camera_names.back();
      if (text.empty() || text.find_first_of("/\\") != std::string::npos || text == "." ||
          text == "..")
        Fail("camera name '", text, "' is not a plain name");
    }
    const auto lo = json.at("box_min").get<std::vector<double>>();
    const auto hi = json.at("box_max").get<std::vector<double>>();
    if (lo.size() != 3 || hi.size() != 3 ||
        !std::all_of(lo.begin(), lo.end(), [](double v) { return std::isfinite(v); }) ||
        !std::all_of(hi.begin(), hi.end(), [](double v) { return std::isfinite(v); }))
      Fail("box_min and box_max must be 3 finite numbers each");
    model.box = Box{Eigen::Vector3d(lo[0], lo[1], lo[2]), Eigen::Vector3d(hi[0], hi[1], hi[2])};
    model.plan = json.value("plan", nlohmann::json::object());
    model.frames = json.value("frames", int64_t{1});
    model.frame_sets = json.value("frame_sets", std::vector<int64_t>{});
    if (model.frames < 1) Fail("frames must be at least 1");
    const int version = json.value("format_version", 1);
    if (version > 2) Fail("format version ", version, " is newer than this program's (2)");
    if (version == 2) {
      model.bases = json.at("delta_bases").get<std::vector<int64_t>>();
      if (static_cast<int64_t>(model.bases.size()) != model.frames)
        Fail("delta_bases must name a base for each of its frames");
      for (int64_t f = 0; f < model.frames; ++f) {
        if (f == 0 ? model.bases[f] != -1 : model.bases[f] < 0 || model.bases[f] >= f)
          Fail("frame ", f, "'s base ", model.bases[f], " is not an earlier frame");
      }
    }
  } catch (const nlohmann::json::exception& e) {
    Fail(file.string(), ": ", e.what());
  } catch (const Error& e) {
    Fail(file.string(), ": ", e.what());
  }
  // A camera model's errors name its own file.
  for (const auto& name : camera_names)
    model.cameras.push_back(CameraModel::Read(dir / "cameras" / (name + ".cameramodel")));
  return model;
}

fs::path SplatDeltaFile(const fs::path& dir, int64_t frame) {
  char name[32];
  std::snprintf(name, sizeof(name), "%06lld.bin", static_cast<long long>(frame));
  return dir / "deltas" / name;
}

splat::Gaussians SplatModel::Frame(const fs::path& dir, int64_t frame,
                                   const splat::Gaussians* previous, int64_t previous_frame) const {
  if (frame < 0 || frame >= frames)
    Fail("frame ", frame, " is outside the splat model's 0..", frames - 1);
  // The frames whose deltas lead from frame 0 (or from `previous`) to `frame`, last first.
  std::vector<int64_t> way;
  bool resume = false;
  for (int64_t k = frame; k > 0; k = Base(k)) {
    if (previous != nullptr && k == previous_frame) {
      resume = true;
      break;
    }
    way.push_back(k);
  }
  splat::Gaussians current = resume ? *previous : gaussians;
  for (auto k = way.rbegin(); k != way.rend(); ++k)
    current = ApplySplatDeltaFile(current, SplatDeltaFile(dir, *k));
  return current;
}

int64_t SplatModel::Base(int64_t frame) const {
  if (frame <= 0) return -1;
  return frame < static_cast<int64_t>(bases.size()) ? bases[frame] : frame - 1;
}

namespace {

// A splat model as playback sees it: its frames drawn natively, one delta after another.
class SplatAvatar : public AvatarModel {
 public:
  SplatAvatar(SplatModel model, fs::path dir, const splat::RasterOptions& options)
      : model_(std::move(model)),
        dir_(std::move(dir)),
        current_(model_.gaussians),
        options_(options) {}
  std::string method() const override { return "splat"; }
  int64_t frame_count() const override { return model_.frames; }
  Box box() const override { return model_.box; }
  std::vector<CameraModel> cameras() const override { return model_.cameras; }
  RenderedView Render(const CameraModel& camera, int64_t frame,
                      const ViewRenderOptions& options) override {
    const auto start = std::chrono::steady_clock::now();
    // Played in order, each frame applies one delta to the one before.
    frame = std::clamp<int64_t>(frame, 0, model_.frames - 1);
    if (frame != current_frame_) {
      current_ = model_.Frame(dir_, frame, &current_, current_frame_);
      current_frame_ = frame;
    }
    SplatRender render = RenderSplats(current_, camera, {}, options_, &scratch_);
    RenderedView view;
    view.color = render.color;
    view.alpha = render.alpha;
    view.depth = render.depth;  // this view's own: marked in place
    for (int y = 0; y < view.depth.rows; ++y) {
      float* depth = view.depth.ptr<float>(y);
      const float* alpha = render.alpha.ptr<float>(y);
      for (int x = 0; x < view.depth.cols; ++x) {
        if (alpha[x] < options.depth_min_alpha) depth[x] = std::numeric_limits<float>::quiet_NaN();
      }
    }
    view.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    return view;
  }

 private:
  SplatModel model_;
  fs::path dir_;
  splat::Gaussians current_;
  int64_t current_frame_ = 0;
  splat::RasterOptions options_;
  SplatRenderScratch scratch_;
};

}  // namespace

std::unique_ptr<AvatarModel> OpenSplatModel(const fs::path& dir,
                                            const splat::RasterOptions& options) {
  return std::make_unique<SplatAvatar>(SplatModel::Load(dir), dir, options);
}

void RegisterSplatAvatarKind(AvatarKindRegistry& registry) {
  registry.Register(
      {"splat", "3D Gaussian splats drawn by the CPU rasteriser",
       [](const fs::path& dir, const nlohmann::json&) { return OpenSplatModel(dir); }});
}

}  // namespace holocap
