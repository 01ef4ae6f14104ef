// Camera paths: the JSON format `holocap render --path` reads (playback/playback.h).
#include <algorithm>
#include <cmath>
#include <nlohmann/json.hpp>
#include <numbers>

#include "core/error.h"
#include "core/pose.h"
#include "playback/internal/camera_path.h"
#include "playback/playback.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;

// The most keys and views a path may hold: an hour at 30 fps is 108000 views.
constexpr int64_t kMaxPathViews = 1'000'000;

Eigen::Vector3d JsonVector(const nlohmann::json& json, const std::string& field,
                           const fs::path& file) {
  if (!json.contains(field) || !json[field].is_array() || json[field].size() != 3 ||
      !std::all_of(json[field].begin(), json[field].end(),
                   [](const nlohmann::json& v) { return v.is_number(); })) {
    Fail(file.string(), ": \"", field, "\" must be an array of 3 numbers");
  }
  const Eigen::Vector3d v(json[field][0].get<double>(), json[field][1].get<double>(),
                          json[field][2].get<double>());
  if (!v.allFinite() || v.cwiseAbs().maxCoeff() > kMaxCameraTranslationM)
    Fail(file.string(), ": \"", field, "\" must be finite and within ", kMaxCameraTranslationM,
         " m of the origin");
  return v;
}

}  // namespace

CameraModel LookAtCamera(const Eigen::Vector3d& eye, const Eigen::Vector3d& target,
                         const Eigen::Vector3d& up, double fov_deg, int width, int height) {
  const double focal = 0.5 * width / std::tan(0.5 * fov_deg * std::numbers::pi / 180);
  return CameraModel::Pinhole(focal, width, height, CamFromWorldLookAt(eye, target, up));
}

CameraPath ParseCameraPath(const std::string& text, const fs::path& file,
                           const Eigen::Vector3d& default_up, int width, int height) {
  if (width < 2 || height < 2 || width % 2 || height % 2)
    Fail("output size must be even and at least 2x2, got ", width, "x", height);
  nlohmann::json json;
  try {
    json = nlohmann::json::parse(text);
  } catch (const nlohmann::json::exception& e) {
    Fail(file.string(), " is not valid JSON: ", e.what());
  }
  if (!json.is_object() || !json.contains("keys") || !json["keys"].is_array() ||
      json["keys"].empty())
    Fail(file.string(), ": \"keys\" must be a non-empty array");
  const auto& keys = json["keys"];
  if (static_cast<int64_t>(keys.size()) > kMaxPathViews)
    Fail(file.string(), ": more than ", kMaxPathViews, " keys");
  CameraPath path;
  // A key's frame: a whole number of frames, finite and within the path's bounds.
  const auto frame_of = [&](const nlohmann::json& key) {
    const double frame = key.value("frame", 0.0);
    if (!std::isfinite(frame) || std::abs(frame) > 1e12)
      Fail(file.string(), ": \"frame\" must be a finite frame number");
    return frame;
  };
  try {
    path.fps = json.value("fps", 30.0);
    if (!(path.fps > 0) || !std::isfinite(path.fps))
      Fail(file.string(), ": \"fps\" must be positive");
    const bool model_keys = keys[0].is_object() && keys[0].contains("cameramodel");
    if (model_keys) {
      for (const auto& key : keys) {
        if (!key.is_object() || !key.contains("cameramodel"))
          Fail(file.string(), ": every key must name a cameramodel when the first does");
        CameraModel camera =
            CameraModel::Read(file.parent_path() / key["cameramodel"].get<std::string>());
        if (camera.width() != width)
          camera = camera.Scaled(static_cast<double>(width) / camera.width());
        path.cameras.push_back(camera);
        path.frames.push_back(std::llround(frame_of(key)));
      }
      return path;
    }
    struct Key {
      Eigen::Vector3d eye, look_at, up;
      double fov;
      double frame;
    };
    std::vector<Key> parsed;
    for (const auto& key : keys) {
      if (!key.is_object()) Fail(file.string(), ": every key must be an object");
      Key k;
      k.eye = JsonVector(key, "eye", file);
      k.look_at = JsonVector(key, "look_at", file);
      k.up = key.contains("up") ? JsonVector(key, "up", file) : default_up;
      k.fov = key.value("fov_deg", 40.0);
      k.frame = frame_of(key);
      if (!(k.fov > 0 && k.fov < 179)) Fail(file.string(), ": fov_deg must be in (0, 179)");
      parsed.push_back(k);
    }
    const int64_t views = json.value("views", static_cast<int64_t>(parsed.size()));
    if (views < 1 || views > kMaxPathViews)
      Fail(file.string(), ": \"views\" must be in [1, ", kMaxPathViews, "]");
    for (int64_t i = 0; i < views; ++i) {
      const double s = views == 1 ? 0 : static_cast<double>(i) * (parsed.size() - 1) / (views - 1);
      const size_t a = std::min(static_cast<size_t>(s), parsed.size() - 1);
      const size_t b = std::min(a + 1, parsed.size() - 1);
      const double t = s - a;
      const Key& ka = parsed[a];
      const Key& kb = parsed[b];
      path.cameras.push_back(LookAtCamera((1 - t) * ka.eye + t * kb.eye,
                                          (1 - t) * ka.look_at + t * kb.look_at,
                                          ((1 - t) * ka.up + t * kb.up).normalized(),
                                          (1 - t) * ka.fov + t * kb.fov, width, height));
      path.frames.push_back(std::llround((1 - t) * ka.frame + t * kb.frame));
    }
  } catch (const nlohmann::json::exception& e) {
    Fail(file.string(), ": ", e.what());
  } catch (const Error& e) {
    const std::string what = e.what();
    if (what.rfind(file.string(), 0) == 0) throw;
    Fail(file.string(), ": ", what);
  }
  return path;
}

}  // namespace holocap
