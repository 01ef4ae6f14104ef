// Board detection: libapriltag (quad_decimate = 1) or OpenCV's chessboard finder, corners
// refined on the image edges (or mrgingham's chessboard corners), views checked for consistency;
// ChArUco boards through OpenCV's aruco module.
#include <Eigen/Dense>
#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <map>
#include <mutex>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <set>
#include <thread>

#include "calibration/calibration.h"
#include "calibration/chessboard_finders.h"
#include "calibration/internal/common.h"
#include "core/apriltag_family.h"
#include "core/charuco.h"
#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/progress.h"
#include "core/take.h"
#include "core/take_plan.h"

extern "C" {
#include <apriltag/apriltag.h>
#include <apriltag/common/zarray.h>
}

namespace holocap {
namespace {

// libapriltag 3.3 reports corners with pixel (0, 0) covering [0, 1]²; holocap's pixel centres
// are at integers. Measured against rendered boards whose corners are known exactly.
constexpr double kApriltagPixelOffset = -0.5;

// The tag borders a board's detection tries: its own, or both for a layout that may have been
// printed either way (Kalibr's target YAML).
std::vector<int> BordersToTry(const BoardLayout& layout) {
  if (layout.border_bits == 0) return {1, 2};
  return {layout.border_bits};
}

struct ApriltagDetectorDeleter {
  void operator()(apriltag_detector_t* detector) const { apriltag_detector_destroy(detector); }
};

// A libapriltag detector and the families it decodes, one per border tried (border_bits[k] for
// families[k]). Each family instance gets its own decode table (libapriltag keeps it in
// family->impl), so every detector owns its families; the detector goes first.
struct Detector {
  std::vector<ApriltagFamilyPtr> families;
  std::vector<int> border_bits;
  std::unique_ptr<apriltag_detector_t, ApriltagDetectorDeleter> detector;
};

Detector MakeDetector(const BoardLayout& layout, const DetectionOptions& options) {
  Detector d;
  d.detector.reset(apriltag_detector_create());
  for (int border : BordersToTry(layout)) {
    d.families.push_back(CreateApriltagFamily(layout.family, border));
    d.border_bits.push_back(border);
    apriltag_detector_add_family_bits(d.detector.get(), d.families.back().get(),
                                      std::max(0, options.max_hamming));
  }
  d.detector->quad_decimate = 1;  // 3.3's decimated corners are biased
  d.detector->quad_sigma = static_cast<float>(options.quad_sigma);
  d.detector->nthreads = 1;  // frames run in parallel instead
  d.detector->refine_edges = true;
  d.detector->decode_sharpening = 0.25;
  return d;
}

cv::Mat ToGrey(const cv::Mat& image) {
  if (image.empty()) Fail("board detection: empty image");
  cv::Mat grey;
  if (image.channels() == 3) {
    cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
  } else if (image.channels() == 4) {
    cv::cvtColor(image, grey, cv::COLOR_BGRA2GRAY);
  } else {
    grey = image;
  }
  if (grey.depth() == CV_16U) grey.convertTo(grey, CV_8U, 1.0 / 257.0);
  if (grey.type() != CV_8UC1) Fail("board detection needs an 8/16-bit grey or colour image");
  return grey;
}

double Bilinear(const cv::Mat& grey, double x, double y) {
  const int x0 = static_cast<int>(std::floor(x));
  const int y0 = static_cast<int>(std::floor(y));
  if (x0 < 0 || y0 < 0 || x0 + 1 >= grey.cols || y0 + 1 >= grey.rows) return NAN;
  const double fx = x - x0, fy = y - y0;
  const uint8_t* r0 = grey.ptr<uint8_t>(y0);
  const uint8_t* r1 = grey.ptr<uint8_t>(y0 + 1);
  return (1 - fy) * ((1 - fx) * r0[x0] + fx * r0[x0 + 1]) +
         fy * ((1 - fx) * r1[x0] + fx * r1[x0 + 1]);
}

// A tag's corners, each from the two quad sides that leave it. Every pixel used inside the quad
// stays within its one-bit border (`bits` bits span a side), clear of the data bits; outside,
// a tag with a white border (tag36h11) is white well beyond a bit, one with a dark outer ring
// (tagStandard41h12, reversed_border) only for one bit. `reach_px` > 0 caps both.
// Returns how many of the four corners it refined (the others stay as they were).
int RefineQuad(const cv::Mat& grey, std::array<Eigen::Vector2d, 4>* corners, int bits,
               bool reversed_border, double reach_px) {
  std::array<Eigen::Vector2d, 4> refined = *corners;
  int count = 0;
  for (int k = 0; k < 4; ++k) {
    const Eigen::Vector2d& c = (*corners)[k];
    const Eigen::Vector2d to_next = (*corners)[(k + 1) % 4] - c;
    const Eigen::Vector2d to_previous = (*corners)[(k + 3) % 4] - c;
    const double side = std::min(to_next.norm(), to_previous.norm());
    // A pixel reaches 0.71 px beyond its centre.
    const double bit = side / bits;
    double inside = std::min(bit - 0.8, 4.0);
    double outside = reversed_border ? inside : std::min(1.5 * bit, 4.0);
    if (reach_px > 0) {
      inside = std::min(inside, reach_px);
      outside = std::min(outside, reach_px);
    }
    count += calibration_internal::RefineEdgeCorner(grey, {to_next, to_previous}, inside, outside,
                                                    0.5 * side, &refined[k]);
  }
  *corners = refined;
  return count;
}

// A chessboard's inner corners (OpenCV's order, width_n per row), each from the four edges
// towards its grid neighbours.
void RefineChessboard(const cv::Mat& grey, int width_n, int height_n,
                      std::vector<cv::Point2f>* corners) {
  auto at = [&](int i, int j) {
    const cv::Point2f& p = (*corners)[static_cast<size_t>(j) * width_n + i];
    return Eigen::Vector2d(p.x, p.y);
  };
  std::vector<cv::Point2f> refined = *corners;
  for (int j = 0; j < height_n; ++j) {
    for (int i = 0; i < width_n; ++i) {
      const Eigen::Vector2d c = at(i, j);
      const Eigen::Vector2d u = i + 1 < width_n ? at(i + 1, j) - c : c - at(i - 1, j);
      const Eigen::Vector2d v = j + 1 < height_n ? at(i, j + 1) - c : c - at(i, j - 1);
      const double side = std::min(u.norm(), v.norm());
      const double reach = std::min(0.3 * side, 4.0);
      const double length = side - 1.5 * reach - 2;
      Eigen::Vector2d p = c;
      if (calibration_internal::RefineEdgeCorner(grey, {u, v, -u, -v}, reach, reach, length, &p)) {
        refined[static_cast<size_t>(j) * width_n + i] =
            cv::Point2f(static_cast<float>(p.x()), static_cast<float>(p.y()));
      }
    }
  }
  *corners = refined;
}

}  // namespace

namespace calibration_internal {

std::vector<int> TurnedGridOrder(int width_n, int height_n, int quarter_turns) {
  const int turns = ((quarter_turns % 4) + 4) % 4;
  if (turns % 2 == 1 && width_n != height_n) Fail("only a square grid turns by a quarter");
  std::vector<int> order(static_cast<size_t>(width_n) * height_n);
  for (int j = 0; j < height_n; ++j) {
    for (int i = 0; i < width_n; ++i) {
      int oi = i, oj = j;
      if (turns == 1) {
        oi = j;
        oj = width_n - 1 - i;
      } else if (turns == 2) {
        oi = width_n - 1 - i;
        oj = height_n - 1 - j;
      } else if (turns == 3) {
        oi = height_n - 1 - j;
        oj = i;
      }
      order[static_cast<size_t>(j) * width_n + i] = oj * width_n + oi;
    }
  }
  return order;
}

std::vector<ViewJob> ViewJobs(const Take& take, const std::vector<std::string>& sensors) {
  std::vector<ViewJob> jobs;
  for (size_t i = 0; i < take.size(); ++i) {
    for (const auto& s : sensors) {
      if (take.entry(i).Find(s) != nullptr) jobs.push_back({i, s});
    }
  }
  return jobs;
}

void RunViewJobs(size_t count, int threads, const std::function<void(size_t)>& work) {
  std::atomic<size_t> next{0};
  std::mutex error_mutex;
  std::string first_error;
  auto run = [&] {
    for (size_t k = next++; k < count; k = next++) {
      try {
        work(k);
      } catch (const Error& e) {
        std::lock_guard<std::mutex> lock(error_mutex);
        if (first_error.empty()) first_error = e.what();
      }
    }
  };
  std::vector<std::thread> pool;
  const int started = ResolveThreads(threads, static_cast<int>(count));
  for (int t = 1; t < started; ++t) pool.emplace_back(run);
  run();
  for (auto& t : pool) t.join();
  if (!first_error.empty()) Fail(first_error);
}

std::vector<int> AmbiguousBoardTurns(const BoardLayout& layout) {
  if (layout.type != BoardType::kChessboard) return {0};
  const int w = layout.chessboard_width_n, h = layout.chessboard_height_n;
  if (w != h) return (w + h) % 2 == 1 ? std::vector<int>{0} : std::vector<int>{0, 2};
  return w % 2 == 1 ? std::vector<int>{0, 2} : std::vector<int>{0, 1, 2, 3};
}

}  // namespace calibration_internal

int BoardObservation::seen() const {
  int count = 0;
  for (int r = 0; r < points.rows(); ++r) count += points(r, 2) > 0;
  return count;
}

void DetectionOptions::Check() const {
  HOLOCAP_CHECK_OPTION_GE(threads, 0);
  HOLOCAP_CHECK_OPTION_GE(refine_half_window_px, 0);
  HOLOCAP_CHECK_OPTION_IN(max_hamming, 0, 3);
  HOLOCAP_CHECK_OPTION_GE(min_decision_margin, 0);
  HOLOCAP_CHECK_OPTION_GE(min_tags, 1);
  HOLOCAP_CHECK_OPTION_GT(min_tag_side_px, 0);
  HOLOCAP_CHECK_OPTION_GE(quad_sigma, 0);
  HOLOCAP_CHECK_OPTION_GT(max_corner_residual_px, 0);
}

nlohmann::json DetectionOptions::ToJson() const {
  return {{"threads", threads},
          {"detector", ToString(chessboard_finder)},
          {"refine_corners", refine_corners},
          {"refine_half_window_px", refine_half_window_px},
          {"max_hamming", max_hamming},
          {"min_decision_margin", min_decision_margin},
          {"min_tags", min_tags},
          {"min_tag_side_px", min_tag_side_px},
          {"quad_sigma", quad_sigma},
          {"max_corner_residual_px", max_corner_residual_px},
          {"quad_decimate", 1}};
}

struct BoardDetector::Impl {
  std::mutex mutex;
  std::vector<Detector> idle;
  BoardLayout layout;
  DetectionOptions options;
  cv::Ptr<cv::aruco::CharucoBoard> charuco;  // ChArUco boards: OpenCV's model of the layout

