// holocap sim: record a take on the simulated rig, with exact ground truth in gt/.
#include <cstdio>
#include <iostream>

#include "app/commands.h"
#include "app/options.h"
#include "core/error.h"
#include "sim/sim.h"

namespace holocap {

namespace {

struct SimArgs {
  SimOptions options;
  std::string out;
  std::string size;
  bool board = false;
  bool no_noise = false;
};

void ParseSize(const std::string& text, int* width, int* height) {
  if (text.empty()) return;
  int w = 0, h = 0;
  char tail = 0;
  int parsed = std::sscanf(text.c_str(), "%dx%d%c", &w, &h, &tail);
  if (parsed == 1 && w > 0) {
    *width = w;
    *height = 0;
    return;
  }
  if (parsed != 2 || w <= 0 || h <= 0)
    Fail("--size must be WIDTH or WIDTHxHEIGHT, got '", text, "'");
  *width = w;
  *height = h;
}

}  // namespace

static void AddSimCommand(CLI::App& app) {
  auto* command = app.add_subcommand(
      "sim", "Record a take on the simulated rig (exact lenses, poses, clocks and ground truth)");
  auto args = std::make_shared<SimArgs>();
  SimOptions& o = args->options;
  command->add_option("--rig", o.rig, "studio8, single-rgbd, or a rig file (YAML/JSON)")
      ->capture_default_str();
  command->add_option("--frames", o.frames, "Frame sets to record")->capture_default_str();
  command->add_option("--out", args->out, "The take directory to create")->required();
  command->add_flag("--board", args->board,
                    "Film the calibration board sequence (same as --scene board)");
  command->add_option("--scene", o.scene, "subject (walking humanoid), object (static) or board")
      ->capture_default_str();
  command->add_option("--seed", o.seed, "Seed of board poses, clocks, noise and drops")
      ->capture_default_str();
  command->add_option("--size", args->size,
                      "Render every sensor at WIDTH or WIDTHxHEIGHT (lenses rescaled)");
  command->add_option("--fps", o.fps, "Frame sets per second (0: the rig's)")
      ->capture_default_str();
  command
      ->add_option("--clean-plate", o.clean_plate_frames, "Leading frame sets without the subject")
      ->capture_default_str();
  command->add_option("--drop", o.drop_probability, "Chance that a sensor drops a frame")
      ->capture_default_str();
  command->add_flag("--no-noise", args->no_noise, "Noise-free, deterministic frames");
  command->add_flag("--motion-blur", o.motion_blur, "Integrate the motion over each exposure");
  command->add_option("--threads", o.threads, "Render threads (0: all cores)")
      ->capture_default_str();
  command->add_flag("--overwrite", o.overwrite, "Replace an existing take directory");
  command->callback([args] {
    SimOptions options = args->options;
    if (args->board) options.scene = "board";
    if (args->no_noise) options.noise = false;
    ParseSize(args->size, &options.image_width, &options.image_height);
    Report report("sim");
    SimSummary summary = SimulateTake(options, args->out, &report);
    report.Write(std::filesystem::path(args->out) / "report.json");
    std::printf("%s: %lld frame sets (%lld frames, %lld dropped) in %.1f s, %.1f frame sets/min\n",
                ToString(summary.termination), static_cast<long long>(summary.frame_sets),
                static_cast<long long>(summary.frames_written),
                static_cast<long long>(summary.frames_dropped), summary.seconds,
                summary.frame_sets_per_minute);
    FailUnlessUsable(summary, "simulation");
  });
}

HOLOCAP_COMMAND(10, AddSimCommand);

}  // namespace holocap
