// A simulated take calibrated as a user calibrates a studio: a board take of the same rig,
// solved with mrcal, its models given to the take (`holocap calibrate TAKE --from BOARD`). The
// benches that publish figures run on such takes; the truth (gt/) only scores them.
#pragma once

#include <cmath>
#include <filesystem>
#include <string>

#include "calibration/calibration.h"
#include "core/error.h"
#include "core/report.h"
#include "sim/sim.h"

namespace holocap::bench {

// Simulates the board take `board_sim` into `board` and calibrates it, unless it is calibrated
// already; returns the calibration's line. Throws Error when it is not usable.
inline std::string CalibrateBoardTake(const SimOptions& board_sim,
                                      const std::filesystem::path& board) {
  if (std::filesystem::exists(board / "calib" / "report.json")) return "calibrated before";
  SimulateTake(board_sim, board);
  TakeCalibrationOptions options;
  options.pictures = false;
  const TakeCalibrationSummary calibrated = CalibrateTake(board, options);
  if (!calibrated.IsUsable())
    Fail("the board take '", board.string(), "' did not calibrate: ", calibrated.message);
  return Cat(ToString(calibrated.termination), ", ", calibrated.calibration.rms_reprojection_px,
             " px RMS, world: ", calibrated.world_frame);
}

// Simulates the board take of `take_sim`'s rig beside `take` (TAKE-board/, reused when it is
// already calibrated), at `board_width` px wide (the lens scaled from there to the take's own
// size), calibrates it and gives its models to `take`. Returns the calibration's message;
// throws Error when it is not usable.
inline std::string CalibrateFromBoardTake(const SimOptions& take_sim,
                                          const std::filesystem::path& take,
                                          int board_width = 640) {
  const std::filesystem::path board = take.string() + "-board";
  SimOptions sim;
  sim.rig = take_sim.rig;
  sim.scene = "board";
  sim.frames = 48;
  sim.seed = take_sim.seed;
  sim.world_scale = take_sim.world_scale;
  sim.up = take_sim.up;
  sim.color_only = take_sim.color_only;
  sim.image_width = board_width;
  if (take_sim.image_width > 0 && take_sim.image_height > 0) {
    sim.image_height = static_cast<int>(std::lround(static_cast<double>(take_sim.image_height) *
                                                    board_width / take_sim.image_width));
  }
  sim.overwrite = true;
  CalibrateBoardTake(sim, board);
  return AdoptCalibration(take, board).message;
}

}  // namespace holocap::bench
