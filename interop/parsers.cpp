// Text parsers and writers of the foreign formats. They are strict: every number must parse
// and be finite, every count must match, so a damaged file gives one clear error instead of a
// camera that is silently wrong.
#include <cerrno>
#include <cinttypes>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <set>
#include <sstream>

#include "core/error.h"
#include "interop/interop.h"

namespace holocap {
namespace {

std::vector<std::string> SplitLines(const std::string& text) {
  std::vector<std::string> lines;
  std::string line;
  std::istringstream in(text);
  while (std::getline(in, line)) {
    if (!line.empty() && line.back() == '\r') line.pop_back();
    lines.push_back(line);
  }
  return lines;
}

std::vector<std::string> Tokens(const std::string& line) {
  std::vector<std::string> tokens;
  std::istringstream in(line);
  std::string token;
  while (in >> token) tokens.push_back(token);
  return tokens;
}

bool IsBlank(const std::string& line) {
  return line.find_first_not_of(" \t\r") == std::string::npos;
}

double Number(const std::string& token, const std::string& where) {
  errno = 0;
  char* end = nullptr;
  double value = std::strtod(token.c_str(), &end);
  if (end == token.c_str() || *end != '\0' || errno == ERANGE || !std::isfinite(value)) {
    Fail(where, ": '", token, "' is not a finite number");
  }
  return value;
}

int64_t Integer(const std::string& token, const std::string& where) {
  errno = 0;
  char* end = nullptr;
  long long value = std::strtoll(token.c_str(), &end, 10);
  if (end == token.c_str() || *end != '\0' || errno == ERANGE) {
    Fail(where, ": '", token, "' is not an integer");
  }
  return value;
}

int Dimension(const std::string& token, const std::string& where) {
  int64_t value = Integer(token, where);
  if (value <= 0 || value > 1000000) Fail(where, ": image size ", value, " is out of range");
  return static_cast<int>(value);
}

std::string Number17(double value) {
  char buffer[40];
  std::snprintf(buffer, sizeof(buffer), "%.17g", value);
  return buffer;
}

std::string At(const std::string& origin, size_t line_index) {
  return Cat(origin, ":", line_index + 1);
}

}  // namespace

std::vector<KrtCamera> ParseMiddleburyPar(const std::string& text, const std::string& origin) {
  std::vector<std::string> lines = SplitLines(text);
  size_t first = 0;
  while (first < lines.size() && IsBlank(lines[first])) ++first;
  if (first == lines.size()) Fail(origin, ": empty camera-parameter file");
  std::vector<std::string> count_tokens = Tokens(lines[first]);
  if (count_tokens.size() != 1)
    Fail(At(origin, first), ": the first line must hold the number of images");
  int64_t count = Integer(count_tokens[0], At(origin, first));
  if (count <= 0) Fail(At(origin, first), ": the image count must be positive, got ", count);
  std::vector<KrtCamera> cameras;
  std::set<std::string> names;
  for (size_t i = first + 1; i < lines.size(); ++i) {
    if (IsBlank(lines[i])) continue;
    std::vector<std::string> tokens = Tokens(lines[i]);
    const std::string where = At(origin, i);
    if (tokens.size() != 22) {
      Fail(where, ": expected 'name k11..k33 r11..r33 t1 t2 t3' (22 fields), got ", tokens.size());
    }
    KrtCamera camera;
    camera.name = tokens[0];
    if (!names.insert(camera.name).second) Fail(where, ": image '", camera.name, "' appears twice");
    for (int k = 0; k < 9; ++k) camera.K(k / 3, k % 3) = Number(tokens[1 + k], where);
    for (int k = 0; k < 9; ++k) camera.R(k / 3, k % 3) = Number(tokens[10 + k], where);
    camera.rotation_origin = where + " (r11..r33)";
    for (int k = 0; k < 3; ++k) camera.t(k) = Number(tokens[19 + k], where);
    cameras.push_back(std::move(camera));
  }
  if (static_cast<int64_t>(cameras.size()) != count) {
    Fail(origin, ": the first line announces ", count, " images, the file holds ", cameras.size());
  }
  return cameras;
}

std::vector<KrtCamera> ParseNeuralVolumesKrt(const std::string& text, const std::string& origin) {
  std::vector<std::string> lines = SplitLines(text);
  std::vector<KrtCamera> cameras;
  std::set<std::string> names;
  size_t i = 0;
  auto numbers_line = [&](size_t expected_min, size_t expected_max, const char* what) {
    if (i >= lines.size())
      Fail(origin, ": camera '", cameras.back().name, "' ends early (", what, " missing)");
    std::vector<std::string> tokens = Tokens(lines[i]);
    const std::string where = At(origin, i);
    if (tokens.size() < expected_min || tokens.size() > expected_max) {
      Fail(where, ": ", what, " needs ",
           expected_min == expected_max ? Cat(expected_min) : Cat(expected_min, "..", expected_max),
           " numbers, got ", tokens.size());
    }
    std::vector<double> values;
    for (const auto& token : tokens) values.push_back(Number(token, where));
    ++i;
    return values;
  };
  while (true) {
    while (i < lines.size() && IsBlank(lines[i])) ++i;
    if (i >= lines.size()) break;
    std::vector<std::string> name_tokens = Tokens(lines[i]);
    if (name_tokens.size() != 1) Fail(At(origin, i), ": expected a camera name alone on its line");
    KrtCamera camera;
    camera.name = name_tokens[0];
    if (!names.insert(camera.name).second)
      Fail(At(origin, i), ": camera '", camera.name, "' appears twice");
    ++i;
    cameras.push_back(camera);
    KrtCamera& c = cameras.back();
    for (int row = 0; row < 3; ++row) {
      std::vector<double> values = numbers_line(3, 3, "a row of K");
      for (int col = 0; col < 3; ++col) c.K(row, col) = values[col];
    }
    c.distortion = numbers_line(0, 14, "the distortion line");
    c.rotation_origin = Cat(At(origin, i), "-", i + 3, " ([R|t])");
    for (int row = 0; row < 3; ++row) {
      std::vector<double> values = numbers_line(4, 4, "a row of [R|t]");
      for (int col = 0; col < 3; ++col) c.R(row, col) = values[col];
      c.t(row) = values[3];
    }
    if (i < lines.size() && !IsBlank(lines[i]))
      Fail(At(origin, i), ": expected a blank line after camera '", c.name, "'");
  }
  if (cameras.empty()) Fail(origin, ": no cameras in the KRT file");
  return cameras;
}

std::string FormatNeuralVolumesKrt(const std::vector<KrtCamera>& cameras) {
  std::string out;
  for (const auto& camera : cameras) {
    out += camera.name + "\n";
    for (int row = 0; row < 3; ++row) {
      out += Number17(camera.K(row, 0)) + " " + Number17(camera.K(row, 1)) + " " +
             Number17(camera.K(row, 2)) + "\n";
    }
    for (size_t k = 0; k < camera.distortion.size(); ++k) {
      if (k > 0) out += ' ';
      out += Number17(camera.distortion[k]);
    }
    out += "\n";
    for (int row = 0; row < 3; ++row) {
      for (int col = 0; col < 3; ++col) out += Number17(camera.R(row, col)) + " ";
      out += Number17(camera.t(row)) + "\n";
    }
    out += "\n";
  }
  return out;
}

namespace {

nlohmann::json ParseJson(const std::string& text, const std::string& origin) {
  try {
    return nlohmann::json::parse(text);
  } catch (const nlohmann::json::exception& e) {
    Fail(origin, " is not valid JSON: ", e.what());
  }
}

double JsonNumber(const nlohmann::json& value, const std::string& where) {
  if (!value.is_number()) Fail(where, " must be a number, got ", value.dump());
  double number = value.get<double>();
  if (!std::isfinite(number)) Fail(where, " is not finite");
  return number;
}

// A rows x cols matrix given as nested lists, or (cols == 1) as a flat list.
Eigen::MatrixXd JsonMatrix(const nlohmann::json& value, int rows, int cols,
                           const std::string& where) {
  if (!value.is_array() || static_cast<int>(value.size()) != rows) {
    Fail(where, " must be a list of ", rows, " rows");
  }
  Eigen::MatrixXd matrix(rows, cols);
  for (int r = 0; r < rows; ++r) {
    const nlohmann::json& row = value[r];
    if (cols == 1 && row.is_number()) {
      matrix(r, 0) = JsonNumber(row, where);
      continue;
    }
    if (!row.is_array() || static_cast<int>(row.size()) != cols)
      Fail(where, " row ", r, " must hold ", cols, " numbers");
    for (int c = 0; c < cols; ++c) matrix(r, c) = JsonNumber(row[c], where);
  }
  return matrix;
}

}  // namespace

std::vector<KrtCamera> ParsePanopticCalibration(const std::string& text,
                                                const std::string& origin) {
  nlohmann::json json = ParseJson(text, origin);
  if (!json.is_object() || !json.contains("cameras") || !json["cameras"].is_array()) {
    Fail(origin, ": expected an object with a 'cameras' list");
  }
  std::vector<KrtCamera> cameras;
  std::set<std::string> names;
  for (size_t i = 0; i < json["cameras"].size(); ++i) {
    const nlohmann::json& item = json["cameras"][i];
    const std::string where = Cat(origin, ": cameras[", i, "]");
    if (!item.is_object()) Fail(where, " must be an object");
    for (const char* key : {"name", "K", "R", "t"}) {
      if (!item.contains(key)) Fail(where, " has no '", key, "'");
    }
    KrtCamera camera;
    if (!item["name"].is_string()) Fail(where, ".name must be a string");
    camera.name = item["name"].get<std::string>();
    if (!names.insert(camera.name).second)
      Fail(where, ": camera '", camera.name, "' appears twice");
    camera.K = JsonMatrix(item["K"], 3, 3, where + ".K");
    camera.R = JsonMatrix(item["R"], 3, 3, where + ".R");
    camera.rotation_origin = where + ".R";
    camera.t = JsonMatrix(item["t"], 3, 1, where + ".t");
    if (item.contains("distCoef")) {
      const nlohmann::json& dist = item["distCoef"];
      if (!dist.is_array() || dist.size() > 14)
        Fail(where, ".distCoef must be a list of at most 14 numbers");
      for (const auto& value : dist)
        camera.distortion.push_back(JsonNumber(value, where + ".distCoef"));
    }
    if (item.contains("resolution")) {
      const nlohmann::json& size = item["resolution"];
      if (!size.is_array() || size.size() != 2 || !size[0].is_number_integer() ||
          !size[1].is_number_integer()) {
        Fail(where, ".resolution must be [width, height]");
      }
      camera.width = Dimension(Cat(size[0].get<int64_t>()), where + ".resolution");
      camera.height = Dimension(Cat(size[1].get<int64_t>()), where + ".resolution");
    }
    cameras.push_back(std::move(camera));
  }
  if (cameras.empty()) Fail(origin, ": no cameras");
  return cameras;
}

namespace {

// COLMAP's camera models and their parameter counts (colmap/sensor/models.h).
const std::map<std::string, size_t>& ColmapModelParamCounts() {
  static const std::map<std::string, size_t> counts = {{"SIMPLE_PINHOLE", 3},
                                                       {"PINHOLE", 4},
                                                       {"SIMPLE_RADIAL", 4},
                                                       {"RADIAL", 5},
                                                       {"OPENCV", 8},
                                                       {"OPENCV_FISHEYE", 8},
                                                       {"FULL_OPENCV", 12},
                                                       {"FOV", 5},
                                                       {"SIMPLE_RADIAL_FISHEYE", 4},
                                                       {"RADIAL_FISHEYE", 5},
                                                       {"THIN_PRISM_FISHEYE", 12},
                                                       {"RAD_TAN_THIN_PRISM_FISHEYE", 16}};
  return counts;
}

// The lines of a COLMAP text file without its comment lines, keeping blank ones (images.txt
// gives an image without 2D points an empty second line).
std::vector<std::pair<size_t, std::string>> ColmapLines(const std::string& text) {
  std::vector<std::pair<size_t, std::string>> kept;
  std::vector<std::string> lines = SplitLines(text);
  for (size_t i = 0; i < lines.size(); ++i) {
    size_t start = lines[i].find_first_not_of(" \t");
    if (start != std::string::npos && lines[i][start] == '#') continue;
    kept.emplace_back(i, lines[i]);
  }
  return kept;
}

}  // namespace

std::map<int64_t, ColmapCamera> ParseColmapCameras(const std::string& text,
                                                   const std::string& origin) {
  std::map<int64_t, ColmapCamera> cameras;
  for (const auto& [index, line] : ColmapLines(text)) {
    if (IsBlank(line)) continue;
    const std::string where = At(origin, index);
    std::vector<std::string> tokens = Tokens(line);
    if (tokens.size() < 4) Fail(where, ": expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]'");
    ColmapCamera camera;
    camera.id = Integer(tokens[0], where);
    camera.model = tokens[1];
    camera.width = Dimension(tokens[2], where);
    camera.height = Dimension(tokens[3], where);
    auto known = ColmapModelParamCounts().find(camera.model);
    if (known == ColmapModelParamCounts().end())
      Fail(where, ": unknown COLMAP camera model '", camera.model, "'");
    if (tokens.size() - 4 != known->second) {
      Fail(where, ": COLMAP model ", camera.model, " takes ", known->second, " parameters, got ",
           tokens.size() - 4);
    }
    for (size_t k = 4; k < tokens.size(); ++k) camera.params.push_back(Number(tokens[k], where));
    if (!cameras.emplace(camera.id, camera).second)
      Fail(where, ": camera id ", camera.id, " appears twice");
  }
  return cameras;
}

std::vector<ColmapImage> ParseColmapImages(const std::string& text, const std::string& origin) {
  std::vector<std::pair<size_t, std::string>> lines = ColmapLines(text);
  // Blank lines between records are not COLMAP's, but a file's trailing newline(s) are common.
  while (!lines.empty() && IsBlank(lines.back().second) && lines.size() % 2 == 1) lines.pop_back();
  std::vector<ColmapImage> images;
  std::set<int64_t> ids;
  for (size_t i = 0; i < lines.size(); i += 2) {
    const std::string where = At(origin, lines[i].first);
    std::vector<std::string> tokens = Tokens(lines[i].second);
    if (tokens.size() < 10) {
      Fail(where, ": expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', got ", tokens.size(),
           " fields");
    }
    ColmapImage image;
    image.id = Integer(tokens[0], where);
    if (!ids.insert(image.id).second) Fail(where, ": image id ", image.id, " appears twice");
    Eigen::Vector4d q(Number(tokens[1], where), Number(tokens[2], where), Number(tokens[3], where),
                      Number(tokens[4], where));
    // COLMAP normalises on reading too; a quaternion far from unit length is a damaged file.
    if (std::abs(q.norm() - 1) > 1e-3)
      Fail(where, ": quaternion (", q.transpose(), ") is not of unit length");
    image.cam_from_world_rotation = Eigen::Quaterniond(q(0), q(1), q(2), q(3)).normalized();
    for (int k = 0; k < 3; ++k) image.cam_from_world_translation(k) = Number(tokens[5 + k], where);
    image.camera_id = Integer(tokens[8], where);
    size_t name_start = 0;
    {
      std::istringstream in(lines[i].second);
      std::string skipped;
      for (int k = 0; k < 9; ++k) in >> skipped;
      name_start = static_cast<size_t>(in.tellg());
    }
    image.name = lines[i].second.substr(name_start);
    image.name.erase(0, image.name.find_first_not_of(" \t"));
    image.name.erase(image.name.find_last_not_of(" \t") + 1);
    if (i + 1 < lines.size()) {
      const std::string points_where = At(origin, lines[i + 1].first);
      std::vector<std::string> points = Tokens(lines[i + 1].second);
      if (points.size() % 3 != 0) Fail(points_where, ": POINTS2D must be triples 'X Y POINT3D_ID'");
      for (size_t k = 0; k < points.size(); k += 3) {
        image.points2d.emplace_back(Number(points[k], points_where),
                                    Number(points[k + 1], points_where));
        image.point3d_ids.push_back(Integer(points[k + 2], points_where));
      }
    }
    images.push_back(std::move(image));
  }
  return images;
}

std::vector<ColmapPoint> ParseColmapPoints(const std::string& text, const std::string& origin) {
  std::vector<ColmapPoint> points;
  std::set<int64_t> ids;
  for (const auto& [index, line] : ColmapLines(text)) {
    if (IsBlank(line)) continue;
    const std::string where = At(origin, index);
    std::vector<std::string> tokens = Tokens(line);
    if (tokens.size() < 8 || (tokens.size() - 8) % 2 != 0) {
      Fail(where, ": expected 'POINT3D_ID X Y Z R G B ERROR (IMAGE_ID POINT2D_IDX)...'");
    }
    ColmapPoint point;
    point.id = Integer(tokens[0], where);
    if (!ids.insert(point.id).second) Fail(where, ": point id ", point.id, " appears twice");
    for (int k = 0; k < 3; ++k) point.xyz(k) = Number(tokens[1 + k], where);
    for (int k = 0; k < 3; ++k) {
      int64_t channel = Integer(tokens[4 + k], where);
      if (channel < 0 || channel > 255) Fail(where, ": colour ", channel, " is outside 0..255");
      point.rgb[k] = static_cast<int>(channel);
    }
    point.error = Number(tokens[7], where);
    for (size_t k = 8; k < tokens.size(); k += 2) {
      point.track.emplace_back(Integer(tokens[k], where), Integer(tokens[k + 1], where));
    }
    points.push_back(std::move(point));
  }
  return points;
}

std::string FormatColmapCameras(const std::map<int64_t, ColmapCamera>& cameras) {
  std::string out =
      "# Camera list with one line of data per camera:\n"
      "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n# Number of cameras: " +
      std::to_string(cameras.size()) + "\n";
  for (const auto& [id, camera] : cameras) {
    out += Cat(id, " ", camera.model, " ", camera.width, " ", camera.height);
    for (double value : camera.params) out += Cat(" ", Number17(value));
    out += "\n";
  }
  return out;
}

std::string FormatColmapImages(const std::vector<ColmapImage>& images) {
  std::string out =
      "# Image list with two lines of data per image:\n"
      "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
      "#   POINTS2D[] as (X, Y, POINT3D_ID)\n# Number of images: " +
      std::to_string(images.size()) + "\n";
  for (const auto& image : images) {
    const Eigen::Quaterniond& q = image.cam_from_world_rotation;
    const Eigen::Vector3d& t = image.cam_from_world_translation;
    out += Cat(image.id, " ", Number17(q.w()), " ", Number17(q.x()), " ", Number17(q.y()), " ",
               Number17(q.z()), " ", Number17(t.x()), " ", Number17(t.y()), " ", Number17(t.z()),
               " ", image.camera_id, " ", image.name, "\n");
    for (size_t k = 0; k < image.points2d.size(); ++k) {
      out += Cat(k ? " " : "", Number17(image.points2d[k].x()), " ",
                 Number17(image.points2d[k].y()), " ", image.point3d_ids[k]);
    }
    out += "\n";
  }
  return out;
}

std::string FormatColmapPoints(const std::vector<ColmapPoint>& points) {
  std::string out =
      "# 3D point list with one line of data per point:\n"
      "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
      "# Number of points: " +
      std::to_string(points.size()) + "\n";
  for (const auto& point : points) {
    out += Cat(point.id, " ", Number17(point.xyz.x()), " ", Number17(point.xyz.y()), " ",
               Number17(point.xyz.z()), " ", point.rgb[0], " ", point.rgb[1], " ", point.rgb[2],
               " ", Number17(point.error));
    for (const auto& [image, index] : point.track) out += Cat(" ", image, " ", index);
    out += "\n";
  }
  return out;
}

namespace {

void ReadNerfIntrinsics(const nlohmann::json& object, const std::string& where,
                        NerfIntrinsics* intrinsics) {
  auto number = [&](const char* key, std::optional<double>* field) {
    if (object.contains(key)) *field = JsonNumber(object[key], Cat(where, ".", key));
  };
  number("fl_x", &intrinsics->fl_x);
  number("fl_y", &intrinsics->fl_y);
  number("cx", &intrinsics->cx);
  number("cy", &intrinsics->cy);
  number("camera_angle_x", &intrinsics->camera_angle_x);
  number("camera_angle_y", &intrinsics->camera_angle_y);
  for (const char* key : {"w", "h"}) {
    if (!object.contains(key)) continue;
    double value = JsonNumber(object[key], Cat(where, ".", key));
    if (value != std::floor(value) || value <= 0 || value > 1000000)
      Fail(where, ".", key, " must be a positive integer");
    (key[0] == 'w' ? intrinsics->w : intrinsics->h) = static_cast<int>(value);
  }
  if (object.contains("camera_model")) {
    if (!object["camera_model"].is_string()) Fail(where, ".camera_model must be a string");
    intrinsics->camera_model = object["camera_model"].get<std::string>();
  }
  for (const char* key : {"k1", "k2", "k3", "k4", "p1", "p2"}) {
    if (object.contains(key))
      intrinsics->distortion[key] = JsonNumber(object[key], Cat(where, ".", key));
  }
}

}  // namespace

std::vector<NerfFrame> ParseNerfTransforms(const std::string& text, const std::string& origin) {
  nlohmann::json json = ParseJson(text, origin);
  if (!json.is_object()) Fail(origin, ": expected a JSON object");
  if (!json.contains("frames") || !json["frames"].is_array()) Fail(origin, ": no 'frames' list");
  NerfIntrinsics common;
  ReadNerfIntrinsics(json, origin, &common);
  std::vector<NerfFrame> frames;
  for (size_t i = 0; i < json["frames"].size(); ++i) {
    const nlohmann::json& item = json["frames"][i];
    const std::string where = Cat(origin, ": frames[", i, "]");
    if (!item.is_object()) Fail(where, " must be an object");
    if (!item.contains("file_path") || !item["file_path"].is_string())
      Fail(where, " has no 'file_path' string");
    if (!item.contains("transform_matrix")) Fail(where, " has no 'transform_matrix'");
    NerfFrame frame;
    frame.file_path = item["file_path"].get<std::string>();
    if (frame.file_path.empty()) Fail(where, ".file_path is empty");
    const nlohmann::json& matrix = item["transform_matrix"];
    // Some writers drop the constant last row.
    int rows = matrix.is_array() && matrix.size() == 3 ? 3 : 4;
    frame.world_from_cam_gl.topRows(rows) =
        JsonMatrix(matrix, rows, 4, where + ".transform_matrix");
    if (frame.world_from_cam_gl.row(3) != Eigen::RowVector4d(0, 0, 0, 1)) {
      Fail(where, ".transform_matrix: last row must be 0 0 0 1");
    }
    frame.intrinsics = common;
    ReadNerfIntrinsics(item, where, &frame.intrinsics);
    frames.push_back(std::move(frame));
  }
  if (frames.empty()) Fail(origin, ": 'frames' is empty");
  return frames;
}

}  // namespace holocap
