// Image quality of a rendered picture against a reference (a captured image): the one
// implementation that training, the web export and the benchmarks score with.
#pragma once

#include <opencv2/core.hpp>

namespace holocap {

// Image quality, on 8-bit or float images of one size and type (float: range [0, 1]).
double PsnrDb(const cv::Mat& image, const cv::Mat& reference, const cv::Mat& mask = {});
double Ssim(const cv::Mat& image, const cv::Mat& reference);

}  // namespace holocap
