#include <gtest/gtest.h>

#include <cstdio>
#include <fstream>
#include <opencv2/aruco/charuco.hpp>
#include <utility>

#include "calibration/calibration.h"
#include "core/error.h"
#include "core/fs.h"
#include "tests/calibration/synthetic_rig.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::RenderBoard;
using testing::TempDir;

// A slightly distorted 640x480 lens looking at the board from 1.1 m, tilted.
struct Scene {
  CameraModel camera{
      "LENSMODEL_OPENCV4", {520.3, 519.1, 322.4, 236.9, -0.082, 0.031, 0.0006, -0.0004}, 640, 480};
  Pose cam_from_board = Pose::Identity();
  explicit Scene(const Board& board, double tilt_deg = 25, double distance = 1.1) {
    const Eigen::Vector3d centre((board.width_n() - 1) * board.layout().spacing / 2,
                                 (board.height_n() - 1) * board.layout().spacing / 2, 0);
    cam_from_board.linear() =
        Eigen::AngleAxisd(tilt_deg * M_PI / 180, Eigen::Vector3d(0.6, 0.8, 0)).toRotationMatrix();
    cam_from_board.translation() =
        Eigen::Vector3d(0.03, -0.02, distance) - cam_from_board.linear() * centre;
  }
};

struct CornerErrors {
  double mean = 0, max = 0;
  int count = 0;
};

CornerErrors Errors(const BoardObservation& obs, const Scene& scene, const Board& board) {
  CornerErrors e;
  const auto grid = board.GridPoints();
  for (int r = 0; r < obs.points.rows(); ++r) {
    if (obs.points(r, 2) <= 0) continue;
    Eigen::Vector2d truth;
    EXPECT_TRUE(scene.camera.Project(scene.cam_from_board * grid[r], &truth));
    const double d = (obs.points.row(r).head<2>().transpose() - truth).norm();
    e.mean += d;
    e.max = std::max(e.max, d);
    ++e.count;
  }
  if (e.count > 0) e.mean /= e.count;
  return e;
}

BoardLayout NineBySixChessboard() {
  BoardLayout layout;
  layout.type = BoardType::kChessboard;
  layout.chessboard_width_n = 9;
  layout.chessboard_height_n = 6;
  layout.spacing = 0.05;
  layout.margin = 0.06;
  return layout;
}

class AprilTagFamilies : public ::testing::TestWithParam<std::string> {};

// Corners against the exact projection of the true grid: libapriltag alone and refined.
TEST_P(AprilTagFamilies, CornersAreSubPixelAgainstTheTruth) {
  BoardLayout layout = testing::TestBoard();
  layout.family = GetParam();
  if (layout.family == "tagStandard41h12") layout.margin = 0.08;
  const Board board(layout);
  const Scene scene(board);
  const cv::Mat image = RenderBoard(scene.camera, board, scene.cam_from_board, 2.0);
  DetectionOptions raw_options;
  raw_options.refine_corners = false;
  BoardObservation raw, refined;
  std::string reason;
  ASSERT_TRUE(BoardDetector(layout, raw_options).Detect(image, &raw, &reason)) << reason;
  ASSERT_TRUE(BoardDetector(layout).Detect(image, &refined, &reason)) << reason;
  const CornerErrors before = Errors(raw, scene, board);
  const CornerErrors after = Errors(refined, scene, board);
  std::printf("[%s] %d corners: libapriltag mean %.3f max %.3f px; refined mean %.3f max %.3f px\n",
              layout.family.c_str(), after.count, before.mean, before.max, after.mean, after.max);
  EXPECT_EQ(after.count, board.width_n() * board.height_n());
  EXPECT_LT(after.mean, 0.06);
  EXPECT_LT(after.max, 0.2);
  EXPECT_LT(after.mean, before.mean);
}

INSTANTIATE_TEST_SUITE_P(Families, AprilTagFamilies,
                         ::testing::Values("tag36h11", "tagStandard41h12"));

