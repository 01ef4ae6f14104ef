// A GigE Vision camera for tests and benchmarks of the `aravis:` driver without hardware:
// libaravis' register and image model of a camera (ArvFakeCamera) behind a GVCP/GVSP peer written
// here, which answers packet resend requests. Apart from aravis this needs only the standard
// library, so that the holocap-fake-gige-camera program stays small and starts quickly.
#pragma once

#include <string>

namespace holocap {

// A simulated GigE Vision camera, a real GVCP/GVSP peer. Its registers, GenICam description and
// images are libaravis' ArvFakeCamera (the model arv-fake-gv-camera-0.8 serves). The protocol is
// served by one of two peers:
//   "holocap": written here. It answers discovery, READREG, WRITEREG, READMEM, WRITEMEM and
//     PACKETRESEND; it keeps the packets of its last frames, so a packet the host asks for again
//     is sent again (never dropped a second time), as a camera with a resend buffer does.
//   "libaravis": libaravis' ArvGvFakeCamera, which leaves resend requests unanswered (0.8.26),
//     so every frame that lost a packet stays incomplete.
struct FakeGigeCameraSpec {
  std::string address = "127.0.0.1";  // IPv4 address of an interface it listens on
  std::string serial = "GV01";        // its device id becomes "Aravis-Fake-<serial>"
  // GVSP packets it leaves unsent on their first sending, per thousand (a resent packet is
  // always sent).
  double lost_per_thousand = 0;
  // How often it looks for a software trigger. arv-fake-gv-camera-0.8 looks 25 times a second
  // (its TriggerMode=On frame period; AcquisitionFrameRate only paces free-running), so
  // triggers closer than 40 ms fold into one frame; a finer tick serves every trigger. The
  // "libaravis" peer busy-polls through the last millisecond before each tick, so 1 kHz keeps
  // a core busy; the "holocap" peer sleeps until the tick.
  double trigger_tick_hz = 25;
  // Pixel values: "ramp", libaravis' diagonal ramp whose start moves with every frame (a frame
  // assembled from two frames' packets breaks it), or "noise", pseudo-random bytes that no
  // codec can shrink, for measuring what a take's disk writes.
  std::string pattern = "ramp";
  std::string peer = "holocap";  // "holocap" | "libaravis" (see above)

  void Check() const;  // throws Error explaining a bad value
};

// Serves one fake camera from this process until SIGTERM or SIGINT; returns the exit status
// (non-zero when the address cannot be bound). Call before this process starts any thread:
// the two signals are blocked for the whole process.
int ServeFakeGigeCamera(const FakeGigeCameraSpec& spec);

// The holocap-fake-gige-camera program built with this library, which serves one fake camera:
//   holocap-fake-gige-camera -i ADDRESS -s SERIAL [-r LOST_PER_THOUSAND] [-t TRIGGER_TICK_HZ]
//                            [-p ramp|noise] [-m holocap|libaravis]
std::string FakeGigeCameraProgram();

}  // namespace holocap
