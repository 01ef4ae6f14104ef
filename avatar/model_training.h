// Whether a model directory's training finished, for the stages that play models back.
#pragma once

#include <filesystem>
#include <string>

#include "avatar/avatar.h"
#include "core/report.h"

namespace holocap {

// How the training that wrote a model directory ended, from its report.json (and, for a
// per-frame run, its frame records: a run whose frames are not all done is FAILURE): a run
// killed or failed part way (FAILURE, e.g. "the run is incomplete: 3 of 5 frame sets complete")
// or whose result its own checks refuted (DEGENERATE) leaves a model that is not the one asked
// for. So does one whose model.json a later, failed run rewrote after the good report. A
// directory without a report.json (a model written through the library, or by hand) is taken as
// it is: a holocap training writes its model.json only as it ends, just before its report.
struct ModelTraining {
  bool reported = false;  // the directory holds a report.json (every holocap training writes one)
  Termination termination = Termination::kFailure;  // when reported
  std::string message;                              // when reported
  bool finished() const { return !reported || IsUsable(termination); }
  // "TERMINATION: message", or that no report was found.
  std::string Describe() const;
};
// Throws Error for a report.json that does not parse as a report.
ModelTraining ReadModelTraining(const std::filesystem::path& dir);

// For playback (render, export web): throws Error (one line naming the model's state and
// `flag`) when the model's training did not finish (ModelTraining::finished() false) and
// `allow_partial` is false (the user did not give `flag`). Returns what was used for the caller's
// plan and report when an unfinished model is allowed; empty for a finished one.
std::string RequireFinishedModel(const std::filesystem::path& dir, bool allow_partial,
                                 const std::string& flag);

}  // namespace holocap
