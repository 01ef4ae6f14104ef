// holocap submit slurm COMMAND TAKE [args]: a per-frame command as a Slurm job array plus a
// dependent merge job; holocap submit status TAKE: the run's per-frame progress from its own
// records.
#include <cstdio>
#include <filesystem>

#include "app/commands.h"
#include "app/options.h"
#include "core/error.h"
#include "core/output.h"
#include "distributed/slurm.h"

namespace holocap {
namespace {

struct SubmitSlurmArgs {
  std::string command;
  std::string take;
  int tasks = 1;
  std::string partition;
  std::string time;
  std::string mem;
  int cpus = 1;
  bool dry_run = false;
};

struct SubmitStatusArgs {
  std::string take;
  std::string command = "reconstruct";
  std::string out;
};

// The running program, which every task runs too (on a filesystem every node sees).
std::filesystem::path ThisProgram() {
  std::error_code ec;
  const std::filesystem::path self = std::filesystem::read_symlink("/proc/self/exe", ec);
  if (ec) Fail("cannot find the holocap program's own path: ", ec.message());
  return self;
}

void AddSlurmCommand(CLI::App* submit) {
  auto* command = submit->add_subcommand(
      "slurm",
      "Run a per-frame command over a take as a Slurm job array (task K does --shard K/N) and a "
      "job after it that merges the frames' reports; the command's own flags follow TAKE");
  auto args = std::make_shared<SubmitSlurmArgs>();
  command
      ->add_option("COMMAND", args->command,
                   "The per-frame command: reconstruct, train splat (two words; its flags "
                   "need --segment-frames) or export web (its flags need --out)")
      ->required();
  command->add_option("TAKE", args->take, "The take, on a filesystem every node sees")->required();
  command->add_option("--tasks", args->tasks, "Array tasks, one shard of the run each")
      ->capture_default_str();
  command->add_option("--partition", args->partition,
                      "sbatch --partition (default: the cluster's)");
  command->add_option("--time", args->time, "sbatch --time per task, e.g. 2:00:00");
  command->add_option("--mem", args->mem, "sbatch --mem per task, e.g. 8G");
  command->add_option("--cpus", args->cpus, "CPUs per task (sbatch --cpus-per-task, --threads)")
      ->capture_default_str();
  command->add_flag("--dry-run", args->dry_run, "Print the two batch scripts; submit nothing");
  command->allow_extras();
  command->callback([command, args] {
    SlurmOptions options;
    options.command = args->command;
    options.take = args->take;
    options.args = command->remaining();
    // A command of two words (train splat, export web): the second was taken as TAKE.
    if (args->command == "train" || args->command == "export") {
      if (options.args.empty())
        Fail("submit slurm ", args->command, " ", args->take, " needs a take after it");
      options.command += " " + args->take;
      options.take = options.args.front();
      options.args.erase(options.args.begin());
    }
    options.tasks = args->tasks;
    options.partition = args->partition;
    options.time = args->time;
    options.mem = args->mem;
    options.cpus = args->cpus;
    options.holocap = ThisProgram();
    if (args->dry_run) {
      const SlurmScripts scripts = MakeSlurmScripts(options);
      std::printf("# %s\n%s\n# %s (submitted with --dependency=afterany:ARRAY_JOB)\n%s",
                  (SlurmDirectory(scripts.out) / "array.sbatch").c_str(), scripts.array.c_str(),
                  (SlurmDirectory(scripts.out) / "merge.sbatch").c_str(), scripts.merge.c_str());
      return;
    }
    RequireSbatch(options.command);  // before anything is written
    const SlurmScripts scripts = MakeSlurmScripts(options);
    // The run's output is the command's: claimed as its, shared with the tasks' own claims.
    const OutputDirectory claimed =
        OutputDirectory::Claim(scripts.out, {options.command, false, {}, true});
    const SubmitSummary summary = SubmitToSlurm(options);
    std::printf("scripts: %s, %s\n", summary.array_script.c_str(), summary.merge_script.c_str());
    std::printf("progress: holocap submit status %s --command '%s' --out %s\n",
                options.take.c_str(), options.command.c_str(), summary.out.c_str());
    EndCommand(summary, "submit slurm");
  });
}

void AddStatusCommand(CLI::App* submit) {
  auto* command = submit->add_subcommand(
      "status",
      "Per-frame progress of a take's run from its own per-frame reports (not from the "
      "scheduler's accounting)");
  auto args = std::make_shared<SubmitStatusArgs>();
  command->add_option("TAKE", args->take, "The take")->required();
  command->add_option("--command", args->command, "The per-frame command (e.g. 'train splat')")
      ->capture_default_str();
  command->add_option("--out", args->out,
                      "The run's output (default: the command's, e.g. TAKE/recon)");
  command->callback([args] {
    const PerFrameCommand& per_frame = FindPerFrameCommand(args->command);
    const std::filesystem::path out =
        args->out.empty() ? std::filesystem::path(args->take) / per_frame.default_out
                          : std::filesystem::path(args->out);
    const RunState run = ReadRunState(out);
    std::printf("%s", DescribeRunProgress(run).c_str());
  });
}

void AddSubmitCommand(CLI::App& app) {
  auto* submit =
      app.add_subcommand("submit", "Per-frame commands on a cluster: submit slurm, submit status");
  submit->require_subcommand(1);
  AddSlurmCommand(submit);
  AddStatusCommand(submit);
}

}  // namespace

HOLOCAP_COMMAND(105, AddSubmitCommand);

}  // namespace holocap
