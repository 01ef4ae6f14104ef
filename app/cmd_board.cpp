// holocap board: print a calibration board to scale.
#include <cstdio>

#include "app/commands.h"
#include "app/options.h"
#include "calibration/calibration.h"
#include "core/board.h"

namespace holocap {
namespace {

struct BoardArgs {
  std::string board;
  std::string out;
  std::string print;
  double dpi = 300;
  bool overwrite = false;
};

void AddBoardCommand(CLI::App& app) {
  auto* command =
      app.add_subcommand("board", "Print a calibration board (YAML layout) to scale as PNG or PDF");
  auto args = std::make_shared<BoardArgs>();
  command
      ->add_option("board", args->board,
                   "Board layout (YAML: type, family, tags_across, ...; or Kalibr's target YAML)")
      ->required();
  command->add_option("--out", args->out, "board.png or board.pdf")->required();
  command->add_option("--dpi", args->dpi, "PNG resolution")->capture_default_str();
  command->add_option("--print", args->print,
                      "tag36h11 boards: holocap (libapriltag's one-bit tag borders, the default) "
                      "or kalibr (as kalibr_create_target_pdf prints them: two-bit borders and "
                      "black squares at the tags' corners)");
  AddOverwriteFlag(command, &args->overwrite);
  command->callback([args] {
    BoardLayout layout = BoardLayout::Load(args->board);
    ApplyBoardPrint(args->print, "--print", &layout);
    const TakeLock lock = ClaimOutputFile(args->out, {"board", args->overwrite, {args->board}});
    WriteBoardPrint(layout, args->out, args->dpi);
    const Board board(layout);
    std::printf("%s board %dx%d points at %.1f mm spacing, %.1f x %.1f mm: %s\n",
                ToString(layout.type), board.width_n(), board.height_n(), 1000 * layout.spacing,
                1000 * (board.u_max() - board.u_min()), 1000 * (board.v_max() - board.v_min()),
                args->out.c_str());
  });
}

}  // namespace

HOLOCAP_COMMAND(35, AddBoardCommand);

}  // namespace holocap
