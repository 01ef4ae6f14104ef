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

// Throws Error (one line) unless mrgingham can run on `layout`: a chessboard with as many inner
// corners per row as per column, and the `mrgingham` program on PATH.
void CheckMrginghamFits(const BoardLayout& layout);

// The gridn x gridn inner corners mrgingham finds in `grey` (8-bit), row-major from the corner
// it starts at (its "top-left"), x along a row; false with `reason` when it finds no board. The
// image goes to a temporary PNG, as the tool reads files only.
bool FindChessboardMrgingham(const cv::Mat& grey, int gridn, std::vector<cv::Point2f>* corners,
                             std::string* reason);

// Runs holocap's finder, OpenCV's recipe (findChessboardCorners, then cornerSubPix with an 11 x 11
// window) and mrgingham on every colour view of `take_dir` (`sensors`; empty: all colour
// cameras), and measures, per pair of finders, the corner distances over the corners both found
// (numbered alike up to the turns that leave the board unchanged), and on a simulated take each
// finder's distance to the true corners (gt/cameras and gt/board.json). Returns the JSON that
// goes into report.json as metrics.detector_agreement; `table` gets the printed table.
nlohmann::json CompareChessboardFinders(const std::filesystem::path& take_dir,
                                        const BoardLayout& layout,
                                        const std::vector<std::string>& sensors, int threads,
                                        std::string* table);

}  // namespace holocap
