// Scaling of `holocap submit slurm reconstruct` on a one-node Slurm cluster this program starts
// on localhost (tests/distributed/slurm_cluster.h; needs root, slurm-wlm and munge): frames per
// minute for 1 and 2 array tasks of one CPU each, interleaved, beside one process's run with
// 1 and 2 threads, the parallel efficiency, and the model of N nodes from the measured
// per-frame cost, the bytes a frame reads and writes, and the disk's measured bandwidth (where
// a shared filesystem becomes the limit). The run's plan is made once, by the first task
// (core/frame_tasks.h PlanOnce); every run's CPU seconds per task (from its frames' records) and
// the plan's give the efficiency on a quiet node, where each task has its CPU to itself.
//
// The runs that measure scaling reconstruct a copy of the simulated take without its true meshes
// (gt/meshes): what a real take gives, where no frame is scored against the truth. Scoring a
// frame (Chamfer, F-score, completeness against gt/meshes) is measured apart, by one process with
// one thread on the take as simulated, interleaved with the others. The cameras are the take's
// true models, asked for with --ground-truth-cameras (the take has no calib/; this bench measures
// scaling, not calibration).
//
//   build/bench/slurm_bench [SIZE=192] [SETS=24] [REPEATS=2] [WORK=/tmp/holocap-slurm-bench]
#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "core/error.h"
#include "core/frame_tasks.h"
#include "core/fs.h"
#include "tests/distributed/slurm_cluster.h"

