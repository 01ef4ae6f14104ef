// A GigE Vision camera simulated by libaravis, for tests and benchmarks of the `aravis:` driver
// without hardware. Apart from aravis this needs only the standard library, so that the
// holocap-fake-gige-camera program stays small and starts quickly.
#pragma once

#include <string>

namespace holocap {

// A GigE Vision camera simulated by libaravis: the ArvGvFakeCamera that arv-fake-gv-camera-0.8
// runs, a real GVCP/GVSP peer for tests and benchmarks without hardware.
struct FakeGigeCameraSpec {
  std::string address = "127.0.0.1";  // IPv4 address of an interface it listens on
  std::string serial = "GV01";         // its device id becomes "Aravis-Fake-<serial>"
  double lost_per_thousand = 0;        // GVSP packets it leaves unsent, per thousand
  // How often it looks for a software trigger. arv-fake-gv-camera-0.8 looks 25 times a second
  // (its TriggerMode=On frame period; AcquisitionFrameRate only paces free-running), so
  // triggers closer than 40 ms fold into one frame; a finer tick serves every trigger. It
  // busy-polls through the last millisecond before each tick, so 1 kHz keeps a core busy.
  double trigger_tick_hz = 25;
  // Pixel values: "ramp", libaravis' diagonal ramp whose start moves with every frame (a frame
  // assembled from two frames' packets breaks it), or "noise", pseudo-random bytes that no
  // codec can shrink, for measuring what a take's disk writes.
  std::string pattern = "ramp";

  void Check() const;  // throws Error explaining a bad value
};

// Serves one fake camera from this process until SIGTERM or SIGINT; returns the exit status
// (non-zero when the address cannot be bound). Call before this process starts any thread:
// the two signals are blocked for the whole process.
int ServeFakeGigeCamera(const FakeGigeCameraSpec& spec);

// The holocap-fake-gige-camera program built with this library, which serves one fake camera:
//   holocap-fake-gige-camera -i ADDRESS -s SERIAL [-r LOST_PER_THOUSAND] [-t TRIGGER_TICK_HZ]
//                            [-p ramp|noise]
std::string FakeGigeCameraProgram();

}  // namespace holocap