// The sub-pixel corner finder on noise-free renders: every corner within 0.05 px of the true
// projection, for tag L corners and chessboard X junctions, through a mildly distorted lens
// and through the real wide OPENCV8 lens (tests/data/lenses, scaled to 640 px across).
TEST(CornerRefiner, NoiseFreeCornersLieWithinFiveHundredthsOfAPixel) {
  const CameraModel wide =
      CameraModel::Read(testing::TestDataDir() / "lenses" / "wide-4000x2200.opencv8.cameramodel")
          .Scaled(640.0 / 4000);
  for (const BoardLayout& layout : {testing::TestBoard(), NineBySixChessboard()}) {
    const Board board(layout);
    for (bool real_lens : {false, true}) {
      for (double tilt : {15.0, 30.0}) {
        Scene scene(board, tilt, real_lens ? 0.6 : 1.0);
        if (real_lens) scene.camera = wide;
        const cv::Mat image = RenderBoard(scene.camera, board, scene.cam_from_board);
        BoardObservation refined;
        std::string reason;
        ASSERT_TRUE(BoardDetector(layout).Detect(image, &refined, &reason)) << reason;
        const CornerErrors e = Errors(refined, scene, board);
        std::printf("[%s, %s lens, tilt %.0f] %d corners: mean %.4f max %.4f px\n",
                    ToString(layout.type), real_lens ? "real OPENCV8" : "OPENCV4", tilt, e.count,
                    e.mean, e.max);
        EXPECT_EQ(e.count, board.width_n() * board.height_n());
        EXPECT_LE(e.max, 0.05);
      }
    }
  }
}

TEST(BoardDetector, FindsChessboardCornersInHolocapOrder) {
  const BoardLayout layout = NineBySixChessboard();
  const Board board(layout);
  for (double tilt : {20.0, 160.0}) {  // 160: seen upside down, OpenCV starts at the other end
    Scene scene(board, 20);
    scene.cam_from_board.linear() =
        scene.cam_from_board.linear() *
        Eigen::AngleAxisd(tilt > 90 ? M_PI : 0, Eigen::Vector3d::UnitZ());
    const Eigen::Vector3d centre(4 * 0.05, 2.5 * 0.05, 0);
    scene.cam_from_board.translation() =
        Eigen::Vector3d(0, 0, 1.0) - scene.cam_from_board.linear() * centre;
    const cv::Mat image = RenderBoard(scene.camera, board, scene.cam_from_board, 2.0);
    BoardObservation obs;
    std::string reason;
    ASSERT_TRUE(BoardDetector(layout).Detect(image, &obs, &reason)) << reason;
    const CornerErrors e = Errors(obs, scene, board);
    EXPECT_EQ(e.count, 54);
    EXPECT_LT(e.max, 0.2) << "rotation " << tilt;
  }
}

// The finder travels in each detector's options: holocap's and mrgingham's detectors, alive
// together in one process, each read the same square chessboard their own way (mrgingham's
// corners lie ~0.1 px from holocap's on such renders).
TEST(BoardDetector, EachDetectorUsesTheFinderItsOptionsName) {
  BoardLayout layout = NineBySixChessboard();
  layout.chessboard_width_n = 7;
  layout.chessboard_height_n = 7;
  const Board board(layout);
  const Scene scene(board, 20, 0.9);
  const cv::Mat image = RenderBoard(scene.camera, board, scene.cam_from_board, 2.0);
  DetectionOptions holocap_options, mrgingham_options;
  mrgingham_options.chessboard_finder = ChessboardFinder::kMrgingham;
  const BoardDetector holocap(layout, holocap_options);
  const BoardDetector mrgingham(layout, mrgingham_options);
  BoardObservation a, b, again;
  std::string reason;
  ASSERT_TRUE(mrgingham.Detect(image, &b, &reason)) << reason;
  ASSERT_TRUE(holocap.Detect(image, &a, &reason)) << reason;
  ASSERT_TRUE(mrgingham.Detect(image, &again, &reason)) << reason;
  EXPECT_EQ(a.seen(), 49);
  EXPECT_EQ(b.seen(), 49);
  // A square board's numbering may start at any corner (the solve makes cameras agree): each
  // of holocap's corners against mrgingham's nearest.
  double largest_gap = 0;
  for (Eigen::Index r = 0; r < a.points.rows(); ++r) {
    double nearest = INFINITY;
    for (Eigen::Index q = 0; q < b.points.rows(); ++q)
      nearest = std::min(nearest, (a.points.row(r) - b.points.row(q)).head<2>().norm());
    largest_gap = std::max(largest_gap, nearest);
  }
  EXPECT_GT(largest_gap, 1e-3) << "both detectors ran the same finder";
  EXPECT_LT(largest_gap, 1.0);
  EXPECT_EQ(again.points, b.points);
}

