// libFuzzer entry for one foreign-format parser, chosen at compile time by HOLOCAP_FUZZ_TARGET.
// A parser may reject its input only with holocap::Error; any other exception, a crash or a
// sanitizer report is a bug. Parsed cameras are also converted, so the conventions code and
// mrcal behind CameraModel see the fuzzed numbers.
#include <cstddef>
#include <cstdint>
#include <string>

#include "core/camera.h"
#include "core/error.h"
#include "interop/interop.h"

namespace holocap {
namespace {

void ConvertKrt(const std::vector<KrtCamera>& cameras) {
  for (KrtCamera camera : cameras) {
    camera.width = 64;
    camera.height = 48;
    try {
      CameraFromKrt(camera, Pose::Identity());
    } catch (const Error&) {
    }
  }
}

void Run(const std::string& text) {
#if HOLOCAP_FUZZ_TARGET == 1
  ConvertKrt(ParseMiddleburyPar(text, "fuzz_par.txt"));
#elif HOLOCAP_FUZZ_TARGET == 2
  std::vector<KrtCamera> cameras = ParseNeuralVolumesKrt(text, "KRT");
  ConvertKrt(cameras);
  ParseNeuralVolumesKrt(FormatNeuralVolumesKrt(cameras), "KRT (rewritten)");
#elif HOLOCAP_FUZZ_TARGET == 3
  ConvertKrt(ParsePanopticCalibration(text, "calibration_fuzz.json"));
#elif HOLOCAP_FUZZ_TARGET == 4
  // The first byte picks the file, so one corpus covers all three.
  if (text.empty()) return;
  const std::string body = text.substr(1);
  switch (static_cast<unsigned char>(text[0]) % 3) {
    case 0:
      for (const auto& [id, camera] : ParseColmapCameras(body, "cameras.txt")) {
        try {
          ColmapFromCamera(CameraFromColmap(camera, Pose::Identity()), id);
        } catch (const Error&) {
        }
      }
      break;
    case 1:
      ParseColmapImages(FormatColmapImages(ParseColmapImages(body, "images.txt")),
                        "images.txt (rewritten)");
      break;
    case 2:
      ParseColmapPoints(FormatColmapPoints(ParseColmapPoints(body, "points3D.txt")),
                        "points3D.txt (rewritten)");
      break;
  }
#elif HOLOCAP_FUZZ_TARGET == 5
  for (const auto& frame : ParseNerfTransforms(text, "transforms.json")) {
    try {
      NerfFromCamera(
          CameraFromNerf(frame.intrinsics, frame.world_from_cam_gl, 0, 0, "transforms.json"));
    } catch (const Error&) {
    }
  }
#elif HOLOCAP_FUZZ_TARGET == 6
  CameraModel::Parse(text, "fuzz.cameramodel");
#else
#error "HOLOCAP_FUZZ_TARGET must be 1..6"
#endif
}

}  // namespace
}  // namespace holocap

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  try {
    holocap::Run(std::string(reinterpret_cast<const char*>(data), size));
  } catch (const holocap::Error&) {
    // The one way a parser may reject its input.
  }
  return 0;
}
