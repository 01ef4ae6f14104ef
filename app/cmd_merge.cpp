// holocap merge PART... --out TAKE: join the parts capture nodes recorded into one take.
#include <iostream>

#include "app/commands.h"
#include "app/options.h"
#include "core/error.h"
#include "distributed/merge.h"

namespace holocap {

static void AddMergeCommand(CLI::App& app) {
  auto* command = app.add_subcommand(
      "merge", "Join the parts that capture nodes recorded into one take (parts are not changed)");
  struct Args {
    std::vector<std::string> parts;
    std::string out;
    MergeOptions options;
  };
  auto args = std::make_shared<Args>();
  command->add_option("parts", args->parts, "The nodes' parts (takes)")->required();
  command->add_option("--out", args->out, "The merged take to create")->required();
  command
      ->add_option("--match", args->options.match,
                   "How sets are formed: auto, timestamp or sequence (frame counters)")
      ->capture_default_str();
  command
      ->add_option("--tolerance-ns", args->options.tolerance_ns,
                   "Largest spread of a merged set across nodes (0: 0.4 frame periods)")
      ->capture_default_str();
  command->add_option("--writers", args->options.writer_threads, "Writer threads")
      ->capture_default_str();
  command->add_flag("--overwrite", args->options.overwrite,
                    "Replace an existing merged take (never a capture's recording)");
  NameFieldFlags(command, {{"writer_threads", "--writers"}});
  command->callback([args] {
    args->options.Check();
    std::vector<std::filesystem::path> parts(args->parts.begin(), args->parts.end());
    Report report("merge");
    report.options() = {{"parts", args->parts},
                        {"out", args->out},
                        {"match", args->options.match},
                        {"tolerance_ns", args->options.tolerance_ns},
                        {"writers", args->options.writer_threads}};
    MergeSummary summary = MergeParts(parts, args->out, args->options, &report);
    report.plan() = {{"match", summary.match}, {"parts", parts.size()}};
    report.metrics() = summary.Metrics();
    report.SetSummary(summary);
    report.Write(std::filesystem::path(args->out) / "report.json");
    for (const auto& part : summary.parts) {
      std::cout << "part " << part.node << " (" << part.part.string() << ", " << part.state
                << "): " << part.sets << " sets, " << part.merged << " merged, " << part.missed
                << " missed, " << part.discarded << " discarded, clock offset "
                << part.offset_ns / 1e3 << " us (" << part.offset_source << ")\n";
    }
    std::cout << "take        " << args->out << "\n";
    EndCommand(summary, "merge");
  });
}

HOLOCAP_COMMAND(22, AddMergeCommand);

}  // namespace holocap