TEST(BoardDetector, RejectsAPartialBoardAndAnEmptyImage) {
  const BoardLayout layout = testing::TestBoard();
  const Board board(layout);
  Scene scene(board, 10, 1.0);
  scene.cam_from_board.translation().x() += 0.75;  // most of the board beyond the right edge
  const cv::Mat image = RenderBoard(scene.camera, board, scene.cam_from_board);
  BoardObservation obs;
  std::string reason;
  DetectionOptions options;
  options.min_tags = 8;
  EXPECT_FALSE(BoardDetector(layout, options).Detect(image, &obs, &reason));
  EXPECT_NE(reason.find("partial"), std::string::npos) << reason;
  EXPECT_EQ(obs.seen(), 0);
  const cv::Mat blank(480, 640, CV_8UC1, cv::Scalar(128));
  EXPECT_FALSE(BoardDetector(layout).Detect(blank, &obs, &reason));
}

BoardLayout SevenByFiveCharuco() {
  return testing::CharucoLayout(7, 5, 0.06, 0.045, "DICT_5X5_100", 3);
}

// The simulator's ChArUco texture is OpenCV's own drawing of the board, pixel for pixel, at
// resolutions where OpenCV's squares, marker margins and marker bits fall on whole pixels. The
// sizes are exact binary fractions: CharucoBoard::draw truncates its float marker size, and
// draws a 4 cm square's 3.5 cm marker one pixel left of and above its object points (which
// detection uses, and the texture follows).
TEST(CharucoBoard, TextureIsOpenCVsDrawing) {
  struct Case {
    int across, down;
    double square, marker;
    std::string dictionary;
    int first_id, px_per_square;
  };
  for (const Case& c : {Case{5, 7, 0.04, 0.03, "DICT_4X4_50", 0, 16},
                        Case{6, 4, 0.0625, 0.0546875, "DICT_5X5_1000", 17, 32}}) {
    const BoardLayout layout =
        testing::CharucoLayout(c.across, c.down, c.square, c.marker, c.dictionary, c.first_id);
    const Board board(layout);
    const cv::Ptr<cv::aruco::CharucoBoard> opencv = cv::aruco::CharucoBoard::create(
        c.across, c.down, static_cast<float>(c.square), static_cast<float>(c.marker),
        cv::aruco::getPredefinedDictionary(ArucoDictionaryId(c.dictionary)));
    std::vector<int> ids(opencv->ids.size());
    for (size_t k = 0; k < ids.size(); ++k) ids[k] = c.first_id + static_cast<int>(k);
    opencv->setIds(ids);
    cv::Mat drawn;
    opencv->draw(cv::Size(c.across * c.px_per_square, c.down * c.px_per_square), drawn, 0, 1);
    ASSERT_EQ(drawn.cols, c.across * c.px_per_square);
    const double px = c.square / c.px_per_square;
    int differ = 0, black = 0;
    for (int y = 0; y < drawn.rows; ++y) {
      for (int x = 0; x < drawn.cols; ++x) {
        // OpenCV's board frame starts at the top-left square's corner, holocap's one square in.
        const double u = (x + 0.5) * px - c.square;
        const double v = (y + 0.5) * px - c.square;
        const bool drawn_black = drawn.at<uint8_t>(y, x) < 128;
        differ += drawn_black != (board.Reflectance(u, v) < 0.5);
        black += drawn_black;
      }
    }
    EXPECT_EQ(differ, 0) << c.dictionary;
    EXPECT_GT(black, drawn.total() / 4) << c.dictionary;
  }
}

