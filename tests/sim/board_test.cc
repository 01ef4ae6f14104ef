#include "core/board.h"

#include <gtest/gtest.h>

#include <fstream>
#include <random>
#include <set>
#include <string>

#include "core/error.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

TEST(BoardTest, EveryGridPointIsACornerOfExactlyOneTag) {
  for (const std::string family : {"tag36h11", "tagStandard41h12"}) {
    BoardLayout layout;
    layout.family = family;
    layout.tags_across = 4;
    layout.tags_down = 3;
    layout.first_id = 7;
    const Board board(layout);
    ASSERT_EQ(board.width_n(), 8);
    ASSERT_EQ(board.height_n(), 6);
    std::set<std::pair<int, int>> seen;
    for (int j = 0; j < board.height_n(); ++j) {
      for (int i = 0; i < board.width_n(); ++i) {
        TagCorner corner;
        ASSERT_TRUE(board.TagCornerOf(i, j, &corner));
        EXPECT_TRUE(seen.insert({corner.tag_id, corner.corner}).second) << family;
        int ri = -1, rj = -1;
        ASSERT_TRUE(board.GridPointOf(corner.tag_id, corner.corner, &ri, &rj));
        EXPECT_EQ(ri, i);
        EXPECT_EQ(rj, j);
      }
    }
    EXPECT_EQ(seen.size(), 4u * 12u);
    EXPECT_EQ(seen.begin()->first, 7);
    EXPECT_FALSE(board.GridPointOf(6, 0, nullptr, nullptr));
  }
}

TEST(BoardTest, TagCornersSitOnTheBlackBorder) {
  // Just inside each detection corner (towards the tag's centre) the border is black; just
  // outside (away from it, diagonally) the tag36h11 quiet ring is white.
  const Board board(BoardLayout{});
  const double s = board.layout().spacing, eps = s / 100;
  for (int j = 0; j < board.height_n(); ++j) {
    for (int i = 0; i < board.width_n(); ++i) {
      const Eigen::Vector3d p = board.GridPoint(i, j);
      const double inward_u = i % 2 == 0 ? 1 : -1, inward_v = j % 2 == 0 ? 1 : -1;
      EXPECT_EQ(board.Reflectance(p.x() + inward_u * eps, p.y() + inward_v * eps), 0.0);
      EXPECT_EQ(board.Reflectance(p.x() - inward_u * eps, p.y() - inward_v * eps), 1.0);
      EXPECT_EQ(board.Reflectance(p.x() - inward_u * eps, p.y() + inward_v * eps), 1.0);
    }
  }
}

TEST(BoardTest, MeanReflectanceIsTheAreaIntegral) {
  for (BoardType type : {BoardType::kAprilGrid, BoardType::kChessboard}) {
    BoardLayout layout;
    layout.type = type;
    const Board board(layout);
    std::mt19937 rng(3);
    std::uniform_real_distribution<double> where(0, 0.3), size(0.002, 0.02);
    for (int trial = 0; trial < 20; ++trial) {
      const Eigen::Vector2d c(where(rng), where(rng));
      const double a = size(rng), b = size(rng);
      // A sheared parallelogram, as a pixel's footprint seen at an angle.
      const Eigen::Vector2d e1(a, 0.3 * b), e2(-0.2 * a, b);
      const std::vector<Eigen::Vector2d> quad = {c, c + e1, c + e1 + e2, c + e2};
      double sum = 0;
      const int n = 400;
      for (int y = 0; y < n; ++y) {
        for (int x = 0; x < n; ++x) {
          const Eigen::Vector2d p = c + (x + 0.5) / n * e1 + (y + 0.5) / n * e2;
          sum += board.Reflectance(p.x(), p.y());
        }
      }
      EXPECT_NEAR(board.MeanReflectance(quad), sum / (n * n), 3e-3);
    }
  }
}

