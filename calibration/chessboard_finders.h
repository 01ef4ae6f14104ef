// Chessboard finders besides holocap's own (OpenCV's findChessboardCorners, then corners refined
// on the image edges): mrcal's finder `mrgingham`, run as its command-line tool, and a check of
// how well the finders agree on the same images.
#pragma once

#include <filesystem>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "calibration/calibration.h"
#include "core/board.h"

namespace holocap {

// Why mrgingham cannot run on `layout` (one line): not a chessboard, a chessboard with unequal
// sides, or no `mrgingham` program on PATH; empty when it can.
std::string WhyMrginghamCannotRun(const BoardLayout& layout);
// Throws Error (one line, `flag` first) unless mrgingham can run on `layout`.
void CheckMrginghamFits(const BoardLayout& layout, const std::string& flag);

// The gridn x gridn inner corners mrgingham finds in `grey` (8-bit), row-major from the corner
// it starts at (its "top-left"), x along a row; false with `reason` when it finds no board. The
// image goes to a temporary PNG, as the tool reads files only.
bool FindChessboardMrgingham(const cv::Mat& grey, int gridn, std::vector<cv::Point2f>* corners,
                             std::string* reason);

// Throws Error (one line) unless CompareBoardDetectors can compare detectors of `layout`: an
// AprilTag board has one detector (libapriltag).
void CheckDetectorsComparable(const BoardLayout& layout);

// Runs every detector that reads `layout` on every colour view of `take_dir` (`sensors`; empty:
// all colour cameras): for a chessboard holocap's finder, OpenCV's recipe (findChessboardCorners,
// then cornerSubPix with an 11 x 11 window) and mrgingham where it can run (a square grid, the
// program on PATH); for a ChArUco board holocap's detector and OpenCV's own (detectMarkers, then
// interpolateCornersCharuco). Measures, per pair of detectors, the corner distances over the
// corners both found (a chessboard's numbered alike up to the turns that leave the board
// unchanged; a ChArUco board's by their ids), and on a simulated take each detector's distance
// to the true corners (gt/cameras and gt/board.json). Returns the JSON that goes into
// report.json as metrics.detector_agreement (a detector that cannot read the board under
// "left_out", with why); `table` gets the printed table. Throws as CheckDetectorsComparable.
nlohmann::json CompareBoardDetectors(const std::filesystem::path& take_dir,
                                     const BoardLayout& layout,
                                     const std::vector<std::string>& sensors, int threads,
                                     std::string* table);

}  // namespace holocap
