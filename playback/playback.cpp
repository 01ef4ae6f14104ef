#include "playback/playback.h"
#include "playback/internal/camera_path.h"

#include <ImfChannelList.h>
#include <ImfFrameBuffer.h>
#include <ImfHeader.h>
#include <ImfOutputFile.h>
#include <unistd.h>

#include <Imath/half.h>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <nlohmann/json.hpp>
#include <numbers>

#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/image.h"
#include "core/pose.h"
#include "core/progress.h"
#include "core/video.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;

Eigen::Vector3d BoxCenter(const AvatarModel& model) { return model.box().center(); }

// Horizontal field of view that keeps the whole box in view from `distance`.
double FitFovDeg(const AvatarModel& model, double distance, int width, int height) {
  const double radius = 0.5 * model.box().size().norm();
  const double half = std::atan(std::min(0.95, 1.1 * radius / std::max(distance, 1e-6)));
  // The box must fit the shorter side; convert that angle to the horizontal one.
  const double aspect = static_cast<double>(width) / height;
  const double half_h = aspect >= 1 ? std::atan(std::tan(half) * aspect) : half;
  return 2 * half_h * 180 / std::numbers::pi;
}

std::string ViewName(int64_t index, const char* extension) {
  char name[32];
  std::snprintf(name, sizeof(name), "%06lld%s", static_cast<long long>(index), extension);
  return name;
}

// Straight-alpha BGRA 8-bit from premultiplied colour.
cv::Mat ToBgra8(const RenderedView& view) {
  cv::Mat out(view.color.size(), CV_8UC4);
  for (int y = 0; y < out.rows; ++y) {
    for (int x = 0; x < out.cols; ++x) {
      const cv::Vec3f c = view.color.at<cv::Vec3f>(y, x);
      const float a = view.alpha.at<float>(y, x);
      cv::Vec4b& o = out.at<cv::Vec4b>(y, x);
      for (int k = 0; k < 3; ++k) {
        const float straight = a > 1e-6f ? c[k] / a : 0.0f;
        o[k] = cv::saturate_cast<uint8_t>(std::lround(255 * std::clamp(straight, 0.0f, 1.0f)));
      }
      o[3] = cv::saturate_cast<uint8_t>(std::lround(255 * std::clamp(a, 0.0f, 1.0f)));
    }
  }
  return out;
}

cv::Mat OverBackground(const RenderedView& view, const Eigen::Vector3d& background) {
  cv::Mat out(view.color.size(), CV_8UC3);
  for (int y = 0; y < out.rows; ++y) {
    for (int x = 0; x < out.cols; ++x) {
      const cv::Vec3f c = view.color.at<cv::Vec3f>(y, x);
      const float a = view.alpha.at<float>(y, x);
      for (int k = 0; k < 3; ++k) {
        out.at<cv::Vec3b>(y, x)[k] = cv::saturate_cast<uint8_t>(
            std::lround(255 * std::clamp(c[k] + (1 - a) * background[k], 0.0, 1.0)));
      }
    }
  }
  return out;
}

}  // namespace

void OrbitOptions::Check() const {
  HOLOCAP_CHECK_OPTION_GE(views, 1);
  HOLOCAP_CHECK_OPTION_GE(width, 2, "H.264: even and at least 2x2");
  HOLOCAP_CHECK_OPTION_GE(height, 2, "H.264: even and at least 2x2");
  HOLOCAP_CHECK_OPTION(width % 2 == 0, width, "H.264: even and at least 2x2");
  HOLOCAP_CHECK_OPTION(height % 2 == 0, height, "H.264: even and at least 2x2");
  HOLOCAP_CHECK_OPTION_GE(fov_deg, 0);
  HOLOCAP_CHECK_OPTION_LT(fov_deg, 179);
  HOLOCAP_CHECK_OPTION_GE(radius_m, 0);
  HOLOCAP_CHECK_OPTION_GE(frame, 0);
  HOLOCAP_CHECK_OPTION_GT(fps, 0);
}

