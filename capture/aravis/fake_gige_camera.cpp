#include <arv.h>
#include <pthread.h>
#include <signal.h>

#include "capture/aravis/fake_gige_camera.h"
#include "core/error.h"

namespace holocap {

void FakeGigeCameraSpec::Check() const {
  if (address.empty()) Fail("fake GigE camera: no address");
  // The GigE Vision bootstrap registers hold the serial in 16 bytes, NUL included.
  if (serial.empty() || serial.size() > 15) Fail("fake GigE camera: serial must have 1..15 characters");
  if (!(lost_per_thousand >= 0 && lost_per_thousand <= 1000)) {
    Fail("fake GigE camera: lost_per_thousand must be 0..1000");
  }
  // The camera sleeps whole microseconds between ticks.
  if (!(trigger_tick_hz > 0 && trigger_tick_hz <= 1e5)) Fail("fake GigE camera: trigger_tick_hz must be in (0, 1e5]");
}

int ServeFakeGigeCamera(const FakeGigeCameraSpec& spec) {
  spec.Check();
  // Blocked before the camera's thread exists, so that only sigwait() below receives them.
  sigset_t stop_signals;
  sigemptyset(&stop_signals);
  sigaddset(&stop_signals, SIGTERM);
  sigaddset(&stop_signals, SIGINT);
  pthread_sigmask(SIG_BLOCK, &stop_signals, nullptr);
  ArvGvFakeCamera* camera = arv_gv_fake_camera_new_full(spec.address.c_str(), spec.serial.c_str(), nullptr);
  if (camera == nullptr) return 2;
  g_object_set(camera, "gvsp-lost-ratio", spec.lost_per_thousand / 1000.0, nullptr);
  arv_fake_camera_set_trigger_frequency(arv_gv_fake_camera_get_fake_camera(camera), spec.trigger_tick_hz);
  int status = 0;
  if (arv_gv_fake_camera_is_running(camera)) {
    int signal = 0;
    sigwait(&stop_signals, &signal);
  } else {
    status = 3;
  }
  g_object_unref(camera);
  return status;
}

std::string FakeGigeCameraProgram() { return HOLOCAP_FAKE_GIGE_CAMERA_PROGRAM; }

}  // namespace holocap
