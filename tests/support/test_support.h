// Helpers shared by the test suites: temporary directories, paths to the CLI and the repository's
// test data, running the CLI as a child process.
#pragma once

#include <filesystem>
#include <string>

#include "core/board.h"
#include "core/take_plan.h"

namespace holocap::testing {

// A fresh directory under the system temp dir, removed when the object dies.
class TempDir {
 public:
  explicit TempDir(const std::string& prefix = "holocap-test");
  ~TempDir();
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  const std::filesystem::path& path() const { return path_; }
  std::filesystem::path operator/(const std::string& name) const { return path_ / name; }

 private:
  std::filesystem::path path_;
};

std::filesystem::path TestDataDir();  // tests/data: real data sets kept in the repository
std::filesystem::path SourceDir();
std::string CliPath();  // the built holocap executable

struct CommandResult {
  int exit_code = -1;
  std::string output;  // stdout and stderr together
};
// Runs the holocap CLI with `args` (shell-quoted by the caller) and captures its output.
CommandResult RunCli(const std::string& args);
// Runs any shell command and captures its output.
CommandResult RunShell(const std::string& command);

// A ChArUco layout: `across` x `down` squares of side `square` (m), `marker` (m) markers of
// OpenCV's `dictionary` numbered from `first_id`, a margin of one square.
inline BoardLayout CharucoLayout(int across, int down, double square, double marker,
                                 const std::string& dictionary, int first_id = 0) {
  BoardLayout layout;
  layout.type = BoardType::kCharuco;
  layout.squares_across = across;
  layout.squares_down = down;
  layout.spacing = square;
  layout.marker_side = marker;
  layout.dictionary = dictionary;
  layout.first_id = first_id;
  layout.margin = square;
  return layout;
}

// A selection that uses a simulated take's true cameras (gt/cameras): for tests that measure a
// stage apart from calibration, saying so (an uncalibrated take is refused otherwise).
TakeSelection TrueCameras();

// Cuts holes (black discs of 1 and 2 px radius) and a crack (a black line 2 px wide across the
// subject) into every view of frame set 0 of a simulated take, inside its true silhouettes
// (gt/masks), as a threshold loses a subject's dark patches.
void CutHolesAndCrack(const std::filesystem::path& take);

// The error contract: exit status non-zero and exactly one line, starting "holocap: error:",
// that holds `needle` (a GoogleTest expectation).
void ExpectOneLineError(const CommandResult& result, const std::string& needle);

}  // namespace holocap::testing
