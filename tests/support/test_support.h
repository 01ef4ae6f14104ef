// Helpers shared by the test suites: temporary directories, paths to the CLI and the repository's
// test data, running the CLI as a child process.
#pragma once

#include <filesystem>
#include <string>

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

// A selection that uses a simulated take's true cameras (gt/cameras): for tests that measure a
// stage apart from calibration, saying so (an uncalibrated take is refused otherwise).
TakeSelection TrueCameras();

// The error contract: exit status non-zero and exactly one line, starting "holocap: error:",
// that holds `needle` (a GoogleTest expectation).
void ExpectOneLineError(const CommandResult& result, const std::string& needle);

}  // namespace holocap::testing