TEST(BoardTest, YamlRoundTripAndChecks) {
  testing::TempDir dir;
  BoardLayout layout;
  layout.family = "tagStandard41h12";
  layout.tags_across = 7;
  layout.spacing = 0.0312;
  layout.margin = 0.05;
  layout.first_id = 100;
  layout.Save(dir / "board.yaml");
  const BoardLayout loaded = BoardLayout::Load(dir / "board.yaml");
  EXPECT_EQ(loaded.family, layout.family);
  EXPECT_EQ(loaded.tags_across, 7);
  EXPECT_EQ(loaded.first_id, 100);
  EXPECT_DOUBLE_EQ(loaded.spacing, 0.0312);
  EXPECT_EQ(BoardLayout::FromJson(layout.ToJson()).ToJson(), layout.ToJson());

  BoardLayout bad = layout;
  bad.margin = 0.001;  // cuts tagStandard41h12's outer data bits
  EXPECT_THROW(bad.Check(), Error);
  bad = layout;
  bad.family = "tag25h9";
  EXPECT_THROW(bad.Check(), Error);
  bad = layout;
  bad.first_id = 2110;
  EXPECT_THROW(bad.Check(), Error);
  bad = layout;
  bad.spacing = 0;
  EXPECT_THROW(bad.Check(), Error);
}

// A ChArUco layout reads back as written; each inconsistency is one error naming its field.
TEST(BoardTest, CharucoYamlRoundTripAndChecks) {
  testing::TempDir dir;
  const BoardLayout layout = testing::CharucoLayout(9, 6, 0.03, 0.022, "DICT_6X6_250", 11);
  layout.Save(dir / "board.yaml");
  const BoardLayout loaded = BoardLayout::Load(dir / "board.yaml");
  EXPECT_EQ(loaded.type, BoardType::kCharuco);
  EXPECT_EQ(loaded.squares_across, 9);
  EXPECT_EQ(loaded.squares_down, 6);
  EXPECT_DOUBLE_EQ(loaded.marker_side, 0.022);
  EXPECT_EQ(loaded.dictionary, "DICT_6X6_250");
  EXPECT_EQ(loaded.first_id, 11);
  EXPECT_EQ(loaded.width_n(), 8);
  EXPECT_EQ(loaded.height_n(), 5);
  EXPECT_EQ(BoardLayout::FromJson(layout.ToJson()).ToJson(), layout.ToJson());

  auto expect_error = [&](const BoardLayout& bad, const std::string& needle) {
    try {
      bad.Check();
      ADD_FAILURE() << "no error for " << needle;
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
    }
  };
  BoardLayout bad = layout;
  bad.marker_side = 0.03;
  expect_error(bad, "smaller than its square");
  bad = layout;
  bad.dictionary = "DICT_5X5";
  expect_error(bad, "DICT_5X5_1000");  // the known names
  bad = layout;
  bad.dictionary = "DICT_4X4_50";
  bad.first_id = 30;  // 27 markers: ids 30..56
  expect_error(bad, "exceed DICT_4X4_50 (50 markers)");
  bad = layout;
  bad.squares_down = 2;
  expect_error(bad, "3x3 squares");
  bad = layout;
  bad.margin = 0.01;
  expect_error(bad, "outer squares");
}

