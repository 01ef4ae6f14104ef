#include "bench/fuzz/targets.h"

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>

#include <unistd.h>

#include <nlohmann/json.hpp>

#include "core/camera.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/mesh.h"
#include "core/report.h"
#include "core/rig.h"
#include "core/take.h"
#include "interop/interop.h"
#include "playback/playback.h"
#include "splat/splat.h"

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

// A folder of this process's own for the readers that take files (removed at exit).
const std::filesystem::path& Scratch() {
  static const std::filesystem::path dir = [] {
    std::string pattern = (std::filesystem::temp_directory_path() / "holocap-fuzz-XXXXXX").string();
    if (::mkdtemp(pattern.data()) == nullptr) std::abort();
    std::atexit([] {
      std::error_code ignored;
      std::filesystem::remove_all(Scratch(), ignored);
    });
    return std::filesystem::path(pattern);
  }();
  return dir;
}

// Input bytes cut at the first NUL: (text before it, bytes after it).
std::pair<std::string, std::string> SplitAtNul(const std::string& text) {
  const size_t at = text.find('\0');
  if (at == std::string::npos) return {text, ""};
  return {text.substr(0, at), text.substr(at + 1)};
}

// model.json, a NUL, then gaussians.bin: the model read, saved and read back.
void SplatModelFiles(const std::string& text) {
  const auto [json, binary] = SplitAtNul(text);
  const std::filesystem::path dir = Scratch() / "model";
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  WriteFileAtomic(dir / "model.json", json);
  WriteFileAtomic(dir / "gaussians.bin", binary);
  const SplatModel model = SplatModel::Load(dir);
  MustReadBack("a splat model", [&] {
    model.Save(Scratch() / "saved");
    SplatModel::Load(Scratch() / "saved");
  });
}

// Two bytes choose the previous frame (0-63 Gaussians, degree 0-3); the rest is its delta.
void SplatDelta(const std::string& text) {
  if (text.size() < 2) return;
  splat::Gaussians previous;
  previous.sh_degree = static_cast<unsigned char>(text[1]) % 4;
  previous.Resize(static_cast<unsigned char>(text[0]) % 64);
  const std::string delta = text.substr(2);
  const splat::Gaussians next = ApplySplatDelta(previous, delta);
  const SplatDeltaCounts counts = CountSplatDelta(delta);
  const std::vector<int64_t> origin = SplatDeltaOrigins(delta);
  if (static_cast<int64_t>(origin.size()) != next.size() ||
      counts.added + previous.size() - counts.removed != next.size()) {
    std::fprintf(stderr, "a splat delta's counts disagree with what it decodes to\n");
    std::abort();
  }
}

// A site's manifest.json (beside an index.html).
void WebManifest(const std::string& text) {
  const std::filesystem::path dir = Scratch() / "site";
  std::filesystem::create_directories(dir);
  if (!std::filesystem::exists(dir / "index.html")) WriteFileAtomic(dir / "index.html", "<html>");
  WriteFileAtomic(dir / "manifest.json", text);
  std::string why;
  IsWebSite(dir, &why);
}

// One frame of a sharded export's record, against a stream folder holding a 16-byte chunk.
void WebRecord(const std::string& text) {
  const std::filesystem::path site = Scratch() / "records";
  if (!std::filesystem::exists(site / "streams/s/000001.hcc")) {
    std::filesystem::create_directories(site / "streams/s");
    WriteFileAtomic(site / "streams/s/000001.hcc", std::string(16, 'c'));
  }
  const nlohmann::json frame = nlohmann::json::parse(text, nullptr, false);
  if (frame.is_discarded()) return;
  CheckWebFrameRecord(frame, site, "streams/s", "s", 1);
}

void Ply(const std::string& text) {
  WriteFileAtomic(Scratch() / "mesh.ply", text);
  const Mesh mesh = ReadPly(Scratch() / "mesh.ply");
  MustReadBack("a PLY mesh", [&] {
    WritePly(Scratch() / "again.ply", mesh);
    ReadPly(Scratch() / "again.ply");
  });
}

void Glb(const std::string& text) {
  WriteFileAtomic(Scratch() / "mesh.glb", text);
  ReadTexturedGlb(Scratch() / "mesh.glb");
}

void CameraPathJson(const std::string& text) {
  ParseCameraPath(text, Scratch() / "path.json", Eigen::Vector3d::UnitZ(), 64, 48);
}

void ReportJson(const std::string& text) {
  const nlohmann::json report = ParseReport(text, "report.json");
  Printable(report["command"].get<std::string>());
  const nlohmann::json& summary = report["summary"];
  if (summary.contains("message")) Printable(summary["message"].get<std::string>());
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
    {"splat_model", SplatModelFiles},
    {"splat_delta", SplatDelta},
    {"web_manifest", WebManifest},
    {"web_record", WebRecord},
    {"ply", Ply},
    {"glb", Glb},
    {"camera_path", CameraPathJson},
    {"report_json", ReportJson},
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
