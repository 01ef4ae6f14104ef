#include "bench/fuzz/targets.h"

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>

#include "core/camera.h"
#include "core/error.h"
#include "core/rig.h"
#include "core/take.h"
#include "interop/interop.h"

namespace holocap::fuzz {
namespace {

// What holocap writes must read back: an Error there is a bug of the writer or the parser.
template <typename Read>
void MustReadBack(const char* what, const Read& read) {
  try {
    read();
  } catch (const Error& e) {
    std::fprintf(stderr, "%s does not read back: %s\n", what, e.what());
    std::abort();
  }
}

// Parsed cameras are converted too, so the conventions code and mrcal see the fuzzed numbers.
void ConvertKrt(const std::vector<KrtCamera>& cameras) {
  for (KrtCamera camera : cameras) {
    if (camera.width == 0) camera.width = 64;
    if (camera.height == 0) camera.height = 48;
    try {
      CameraFromKrt(camera, Pose::Identity());
    } catch (const Error&) {
    }
  }
}

void Middlebury(const std::string& text) { ConvertKrt(ParseMiddleburyPar(text, "fuzz_par.txt")); }

void Krt(const std::string& text) {
  std::vector<KrtCamera> cameras = ParseNeuralVolumesKrt(text, "KRT");
  ConvertKrt(cameras);
  MustReadBack("KRT", [&] { ParseNeuralVolumesKrt(FormatNeuralVolumesKrt(cameras), "KRT'"); });
}

void Panoptic(const std::string& text) {
  ConvertKrt(ParsePanopticCalibration(text, "calibration_fuzz.json"));
}

void ColmapCameras(const std::string& text) {
  std::map<int64_t, ColmapCamera> cameras = ParseColmapCameras(text, "cameras.txt");
  for (const auto& [id, camera] : cameras) {
    try {
      ColmapFromCamera(CameraFromColmap(camera, Pose::Identity()), id);
    } catch (const Error&) {
    }
  }
  MustReadBack("cameras.txt",
               [&] { ParseColmapCameras(FormatColmapCameras(cameras), "cameras.txt'"); });
}

void ColmapImages(const std::string& text) {
  std::vector<ColmapImage> images = ParseColmapImages(text, "images.txt");
  MustReadBack("images.txt", [&] { ParseColmapImages(FormatColmapImages(images), "images.txt'"); });
}

void ColmapPoints(const std::string& text) {
  std::vector<ColmapPoint> points = ParseColmapPoints(text, "points3D.txt");
  MustReadBack("points3D.txt",
               [&] { ParseColmapPoints(FormatColmapPoints(points), "points3D.txt'"); });
}

void Nerf(const std::string& text) {
  for (const auto& frame : ParseNerfTransforms(text, "transforms.json")) {
    try {
      NerfFromCamera(
          CameraFromNerf(frame.intrinsics, frame.world_from_cam_gl, 0, 0, "transforms.json"));
    } catch (const Error&) {
    }
  }
}

void Cameramodel(const std::string& text) {
  CameraModel camera = CameraModel::Parse(text, "fuzz.cameramodel");
  MustReadBack(".cameramodel", [&] { CameraModel::Parse(camera.ToString(), "fuzz.cameramodel'"); });
}

// Index lines name frame files; here every non-empty name exists.
bool FrameExists(const std::string& file) { return !file.empty(); }

void TakeJson(const std::string& text) {
  Take take = Take::Parse("fuzz-take", text, "", FrameExists);
  MustReadBack("take.json rig", [&] { RigDescription::FromJson(take.rig().ToJson(), "rig'"); });
  for (const StreamInfo& stream : take.streams())
    MustReadBack("take.json stream", [&] { StreamInfo::FromJson(stream.ToJson()); });
}

void IndexJsonl(const std::string& text) {
  static const std::string manifest = R"({"format": "holocap-take", "format_version": 1,
    "state": "complete", "rig": {"name": "rig", "sync": "software", "fps": 30, "sensors": [
      {"name": "cam0", "uri": "sim:studio8#cam0", "role": "color"},
      {"name": "depth0", "uri": "sim:studio8#depth0", "role": "depth", "paired_with": "cam0"}]},
    "streams": [
      {"name": "cam0", "uri": "sim:studio8#cam0", "role": "color", "width": 64, "height": 48,
       "pixel_format": "bgr8", "codec": "png", "clock": "sim"},
      {"name": "depth0", "uri": "sim:studio8#depth0", "role": "depth", "width": 64,
       "height": 48, "pixel_format": "depth_m", "codec": "exr", "clock": "sim",
       "paired_with": "cam0"}],
    "metadata": {}, "dropped": {"cam0": 0, "depth0": 0}, "frame_sets": 2, "index": "index.jsonl"})";
  Take take = Take::Parse("fuzz-take", manifest, text, FrameExists);
  for (const FrameSetEntry& entry : take.entries()) {
    for (const FrameSetEntry::Item& item : entry.items) take.stream(item.sensor);
  }
}

void RigYaml(const std::string& text) {
  RigDescription rig = RigDescription::ParseYaml(text, "rig.yaml");
  MustReadBack("rig.yaml", [&] { RigDescription::ParseJson(rig.ToJson().dump(), "rig.json'"); });
}

void RigJson(const std::string& text) {
  RigDescription rig = RigDescription::ParseJson(text, "rig.json");
  MustReadBack("rig.json", [&] { RigDescription::ParseJson(rig.ToJson().dump(), "rig.json'"); });
}

using Parser = void (*)(const std::string& text);
struct NamedParser {
  const char* name;
  Parser parse;
};
constexpr NamedParser kTargets[] = {
    {"middlebury", Middlebury},
    {"krt", Krt},
    {"panoptic", Panoptic},
    {"colmap_cameras", ColmapCameras},
    {"colmap_images", ColmapImages},
    {"colmap_points", ColmapPoints},
    {"nerf", Nerf},
    {"cameramodel", Cameramodel},
    {"take_json", TakeJson},
    {"index_jsonl", IndexJsonl},
    {"rig_yaml", RigYaml},
    {"rig_json", RigJson},
};

Parser Find(const char* target) {
  for (const NamedParser& named : kTargets) {
    if (std::strcmp(named.name, target) == 0) return named.parse;
  }
  std::fprintf(stderr, "no fuzz target named '%s'\n", target);
  std::abort();
}

}  // namespace

int RunTarget(const char* target, const uint8_t* data, size_t size) {
  static const Parser parse = Find(target);
  try {
    parse(std::string(reinterpret_cast<const char*>(data), size));
  } catch (const Error&) {
    // The one way a parser may reject its input.
  }
  return 0;
}

}  // namespace holocap::fuzz
