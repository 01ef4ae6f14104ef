// Command-line pieces shared by the subcommands: the take-selection flags (defined once, the
// same on every command that reads a take), lengths, frame ranges, bounds, name lists, and the
// one exit rule of every command.
#pragma once

#include <CLI/CLI.hpp>
#include <Eigen/Core>
#include <cstdint>
#include <functional>
#include <map>
#include <string>
#include <vector>

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

// Runs `check` (an Options::Check()); an Error whose message begins with a field name in
// `flag_of_field` is rethrown beginning with the flag the user typed instead.
void CheckNamingFlags(const std::function<void()>& check,
                      const std::map<std::string, std::string>& flag_of_field);

// --overwrite on a command that writes results: write into a non-empty output another command
// made, or replace an output file (core/output.h; nothing is removed, no input is written).
void AddOverwriteFlag(CLI::App* command, bool* overwrite);

// The one exit rule (core/report.h): prints "STATE: message", and for a state that is not
// usable ends the command with one `holocap: error:` line (exit status 1).
void EndCommand(const Summary& summary, const std::string& what);
// The same rule for a command that printed its state line itself.
void FailUnlessUsable(const Summary& summary, const std::string& what);

}  // namespace holocap
