// Calibration boards: the layout that the simulated rig renders and that calibration detects.
//
// Board frame: the board is the z = 0 plane, u = x to the right and v = y downwards as the
// board is seen from its printed (front) side, which faces -z. Grid points lie at
// (i * spacing, j * spacing, 0) for i < width_n, j < height_n, exactly mrcal's board model.
//
// AprilTag boards put the tags' detection corners on that one grid: every tag is
// tag_steps * spacing wide (its detection square, i.e. libapriltag's width_at_border bits) and
// neighbouring tags are gap_steps * spacing apart. holocap's own boards have tag_steps =
// gap_steps = 1, so grid point (i, j) is a corner of exactly one tag: tag (i / 2, j / 2) of the
// tag grid, with id first_id + (j / 2) * tags_across + i / 2. Kalibr's aprilgrid (tags
// tagSize apart by tagSpacing * tagSize) is not one uniform grid of corners; it becomes one with
// spacing tagSize / tag_steps when tagSpacing * tag_steps is a whole number (gap_steps), and
// the grid points between the tag corners are never seen (mrcal's weight < 0). Ids run row by
// row from the top row down, or with ids_upward from the bottom row up (Kalibr's: tag 0 at the
// bottom left). The corner numbering is libapriltag's detection order, which wraps
// counter-clockwise in the image as seen from the front: 0 = (-u, +v), 1 = (+u, +v),
// 2 = (+u, -v), 3 = (-u, -v); Kalibr numbers a tag's corners the same way (bottom left, bottom
// right, top right, top left).
// A tag's black square may carry a black border of one bit (libapriltag's tags, holocap's prints)
// or of two bits (border_bits = 2: Kalibr's kalibr_create_target_pdf prints, which also fill
// every crossing of the gaps between tags, outer ones included, with a black square of the gap's
// side that touches the tags' corners); either way the tag side tag_steps * spacing is the black
// square's, and its corners are the tag's corners.
// Chessboards put the grid on the inner corners: (width_n + 1) x (height_n + 1) squares with
// the square at (-spacing, -spacing) black.
// ChArUco boards (OpenCV's CharucoBoard, as OpenCV 4.6 draws it) are such a chessboard of
// squares_across x squares_down squares, the square at (-spacing, -spacing) black, with an ArUco
// marker of side marker_side centred in every white square; markers are numbered row by row from
// first_id. ChArUco corner id k is grid point (k % width_n, k / width_n): OpenCV's board frame
// is holocap's shifted by one square (x right, y down, seen from the front).
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

namespace holocap {

enum class BoardType { kAprilGrid, kChessboard, kCharuco };
const char* ToString(BoardType type);                    // "apriltag", "chessboard", "charuco"
BoardType BoardTypeFromString(const std::string& text);  // throws Error

struct BoardLayout {
  BoardType type = BoardType::kAprilGrid;  // tags on one corner grid, a chessboard, a ChArUco
  std::string family = "tag36h11";         // AprilTag family: "tag36h11" or "tagStandard41h12"
  int tags_across = 6;          // AprilTag boards: tags per row (grid is 2x as many points)
  int tags_down = 5;            // AprilTag boards: tags per column
  int chessboard_width_n = 9;   // chessboards: inner corners per row
  int chessboard_height_n = 6;  // chessboards: inner corners per column
  int squares_across = 5;       // ChArUco boards: squares per row (grid: one point fewer)
  int squares_down = 7;         // ChArUco boards: squares per column
  double marker_side = 0.03;    // ChArUco boards: metres, the ArUco marker's black outline
  std::string dictionary = "DICT_5X5_1000";  // ChArUco boards: OpenCV's ArUco dictionary name
  double spacing = 0.04;    // metres between neighbouring grid points (the square side; the
                            // tag side over tag_steps)
  int tag_steps = 1;        // AprilTag boards: grid steps along a tag's side
  int gap_steps = 1;        // AprilTag boards: grid steps between neighbouring tags
  bool ids_upward = false;  // AprilTag boards: ids run from the bottom row up (Kalibr's order)
  // AprilTag boards (tag36h11 only for other than 1): the printed tags' black border in bits,
  // 1 (libapriltag's) or 2 (Kalibr's print, corner squares included); 0 when the print may be
  // either (Kalibr's target YAML): detection tries both borders, and the board is drawn with 1.
  int border_bits = 1;
  int first_id = 0;      // id of the top-left tag or marker (bottom-left with ids_upward); ids run
                         // row by row
  double margin = 0.04;  // metres of white between the outermost grid points and
                         // the board's edge (covers the tags' outer bits)

  // Throws Error with the reason for an inconsistent layout (unknown family or dictionary, too
  // few points, ids beyond the family or dictionary, a marker not smaller than its square, a
  // margin that cuts the tags' outer bits or the outer squares).
  void Check() const;

  int width_n() const;   // grid points per row
  int height_n() const;  // grid points per column
  // Grid steps along the side of what a detector needs large enough to see: a tag's side for
  // AprilTag boards, 1 (a square) for the others.
  int feature_steps() const;
  // The border the board is drawn with (AprilTag boards): border_bits, or 1 for 0.
  int drawn_border_bits() const { return border_bits == 2 ? 2 : 1; }

