// Binary glTF (.glb) meshes as holocap writes them, read back for playback and the web export.
#include <cstring>
#include <nlohmann/json.hpp>
#include <opencv2/imgproc.hpp>

#include "core/error.h"
#include "core/fs.h"
#include "core/image.h"
#include "playback/playback.h"

namespace holocap {
namespace {

uint32_t ReadU32(const std::string& bytes, size_t offset) {
  uint32_t value = 0;
  std::memcpy(&value, bytes.data() + offset, 4);
  return value;
}

// A glTF accessor's bytes, checked against the BIN chunk and the expected layout.
struct GlbReader {
  std::filesystem::path file;
  nlohmann::json json;
  std::string bin;

  std::string_view View(int view_index) const {
    const auto& view = json.at("bufferViews").at(view_index);
    const size_t offset = view.value("byteOffset", size_t{0});
    const size_t length = view.at("byteLength").get<size_t>();
    if (offset > bin.size() || length > bin.size() - offset)
      Fail(file.string(), ": bufferView ", view_index, " runs past the binary chunk");
    return std::string_view(bin).substr(offset, length);
  }
  std::string_view Accessor(int index, int component, const char* type, size_t element_bytes,
                            size_t* count) const {
    const auto& accessor = json.at("accessors").at(index);
    if (accessor.at("componentType").get<int>() != component ||
        accessor.at("type").get<std::string>() != type || accessor.contains("byteOffset")) {
      Fail(file.string(), ": accessor ", index, " is not a packed ", type,
           " of the component type holocap writes");
    }
    *count = accessor.at("count").get<size_t>();
    const std::string_view view = View(accessor.at("bufferView").get<int>());
    if (*count > view.size() / element_bytes)
      Fail(file.string(), ": accessor ", index, " is shorter than its count");
    return view.substr(0, *count * element_bytes);
  }
};

GlbReader OpenGlb(const std::filesystem::path& file) {
  GlbReader reader{file, {}, {}};
  const std::string bytes = ReadFileToString(file);
  if (bytes.size() < 20 || bytes.compare(0, 4, "glTF") != 0 || ReadU32(bytes, 4) != 2)
    Fail(file.string(), " is not a binary glTF 2.0 file");
  size_t offset = 12;
  while (offset + 8 <= bytes.size()) {
    const uint32_t length = ReadU32(bytes, offset), type = ReadU32(bytes, offset + 4);
    if (length > bytes.size() - offset - 8) Fail(file.string(), " is truncated");
    const std::string chunk = bytes.substr(offset + 8, length);
    if (type == 0x4E4F534Au) {
      reader.json = nlohmann::json::parse(chunk, nullptr, false);
      if (reader.json.is_discarded()) Fail(file.string(), ": its JSON chunk does not parse");
    } else if (type == 0x004E4942u) {
      reader.bin = chunk;
    }
    offset += 8 + length;
  }
  if (!reader.json.is_object()) Fail(file.string(), " has no JSON chunk");
  return reader;
}

// The atlas the primitive's material names (an embedded image), or empty.
cv::Mat ReadAtlas(const GlbReader& glb, const nlohmann::json& primitive) {
  if (!primitive.contains("material")) return {};
  const auto& material = glb.json.at("materials").at(primitive.at("material").get<int>());
  const auto pbr = material.value("pbrMetallicRoughness", nlohmann::json::object());
  if (!pbr.contains("baseColorTexture")) return {};
  const auto& texture =
      glb.json.at("textures").at(pbr.at("baseColorTexture").at("index").get<int>());
  const auto& image = glb.json.at("images").at(texture.at("source").get<int>());
  const std::string_view encoded = glb.View(image.at("bufferView").get<int>());
  // Checked like a frame before it is decoded: a complete PNG whose header asks no more
  // pixels than the limit and its bytes allow.
  cv::Mat atlas = DecodePng(std::string(encoded), glb.file.string() + " (its atlas)");
  if (atlas.depth() != CV_8U) Fail(glb.file.string(), ": its atlas is not 8-bit");
  if (atlas.channels() == 1) cv::cvtColor(atlas, atlas, cv::COLOR_GRAY2BGR);
  if (atlas.channels() == 4) cv::cvtColor(atlas, atlas, cv::COLOR_BGRA2BGR);
  if (atlas.channels() != 3) Fail(glb.file.string(), ": its atlas is not a colour image");
  return atlas;
}

}  // namespace

TexturedMeshFrame ReadTexturedGlb(const std::filesystem::path& file) {
  const GlbReader glb = OpenGlb(file);
  TexturedMeshFrame mesh;
  try {
    const auto& primitive = glb.json.at("meshes").at(0).at("primitives").at(0);
    const auto& attributes = primitive.at("attributes");
    constexpr int kFloat = 5126, kUnsignedInt = 5125, kUnsignedByte = 5121;
    size_t vertices = 0, indices = 0, count = 0;
    const std::string_view positions =
        glb.Accessor(attributes.at("POSITION").get<int>(), kFloat, "VEC3", 12, &vertices);
    const std::string_view index_bytes =
        glb.Accessor(primitive.at("indices").get<int>(), kUnsignedInt, "SCALAR", 4, &indices);
    std::string_view uvs, colors;
    // Every attribute holds one value per vertex the indices may name.
    if (attributes.contains("TEXCOORD_0")) {
      uvs = glb.Accessor(attributes.at("TEXCOORD_0").get<int>(), kFloat, "VEC2", 8, &count);
      if (count < vertices) Fail(file.string(), ": TEXCOORD_0 has fewer values than POSITION");
    }
    if (attributes.contains("COLOR_0")) {
      colors = glb.Accessor(attributes.at("COLOR_0").get<int>(), kUnsignedByte, "VEC4", 4, &count);
      if (count < vertices) Fail(file.string(), ": COLOR_0 has fewer values than POSITION");
    }
    if (indices % 3 != 0) Fail(file.string(), ": the index count is not a multiple of 3");
    mesh.positions.resize(indices);
    if (!uvs.empty()) mesh.uvs.resize(indices);
    if (!colors.empty() && uvs.empty()) mesh.colors.resize(indices);
    for (size_t i = 0; i < indices; ++i) {
      uint32_t v = 0;
      std::memcpy(&v, index_bytes.data() + 4 * i, 4);
      if (v >= vertices) Fail(file.string(), ": index ", v, " names a missing vertex");
      std::memcpy(mesh.positions[i].data(), positions.data() + 12 * v, 12);
      if (!mesh.uvs.empty()) std::memcpy(mesh.uvs[i].data(), uvs.data() + 8 * v, 8);
      if (!mesh.colors.empty()) std::memcpy(mesh.colors[i].data(), colors.data() + 4 * v, 3);
    }
    if (!mesh.uvs.empty()) mesh.atlas = ReadAtlas(glb, primitive);
    if (mesh.atlas.empty()) mesh.uvs.clear();
  } catch (const nlohmann::json::exception& e) {
    Fail(file.string(), ": not a mesh as holocap writes it: ", e.what());
  }
  return mesh;
}

}  // namespace holocap
