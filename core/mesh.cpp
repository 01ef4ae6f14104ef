#include "core/mesh.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <random>
#include <sstream>

#include "core/error.h"
#include "core/fs.h"

namespace holocap {

void Mesh::ComputeNormals() {
  normals.assign(vertices.size(), Eigen::Vector3f::Zero());
  for (const auto& face : faces) {
    const Eigen::Vector3f& a = vertices[face[0]];
    Eigen::Vector3f n = (vertices[face[1]] - a).cross(vertices[face[2]] - a);  // |n| = 2 area
    for (int k = 0; k < 3; ++k) normals[face[k]] += n;
  }
  for (auto& n : normals) {
    float norm = n.norm();
    n = norm > 0 ? Eigen::Vector3f(n / norm) : Eigen::Vector3f::Zero();
  }
}

VertexNeighbours NeighboursOf(const Mesh& mesh) {
  const size_t n = mesh.vertices.size();
  VertexNeighbours out;
  out.start.assign(n + 1, 0);
  for (const Eigen::Vector3i& f : mesh.faces) {
    for (int k = 0; k < 3; ++k) out.start[f[k] + 1] += 2;
  }
  for (size_t i = 0; i < n; ++i) out.start[i + 1] += out.start[i];
  out.neighbours.resize(out.start[n]);
  std::vector<int32_t> fill(out.start.begin(), out.start.end() - 1);
  for (const Eigen::Vector3i& f : mesh.faces) {
    for (int k = 0; k < 3; ++k) {
      out.neighbours[fill[f[k]]++] = f[(k + 1) % 3];
      out.neighbours[fill[f[k]]++] = f[(k + 2) % 3];
    }
  }
  return out;
}

void Mesh::Append(const Mesh& other) {
  const int offset = static_cast<int>(vertices.size());
  const bool keep_normals =
      normals.size() == vertices.size() && other.normals.size() == other.vertices.size();
  const bool keep_colors =
      colors.size() == vertices.size() && other.colors.size() == other.vertices.size();
  vertices.insert(vertices.end(), other.vertices.begin(), other.vertices.end());
  for (const auto& face : other.faces) faces.push_back(face.array() + offset);
  if (keep_normals) {
    normals.insert(normals.end(), other.normals.begin(), other.normals.end());
  } else {
    normals.clear();
  }
  if (keep_colors) {
    colors.insert(colors.end(), other.colors.begin(), other.colors.end());
  } else {
    colors.clear();
  }
}

double Mesh::SurfaceArea() const {
  double area = 0;
  for (const auto& face : faces) {
    Eigen::Vector3d a = vertices[face[0]].cast<double>();
    area +=
        0.5 *
        (vertices[face[1]].cast<double>() - a).cross(vertices[face[2]].cast<double>() - a).norm();
  }
  return area;
}

std::vector<Eigen::Vector3d> Mesh::SampleSurface(size_t count, uint64_t seed) const {
  std::vector<Eigen::Vector3d> points;
  if (faces.empty() || count == 0) return points;
  std::vector<double> cumulative(faces.size());
  double total = 0;
  for (size_t i = 0; i < faces.size(); ++i) {
    Eigen::Vector3d a = vertices[faces[i][0]].cast<double>();
    total += 0.5 * (vertices[faces[i][1]].cast<double>() - a)
                       .cross(vertices[faces[i][2]].cast<double>() - a)
                       .norm();
    cumulative[i] = total;
  }
  std::mt19937_64 random(seed);
  std::uniform_real_distribution<double> uniform(0.0, 1.0);
  points.reserve(count);
  for (size_t n = 0; n < count; ++n) {
    size_t i = std::lower_bound(cumulative.begin(), cumulative.end(), uniform(random) * total) -
               cumulative.begin();
    i = std::min(i, faces.size() - 1);
    double r1 = std::sqrt(uniform(random)), r2 = uniform(random);
    Eigen::Vector3d a = vertices[faces[i][0]].cast<double>();
    Eigen::Vector3d b = vertices[faces[i][1]].cast<double>();
    Eigen::Vector3d c = vertices[faces[i][2]].cast<double>();
    points.push_back((1 - r1) * a + r1 * (1 - r2) * b + r1 * r2 * c);
  }
  return points;
}

void WritePly(const std::filesystem::path& file, const Mesh& mesh, bool durable) {
  const bool has_normals = !mesh.normals.empty() && mesh.normals.size() == mesh.vertices.size();
  const bool has_colors = !mesh.colors.empty() && mesh.colors.size() == mesh.vertices.size();
  std::ostringstream header;
  header << "ply\nformat binary_little_endian 1.0\ncomment holocap\n"
         << "element vertex " << mesh.vertices.size() << "\n"
         << "property float x\nproperty float y\nproperty float z\n";
  if (has_normals) header << "property float nx\nproperty float ny\nproperty float nz\n";
  if (has_colors) header << "property uchar red\nproperty uchar green\nproperty uchar blue\n";
  header << "element face " << mesh.faces.size() << "\n"
         << "property list uchar int vertex_indices\nend_header\n";
  std::string bytes = header.str();
  auto put = [&bytes](const void* data, size_t size) {
    bytes.append(static_cast<const char*>(data), size);
  };
  for (size_t i = 0; i < mesh.vertices.size(); ++i) {
    put(mesh.vertices[i].data(), 12);
    if (has_normals) put(mesh.normals[i].data(), 12);
    if (has_colors) put(mesh.colors[i].data(), 3);
  }
  for (const auto& face : mesh.faces) {
    uint8_t three = 3;
    put(&three, 1);
    put(face.data(), 12);
  }
  WriteFileAtomic(file, bytes, durable);
}

namespace {

struct PlyProperty {
  std::string name;
  std::string type;        // scalar type, or the index type of a list
  std::string count_type;  // non-empty for lists
};

struct PlyElement {
  std::string name;
  size_t count = 0;
  std::vector<PlyProperty> properties;
};

size_t SizeOfPlyType(const std::string& type, const std::string& origin) {
  if (type == "char" || type == "uchar" || type == "int8" || type == "uint8") return 1;
  if (type == "short" || type == "ushort" || type == "int16" || type == "uint16") return 2;
  if (type == "int" || type == "uint" || type == "float" || type == "int32" || type == "uint32" ||
      type == "float32")
    return 4;
  if (type == "double" || type == "float64") return 8;
  Fail("'", origin, "': unknown PLY type '", type, "'");
}

double ReadBinary(const char* p, const std::string& type) {
  auto get = [p](auto value) {
    std::memcpy(&value, p, sizeof(value));
    return static_cast<double>(value);
  };
  if (type == "char" || type == "int8") return get(int8_t{});
  if (type == "uchar" || type == "uint8") return get(uint8_t{});
  if (type == "short" || type == "int16") return get(int16_t{});
  if (type == "ushort" || type == "uint16") return get(uint16_t{});
  if (type == "int" || type == "int32") return get(int32_t{});
  if (type == "uint" || type == "uint32") return get(uint32_t{});
  if (type == "float" || type == "float32") return get(float{});
  return get(double{});
}

}  // namespace

namespace {

// A colour channel as a byte: values outside 0..255 (a signed char property's negatives, a
// float's 300) are clamped.
uint8_t ColorByte(double value) { return static_cast<uint8_t>(std::clamp(value, 0.0, 255.0)); }

}  // namespace

Mesh ReadPly(const std::filesystem::path& file) {
  const std::string origin = file.string();
  std::string bytes = ReadFileToString(file);
  size_t header_end = bytes.find("end_header");
  if (bytes.rfind("ply", 0) != 0 || header_end == std::string::npos)
    Fail("'", origin, "' is not a PLY file");
  size_t data_start = bytes.find('\n', header_end);
  if (data_start == std::string::npos) Fail("'", origin, "' is truncated");
  ++data_start;
  std::istringstream header(bytes.substr(0, header_end));
  std::string line, format;
  std::vector<PlyElement> elements;
  while (std::getline(header, line)) {
    std::istringstream words(line);
    std::string keyword;
    words >> keyword;
    if (keyword == "format") {
      words >> format;
    } else if (keyword == "element") {
      PlyElement element;
      words >> element.name >> element.count;
      elements.push_back(element);
    } else if (keyword == "property") {
      if (elements.empty()) Fail("'", origin, "': property before any element");
      PlyProperty property;
      std::string type;
      words >> type;
      if (type == "list") {
        words >> property.count_type >> property.type >> property.name;
      } else {
        property.type = type;
        words >> property.name;
      }
      elements.back().properties.push_back(property);
    }
  }
  if (format != "binary_little_endian" && format != "ascii")
    Fail("'", origin, "': unsupported PLY format '", format, "'");
  const bool ascii = format == "ascii";
  Mesh mesh;
  size_t offset = data_start;
  std::istringstream text(ascii ? bytes.substr(data_start) : std::string());
  auto next = [&](const std::string& type) -> double {
    if (ascii) {
      double value;
      if (!(text >> value)) Fail("'", origin, "' is truncated");
      return value;
    }
    size_t size = SizeOfPlyType(type, origin);
    if (offset + size > bytes.size()) Fail("'", origin, "' is truncated");
    double value = ReadBinary(bytes.data() + offset, type);
    offset += size;
    return value;
  };
  for (const auto& element : elements) {
    const bool is_vertex = element.name == "vertex";
    const bool is_face = element.name == "face";
    // An element of no properties holds no bytes, however many it counts.
    const size_t count = element.properties.empty() ? 0 : element.count;
    for (size_t i = 0; i < count; ++i) {
      Eigen::Vector3f position = Eigen::Vector3f::Zero(), normal = Eigen::Vector3f::Zero();
      Eigen::Matrix<uint8_t, 3, 1> color = Eigen::Matrix<uint8_t, 3, 1>::Zero();
      bool has_normal = false, has_color = false;
      for (const auto& property : element.properties) {
        if (!property.count_type.empty()) {
          // A list's length and entries are whole numbers in range: a face of at most 255
          // corners (a uchar count, as every writer uses), indices within int.
          const double length = next(property.count_type);
          if (!(length >= 0 && length <= 255) || length != std::floor(length))
            Fail("'", origin, "': a list of length ", length, " (0 to 255)");
          const int count = static_cast<int>(length);
          std::vector<int> indices(count);
          for (int k = 0; k < count; ++k) {
            const double index = next(property.type);
            if (!(index >= 0 && index <= std::numeric_limits<int>::max()) ||
                index != std::floor(index))
              Fail("'", origin, "': a face refers to vertex ", index);
            indices[k] = static_cast<int>(index);
          }
          if (is_face && property.name.find("vertex_ind") == 0) {
            for (int k = 1; k + 1 < count; ++k)
              mesh.faces.emplace_back(indices[0], indices[k], indices[k + 1]);
          }
          continue;
        }
        double value = next(property.type);
        if (!is_vertex) continue;
        if (!std::isfinite(value)) Fail("'", origin, "': vertex ", i, " holds ", value);
        const std::string& n = property.name;
        if (n == "x")
          position.x() = value;
        else if (n == "y")
          position.y() = value;
        else if (n == "z")
          position.z() = value;
        else if (n == "nx") {
          normal.x() = value;
          has_normal = true;
        } else if (n == "ny")
          normal.y() = value;
        else if (n == "nz")
          normal.z() = value;
        else if (n == "red") {
          color.x() = ColorByte(value);
          has_color = true;
        } else if (n == "green")
          color.y() = ColorByte(value);
        else if (n == "blue")
          color.z() = ColorByte(value);
      }
      if (is_vertex) {
        mesh.vertices.push_back(position);
        if (has_normal) mesh.normals.push_back(normal);
        if (has_color) mesh.colors.push_back(color);
      }
    }
  }
  for (const auto& face : mesh.faces) {
    for (int k = 0; k < 3; ++k) {
      if (face[k] < 0 || face[k] >= static_cast<int>(mesh.vertices.size())) {
        Fail("'", origin, "': a face refers to vertex ", face[k], " of ", mesh.vertices.size());
      }
    }
  }
  return mesh;
}

}  // namespace holocap
