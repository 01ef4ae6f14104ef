// Silhouettes by background subtraction against a clean plate, by thresholding a bright
// subject on a dark background (at a given level or one chosen per image by Otsu's method), or
// from the frames' own alpha channel.
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <array>
#include <cmath>

#include "core/check_option.h"
#include "core/error.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

void SilhouetteOptions::Check() const {
  HOLOCAP_CHECK_OPTION_GT(noise_sigmas, 0);
  HOLOCAP_CHECK_OPTION_GE(min_difference, 0);
  HOLOCAP_CHECK_OPTION_LT(min_difference, 255, "DN");
  HOLOCAP_CHECK_OPTION_GE(hysteresis_sigmas, 0);
  HOLOCAP_CHECK_OPTION_LT(hysteresis_sigmas, 100);
  HOLOCAP_CHECK_OPTION_GE(hysteresis_min_difference, 0);
  HOLOCAP_CHECK_OPTION_LT(hysteresis_min_difference, 255, "DN");
  HOLOCAP_CHECK_OPTION_GT(threshold, 0);
  HOLOCAP_CHECK_OPTION_LT(threshold, 1);
  HOLOCAP_CHECK_OPTION_IN(open_px, 0, 50);
  HOLOCAP_CHECK_OPTION_IN(dilate_px, 0, 50);
  HOLOCAP_CHECK_OPTION_IN(erode_px, 0, 50);
  HOLOCAP_CHECK_OPTION_GE(morphology_width, 0);
  HOLOCAP_CHECK_OPTION_GE(min_component_fraction, 0);
  HOLOCAP_CHECK_OPTION_LT(min_component_fraction, 1);
}

namespace {

cv::Mat Disk(int radius) {
  return cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * radius + 1, 2 * radius + 1));
}

// Largest colour channel of an 8-bit image (alpha left out), or the image itself when
// single-channel.
// The median plus four robust deviations (1.4826 median absolute deviations) of the 8-bit
// pixels at or below `level`: the brightest a background pixel of that class is likely to be.
double DarkClassCeiling(const cv::Mat& grey, double level) {
  std::array<int64_t, 256> histogram{};
  int64_t count = 0;
  for (int y = 0; y < grey.rows; ++y) {
    const uint8_t* row = grey.ptr<uint8_t>(y);
    for (int x = 0; x < grey.cols; ++x) {
      if (row[x] > level) continue;
      ++histogram[row[x]];
      ++count;
    }
  }
  if (count == 0) return 0;
  const auto median_of = [&](const std::array<int64_t, 256>& h) {
    int64_t seen = 0;
    for (int v = 0; v < 256; ++v) {
      seen += h[v];
      if (2 * seen > count) return v;
    }
    return 255;
  };
  const int median = median_of(histogram);
  std::array<int64_t, 256> deviations{};
  for (int v = 0; v < 256; ++v) deviations[std::abs(v - median)] += histogram[v];
  return median + 4 * 1.4826 * median_of(deviations);
}

cv::Mat MaxChannel(const cv::Mat& image) {
  if (image.channels() == 1) return image;
  std::vector<cv::Mat> channels;
  cv::split(image, channels);
  cv::Mat out = channels[0];
  for (size_t c = 1; c < std::min<size_t>(channels.size(), 3); ++c) cv::max(out, channels[c], out);
  return out;
}

// Weak pixels join `mask` where a connected path of weak pixels reaches it.
void JoinConnected(cv::Mat weak, cv::Mat* mask) {
  weak |= *mask;
  cv::Mat labels;
  const int count = cv::connectedComponents(weak, labels, 8, CV_32S);
  std::vector<uint8_t> seeded(count, 0);
  for (int y = 0; y < mask->rows; ++y) {
    const uint8_t* m = mask->ptr<uint8_t>(y);
    const int* label = labels.ptr<int>(y);
    for (int x = 0; x < mask->cols; ++x) seeded[label[x]] |= m[x] != 0;
  }
  seeded[0] = 0;
  for (int y = 0; y < mask->rows; ++y) {
    uint8_t* m = mask->ptr<uint8_t>(y);
    const int* label = labels.ptr<int>(y);
    for (int x = 0; x < mask->cols; ++x) m[x] = seeded[label[x]] ? 255 : 0;
  }
}

}  // namespace

