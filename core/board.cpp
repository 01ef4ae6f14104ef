#include "core/board.h"

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <initializer_list>
#include <memory>
#include <utility>

#include "core/apriltag_family.h"
#include "core/charuco.h"
#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"

extern "C" {
#include <apriltag/apriltag.h>
}

namespace holocap {
namespace {

// libapriltag's families as drawn, created once (never given to a detector, which would keep
// its decode table in them); nullptr for a family or border holocap does not know.
const apriltag_family_t* FindFamily(const std::string& name, int border_bits = 1) {
  static const ApriltagFamilyPtr tag36h11 = CreateApriltagFamily("tag36h11");
  static const ApriltagFamilyPtr tag36h11_kalibr = CreateApriltagFamily("tag36h11", 2);
  static const ApriltagFamilyPtr standard41h12 = CreateApriltagFamily("tagStandard41h12");
  if (name == "tag36h11") return border_bits == 2 ? tag36h11_kalibr.get() : tag36h11.get();
  if (name == "tagStandard41h12" && border_bits == 1) return standard41h12.get();
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

// OpenCV's predefined ArUco dictionaries by name, in its enum's order.
constexpr std::pair<const char*, cv::aruco::PREDEFINED_DICTIONARY_NAME> kArucoDictionaries[] = {
    {"DICT_4X4_50", cv::aruco::DICT_4X4_50},
    {"DICT_4X4_100", cv::aruco::DICT_4X4_100},
    {"DICT_4X4_250", cv::aruco::DICT_4X4_250},
    {"DICT_4X4_1000", cv::aruco::DICT_4X4_1000},
    {"DICT_5X5_50", cv::aruco::DICT_5X5_50},
    {"DICT_5X5_100", cv::aruco::DICT_5X5_100},
    {"DICT_5X5_250", cv::aruco::DICT_5X5_250},
    {"DICT_5X5_1000", cv::aruco::DICT_5X5_1000},
    {"DICT_6X6_50", cv::aruco::DICT_6X6_50},
    {"DICT_6X6_100", cv::aruco::DICT_6X6_100},
    {"DICT_6X6_250", cv::aruco::DICT_6X6_250},
    {"DICT_6X6_1000", cv::aruco::DICT_6X6_1000},
    {"DICT_7X7_50", cv::aruco::DICT_7X7_50},
    {"DICT_7X7_100", cv::aruco::DICT_7X7_100},
    {"DICT_7X7_250", cv::aruco::DICT_7X7_250},
    {"DICT_7X7_1000", cv::aruco::DICT_7X7_1000},
    {"DICT_ARUCO_ORIGINAL", cv::aruco::DICT_ARUCO_ORIGINAL},
    {"DICT_APRILTAG_16h5", cv::aruco::DICT_APRILTAG_16h5},
    {"DICT_APRILTAG_25h9", cv::aruco::DICT_APRILTAG_25h9},
    {"DICT_APRILTAG_36h10", cv::aruco::DICT_APRILTAG_36h10},
    {"DICT_APRILTAG_36h11", cv::aruco::DICT_APRILTAG_36h11},
};

cv::Ptr<cv::aruco::Dictionary> ArucoDictionary(const std::string& name) {
  const int id = ArucoDictionaryId(name);
  if (id < 0) Fail("unknown ArUco dictionary '", name, "' (known: ", ArucoDictionaryNames(), ")");
  return cv::aruco::getPredefinedDictionary(id);
}

// Black area of the cells of a lattice (side `cell`, top-left corner `u0`, `v0`, `across` x
// `down` cells, `black` row-major) inside a convex polygon whose bounding box is given.
double LatticeBlackArea(const std::vector<Eigen::Vector2d>& polygon, const Eigen::Vector4d& box,
                        double u0, double v0, double cell, int across, int down,
                        const std::vector<uint8_t>& black) {
  const int cu0 = std::max(0, static_cast<int>(std::floor((box[0] - u0) / cell)));
  const int cu1 = std::min(across - 1, static_cast<int>(std::floor((box[1] - u0) / cell)));
  const int cv0 = std::max(0, static_cast<int>(std::floor((box[2] - v0) / cell)));
  const int cv1 = std::min(down - 1, static_cast<int>(std::floor((box[3] - v0) / cell)));
  double area = 0;
  for (int cv = cv0; cv <= cv1; ++cv) {
    for (int cu = cu0; cu <= cu1; ++cu) {
      if (black[static_cast<size_t>(cv) * across + cu] == 0) continue;
      const double u = u0 + cu * cell;
      const double v = v0 + cv * cell;
      area += ClippedArea(polygon, u, v, u + cell, v + cell);
    }
  }
  return area;
}

// Appends the runs of black cells along each row of a lattice as rectangles.
void AppendBlackRuns(double u0, double v0, double cell, int across, int down,
                     const std::vector<uint8_t>& black, std::vector<Eigen::Vector4d>* rectangles) {
  for (int cv = 0; cv < down; ++cv) {
    int run_start = -1;
    for (int cu = 0; cu <= across; ++cu) {
      const bool is_black = cu < across && black[static_cast<size_t>(cv) * across + cu] != 0;
      if (is_black && run_start < 0) run_start = cu;
      if (!is_black && run_start >= 0) {
        rectangles->emplace_back(u0 + run_start * cell, v0 + cv * cell, (cu - run_start) * cell,
                                 cell);
        run_start = -1;
      }
    }
  }
}

}  // namespace

int ArucoDictionaryId(const std::string& name) {
  for (const auto& [known, id] : kArucoDictionaries) {
    if (name == known) return static_cast<int>(id);
  }
  return -1;
}

std::string ArucoDictionaryNames() {
  std::string names;
  for (const auto& [known, id] : kArucoDictionaries)
    names += (names.empty() ? "" : ", ") + std::string(known);
  return names;
}

cv::Ptr<cv::aruco::CharucoBoard> MakeCharucoBoard(const BoardLayout& layout) {
  if (layout.type != BoardType::kCharuco) Fail("a ", ToString(layout.type), " is no ChArUco board");
  layout.Check();
  cv::Ptr<cv::aruco::CharucoBoard> board = cv::aruco::CharucoBoard::create(
      layout.squares_across, layout.squares_down, static_cast<float>(layout.spacing),
      static_cast<float>(layout.marker_side), ArucoDictionary(layout.dictionary));
  std::vector<int> ids(board->ids.size());
  for (size_t k = 0; k < ids.size(); ++k) ids[k] = layout.first_id + static_cast<int>(k);
  board->setIds(ids);
  return board;
}

const char* ToString(BoardType type) {
  switch (type) {
    case BoardType::kAprilGrid:
      return "apriltag";
    case BoardType::kChessboard:
      return "chessboard";
    case BoardType::kCharuco:
      return "charuco";
  }
  return "unknown";
}

BoardType BoardTypeFromString(const std::string& text) {
  if (text == "apriltag") return BoardType::kAprilGrid;
  if (text == "chessboard") return BoardType::kChessboard;
  if (text == "charuco") return BoardType::kCharuco;
  Fail("unknown board type '", text, "' (known: apriltag, chessboard, charuco)");
}

int BoardLayout::width_n() const {
  switch (type) {
    case BoardType::kAprilGrid:
      return (tags_across - 1) * (tag_steps + gap_steps) + tag_steps + 1;
    case BoardType::kChessboard:
      return chessboard_width_n;
    case BoardType::kCharuco:
      return squares_across - 1;
  }
  return 0;
}

int BoardLayout::height_n() const {
  switch (type) {
    case BoardType::kAprilGrid:
      return (tags_down - 1) * (tag_steps + gap_steps) + tag_steps + 1;
    case BoardType::kChessboard:
      return chessboard_height_n;
    case BoardType::kCharuco:
      return squares_down - 1;
  }
  return 0;
}

int BoardLayout::feature_steps() const { return type == BoardType::kAprilGrid ? tag_steps : 1; }

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
  if (type == BoardType::kCharuco) {
    HOLOCAP_CHECK_OPTION_GE(squares_across, 3, "a ChArUco board needs at least 3x3 squares");
    HOLOCAP_CHECK_OPTION_GE(squares_down, 3, "a ChArUco board needs at least 3x3 squares");
    HOLOCAP_CHECK_OPTION_GT(marker_side, 0);
    HOLOCAP_CHECK_OPTION(
        marker_side < spacing, marker_side,
        Cat("the marker must be smaller than its square (spacing ", spacing, " m)"));
    HOLOCAP_CHECK_OPTION(ArucoDictionaryId(dictionary) >= 0, dictionary,
                         Cat("known: ", ArucoDictionaryNames()));
    const int markers = squares_across * squares_down / 2;
    const int codes = ArucoDictionary(dictionary)->bytesList.rows;
    HOLOCAP_CHECK_OPTION_GE(first_id, 0);
    HOLOCAP_CHECK_OPTION(first_id + markers <= codes, first_id,
                         Cat("marker ids ", first_id, "..", first_id + markers - 1, " exceed ",
                             dictionary, " (", codes, " markers)"));
    HOLOCAP_CHECK_OPTION(
        margin >= spacing * (1 - 1e-9), margin,
        Cat("the margin cuts the outer squares: it needs >= spacing ", spacing, " m"));
    return;
  }
  HOLOCAP_CHECK_OPTION(FindFamily(family) != nullptr, family, "known: tag36h11, tagStandard41h12");
  HOLOCAP_CHECK_OPTION_IN(border_bits, 0, 2);
  HOLOCAP_CHECK_OPTION(
      border_bits == 1 || this->family == "tag36h11", border_bits,
      Cat("only tag36h11 is printed with Kalibr's two-bit borders, not ", this->family));
  const apriltag_family_t* family = FindFamily(this->family, drawn_border_bits());
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
  HOLOCAP_CHECK_OPTION_GE(tag_steps, 1);
  HOLOCAP_CHECK_OPTION_GE(gap_steps, 1);
  const double bit = tag_steps * spacing / family->width_at_border;
  const double outer = bit * OuterBits(family);
  HOLOCAP_CHECK_OPTION(margin >= outer * (1 - 1e-9), margin,
                       Cat("the margin cuts the tags' outer bits: it needs >= ", outer, " m"));
  HOLOCAP_CHECK_OPTION(gap_steps * spacing >= 2 * outer * (1 - 1e-9), gap_steps,
                       Cat("the gap between tags (", gap_steps * spacing,
                           " m) must hold both tags' outer bits: >= ", 2 * outer, " m"));
  HOLOCAP_CHECK_OPTION(drawn_border_bits() == 1 || margin >= gap_steps * spacing * (1 - 1e-9),
                       margin,
                       Cat("Kalibr's print puts squares of the gap's side (", gap_steps * spacing,
                           " m) at the outer tags' corners: the margin needs >= that"));
}

nlohmann::json BoardLayout::ToJson() const {
  nlohmann::json json = {{"type", ToString(type)}, {"spacing", spacing}, {"margin", margin}};
  if (type == BoardType::kAprilGrid) {
    json["family"] = family;
    json["tags_across"] = tags_across;
    json["tags_down"] = tags_down;
    json["tag_steps"] = tag_steps;
    json["gap_steps"] = gap_steps;
    json["ids_upward"] = ids_upward;
    json["first_id"] = first_id;
    json["border_bits"] = border_bits;
  } else if (type == BoardType::kChessboard) {
    json["chessboard_width_n"] = chessboard_width_n;
    json["chessboard_height_n"] = chessboard_height_n;
  } else {
    json["squares_across"] = squares_across;
    json["squares_down"] = squares_down;
    json["marker_side"] = marker_side;
    json["dictionary"] = dictionary;
    json["first_id"] = first_id;
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
    layout.squares_across = json.value("squares_across", layout.squares_across);
    layout.squares_down = json.value("squares_down", layout.squares_down);
    layout.marker_side = json.value("marker_side", layout.marker_side);
    layout.dictionary = json.value("dictionary", layout.dictionary);
    layout.spacing = json.value("spacing", layout.spacing);
    layout.tag_steps = json.value("tag_steps", layout.tag_steps);
    layout.gap_steps = json.value("gap_steps", layout.gap_steps);
    layout.ids_upward = json.value("ids_upward", layout.ids_upward);
    layout.first_id = json.value("first_id", layout.first_id);
    layout.border_bits = json.value("border_bits", layout.border_bits);
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
  if (node["target_type"]) return FromKalibrYaml(text, origin);
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
  layout.squares_across = YamlField(node, "squares_across", layout.squares_across, origin);
  layout.squares_down = YamlField(node, "squares_down", layout.squares_down, origin);
  layout.marker_side = YamlField(node, "marker_side", layout.marker_side, origin);
  layout.dictionary = YamlField(node, "dictionary", layout.dictionary, origin);
  layout.spacing = YamlField(node, "spacing", layout.spacing, origin);
  layout.tag_steps = YamlField(node, "tag_steps", layout.tag_steps, origin);
  layout.gap_steps = YamlField(node, "gap_steps", layout.gap_steps, origin);
  layout.ids_upward = YamlField(node, "ids_upward", layout.ids_upward, origin);
  layout.first_id = YamlField(node, "first_id", layout.first_id, origin);
  layout.border_bits = YamlField(node, "border_bits", layout.border_bits, origin);
  layout.margin = YamlField(node, "margin", layout.margin, origin);
  try {
    layout.Check();
  } catch (const Error& e) {
    Fail(origin, ": ", e.what());
  }
  return layout;
}

namespace {

// A Kalibr field that must be there.
template <typename T>
T KalibrField(const YAML::Node& node, const char* key, const std::string& origin) {
  if (!node[key]) Fail(origin, ": Kalibr's target needs field '", key, "'");
  return YamlField<T>(node, key, T{}, origin);
}

// Refuses a field of a Kalibr target that holocap does not read.
void RefuseOtherKalibrFields(const YAML::Node& node, std::initializer_list<const char*> known,
                             const std::string& origin, const std::string& target_type) {
  std::string names;
  for (const char* k : known) names += (names.empty() ? "" : ", ") + std::string(k);
  for (const auto& entry : node) {
    const std::string key = entry.first.as<std::string>();
    if (std::none_of(known.begin(), known.end(), [&](const char* k) { return key == k; })) {
      Fail(origin, ": field '", key, "' of a Kalibr ", target_type,
           " is not supported (read: ", names, ")");
    }
  }
}

}  // namespace

BoardLayout BoardLayout::FromKalibrYaml(const std::string& text, const std::string& origin) {
  YAML::Node node;
  try {
    node = YAML::Load(text);
  } catch (const YAML::Exception& e) {
    Fail(origin, ": not YAML: ", e.what());
  }
  if (!node.IsMap()) Fail(origin, ": Kalibr's target must be a mapping");
  const std::string target_type = KalibrField<std::string>(node, "target_type", origin);
  BoardLayout layout;
  if (target_type == "checkerboard") {
    RefuseOtherKalibrFields(
        node, {"target_type", "targetCols", "targetRows", "rowSpacingMeters", "colSpacingMeters"},
        origin, target_type);
    const double row_spacing = KalibrField<double>(node, "rowSpacingMeters", origin);
    const double col_spacing = KalibrField<double>(node, "colSpacingMeters", origin);
    if (!(std::abs(row_spacing - col_spacing) <= 1e-9 * std::abs(col_spacing))) {
      Fail(origin, ": field 'rowSpacingMeters': holocap's chessboards have square cells, but ",
           row_spacing, " != colSpacingMeters ", col_spacing);
    }
    layout.type = BoardType::kChessboard;
    layout.chessboard_width_n = KalibrField<int>(node, "targetCols", origin);
    layout.chessboard_height_n = KalibrField<int>(node, "targetRows", origin);
    layout.spacing = col_spacing;
    layout.margin = col_spacing;
  } else if (target_type == "aprilgrid") {
    RefuseOtherKalibrFields(node, {"target_type", "tagCols", "tagRows", "tagSize", "tagSpacing"},
                            origin, target_type);
    const double tag_size = KalibrField<double>(node, "tagSize", origin);
    const double tag_spacing = KalibrField<double>(node, "tagSpacing", origin);
    if (!(tag_size > 0) || !std::isfinite(tag_size))
      Fail(origin, ": field 'tagSize': must be a positive length in metres, got ", tag_size);
    if (!(tag_spacing > 0) || !std::isfinite(tag_spacing))
      Fail(origin, ": field 'tagSpacing': must be a positive fraction of tagSize, got ",
           tag_spacing);
    // The smallest grid that holds every tag corner: tagSize / steps with tagSpacing * steps
    // whole (0.3: tenths of a tag, 0.25: quarters).
    int steps = 0;
    for (int k = 1; k <= kMaxKalibrTagSteps && steps == 0; ++k) {
      const double gap = tag_spacing * k;
      if (std::abs(gap - std::round(gap)) <= 1e-6 * k) steps = k;
    }
    if (steps == 0) {
      Fail(origin, ": field 'tagSpacing': ", tag_spacing, " times no whole number of steps up to ",
           kMaxKalibrTagSteps,
           " is whole, so the tag corners lie on no grid holocap solves (use a "
           "tagSpacing in multiples of 1/",
           kMaxKalibrTagSteps, ")");
    }
    layout.type = BoardType::kAprilGrid;
    layout.family = "tag36h11";
    layout.tags_across = KalibrField<int>(node, "tagCols", origin);
    layout.tags_down = KalibrField<int>(node, "tagRows", origin);
    layout.tag_steps = steps;
    layout.gap_steps = static_cast<int>(std::lround(tag_spacing * steps));
    layout.spacing = tag_size / steps;
    layout.ids_upward = true;
    layout.first_id = 0;
    layout.border_bits = 0;  // printed by Kalibr (2) or by holocap board (1)
    layout.margin = layout.gap_steps * layout.spacing;
  } else {
    Fail(origin, ": field 'target_type': Kalibr's '", target_type,
         "' is not supported (supported: aprilgrid, checkerboard)");
  }
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
    out << YAML::Key << "tag_steps" << YAML::Value << tag_steps;
    out << YAML::Key << "gap_steps" << YAML::Value << gap_steps;
    out << YAML::Key << "ids_upward" << YAML::Value << ids_upward;
    out << YAML::Key << "first_id" << YAML::Value << first_id;
    out << YAML::Key << "border_bits" << YAML::Value << border_bits;
  } else if (type == BoardType::kChessboard) {
    out << YAML::Key << "chessboard_width_n" << YAML::Value << chessboard_width_n;
    out << YAML::Key << "chessboard_height_n" << YAML::Value << chessboard_height_n;
  } else {
    out << YAML::Key << "squares_across" << YAML::Value << squares_across;
    out << YAML::Key << "squares_down" << YAML::Value << squares_down;
    out << YAML::Key << "marker_side" << YAML::Value << marker_side;
    out << YAML::Key << "dictionary" << YAML::Value << dictionary;
    out << YAML::Key << "first_id" << YAML::Value << first_id;
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

  if (layout_.type != BoardType::kAprilGrid) {
    cell_ = s;
    origin_ = -s;
    cells_u_ = layout_.width_n() + 1;
    cells_v_ = layout_.height_n() + 1;
    black_.resize(static_cast<size_t>(cells_u_) * cells_v_);
    for (int cv = 0; cv < cells_v_; ++cv) {
      for (int cu = 0; cu < cells_u_; ++cu) black_[cv * cells_u_ + cu] = (cu + cv) % 2 == 0;
    }
    if (layout_.type == BoardType::kCharuco) BuildCharuco();
    return;
  }

  BuildAprilTags();
}

// One cell per tag, a tag pitch wide, the tag's whole image (its outer bits included) at the
// cell's top left: Check() keeps the gap wide enough for both neighbours' outer bits, so the
// image never leaves its cell.
void Board::BuildAprilTags() {
  const apriltag_family_t* family = FindFamily(layout_.family, layout_.drawn_border_bits());
  const int border = family->width_at_border;
  const int total = family->total_width;
  const double bit = layout_.tag_steps * layout_.spacing / border;
  cell_ = (layout_.tag_steps + layout_.gap_steps) * layout_.spacing;
  origin_ = -OuterBits(family) * bit;
  cells_u_ = layout_.tags_across;
  cells_v_ = layout_.tags_down;
  black_.assign(static_cast<size_t>(cells_u_) * cells_v_, 0);
  marker_of_cell_.assign(static_cast<size_t>(cells_u_) * cells_v_, -1);
  for (int tj = 0; tj < layout_.tags_down; ++tj) {
    for (int ti = 0; ti < layout_.tags_across; ++ti) {
      const int row = layout_.ids_upward ? layout_.tags_down - 1 - tj : tj;
      Marker marker;
      marker.bits = total;
      marker.bit = bit;
      marker.u0 = origin_ + ti * cell_;
      marker.v0 = origin_ + tj * cell_;
      marker.black = TagBits(family, layout_.first_id + row * layout_.tags_across + ti);
      marker_of_cell_[static_cast<size_t>(tj) * cells_u_ + ti] = static_cast<int>(markers_.size());
      markers_.push_back(std::move(marker));
    }
  }
  if (layout_.drawn_border_bits() == 2) BuildCornerSquares();
}

// Kalibr's kalibr_create_target_pdf puts a black square of the gap's side diagonally beyond each
// corner of every tag: together, one at every crossing of a gap column with a gap row, the
// board's outer gaps (its margin) included.
void Board::BuildCornerSquares() {
  const int pitch = layout_.tag_steps + layout_.gap_steps;
  Lattice& l = corner_squares_;
  l.cell = layout_.spacing;
  l.u0 = l.v0 = -layout_.gap_steps * layout_.spacing;
  l.across = layout_.tags_across * pitch + layout_.gap_steps;
  l.down = layout_.tags_down * pitch + layout_.gap_steps;
  // Step k of the lattice lies in a gap when, counted from the first gap's start, it falls
  // within the gap of its pitch.
  auto in_gap = [&](int k) { return k % pitch < layout_.gap_steps; };
  l.black.assign(static_cast<size_t>(l.across) * l.down, 0);
  for (int cv = 0; cv < l.down; ++cv) {
    for (int cu = 0; cu < l.across; ++cu) {
      l.black[static_cast<size_t>(cv) * l.across + cu] = in_gap(cu) && in_gap(cv);
    }
  }
}

// The markers where OpenCV's CharucoBoard puts them (its object points, shifted from its frame
// to holocap's by one square), each drawn by OpenCV at one pixel per bit.
void Board::BuildCharuco() {
  const cv::Ptr<cv::aruco::CharucoBoard> charuco = MakeCharucoBoard(layout_);
  const cv::Ptr<cv::aruco::Dictionary>& dictionary = charuco->dictionary;
  marker_of_cell_.assign(static_cast<size_t>(cells_u_) * cells_v_, -1);
  const int bits = dictionary->markerSize + 2;
  for (size_t k = 0; k < charuco->ids.size(); ++k) {
    // The marker's corner 0 is its top-left; float object points, so the square it sits in
    // comes from its centre and its offset from the layout, exactly.
    const std::vector<cv::Point3f>& corners = charuco->objPoints[k];
    const double centre_u = 0.5 * (corners[0].x + corners[2].x) - layout_.spacing;
    const double centre_v = 0.5 * (corners[0].y + corners[2].y) - layout_.spacing;
    const int cu = static_cast<int>(std::floor((centre_u - origin_) / cell_));
    const int cv = static_cast<int>(std::floor((centre_v - origin_) / cell_));
    if (cu < 0 || cv < 0 || cu >= cells_u_ || cv >= cells_v_ || CellIsBlack(cu, cv)) {
      Fail("ChArUco marker ", k, " is not inside a white square of the board");
    }
    Marker marker;
    marker.bits = bits;
    marker.bit = layout_.marker_side / bits;
    marker.u0 = origin_ + cu * cell_ + 0.5 * (cell_ - layout_.marker_side);
    marker.v0 = origin_ + cv * cell_ + 0.5 * (cell_ - layout_.marker_side);
    cv::Mat image;
    dictionary->drawMarker(charuco->ids[k], bits, image, 1);
    marker.black.resize(static_cast<size_t>(bits) * bits);
    for (int y = 0; y < bits; ++y) {
      for (int x = 0; x < bits; ++x) {
        marker.black[static_cast<size_t>(y) * bits + x] = image.at<uint8_t>(y, x) < 128;
      }
    }
    marker_of_cell_[static_cast<size_t>(cv) * cells_u_ + cu] = static_cast<int>(markers_.size());
    markers_.push_back(std::move(marker));
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

bool Board::TagCornerOf(int i, int j, TagCorner* corner) const {
  if (layout_.type != BoardType::kAprilGrid)
    Fail("a ", ToString(layout_.type), " has no tag corners");
  if (i < 0 || j < 0 || i >= width_n() || j >= height_n()) {
    Fail("grid point (", i, ", ", j, ") is off the ", width_n(), "x", height_n(), " board");
  }
  const int pitch = layout_.tag_steps + layout_.gap_steps;
  const int di = i % pitch, dj = j % pitch;
  if ((di != 0 && di != layout_.tag_steps) || (dj != 0 && dj != layout_.tag_steps)) return false;
  const int tj = j / pitch;
  const int row = layout_.ids_upward ? layout_.tags_down - 1 - tj : tj;
  corner->tag_id = layout_.first_id + row * layout_.tags_across + i / pitch;
  const bool right = di != 0;
  const bool bottom = dj != 0;
  corner->corner = bottom ? (right ? 1 : 0) : (right ? 2 : 3);
  return true;
}

bool Board::GridPointOf(int tag_id, int corner, int* i, int* j) const {
  if (layout_.type != BoardType::kAprilGrid || corner < 0 || corner > 3) return false;
  const int index = tag_id - layout_.first_id;
  if (index < 0 || index >= tag_count()) return false;
  const int pitch = layout_.tag_steps + layout_.gap_steps;
  const int row = index / layout_.tags_across;
  const int tj = layout_.ids_upward ? layout_.tags_down - 1 - row : row;
  const bool right = corner == 1 || corner == 2;
  const bool bottom = corner == 0 || corner == 1;
  *i = pitch * (index % layout_.tags_across) + (right ? layout_.tag_steps : 0);
  *j = pitch * tj + (bottom ? layout_.tag_steps : 0);
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
  if (!corner_squares_.black.empty()) {
    const Lattice& l = corner_squares_;
    const int su = static_cast<int>(std::floor((u - l.u0) / l.cell));
    const int sv = static_cast<int>(std::floor((v - l.v0) / l.cell));
    if (su >= 0 && sv >= 0 && su < l.across && sv < l.down &&
        l.black[static_cast<size_t>(sv) * l.across + su] != 0) {
      return 0.0;
    }
  }
  const int cu = static_cast<int>(std::floor((u - origin_) / cell_));
  const int cv = static_cast<int>(std::floor((v - origin_) / cell_));
  if (CellIsBlack(cu, cv)) return 0.0;
  if (markers_.empty() || cu < 0 || cv < 0 || cu >= cells_u_ || cv >= cells_v_) return 1.0;
  const int index = marker_of_cell_[static_cast<size_t>(cv) * cells_u_ + cu];
  if (index < 0) return 1.0;
  const Marker& m = markers_[index];
  const int bu = static_cast<int>(std::floor((u - m.u0) / m.bit));
  const int bv = static_cast<int>(std::floor((v - m.v0) / m.bit));
  if (bu < 0 || bv < 0 || bu >= m.bits || bv >= m.bits) return 1.0;
  return m.black[static_cast<size_t>(bv) * m.bits + bu] != 0 ? 0.0 : 1.0;
}

std::vector<Eigen::Vector4d> Board::BlackRectangles() const {
  std::vector<Eigen::Vector4d> rectangles;
  AppendBlackRuns(origin_, origin_, cell_, cells_u_, cells_v_, black_, &rectangles);
  for (const Marker& m : markers_) {
    AppendBlackRuns(m.u0, m.v0, m.bit, m.bits, m.bits, m.black, &rectangles);
  }
  const Lattice& l = corner_squares_;
  AppendBlackRuns(l.u0, l.v0, l.cell, l.across, l.down, l.black, &rectangles);
  return rectangles;
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
  const Eigen::Vector4d box(lo_u, hi_u, lo_v, hi_v);
  double black =
      LatticeBlackArea(polygon, box, origin_, origin_, cell_, cells_u_, cells_v_, black_);
  // The corner squares lie in the gaps, clear of every tag's black bits.
  const Lattice& l = corner_squares_;
  if (!l.black.empty()) {
    black += LatticeBlackArea(polygon, box, l.u0, l.v0, l.cell, l.across, l.down, l.black);
  }
  if (!markers_.empty()) {
    const int cu0 = std::max(0, static_cast<int>(std::floor((lo_u - origin_) / cell_)));
    const int cu1 = std::min(cells_u_ - 1, static_cast<int>(std::floor((hi_u - origin_) / cell_)));
    const int cv0 = std::max(0, static_cast<int>(std::floor((lo_v - origin_) / cell_)));
    const int cv1 = std::min(cells_v_ - 1, static_cast<int>(std::floor((hi_v - origin_) / cell_)));
    for (int cv = cv0; cv <= cv1; ++cv) {
      for (int cu = cu0; cu <= cu1; ++cu) {
        const int index = marker_of_cell_[static_cast<size_t>(cv) * cells_u_ + cu];
        if (index < 0) continue;
        const Marker& m = markers_[index];
        black += LatticeBlackArea(polygon, box, m.u0, m.v0, m.bit, m.bits, m.bits, m.black);
      }
    }
  }
  return std::clamp(1.0 - black / area, 0.0, 1.0);
}

}  // namespace holocap
