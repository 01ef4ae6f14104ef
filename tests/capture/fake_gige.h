// Fake GigE Vision cameras for tests, each a real process speaking GVCP/GVSP. The test process
// first moves into a network namespace of its own, so the addresses 127.0.0.1..N exist only
// there and vanish with the process, even when a test crashes; the cameras are started and
// stopped by their own process ids and are killed by the kernel if the test process dies first.
//
// By default each camera is arv-fake-gv-camera-0.8, which serves a software trigger only on a
// fixed 25 Hz tick. With a trigger tick given, each camera is holocap-fake-gige-camera, looking
// for triggers that often: libaravis' camera model behind holocap's GVCP/GVSP peer, which answers
// packet resend requests, or behind libaravis' own peer, which does not.
#pragma once

#include <fcntl.h>
#include <sched.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include "capture/aravis/aravis_driver.h"
#include "capture/aravis/fake_gige_camera.h"
#include "core/error.h"

namespace holocap::testing {

// Shared by the tests and bench/capture_bench; failures throw holocap::Error.

// Enters a private network namespace with the loopback interface up (once per process).
// Returns an empty string on success, else why it could not.
inline std::string EnterPrivateNetwork() {
  static std::string result = [] {
    if (unshare(CLONE_NEWNET) != 0)
      return std::string("unshare(CLONE_NEWNET) failed: ") + strerror(errno);
    if (std::system("ip link set lo up") != 0) return std::string("cannot bring lo up");
    return std::string();
  }();
  return result;
}

// Why this process cannot start fake cameras for lack of privilege (a network namespace of its
// own needs CAP_SYS_ADMIN, e.g. root), or an empty string when it can.
inline std::string LacksNetworkPrivilege() {
  const std::string error = EnterPrivateNetwork();
  return error.find(strerror(EPERM)) != std::string::npos
             ? error + " (needs CAP_SYS_ADMIN, e.g. root)"
             : "";
}

// For a test that starts fake cameras: skips, with the reason, without the privilege.
#define HOLOCAP_SKIP_WITHOUT_NETWORK_PRIVILEGE()                                         \
  if (const std::string why = ::holocap::testing::LacksNetworkPrivilege(); !why.empty()) \
  GTEST_SKIP() << "fake GigE cameras: " << why

class FakeGigeCameras {
 public:
  // SCHED_FIFO priority of the camera processes: above the recorder's trigger threads
  // (RecorderOptions::trigger_priority), which wait for each camera's acknowledgement.
  static constexpr int kCameraPriority = 20;

  // Starts `count` cameras on 127.0.0.1..count with serials HC1..HCn. `lost_per_thousand` is
  // their GVSP packet loss; `trigger_tick_hz` > 0 runs holocap-fake-gige-camera with that
  // software-trigger tick, 0 runs arv-fake-gv-camera-0.8 (25 Hz tick); `pattern` "noise"
  // (holocap-fake-gige-camera only) fills frames with bytes no codec can shrink; `peer` picks
  // holocap-fake-gige-camera's protocol peer ("holocap" resends lost packets, "libaravis" not).
  FakeGigeCameras(int count, int lost_per_thousand = 0, double trigger_tick_hz = 0,
                  const std::string& pattern = "ramp", const std::string& peer = "holocap") {
    if (pattern != "ramp" && trigger_tick_hz <= 0)
      Fail("fake GigE cameras: arv-fake-gv-camera-0.8 has only the ramp");
    std::string error = EnterPrivateNetwork();
    if (!error.empty()) Fail("fake GigE cameras: ", error);
    for (int i = 1; i <= count; ++i) {
      const std::string address = "127.0.0." + std::to_string(i);
      if (i > 1) std::system(("ip addr add " + address + "/32 dev lo 2>/dev/null").c_str());
      const std::string serial = "HC" + std::to_string(i);
      const std::string ratio = std::to_string(lost_per_thousand);
      // Built before fork(): the child of a threaded process may only exec.
      const std::string program = FakeGigeCameraProgram();
      const std::string tick = std::to_string(trigger_tick_hz);
      const int null_output = open("/dev/null", O_WRONLY | O_CLOEXEC);
      std::fflush(nullptr);  // or the child flushes our buffered output a second time
      pid_t pid = fork();
      if (pid == 0) {
        prctl(PR_SET_PDEATHSIG, SIGKILL);
        // A camera is hardware of its own: the host's load never delays its answer to a
        // trigger. Real-time scheduling gives each simulated camera that independence on a
        // machine whose cores the recorder and other work share (kept when refused).
        sched_param param{};
        param.sched_priority = kCameraPriority;
        sched_setscheduler(0, SCHED_FIFO, &param);
        if (null_output >= 0) dup2(null_output, STDOUT_FILENO);
        if (trigger_tick_hz > 0) {
          execl(program.c_str(), program.c_str(), "-i", address.c_str(), "-s", serial.c_str(), "-r",
                ratio.c_str(), "-t", tick.c_str(), "-p", pattern.c_str(), "-m", peer.c_str(),
                static_cast<char*>(nullptr));
        } else {
          execlp("arv-fake-gv-camera-0.8", "arv-fake-gv-camera-0.8", "-i", address.c_str(), "-s",
                 serial.c_str(), "-r", ratio.c_str(), static_cast<char*>(nullptr));
        }
        _exit(127);
      }
      if (null_output >= 0) close(null_output);
      pids_.push_back(pid);
      ids_.push_back("Aravis-Fake-HC" + std::to_string(i));
    }
    WaitUntilDiscovered();
  }
  ~FakeGigeCameras() {
    for (size_t i = 0; i < pids_.size(); ++i) Stop(static_cast<int>(i));
  }
  FakeGigeCameras(const FakeGigeCameras&) = delete;
  FakeGigeCameras& operator=(const FakeGigeCameras&) = delete;

  // The device id of camera i (0-based), as aravis names it.
  const std::string& id(int i) const { return ids_.at(i); }
  pid_t pid(int i) const { return pids_.at(i); }
  int size() const { return static_cast<int>(ids_.size()); }

  // Kills camera i now (a camera that vanishes) and reaps it.
  void Kill(int i) { Stop(i, SIGKILL); }

 private:
  void Stop(int i, int signal = SIGTERM) {
    if (pids_[i] <= 0) return;
    kill(pids_[i], signal);
    int status = 0;
    for (int tries = 0; tries < 100; ++tries) {
      if (waitpid(pids_[i], &status, WNOHANG) == pids_[i]) {
        pids_[i] = -1;
        return;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    kill(pids_[i], SIGKILL);
    waitpid(pids_[i], &status, 0);
    pids_[i] = -1;
  }

  void WaitUntilDiscovered() {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(5);
    DriverRegistry registry;
    RegisterAravisDriver(registry);
    while (std::chrono::steady_clock::now() < deadline) {
      int found = 0;
      for (const auto& device : registry.ForUri("aravis:x").Enumerate()) {
        for (const auto& id : ids_) found += device.uri == "aravis:" + id;
      }
      if (found == static_cast<int>(ids_.size())) return;
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    for (size_t i = 0; i < pids_.size(); ++i) Stop(static_cast<int>(i));
    Fail("the fake cameras did not all answer discovery within 5 s");
  }

  std::vector<pid_t> pids_;
  std::vector<std::string> ids_;
};

}  // namespace holocap::testing
