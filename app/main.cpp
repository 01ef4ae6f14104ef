// holocap: capture-to-avatar pipeline for multi-camera rigs.
#include <algorithm>
#include <cctype>
#include <cstdio>
#include <exception>
#include <new>
#include <string>
#include <vector>

#include "app/commands.h"
#include "app/options.h"
#include "core/check_option.h"
#include "core/error.h"
#include "core/report.h"

namespace holocap {
std::vector<CommandEntry>& CommandTable() {
  static std::vector<CommandEntry> table;
  return table;
}
}  // namespace holocap

namespace {

// The one error line: quoted input is escaped so the message stays one printable line.
void PrintError(std::string message) {
  while (!message.empty() && std::isspace(static_cast<unsigned char>(message.back())))
    message.pop_back();
  std::fprintf(stderr, "holocap: error: %s\n", holocap::Printable(message).c_str());
}

// The command the user ran: the deepest subcommand parsed (train nvol, submit slurm).
const CLI::App& CommandRun(const CLI::App& app) {
  const CLI::App* command = &app;
  while (!command->get_subcommands().empty()) command = command->get_subcommands().front();
  return *command;
}

std::string CommandLine(int argc, char** argv) {
  std::string line;
  for (int i = 1; i < argc && line.size() < 400; ++i) line += std::string(" ") + argv[i];
  return line;
}

}  // namespace

namespace {

// The program: parses the command line, runs the command, and ends every error in one line.
int Run(int argc, char** argv) {
  holocap::SetProgramArguments(argc, argv);
  CLI::App app{
      "holocap: record multi-camera takes, calibrate the rig, reconstruct geometry, learn an "
      "avatar and play it back from any viewpoint"};
  app.require_subcommand(1);
  app.set_version_flag("--version", "holocap 0.1.0");
  holocap::RegisterBuiltinDrivers();
  holocap::RegisterAvatarKinds();
  auto& table = holocap::CommandTable();
  std::stable_sort(table.begin(), table.end(),
                   [](const auto& a, const auto& b) { return a.order < b.order; });
  for (const auto& entry : table) entry.add(app);
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    // --help and --version print as CLI11 prints them; a flag CLI11 cannot read (a count of
    // "1e9", a missing value) is one error line like every other, naming where help is.
    if (e.get_exit_code() == 0) return app.exit(e);
    const CLI::App& command = CommandRun(app);
    std::vector<std::string> names;  // the command's words, innermost first
    for (const CLI::App* at = &command; at != nullptr && at != &app; at = at->get_parent())
      names.push_back(at->get_name());
    std::string message = e.what();
    message += " (holocap ";
    for (auto name = names.rbegin(); name != names.rend(); ++name)
      message.append(*name).append(" ");
    message += "--help lists the options)";
    PrintError(message);
    return e.get_exit_code();
  } catch (const holocap::OptionError& e) {
    // The commands check their options while parsing (in their callbacks): the line names the
    // flag the user typed where one fills the field.
    const std::string message = holocap::OptionErrorMessage(CommandRun(app), e);
    holocap::WritePendingFailureReports(message);
    PrintError(message);
    return 1;
  } catch (const std::bad_alloc&) {
    // The allocation that failed is not known here; the command line says what was asked.
    const std::string message =
        "out of memory: a size or count asked for needs more memory than this machine can give "
        "(asked: holocap" +
        CommandLine(argc, argv) + ")";
    holocap::WritePendingFailureReports(message);
    PrintError(message);
    return 1;
  } catch (const std::exception& e) {
    // The reports of the stages it stopped hold FAILURE, this line, and what ran before it.
    holocap::WritePendingFailureReports(e.what());
    PrintError(e.what());
    return 1;
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return Run(argc, argv);
  } catch (...) {
    // Run ends every std::exception in one line; anything else is no error of the input's.
    std::fputs("holocap: error: an unexpected failure (not a std::exception)\n", stderr);
    return 1;
  }
}
