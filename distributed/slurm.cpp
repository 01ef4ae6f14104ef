#include "distributed/slurm.h"

#include <fcntl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cctype>
#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <sstream>

#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"

namespace holocap {
namespace {

const std::vector<PerFrameCommand>& PerFrameCommands() {
  static const std::vector<PerFrameCommand> commands = {
      {"reconstruct", "recon", true},
      {"train splat", "models/splat", true},
      {"export web", "site", false},
  };
  return commands;
}

// `text` in single quotes for bash (a quote inside becomes '\'').
std::string ShellQuote(const std::string& text) {
  std::string quoted = "'";
  for (char c : text) {
    if (c == '\'')
      quoted += "'\\''";
    else
      quoted += c;
  }
  return quoted + "'";
}

// A value that goes into an #SBATCH line as it is: no spaces, quotes or shell syntax.
void CheckSbatchValue(const std::string& value, const char* flag) {
  for (char c : value) {
    const bool plain = std::isalnum(static_cast<unsigned char>(c)) || c == ':' || c == '-' ||
                       c == '_' || c == '.' || c == ',';
    if (!plain)
      Fail(flag, " '", value, "' holds '", std::string(1, c), "' (letters, digits, :-_.,)");
  }
}

// Text written into a batch script: a newline or another control character would end the line
// it stands in (an #SBATCH line, the command) and start one of its own, so it is refused.
void CheckScriptText(const std::string& text, const std::string& what) {
  for (char c : text) {
    const auto byte = static_cast<unsigned char>(c);
    if (byte < 0x20 || byte == 0x7f) {
      Fail(what, " '", Printable(text), "' holds a control character (byte ", int{byte},
           "); a batch script cannot carry it: rename it");
    }
  }
}

struct ProgramResult {
  int exit_code = -1;
  std::string output;  // stdout and stderr together
};

// Runs `argv` (no shell) and captures what it prints.
ProgramResult RunProgram(const std::vector<std::string>& argv) {
  int pipe_fds[2];
  if (::pipe2(pipe_fds, O_CLOEXEC) != 0) Fail("cannot run ", argv[0], ": ", std::strerror(errno));
  std::vector<char*> args;
  for (const auto& a : argv) args.push_back(const_cast<char*>(a.c_str()));
  args.push_back(nullptr);
  const pid_t pid = ::fork();
  if (pid < 0) Fail("cannot run ", argv[0], ": ", std::strerror(errno));
  if (pid == 0) {
    ::dup2(pipe_fds[1], STDOUT_FILENO);
    ::dup2(pipe_fds[1], STDERR_FILENO);
    ::execvp(args[0], args.data());
    _exit(127);
  }
  ::close(pipe_fds[1]);
  ProgramResult result;
  std::array<char, 4096> buffer;
  ssize_t n;
  while ((n = ::read(pipe_fds[0], buffer.data(), buffer.size())) != 0) {
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) break;
    result.output.append(buffer.data(), static_cast<size_t>(n));
  }
  ::close(pipe_fds[0]);
  int status = 0;
  while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {
  }
  result.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
  while (!result.output.empty() && result.output.back() == '\n') result.output.pop_back();
  return result;
}

// sbatch --parsable prints "JOBID" or "JOBID;CLUSTER".
std::string JobIdOf(const std::string& output) {
  const std::string line =
      output.substr(output.rfind('\n') == std::string::npos ? 0 : output.rfind('\n') + 1);
  const std::string id = line.substr(0, line.find(';'));
  if (id.empty() || id.find_first_not_of("0123456789") != std::string::npos) return "";
  return id;
}

bool HasFlag(const std::vector<std::string>& args, const std::string& flag) {
  for (const auto& a : args) {
    if (a == flag || a.rfind(flag + "=", 0) == 0) return true;
  }
  return false;
}

}  // namespace

const PerFrameCommand& FindPerFrameCommand(const std::string& name) {
  std::string known;
  for (const auto& command : PerFrameCommands()) {
    if (name == command.name) return command;
    known += (known.empty() ? "" : ", ") + std::string(command.name);
  }
  Fail("'", name, "' is not a per-frame command a job array can run (known: ", known, ")");
}

std::filesystem::path PerFrameOutput(const PerFrameCommand& command,
                                     const std::filesystem::path& take,
                                     const std::vector<std::string>& args) {
  for (size_t i = 0; i < args.size(); ++i) {
    if (args[i] == "--out" && i + 1 < args.size()) return args[i + 1];
    if (args[i].rfind("--out=", 0) == 0) return args[i].substr(6);
  }
  return take / command.default_out;
}