namespace holocap {
namespace {

using testing::LocalSlurm;
using testing::RunShell;
namespace fs = std::filesystem;

double Now() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

std::string Load() {
  std::string text = ReadFileToString("/proc/loadavg");
  return text.substr(0, text.find(' '));
}

std::string Run(const std::string& command) {
  const auto result = RunShell(command);
  if (result.exit_code != 0) Fail("'", command, "' failed: ", result.output);
  return result.output;
}

// The number after `label` in `text`.
std::string After(const std::string& text, const std::string& label) {
  const size_t at = text.find(label);
  if (at == std::string::npos) Fail("no '", label, "' in: ", text);
  const size_t begin = at + label.size();
  return text.substr(begin, text.find_first_not_of("0123456789", begin) - begin);
}

struct Measure {
  std::string what;
  double wall_s = 0;
  double frame_s = 0;          // mean per-frame seconds (the tasks' own)
  double task_overhead_s = 0;  // a task's wall less its frames: start, planning, merge
  std::string load;
  double cpu_s = 0;       // CPU seconds of all its tasks together (at their last records)
  double plan_cpu_s = 0;  // CPU seconds the run's plan took, in the task that made it
  // The run's compute on a quiet node (each task its own CPU): the longest task, counting
  // for a task that read the plan the time the task that made it took.
  double quiet_s = 0;
};

// Mean per-frame seconds of a merged run, and its tasks' mean overhead.
void ReadRun(const fs::path& out, Measure* m) {
  const auto report = nlohmann::json::parse(ReadFileToString(out / "report.json"));
  if (report["summary"]["termination"] != "SUCCESS") Fail(out.string(), " did not succeed");
  m->frame_s = report["metrics"]["timing"]["mean_frame_s"].get<double>();
  const auto plan = nlohmann::json::parse(ReadFileToString(out / "plan" / "plan.json"));
  m->plan_cpu_s = plan["made_cpu_s"].get<double>();
  for (const auto& [task, cpu] : report["metrics"]["timing"]["cpu_s_by_task"].items()) {
    m->cpu_s += cpu.get<double>();
    const bool read_plan = task != plan["made_by"].get<std::string>();
    m->quiet_s = std::max(m->quiet_s, cpu.get<double>() + (read_plan ? m->plan_cpu_s : 0));
  }
  double overhead = 0;
  int tasks = 0;
  std::error_code ec;
  if (!fs::is_directory(out / "tasks", ec)) return;
  for (const auto& entry : fs::directory_iterator(out / "tasks")) {
    const auto task = nlohmann::json::parse(ReadFileToString(entry.path() / "report.json"));
    double frames = 0;
    for (const auto& f : task["metrics"]["frames"]) frames += f["seconds"].get<double>();
    overhead += task["metrics"]["timing"]["wall_s"].get<double>() - frames;
    ++tasks;
  }
  m->task_overhead_s = tasks > 0 ? overhead / tasks : 0;
}

// Bytes per second written with fdatasync, 256 MB in 4 MB blocks.
double DiskWriteBandwidth(const fs::path& dir) {
  const fs::path file = dir / "bandwidth.bin";
  const std::string block(4 << 20, 'x');
  const int fd = ::open(file.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  if (fd < 0) Fail("cannot write ", file.string());
  const double t0 = Now();
  for (int i = 0; i < 64; ++i) {
    if (::write(fd, block.data(), block.size()) != static_cast<ssize_t>(block.size()))
      Fail("short write to ", file.string());
  }
  ::fdatasync(fd);
  const double seconds = Now() - t0;
  ::close(fd);
  fs::remove(file);
  return 64.0 * block.size() / seconds;
}

uint64_t BytesOfSet(const fs::path& take, int64_t set) {
  char name[32];
  std::snprintf(name, sizeof(name), "%06lld.", static_cast<long long>(set));
  uint64_t bytes = 0;
  for (const auto& sensor : fs::directory_iterator(take / "frames")) {
    for (const auto& frame : fs::directory_iterator(sensor.path())) {
      if (frame.path().filename().string().rfind(name, 0) == 0) bytes += frame.file_size();
    }
  }
  return bytes;
}

uint64_t BytesWritten(const fs::path& out, int64_t set) {
  uint64_t bytes = fs::file_size(FrameRecordPath(out, set));
  const auto record = nlohmann::json::parse(ReadFileToString(FrameRecordPath(out, set)));
  for (const auto& output : record["outputs"]) bytes += output["bytes"].get<uint64_t>();
  return bytes;
}

int Main(int argc, char** argv) {
  const int size = argc > 1 ? std::atoi(argv[1]) : 192;
  const int sets = argc > 2 ? std::atoi(argv[2]) : 24;
  const int repeats = argc > 3 ? std::atoi(argv[3]) : 2;
  const fs::path work = argc > 4 ? fs::path(argv[4]) : fs::path("/tmp/holocap-slurm-bench");
  if (geteuid() != 0) Fail("slurm_bench starts munged, slurmctld and slurmd: run it as root");
  const std::string cli = testing::CliPath();
  fs::remove_all(work);
  CreateDirectories(work);
  const fs::path scored_take = work / "take-scored";
  Run("HOLOCAP_NO_PROGRESS=1 '" + cli + "' sim --rig studio8 --frames " + std::to_string(sets + 1) +
      " --clean-plate 1 --size " + std::to_string(size) + " --out " + scored_take.string());
  // The same frames without the true meshes: nothing to score a frame against.
  const fs::path take = work / "take";
  fs::copy(scored_take, take, fs::copy_options::recursive | fs::copy_options::create_hard_links);
  fs::remove_all(take / "gt" / "meshes");
  const std::string options = " --no-sweep --ground-truth-cameras";
  const std::string recon = "reconstruct " + take.string() + options;
  std::vector<Measure> measures;
  const std::string scored_label = "1 process, 1 thread(s), scored";
  auto one_process = [&](int threads, int rep, bool scored = false) {
    Measure m{scored ? scored_label : Cat("1 process, ", threads, " thread(s)"), 0, 0, 0, Load()};
    const fs::path out = work / Cat(scored ? "scored-" : "process-", threads, "-", rep);
    const double t0 = Now();
    Run("HOLOCAP_NO_PROGRESS=1 '" + cli + "' reconstruct " +
        (scored ? scored_take : take).string() + options + " --threads " + std::to_string(threads) +
        " --out " + out.string());
    m.wall_s = Now() - t0;
    ReadRun(out, &m);
    // Two threads share one task's CPU seconds: no single-CPU critical path to read from them.
    if (threads > 1) m.quiet_s = 0;
    measures.push_back(m);
  };
  LocalSlurm cluster(work / "cluster");
  std::string why;
  if (!cluster.Start(&why)) Fail("the cluster did not start: ", why);
  auto slurm = [&](int tasks, int rep) {
    Measure m{Cat("Slurm, ", tasks, " task(s) x 1 CPU"), 0, 0, 0, Load()};
    fs::path out = work / Cat("slurm-", tasks, "-", rep);
    const double t0 = Now();
    const std::string submitted =
        Run("HOLOCAP_NO_PROGRESS=1 '" + cli + "' submit slurm " + recon + " --out " + out.string() +
            " --tasks " + std::to_string(tasks) + " --cpus 1");
    if (!LocalSlurm::WaitForJob(After(submitted, "merge job "), 6000))
      Fail("the merge job did not end");
    m.wall_s = Now() - t0;
    ReadRun(out, &m);
    measures.push_back(m);
    return out;
  };
  fs::path last;
  for (int rep = 0; rep < repeats; ++rep) {
    one_process(1, rep);
    slurm(1, rep);
    last = slurm(2, rep);
    one_process(2, rep);
    one_process(1, rep, /*scored=*/true);
  }
  std::printf(
      "holocap submit slurm reconstruct: studio8 at %d px, %d frame sets, --no-sweep, no frame "
      "scored against the truth (but the \"scored\" row), one-node cluster on this machine (%u "
      "cores); load = 1-min load average at start\n\n",
      size, sets, std::thread::hardware_concurrency());
  std::printf(
      "| run | wall s | frames/min | mean frame s | task overhead s | CPU s (all tasks) | plan "
      "CPU s | quiet-node s | load |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|\n");
  std::map<std::string, std::vector<double>> fpm, quiet, cpu;
  for (const Measure& m : measures) {
    const double rate = 60.0 * sets / m.wall_s;
    fpm[m.what].push_back(rate);
    quiet[m.what].push_back(m.quiet_s);
    cpu[m.what].push_back(m.cpu_s);
    char quiet_s[32] = "-";
    if (m.quiet_s > 0) std::snprintf(quiet_s, sizeof(quiet_s), "%.1f", m.quiet_s);
    std::printf("| %s | %.1f | %.2f | %.2f | %.1f | %.1f | %.1f | %s | %s |\n", m.what.c_str(),
                m.wall_s, rate, m.frame_s, m.task_overhead_s, m.cpu_s, m.plan_cpu_s, quiet_s,
                m.load.c_str());
  }
  auto mean = [](const std::vector<double>& v) {
    double s = 0;
    for (double x : v) s += x;
    return v.empty() ? 0 : s / v.size();
  };
  const double one = mean(fpm["Slurm, 1 task(s) x 1 CPU"]);
  const double two = mean(fpm["Slurm, 2 task(s) x 1 CPU"]);
  std::printf(
      "\nparallel efficiency, 2 tasks against 1 (mean of %d interleaved pairs): "
      "%.2f / (2 x %.2f) = %.0f %%\n",
      repeats, two, one, 100.0 * two / (2 * one));
  std::printf("Slurm 1 task against 1 process with 1 thread: %.0f %% of its frames per minute\n",
              100.0 * one / mean(fpm["1 process, 1 thread(s)"]));
  const double quiet_one = mean(quiet["Slurm, 1 task(s) x 1 CPU"]);
  const double quiet_two = mean(quiet["Slurm, 2 task(s) x 1 CPU"]);
  std::printf(
      "on a quiet node, from the CPU seconds (compute only, Slurm's start and merge aside): "
      "%.1f s / (2 x %.1f s) = %.0f %%\n",
      quiet_one, quiet_two, 100.0 * quiet_one / (2 * quiet_two));
  const double cpu_plain = mean(cpu["1 process, 1 thread(s)"]) / sets;
  const double cpu_scored = mean(cpu[scored_label]) / sets;
  std::printf(
      "scoring against the true meshes, apart (1 process, 1 thread, mean of %d): %.3f CPU s a "
      "frame set scored, %.3f unscored: scoring costs %.3f s, %.0f %% of a scored set's CPU "
      "(%.2f frames/min scored against %.2f)\n",
      repeats, cpu_scored, cpu_plain, cpu_scored - cpu_plain,
      100.0 * (cpu_scored - cpu_plain) / cpu_scored, mean(fpm[scored_label]),
      mean(fpm["1 process, 1 thread(s)"]));

  // The model: N nodes like this one each run 2 tasks at the measured rate; every frame reads
  // its frame set from, and writes its meshes and record to, the shared filesystem.
  double read_bytes = 0, written_bytes = 0;
  const RunState run = ReadRunState(last);
  for (int64_t set : run.sets) {
    read_bytes += BytesOfSet(take, set);
    written_bytes += BytesWritten(last, set);
  }
  read_bytes /= run.sets.size();
  written_bytes /= run.sets.size();
  const double disk = DiskWriteBandwidth(work);
  std::printf(
      "\nper frame set: reads %.2f MB, writes %.2f MB; this disk writes %.0f MB/s "
      "(256 MB, fdatasync)\n",
      read_bytes / 1e6, written_bytes / 1e6, disk / 1e6);
  std::printf(
      "\n| shared filesystem | MB/s | frames/min it carries | nodes at which it is the "
      "limit (%.2f frames/min per node) |\n|---|---|---|---|\n",
      two);
  const std::vector<std::pair<std::string, double>> filesystems = {
      {"this machine's disk (measured)", disk},
      {"NFS over 1 GbE", 117e6},
      {"NFS over 10 GbE", 1170e6},
      {"parallel FS, 10 GB/s", 10e9}};
  for (const auto& [name, bandwidth] : filesystems) {
    const double carried = 60.0 * bandwidth / (read_bytes + written_bytes);
    std::printf("| %s | %.0f | %.0f | %.0f |\n", name.c_str(), bandwidth / 1e6, carried,
                carried / two);
  }
  std::printf(
      "\n| nodes | frames/min (compute) | frames/min (NFS 10 GbE) | hours for 18,000 "
      "frame sets |\n|---|---|---|---|\n");
  const double nfs = 60.0 * 1170e6 / (read_bytes + written_bytes);
  for (int nodes : {1, 2, 4, 8, 16, 32, 64, 128, 256, 512}) {
    const double rate = std::min(nodes * two, nfs);
    std::printf("| %d | %.0f | %.0f | %.1f |\n", nodes, nodes * two, rate, 18000 / rate / 60);
  }
  return 0;
}

}  // namespace
}  // namespace holocap

int main(int argc, char** argv) {
  try {
    return holocap::Main(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "slurm_bench: %s\n", e.what());
    return 1;
  }
}