void PlaybackOptions::Check() const {
  HOLOCAP_CHECK_OPTION(!out.empty(), out, "a directory or a .mp4 file");
  HOLOCAP_CHECK_OPTION_IN(crf, 0, 51);
  HOLOCAP_CHECK_OPTION_GT(render.step_voxels, 0);
  HOLOCAP_CHECK_OPTION(out.extension() == ".mp4" || png || exr || !write_frames, out,
                       "a frame directory needs PNG or EXR output");
}

Eigen::Vector3d ModelUp(const AvatarModel& model) {
  Eigen::Vector3d up = Eigen::Vector3d::Zero();
  for (const auto& camera : model.cameras()) up -= camera.world_from_cam().rotation().col(1);
  if (up.norm() < 1e-6) return Eigen::Vector3d::UnitZ();
  return up.normalized();
}

CameraPath OrbitPath(const AvatarModel& model, const OrbitOptions& options) {
  options.Check();
  const Eigen::Vector3d center = BoxCenter(model);
  const Eigen::Vector3d up = ModelUp(model);
  const auto cameras = model.cameras();
  double radius = 0, height = 0;
  Eigen::Vector3d start = Eigen::Vector3d::UnitX();
  for (size_t i = 0; i < cameras.size(); ++i) {
    const Eigen::Vector3d offset = cameras[i].center_in_world() - center;
    const double along = offset.dot(up);
    const Eigen::Vector3d flat = offset - along * up;
    radius += flat.norm() / cameras.size();
    height += along / cameras.size();
    if (i == 0 && flat.norm() > 1e-9) start = flat.normalized();
  }
  if (cameras.empty()) radius = 2 * model.box().size().norm();
  if (options.radius_m > 0) radius = options.radius_m;
  if (options.use_height) height = options.height_m;
  if (std::abs(start.dot(up)) > 0.99) start = up.unitOrthogonal();
  const Eigen::Vector3d side = up.cross(start).normalized();
  const double distance = std::hypot(radius, height);
  const double fov = options.fov_deg > 0
                         ? options.fov_deg
                         : FitFovDeg(model, distance, options.width, options.height);
  CameraPath path;
  path.fps = options.fps;
  for (int i = 0; i < options.views; ++i) {
    const double angle = 2 * std::numbers::pi * i / options.views;
    const Eigen::Vector3d eye =
        center + radius * (std::cos(angle) * start + std::sin(angle) * side) + height * up;
    path.cameras.push_back(LookAtCamera(eye, center, up, fov, options.width, options.height));
    path.frames.push_back(options.advance_frames
                              ? i % std::max<int64_t>(model.frame_count(), 1)
                              : std::min(options.frame, model.frame_count() - 1));
  }
  return path;
}

CameraPath ReadCameraPath(const fs::path& file, const AvatarModel& model, int width, int height) {
  return ParseCameraPath(ReadFileToString(file), file, ModelUp(model), width, height);
}

