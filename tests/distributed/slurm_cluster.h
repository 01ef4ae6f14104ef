// A one-node Slurm cluster on localhost for tests and benchmarks: munged, slurmctld and slurmd
// as root, each in the foreground as a child of this process, with their own munge key and
// socket, free ports, state, spool and logs under a directory the caller owns, so that nothing
// else on the machine is touched. The destructor cancels the cluster's jobs and stops every
// daemon by its pid (TERM, then KILL), however the caller ends.
#pragma once

#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "core/error.h"
#include "core/fs.h"
#include "tests/support/test_support.h"

namespace holocap::testing {

namespace fs = std::filesystem;

inline void Sleep(int ms) { std::this_thread::sleep_for(std::chrono::milliseconds(ms)); }

// A TCP port nobody listens on now (the kernel's choice for port 0).
inline int FreePort() {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t length = sizeof(address);
  if (fd < 0 || bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)) != 0 ||
      getsockname(fd, reinterpret_cast<sockaddr*>(&address), &length) != 0) {
    Fail("cannot find a free port");
  }
  close(fd);
  return ntohs(address.sin_port);
}

inline std::string FindProgram(const std::string& name) {
  for (const char* dir : {"/usr/sbin", "/usr/bin", "/sbin", "/bin"}) {
    const fs::path path = fs::path(dir) / name;
    if (access(path.c_str(), X_OK) == 0) return path.string();
  }
  return "";
}

// A one-node cluster on localhost, every daemon in the foreground as a child of this process;
// the destructor cancels the cluster's jobs and stops each daemon by its pid (TERM, then KILL).
class LocalSlurm {
 public:
  explicit LocalSlurm(const fs::path& dir) : dir_(dir) {}
  ~LocalSlurm() { Stop(); }
  LocalSlurm(const LocalSlurm&) = delete;
  LocalSlurm& operator=(const LocalSlurm&) = delete;

  // Starts munged, slurmctld and slurmd; false (with `why`) when the node does not come up.
  bool Start(std::string* why) {
    const fs::path key_dir = dir_ / "munge-key", run_dir = dir_ / "munge-run";
    CreateDirectories(key_dir);
    CreateDirectories(run_dir);
    std::random_device random;
    std::string key(1024, '\0');
    for (char& c : key) c = static_cast<char>(random());
    WriteFileAtomic(key_dir / "munge.key", key);
    RunShell("chown -R munge:munge '" + key_dir.string() + "' '" + run_dir.string() + "'");
    chmod(key_dir.c_str(), 0700);
    chmod((key_dir / "munge.key").c_str(), 0400);
    chmod(run_dir.c_str(), 0755);
    socket_ = (run_dir / "munge.socket").string();
    // setpriv execs munged itself (as the munge user), so its pid is munged's.
    Spawn({FindProgram("setpriv"), "--reuid=munge", "--regid=munge", "--clear-groups",
           FindProgram("munged"), "--foreground", "--socket=" + socket_,
           "--key-file=" + (key_dir / "munge.key").string(),
           "--pid-file=" + (run_dir / "munged.pid").string(),
           "--log-file=" + (key_dir / "munged.log").string(),
           "--seed-file=" + (key_dir / "munged.seed").string()});
    for (int i = 0; i < 100 && !fs::exists(socket_); ++i) Sleep(100);
    if (!fs::exists(socket_)) return *why = "munged did not open its socket", false;
    WriteConf();
    setenv("SLURM_CONF", conf_.c_str(), 1);
    Spawn({FindProgram("slurmctld"), "-D", "-i", "-f", conf_});
    Spawn({FindProgram("slurmd"), "-D", "-f", conf_, "-N", "localhost"});
    for (int i = 0; i < 300; ++i) {
      const auto state = RunShell("sinfo -h -o %T");
      if (state.exit_code == 0 && state.output.rfind("idle", 0) == 0) return true;
      Sleep(200);
    }
    *why = "the node did not become idle: " + RunShell("sinfo -h -o %T").output +
           ReadLog("slurmctld.log") + ReadLog("slurmd.log");
    return false;
  }

