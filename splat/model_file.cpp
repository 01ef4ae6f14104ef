// A splat model's files: model.json, gaussians.bin, cameras/ and the deltas of its frames, written
// and read (every count checked against the bytes that hold it).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>

#include "core/error.h"
#include "core/fs.h"
#include "splat/splat.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;

// gaussians.bin holds these fields one after the other, float32 little-endian.
struct Field {
  const char* name;
  std::vector<float> splat::Gaussians::*member;
  int per_gaussian;  // 0: 3 x coefficients
};
const Field kFields[] = {{"position", &splat::Gaussians::position, 3},
                         {"rotation", &splat::Gaussians::rotation, 4},
                         {"log_scale", &splat::Gaussians::log_scale, 3},
                         {"opacity", &splat::Gaussians::opacity, 1},
                         {"sh", &splat::Gaussians::sh, 0}};

}  // namespace

void SplatModel::Save(const fs::path& dir, bool write_gaussians) const {
  CreateDirectories(dir / "cameras");
  std::string bytes;
  nlohmann::json fields = nlohmann::json::array();
  for (const Field& field : kFields) {
    const std::vector<float>& values = gaussians.*field.member;
    if (write_gaussians)
      bytes.append(reinterpret_cast<const char*>(values.data()), values.size() * sizeof(float));
    fields.push_back(field.name);
  }
  if (write_gaussians) WriteFileAtomic(dir / "gaussians.bin", bytes);
  nlohmann::json names = nlohmann::json::array();
  for (size_t k = 0; k < cameras.size(); ++k) {
    const std::string name = Cat("view", k);
    if (write_gaussians) cameras[k].Write(dir / "cameras" / (name + ".cameramodel"));
    names.push_back(name);
  }
  const Eigen::Vector3d lo = box.min, hi = box.max;
  nlohmann::json json = {
      {"method", "splat"},
      {"format_version", bases.empty() ? 1 : 2},
      {"gaussians", gaussians.size()},
      {"frames", frames},
      {"frame_sets",
       std::vector<int64_t>(frame_sets.begin(),
                            frame_sets.begin() + std::min<int64_t>(frames, frame_sets.size()))},
      {"deltas", "deltas/<frame, 6 digits>.bin (splat/splat.h)"},
      {"sh_degree", gaussians.sh_degree},
      {"fields", fields},
      {"format", "float32 little-endian, each field for every Gaussian in turn"},
      {"cameras", names},
      {"box_min", {lo.x(), lo.y(), lo.z()}},
      {"box_max", {hi.x(), hi.y(), hi.z()}},
      {"plan", plan}};
  if (!bases.empty()) {
    json["delta_bases"] = std::vector<int64_t>(
        bases.begin(), bases.begin() + std::min<int64_t>(frames, bases.size()));
  }
  WriteFileAtomic(dir / "model.json", json.dump(2) + "\n");
}

