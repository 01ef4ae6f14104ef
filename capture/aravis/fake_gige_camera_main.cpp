// holocap-fake-gige-camera: one simulated GigE Vision camera, libaravis' camera model served
// by holocap's GVCP/GVSP peer (which answers packet resend requests) or by libaravis' own, with
// a chosen software-trigger tick (see FakeGigeCameraSpec). Started by the capture tests and
// capture_bench.
//
//   holocap-fake-gige-camera -i ADDRESS -s SERIAL [-r LOST_PER_THOUSAND] [-t TRIGGER_TICK_HZ]
//                            [-p ramp|noise] [-m holocap|libaravis]
#include <cstdio>
#include <string>

#include "capture/aravis/fake_gige_camera.h"
#include "core/error.h"

int main(int argc, char** argv) {
  holocap::FakeGigeCameraSpec spec;
  try {
    for (int i = 1; i < argc; i += 2) {
      const std::string flag = argv[i];
      if (i + 1 >= argc) holocap::Fail("option ", flag, " needs a value");
      const std::string value = argv[i + 1];
      if (flag == "-i") {
        spec.address = value;
      } else if (flag == "-s") {
        spec.serial = value;
      } else if (flag == "-r") {
        spec.lost_per_thousand = std::stod(value);
      } else if (flag == "-t") {
        spec.trigger_tick_hz = std::stod(value);
      } else if (flag == "-p") {
        spec.pattern = value;
      } else if (flag == "-m") {
        spec.peer = value;
      } else {
        holocap::Fail("unknown option ", flag,
                      " (expected -i ADDRESS -s SERIAL [-r LOST] [-t TICK_HZ] [-p ramp|noise]",
                      " [-m holocap|libaravis])");
      }
    }
    const int status = holocap::ServeFakeGigeCamera(spec);
    if (status != 0)
      std::fprintf(stderr, "holocap-fake-gige-camera: cannot serve on %s\n", spec.address.c_str());
    return status;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "holocap-fake-gige-camera: %s\n", e.what());
    return 2;
  }
}