  Detector Acquire() {
    {
      std::lock_guard<std::mutex> lock(mutex);
      if (!idle.empty()) {
        Detector d = std::move(idle.back());
        idle.pop_back();
        return d;
      }
    }
    return MakeDetector(layout, options);
  }
  void Release(Detector d) {
    std::lock_guard<std::mutex> lock(mutex);
    idle.push_back(std::move(d));
  }
};

BoardDetector::BoardDetector(const BoardLayout& layout, const DetectionOptions& options)
    : board_(layout), options_(options), impl_(new Impl) {
  options_.Check();
  impl_->layout = layout;
  impl_->options = options_;
  if (layout.type == BoardType::kCharuco) impl_->charuco = MakeCharucoBoard(layout);
}

BoardDetector::~BoardDetector() { delete impl_; }

namespace {

struct TagSeen {
  int id = 0;
  std::array<Eigen::Vector2d, 4> corners;
  int border_bits = 1;      // the black border it was decoded with
  int width_at_border = 0;  // its family's detection square, in bits
  bool reversed_border = false;
  int hamming = 0;
  double decision_margin = 0;
  bool shrunk = false;  // found in the shrunk image (FindTags), its corners not yet on the image
};

std::vector<TagSeen> RunApriltag(const Detector& d, const cv::Mat& grey,
                                 const DetectionOptions& options, bool filter) {
  image_u8_t image{grey.cols, grey.rows, static_cast<int32_t>(grey.step[0]),
                   const_cast<uint8_t*>(grey.ptr<uint8_t>(0))};
  zarray_t* detections = apriltag_detector_detect(d.detector.get(), &image);
  std::vector<TagSeen> tags;
  for (int k = 0; k < zarray_size(detections); ++k) {
    apriltag_detection_t* detection = nullptr;
    zarray_get(detections, k, &detection);
    if (filter && (detection->hamming > options.max_hamming ||
                   detection->decision_margin < options.min_decision_margin)) {
      continue;
    }
    TagSeen tag;
    tag.id = detection->id;
    for (size_t f = 0; f < d.families.size(); ++f) {
      if (d.families[f].get() == detection->family) tag.border_bits = d.border_bits[f];
    }
    tag.width_at_border = detection->family->width_at_border;
    tag.reversed_border = detection->family->reversed_border;
    tag.hamming = detection->hamming;
    tag.decision_margin = detection->decision_margin;
    for (int c = 0; c < 4; ++c) {
      tag.corners[c] = Eigen::Vector2d(detection->p[c][0], detection->p[c][1]) +
                       Eigen::Vector2d::Constant(kApriltagPixelOffset);
    }
    tags.push_back(tag);
  }
  apriltag_detections_destroy(detections);
  return tags;
}

bool SameQuad(const TagSeen& a, const TagSeen& b, double tolerance_px) {
  for (int c = 0; c < 4; ++c) {
    if ((a.corners[c] - b.corners[c]).norm() > tolerance_px) return false;
  }
  return true;
}

// One decoding per quad: both borders can decode the same quad to the same id (a tag of one
// border read with the other's bit grid, a bit or two corrected); the one with fewer corrected
// bits, then the larger margin, is the tag's border.
void KeepBestDecodingPerQuad(std::vector<TagSeen>* tags) {
  std::vector<TagSeen> kept;
  for (const TagSeen& t : *tags) {
    auto same = std::find_if(kept.begin(), kept.end(),
                             [&](const TagSeen& k) { return k.id == t.id && SameQuad(k, t, 1.0); });
    if (same == kept.end()) {
      kept.push_back(t);
    } else if (t.hamming < same->hamming ||
               (t.hamming == same->hamming && t.decision_margin > same->decision_margin)) {
      *same = t;
    }
  }
  *tags = std::move(kept);
}

// The tags of a board: libapriltag on the image and, where Kalibr's print may be seen, again on
// the image with its dark regions shrunk by a pixel (each pixel the maximum of itself and its
// left, upper and upper-left neighbours). Kalibr's black squares touch the tags' corners;
// blurred, a corner's pixel joins tag and square into one black region whose outline is no
// quad, and libapriltag finds no tag there. Shrinking cuts those joins, and a tag found only
// there is added, marked `shrunk`: its square lost a pixel on its left and upper sides.
std::vector<TagSeen> FindTags(const Detector& d, const cv::Mat& grey,
                              const DetectionOptions& options) {
  std::vector<TagSeen> tags = RunApriltag(d, grey, options, true);
  KeepBestDecodingPerQuad(&tags);
  if (std::find(d.border_bits.begin(), d.border_bits.end(), 2) == d.border_bits.end()) return tags;
  cv::Mat shrunk;
  cv::dilate(grey, shrunk, cv::Mat::ones(2, 2, CV_8U), cv::Point(1, 1));
  std::vector<TagSeen> more = RunApriltag(d, shrunk, options, true);
  KeepBestDecodingPerQuad(&more);
  for (TagSeen& t : more) {
    const bool known = std::any_of(tags.begin(), tags.end(), [&](const TagSeen& k) {
      return k.id == t.id && SameQuad(k, t, 3.0);
    });
    if (known) continue;
    t.shrunk = true;
    tags.push_back(t);
  }
  return tags;
}

struct MarkersSeen {
  std::vector<std::vector<cv::Point2f>> corners;
  std::vector<int> ids;
};

MarkersSeen RunAruco(const cv::Mat& grey, const cv::aruco::CharucoBoard& board) {
  MarkersSeen markers;
  const cv::Ptr<cv::aruco::DetectorParameters> parameters = cv::aruco::DetectorParameters::create();
  cv::aruco::detectMarkers(grey, board.dictionary, markers.corners, markers.ids, parameters);
  return markers;
}

double MinSide(const std::array<Eigen::Vector2d, 4>& corners) {
  double side = 1e300;
  for (int k = 0; k < 4; ++k) side = std::min(side, (corners[(k + 1) % 4] - corners[k]).norm());
  return side;
}

}  // namespace

std::vector<int> BoardDetector::DetectTagIds(const cv::Mat& image) const {
  if (board_.layout().type == BoardType::kCharuco) {
    std::vector<int> ids = RunAruco(ToGrey(image), *impl_->charuco).ids;
    std::sort(ids.begin(), ids.end());
    return ids;
  }
  if (board_.layout().type != BoardType::kAprilGrid) return {};
  const cv::Mat grey = ToGrey(image);
  Detector d = impl_->Acquire();
  std::vector<TagSeen> tags = FindTags(d, grey, options_);
  impl_->Release(std::move(d));
  std::vector<int> ids;
  ids.reserve(tags.size());
  for (const auto& t : tags) ids.push_back(t.id);
  std::sort(ids.begin(), ids.end());
  return ids;
}

bool BoardDetector::DetectChessboard(const cv::Mat& grey, BoardObservation* observation,
                                     std::string* reason) const {
  const int width_n = board_.width_n();
  const int height_n = board_.height_n();
  std::vector<cv::Point2f> corners;
  const cv::Size size(width_n, height_n);
  if (options_.chessboard_finder == ChessboardFinder::kMrgingham) {
    // mrgingham's corners as it gives them, row-major from one end as OpenCV's.
    if (width_n != height_n) Fail("mrgingham finds square grids only");
    if (!FindChessboardMrgingham(grey, width_n, &corners, reason)) return false;
  } else {
    // The fast check turns frames without a board away in milliseconds, not seconds.
    if (!cv::findChessboardCorners(grey, size, corners,
                                   cv::CALIB_CB_ADAPTIVE_THRESH | cv::CALIB_CB_NORMALIZE_IMAGE |
                                       cv::CALIB_CB_FAST_CHECK)) {
      *reason = "no chessboard found";
      return false;
    }
    cv::cornerSubPix(grey, corners, cv::Size(5, 5), cv::Size(-1, -1),
                     cv::TermCriteria(cv::TermCriteria::EPS + cv::TermCriteria::COUNT, 40, 0.001));
    if (options_.refine_corners) RefineChessboard(grey, width_n, height_n, &corners);
  }
  // OpenCV may start from any end of a board. On holocap's chessboards the square diagonally
  // outside the first corner is black and its neighbour along the first column white. Where
  // the other ends' corner squares differ in colour (width_n + height_n odd: the opposite end;
  // a square board with an odd side: the ends a quarter turn away) that fixes the numbering
  // here; the turns that keep the colours (calibration_internal::AmbiguousBoardTurns) are
  // left to the solve, which makes every camera of a frame set agree.
  const Eigen::Vector2d c0(corners[0].x, corners[0].y);
  const Eigen::Vector2d c1(corners[1].x, corners[1].y);
  const Eigen::Vector2d cw(corners[width_n].x, corners[width_n].y);
  const Eigen::Vector2d diagonal = c0 - 0.5 * (c1 - c0) - 0.5 * (cw - c0);
  const Eigen::Vector2d beside = c0 - 0.5 * (c1 - c0) + 0.5 * (cw - c0);
  const double diagonal_value = Bilinear(grey, diagonal.x(), diagonal.y());
  const double beside_value = Bilinear(grey, beside.x(), beside.y());
  const bool other_colour =
      std::isfinite(diagonal_value) && std::isfinite(beside_value) && diagonal_value > beside_value;
  const bool square = width_n == height_n;
  const int colour_turn = (width_n + height_n) % 2 == 1 ? 2 : square && width_n % 2 == 1 ? 1 : 0;
  if (other_colour && colour_turn != 0) {
    const std::vector<int> order =
        calibration_internal::TurnedGridOrder(width_n, height_n, colour_turn);
    std::vector<cv::Point2f> turned(corners.size());
    for (size_t r = 0; r < order.size(); ++r) turned[r] = corners[order[r]];
    corners = turned;
  }
  for (int k = 0; k < static_cast<int>(corners.size()); ++k) {
    observation->points.row(k) << corners[k].x, corners[k].y, 1.0;
  }
  return true;
}

bool BoardDetector::Detect(const cv::Mat& image, BoardObservation* observation,
                           std::string* reason) const {
  const cv::Mat grey = ToGrey(image);
  const int width_n = board_.width_n();
  const int height_n = board_.height_n();
  observation->points.setZero(static_cast<Eigen::Index>(width_n) * height_n, 3);
  observation->points.col(2).setConstant(-1);

  if (board_.layout().type == BoardType::kChessboard)
    return DetectChessboard(grey, observation, reason);
  if (board_.layout().type == BoardType::kCharuco) return DetectCharuco(grey, observation, reason);

  Detector d = impl_->Acquire();
  std::vector<TagSeen> tags = FindTags(d, grey, options_);
  impl_->Release(std::move(d));

  // Ids seen twice are ambiguous (a second board, a reflection): both are dropped.
  std::map<int, int> count;
  for (const auto& t : tags) ++count[t.id];
  std::map<std::pair<int, int>, int> tag_at;  // tag grid cell -> index in `tags`
  std::vector<TagSeen> kept;
  int foreign = 0;
  for (const auto& t : tags) {
    int i = 0, j = 0;
    if (!board_.GridPointOf(t.id, 0, &i, &j)) {
      ++foreign;
      continue;
    }
    if (count[t.id] > 1) continue;
    if (MinSide(t.corners) < options_.min_tag_side_px) continue;
    kept.push_back(t);
  }
  // A tag found in the shrunk image always has its corners refined on the image itself, from its
  // square grown back by the pixel the shrinking took (half a pixel on every side, the centre
  // half a pixel up and left); one whose corners do not all refine is left out.
  std::vector<TagSeen> refined;
  for (auto& t : kept) {
    if (t.shrunk) {
      const Eigen::Vector2d centre =
          0.25 * (t.corners[0] + t.corners[1] + t.corners[2] + t.corners[3]);
      for (Eigen::Vector2d& c : t.corners) {
        c += std::sqrt(0.5) * (c - centre).normalized() - Eigen::Vector2d(0.5, 0.5);
      }
    }
    if (options_.refine_corners || t.shrunk) {
      const int count = RefineQuad(grey, &t.corners, t.width_at_border, t.reversed_border,
                                   options_.refine_half_window_px);
      if (t.shrunk && count < 4) continue;
    }
    refined.push_back(t);
  }
  kept = std::move(refined);
  for (size_t k = 0; k < kept.size(); ++k) {
    const int index = kept[k].id - board_.layout().first_id;
    tag_at[{index % board_.layout().tags_across, index / board_.layout().tags_across}] =
        static_cast<int>(k);
  }

  // Consistency: each tag's corners against the homography of its neighbours' corners. A tag
  // decoded with the wrong id or with a shifted corner lands far from where they put it.
  std::vector<bool> consistent(kept.size(), true);
  for (const auto& [cell, k] : tag_at) {
    std::vector<cv::Point2f> board_points, image_points;
    for (int dj = -1; dj <= 1; ++dj) {
      for (int di = -1; di <= 1; ++di) {
        if (di == 0 && dj == 0) continue;
        auto it = tag_at.find({cell.first + di, cell.second + dj});
        if (it == tag_at.end()) continue;
        const TagSeen& n = kept[it->second];
        for (int c = 0; c < 4; ++c) {
          int i = 0, j = 0;
          board_.GridPointOf(n.id, c, &i, &j);
          board_points.emplace_back(static_cast<float>(i), static_cast<float>(j));
          image_points.emplace_back(static_cast<float>(n.corners[c].x()),
                                    static_cast<float>(n.corners[c].y()));
        }
      }
    }
    if (board_points.size() < 8) continue;  // too few neighbours to judge
    cv::Mat h = cv::findHomography(board_points, image_points, 0);
    if (h.empty()) continue;
    const TagSeen& t = kept[k];
    const double tolerance = std::max(options_.max_corner_residual_px, 0.25 * MinSide(t.corners));
    for (int c = 0; c < 4; ++c) {
      int i = 0, j = 0;
      board_.GridPointOf(t.id, c, &i, &j);
      const cv::Mat p = h * (cv::Mat_<double>(3, 1) << i, j, 1);
      const Eigen::Vector2d predicted(p.at<double>(0) / p.at<double>(2),
                                      p.at<double>(1) / p.at<double>(2));
      if ((predicted - t.corners[c]).norm() > tolerance) consistent[k] = false;
    }
  }

  int used = 0;
  int two_bit = 0;  // tags decoded with Kalibr's two-bit border
  for (size_t k = 0; k < kept.size(); ++k) {
    if (!consistent[k]) continue;
    ++used;
    two_bit += kept[k].border_bits == 2;
    for (int c = 0; c < 4; ++c) {
      int i = 0, j = 0;
      board_.GridPointOf(kept[k].id, c, &i, &j);
      observation->points.row(static_cast<Eigen::Index>(j) * width_n + i) << kept[k].corners[c].x(),
          kept[k].corners[c].y(), 1.0;
    }
  }
  if (used < options_.min_tags) {
    *reason = used == 0 && foreign > 0
                  ? Cat(foreign, " tags of ", board_.layout().family, " not on this board")
                  : Cat("partial board: ", used, " tags (needs ", options_.min_tags, ")");
    observation->points.col(2).setConstant(-1);
    return false;
  }
  observation->tag_border_bits = 2 * two_bit > used ? 2 : 1;
  return true;
}

namespace {

// ChArUco corners (OpenCV's ids) refined on the four square edges that leave each, as a
// chessboard's are, measured no further across an edge than the white margin between the
// square's side and the marker inside the white square beside it. The directions to the grid
// neighbours come from the homography of all the corners seen.
void RefineCharucoCorners(const cv::Mat& grey, const BoardLayout& layout,
                          const std::vector<int>& ids, std::vector<cv::Point2f>* corners) {
  if (ids.size() < 4) return;
  const int width_n = layout.width_n();
  std::vector<cv::Point2f> grid;
  grid.reserve(ids.size());
  for (int id : ids) {
    const int i = id % width_n;
    const int j = id / width_n;
    grid.emplace_back(static_cast<float>(i), static_cast<float>(j));
  }
  const cv::Mat h = cv::findHomography(grid, *corners, 0);
  if (h.empty()) return;
  auto at = [&](double i, double j) {
    const cv::Mat p = h * (cv::Mat_<double>(3, 1) << i, j, 1);
    return Eigen::Vector2d(p.at<double>(0) / p.at<double>(2), p.at<double>(1) / p.at<double>(2));
  };
  const double margin = 0.5 * (layout.spacing - layout.marker_side) / layout.spacing;
  for (size_t k = 0; k < ids.size(); ++k) {
    const double i = grid[k].x, j = grid[k].y;
    const Eigen::Vector2d u = at(i + 1, j) - at(i, j);
    const Eigen::Vector2d v = at(i, j + 1) - at(i, j);
    const double side = std::min(u.norm(), v.norm());
    const double reach = std::min(margin * side - 1.0, 4.0);
    if (reach < 1.0) continue;
    const double length = side - 1.5 * reach - 2;
    Eigen::Vector2d p((*corners)[k].x, (*corners)[k].y);
    if (calibration_internal::RefineEdgeCorner(grey, {u, v, -u, -v}, reach, reach, length, &p)) {
      (*corners)[k] = cv::Point2f(static_cast<float>(p.x()), static_cast<float>(p.y()));
    }
  }
}

}  // namespace

// ChArUco: the markers, then every chessboard corner between two of them that OpenCV's
// interpolateCornersCharuco finds (local homographies, then cornerSubPix). A partial view keeps
// the corners it has; the rows of the others stay at weight -1, as for AprilTag boards.
bool BoardDetector::DetectCharuco(const cv::Mat& grey, BoardObservation* observation,
                                  std::string* reason) const {
  const BoardLayout& layout = board_.layout();
  const cv::Ptr<cv::aruco::CharucoBoard>& charuco = impl_->charuco;
  const MarkersSeen seen = RunAruco(grey, *charuco);
  // Ids seen twice are ambiguous (a second board, a reflection): both are dropped.
  std::map<int, int> count;
  for (int id : seen.ids) ++count[id];
  const int markers = static_cast<int>(charuco->ids.size());
  MarkersSeen kept;
  int foreign = 0;
  for (size_t k = 0; k < seen.ids.size(); ++k) {
    const int id = seen.ids[k];
    if (id < layout.first_id || id >= layout.first_id + markers) {
      ++foreign;
      continue;
    }
    if (count[id] > 1) continue;
    kept.ids.push_back(id);
    kept.corners.push_back(seen.corners[k]);
  }
  const int used = static_cast<int>(kept.ids.size());
  if (used < options_.min_tags) {
    *reason = used == 0 && foreign > 0
                  ? Cat(foreign, " markers of ", layout.dictionary, " not on this board")
                  : Cat("partial board: ", used, " markers (needs ", options_.min_tags, ")");
    return false;
  }
  std::vector<cv::Point2f> corners;
  std::vector<int> ids;
  // A corner needs both markers beside it: one alone can place it on the wrong square.
  cv::aruco::interpolateCornersCharuco(kept.corners, kept.ids, grey, charuco, corners, ids,
                                       cv::noArray(), cv::noArray(), 2);
  // interpolateCornersCharuco leaves its corners where the markers' homographies put them, half
  // a pixel off (its own cornerSubPix stops at once); cornerSubPix again, each corner with the
  // widest window that stays clear of the markers beside it: nearer than its nearest marker
  // corner by a pixel, in both axes.
  const cv::TermCriteria criteria(cv::TermCriteria::EPS + cv::TermCriteria::COUNT, 40, 0.001);
  for (cv::Point2f& corner : corners) {
    double nearest = 1e300;
    for (const auto& marker : kept.corners) {
      for (const cv::Point2f& m : marker) nearest = std::min(nearest, cv::norm(m - corner));
    }
    const int half = std::clamp(static_cast<int>(nearest / std::sqrt(2.0) - 1), 2, 5);
    std::vector<cv::Point2f> one = {corner};
    cv::cornerSubPix(grey, one, cv::Size(half, half), cv::Size(-1, -1), criteria);
    corner = one[0];
  }
  const int width_n = board_.width_n();
  if (options_.refine_corners) RefineCharucoCorners(grey, layout, ids, &corners);
  for (size_t k = 0; k < ids.size(); ++k) {
    const int i = ids[k] % width_n;
    const int j = ids[k] / width_n;
    observation->points.row(static_cast<Eigen::Index>(j) * width_n + i) << corners[k].x,
        corners[k].y, 1.0;
  }
  if (ids.size() < 4) {
    *reason = Cat("partial board: ", ids.size(), " ChArUco corners");
    observation->points.col(2).setConstant(-1);
    return false;
  }
  return true;
}

nlohmann::json DetectionSummary::ToJson() const {
  nlohmann::json borders = nlohmann::json::object();
  for (const auto& [bits, views] : views_per_tag_border_bits) borders[std::to_string(bits)] = views;
  nlohmann::json rejected_json = nlohmann::json::array();
  for (const auto& r : rejected) {
    rejected_json.push_back(
        {{"sensor", r.sensor}, {"frame_set", r.frame_set}, {"reason", r.reason}});
  }
  return {{"frames", frames},
          {"views", views},
          {"rejected", rejected_json},
          {"seconds", seconds},
          {"frames_per_second", frames_per_second},
          {"views_per_sensor", views_per_sensor},
          {"views_per_tag_border_bits", borders},
          {"foreign_tag_ids", foreign_tag_ids}};
}

std::vector<BoardObservation> DetectBoardsInTake(const Take& take, const BoardLayout& layout,
                                                 const std::vector<std::string>& sensors_in,
                                                 const DetectionOptions& options,
                                                 DetectionSummary* summary) {
  options.Check();
  if (options.chessboard_finder == ChessboardFinder::kMrgingham)
    CheckMrginghamFits(layout, "--detector mrgingham");
  const std::vector<std::string> sensors = ChooseColorSensors(take, sensors_in);
  if (take.size() == 0) Fail("take ", take.dir().string(), " has no complete frame sets");

  const std::vector<calibration_internal::ViewJob> jobs =
      calibration_internal::ViewJobs(take, sensors);
  BoardDetector detector(layout, options);
  std::vector<std::optional<BoardObservation>> results(jobs.size());
  std::vector<std::string> reasons(jobs.size());
  std::vector<std::vector<int>> foreign_ids(jobs.size());
  Progress progress("detect", static_cast<int64_t>(jobs.size()));
  const auto start = std::chrono::steady_clock::now();
  calibration_internal::RunViewJobs(jobs.size(), options.threads, [&](size_t k) {
    const FrameSetEntry& entry = take.entry(jobs[k].set);
    const cv::Mat image = take.ReadFrame(jobs[k].set, jobs[k].sensor);
    BoardObservation observation;
    observation.sensor = jobs[k].sensor;
    observation.frame_set = entry.index;
    observation.timestamp_ns = entry.Find(jobs[k].sensor)->timestamp_ns;
    std::string reason;
    if (detector.Detect(image, &observation, &reason)) {
      results[k] = std::move(observation);
    } else {
      reasons[k] = reason;
      if (reason.find("not on this board") != std::string::npos) {
        foreign_ids[k] = detector.DetectTagIds(image);
      }
    }
    progress.Increment();
  });
  progress.Finish();

  DetectionSummary local;
  DetectionSummary& s = summary != nullptr ? *summary : local;
  s = DetectionSummary{};
  s.frames = static_cast<int64_t>(jobs.size());
  s.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  s.frames_per_second = s.seconds > 0 ? s.frames / s.seconds : 0;
  std::vector<BoardObservation> observations;
  std::set<int> foreign;
  for (size_t k = 0; k < jobs.size(); ++k) {
    if (results[k]) {
      ++s.views_per_sensor[jobs[k].sensor];
      if (results[k]->tag_border_bits > 0)
        ++s.views_per_tag_border_bits[results[k]->tag_border_bits];
      observations.push_back(std::move(*results[k]));
    } else {
      s.rejected.push_back({jobs[k].sensor, take.entry(jobs[k].set).index, reasons[k]});
      for (int id : foreign_ids[k]) foreign.insert(id);
    }
  }
  s.views = static_cast<int64_t>(observations.size());
  s.foreign_tag_ids.assign(foreign.begin(), foreign.end());
  for (const auto& name : sensors) s.views_per_sensor.emplace(name, 0);
  if (observations.empty()) {
    if (!foreign.empty()) {
      const bool charuco = layout.type == BoardType::kCharuco;
      const int markers = charuco ? layout.squares_across * layout.squares_down / 2
                                  : layout.tags_across * layout.tags_down;
      Fail("the board file does not match the prints: the take shows ",
           charuco ? layout.dictionary + " markers" : layout.family + " tags", " with ids ",
           *foreign.begin(), "..", *foreign.rbegin(), " but the board has ids ", layout.first_id,
           "..", layout.first_id + markers - 1);
    }
    Fail("no board visible in any of the ", s.frames, " frames of ", take.dir().string(), " (",
         ToString(layout.type), " ", layout.width_n(), "x", layout.height_n(), ")");
  }
  return observations;
}

void WriteCornersVnl(const std::vector<BoardObservation>& views,
                     const std::function<std::string(const BoardObservation&)>& image_name,
                     const std::filesystem::path& file) {
  std::string vnl = "# filename x y level\n";
  for (const auto& view : views) {
    const std::string name = image_name(view);
    for (Eigen::Index r = 0; r < view.points.rows(); ++r) {
      if (view.points(r, 2) > 0) {
        std::array<char, 64> xy{};
        std::snprintf(xy.data(), xy.size(), " %.6f %.6f 0\n", view.points(r, 0), view.points(r, 1));
        vnl += name + xy.data();
      } else {
        vnl += name + " - - -\n";
      }
    }
  }
  WriteFileAtomic(file, vnl);
}

}  // namespace holocap