// Kalibr's aprilgrid YAML (its README's 6 x 6 board): every tag corner sits where Kalibr's own
// target puts it. Kalibr's points are numbered row by row from the bottom (y up), two rows and
// columns per tag, at x = (c / 2) (1 + tagSpacing) tagSize + (c % 2) tagSize; tag k's corners
// are its points base, base + 1, base + cols + 1, base + cols with base = (k / tagCols) 2 cols
// + (k % tagCols) 2 (GridCalibrationTargetAprilgrid). holocap's board frame has v down.
TEST(KalibrAprilgrid, EveryTagCornerIsWhereKalibrPutsIt) {
  testing::TempDir dir;
  std::ofstream(dir / "kalibr.yaml") << "target_type: 'aprilgrid'\ntagCols: 6\ntagRows: 6\n"
                                        "tagSize: 0.088\ntagSpacing: 0.3\n";
  const BoardLayout layout = BoardLayout::Load(dir / "kalibr.yaml");
  EXPECT_EQ(layout.family, "tag36h11");
  EXPECT_EQ(layout.tag_steps, 10);
  EXPECT_EQ(layout.gap_steps, 3);
  EXPECT_DOUBLE_EQ(layout.spacing, 0.0088);
  const Board board(layout);
  ASSERT_EQ(board.width_n(), 76);
  ASSERT_EQ(board.height_n(), 76);
  const double tag_size = 0.088, tag_spacing = 0.3;
  const int cols = 12;  // Kalibr's points per row: 2 per tag
  const double top = (board.height_n() - 1) * layout.spacing;
  auto kalibr_point = [&](int index) {
    const int r = index / cols, c = index % cols;
    const int tag_column = c / 2, tag_row = r / 2;
    return Eigen::Vector2d(tag_column * (1 + tag_spacing) * tag_size + (c % 2) * tag_size,
                           tag_row * (1 + tag_spacing) * tag_size + (r % 2) * tag_size);
  };
  for (int id = 0; id < 36; ++id) {
    const int base = (id / 6) * cols * 2 + (id % 6) * 2;
    const int kalibr_index[4] = {base, base + 1, base + cols + 1, base + cols};
    for (int corner = 0; corner < 4; ++corner) {
      int i = -1, j = -1;
      ASSERT_TRUE(board.GridPointOf(id, corner, &i, &j));
      const Eigen::Vector3d p = board.GridPoint(i, j);
      const Eigen::Vector2d expected = kalibr_point(kalibr_index[corner]);
      EXPECT_NEAR(p.x(), expected.x(), 1e-12) << "tag " << id << " corner " << corner;
      EXPECT_NEAR(top - p.y(), expected.y(), 1e-12) << "tag " << id << " corner " << corner;
      TagCorner back;
      ASSERT_TRUE(board.TagCornerOf(i, j, &back));
      EXPECT_EQ(back.tag_id, id);
      EXPECT_EQ(back.corner, corner);
    }
  }
  // Only the 144 tag corners are corners; the other 5632 grid points are never observed.
  int corners = 0;
  for (int j = 0; j < board.height_n(); ++j) {
    for (int i = 0; i < board.width_n(); ++i) {
      TagCorner c;
      corners += board.TagCornerOf(i, j, &c);
    }
  }
  EXPECT_EQ(corners, 144);
  // The printed tags are black up to their corners, with white in the gaps between them.
  const double eps = layout.spacing / 10;
  for (int id : {0, 5, 30, 35}) {
    int i = 0, j = 0;
    board.GridPointOf(id, 0, &i, &j);  // bottom left
    const Eigen::Vector3d p = board.GridPoint(i, j);
    EXPECT_EQ(board.Reflectance(p.x() + eps, p.y() - eps), 0.0) << id;
    EXPECT_EQ(board.Reflectance(p.x() - eps, p.y() + eps), 1.0) << id;
  }
  // holocap's own layout written back and read again is the same board.
  layout.Save(dir / "saved.yaml");
  EXPECT_EQ(BoardLayout::Load(dir / "saved.yaml").ToJson(), layout.ToJson());

  // Kalibr's own print of it (kalibr_create_target_pdf): the same black squares, now with
  // black borders two bits (a tenth of a tag) wide, and a black square of the gap's side
  // diagonally beyond each tag corner, white elsewhere in the gaps.
  BoardLayout kalibr_print = layout;
  kalibr_print.border_bits = 2;
  const Board printed(kalibr_print);
  const double bit = tag_size / 10, gap = tag_spacing * tag_size;
  for (int id : {0, 5, 30, 35}) {
    int i = 0, j = 0;
    printed.GridPointOf(id, 0, &i, &j);  // bottom left: u right, v down
    const Eigen::Vector3d p = printed.GridPoint(i, j);
    EXPECT_EQ(printed.Reflectance(p.x() + eps, p.y() - eps), 0.0) << id;
    EXPECT_EQ(printed.Reflectance(p.x() + 1.5 * bit, p.y() - 5 * bit), 0.0) << id;  // border
    EXPECT_EQ(printed.Reflectance(p.x() - eps, p.y() + eps), 0.0) << id;            // corner square
    EXPECT_EQ(printed.Reflectance(p.x() - gap + eps, p.y() + gap - eps), 0.0) << id;
    EXPECT_EQ(printed.Reflectance(p.x() - gap - eps, p.y() + eps), 1.0) << id;  // beyond it
    EXPECT_EQ(printed.Reflectance(p.x() + eps, p.y() + eps), 1.0) << id;        // the gap below
    EXPECT_EQ(printed.Reflectance(p.x() - eps, p.y() - eps), 1.0) << id;        // the gap left
  }
  EXPECT_DOUBLE_EQ(printed.u_min(), -gap);  // the outer squares fill the margin
  EXPECT_THROW(
      [&] {
        BoardLayout standard = kalibr_print;
        standard.family = "tagStandard41h12";
        standard.Check();
      }(),
      Error);
}