  nlohmann::json ToJson() const;
  static BoardLayout FromJson(const nlohmann::json& json, const std::string& origin = "board");
  // YAML (or JSON, which YAML reads) with the field names above; `type` is "apriltag",
  // "chessboard" or "charuco". Missing fields keep their defaults. A file with Kalibr's
  // `target_type` is read as Kalibr's target (FromKalibrYaml). Throws Error naming file and
  // field.
  static BoardLayout Load(const std::filesystem::path& file);
  // Kalibr's target YAML: target_type 'aprilgrid' (tagCols, tagRows, tagSize in metres,
  // tagSpacing as a fraction of tagSize; tag36h11, ids from the bottom-left tag, border_bits 0:
  // printed by Kalibr or by holocap board) or
  // 'checkerboard' with square cells (targetCols x targetRows inner corners, rowSpacingMeters
  // = colSpacingMeters). The aprilgrid's grid spacing is tagSize / tag_steps for the smallest
  // tag_steps <= kMaxKalibrTagSteps that makes tagSpacing * tag_steps whole. Throws Error
  // naming the field for anything else (other target types, unknown or missing fields, a
  // tagSpacing without such a divisor).
  static BoardLayout FromKalibrYaml(const std::string& text, const std::string& origin);
  static constexpr int kMaxKalibrTagSteps = 10;
  void Save(const std::filesystem::path& file) const;  // YAML, atomic
};

// OpenCV's cv::aruco::PREDEFINED_DICTIONARY_NAME value of a dictionary name ("DICT_5X5_1000"),
// -1 for a name OpenCV does not define; and the names it knows, comma-separated.
int ArucoDictionaryId(const std::string& name);
std::string ArucoDictionaryNames();

// Which tag corner a grid point is (AprilTag boards).
struct TagCorner {
  int tag_id = 0;
  int corner = 0;  // libapriltag's corner index 0..3
};

// A board built from its layout: the grid points and an exact texture built from
// libapriltag's own family bitmaps, or from OpenCV's own ArUco marker bitmaps placed where its
// CharucoBoard puts them. Immutable and safe to share between threads.
class Board {
 public:
  explicit Board(const BoardLayout& layout);  // checks the layout

  const BoardLayout& layout() const { return layout_; }
  int width_n() const { return layout_.width_n(); }
  int height_n() const { return layout_.height_n(); }

  // All grid points in board coordinates (z = 0), row-major: index j * width_n + i.
  std::vector<Eigen::Vector3d> GridPoints() const;
  Eigen::Vector3d GridPoint(int i, int j) const;
  // AprilTag boards only (throws Error for the others): the tag corner at grid point (i, j);
  // false for a point between tags' corners (boards with tag_steps > 1).
  bool TagCornerOf(int i, int j, TagCorner* corner) const;
  // The grid point of a tag corner; false when the id is not on this board.
  bool GridPointOf(int tag_id, int corner, int* i, int* j) const;
  int tag_count() const;

  // The board's outline in board coordinates: [u_min, u_max] x [v_min, v_max].
  double u_min() const { return u_min_; }
  double u_max() const { return u_max_; }
  double v_min() const { return v_min_; }
  double v_max() const { return v_max_; }
  bool Contains(double u, double v) const;

  // The printed side's reflectance at (u, v): 0 black, 1 white; 1 outside the pattern but on
  // the board, and also off the board (callers test Contains()).
  double Reflectance(double u, double v) const;
  // The printed pattern as black rectangles (u, v of the top-left corner, width, height): runs
  // of black cells along each row of the pattern's lattices, for vector prints.
  std::vector<Eigen::Vector4d> BlackRectangles() const;
  // Mean reflectance over a convex polygon (board coordinates, either winding): the exact
  // area integral of Reflectance(), for anti-aliasing a pixel's footprint.
  double MeanReflectance(const std::vector<Eigen::Vector2d>& polygon) const;

 private:
  // The pattern is a lattice of square cells of side cell_ starting at (origin_, origin_).
  bool CellIsBlack(int cu, int cv) const;
  // ChArUco boards: a marker's bits, a finer lattice inside one white cell. AprilTag boards:
  // a tag's bits (its total_width), at the top left of its cell, one cell per tag.
  struct Marker {
    double u0 = 0, v0 = 0;       // the marker's top-left corner
    double bit = 0;              // side of one bit
    int bits = 0;                // bits per side, black border included
    std::vector<uint8_t> black;  // bits x bits, row-major
  };
  void BuildCharuco();
  void BuildAprilTags();

  // Kalibr's prints: the black squares at the crossings of the gaps, one lattice of grid steps
  // from (-gap, -gap), black where both its column and its row lie in a gap.
  struct Lattice {
    double u0 = 0, v0 = 0, cell = 0;
    int across = 0, down = 0;
    std::vector<uint8_t> black;  // across x down, row-major
  };
  void BuildCornerSquares();

  std::vector<Marker> markers_;
  Lattice corner_squares_;
  std::vector<int> marker_of_cell_;  // cells_u_ x cells_v_: index into markers_, or -1

  BoardLayout layout_;
  double cell_ = 0;
  double origin_ = 0;
  int cells_u_ = 0;
  int cells_v_ = 0;
  std::vector<uint8_t> black_;  // cells_u_ x cells_v_, row-major
  double u_min_ = 0, u_max_ = 0, v_min_ = 0, v_max_ = 0;
};

}  // namespace holocap
