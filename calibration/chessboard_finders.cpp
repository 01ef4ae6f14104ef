// mrgingham as a chessboard finder, and the agreement of the chessboard finders.
#include "calibration/chessboard_finders.h"

#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <map>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <sstream>

#include "calibration/calibration.h"
#include "calibration/internal/common.h"
#include "core/camera.h"
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

void CheckMrginghamFits(const BoardLayout& layout) {
  if (layout.type != BoardType::kChessboard) {
    Fail("--detector mrgingham finds chessboards only; this board is ", ToString(layout.type));
  }
  if (layout.chessboard_width_n != layout.chessboard_height_n) {
    Fail("--detector mrgingham finds square grids only (N x N inner corners); this chessboard has ",
         layout.chessboard_width_n, " x ", layout.chessboard_height_n);
  }
  if (!OnPath("mrgingham")) {
    Fail("--detector mrgingham: the mrgingham program is not on PATH (Debian package mrgingham)");
  }
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

// The per-corner distances between `a` and `b`, `b` renumbered by the turn of the grid (any
// that keeps its shape) that brings it closest to `a`: finders may start from any end.
std::vector<double> MatchedDistances(const Corners& a, const Corners& b, int width_n,
                                     int height_n) {
  std::vector<double> best;
  double best_sum = INFINITY;
  for (int turn = 0; turn < 4; ++turn) {
    if (turn % 2 == 1 && width_n != height_n) continue;
    const std::vector<int> order = calibration_internal::TurnedGridOrder(width_n, height_n, turn);
    std::vector<double> d(a.size());
    double sum = 0;
    for (size_t r = 0; r < a.size(); ++r) {
      d[r] = (a[r] - b[order[r]]).norm();
      sum += d[r];
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

nlohmann::json CompareChessboardFinders(const std::filesystem::path& take_dir,
                                        const BoardLayout& layout,
                                        const std::vector<std::string>& sensors_in, int threads,
                                        std::string* table) {
  CheckMrginghamFits(layout);
  const Take take = Take::Open(take_dir);
  const std::vector<std::string> sensors = ChooseColorSensors(take, sensors_in);
  const Board board(layout);
  const int width_n = board.width_n(), height_n = board.height_n();
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
  std::vector<std::array<std::optional<Corners>, kFinders>> found(jobs.size());
  std::vector<std::optional<Corners>> truth(jobs.size());
  calibration_internal::RunViewJobs(jobs.size(), threads, [&](size_t k) {
    const cv::Mat image = take.ReadFrame(jobs[k].set, jobs[k].sensor);
    cv::Mat grey = image;
    if (image.channels() == 3) cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
    if (grey.depth() == CV_16U) grey.convertTo(grey, CV_8U, 1.0 / 257.0);
    BoardObservation observation;
    std::string reason;
    if (holocap.Detect(image, &observation, &reason)) {
      Corners c;
      for (Eigen::Index r = 0; r < observation.points.rows(); ++r)
        c.emplace_back(observation.points(r, 0), observation.points(r, 1));
      found[k][0] = c;
    }
    found[k][1] = FindOpenCv(grey, width_n, height_n);
    std::vector<cv::Point2f> points;
    if (FindChessboardMrgingham(grey, width_n, &points, &reason)) found[k][2] = ToCorners(points);
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

  std::array<int, kFinders> views_found{};
  std::map<std::pair<int, int>, Tally> pairs;
  std::array<Tally, kFinders> to_truth;
  for (size_t k = 0; k < jobs.size(); ++k) {
    for (int a = 0; a < kFinders; ++a) {
      if (!found[k][a]) continue;
      ++views_found[a];
      for (int b = a + 1; b < kFinders; ++b) {
        if (!found[k][b]) continue;
        Tally& t = pairs[{a, b}];
        ++t.views;
        const auto d = MatchedDistances(*found[k][a], *found[k][b], width_n, height_n);
        t.distances.insert(t.distances.end(), d.begin(), d.end());
      }
      if (truth[k]) {
        Tally& t = to_truth[a];
        ++t.views;
        for (double d : MatchedDistances(*truth[k], *found[k][a], width_n, height_n)) {
          if (std::isfinite(d)) t.distances.push_back(d);
        }
      }
    }
  }

  nlohmann::json result = {
      {"views", jobs.size()},
      {"opencv_recipe",
       "findChessboardCorners (ADAPTIVE_THRESH | NORMALIZE_IMAGE | FAST_CHECK), cornerSubPix "
       "winSize 11 x 11 (half sizes) or half the view's smallest corner spacing where smaller, "
       "30 iterations / 0.001"},
      {"matching", "per view, the second finder's corners renumbered by the grid turn closest"},
      {"pairs", nlohmann::json::array()},
      {"truth", nlohmann::json::array()}};
  std::ostringstream out;
  char line[160];
  std::snprintf(line, sizeof(line), "%-22s %6s %8s %9s %9s %9s\n", "detectors", "views", "corners",
                "mean_px", "p95_px", "max_px");
  out << line;
  auto row = [&](const std::string& name, const nlohmann::json& j) {
    std::snprintf(line, sizeof(line), "%-22s %6d %8d %9.4f %9.4f %9.4f\n", name.c_str(),
                  j["views"].get<int>(), j["corners"].get<int>(), j["mean_px"].get<double>(),
                  j["p95_px"].get<double>(), j["max_px"].get<double>());
    out << line;
  };
  for (int a = 0; a < kFinders; ++a) {
    result["found"][kFinderNames[a]] = views_found[a];
    for (int b = a + 1; b < kFinders; ++b) {
      nlohmann::json j = pairs[{a, b}].ToJson();
      j["a"] = kFinderNames[a];
      j["b"] = kFinderNames[b];
      row(Cat(kFinderNames[a], " - ", kFinderNames[b]), j);
      result["pairs"].push_back(j);
    }
  }
  if (!truth_cameras.empty()) {
    for (int a = 0; a < kFinders; ++a) {
      nlohmann::json j = to_truth[a].ToJson();
      j["detector"] = kFinderNames[a];
      row(Cat(kFinderNames[a], " - truth"), j);
      result["truth"].push_back(j);
    }
  }
  *table = out.str();
  return result;
}

}  // namespace holocap