SplatModel SplatModel::Load(const fs::path& dir) {
  const fs::path file = dir / "model.json";
  const fs::path binary = dir / "gaussians.bin";
  nlohmann::json json;
  try {
    json = nlohmann::json::parse(ReadFileToString(file));
  } catch (const nlohmann::json::exception& e) {
    Fail("cannot read ", file.string(), ": ", e.what());
  }
  SplatModel model;
  std::vector<std::string> camera_names;
  if (!json.is_object() || !json.contains("method") || json["method"] != "splat")
    Fail(dir.string(), " does not hold a splat model");
  try {
    const int64_t count = json.at("gaussians").get<int64_t>();
    model.gaussians.sh_degree = json.at("sh_degree").get<int>();
    if (count < 0 || model.gaussians.sh_degree < 0 ||
        model.gaussians.sh_degree > splat::kMaxShDegree) {
      Fail("bad count or degree");
    }
    // The count is checked against gaussians.bin's real size before anything is allocated.
    const uint64_t per_gaussian =
        sizeof(float) *
        (11 + 3 * static_cast<uint64_t>(splat::ShCoefficients(model.gaussians.sh_degree)));
    const std::string bytes = ReadFileToString(binary);
    if (static_cast<uint64_t>(count) != bytes.size() / per_gaussian ||
        bytes.size() % per_gaussian != 0) {
      Fail("it declares ", count, " Gaussians of degree ", model.gaussians.sh_degree, " (",
           per_gaussian, " bytes each) but '", binary.string(), "' holds ", bytes.size(), " bytes");
    }
    model.gaussians.Resize(count);
    size_t offset = 0;
    for (const Field& field : kFields) {
      std::vector<float>& values = model.gaussians.*field.member;
      const size_t size = values.size() * sizeof(float);
      std::memcpy(values.data(), bytes.data() + offset, size);
      offset += size;
    }
    for (const auto& name : json.at("cameras")) {
      camera_names.push_back(name.get<std::string>());
      const std::string& text = camera_names.back();
      if (text.empty() || text.find_first_of("/\\") != std::string::npos || text == "." ||
          text == "..")
        Fail("camera name '", text, "' is not a plain name");
    }
    const auto lo = json.at("box_min").get<std::vector<double>>();
    const auto hi = json.at("box_max").get<std::vector<double>>();
    if (lo.size() != 3 || hi.size() != 3 ||
        !std::all_of(lo.begin(), lo.end(), [](double v) { return std::isfinite(v); }) ||
        !std::all_of(hi.begin(), hi.end(), [](double v) { return std::isfinite(v); }))
      Fail("box_min and box_max must be 3 finite numbers each");
    model.box = Box{Eigen::Vector3d(lo[0], lo[1], lo[2]), Eigen::Vector3d(hi[0], hi[1], hi[2])};
    model.plan = json.value("plan", nlohmann::json::object());
    model.frames = json.value("frames", int64_t{1});
    model.frame_sets = json.value("frame_sets", std::vector<int64_t>{});
    if (model.frames < 1) Fail("frames must be at least 1");
    const int version = json.value("format_version", 1);
    if (version > 2) Fail("format version ", version, " is newer than this program's (2)");
    if (version == 2) {
      model.bases = json.at("delta_bases").get<std::vector<int64_t>>();
      if (static_cast<int64_t>(model.bases.size()) != model.frames)
        Fail("delta_bases must name a base for each of its frames");
      for (int64_t f = 0; f < model.frames; ++f) {
        if (f == 0 ? model.bases[f] != -1 : model.bases[f] < 0 || model.bases[f] >= f)
          Fail("frame ", f, "'s base ", model.bases[f], " is not an earlier frame");
      }
    }
  } catch (const nlohmann::json::exception& e) {
    Fail(file.string(), ": ", e.what());
  } catch (const Error& e) {
    Fail(file.string(), ": ", e.what());
  }
  // A camera model's errors name its own file.
  for (const auto& name : camera_names)
    model.cameras.push_back(CameraModel::Read(dir / "cameras" / (name + ".cameramodel")));
  return model;
}

fs::path SplatDeltaFile(const fs::path& dir, int64_t frame) {
  char name[32];
  std::snprintf(name, sizeof(name), "%06lld.bin", static_cast<long long>(frame));
  return dir / "deltas" / name;
}

splat::Gaussians SplatModel::Frame(const fs::path& dir, int64_t frame,
                                   const splat::Gaussians* previous, int64_t previous_frame) const {
  if (frame < 0 || frame >= frames)
    Fail("frame ", frame, " is outside the splat model's 0..", frames - 1);
  // The frames whose deltas lead from frame 0 (or from `previous`) to `frame`, last first.
  std::vector<int64_t> way;
  bool resume = false;
  for (int64_t k = frame; k > 0; k = Base(k)) {
    if (previous != nullptr && k == previous_frame) {
      resume = true;
      break;
    }
    way.push_back(k);
  }
  splat::Gaussians current = resume ? *previous : gaussians;
  for (auto k = way.rbegin(); k != way.rend(); ++k)
    current = ApplySplatDeltaFile(current, SplatDeltaFile(dir, *k));
  return current;
}

int64_t SplatModel::Base(int64_t frame) const {
  if (frame <= 0) return -1;
  return frame < static_cast<int64_t>(bases.size()) ? bases[frame] : frame - 1;
}

}  // namespace holocap
