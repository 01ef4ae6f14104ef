// The reconstruction's textured meshes read back from binary glTF and drawn natively the way the
// web player's mesh stream draws them.
#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "core/error.h"
#include "core/fs.h"
#include "playback/internal/web_stream.h"
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
    if (offset + length > bin.size())
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
    if (view.size() < *count * element_bytes)
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
    if (offset + 8 + length > bytes.size()) Fail(file.string(), " is truncated");
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
  cv::Mat atlas = cv::imdecode(
      cv::Mat(1, static_cast<int>(encoded.size()), CV_8U, const_cast<char*>(encoded.data())),
      cv::IMREAD_COLOR);
  if (atlas.empty()) Fail(glb.file.string(), ": its atlas image does not decode");
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
    if (attributes.contains("TEXCOORD_0"))
      uvs = glb.Accessor(attributes.at("TEXCOORD_0").get<int>(), kFloat, "VEC2", 8, &count);
    if (attributes.contains("COLOR_0"))
      colors = glb.Accessor(attributes.at("COLOR_0").get<int>(), kUnsignedByte, "VEC4", 4, &count);
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

cv::Vec3f web::SampleAtlas(const cv::Mat& atlas, float u, float v) {
  const float x = u * atlas.cols - 0.5f, y = v * atlas.rows - 0.5f;
  const int x0 = static_cast<int>(std::floor(x)), y0 = static_cast<int>(std::floor(y));
  const float fx = x - x0, fy = y - y0;
  auto at = [&](int xi, int yi) {
    const cv::Vec3b& t =
        atlas.at<cv::Vec3b>(std::clamp(yi, 0, atlas.rows - 1), std::clamp(xi, 0, atlas.cols - 1));
    return cv::Vec3f(t[0], t[1], t[2]) * (1.0f / 255);
  };
  return (at(x0, y0) * (1 - fx) + at(x0 + 1, y0) * fx) * (1 - fy) +
         (at(x0, y0 + 1) * (1 - fx) + at(x0 + 1, y0 + 1) * fx) * fy;
}

RenderedView RenderTexturedMesh(const TexturedMeshFrame& mesh, const CameraModel& camera) {
  if (!camera.has_core()) Fail("camera lens ", camera.lensmodel(), " has no pinhole core");
  const double fx = camera.intrinsics()[0], fy = camera.intrinsics()[1];
  const double cx = camera.intrinsics()[2], cy = camera.intrinsics()[3];
  const int w = camera.width(), h = camera.height();
  RenderedView view;
  view.color = cv::Mat::zeros(h, w, CV_32FC3);
  view.alpha = cv::Mat::zeros(h, w, CV_32FC1);
  view.depth = cv::Mat(h, w, CV_32FC1, cv::Scalar(std::numeric_limits<float>::infinity()));
  const bool textured = !mesh.atlas.empty();
  constexpr double kNear = 1e-3;
  for (size_t f = 0; f < mesh.faces(); ++f) {
    Eigen::Vector3d p[3];
    double x[3], y[3], inv_z[3];
    bool behind = false;
    for (int k = 0; k < 3; ++k) {
      p[k] = camera.cam_from_world() * mesh.positions[3 * f + k].cast<double>();
      behind = behind || p[k].z() < kNear;
      inv_z[k] = 1.0 / p[k].z();
      x[k] = fx * p[k].x() * inv_z[k] + cx;
      y[k] = fy * p[k].y() * inv_z[k] + cy;
    }
    if (behind) continue;
    const double area = (x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0]);
    if (std::abs(area) < 1e-12) continue;
    const int x_lo = std::max(0, static_cast<int>(std::ceil(std::min({x[0], x[1], x[2]}))));
    const int x_hi = std::min(w - 1, static_cast<int>(std::floor(std::max({x[0], x[1], x[2]}))));
    const int y_lo = std::max(0, static_cast<int>(std::ceil(std::min({y[0], y[1], y[2]}))));
    const int y_hi = std::min(h - 1, static_cast<int>(std::floor(std::max({y[0], y[1], y[2]}))));
    for (int py = y_lo; py <= y_hi; ++py) {
      for (int px = x_lo; px <= x_hi; ++px) {
        double b[3];
        for (int k = 0; k < 3; ++k) {
          const int i = (k + 1) % 3, j = (k + 2) % 3;
          b[k] = ((x[j] - x[i]) * (py - y[i]) - (y[j] - y[i]) * (px - x[i])) / area;
        }
        if (b[0] < 0 || b[1] < 0 || b[2] < 0) continue;
        // Perspective-correct weights: screen barycentrics over depth, renormalised.
        const double q0 = b[0] * inv_z[0], q1 = b[1] * inv_z[1], q2 = b[2] * inv_z[2];
        const double inv = q0 + q1 + q2;
        const float z = static_cast<float>(1.0 / inv);
        float& depth = view.depth.at<float>(py, px);
        if (z >= depth) continue;
        depth = z;
        const float w0 = static_cast<float>(q0 / inv), w1 = static_cast<float>(q1 / inv),
                    w2 = 1.0f - w0 - w1;
        cv::Vec3f color;
        if (textured) {
          const Eigen::Vector2f uv =
              w0 * mesh.uvs[3 * f] + w1 * mesh.uvs[3 * f + 1] + w2 * mesh.uvs[3 * f + 2];
          color = web::SampleAtlas(mesh.atlas, uv.x(), uv.y());
        } else if (!mesh.colors.empty()) {
          const Eigen::Vector3f rgb =
              (w0 * mesh.colors[3 * f].cast<float>() + w1 * mesh.colors[3 * f + 1].cast<float>() +
               w2 * mesh.colors[3 * f + 2].cast<float>()) /
              255.0f;
          color = cv::Vec3f(rgb.z(), rgb.y(), rgb.x());
        } else {
          color = cv::Vec3f(0.5f, 0.5f, 0.5f);
        }
        view.color.at<cv::Vec3f>(py, px) = color;
        view.alpha.at<float>(py, px) = 1.0f;
      }
    }
  }
  view.depth.setTo(std::numeric_limits<float>::quiet_NaN(),
                   view.depth == std::numeric_limits<float>::infinity());
  return view;
}

}  // namespace holocap