// Anything of a Kalibr target file holocap does not read is one error naming it.
TEST(KalibrAprilgrid, RefusesWhatItDoesNotReadByName) {
  testing::TempDir dir;
  auto error_of = [&](const std::string& yaml) -> std::string {
    std::ofstream(dir / "target.yaml") << yaml;
    try {
      BoardLayout::Load(dir / "target.yaml");
    } catch (const Error& e) {
      return e.what();
    }
    return "no error";
  };
  const std::string grid = "target_type: 'aprilgrid'\ntagCols: 6\ntagRows: 6\ntagSize: 0.088\n";
  EXPECT_NE(error_of(grid + "tagSpacing: 0.3\ncodeOffset: 36\n").find("field 'codeOffset'"),
            std::string::npos);
  EXPECT_NE(error_of(grid).find("needs field 'tagSpacing'"), std::string::npos);
  EXPECT_NE(error_of(grid + "tagSpacing: 0.33\n").find("field 'tagSpacing': 0.33"),
            std::string::npos);
  EXPECT_NE(error_of(grid + "tagSpacing: 0.1\n").find("outer bits"), std::string::npos);
  EXPECT_NE(error_of(grid + "tagSpacing: -0.3\n").find("field 'tagSpacing'"), std::string::npos);
  EXPECT_NE(error_of("target_type: 'circlegrid'\ntargetCols: 6\n").find("'circlegrid'"),
            std::string::npos);
  EXPECT_NE(error_of("target_type: 'checkerboard'\ntargetCols: 6\ntargetRows: 7\n"
                     "rowSpacingMeters: 0.06\ncolSpacingMeters: 0.05\n")
                .find("square cells"),
            std::string::npos);

  // Kalibr's checkerboard with square cells is holocap's chessboard.
  std::ofstream(dir / "checker.yaml") << "target_type: 'checkerboard'\ntargetCols: 6\n"
                                         "targetRows: 7\nrowSpacingMeters: 0.06\n"
                                         "colSpacingMeters: 0.06\n";
  const BoardLayout chess = BoardLayout::Load(dir / "checker.yaml");
  EXPECT_EQ(chess.type, BoardType::kChessboard);
  EXPECT_EQ(chess.width_n(), 6);
  EXPECT_EQ(chess.height_n(), 7);
  EXPECT_DOUBLE_EQ(chess.spacing, 0.06);
}

}  // namespace
}  // namespace holocap
