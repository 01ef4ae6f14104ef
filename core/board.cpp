#include "core/board.h"

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <memory>

#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"

extern "C" {
#include <apriltag/apriltag.h>
#include <apriltag/tag36h11.h>
#include <apriltag/tagStandard41h12.h>
}

namespace holocap {
namespace {

// libapriltag's families, created once: their code tables are static data.
struct FamilyHandle {
  apriltag_family_t* family = nullptr;
  void (*destroy)(apriltag_family_t*) = nullptr;
  ~FamilyHandle() {
    if (family != nullptr) destroy(family);
  }
};

const apriltag_family_t* FindFamily(const std::string& name) {
  static const FamilyHandle tag36h11{tag36h11_create(), tag36h11_destroy};
  static const FamilyHandle standard41h12{tagStandard41h12_create(), tagStandard41h12_destroy};
  if (name == "tag36h11") return tag36h11.family;
  if (name == "tagStandard41h12") return standard41h12.family;
  return nullptr;
}

// The bitmap of one tag, total_width x total_width, true = black. apriltag_to_image allocates
// with libapriltag's image_u8 allocator, whose destructor lives only in libapriltag-utils; its
// layout is a calloc'ed struct owning a calloc'ed buffer, so free() releases both.
std::vector<uint8_t> TagBits(const apriltag_family_t* family, int id) {
  image_u8_t* image = apriltag_to_image(const_cast<apriltag_family_t*>(family), id);
  if (image == nullptr) Fail("libapriltag could not draw tag ", id, " of ", family->name);
  std::vector<uint8_t> black(static_cast<size_t>(image->width) * image->height);
  for (int y = 0; y < image->height; ++y) {
    for (int x = 0; x < image->width; ++x) {
      black[static_cast<size_t>(y) * image->width + x] = image->buf[y * image->stride + x] == 0;
    }
  }
  free(image->buf);
  free(image);
  return black;
}

// Outer bits of a tag beyond its detection square, in bits per side.
int OuterBits(const apriltag_family_t* family) {
  return (family->total_width - family->width_at_border) / 2;
}

double PolygonArea(const std::vector<Eigen::Vector2d>& polygon) {
  double twice = 0;
  for (size_t k = 0; k < polygon.size(); ++k) {
    const Eigen::Vector2d& a = polygon[k];
    const Eigen::Vector2d& b = polygon[(k + 1) % polygon.size()];
    twice += a.x() * b.y() - a.y() * b.x();
  }
  return 0.5 * twice;
}

// Sutherland-Hodgman against one axis-aligned half plane: keeps sign * (p[axis] - bound) >= 0.
void ClipHalfPlane(const std::vector<Eigen::Vector2d>& in, int axis, double bound, double sign,
                   std::vector<Eigen::Vector2d>* out) {
  out->clear();
  for (size_t k = 0; k < in.size(); ++k) {
    const Eigen::Vector2d& a = in[k];
    const Eigen::Vector2d& b = in[(k + 1) % in.size()];
    const double da = sign * (a[axis] - bound);
    const double db = sign * (b[axis] - bound);
    if (da >= 0) out->push_back(a);
    if ((da >= 0) != (db >= 0)) out->push_back(a + (b - a) * (da / (da - db)));
  }
}

double ClippedArea(const std::vector<Eigen::Vector2d>& polygon, double u0, double v0, double u1,
                   double v1) {
  std::vector<Eigen::Vector2d> a = polygon, b;
  ClipHalfPlane(a, 0, u0, 1, &b);
  ClipHalfPlane(b, 0, u1, -1, &a);
  ClipHalfPlane(a, 1, v0, 1, &b);
  ClipHalfPlane(b, 1, v1, -1, &a);
  return a.size() < 3 ? 0.0 : std::abs(PolygonArea(a));
}

template <typename T>
T YamlField(const YAML::Node& node, const char* key, T fallback, const std::string& origin) {
  if (!node[key]) return fallback;
  try {
    return node[key].as<T>();
  } catch (const YAML::Exception& e) {
    Fail(origin, ": field '", key, "': ", e.what());
  }
}

}  // namespace

const char* ToString(BoardType type) {
  return type == BoardType::kAprilGrid ? "apriltag" : "chessboard";
}

BoardType BoardTypeFromString(const std::string& text) {
  if (text == "apriltag") return BoardType::kAprilGrid;
  if (text == "chessboard") return BoardType::kChessboard;
  Fail("unknown board type '", text, "' (known: apriltag, chessboard)");
}

int BoardLayout::width_n() const {
  return type == BoardType::kAprilGrid ? 2 * tags_across : chessboard_width_n;
}

int BoardLayout::height_n() const {
  return type == BoardType::kAprilGrid ? 2 * tags_down : chessboard_height_n;
}

void BoardLayout::Check() const {
  HOLOCAP_CHECK_OPTION_GT(spacing, 0);
  HOLOCAP_CHECK_OPTION(std::isfinite(spacing), spacing);
  HOLOCAP_CHECK_OPTION_GE(margin, 0);
  HOLOCAP_CHECK_OPTION(std::isfinite(margin), margin);
  if (type == BoardType::kChessboard) {
    HOLOCAP_CHECK_OPTION_GE(chessboard_width_n, 2, "a chessboard needs at least 2x2 inner corners");
    HOLOCAP_CHECK_OPTION_GE(chessboard_height_n, 2,
                            "a chessboard needs at least 2x2 inner corners");
    HOLOCAP_CHECK_OPTION(
        margin >= spacing * (1 - 1e-9), margin,
        Cat("the margin cuts the outer squares: it needs >= spacing ", spacing, " m"));
    return;
  }
  HOLOCAP_CHECK_OPTION(FindFamily(family) != nullptr, family, "known: tag36h11, tagStandard41h12");
  const apriltag_family_t* family = FindFamily(this->family);
  HOLOCAP_CHECK_OPTION_GE(tags_across, 1, "an AprilTag board needs at least 2 tags");
  HOLOCAP_CHECK_OPTION_GE(tags_down, 1, "an AprilTag board needs at least 2 tags");
  HOLOCAP_CHECK_OPTION(
      tags_across * tags_down >= 2, tags_across,
      Cat("an AprilTag board needs at least 2 tags, got ", tags_across, "x", tags_down));
  HOLOCAP_CHECK_OPTION_GE(first_id, 0);
  HOLOCAP_CHECK_OPTION(first_id + tags_across * tags_down <= static_cast<int>(family->ncodes),
                       first_id,
                       Cat("tag ids ", first_id, "..", first_id + tags_across * tags_down - 1,
                           " exceed ", this->family, " (", family->ncodes, " codes)"));
  const double outer = spacing * OuterBits(family) / family->width_at_border;
  HOLOCAP_CHECK_OPTION(margin >= outer * (1 - 1e-9), margin,
                       Cat("the margin cuts the tags' outer bits: it needs >= ", outer, " m"));
}

nlohmann::json BoardLayout::ToJson() const {
  nlohmann::json json = {{"type", ToString(type)}, {"spacing", spacing}, {"margin", margin}};
  if (type == BoardType::kAprilGrid) {
    json["family"] = family;
    json["tags_across"] = tags_across;
    json["tags_down"] = tags_down;
    json["first_id"] = first_id;
  } else {
    json["chessboard_width_n"] = chessboard_width_n;
    json["chessboard_height_n"] = chessboard_height_n;
  }
  json["width_n"] = width_n();
  json["height_n"] = height_n();
  return json;
}

BoardLayout BoardLayout::FromJson(const nlohmann::json& json, const std::string& origin) {
  if (!json.is_object()) Fail(origin, ": a board layout must be an object");
  BoardLayout layout;
  try {
    layout.type = BoardTypeFromString(json.value("type", std::string(ToString(layout.type))));
    layout.family = json.value("family", layout.family);
    layout.tags_across = json.value("tags_across", layout.tags_across);
    layout.tags_down = json.value("tags_down", layout.tags_down);
    layout.chessboard_width_n = json.value("chessboard_width_n", layout.chessboard_width_n);
    layout.chessboard_height_n = json.value("chessboard_height_n", layout.chessboard_height_n);
    layout.spacing = json.value("spacing", layout.spacing);
    layout.first_id = json.value("first_id", layout.first_id);
    layout.margin = json.value("margin", layout.margin);
    layout.Check();
  } catch (const nlohmann::json::exception& e) {
    Fail(origin, ": ", e.what());
  } catch (const Error& e) {
    Fail(origin, ": ", e.what());
  }
  return layout;
}

BoardLayout BoardLayout::Load(const std::filesystem::path& file) {
  const std::string origin = file.string();
  const std::string text = ReadFileToString(file);
  YAML::Node node;
  try {
    node = YAML::Load(text);
  } catch (const YAML::Exception& e) {
    Fail(origin, ": not YAML: ", e.what());
  }
  if (!node.IsMap()) Fail(origin, ": a board layout must be a mapping");
  BoardLayout layout;
  try {
    layout.type =
        BoardTypeFromString(YamlField<std::string>(node, "type", ToString(layout.type), origin));
  } catch (const Error& e) {
    Fail(origin, ": field 'type': ", e.what());
  }
  layout.family = YamlField(node, "family", layout.family, origin);
  layout.tags_across = YamlField(node, "tags_across", layout.tags_across, origin);
  layout.tags_down = YamlField(node, "tags_down", layout.tags_down, origin);
  layout.chessboard_width_n =
      YamlField(node, "chessboard_width_n", layout.chessboard_width_n, origin);
  layout.chessboard_height_n =
      YamlField(node, "chessboard_height_n", layout.chessboard_height_n, origin);
  layout.spacing = YamlField(node, "spacing", layout.spacing, origin);
  layout.first_id = YamlField(node, "first_id", layout.first_id, origin);
  layout.margin = YamlField(node, "margin", layout.margin, origin);
  try {
    layout.Check();
  } catch (const Error& e) {
    Fail(origin, ": ", e.what());
  }
  return layout;
}

void BoardLayout::Save(const std::filesystem::path& file) const {
  YAML::Emitter out;
  out.SetDoublePrecision(17);
  out << YAML::BeginMap;
  out << YAML::Key << "type" << YAML::Value << ToString(type);
  if (type == BoardType::kAprilGrid) {
    out << YAML::Key << "family" << YAML::Value << family;
    out << YAML::Key << "tags_across" << YAML::Value << tags_across;
    out << YAML::Key << "tags_down" << YAML::Value << tags_down;
    out << YAML::Key << "first_id" << YAML::Value << first_id;
  } else {
    out << YAML::Key << "chessboard_width_n" << YAML::Value << chessboard_width_n;
    out << YAML::Key << "chessboard_height_n" << YAML::Value << chessboard_height_n;
  }
  out << YAML::Key << "spacing" << YAML::Value << spacing;
  out << YAML::Key << "margin" << YAML::Value << margin;
  out << YAML::EndMap;
  WriteFileAtomic(file, std::string(out.c_str()) + "\n");
}

Board::Board(const BoardLayout& layout) : layout_(layout) {
  layout_.Check();
  const double s = layout_.spacing;
  u_min_ = v_min_ = -layout_.margin;
  u_max_ = (layout_.width_n() - 1) * s + layout_.margin;
  v_max_ = (layout_.height_n() - 1) * s + layout_.margin;

  if (layout_.type == BoardType::kChessboard) {
    cell_ = s;
    origin_ = -s;
    cells_u_ = layout_.chessboard_width_n + 1;
    cells_v_ = layout_.chessboard_height_n + 1;
    black_.resize(static_cast<size_t>(cells_u_) * cells_v_);
    for (int cv = 0; cv < cells_v_; ++cv) {
      for (int cu = 0; cu < cells_u_; ++cu) black_[cv * cells_u_ + cu] = (cu + cv) % 2 == 0;
    }
    return;
  }

  // Tags repeat every 2 * spacing = 2 * width_at_border bits, so one bit lattice covers all.
  const apriltag_family_t* family = FindFamily(layout_.family);
  const int border = family->width_at_border;
  const int total = family->total_width;
  const int outer = OuterBits(family);
  cell_ = s / border;
  origin_ = -outer * cell_;
  cells_u_ = (2 * layout_.tags_across - 1) * border + total - border;
  cells_v_ = (2 * layout_.tags_down - 1) * border + total - border;
  black_.assign(static_cast<size_t>(cells_u_) * cells_v_, 0);
  for (int tj = 0; tj < layout_.tags_down; ++tj) {
    for (int ti = 0; ti < layout_.tags_across; ++ti) {
      const std::vector<uint8_t> bits =
          TagBits(family, layout_.first_id + tj * layout_.tags_across + ti);
      for (int y = 0; y < total; ++y) {
        for (int x = 0; x < total; ++x) {
          black_[static_cast<size_t>(2 * tj * border + y) * cells_u_ + 2 * ti * border + x] =
              bits[y * total + x];
        }
      }
    }
  }
}

int Board::tag_count() const {
  return layout_.type == BoardType::kAprilGrid ? layout_.tags_across * layout_.tags_down : 0;
}

Eigen::Vector3d Board::GridPoint(int i, int j) const {
  return Eigen::Vector3d(i * layout_.spacing, j * layout_.spacing, 0);
}

std::vector<Eigen::Vector3d> Board::GridPoints() const {
  std::vector<Eigen::Vector3d> points;
  points.reserve(static_cast<size_t>(width_n()) * height_n());
  for (int j = 0; j < height_n(); ++j) {
    for (int i = 0; i < width_n(); ++i) points.push_back(GridPoint(i, j));
  }
  return points;
}

TagCorner Board::TagCornerOf(int i, int j) const {
  if (layout_.type != BoardType::kAprilGrid) Fail("a chessboard has no tag corners");
  if (i < 0 || j < 0 || i >= width_n() || j >= height_n()) {
    Fail("grid point (", i, ", ", j, ") is off the ", width_n(), "x", height_n(), " board");
  }
  TagCorner result;
  result.tag_id = layout_.first_id + (j / 2) * layout_.tags_across + i / 2;
  const bool right = i % 2 == 1;
  const bool bottom = j % 2 == 1;
  result.corner = bottom ? (right ? 1 : 0) : (right ? 2 : 3);
  return result;
}

bool Board::GridPointOf(int tag_id, int corner, int* i, int* j) const {
  if (layout_.type != BoardType::kAprilGrid || corner < 0 || corner > 3) return false;
  const int index = tag_id - layout_.first_id;
  if (index < 0 || index >= tag_count()) return false;
  const bool right = corner == 1 || corner == 2;
  const bool bottom = corner == 0 || corner == 1;
  *i = 2 * (index % layout_.tags_across) + (right ? 1 : 0);
  *j = 2 * (index / layout_.tags_across) + (bottom ? 1 : 0);
  return true;
}

bool Board::Contains(double u, double v) const {
  return u >= u_min_ && u <= u_max_ && v >= v_min_ && v <= v_max_;
}

bool Board::CellIsBlack(int cu, int cv) const {
  if (cu < 0 || cv < 0 || cu >= cells_u_ || cv >= cells_v_) return false;
  return black_[static_cast<size_t>(cv) * cells_u_ + cu] != 0;
}

double Board::Reflectance(double u, double v) const {
  const int cu = static_cast<int>(std::floor((u - origin_) / cell_));
  const int cv = static_cast<int>(std::floor((v - origin_) / cell_));
  return CellIsBlack(cu, cv) ? 0.0 : 1.0;
}

double Board::MeanReflectance(const std::vector<Eigen::Vector2d>& polygon) const {
  if (polygon.size() < 3) Fail("MeanReflectance needs a polygon of at least 3 vertices");
  const double area = std::abs(PolygonArea(polygon));
  if (!(area > 0)) {
    return Reflectance(polygon[0].x(), polygon[0].y());
  }
  double lo_u = polygon[0].x(), hi_u = lo_u, lo_v = polygon[0].y(), hi_v = lo_v;
  for (const Eigen::Vector2d& p : polygon) {
    lo_u = std::min(lo_u, p.x());
    hi_u = std::max(hi_u, p.x());
    lo_v = std::min(lo_v, p.y());
    hi_v = std::max(hi_v, p.y());
  }
  const int cu0 = std::max(0, static_cast<int>(std::floor((lo_u - origin_) / cell_)));
  const int cu1 = std::min(cells_u_ - 1, static_cast<int>(std::floor((hi_u - origin_) / cell_)));
  const int cv0 = std::max(0, static_cast<int>(std::floor((lo_v - origin_) / cell_)));
  const int cv1 = std::min(cells_v_ - 1, static_cast<int>(std::floor((hi_v - origin_) / cell_)));
  double black = 0;
  for (int cv = cv0; cv <= cv1; ++cv) {
    for (int cu = cu0; cu <= cu1; ++cu) {
      if (!CellIsBlack(cu, cv)) continue;
      const double u0 = origin_ + cu * cell_;
      const double v0 = origin_ + cv * cell_;
      black += ClippedArea(polygon, u0, v0, u0 + cell_, v0 + cell_);
    }
  }
  return std::clamp(1.0 - black / area, 0.0, 1.0);
}

}  // namespace holocap
