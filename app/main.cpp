// holocap: capture-to-avatar pipeline for multi-camera rigs.
#include <algorithm>
#include <cstdio>
#include <exception>

#include "app/commands.h"
#include "core/error.h"
#include "core/report.h"

namespace holocap {
std::vector<CommandEntry>& CommandTable() {
  static std::vector<CommandEntry> table;
  return table;
}
}  // namespace holocap

int main(int argc, char** argv) {
  holocap::HandOverNeuralCommands(argc, argv);
  CLI::App app{
      "holocap: record multi-camera takes, calibrate the rig, reconstruct geometry, learn an "
      "avatar and play it back from any viewpoint"};
  app.require_subcommand(1);
  app.set_version_flag("--version", "holocap 0.1.0");
  holocap::RegisterBuiltinDrivers();
  auto& table = holocap::CommandTable();
  std::stable_sort(table.begin(), table.end(),
                   [](const auto& a, const auto& b) { return a.order < b.order; });
  for (const auto& entry : table) entry.add(app);
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e);
  } catch (const std::exception& e) {
    // The reports of the stages it stopped hold FAILURE, this line, and what ran before it.
    holocap::WritePendingFailureReports(e.what());
    std::fprintf(stderr, "holocap: error: %s\n", e.what());
    return 1;
  }
  return 0;
}
