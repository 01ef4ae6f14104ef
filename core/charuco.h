// OpenCV's model of a ChArUco board layout, for the code that draws and detects it (which links
// opencv_aruco itself).
#pragma once

#include <opencv2/aruco/charuco.hpp>

#include "core/board.h"

namespace holocap {

// OpenCV's CharucoBoard of a kCharuco layout (its squares, marker side and dictionary), its
// markers numbered from layout.first_id. Throws Error for another board type or a layout that
// does not hold together.
cv::Ptr<cv::aruco::CharucoBoard> MakeCharucoBoard(const BoardLayout& layout);

}  // namespace holocap
