// holocap sim: record a take on the simulated rig, with exact ground truth in gt/.
#include <algorithm>
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
  std::string up;
  std::string board_layout;
  std::string board_print;
  bool board = false;
  bool no_noise = false;
  bool dark = false;
};

// --dark: a dark object (its albedo halved) before a near-black backdrop (a tenth), as a
// studio's black cloth: a fixed threshold cuts the subject's darker parts.
constexpr double kDarkSubjectAlbedo = 0.5;
constexpr double kDarkBackgroundAlbedo = 0.1;

// The variants of a capture a user brings (see sim/sim.h, "Variants").
void AddVariantFlags(CLI::App* command, SimArgs* args) {
  SimOptions& o = args->options;
  command
      ->add_option("--world-scale", o.world_scale,
                   "Scale the whole world (rig, subject, room, depth); 0.05: a 9 cm subject")
      ->capture_default_str();
  command->add_option("--up", args->up, "The take's up axis: +z, -y, ... or x,y,z (default +z)");
  command->add_flag("--color-only", o.color_only, "Leave the rig's depth sensors out");
  command->add_option("--subject-albedo", o.subject_albedo, "Multiplies the subject's albedo")
      ->capture_default_str();
  command->add_option("--background-albedo", o.background_albedo, "Multiplies the room's albedo")
      ->capture_default_str();
  command->add_flag("--dark", args->dark,
                    "A dark subject on a near-black backdrop (--subject-albedo 0.5 "
                    "--background-albedo 0.1)");
  command->add_flag("--alpha", o.alpha,
                    "Colour streams as bgra8 with the true silhouette in alpha");
}

// WIDTH or WIDTHxHEIGHT, each a whole decimal number of pixels (1e9 or 64.5 is refused, not
// read as its first digits).
void ParseSize(const std::string& text, int* width, int* height) {
  if (text.empty()) return;
  const auto whole = [&](const std::string& part) {
    if (part.empty() || part.size() > 6 ||
        !std::all_of(part.begin(), part.end(), [](char c) { return c >= '0' && c <= '9'; }))
      Fail("--size must be WIDTH or WIDTHxHEIGHT in whole pixels (at most 999999), got '", text,
           "'");
    return std::stoi(part);
  };
  const size_t x = text.find('x');
  const int w = whole(text.substr(0, x));
  const int h = x == std::string::npos ? 0 : whole(text.substr(x + 1));
  if (w <= 0 || (x != std::string::npos && h <= 0))
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
  command
      ->add_option("--rig", o.rig,
                   "studio8, single-rgbd, sphereN (N colour cameras on a sphere around the object "
                   "scene, e.g. sphere100), or a rig file (YAML/JSON)")
      ->capture_default_str();
  command->add_option("--frames", o.frames, "Frame sets to record")->capture_default_str();
  command->add_option("--out", args->out, "The take directory to create")->required();
  command->add_flag("--board", args->board,
                    "Film the calibration board sequence (same as --scene board)");
  command->add_option("--scene", o.scene, "subject (walking humanoid), object (static) or board")
      ->capture_default_str();
  command->add_option("--board-layout", args->board_layout,
                      "The board scene's board: a layout YAML as holocap board prints (e.g. a "
                      "square chessboard, a ChArUco board, Kalibr's aprilgrid YAML); default: the "
                      "5x4 AprilTag board");
  command->add_option("--board-print", args->board_print,
                      "How the board scene's tag36h11 board is printed: holocap (libapriltag's "
                      "one-bit tag borders) or kalibr (kalibr_create_target_pdf's two-bit borders "
                      "and black squares at the tags' corners); default: the layout's");
  command->add_flag("--board-still", o.board_still,
                    "The board never moves: every frame set shows the first pose cam0 and cam1 "
                    "share (no lens can be calibrated from it)");
  command
      ->add_option("--board-partial", o.board_partial,
                   "Share (0..1) of the single-camera board views whose board reaches past the "
                   "image's edge (35-85 % of its grid points in view)")
      ->capture_default_str();
  command
      ->add_option("--upside-down", o.upside_down,
                   "Sensors mounted upside down (turned 180 degrees about their optical axes), "
                   "comma-separated")
      ->delimiter(',');
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
  command
      ->add_option("--trajectory", o.trajectory,
                   "Sensor motion: fixed, orbit (circle the subject), handheld (walk around it "
                   "with shake and motion blur) or turn (the subject turns before the sensors); "
                   "true poses in gt/trajectory/")
      ->capture_default_str();
  command
      ->add_option("--trajectory-speed", o.trajectory_deg_per_s,
                   "Degrees per second around the subject (orbit, handheld, turn)")
      ->capture_default_str();
  command->add_option("--threads", o.threads, "Render threads (0: all cores)")
      ->capture_default_str();
  command->add_flag("--overwrite", o.overwrite, "Replace an existing take directory");
  AddVariantFlags(command, args.get());
  NameFieldFlags(command, {{"image_width", "--size"},
                           {"image_height", "--size"},
                           {"clean_plate_frames", "--clean-plate"},
                           {"drop_probability", "--drop"},
                           {"trajectory_deg_per_s", "--trajectory-speed"}});
  command->callback([args] {
    SimOptions options = args->options;
    if (args->board) options.scene = "board";
    if (!args->board_layout.empty()) options.board = BoardLayout::Load(args->board_layout);
    ApplyBoardPrint(args->board_print, "--board-print", &options.board);
    if (args->no_noise) options.noise = false;
    if (!args->up.empty()) options.up = ParseUp(args->up);
    if (args->dark) {
      options.subject_albedo = kDarkSubjectAlbedo;
      options.background_albedo = kDarkBackgroundAlbedo;
    }
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
