// mrgingham as a chessboard finder, and the agreement of the chessboard finders.
#include "calibration/chessboard_finders.h"

#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <map>
#include <opencv2/aruco/charuco.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <sstream>

#include "calibration/calibration.h"
#include "calibration/internal/common.h"
#include "core/camera.h"
#include "core/charuco.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/pose.h"
#include "core/take.h"
#include "core/take_plan.h"

namespace holocap {
namespace {

std::atomic<int64_t> temp_counter{0};

bool OnPath(const std::string& program) {
  const char* path = std::getenv("PATH");
  std::stringstream dirs(path != nullptr ? path : "");
  for (std::string dir; std::getline(dirs, dir, ':');) {
    if (!dir.empty() && ::access((std::filesystem::path(dir) / program).c_str(), X_OK) == 0)
      return true;
  }
  return false;
}

}  // namespace

ChessboardFinder ParseChessboardFinder(const std::string& name) {
  if (name == "holocap") return ChessboardFinder::kHolocap;
  if (name == "mrgingham") return ChessboardFinder::kMrgingham;
  Fail("unknown chessboard detector '", name, "' (holocap or mrgingham)");
}

const char* ToString(ChessboardFinder finder) {
  return finder == ChessboardFinder::kMrgingham ? "mrgingham" : "holocap";
}

std::string WhyMrginghamCannotRun(const BoardLayout& layout) {
  if (layout.type != BoardType::kChessboard) {
    return Cat("mrgingham finds chessboards only; this board is ", ToString(layout.type));
  }
  if (layout.chessboard_width_n != layout.chessboard_height_n) {
    return Cat("mrgingham finds square grids only (N x N inner corners); this chessboard has ",
               layout.chessboard_width_n, " x ", layout.chessboard_height_n);
  }
  if (!OnPath("mrgingham")) {
    return "the mrgingham program is not on PATH (Debian package mrgingham)";
  }
  return "";
}

void CheckMrginghamFits(const BoardLayout& layout, const std::string& flag) {
  if (const std::string why = WhyMrginghamCannotRun(layout); !why.empty()) Fail(flag, ": ", why);
}

bool FindChessboardMrgingham(const cv::Mat& grey, int gridn, std::vector<cv::Point2f>* corners,
                             std::string* reason) {
  const std::filesystem::path file =
      std::filesystem::temp_directory_path() /
      Cat("holocap-mrgingham-", ::getpid(), "-", temp_counter++, ".png");
  if (!cv::imwrite(file.string(), grey)) Fail("cannot write ", file.string());
  std::string output;
  FILE* pipe = popen(Cat("mrgingham --gridn ", gridn, " '", file.string(), "' 2>&1").c_str(), "r");
  if (pipe != nullptr) {
    char buffer[512];
    while (std::fgets(buffer, sizeof(buffer), pipe) != nullptr) output += buffer;
  }
  const int status = pipe != nullptr ? pclose(pipe) : -1;
  std::error_code ec;
  std::filesystem::remove(file, ec);
  if (status != 0) {
    Fail("mrgingham failed (status ", status, "): ", Printable(output.substr(0, 200)));
  }
  corners->clear();
  std::istringstream lines(output);
  for (std::string line; std::getline(lines, line);) {
    if (line.empty() || line[0] == '#') continue;
    std::istringstream fields(line);
    std::string name, x, y;
    fields >> name >> x >> y;
    if (x == "-") break;
    corners->emplace_back(std::stof(x), std::stof(y));
  }
  if (corners->empty()) {
    *reason = "no chessboard found (mrgingham)";
    return false;
  }
  if (corners->size() != static_cast<size_t>(gridn) * gridn) {
    *reason = Cat("mrgingham gave ", corners->size(), " corners, not ", gridn, " x ", gridn);
    return false;
  }
  return true;
}

namespace {

constexpr int kFinders = 3;
constexpr std::array<const char*, kFinders> kFinderNames = {"holocap", "opencv", "mrgingham"};

using Corners = std::vector<Eigen::Vector2d>;  // row-major, width_n per row

std::optional<Corners> ToCorners(const std::vector<cv::Point2f>& points) {
  Corners c;
  for (const auto& p : points) c.emplace_back(p.x, p.y);
  return c;
}

// The corners a BoardObservation holds, NaN where it saw none.
Corners ToCorners(const BoardObservation& observation) {
  Corners c;
  for (Eigen::Index r = 0; r < observation.points.rows(); ++r) {
    c.push_back(observation.points(r, 2) > 0
                    ? Eigen::Vector2d(observation.points(r, 0), observation.points(r, 1))
                    : Eigen::Vector2d::Constant(NAN));
  }
  return c;
}

// OpenCV's own ChArUco detector as its documentation uses it: detectMarkers, then
// interpolateCornersCharuco (local homographies, then its cornerSubPix), corner id k being grid
// point k. Nothing when it finds fewer than 4 corners.
std::optional<Corners> FindOpenCvCharuco(const cv::Mat& grey,
                                         const cv::Ptr<cv::aruco::CharucoBoard>& board,
                                         size_t grid_points) {
  std::vector<std::vector<cv::Point2f>> markers;
  std::vector<int> marker_ids;
  cv::aruco::detectMarkers(grey, board->dictionary, markers, marker_ids);
  if (marker_ids.empty()) return std::nullopt;
  std::vector<cv::Point2f> points;
  std::vector<int> ids;
  cv::aruco::interpolateCornersCharuco(markers, marker_ids, grey, board, points, ids);
  if (ids.size() < 4) return std::nullopt;
  Corners c(grid_points, Eigen::Vector2d::Constant(NAN));
  for (size_t k = 0; k < ids.size(); ++k) {
    if (ids[k] >= 0 && static_cast<size_t>(ids[k]) < grid_points)
      c[ids[k]] = Eigen::Vector2d(points[k].x, points[k].y);
  }
  return c;
}

// OpenCV's common recipe: findChessboardCorners, then cornerSubPix with winSize 11 x 11 (half
// sizes), shrunk to half the view's smallest corner spacing: a window reaching past the
// neighbouring corners pulls every corner towards them (5.9 px at the 95th percentile on
// 15 px squares).
std::optional<Corners> FindOpenCv(const cv::Mat& grey, int width_n, int height_n) {
  std::vector<cv::Point2f> points;
  if (!cv::findChessboardCorners(
          grey, cv::Size(width_n, height_n), points,
          cv::CALIB_CB_ADAPTIVE_THRESH | cv::CALIB_CB_NORMALIZE_IMAGE | cv::CALIB_CB_FAST_CHECK)) {
    return std::nullopt;
  }
  double spacing = INFINITY;
  for (int j = 0; j < height_n; ++j) {
    for (int i = 0; i < width_n; ++i) {
      const cv::Point2f& p = points[static_cast<size_t>(j) * width_n + i];
      if (i + 1 < width_n) spacing = std::min(spacing, cv::norm(points[j * width_n + i + 1] - p));
      if (j + 1 < height_n)
        spacing = std::min(spacing, cv::norm(points[(j + 1) * width_n + i] - p));
    }
  }
  const int half = std::clamp(static_cast<int>(0.5 * spacing), 2, 11);
  cv::cornerSubPix(grey, points, cv::Size(half, half), cv::Size(-1, -1),
                   cv::TermCriteria(cv::TermCriteria::EPS + cv::TermCriteria::COUNT, 30, 0.001));
  return ToCorners(points);
}

// The per-corner distances between `a` and `b` over the corners both found, `b` renumbered by
// the turn of the grid among `turns` (quarter turns) that brings it closest to `a`: chessboard
// finders may start from any end, ChArUco corners are numbered by their ids (turn 0 only).
std::vector<double> MatchedDistances(const Corners& a, const Corners& b, int width_n, int height_n,
                                     const std::vector<int>& turns) {
  std::vector<double> best;
  double best_sum = INFINITY;
  for (int turn : turns) {
    if (turn % 2 == 1 && width_n != height_n) continue;
    const std::vector<int> order = calibration_internal::TurnedGridOrder(width_n, height_n, turn);
    std::vector<double> d;
    double sum = 0;
    for (size_t r = 0; r < a.size(); ++r) {
      const double distance = (a[r] - b[order[r]]).norm();
      if (!std::isfinite(distance)) continue;
      d.push_back(distance);
      sum += distance;
    }
    if (sum < best_sum) {
      best_sum = sum;
      best = std::move(d);
    }
  }
  return best;
}

struct Tally {
  int views = 0;
  std::vector<double> distances;
  nlohmann::json ToJson() const {
    std::vector<double> sorted = distances;
    std::sort(sorted.begin(), sorted.end());
    double mean = 0;
    for (double d : sorted) mean += d;
    const bool any = !sorted.empty();
    const size_t p95 =
        any ? std::min(sorted.size() - 1, static_cast<size_t>(0.95 * sorted.size())) : 0;
    return {{"views", views},
            {"corners", sorted.size()},
            {"mean_px", any ? mean / static_cast<double>(sorted.size()) : 0.0},
            {"p95_px", any ? sorted[p95] : 0.0},
            {"max_px", any ? sorted.back() : 0.0}};
  }
};

std::map<int64_t, Pose> BoardPosesOf(const Take& take) {
  std::map<int64_t, Pose> poses;
  const std::filesystem::path file = take.gt_dir() / "board.json";
  if (!std::filesystem::exists(file)) return poses;
  const nlohmann::json json = nlohmann::json::parse(ReadFileToString(file), nullptr, false);
  if (json.is_discarded() || !json.contains("world_from_board")) return poses;
  for (const auto& entry : json["world_from_board"]) {
    const auto rt = entry.at("rt").get<std::vector<double>>();
    if (rt.size() == 6) {
      poses[entry.at("set").get<int64_t>()] =
          PoseFromRt({rt[0], rt[1], rt[2], rt[3], rt[4], rt[5]});
    }
  }
  return poses;
}

}  // namespace

void CheckDetectorsComparable(const BoardLayout& layout) {
  if (layout.type != BoardType::kChessboard && layout.type != BoardType::kCharuco) {
    Fail("--compare-detectors compares chessboard and ChArUco detectors; this board is ",
         ToString(layout.type), " (", layout.family, "), which libapriltag alone reads");
  }
}

nlohmann::json CompareBoardDetectors(const std::filesystem::path& take_dir,
                                     const BoardLayout& layout,
                                     const std::vector<std::string>& sensors_in, int threads,
                                     std::string* table) {
  CheckDetectorsComparable(layout);
  const bool charuco = layout.type == BoardType::kCharuco;
  std::vector<std::string> names = {"holocap", "opencv"};
  nlohmann::json left_out = nlohmann::json::object();
  if (const std::string why = WhyMrginghamCannotRun(layout); why.empty()) {
    names.emplace_back("mrgingham");
  } else {
    left_out["mrgingham"] = why;
  }
  const size_t finders = names.size();
  const Take take = Take::Open(take_dir);
  const std::vector<std::string> sensors = ChooseColorSensors(take, sensors_in);
  const Board board(layout);
  const int width_n = board.width_n(), height_n = board.height_n();
  const size_t grid_points = static_cast<size_t>(width_n) * height_n;
  // Chessboard finders may number from any end; ChArUco corners carry their ids.
  const std::vector<int> turns = charuco ? std::vector<int>{0} : std::vector<int>{0, 1, 2, 3};
  const cv::Ptr<cv::aruco::CharucoBoard> charuco_board =
      charuco ? MakeCharucoBoard(layout) : nullptr;
  const std::map<int64_t, Pose> poses = BoardPosesOf(take);
  std::map<std::string, CameraModel> truth_cameras;
  if (!poses.empty()) {
    for (const auto& s : sensors) {
      const auto file = take.gt_dir() / "cameras" / (s + ".cameramodel");
      if (std::filesystem::exists(file)) truth_cameras.emplace(s, CameraModel::Read(file));
    }
  }

  const std::vector<calibration_internal::ViewJob> jobs =
      calibration_internal::ViewJobs(take, sensors);
  DetectionOptions holocap_options;
  holocap_options.chessboard_finder = ChessboardFinder::kHolocap;
  BoardDetector holocap(layout, holocap_options);
  std::vector<std::vector<std::optional<Corners>>> found(
      jobs.size(), std::vector<std::optional<Corners>>(finders));
  std::vector<std::optional<Corners>> truth(jobs.size());
  calibration_internal::RunViewJobs(jobs.size(), threads, [&](size_t k) {
    const cv::Mat image = take.ReadFrame(jobs[k].set, jobs[k].sensor);
    cv::Mat grey = image;
    if (image.channels() == 3) cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
    if (grey.depth() == CV_16U) grey.convertTo(grey, CV_8U, 1.0 / 257.0);
    BoardObservation observation;
    std::string reason;
    if (holocap.Detect(image, &observation, &reason)) found[k][0] = ToCorners(observation);
    found[k][1] = charuco ? FindOpenCvCharuco(grey, charuco_board, grid_points)
                          : FindOpenCv(grey, width_n, height_n);
    if (finders > 2) {
      std::vector<cv::Point2f> points;
      if (FindChessboardMrgingham(grey, width_n, &points, &reason)) found[k][2] = ToCorners(points);
    }
    const auto camera = truth_cameras.find(jobs[k].sensor);
    const auto pose = poses.find(take.entry(jobs[k].set).index);
    if (camera != truth_cameras.end() && pose != poses.end()) {
      Corners c;
      for (const auto& p : board.GridPoints()) {
        Eigen::Vector2d pixel;
        if (!camera->second.ProjectWorld(pose->second * p, &pixel)) pixel.setConstant(NAN);
        c.push_back(pixel);
      }
      truth[k] = c;
    }
  });

  std::vector<int> views_found(finders, 0);
  std::map<std::pair<size_t, size_t>, Tally> pairs;
  std::vector<Tally> to_truth(finders);
  for (size_t k = 0; k < jobs.size(); ++k) {
    for (size_t a = 0; a < finders; ++a) {
      if (!found[k][a]) continue;
      ++views_found[a];
      for (size_t b = a + 1; b < finders; ++b) {
        if (!found[k][b]) continue;
        Tally& t = pairs[{a, b}];
        ++t.views;
        const auto d = MatchedDistances(*found[k][a], *found[k][b], width_n, height_n, turns);
        t.distances.insert(t.distances.end(), d.begin(), d.end());
      }
      if (truth[k]) {
        Tally& t = to_truth[a];
        ++t.views;
        const auto d = MatchedDistances(*truth[k], *found[k][a], width_n, height_n, turns);
        t.distances.insert(t.distances.end(), d.begin(), d.end());
      }
    }
  }

  nlohmann::json result = {
      {"board", ToString(layout.type)},
      {"views", jobs.size()},
      {"detectors", names},
      {"left_out", left_out},
      {"opencv_recipe",
       charuco ? "detectMarkers, then interpolateCornersCharuco (its own cornerSubPix)"
               : "findChessboardCorners (ADAPTIVE_THRESH | NORMALIZE_IMAGE | FAST_CHECK), "
                 "cornerSubPix winSize 11 x 11 (half sizes) or half the view's smallest corner "
                 "spacing where smaller, 30 iterations / 0.001"},
      {"matching", charuco ? "per view, the corners both found, by their ChArUco ids"
                           : "per view, the second finder's corners renumbered by the grid "
                             "turn closest"},
      {"pairs", nlohmann::json::array()},
      {"truth", nlohmann::json::array()}};
  std::ostringstream out;
  std::array<char, 160> line{};
  std::snprintf(line.data(), line.size(), "%-22s %6s %8s %9s %9s %9s\n", "detectors", "views",
                "corners", "mean_px", "p95_px", "max_px");
  out << line.data();
  auto row = [&](const std::string& name, const nlohmann::json& j) {
    std::snprintf(line.data(), line.size(), "%-22s %6d %8d %9.4f %9.4f %9.4f\n", name.c_str(),
                  j["views"].get<int>(), j["corners"].get<int>(), j["mean_px"].get<double>(),
                  j["p95_px"].get<double>(), j["max_px"].get<double>());
    out << line.data();
  };
  for (size_t a = 0; a < finders; ++a) {
    result["found"][names[a]] = views_found[a];
    for (size_t b = a + 1; b < finders; ++b) {
      nlohmann::json j = pairs[{a, b}].ToJson();
      j["a"] = names[a];
      j["b"] = names[b];
      row(Cat(names[a], " - ", names[b]), j);
      result["pairs"].push_back(j);
    }
  }
  if (!truth_cameras.empty()) {
    for (size_t a = 0; a < finders; ++a) {
      nlohmann::json j = to_truth[a].ToJson();
      j["detector"] = names[a];
      row(Cat(names[a], " - truth"), j);
      result["truth"].push_back(j);
    }
  }
  for (const auto& [name, why] : left_out.items()) {
    out << name << " left out: " << why.get<std::string>() << "\n";
  }
  *table = out.str();
  return result;
}

}  // namespace holocap