void WriteViewExr(const fs::path& file, const RenderedView& view) {
  const int w = view.color.cols, h = view.color.rows;
  std::vector<half> channels[4];
  for (auto& c : channels) c.resize(static_cast<size_t>(w) * h);
  cv::Mat depth = view.depth.isContinuous() ? view.depth : view.depth.clone();
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const size_t i = static_cast<size_t>(y) * w + x;
      const cv::Vec3f c = view.color.at<cv::Vec3f>(y, x);
      channels[0][i] = half(c[2]);  // EXR's R, G, B from BGR
      channels[1][i] = half(c[1]);
      channels[2][i] = half(c[0]);
      channels[3][i] = half(view.alpha.at<float>(y, x));
    }
  }
  fs::path temp = file;
  temp += ".partial";
  try {
    Imf::Header header(w, h);
    for (const char* name : {"R", "G", "B", "A"})
      header.channels().insert(name, Imf::Channel(Imf::HALF));
    header.channels().insert("Z", Imf::Channel(Imf::FLOAT));
    header.compression() = Imf::ZIP_COMPRESSION;
    Imf::OutputFile out(temp.c_str(), header);
    Imf::FrameBuffer buffer;
    const char* names[4] = {"R", "G", "B", "A"};
    for (int c = 0; c < 4; ++c) {
      buffer.insert(names[c], Imf::Slice(Imf::HALF, reinterpret_cast<char*>(channels[c].data()),
                                         sizeof(half), sizeof(half) * w));
    }
    buffer.insert("Z", Imf::Slice(Imf::FLOAT, reinterpret_cast<char*>(depth.ptr<float>()),
                                  sizeof(float), sizeof(float) * w));
    out.setFrameBuffer(buffer);
    out.writePixels(h);
  } catch (const std::exception& e) {
    std::error_code ec;
    fs::remove(temp, ec);
    Fail("cannot write '", file.string(), "': ", e.what());
  }
  fs::rename(temp, file);
}

PlaybackSummary RenderPath(AvatarModel& model, const CameraPath& path,
                           const PlaybackOptions& options, Report* report) {
  options.Check();
  if (path.size() == 0) Fail("the camera path has no view");
  const auto start = std::chrono::steady_clock::now();
  const bool video = options.out.extension() == ".mp4";
  std::unique_ptr<Mp4Writer> writer;
  if (options.write_frames) {
    if (video) {
      if (options.out.has_parent_path()) CreateDirectories(options.out.parent_path());
      const auto& first = path.cameras.front();
      for (const auto& camera : path.cameras) {
        if (camera.width() != first.width() || camera.height() != first.height())
          Fail("every view of a video must have one size");
      }
      writer = std::make_unique<Mp4Writer>(options.out, first.width(), first.height(), path.fps,
                                           options.crf);
    } else {
      CreateDirectories(options.out);
    }
  }
  PlaybackSummary summary;
  summary.output = options.out;
  Progress progress("render", static_cast<int64_t>(path.size()));
  double samples = 0;
  for (size_t i = 0; i < path.size(); ++i) {
    RenderedView view = model.Render(path.cameras[i], path.frames[i], options.render);
    summary.render_seconds += view.seconds;
    samples += view.samples_per_ray;
    if (options.write_frames) {
      if (video) {
        writer->Write(OverBackground(view, options.background));
      } else {
        if (options.png) WritePng(options.out / ViewName(i, ".png"), ToBgra8(view));
        if (options.exr) WriteViewExr(options.out / ViewName(i, ".exr"), view);
      }
    }
    progress.Update(static_cast<int64_t>(i + 1), Cat(view.samples_per_ray, " samples/ray"));
  }
  if (writer) writer->Close();
  progress.Finish();
  summary.views = static_cast<int64_t>(path.size());
  summary.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  summary.render_fps = summary.views / std::max(summary.render_seconds, 1e-9);
  summary.overall_fps = summary.views / std::max(summary.seconds, 1e-9);
  summary.samples_per_ray = samples / summary.views;
  // Models that march no rays (rerendering rasterises) report no samples per ray.
  summary.End(
      Termination::kSuccess,
      Cat(summary.views, " views rendered at ", summary.render_fps, " fps (", summary.overall_fps,
          " fps with writing)",
          summary.samples_per_ray > 0 ? Cat(", ", summary.samples_per_ray, " samples/ray") : ""));
  if (report != nullptr) {
    report->metrics()["playback"] = {{"views", summary.views},
                                     {"render_fps", summary.render_fps},
                                     {"overall_fps", summary.overall_fps},
                                     {"samples_per_ray", summary.samples_per_ray},
                                     {"seconds", summary.seconds}};
  }
  return summary;
}

}  // namespace holocap