cv::Mat ExtractSilhouette(const cv::Mat& image, const cv::Mat& clean_plate,
                          const SilhouetteOptions& options) {
  options.Check();
  if (image.empty()) Fail("silhouette: empty image");
  if (image.depth() != CV_8U) Fail("silhouette: image must be 8-bit");
  cv::Mat mask;
  if (options.mode == SilhouetteMode::kAlpha) {
    if (image.channels() != 4) Fail("silhouette: alpha mode needs a 4-channel (BGRA) image");
    cv::extractChannel(image, mask, 3);
    cv::threshold(mask, mask, 127, 255, cv::THRESH_BINARY);
    return mask;
  }
  if (options.mode == SilhouetteMode::kThreshold) {
    cv::threshold(MaxChannel(image), mask, options.threshold * 255, 255, cv::THRESH_BINARY);
  } else if (options.mode == SilhouetteMode::kOtsu) {
    // Otsu's level splits the subject's lit side from its shaded side as readily as the subject
    // from the background: pixels above half of it join where connected to pixels above it,
    // unless they could be background: the weak level stays 4 robust deviations above the
    // darker class's median (on a dim room the floor a subject stands on would join; on
    // Middlebury's black cloth the rule never bites).
    const cv::Mat brightest = MaxChannel(image).clone();
    const double level =
        cv::threshold(brightest, mask, 0, 255, cv::THRESH_BINARY | cv::THRESH_OTSU);
    if (options.hysteresis_sigmas > 0) {
      const double weak_level =
          std::min(level, std::max(0.5 * level, DarkClassCeiling(brightest, level)));
      cv::Mat weak;
      cv::threshold(brightest, weak, weak_level, 255, cv::THRESH_BINARY);
      JoinConnected(weak, &mask);
    }
  } else {
    if (clean_plate.empty()) Fail("silhouette: background subtraction needs a clean plate");
    if (clean_plate.size() != image.size() || clean_plate.type() != image.type()) {
      Fail("silhouette: clean plate is ", clean_plate.cols, "x", clean_plate.rows,
           " but the image is ", image.cols, "x", image.rows, " (or their types differ)");
    }
    // Euclidean rather than the largest channel: skin against a brown wall differs a little
    // in every channel, and only their sum stands out of the noise.
    cv::Mat difference;
    {
      cv::Mat a, b, squared;
      image.convertTo(a, CV_32F);
      clean_plate.convertTo(b, CV_32F);
      if (image.channels() == 4) {  // colour only: alpha is not what the plate is compared on
        cv::cvtColor(a, a, cv::COLOR_BGRA2BGR);
        cv::cvtColor(b, b, cv::COLOR_BGRA2BGR);
      }
      cv::Mat delta = a - b;
      cv::multiply(delta, delta, squared);
      squared = squared.reshape(1, static_cast<int>(squared.total()));
      cv::reduce(squared, squared, 1, cv::REDUCE_SUM);
      cv::sqrt(squared.reshape(1, image.rows), difference);
    }
    // Robust noise: most pixels are background, so the median distance is noise (a histogram
    // of 0.25 DN bins finds it in one pass).
    constexpr int kBins = 2048;
    constexpr float kBinsPerDn = 4;
    std::vector<int64_t> histogram(kBins, 0);
    for (int y = 0; y < difference.rows; ++y) {
      const float* row = difference.ptr<float>(y);
      for (int x = 0; x < difference.cols; ++x)
        ++histogram[std::min(kBins - 1, static_cast<int>(row[x] * kBinsPerDn))];
    }
    int64_t half = static_cast<int64_t>(difference.total()) / 2, seen = 0;
    int median = 0;
    for (; median < kBins - 1; ++median) {
      seen += histogram[median];
      if (seen > half) break;
    }
    // 1.4826 x median is the usual MAD scale; for a distance over three noisy channels (a chi
    // distribution) it errs high, which keeps the thresholds above the noise.
    const double sigma = 1.4826 * std::max((median + 0.5) / kBinsPerDn, 1.0);
    const double strong = std::max(options.min_difference, options.noise_sigmas * sigma);
    cv::threshold(difference, mask, strong, 255, cv::THRESH_BINARY);
    mask.convertTo(mask, CV_8U);
    if (options.hysteresis_sigmas > 0) {
      // Specks are opened away before they can seed a region; weak pixels join only through a
      // connected path to what remains.
      if (options.open_px > 0) cv::morphologyEx(mask, mask, cv::MORPH_OPEN, Disk(options.open_px));
      const double weak_threshold = std::min(
          strong, std::max(options.hysteresis_min_difference, options.hysteresis_sigmas * sigma));
      cv::Mat weak;
      cv::threshold(difference, weak, weak_threshold, 255, cv::THRESH_BINARY);
      weak.convertTo(weak, CV_8U);
      JoinConnected(weak, &mask);
    }
  }
  const double scale =
      options.morphology_width > 0 ? static_cast<double>(image.cols) / options.morphology_width : 1;
  const auto radius = [scale](int px) { return static_cast<int>(std::lround(px * scale)); };
  if (radius(options.open_px) > 0)
    cv::morphologyEx(mask, mask, cv::MORPH_OPEN, Disk(radius(options.open_px)));
  if (radius(options.dilate_px) > 0) cv::dilate(mask, mask, Disk(radius(options.dilate_px)));
  if (radius(options.erode_px) > 0) cv::erode(mask, mask, Disk(radius(options.erode_px)));
  if (options.min_component_fraction > 0) {
    cv::Mat labels, stats, centroids;
    int count = cv::connectedComponentsWithStats(mask, labels, stats, centroids, 8, CV_32S);
    const double min_area = options.min_component_fraction * static_cast<double>(mask.total());
    std::vector<uint8_t> keep(count, 0);
    for (int i = 1; i < count; ++i) keep[i] = stats.at<int>(i, cv::CC_STAT_AREA) >= min_area;
    for (int y = 0; y < mask.rows; ++y) {
      const int* label = labels.ptr<int>(y);
      uint8_t* row = mask.ptr<uint8_t>(y);
      for (int x = 0; x < mask.cols; ++x) row[x] = keep[label[x]] ? 255 : 0;
    }
  }
  return mask;
}