void SlurmOptions::Check() const {
  FindPerFrameCommand(command);
  HOLOCAP_CHECK_OPTION(!take.empty(), take, "submit slurm needs a take");
  HOLOCAP_CHECK_OPTION_IN(tasks, 1, 100000);
  HOLOCAP_CHECK_OPTION_IN(cpus, 1, 1024);
  CheckSbatchValue(partition, "--partition");
  CheckSbatchValue(time, "--time");
  CheckSbatchValue(mem, "--mem");
  HOLOCAP_CHECK_OPTION(!holocap.empty() && holocap.is_absolute(), holocap,
                       "the absolute path of the holocap program");
  HOLOCAP_CHECK_OPTION(!HasFlag(args, "--shard"), args,
                       "submit slurm gives each task its --shard; leave it out of the command's "
                       "flags");
  HOLOCAP_CHECK_OPTION(command != "train splat" || HasFlag(args, "--segment-frames"), command,
                       "submit slurm train splat runs a per-frame run: give --segment-frames S "
                       "(and --iterations, --frame-iterations)");
  HOLOCAP_CHECK_OPTION(command != "export web" || HasFlag(args, "--out"), command,
                       "submit slurm export web needs the site's --out DIR (every task writes "
                       "into it)");
}

nlohmann::json SlurmOptions::ToJson() const {
  return {{"command", command}, {"take", take.string()},  {"args", args},
          {"tasks", tasks},     {"partition", partition}, {"time", time},
          {"mem", mem},         {"cpus", cpus},           {"holocap", holocap.string()}};
}

std::filesystem::path SlurmDirectory(const std::filesystem::path& out) { return out / "slurm"; }

SlurmScripts MakeSlurmScripts(const SlurmOptions& options) {
  options.Check();
  const PerFrameCommand& command = FindPerFrameCommand(options.command);
  SlurmScripts scripts;
  scripts.out = std::filesystem::absolute(PerFrameOutput(command, options.take, options.args));
  const std::filesystem::path logs = SlurmDirectory(scripts.out) / "logs";
  CheckScriptText(std::filesystem::absolute(options.take).string(), "the take's path");
  CheckScriptText(scripts.out.string(), "the output's path");
  CheckScriptText(options.holocap.string(), "holocap's path");
  for (const auto& arg : options.args) CheckScriptText(arg, "the argument");
  // An #SBATCH line is split at blanks and quotes, the shell's words are not: its path holds none.
  if (logs.string().find_first_of(" \t\"'\\") != std::string::npos) {
    Fail("the output's path '", scripts.out.string(),
         "' holds a blank, quote or backslash, which an #SBATCH --output line cannot carry; "
         "choose an output without them");
  }
  std::ostringstream header;
  if (!options.partition.empty()) header << "#SBATCH --partition=" << options.partition << "\n";
  if (!options.time.empty()) header << "#SBATCH --time=" << options.time << "\n";
  if (!options.mem.empty()) header << "#SBATCH --mem=" << options.mem << "\n";

  // "train splat" -> "train-splat": a job name holds no space.
  std::string job_name = options.command;
  std::replace(job_name.begin(), job_name.end(), ' ', '-');
  std::ostringstream array;
  array << "#!/bin/bash\n"
        << "#SBATCH --job-name=holocap-" << job_name << "\n"
        << "#SBATCH --array=0-" << options.tasks - 1 << "\n"
        << "#SBATCH --ntasks=1\n"
        << "#SBATCH --cpus-per-task=" << options.cpus << "\n"
        << "#SBATCH --output=" << (logs / "%A_%a.out").string() << "\n"
        << header.str()
        << "# One shard of the run per array task. A task skips the frame sets whose outputs\n"
        << "# are complete, so a resubmitted array redoes only what a killed task left.\n"
        << "set -euo pipefail\n"
        << "export OMP_NUM_THREADS=\"${SLURM_CPUS_PER_TASK:-" << options.cpus << "}\"\n"
        << "exec " << ShellQuote(options.holocap.string()) << " " << options.command << " "
        << ShellQuote(std::filesystem::absolute(options.take).string());
  for (const auto& arg : options.args) array << " " << ShellQuote(arg);
  if (command.has_threads && !HasFlag(options.args, "--threads"))
    array << " --threads \"$OMP_NUM_THREADS\"";
  array << " --shard \"${SLURM_ARRAY_TASK_ID}/" << options.tasks << "\"\n";
  scripts.array = array.str();

  std::ostringstream merge;
  merge << "#!/bin/bash\n"
        << "#SBATCH --job-name=holocap-" << job_name << "-merge\n"
        << "#SBATCH --ntasks=1\n"
        << "#SBATCH --cpus-per-task=1\n"
        << "#SBATCH --output=" << (logs / "%j-merge.out").string() << "\n"
        << header.str()
        << "# Runs after every task of the array has ended, however it ended (afterany): the\n"
        << "# frames' reports merge into the run's report.json, FAILURE naming any frame set\n"
        << "# left incomplete.\n"
        << "set -euo pipefail\n"
        << "exec " << ShellQuote(options.holocap.string()) << " report "
        << ShellQuote(scripts.out.string()) << " --merge\n";
  scripts.merge = merge.str();
  return scripts;
}

