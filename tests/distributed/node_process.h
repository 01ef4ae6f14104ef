// A `holocap capture-node` process for the tests and bench/node_capture_bench: started with
// fork/exec (killed by the kernel if its parent dies first), stopped by its pid.
#pragma once

#include <fcntl.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iterator>
#include <sstream>
#include <string>
#include <thread>

namespace holocap::testing {

// A `holocap capture-node` process, killed by its pid when the object dies.
class NodeProcess {
 public:
  NodeProcess(const std::string& cli, const std::string& name, const std::string& endpoint) {
    const int null_output = open("/dev/null", O_WRONLY | O_CLOEXEC);
    std::fflush(nullptr);
    pid_ = fork();
    if (pid_ == 0) {
      prctl(PR_SET_PDEATHSIG, SIGKILL);
      if (null_output >= 0) dup2(null_output, STDOUT_FILENO);
      execl(cli.c_str(), cli.c_str(), "capture-node", "--listen", endpoint.c_str(), "--name",
            name.c_str(), static_cast<char*>(nullptr));
      _exit(127);
    }
    if (null_output >= 0) close(null_output);
  }
  ~NodeProcess() { Stop(SIGTERM); }
  NodeProcess(const NodeProcess&) = delete;
  NodeProcess& operator=(const NodeProcess&) = delete;

  pid_t pid() const { return pid_; }
  // Sends `signal`, then SIGKILL if it has not ended within 5 s, and reaps it.
  void Stop(int signal) {
    if (pid_ <= 0) return;
    kill(pid_, signal);
    int status = 0;
    for (int tries = 0; tries < 500; ++tries) {
      if (waitpid(pid_, &status, WNOHANG) == pid_) {
        pid_ = -1;
        return;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    kill(pid_, SIGKILL);
    waitpid(pid_, &status, 0);
    pid_ = -1;
  }

 private:
  pid_t pid_ = -1;
};

// CPU seconds (user + system) a process has used so far, from /proc/PID/stat.
inline double ProcessCpuSeconds(pid_t pid) {
  std::ifstream stat("/proc/" + std::to_string(pid) + "/stat");
  std::string text((std::istreambuf_iterator<char>(stat)), std::istreambuf_iterator<char>());
  const size_t end = text.rfind(')');
  if (end == std::string::npos) return 0;
  std::istringstream fields(text.substr(end + 2));
  std::string field;
  unsigned long long utime = 0, stime = 0;
  for (int i = 3; i <= 15 && fields >> field; ++i) {
    if (i == 14) utime = std::stoull(field);
    if (i == 15) stime = std::stoull(field);
  }
  return static_cast<double>(utime + stime) / static_cast<double>(sysconf(_SC_CLK_TCK));
}

}  // namespace holocap::testing
