#include <arv.h>
#include <pthread.h>
#include <signal.h>

#include <cstdint>

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
  if (pattern != "ramp" && pattern != "noise") Fail("fake GigE camera: pattern must be ramp or noise (not '", pattern, "')");
}

namespace {

// ArvFakeCameraFillPattern: every byte of the frame from a xorshift generator that runs on
// from frame to frame.
void FillNoise(ArvBuffer* buffer, void* state, guint32, guint32, ArvPixelFormat pixel_format) {
  // The buffer's received size is still 0 here: the image's own size says what to fill.
  const size_t size = static_cast<size_t>(arv_buffer_get_image_width(buffer)) * arv_buffer_get_image_height(buffer) *
                      ARV_PIXEL_FORMAT_BIT_PER_PIXEL(pixel_format) / 8;
  auto* data = static_cast<uint8_t*>(const_cast<void*>(arv_buffer_get_data(buffer, nullptr)));
  uint64_t& x = *static_cast<uint64_t*>(state);
  for (size_t i = 0; i < size; i += 8) {
    x ^= x << 13;
    x ^= x >> 7;
    x ^= x << 17;
    for (size_t k = 0; k < 8 && i + k < size; ++k) data[i + k] = static_cast<uint8_t>(x >> (8 * k));
  }
}

}  // namespace

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
  ArvFakeCamera* fake = arv_gv_fake_camera_get_fake_camera(camera);
  arv_fake_camera_set_trigger_frequency(fake, spec.trigger_tick_hz);
  uint64_t noise_state = 0x9e3779b97f4a7c15ull;
  if (spec.pattern == "noise") arv_fake_camera_set_fill_pattern(fake, &FillNoise, &noise_state);
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