// ChArUco corners against the exact projection of the true grid, the whole board in view and
// most of it beyond the image's edge: every corner found lands on its own grid point (measured
// 0.005 and 0.014 px on average, 0.02 px at most; 0.09 px before the edge refinement, and a
// corner numbered onto another grid point is a square, tens of pixels, away).
TEST(CharucoBoard, CornersLieOnTheTrueGridAlsoInAPartialView) {
  const BoardLayout layout = SevenByFiveCharuco();
  const Board board(layout);
  for (const double shift_m : {0.0, 0.5}) {
    Scene scene(board, 25, 0.9);
    scene.cam_from_board.translation().x() += shift_m;
    const cv::Mat image = RenderBoard(scene.camera, board, scene.cam_from_board, 2.0);
    BoardObservation obs;
    std::string reason;
    ASSERT_TRUE(BoardDetector(layout).Detect(image, &obs, &reason)) << reason;
    const CornerErrors e = Errors(obs, scene, board);
    if (shift_m == 0) {
      EXPECT_EQ(e.count, 24);
    } else {
      EXPECT_GE(e.count, 4);
      EXPECT_LT(e.count, 20);
    }
    EXPECT_LT(e.mean, 0.05) << "shift " << shift_m;
    EXPECT_LT(e.max, 0.1) << "shift " << shift_m;
    std::printf("ChArUco shift %.1f m: %d corners, mean %.4f px, max %.4f px\n", shift_m, e.count,
                e.mean, e.max);
  }
}

// Another board's tags or ArUco markers (ids outside this layout) are told apart from "no
// board".
TEST(BoardDetector, NamesTagsOfADifferentBoard) {
  for (const auto& [layout, foreign_id] :
       {std::pair{testing::TestBoard(), 100}, std::pair{SevenByFiveCharuco(), 40}}) {
    BoardLayout printed = layout;
    printed.first_id = foreign_id;
    const Board board(printed);
    const Scene scene(board);
    const cv::Mat image = RenderBoard(scene.camera, board, scene.cam_from_board);
    BoardObservation obs;
    std::string reason;
    EXPECT_FALSE(BoardDetector(layout).Detect(image, &obs, &reason));
    EXPECT_NE(reason.find("not on this board"), std::string::npos) << reason;
    EXPECT_EQ(obs.seen(), 0);
    EXPECT_EQ(BoardDetector(layout).DetectTagIds(image).front(), foreign_id);
  }
}

// The board at 0.8 m, tilted 20 degrees and turned about its normal through `centre` by
// `quarter` quarter turns.
Scene TurnedScene(const Board& board, const Eigen::Vector3d& centre, int quarter) {
  Scene scene(board, 20, 0.8);
  Pose turn = Pose::Identity();
  turn.linear() = Eigen::AngleAxisd(quarter * M_PI / 2, Eigen::Vector3d::UnitZ()).matrix();
  turn.translation() = centre - turn.linear() * centre;
  scene.cam_from_board = scene.cam_from_board * turn;
  return scene;
}

