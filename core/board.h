// Calibration boards: the layout that the simulated rig renders and that calibration detects.
//
// Board frame: the board is the z = 0 plane, u = x to the right and v = y downwards as the
// board is seen from its printed (front) side, which faces -z. Grid points lie at
// (i * spacing, j * spacing, 0) for i < width_n, j < height_n, exactly mrcal's board model.
//
// AprilTag boards put the tags' detection corners on that one grid: every tag is `spacing`
// wide (its detection square, i.e. libapriltag's width_at_border bits) and neighbouring tags
// are one `spacing` apart, so grid point (i, j) is a corner of exactly one tag:
// tag (i / 2, j / 2) of the tag grid, with id first_id + (j / 2) * tags_across + i / 2. The
// corner numbering is libapriltag's detection order, which wraps counter-clockwise in the
// image as seen from the front: 0 = (-u, +v), 1 = (+u, +v), 2 = (+u, -v), 3 = (-u, -v).
// Chessboards put the grid on the inner corners: (width_n + 1) x (height_n + 1) squares with
// the square at (-spacing, -spacing) black.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

namespace holocap {

enum class BoardType { kAprilGrid, kChessboard };
const char* ToString(BoardType type);                    // "apriltag", "chessboard"
BoardType BoardTypeFromString(const std::string& text);  // throws Error

struct BoardLayout {
  BoardType type = BoardType::kAprilGrid;  // tags on one corner grid, or a chessboard
  std::string family = "tag36h11";         // AprilTag family: "tag36h11" or "tagStandard41h12"
  int tags_across = 6;          // AprilTag boards: tags per row (grid is 2x as many points)
  int tags_down = 5;            // AprilTag boards: tags per column
  int chessboard_width_n = 9;   // chessboards: inner corners per row
  int chessboard_height_n = 6;  // chessboards: inner corners per column
  double spacing = 0.04;        // metres between neighbouring grid points (the tag side)
  int first_id = 0;             // id of the top-left tag; ids run row by row
  double margin = 0.04;         // metres of white between the outermost grid points and
                                // the board's edge (covers the tags' outer bits)

  // Throws Error with the reason for an inconsistent layout (unknown family, too few points,
  // ids beyond the family, a margin that cuts the tags' outer bits).
  void Check() const;

  int width_n() const;   // grid points per row
  int height_n() const;  // grid points per column

  nlohmann::json ToJson() const;
  static BoardLayout FromJson(const nlohmann::json& json, const std::string& origin = "board");
  // YAML (or JSON, which YAML reads) with the field names above; `type` is "apriltag" or
  // "chessboard". Missing fields keep their defaults. Throws Error naming file and field.
  static BoardLayout Load(const std::filesystem::path& file);
  void Save(const std::filesystem::path& file) const;  // YAML, atomic
};

// Which tag corner a grid point is (AprilTag boards).
struct TagCorner {
  int tag_id = 0;
  int corner = 0;  // libapriltag's corner index 0..3
};

// A board built from its layout: the grid points and an exact texture built from
// libapriltag's own family bitmaps. Immutable and safe to share between threads.
class Board {
 public:
  explicit Board(const BoardLayout& layout);  // checks the layout

  const BoardLayout& layout() const { return layout_; }
  int width_n() const { return layout_.width_n(); }
  int height_n() const { return layout_.height_n(); }

  // All grid points in board coordinates (z = 0), row-major: index j * width_n + i.
  std::vector<Eigen::Vector3d> GridPoints() const;
  Eigen::Vector3d GridPoint(int i, int j) const;
  // AprilTag boards only (throws Error for chessboards).
  TagCorner TagCornerOf(int i, int j) const;
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
  // Mean reflectance over a convex polygon (board coordinates, either winding): the exact
  // area integral of Reflectance(), for anti-aliasing a pixel's footprint.
  double MeanReflectance(const std::vector<Eigen::Vector2d>& polygon) const;

 private:
  // The pattern is a lattice of square cells of side cell_ starting at (origin_, origin_).
  bool CellIsBlack(int cu, int cv) const;

  BoardLayout layout_;
  double cell_ = 0;
  double origin_ = 0;
  int cells_u_ = 0;
  int cells_v_ = 0;
  std::vector<uint8_t> black_;  // cells_u_ x cells_v_, row-major
  double u_min_ = 0, u_max_ = 0, v_min_ = 0, v_max_ = 0;
};

}  // namespace holocap