cv::Mat TemporalMedian(const std::vector<cv::Mat>& frames) {
  if (frames.empty()) Fail("temporal median: no frames");
  const cv::Mat& first = frames.front();
  if (first.depth() != CV_8U) Fail("temporal median: frames must be 8-bit");
  for (const cv::Mat& frame : frames) {
    if (frame.size() != first.size() || frame.type() != first.type())
      Fail("temporal median: frames differ in size or type");
  }
  cv::Mat median(first.size(), first.type());
  const int values_per_row = first.cols * first.channels();
  const size_t middle = frames.size() / 2;
  std::vector<uint8_t> values(frames.size());
  for (int y = 0; y < first.rows; ++y) {
    std::vector<const uint8_t*> rows;
    for (const cv::Mat& frame : frames) rows.push_back(frame.ptr<uint8_t>(y));
    uint8_t* out = median.ptr<uint8_t>(y);
    for (int i = 0; i < values_per_row; ++i) {
      for (size_t f = 0; f < frames.size(); ++f) values[f] = rows[f][i];
      std::nth_element(values.begin(), values.begin() + middle, values.end());
      out[i] = values[middle];
    }
  }
  return median;
}

double MaskIoU(const cv::Mat& a, const cv::Mat& b) {
  if (a.size() != b.size()) Fail("MaskIoU: masks differ in size");
  cv::Mat ba = a != 0, bb = b != 0;
  double inter = cv::countNonZero(ba & bb), uni = cv::countNonZero(ba | bb);
  return uni == 0 ? 1.0 : inter / uni;
}

}  // namespace holocap