// Kalibr's aprilgrid (6 x 6 tags of 5 cm, gaps of 0.3 tags) turned about its normal by 0, 90,
// 180 and 270 degrees: the detector numbers every corner from the tag libapriltag decodes, so
// each lies on the true projection of the grid point Kalibr's numbering gives it, whichever
// way up the board is, and only the 144 tag corners of the 76 x 76 grid are seen.
TEST(KalibrAprilgrid, CornersKeepKalibrsNumberingOnATurnedBoard) {
  TempDir dir;
  std::ofstream(dir / "kalibr.yaml") << "target_type: 'aprilgrid'\ntagCols: 6\ntagRows: 6\n"
                                        "tagSize: 0.05\ntagSpacing: 0.3\n";
  const BoardLayout layout = BoardLayout::Load(dir / "kalibr.yaml");
  const Board board(layout);
  ASSERT_EQ(board.width_n() * board.height_n(), 76 * 76);
  const Eigen::Vector3d centre((board.width_n() - 1) * layout.spacing / 2,
                               (board.height_n() - 1) * layout.spacing / 2, 0);
  for (int quarter = 0; quarter < 4; ++quarter) {
    const Scene scene = TurnedScene(board, centre, quarter);
    const cv::Mat image = RenderBoard(scene.camera, board, scene.cam_from_board, 2.0);
    BoardObservation obs;
    std::string reason;
    ASSERT_TRUE(BoardDetector(layout).Detect(image, &obs, &reason)) << reason;
    const CornerErrors e = Errors(obs, scene, board);
    std::printf("Kalibr aprilgrid turned %d degrees: %d corners, mean %.3f max %.3f px\n",
                90 * quarter, e.count, e.mean, e.max);
    EXPECT_EQ(e.count, 144) << quarter;
    EXPECT_LT(e.mean, 0.06) << quarter;
    EXPECT_LT(e.max, 0.2) << quarter;
    EXPECT_EQ(obs.tag_border_bits, 1) << quarter;  // holocap's print of Kalibr's YAML
  }
}

// The same aprilgrid as Kalibr's kalibr_create_target_pdf prints it (tags with two-bit black
// borders, black squares at the gaps' crossings touching the tags' corners), read with the
// Kalibr YAML (printed by Kalibr or by holocap board, so both borders are tried), turned about
// its normal by 0, 90, 180 and 270 degrees at 0.8 m (tags of about 32 px): every tag is found
// with the two-bit border, and each corner lies on the true projection of where Kalibr's own
// target puts it, from tag 0's bottom-left corner with y up: tag k's corner c at
// x = (k % tagCols) (1 + tagSpacing) tagSize + [c is 1 or 2] tagSize,
// y = (k / tagCols) (1 + tagSpacing) tagSize + [c is 2 or 3] tagSize
// (GridCalibrationTargetAprilgrid), holocap's v = the grid's height - y.
TEST(KalibrAprilgrid, FindsKalibrsOwnPrintWhereKalibrPutsItsCorners) {
  TempDir dir;
  std::ofstream(dir / "kalibr.yaml") << "target_type: 'aprilgrid'\ntagCols: 6\ntagRows: 6\n"
                                        "tagSize: 0.05\ntagSpacing: 0.3\n";
  const BoardLayout layout = BoardLayout::Load(dir / "kalibr.yaml");
  EXPECT_EQ(layout.border_bits, 0);
  BoardLayout kalibr_print = layout;
  kalibr_print.border_bits = 2;
  const Board printed(kalibr_print);
  const Board board(layout);
  const double tag_size = 0.05, tag_spacing = 0.3;
  const double height = 5 * (1 + tag_spacing) * tag_size + tag_size;
  const Eigen::Vector3d centre(height / 2, height / 2, 0);
  for (int quarter = 0; quarter < 4; ++quarter) {
    const Scene scene = TurnedScene(board, centre, quarter);
    const cv::Mat image = RenderBoard(scene.camera, printed, scene.cam_from_board, 2.0);
    BoardObservation obs;
    std::string reason;
    ASSERT_TRUE(BoardDetector(layout).Detect(image, &obs, &reason)) << reason;
    EXPECT_EQ(obs.tag_border_bits, 2) << quarter;
    int count = 0;
    double sum = 0, max = 0;
    for (int id = 0; id < 36; ++id) {
      for (int c = 0; c < 4; ++c) {
        int i = 0, j = 0;
        ASSERT_TRUE(board.GridPointOf(id, c, &i, &j));
        const auto row = static_cast<Eigen::Index>(j) * board.width_n() + i;
        if (obs.points(row, 2) <= 0) continue;
        const int tag_column = id % 6;
        const int tag_row = id / 6;
        const double x = tag_column * (1 + tag_spacing) * tag_size + (c == 1 || c == 2) * tag_size;
        const double y = tag_row * (1 + tag_spacing) * tag_size + (c == 2 || c == 3) * tag_size;
        Eigen::Vector2d truth;
        ASSERT_TRUE(
            scene.camera.Project(scene.cam_from_board * Eigen::Vector3d(x, height - y, 0), &truth));
        const double d = (obs.points.row(row).head<2>().transpose() - truth).norm();
        sum += d;
        max = std::max(max, d);
        ++count;
      }
    }
    std::printf("Kalibr's print turned %d degrees: %d corners, mean %.3f max %.3f px\n",
                90 * quarter, count, sum / std::max(count, 1), max);
    EXPECT_EQ(count, 144) << quarter;
    EXPECT_LT(sum / std::max(count, 1), 0.06) << quarter;
    EXPECT_LT(max, 0.2) << quarter;
  }
}

