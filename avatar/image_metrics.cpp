#include "avatar/image_metrics.h"

#include <cmath>
#include <cstdint>
#include <limits>
#include <opencv2/imgproc.hpp>
#include <vector>

#include "core/error.h"

namespace holocap {

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