bool OnPath(const std::string& program) {
  const char* path = std::getenv("PATH");
  if (path == nullptr) return false;
  std::stringstream dirs(path);
  std::string dir;
  while (std::getline(dirs, dir, ':')) {
    const std::filesystem::path file = std::filesystem::path(dir.empty() ? "." : dir) / program;
    if (::access(file.c_str(), X_OK) == 0) return true;
  }
  return false;
}

void RequireSbatch(const std::string& command) {
  if (OnPath("sbatch")) return;
  Fail(
      "submit slurm needs Slurm's sbatch on PATH and it is not there; without Slurm, start "
      "each shard with any launcher: holocap ",
      command, " TAKE --shard K/N");
}

SubmitSummary SubmitToSlurm(const SlurmOptions& options) {
  RequireSbatch(options.command);
  const SlurmScripts scripts = MakeSlurmScripts(options);
  SubmitSummary summary;
  summary.out = scripts.out;
  const std::filesystem::path dir = SlurmDirectory(scripts.out);
  CreateDirectories(dir / "logs");
  summary.array_script = dir / "array.sbatch";
  summary.merge_script = dir / "merge.sbatch";
  WriteFileAtomic(summary.array_script, scripts.array, /*durable=*/true);
  WriteFileAtomic(summary.merge_script, scripts.merge, /*durable=*/true);

  const ProgramResult array = RunProgram({"sbatch", "--parsable", summary.array_script.string()});
  summary.array_job_id = JobIdOf(array.output);
  if (array.exit_code != 0 || summary.array_job_id.empty()) {
    summary.End(Termination::kFailure, Cat("sbatch refused the array: ", array.output));
    return summary;
  }
  const ProgramResult merge =
      RunProgram({"sbatch", "--parsable", "--dependency=afterany:" + summary.array_job_id,
                  summary.merge_script.string()});
  summary.merge_job_id = JobIdOf(merge.output);
  if (merge.exit_code != 0 || summary.merge_job_id.empty()) {
    RunProgram({"scancel", summary.array_job_id});
    summary.End(Termination::kFailure, Cat("sbatch refused the merge job (the array ",
                                           summary.array_job_id, " is cancelled): ", merge.output));
    return summary;
  }
  LineAppender(dir / "submissions.jsonl", /*durable=*/true)
      .Append(nlohmann::json{{"submitted_unix_s", UnixSeconds()},
                             {"array_job", summary.array_job_id},
                             {"merge_job", summary.merge_job_id},
                             {"options", options.ToJson()}}
                  .dump());
  summary.End(Termination::kSuccess,
              Cat("array job ", summary.array_job_id, " (", options.tasks, " tasks) and merge job ",
                  summary.merge_job_id, " (after it) submitted"));
  return summary;
}

std::string DescribeRunProgress(const RunState& run) {
  std::ostringstream text;
  char line[512];
  for (int64_t set : run.sets) {
    const auto done = run.complete.find(set);
    if (done != run.complete.end()) {
      const nlohmann::json& result = done->second["result"];
      std::snprintf(line, sizeof(line), "  set %06lld  complete   %-11s %7.2f s  %s\n",
                    static_cast<long long>(set), result.value("termination", "?").c_str(),
                    result.value("seconds", 0.0), done->second.value("task", "?").c_str());
    } else {
      std::snprintf(line, sizeof(line), "  set %06lld  incomplete (%s)\n",
                    static_cast<long long>(set), run.incomplete.at(set).c_str());
    }
    text << line;
  }
  std::error_code ec;
  const std::filesystem::path tasks = run.out / "tasks";
  if (std::filesystem::is_directory(tasks, ec)) {
    for (const auto& entry : std::filesystem::directory_iterator(tasks, ec)) {
      const std::filesystem::path file = entry.path() / "report.json";
      if (!std::filesystem::is_regular_file(file, ec)) continue;
      const nlohmann::json report =
          nlohmann::json::parse(ReadFileToString(file), nullptr, /*allow_exceptions=*/false);
      if (report.is_discarded() || !report.contains("summary")) continue;
      text << "  task " << entry.path().filename().string() << ": "
           << report["summary"].value("termination", "?") << ": "
           << report["summary"].value("message", "") << "\n";
    }
  }
  text << run.command << " " << run.out.string() << ": " << run.Describe() << "\n";
  return text.str();
}

}  // namespace holocap