  // Waits until `job` (and its array tasks) left the queue; false after the budget.
  static bool WaitForJob(const std::string& job, int polls = 1500) {
    for (int i = 0; i < polls; ++i) {
      const auto queue = RunShell("squeue -h -j " + job + " -o %i");
      const bool listed = queue.output.find_first_not_of(" \n") != std::string::npos;
      const bool forgotten = queue.output.find("Invalid job id") != std::string::npos;
      if ((queue.exit_code == 0 && !listed) || forgotten) return true;
      Sleep(200);
    }
    return false;
  }

  std::string ReadLog(const std::string& name) const {
    std::error_code ec;
    return fs::exists(dir_ / name, ec) ? "\n" + name + ":\n" + ReadFileToString(dir_ / name) : "";
  }

 private:
  void WriteConf() {
    conf_ = (dir_ / "slurm.conf").string();
    const std::string d = dir_.string();
    std::ofstream(conf_) << "ClusterName=holocap" << getpid() << "\n"
                         << "SlurmctldHost=localhost(127.0.0.1)\n"
                         << "SlurmctldPort=" << FreePort() << "\n"
                         << "SlurmdPort=" << FreePort() << "\n"
                         << "SlurmUser=root\nSlurmdUser=root\n"
                         << "AuthType=auth/munge\nCredType=cred/munge\n"
                         << "AuthInfo=socket=" << socket_ << "\n"
                         << "ProctrackType=proctrack/linuxproc\nTaskPlugin=task/none\n"
                         << "SelectType=select/cons_tres\nSelectTypeParameters=CR_CPU\n"
                         << "JobAcctGatherType=jobacct_gather/none\n"
                         << "AccountingStorageType=accounting_storage/none\n"
                         << "MpiDefault=none\nReturnToService=2\nKillWait=5\n"
                         << "StateSaveLocation=" << d << "/state\n"
                         << "SlurmdSpoolDir=" << d << "/spool\n"
                         << "SlurmctldPidFile=" << d << "/slurmctld.pid\n"
                         << "SlurmdPidFile=" << d << "/slurmd.pid\n"
                         << "SlurmctldLogFile=" << d << "/slurmctld.log\n"
                         << "SlurmdLogFile=" << d << "/slurmd.log\n"
                         << "NodeName=localhost NodeAddr=127.0.0.1 CPUs=2 State=UNKNOWN\n"
                         << "PartitionName=holocap Nodes=localhost Default=YES "
                            "MaxTime=INFINITE State=UP\n";
    CreateDirectories(dir_ / "state");
    CreateDirectories(dir_ / "spool");
  }

  void Spawn(const std::vector<std::string>& argv) {
    std::vector<char*> args;
    args.reserve(argv.size() + 1);
    for (const auto& a : argv) args.push_back(const_cast<char*>(a.c_str()));
    args.push_back(nullptr);
    const std::string log = (dir_ / "daemons.out").string();
    const pid_t pid = fork();
    if (pid < 0) Fail("cannot fork");
    if (pid == 0) {
      setpgid(0, 0);  // its own process group: stopped apart from the test's
      if (!freopen(log.c_str(), "a", stdout) || !freopen(log.c_str(), "a", stderr)) _exit(126);
      execv(args[0], args.data());
      _exit(127);
    }
    pids_.push_back(pid);
  }

  void Stop() {
    if (!conf_.empty() && !pids_.empty()) {
      RunShell("scancel --user=root --full");
      for (int i = 0; i < 100; ++i) {
        const auto queue = RunShell("squeue -h -o %i");
        if (queue.exit_code != 0 || queue.output.empty()) break;
        Sleep(100);
      }
    }
    for (auto pid = pids_.rbegin(); pid != pids_.rend(); ++pid) {
      kill(*pid, SIGTERM);
      int status = 0;
      bool ended = false;
      for (int i = 0; i < 100 && !ended; ++i) {
        ended = waitpid(*pid, &status, WNOHANG) == *pid;
        if (!ended) Sleep(50);
      }
      if (!ended) {
        kill(*pid, SIGKILL);
        waitpid(*pid, &status, 0);
      }
    }
    pids_.clear();
    if (!conf_.empty()) unsetenv("SLURM_CONF");
  }

  fs::path dir_;
  std::string socket_;
  std::string conf_;
  std::vector<pid_t> pids_;  // munged, slurmctld, slurmd
};

}  // namespace holocap::testing