TEST(BoardPrint, PdfPageIsTheBoardsSizeAndThePngDetects) {
  TempDir dir;
  const BoardLayout layout = testing::TestBoard();
  const Board board(layout);
  WriteBoardPrint(layout, dir / "board.pdf");
  const std::string pdf = ReadFileToString(dir / "board.pdf");
  const double width_pt = (board.u_max() - board.u_min()) / 0.0254 * 72;
  char media[96];
  std::snprintf(media, sizeof(media), "/MediaBox [0 0 %.4f ", width_pt);
  EXPECT_NE(pdf.find(media), std::string::npos) << pdf.substr(0, 300);
  EXPECT_EQ(pdf.substr(0, 8), "%PDF-1.4");

  const cv::Mat print = RenderBoardImage(layout, 100);
  EXPECT_NEAR(print.cols, (board.u_max() - board.u_min()) / 0.0254 * 100, 1.0);
  EXPECT_EQ(BoardDetector(layout).DetectTagIds(print).size(), 20u);
  EXPECT_THROW(WriteBoardPrint(layout, dir / "board.jpg"), Error);
}

// A ChArUco print: squares and marker bits in the PDF, every corner found in the PNG.
TEST(BoardPrint, ACharucoPrintDetects) {
  TempDir dir;
  const BoardLayout layout = SevenByFiveCharuco();
  const Board board(layout);
  WriteBoardPrint(layout, dir / "board.pdf");
  const std::string pdf = ReadFileToString(dir / "board.pdf");
  size_t rectangles = 0;
  for (size_t at = pdf.find(" re\n"); at != std::string::npos; at = pdf.find(" re\n", at + 1))
    ++rectangles;
  EXPECT_EQ(rectangles, board.BlackRectangles().size());
  EXPECT_GT(board.BlackRectangles().size(), 17u * 7);  // the squares' rows and every marker's
  const cv::Mat print = RenderBoardImage(layout, 100);
  BoardObservation obs;
  std::string reason;
  cv::Mat padded;
  cv::copyMakeBorder(print, padded, 40, 40, 40, 40, cv::BORDER_CONSTANT, cv::Scalar(255));
  ASSERT_TRUE(BoardDetector(layout).Detect(padded, &obs, &reason)) << reason;
  EXPECT_EQ(obs.seen(), 24);
}

}  // namespace
}  // namespace holocap
