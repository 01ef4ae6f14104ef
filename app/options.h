// Command-line pieces shared by the subcommands: the take-selection flags (defined once, the
// same on every command that reads a take), lengths, frame ranges, bounds, name lists, and the
// one exit rule of every command.
#pragma once

#include <CLI/CLI.hpp>
#include <Eigen/Core>
#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "core/board.h"
#include "core/check_option.h"
#include "core/output.h"
#include "core/report.h"
#include "core/take_plan.h"

namespace holocap {

struct Box;

// --frames A:B, --clean-plate N, --ground-truth-cameras.
struct TakeSelectionFlags {
  std::string frames;
  int64_t clean_plate = -1;
  bool ground_truth_cameras = false;
  bool no_depth = false;

  TakeSelection Parse() const;  // throws Error naming the flag
};
void AddTakeSelectionFlags(CLI::App* command, TakeSelectionFlags* flags);

// --bounds, --up, --silhouettes, --silhouette-threshold: the scene a command works in, where
// the take's own (from the rig) is not wanted. Recorded in the plan as the user's.
struct SceneFlags {
  std::string bounds;
  std::string up;
  std::string silhouettes = "auto";
  double silhouette_threshold = 0;

  void Apply(TakeSelection* selection) const;  // throws Error naming the flag
};
void AddSceneFlags(CLI::App* command, SceneFlags* flags);

// "+z", "-y", "z" or "x,y,z" (any non-zero direction); throws Error naming `option`.
Eigen::Vector3d ParseUp(const std::string& text, const char* option = "--up");

// "a:b", "a:" or "a" (one frame set), counted after the clean plate, into the selection's
// range; or a list "a-b,c,d-e" (ranges inclusive, as sbatch --array writes them) into its
// frame_list, in increasing order, each set once.
void ParseFrames(const std::string& text, TakeSelection* selection);
// "4mm", "4 mm", "0.4cm", "0.004m" or a bare number of metres; throws Error naming `what`.
double ParseLength(const std::string& text, const char* what);
// A capture volume given as "xmin,ymin,zmin,xmax,ymax,zmax" (metres); throws Error naming
// `option` when it is not six numbers with max above min on every axis.
Box ParseBounds(const std::string& text, const char* option = "--bounds");
// How an AprilTag board is printed: "holocap" (libapriltag's one-bit tag borders, as holocap
// board prints) or "kalibr" (Kalibr's kalibr_create_target_pdf: two-bit borders and black
// squares at the tags' corners) into layout->border_bits; "" leaves the layout's. Throws Error
// naming `option` for another name or a board that is no tag36h11 AprilTag board.
void ApplyBoardPrint(const std::string& print, const char* option, BoardLayout* layout);

// Option errors name the flag the user typed. An OptionError (core/check_option.h) names a
// field; the flag that fills it is the one `command`'s table gives (NameFieldFlags), else the
// one every command that has it shares (the take selection's --frames and --clean-plate,
// --shard), else the field's name (kl_weight: --kl-weight), else its name without a unit
// (gate_m: --gate, voxel_m: --voxel, start_lead_s: --start-lead).
//
// NameFieldFlags adds to `command`'s table: keys are "Options::field" or "field" as the error
// names them, values the flag; "" where no flag of the command fills a field of that name.
void NameFieldFlags(CLI::App* command, const std::map<std::string, std::string>& flag_of_field);
// The flag of `command` that fills the field `error` names, when the user gave it; else "".
std::string FlagOfField(const CLI::App& command, const OptionError& error);
// The error line: "--kl-weight -1 violates kl_weight >= 0" (the flag and what the user typed
// after it) where FlagOfField finds a flag, else the error's own message.
std::string OptionErrorMessage(const CLI::App& command, const OptionError& error);

// --overwrite on a command that writes results: write into a non-empty output another command
// made, or replace an output file (core/output.h; nothing is removed, no input is written).
void AddOverwriteFlag(CLI::App* command, bool* overwrite);

// The one exit rule (core/report.h): prints "STATE: message", and for a state that is not
// usable ends the command with one `holocap: error:` line (exit status 1).
void EndCommand(const Summary& summary, const std::string& what);
// The same rule for a command that printed its state line itself.
void FailUnlessUsable(const Summary& summary, const std::string& what);

}  // namespace holocap
