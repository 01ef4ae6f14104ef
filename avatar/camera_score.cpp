#include "avatar/camera_score.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "core/error.h"
#include "core/take.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

namespace {

namespace fs = std::filesystem;

// A captured image as 8-bit BGR (16-bit scaled down, alpha dropped, grey spread).
cv::Mat Bgr8(const cv::Mat& image) {
  cv::Mat out = image;
  if (out.depth() == CV_16U) out.convertTo(out, CV_8U, 1.0 / 257.0);
  if (out.channels() == 4) cv::cvtColor(out, out, cv::COLOR_BGRA2BGR);
  if (out.channels() == 1) cv::cvtColor(out, out, cv::COLOR_GRAY2BGR);
  return out;
}

cv::Mat UnitFloat(const cv::Mat& image) {
  cv::Mat out;
  image.convertTo(out, CV_32FC3, image.depth() == CV_8U ? 1.0 / 255.0 : 1.0);
  return out;
}

std::string SetName(int64_t set) {
  char name[32];
  std::snprintf(name, sizeof(name), "%06lld", static_cast<long long>(set));
  return name;
}

}  // namespace

Undistortion::Undistortion(const CameraModel& lens) {
  const auto& k = lens.intrinsics();
  pinhole = CameraModel("LENSMODEL_PINHOLE", {k[0], k[1], k[2], k[3]}, lens.width(), lens.height(),
                        lens.cam_from_world());
  if (lens.lensmodel() == "LENSMODEL_PINHOLE") return;
  const int w = lens.width(), h = lens.height();
  Eigen::Matrix3Xd rays(3, static_cast<int64_t>(w) * h);
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x)
      rays.col(static_cast<int64_t>(y) * w + x) << (x - k[2]) / k[0], (y - k[3]) / k[1], 1.0;
  }
  const Eigen::Matrix2Xd pixels = lens.ProjectMany(rays);
  map_x.create(h, w, CV_32FC1);
  map_y.create(h, w, CV_32FC1);
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      map_x.at<float>(y, x) = static_cast<float>(pixels(0, static_cast<int64_t>(y) * w + x));
      map_y.at<float>(y, x) = static_cast<float>(pixels(1, static_cast<int64_t>(y) * w + x));
    }
  }
}

cv::Mat Undistortion::Color(const cv::Mat& image) const {
  if (map_x.empty()) return image;
  cv::Mat out;
  cv::remap(image, out, map_x, map_y, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
  return out;
}

cv::Mat Undistortion::Mask(const cv::Mat& mask) const {
  if (map_x.empty()) return mask;
  cv::Mat out;
  cv::remap(mask, out, map_x, map_y, cv::INTER_NEAREST, cv::BORDER_CONSTANT);
  return out;
}

cv::Mat SubjectMask(const cv::Mat& silhouette) {
  cv::Mat mask;
  cv::dilate(silhouette != 0, mask, cv::Mat(), cv::Point(-1, -1), 3);
  return mask;
}

cv::Mat OverBackground(const RenderedView& view, const cv::Mat& background) {
  cv::Mat out = UnitFloat(view.color);
  if (background.empty()) return out;
  if (background.size() != out.size())
    Fail("a background of ", background.cols, "x", background.rows, " behind a view of ", out.cols,
         "x", out.rows);
  const cv::Mat behind = UnitFloat(background);
  for (int y = 0; y < out.rows; ++y) {
    for (int x = 0; x < out.cols; ++x) {
      const float a = view.alpha.empty() ? 0.0f : view.alpha.at<float>(y, x);
      out.at<cv::Vec3f>(y, x) += (1.0f - a) * behind.at<cv::Vec3f>(y, x);
    }
  }
  return out;
}

void SquaredError::Add(const cv::Mat& picture, const cv::Mat& captured, const cv::Mat& mask) {
  if (picture.size() != captured.size() || picture.size() != mask.size())
    Fail("a picture of ", picture.cols, "x", picture.rows, " scored against an image of ",
         captured.cols, "x", captured.rows, " in a mask of ", mask.cols, "x", mask.rows);
  const cv::Mat a = UnitFloat(picture), b = UnitFloat(captured);
  for (int y = 0; y < a.rows; ++y) {
    for (int x = 0; x < a.cols; ++x) {
      if (mask.at<uint8_t>(y, x) == 0) continue;
      cv::Vec3f d;
      for (int c = 0; c < 3; ++c)
        d[c] = std::clamp(a.at<cv::Vec3f>(y, x)[c], 0.0f, 1.0f) - b.at<cv::Vec3f>(y, x)[c];
      squared += d.dot(d);
      count += 3;
    }
  }
}

double SquaredError::PsnrDb() const {
  if (count == 0) return std::numeric_limits<double>::quiet_NaN();
  const double mse = squared / static_cast<double>(count);
  return mse <= 1e-12 ? 99.0 : -10.0 * std::log10(mse);
}

CameraTruth ReadCameraTruth(const Take& take, const std::string& sensor, const CameraModel& camera,
                            int64_t set, int64_t plate_set) {
  const Undistortion undistortion(camera);
  CameraTruth truth;
  truth.sensor = sensor;
  truth.set = set;
  truth.pinhole = undistortion.pinhole;
  cv::Mat image = Bgr8(take.ReadFrame(static_cast<size_t>(set), sensor));
  if (image.cols != camera.width() || image.rows != camera.height())
    Fail("the image of ", sensor, " in frame set ", set, " is ", image.cols, "x", image.rows,
         ", its camera model ", camera.width(), "x", camera.height());
  cv::Mat silhouette;
  const fs::path gt_mask = take.gt_dir() / "masks" / sensor / (SetName(set) + ".png");
  if (fs::exists(gt_mask)) {
    silhouette = cv::imread(gt_mask.string(), cv::IMREAD_GRAYSCALE);
    truth.silhouette_source = "the simulation's true silhouette (gt/masks)";
  } else if (plate_set >= 0 && plate_set != set) {
    silhouette = ExtractSilhouette(
        image, Bgr8(take.ReadFrame(static_cast<size_t>(plate_set), sensor)), SilhouetteOptions{});
    truth.silhouette_source = "background subtraction against the clean plate";
  } else {
    truth.silhouette_source = "none: the take has no true silhouettes (gt/) and no clean plate";
  }
  truth.image = undistortion.Color(image);
  if (!silhouette.empty()) {
    if (silhouette.size() != image.size()) Fail(gt_mask.string(), " is not the image's size");
    truth.subject = SubjectMask(undistortion.Mask(silhouette));
  }
  return truth;
}

cv::Mat BackgroundInPinhole(const cv::Mat& background, const CameraModel& camera) {
  cv::Mat sized = Bgr8(background);
  if (sized.cols != camera.width() || sized.rows != camera.height())
    cv::resize(sized, sized, cv::Size(camera.width(), camera.height()), 0, 0, cv::INTER_LINEAR);
  return Undistortion(camera).Color(sized);
}

}  // namespace holocap
