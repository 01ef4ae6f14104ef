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
  HOLOCAP_CHECK_OPTION_GE(cpu_minutes, 0, "0: the wall clock (minutes)");
  HOLOCAP_CHECK_OPTION(std::isfinite(cpu_minutes), cpu_minutes, "a budget must end");
  HOLOCAP_CHECK_OPTION(cpu_minutes == 0 || (minutes > 0 && frame_minutes > 0), cpu_minutes,
                       "minutes and frame_minutes share a CPU budget between the frames: both "
                       "must be positive");
  HOLOCAP_CHECK_OPTION(cpu_minutes == 0 || segment_frames == 0, cpu_minutes,
                       "a per-frame run trains for iterations only");
  HOLOCAP_CHECK_OPTION(IsOneOf(seed_method, {"auto", "hull", "tsdf", "mvs"}), seed_method);
  HOLOCAP_CHECK_OPTION(!take.color_only || seed_method != "tsdf", seed_method,
                       "TSDF fusion reads the depth sensors that --no-depth leaves out");
  HOLOCAP_CHECK_OPTION_GT(learning_rate, 0);
  HOLOCAP_CHECK_OPTION_GT(position_lr, 0);
  HOLOCAP_CHECK_OPTION_GT(sh_lr, 0);
  HOLOCAP_CHECK_OPTION_GT(opacity_lr, 0);
  HOLOCAP_CHECK_OPTION_GT(scale_lr, 0);
  HOLOCAP_CHECK_OPTION_GT(rotation_lr, 0);
  HOLOCAP_CHECK_OPTION_IN(ssim_weight, 0, 1);
  HOLOCAP_CHECK_OPTION_GT(min_scale_px, 0);
  HOLOCAP_CHECK_OPTION_GE(pixel_budget, 0);
  HOLOCAP_CHECK_OPTION_IN(full_resolution_at, 0, 1);
  HOLOCAP_CHECK_OPTION_GT(max_scale_view, 0);
  HOLOCAP_CHECK_OPTION_GE(densify_every, 1);
  HOLOCAP_CHECK_OPTION_GT(densify_gradient, 0);
  HOLOCAP_CHECK_OPTION_GT(split_scale_view, 0);
  HOLOCAP_CHECK_OPTION_GT(prune_opacity, 0);
  HOLOCAP_CHECK_OPTION_LT(prune_opacity, 1);
  HOLOCAP_CHECK_OPTION_GT(prune_scale_view, 0);
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
  HOLOCAP_CHECK_OPTION_GE(frame_motion_spacings, 0);
  HOLOCAP_CHECK_OPTION_GE(frame_own_position_lr_scale, 0);
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
  nlohmann::json json = {{"frame", frame},
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
  if (std::isfinite(heldout_psnr_white_db)) json["heldout_psnr_white_db"] = heldout_psnr_white_db;
  return json;
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
          {"seed_method", seed_method},
          {"minutes", minutes},
          {"cpu_minutes", cpu_minutes},
          {"iterations", iterations},
          {"learning_rate", learning_rate},
          {"position_lr", position_lr},
          {"sh_lr", sh_lr},
          {"opacity_lr", opacity_lr},
          {"scale_lr", scale_lr},
          {"rotation_lr", rotation_lr},
          {"ssim_weight", ssim_weight},
          {"min_scale_px", min_scale_px},
          {"pixel_budget", pixel_budget},
          {"full_resolution_at", full_resolution_at},
          {"max_scale_view", max_scale_view},
          {"seed", seed},
          {"densify_from", densify_from},
          {"densify_until", densify_until},
          {"densify_every", densify_every},
          {"densify_gradient", densify_gradient},
          {"split_scale_view", split_scale_view},
          {"prune_opacity", prune_opacity},
          {"prune_scale_view", prune_scale_view},
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
          {"frame_motion_spacings", frame_motion_spacings},
          {"frame_own_position_lr_scale", frame_own_position_lr_scale},
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
