// Scores against the camera: a picture drawn through a capture camera (a held-out one, never
// trained on nor reconstructed from) against the image that camera captured, inside the
// subject's silhouette, in the pinhole of the camera's intrinsics core (where the web player
// draws). Training, `holocap export web` and the benchmarks score with it.
#pragma once

#include <cstdint>
#include <opencv2/core.hpp>
#include <string>

#include "avatar/avatar.h"
#include "core/camera.h"

namespace holocap {

class Take;

// The pinhole of a lens's intrinsics core (fx, fy, cx, cy; same pose and size) and the maps that
// resample the lens's images into it.
struct Undistortion {
  CameraModel pinhole;
  cv::Mat map_x, map_y;  // empty for a pinhole lens: its images are already there

  explicit Undistortion(const CameraModel& lens);
  cv::Mat Color(const cv::Mat& image) const;  // bilinear
  cv::Mat Mask(const cv::Mat& mask) const;    // nearest, zero outside the lens's image
};

// The subject's pixels of a silhouette (non-zero: the subject), grown by 3 pixels as training
// scores its held-out views: a picture's subject may reach a little past the silhouette's edge.
cv::Mat SubjectMask(const cv::Mat& silhouette);

// A view's premultiplied colour over `background` (8-bit or float BGR in [0, 1] at the view's
// size; empty: black): CV_32FC3, colour + (1 - alpha) background.
cv::Mat OverBackground(const RenderedView& view, const cv::Mat& background);

// The squared colour differences (each channel, 0..1) of a picture against a captured image
// inside a mask, and how many values they sum; PSNR from their mean.
struct SquaredError {
  double squared = 0;
  int64_t count = 0;  // values: pixels x 3
  void Add(const cv::Mat& picture, const cv::Mat& captured, const cv::Mat& mask);
  double PsnrDb() const;  // 99 for no difference; NaN without a value
};

// What capture camera `sensor` saw at frame set `set` of `take`, in its pinhole core.
struct CameraTruth {
  std::string sensor;
  int64_t set = 0;
  CameraModel pinhole;            // the camera's pinhole core
  cv::Mat image;                  // CV_8UC3 BGR, resampled into the pinhole core
  cv::Mat subject;                // CV_8UC1 SubjectMask of its silhouette; empty: none known
  std::string silhouette_source;  // where the silhouette came from, or why there is none
};

// Reads the camera's image of `set` and its silhouette: the simulation's true one
// (gt/masks/<sensor>/<set>.png) where the take has it (truth that only measures), else the
// take's own, background subtraction against its clean plate (frame set `plate_set`, -1: none);
// without either, `subject` is left empty and `silhouette_source` says why. `camera` is the
// sensor's model as the run uses it (calib/ or gt/cameras).
CameraTruth ReadCameraTruth(const Take& take, const std::string& sensor, const CameraModel& camera,
                            int64_t set, int64_t plate_set);

// A background image for `camera` (any size of the same aspect, in the lens's own geometry, as
// a model's backgrounds/<camera>.png or a clean plate are) resized to the camera and resampled
// into its pinhole core: CV_8UC3 BGR.
cv::Mat BackgroundInPinhole(const cv::Mat& background, const CameraModel& camera);

}  // namespace holocap
