// holocap report REPORT.json|DIR...: what a run did and how its error fell with time, as text
// and as a plot a person can look at; several reports given at once share one plot (one line
// per run in each metric's panel), so that methods trained on one take compare at a glance.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <string>
#include <vector>

#include "app/commands.h"
#include "app/options.h"
#include "core/error.h"
#include "core/frame_tasks.h"
#include "core/fs.h"
#include "reconstruction/reconstruction.h"

namespace holocap {
namespace {

struct Point {
  double t_s = 0;
  int64_t iter = 0;
  double value = 0;
};
using Series = std::map<std::string, std::vector<Point>>;

// A run's series under the name its line carries on a shared plot.
struct Run {
  std::string label;
  Series series;
};

struct ReportArgs {
  std::vector<std::string> paths;
  std::string out;
  std::vector<std::string> metrics;
  int rows = 8;
  bool log_y = false;
  bool overwrite = false;
  bool merge = false;
};

nlohmann::json LoadReport(const std::filesystem::path& file) {
  return ParseReport(ReadFileToString(file), file.string());
}

Series SeriesOf(const nlohmann::json& report, const std::vector<std::string>& only) {
  Series series;
  if (!report.contains("series") || !report["series"].is_array()) return series;
  for (const auto& point : report["series"]) {
    if (!point.is_object() || !point.contains("metric") || !point.contains("value") ||
        !point["value"].is_number()) {
      continue;
    }
    const std::string metric = point["metric"].get<std::string>();
    if (!only.empty() && std::find(only.begin(), only.end(), metric) == only.end()) continue;
    series[metric].push_back(
        {point.value("t_s", 0.0), point.value("iter", int64_t{0}), point["value"].get<double>()});
  }
  return series;
}

// Nested metrics as dotted names, numbers and strings only; long arrays are summarised.
void FlattenMetrics(const nlohmann::json& json, const std::string& prefix,
                    std::vector<std::pair<std::string, std::string>>* out) {
  if (json.is_object()) {
    for (const auto& [key, value] : json.items()) {
      FlattenMetrics(value, prefix.empty() ? key : prefix + "." + key, out);
    }
  } else if (json.is_array()) {
    if (json.size() <= 4) {
      out->push_back({prefix, json.dump()});
    } else {
      out->push_back({prefix, "[" + std::to_string(json.size()) + " items]"});
    }
  } else if (json.is_number_float()) {
    char text[64];
    std::snprintf(text, sizeof(text), "%.6g", json.get<double>());
    out->push_back({prefix, text});
  } else {
    out->push_back({prefix, json.is_string() ? json.get<std::string>() : json.dump()});
  }
}

void PrintReport(const std::filesystem::path& file, const nlohmann::json& report,
                 const Series& series, int rows) {
  const auto& summary = report["summary"];
  // A report's text is printed through Printable: escape sequences in a file never reach the
  // terminal.
  std::printf("%s  (%s, %.1f s)\n", Printable(file.string()).c_str(),
              Printable(report["command"].get<std::string>()).c_str(),
              report.value("elapsed_s", 0.0));
  std::printf("  %s: %s\n", Printable(summary.value("termination", "?")).c_str(),
              Printable(summary.value("message", "")).c_str());
  if (report.contains("metrics")) {
    std::vector<std::pair<std::string, std::string>> metrics;
    FlattenMetrics(report["metrics"], "", &metrics);
    if (!metrics.empty()) std::printf("  metrics\n");
    for (const auto& [name, value] : metrics)
      std::printf("    %-40s %s\n", Printable(name).c_str(), Printable(value).c_str());
  }
  for (const auto& [metric, points] : series) {
    std::printf("  %s against time (%zu points)\n    %10s %10s %14s\n", Printable(metric).c_str(),
                points.size(), "t_s", "iter", "value");
    // Evenly spread rows, always the first and the last.
    const size_t shown = std::min<size_t>(points.size(), std::max(rows, 2));
    for (size_t k = 0; k < shown; ++k) {
      const size_t i = shown == 1 ? 0 : k * (points.size() - 1) / (shown - 1);
      std::printf("    %10.2f %10lld %14.6g\n", points[i].t_s,
                  static_cast<long long>(points[i].iter), points[i].value);
    }
  }
}

std::string Tick(double value) {
  char text[32];
  std::snprintf(text, sizeof(text), "%.3g", value);
  return text;
}

// The line colours of the runs on one plot (BGR), in turn.
const cv::Scalar kRunColors[] = {{180, 90, 20}, {30, 120, 230}, {60, 160, 40},
                                 {40, 40, 200}, {160, 60, 160}, {20, 20, 20}};

// One panel per metric: value against wall time, one line per run, log scale where asked or where
// the values span more than two decades (losses do).
cv::Mat PlotSeries(const std::string& title, const std::vector<Run>& runs, bool log_y) {
  constexpr int kPanelWidth = 720, kPanelHeight = 260, kLeft = 80, kRight = 20, kTop = 34,
                kBottom = 40;
  std::vector<std::string> metrics;
  for (const Run& run : runs) {
    for (const auto& [metric, points] : run.series)
      if (std::find(metrics.begin(), metrics.end(), metric) == metrics.end())
        metrics.push_back(metric);
  }
  std::sort(metrics.begin(), metrics.end());
  const int legend = runs.size() > 1 ? 18 * static_cast<int>(runs.size()) : 0;
  cv::Mat image(kPanelHeight * static_cast<int>(metrics.size()) + 30 + legend, kPanelWidth, CV_8UC3,
                cv::Scalar(255, 255, 255));
  cv::putText(image, title, {10, 20}, cv::FONT_HERSHEY_SIMPLEX, 0.55, {0, 0, 0}, 1, cv::LINE_AA);
  auto color = [&](size_t r) { return kRunColors[r % std::size(kRunColors)]; };
  for (size_t r = 0; r < runs.size() && runs.size() > 1; ++r) {
    const int y = 30 + 18 * static_cast<int>(r) + 9;
    cv::line(image, {12, y}, {40, y}, color(r), 2, cv::LINE_AA);
    cv::putText(image, runs[r].label, {48, y + 5}, cv::FONT_HERSHEY_SIMPLEX, 0.45, {0, 0, 0}, 1,
                cv::LINE_AA);
  }
  // One time axis for every panel and run, so that the series line up.
  double t_max = 0;
  for (const Run& run : runs) {
    for (const auto& [metric, points] : run.series)
      for (const auto& p : points) t_max = std::max(t_max, p.t_s);
  }
  if (t_max <= 0) t_max = 1;
  int panel = 0;
  for (const std::string& metric : metrics) {
    const int y0 = 30 + legend + panel++ * kPanelHeight;
    double v_min = INFINITY, v_max = -INFINITY;
    bool positive = true;
    for (const Run& run : runs) {
      if (!run.series.count(metric)) continue;
      for (const auto& p : run.series.at(metric)) {
        if (!std::isfinite(p.value)) continue;
        v_min = std::min(v_min, p.value);
        v_max = std::max(v_max, p.value);
        positive = positive && p.value > 0;
      }
    }
    const bool log_scale = positive && (log_y || (v_min > 0 && v_max / v_min > 100));
    auto to_axis = [&](double v) { return log_scale ? std::log10(v) : v; };
    double a_min = to_axis(v_min), a_max = to_axis(v_max);
    if (!std::isfinite(a_min)) a_min = 0, a_max = 1;
    if (a_max - a_min < 1e-12) a_min -= 0.5, a_max += 0.5;
    const cv::Rect box(kLeft, y0 + kTop, kPanelWidth - kLeft - kRight,
                       kPanelHeight - kTop - kBottom);
    cv::rectangle(image, box, {0, 0, 0}, 1);
    auto to_pixel = [&](const Point& p) {
      return cv::Point(box.x + static_cast<int>(std::lround(p.t_s / t_max * box.width)),
                       box.y + box.height -
                           static_cast<int>(std::lround((to_axis(p.value) - a_min) /
                                                        (a_max - a_min) * box.height)));
    };
    for (int k = 0; k <= 4; ++k) {
      const double a = a_min + (a_max - a_min) * k / 4;
      const int y = box.y + box.height - box.height * k / 4;
      cv::line(image, {box.x, y}, {box.x + box.width, y}, {225, 225, 225}, 1);
      cv::putText(image, Tick(log_scale ? std::pow(10, a) : a), {6, y + 4},
                  cv::FONT_HERSHEY_SIMPLEX, 0.4, {60, 60, 60}, 1, cv::LINE_AA);
      const int x = box.x + box.width * k / 4;
      cv::putText(image, Tick(t_max * k / 4), {x - 12, box.y + box.height + 16},
                  cv::FONT_HERSHEY_SIMPLEX, 0.4, {60, 60, 60}, 1, cv::LINE_AA);
    }
    cv::putText(image, metric + (log_scale ? "  (log scale)" : "") + "  against seconds",
                {box.x, y0 + 24}, cv::FONT_HERSHEY_SIMPLEX, 0.5, {0, 0, 0}, 1, cv::LINE_AA);
    for (size_t r = 0; r < runs.size(); ++r) {
      if (!runs[r].series.count(metric)) continue;
      const Point* previous = nullptr;
      for (const auto& p : runs[r].series.at(metric)) {
        if (!std::isfinite(p.value) || (log_scale && p.value <= 0)) continue;
        if (previous != nullptr)
          cv::line(image, to_pixel(*previous), to_pixel(p), color(r), 2, cv::LINE_AA);
        cv::circle(image, to_pixel(p), 2, color(r), cv::FILLED, cv::LINE_AA);
        previous = &p;
      }
    }
  }
  return image;
}

void WritePlot(const std::filesystem::path& png, const cv::Mat& plot) {
  std::vector<uchar> bytes;
  cv::imencode(".png", plot, bytes);
  WriteFileAtomic(png, std::string(bytes.begin(), bytes.end()));
  std::printf("  plot: %s\n", png.c_str());
}

// The metrics every run has (all of them when the runs share none).
bool Shared(const std::vector<Run>& runs, const std::string& metric) {
  for (const Run& run : runs)
    if (!run.series.count(metric)) return false;
  return true;
}

std::vector<std::filesystem::path> ReportsUnder(const std::filesystem::path& path) {
  if (!std::filesystem::exists(path)) Fail("'", path.string(), "' does not exist");
  if (!std::filesystem::is_directory(path)) return {path};
  std::vector<std::filesystem::path> files;
  for (const auto& entry : std::filesystem::recursive_directory_iterator(path)) {
    if (entry.is_regular_file() && entry.path().filename() == "report.json")
      files.push_back(entry.path());
  }
  if (files.empty()) Fail("no report.json under '", path.string(), "'");
  std::sort(files.begin(), files.end());
  return files;
}

// Merges a per-frame run's records into its report.json (beside the run's tasks, which may
// still be writing: the take's lock is shared with them). An incomplete run gets a FAILURE
// report naming its incomplete frame sets, and the command ends with that state.
}  // namespace

std::map<std::string, RunMerger>& RunMergers() {
  static std::map<std::string, RunMerger> mergers;
  return mergers;
}

namespace {

void MergeRun(const std::filesystem::path& out) {
  const RunState run = ReadRunState(out);
  if (run.command != "reconstruct" && run.command != "train splat" && run.command != "export web")
    Fail("'", out.string(), "' holds a run of ", run.command, ", which has no merge");
  // A run whose command this program does not link (export web bakes volumes) is merged by
  // holocap-neural, before anything here is claimed.
  if (run.command != "reconstruct" && RunMergers().count(run.command) == 0)
    HandOverToLibTorchProgram("holocap report --merge of a " + run.command + " run");
  const OutputDirectory claimed = OutputDirectory::Claim(out, {run.command, false, {}, true});
  Report report(run.command);
  if (run.command == "reconstruct") {
    FailUnlessUsable(MergeReconstruction(out, &report), "the merged run");
  } else {
    FailUnlessUsable(RunMergers().at(run.command)(out, &report), "the merged run");
  }
  std::printf("merged %zu frame record(s) into %s\n", run.complete.size(),
              (out / "report.json").c_str());
}

void AddReportCommand(CLI::App& app) {
  auto* command = app.add_subcommand("report",
                                     "Show a run's report.json (or every one under a directory): "
                                     "outcome, metrics, error against time");
  auto args = std::make_shared<ReportArgs>();
  command
      ->add_option("PATH", args->paths,
                   "A report.json, or a directory searched for them; several: one plot of all "
                   "(a line per run, the series they share)")
      ->required();
  command->add_option(
      "--out", args->out,
      "Plot the error-against-time series to this PNG (with one directory: one PNG per report, "
      "into this directory)");
  command
      ->add_option("--metric", args->metrics, "Only these series, comma-separated (default: all)")
      ->delimiter(',');
  command->add_option("--rows", args->rows, "Rows shown per series")
      ->capture_default_str()
      ->check(CLI::Range(2, 1000));
  command->add_flag("--log", args->log_y, "Log scale for every positive series");
  AddOverwriteFlag(command, &args->overwrite);
  command->add_flag("--merge", args->merge,
                    "PATH is the output of a per-frame run (reconstruct, train splat "
                    "--segment-frames, export web, with or without --shard): merge its frames' "
                    "reports into its report.json (a splat run's model.json, a site's "
                    "manifest.json) first");
  command->callback([args] {
    if (args->merge) {
      for (const std::string& path : args->paths) MergeRun(path);
    }
    std::vector<std::filesystem::path> files;
    for (const std::string& path : args->paths) {
      const auto under = ReportsUnder(path);
      files.insert(files.end(), under.begin(), under.end());
    }
    const bool together = args->paths.size() > 1;
    const bool many =
        !together && (files.size() > 1 || std::filesystem::is_directory(args->paths.front()));
    const OutputRequest request{"report", args->overwrite, {}};
    std::optional<OutputDirectory> claimed;
    TakeLock file_lock;
    if (many && !args->out.empty()) claimed = OutputDirectory::Claim(args->out, request);
    if (!many && !args->out.empty()) file_lock = ClaimOutputFile(args->out, request);
    std::vector<Run> runs;
    for (const auto& file : files) {
      const nlohmann::json report = LoadReport(file);
      Series series;
      try {
        series = SeriesOf(report, args->metrics);
        PrintReport(file, report, series, args->rows);
      } catch (const nlohmann::json::exception& e) {
        std::fflush(stdout);
        Fail("'", file.string(), "' holds a field of the wrong type: ", e.what());
      }
      runs.push_back(
          {Cat(report["command"].get<std::string>(), " (", file.parent_path().string(), ")"),
           series});
      if (together || args->out.empty() || series.empty()) continue;
      std::filesystem::path png = args->out;
      if (many) {
        std::string name =
            std::filesystem::relative(file.parent_path(), args->paths.front()).string();
        std::replace(name.begin(), name.end(), '/', '-');
        png = std::filesystem::path(args->out) /
              ((name == "." ? std::string("report") : name) + ".png");
      }
      WritePlot(png, PlotSeries(file.string(), {runs.back()}, args->log_y));
    }
    if (!together || args->out.empty()) return;
    // Without --metric, the series every run has: the curves that compare.
    std::vector<Run> shared = runs;
    bool any = false;
    for (const auto& [metric, points] : runs.front().series) any = any || Shared(runs, metric);
    for (Run& run : shared) {
      for (auto it = run.series.begin(); any && it != run.series.end();)
        it = Shared(runs, it->first) ? std::next(it) : run.series.erase(it);
    }
    WritePlot(args->out, PlotSeries(Cat(runs.size(), " runs"), shared, args->log_y));
  });
}

}  // namespace

HOLOCAP_COMMAND(110, AddReportCommand);

}  // namespace holocap
