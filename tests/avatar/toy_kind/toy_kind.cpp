#include "tests/avatar/toy_kind/toy_kind.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <memory>

#include "core/error.h"
#include "core/fs.h"

namespace holocap::toy {
namespace {

class ToyAvatar : public AvatarModel {
 public:
  explicit ToyAvatar(const nlohmann::json& json)
      : center_(json.at("center").at(0), json.at("center").at(1), json.at("center").at(2)),
        radius_(json.at("radius")),
        bgr_(json.at("color").at(0), json.at("color").at(1), json.at("color").at(2)) {
    if (!(radius_ > 0)) Fail("a toy model's radius must be positive");
  }

  std::string method() const override { return "toy"; }
  int64_t frame_count() const override { return 1; }
  Box box() const override {
    return {center_ - Eigen::Vector3d::Constant(radius_),
            center_ + Eigen::Vector3d::Constant(radius_)};
  }
  std::vector<CameraModel> cameras() const override { return {}; }

  // Each pixel's ray against the ball, exactly.
  RenderedView Render(const CameraModel& camera, int64_t /*frame*/,
                      const ViewRenderOptions& /*options*/) override {
    const auto start = std::chrono::steady_clock::now();
    const int w = camera.width(), h = camera.height();
    RenderedView view;
    view.color = cv::Mat(h, w, CV_32FC3, cv::Scalar::all(0));
    view.alpha = cv::Mat(h, w, CV_32FC1, cv::Scalar::all(0));
    view.depth = cv::Mat(h, w, CV_32FC1, cv::Scalar::all(std::numeric_limits<float>::quiet_NaN()));
    const Eigen::Vector3d center_in_cam = camera.cam_from_world() * center_;
    for (int y = 0; y < h; ++y) {
      for (int x = 0; x < w; ++x) {
        const Eigen::Vector3d ray = camera.Unproject(Eigen::Vector2d(x, y)).normalized();
        const double along = ray.dot(center_in_cam);
        const double miss2 = (center_in_cam - along * ray).squaredNorm();
        if (!(along > 0) || miss2 > radius_ * radius_) continue;
        const double t = along - std::sqrt(radius_ * radius_ - miss2);
        view.color.at<cv::Vec3f>(y, x) = cv::Vec3f(bgr_.x(), bgr_.y(), bgr_.z());
        view.alpha.at<float>(y, x) = 1;
        view.depth.at<float>(y, x) = static_cast<float>(t * ray.z());
        ++view.rays_in_volume;
      }
    }
    view.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    return view;
  }

  // The ball as the RGBA grid the web export streams: opaque inside, empty outside.
  bool Bake(int64_t /*frame*/, const ViewRenderOptions& options, BakedFrame* out) override {
    constexpr int kGrid = 32;
    out->box = box();
    out->grid = kGrid;
    out->rgba.assign(static_cast<size_t>(kGrid) * kGrid * kGrid * 4, 0.0f);
    const double voxel = 2 * radius_ / kGrid;
    for (int z = 0; z < kGrid; ++z) {
      for (int y = 0; y < kGrid; ++y) {
        for (int x = 0; x < kGrid; ++x) {
          const Eigen::Vector3d p =
              out->box.min + voxel * Eigen::Vector3d(x + 0.5, y + 0.5, z + 0.5);
          if ((p - center_).norm() > radius_) continue;
          float* v = &out->rgba[((static_cast<size_t>(z) * kGrid + y) * kGrid + x) * 4];
          v[0] = static_cast<float>(bgr_.x());  // the channels of the images it renders
          v[1] = static_cast<float>(bgr_.y());
          v[2] = static_cast<float>(bgr_.z());
          v[3] = static_cast<float>(1e4);  // density in 1/m: opaque within a millimetre
        }
      }
    }
    out->step_m = options.step_voxels * voxel;
    return true;
  }

 private:
  Eigen::Vector3d center_;
  double radius_;
  Eigen::Vector3d bgr_;
};

}  // namespace

void WriteToyModel(const std::filesystem::path& dir, const Eigen::Vector3d& center_m,
                   double radius_m, const Eigen::Vector3d& bgr) {
  CreateDirectories(dir);
  // "frame_sets": the take's frame sets the model shows (the web export's timeline).
  const nlohmann::json json = {{"method", "toy"},
                               {"frame_sets", {0}},
                               {"center", {center_m.x(), center_m.y(), center_m.z()}},
                               {"radius", radius_m},
                               {"color", {bgr.x(), bgr.y(), bgr.z()}}};
  WriteFileAtomic(dir / "model.json", json.dump(2));
}

void RegisterToyAvatarKind(AvatarKindRegistry& registry) {
  registry.Register(
      {"toy", "a ball of one colour", [](const std::filesystem::path&, const nlohmann::json& json) {
         return std::unique_ptr<AvatarModel>(new ToyAvatar(json));
       }});
}

}  // namespace holocap::toy
