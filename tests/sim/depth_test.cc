// Depth sensors: noise sigma(z) = k z^2 on top of millimetre quantisation, and no measurement
// at grazing incidence and next to depth jumps.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <limits>

#include "sim/render.h"

namespace holocap::sim {
namespace {

DepthRender Plane(int width, int height, double z, double cos_incidence) {
  DepthRender truth;
  truth.z = cv::Mat(height, width, CV_32F, cv::Scalar(z));
  truth.cos_incidence = cv::Mat(height, width, CV_32F, cv::Scalar(cos_incidence));
  truth.mask = cv::Mat::zeros(height, width, CV_8U);
  return truth;
}

TEST(DepthSensorTest, NoiseFollowsKZSquared) {
  DepthSensorModel model;
  for (double z : {1.0, 2.5, 4.0}) {
    const cv::Mat depth = MeasureDepth(Plane(200, 200, z, 1.0), model, 11);
    double sum = 0, sum_squares = 0;
    int n = 0;
    for (int y = 0; y < depth.rows; ++y) {
      for (int x = 0; x < depth.cols; ++x) {
        const double d = depth.at<float>(y, x);
        ASSERT_TRUE(std::isfinite(d));
        // Z16: whole millimetres.
        ASSERT_NEAR(d * 1000, std::round(d * 1000), 1e-3);
        sum += d - z;
        sum_squares += (d - z) * (d - z);
        ++n;
      }
    }
    const double mean = sum / n;
    const double sigma = std::sqrt(sum_squares / n - mean * mean);
    const double expected = std::sqrt(std::pow(model.noise_k * z * z, 2) + 1e-6 / 12);
    std::printf("z %.1f m: measured sigma %.3f mm, model %.3f mm (k = %.4f /m), bias %.3f mm\n", z,
                sigma * 1000, expected * 1000, model.noise_k, mean * 1000);
    EXPECT_NEAR(sigma / expected, 1.0, 0.03);
    EXPECT_LT(std::abs(mean), 3 * expected / std::sqrt(n) + 1e-5);
  }
}

TEST(DepthSensorTest, GrazingIncidenceRangeAndEdgesGiveNoMeasurement) {
  DepthSensorModel model;
  const double limit = std::cos(model.max_incidence_deg * M_PI / 180);
  EXPECT_EQ(cv::countNonZero(MeasureDepth(Plane(20, 20, 2.0, limit * 1.01), model, 1) ==
                             MeasureDepth(Plane(20, 20, 2.0, limit * 1.01), model, 1)),
            400);  // all valid (NaN != NaN would drop them)
  EXPECT_EQ(cv::countNonZero(MeasureDepth(Plane(20, 20, 2.0, limit * 0.99), model, 1) ==
                             MeasureDepth(Plane(20, 20, 2.0, limit * 0.99), model, 1)),
            0);
  EXPECT_EQ(cv::countNonZero(MeasureDepth(Plane(20, 20, model.max_m + 0.1, 1), model, 1) ==
                             MeasureDepth(Plane(20, 20, model.max_m + 0.1, 1), model, 1)),
            0);

  // A step from 1.5 m to 2.5 m at column 10: the two columns beside the step are lost.
  DepthRender step = Plane(20, 10, 1.5, 1.0);
  step.z.colRange(10, 20).setTo(2.5);
  const cv::Mat depth = MeasureDepth(step, model, 2);
  for (int y = 0; y < 10; ++y) {
    for (int x = 0; x < 20; ++x) {
      EXPECT_EQ(std::isnan(depth.at<float>(y, x)), x == 9 || x == 10) << x << "," << y;
    }
  }

  DepthSensorModel holes = model;
  holes.dropout_probability = 0.2;
  const cv::Mat holed = MeasureDepth(Plane(100, 100, 2.0, 1.0), holes, 3);
  const double missing = 1.0 - cv::countNonZero(holed == holed) / 1e4;
  EXPECT_NEAR(missing, 0.2, 0.03);
}

}  // namespace
}  // namespace holocap::sim
