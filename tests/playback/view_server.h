// `holocap view` as a child process for the playback tests: started with fork/exec (killed by the
// kernel if the test dies first), its stdout and stderr read through one pipe, stopped by a
// signal to its pid.
#pragma once

#include <fcntl.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <functional>
#include <string>
#include <thread>
#include <vector>

#include "tests/support/test_support.h"

namespace holocap::testing {

class ViewServer {
 public:
  struct Start {
    std::vector<std::string> arguments;      // after `holocap view`
    std::filesystem::path tmpdir;            // the child's TMPDIR (empty: this process's)
    std::function<void(pid_t)> before_exec;  // runs here while the child waits to exec
  };

  // `holocap view SITE --port 0`, read up to its URL.
  explicit ViewServer(const std::filesystem::path& site)
      : ViewServer(Start{{site.string(), "--port", "0"}, {}, {}}) {
    WaitForUrl();
  }
  explicit ViewServer(const Start& start) {
    std::vector<std::string> words = {CliPath(), "view"};
    words.insert(words.end(), start.arguments.begin(), start.arguments.end());
    std::vector<char*> argv;
    argv.reserve(words.size() + 1);
    for (std::string& word : words) argv.push_back(word.data());
    argv.push_back(nullptr);
    std::string tmpdir = "TMPDIR=" + start.tmpdir.string();
    std::vector<char*> environment;
    for (char** entry = environ; *entry != nullptr; ++entry)
      if (start.tmpdir.empty() || std::string(*entry).rfind("TMPDIR=", 0) != 0)
        environment.push_back(*entry);
    if (!start.tmpdir.empty()) environment.push_back(tmpdir.data());
    environment.push_back(nullptr);
    int output[2], go[2];
    if (pipe2(output, O_CLOEXEC) != 0 || pipe2(go, O_CLOEXEC) != 0) return;
    std::fflush(nullptr);
    pid_ = fork();
    if (pid_ == 0) {
      prctl(PR_SET_PDEATHSIG, SIGKILL);
      dup2(output[1], STDOUT_FILENO);
      dup2(output[1], STDERR_FILENO);
      close(go[1]);
      char byte = 0;
      while (read(go[0], &byte, 1) < 0) {
      }
      execve(argv[0], argv.data(), environment.data());
      _exit(127);
    }
    close(output[1]);
    close(go[0]);
    if (pid_ > 0 && start.before_exec) start.before_exec(pid_);
    close(go[1]);
    output_ = fdopen(output[0], "r");
  }
  ~ViewServer() {
    Stop();
    if (output_ != nullptr) fclose(output_);
  }
  ViewServer(const ViewServer&) = delete;
  ViewServer& operator=(const ViewServer&) = delete;

  // Reads its output up to the line with the URL; false when it ended first.
  bool WaitForUrl() {
    char line[512];
    while (output_ != nullptr && fgets(line, sizeof(line), output_) != nullptr) {
      first_line_ = line;
      printed_ += line;
      const auto at = first_line_.find("http://");
      if (at != std::string::npos) {
        url_ = first_line_.substr(at, first_line_.find(' ', at) - at);
        return true;
      }
    }
    return false;
  }
  // Sends `signal` (SIGKILL after 30 s more), reaps it and reads the rest of its output; its wait
  // status (-1 if it never ran).
  int Stop(int signal = SIGTERM) {
    if (pid_ > 0) {
      kill(pid_, signal);
      const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(30);
      while (!Ended()) {
        if (std::chrono::steady_clock::now() > deadline) kill(pid_, SIGKILL);
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
      }
    }
    char line[512];
    while (output_ != nullptr && fgets(line, sizeof(line), output_) != nullptr) printed_ += line;
    return status_;
  }
  // Whether it has ended (reaped then; Stop() gives its status).
  bool Ended() {
    if (pid_ > 0 && waitpid(pid_, &status_, WNOHANG) == pid_) pid_ = -1;
    return pid_ <= 0;
  }

  pid_t pid() const { return pid_; }
  const std::string& url() const { return url_; }
  int port() const { return url_.empty() ? -1 : std::atoi(url_.c_str() + url_.rfind(':') + 1); }
  const std::string& first_line() const { return first_line_; }
  // Its output read so far: up to the URL, or everything once stopped.
  const std::string& printed() const { return printed_; }

 private:
  pid_t pid_ = -1;
  int status_ = -1;
  FILE* output_ = nullptr;
  std::string url_, first_line_, printed_;
};

// Why the browser tests cannot run here (empty when they can): Debian's chromium and
// puppeteer-core beside tests/playback/browser/drive.mjs (`driver`).
inline std::string BrowserMissing(const std::filesystem::path& driver) {
  if (RunShell("command -v chromium").exit_code != 0)
    return "Debian's chromium is not installed (scripts/setup.sh --tests installs it)";
  if (!std::filesystem::exists(driver / "node_modules/puppeteer-core"))
    return "puppeteer-core is not installed (scripts/setup.sh --tests: npm ci in " +
           driver.string() + ")";
  return "";
}

}  // namespace holocap::testing
