// Live from sensors: a recording's frame sets composed as they arrive (see LiveStream).
#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <mutex>
#include <optional>
#include <thread>

#include "core/error.h"
#include "core/fs.h"
#include "core/output.h"
#include "live/internal/live.h"
#include "live/live.h"

namespace holocap {

namespace fs = std::filesystem;
using Json = nlohmann::json;
using Clock = std::chrono::steady_clock;

struct LiveStream::State {
  // Fixed at construction.
  fs::path scan_dir, out;
  bool overwrite = false;
  LiveOptions options;
  std::string depth_sensor, color_sensor;
  CameraModel depth_camera, color_camera;
  Mesh scan;
  std::optional<ScanAlbedo> albedo;  // the scan's light and albedo (nullopt: not relit)
  std::string unlit;                 // ... or why not
  bool relit = false;                // for the report, once albedo has gone to the compositor
  Eigen::Vector3d scan_light = Eigen::Vector3d::Zero();
  Clock::time_point start = Clock::now();

  // Shared between Offer() and the thread.
  struct Pending {
    int64_t set = 0;
    cv::Mat depth, color;
    Clock::time_point arrived;
  };
  mutable std::mutex mutex;
  std::condition_variable wake;
  std::optional<Pending> pending;
  bool finishing = false;
  LiveStreamStatus status;
  std::vector<LiveFrame> frames;
  std::vector<double> latencies_s;
  std::string failure;  // set: the output failed, nothing more is composed

  // The thread's own.
  std::optional<OutputDirectory> claimed;
  std::unique_ptr<Report> report;
  std::optional<LiveCompositor> compositor;
  std::string up_source;
  std::thread thread;

  void Run();
  LiveFrame Compose(const Pending& job);
  void Start(const cv::Mat& first_depth);
};

// The output claimed and the compositor made with the floor of the first depth frame.
void LiveStream::State::Start(const cv::Mat& first_depth) {
  claimed.emplace(OutputDirectory::Claim(out, {"live", overwrite, {scan_dir}}));
  CreateDirectories(out / "recon");
  report = std::make_unique<Report>("live");
  report->SetFailureDestination(out / "report.json");
  Eigen::Vector3d up = UpFromCameras({depth_camera, color_camera}, &up_source);
  Eigen::Vector3d normal;
  double offset = 0, tolerance = 0, floor_m = std::numeric_limits<double>::quiet_NaN();
  std::string why;
  if (FloorFromDepth({{depth_camera, first_depth}}, up, &normal, &offset, &tolerance, &why)) {
    why = "floor plane (" + why + ")";
    up = SnapToAxis(normal, 5, &why);
    up_source = why;
    if ((up.array() != 0).count() == 1) floor_m = up.dot(normal) * offset - tolerance;
  } else {
    up_source += "; no floor in the first depth frame: " + why;
  }
  report->options() = options.ToJson();
  report->options()["scan"] = scan_dir.string();
  report->plan() = {{"source", "sensors (holocap capture --live)"},
                    {"depth_sensor", depth_sensor},
                    {"color_sensor", color_sensor},
                    {"up", {up.x(), up.y(), up.z()}},
                    {"up_source", up_source},
                    {"floor_m", std::isfinite(floor_m) ? Json(floor_m) : Json(nullptr)}};
  compositor.emplace(std::move(scan), options, up, floor_m + tolerance, std::move(albedo));
}

LiveFrame LiveStream::State::Compose(const Pending& job) {
  if (!compositor) Start(job.depth);
  LiveFrame frame;
  frame.set = job.set;
  if (job.depth.empty()) {
    frame.state = LiveState::kNoDepth;
    frame.why = "no depth frame in this set";
    return frame;
  }
  LiveResult result =
      compositor->Process(job.set, job.depth, depth_camera, job.color, color_camera);
  if (result.frame.state == LiveState::kComposed)
    live::WriteComposed(out / "recon", job.set, result.composed, options.write_glb);
  live::RecordFrame(report.get(), result.frame);
  return result.frame;
}

void LiveStream::State::Run() {
  while (true) {
    Pending job;
    {
      std::unique_lock lock(mutex);
      wake.wait(lock, [&] { return pending.has_value() || finishing; });
      if (!pending) return;
      job = std::move(*pending);
      pending.reset();
    }
    LiveFrame frame;
    std::string error;
    try {
      frame = Compose(job);
    } catch (const std::exception& e) {
      error = Cat("set ", job.set, ": ", e.what());
    }
    const double latency_s = std::chrono::duration<double>(Clock::now() - job.arrived).count();
    std::lock_guard lock(mutex);
    if (!error.empty()) {
      failure = error;
      continue;
    }
    frames.push_back(frame);
    if (frame.state == LiveState::kComposed) {
      ++status.composed;
      latencies_s.push_back(latency_s);
      status.last_latency_s = latency_s;
    }
    if (frame.state == LiveState::kRefused) ++status.refused;
    if (frame.state == LiveState::kNoDepth) ++status.no_depth;
  }
}

LiveStream::LiveStream(const fs::path& scan_dir, std::string depth_sensor, CameraModel depth_camera,
                       std::string color_sensor, CameraModel color_camera, fs::path out,
                       bool overwrite, const LiveOptions& options)
    : state_(std::make_unique<State>()) {
  options.Check();
  State& s = *state_;
  s.scan = ReadScan(scan_dir);
  if (options.relight)
    s.albedo = ReadScanAlbedo(scan_dir, s.scan, &s.unlit);
  else
    s.unlit = "relight is off";
  s.relit = s.albedo.has_value();
  if (s.albedo) s.scan_light = s.albedo->light.light;
  s.scan_dir = scan_dir;
  s.out = std::move(out);
  s.overwrite = overwrite;
  s.options = options;
  s.depth_sensor = std::move(depth_sensor);
  s.color_sensor = std::move(color_sensor);
  s.depth_camera = std::move(depth_camera);
  s.color_camera = std::move(color_camera);
  s.thread = std::thread([&s] { s.Run(); });
}

LiveStream::~LiveStream() {
  if (!state_->thread.joinable()) return;
  {
    std::lock_guard lock(state_->mutex);
    state_->finishing = true;
    state_->pending.reset();
  }
  state_->wake.notify_all();
  state_->thread.join();
}

void LiveStream::Offer(const FrameSet& set) {
  State& s = *state_;
  State::Pending job;
  job.set = set.index;
  job.arrived = Clock::now();
  if (const Frame* depth = set.Find(s.depth_sensor)) job.depth = depth->image;
  if (const Frame* color = set.Find(s.color_sensor)) job.color = live::ThreeChannels(color->image);
  {
    std::lock_guard lock(s.mutex);
    ++s.status.offered;
    if (s.finishing || !s.failure.empty()) return;
    if (s.pending) {
      LiveFrame skipped;
      skipped.set = s.pending->set;
      skipped.state = LiveState::kSkipped;
      skipped.why = Cat("behind: set ", set.index, " arrived before this one was composed");
      s.frames.push_back(skipped);
      ++s.status.skipped;
    }
    s.pending = std::move(job);
  }
  s.wake.notify_one();
}

LiveStreamStatus LiveStream::status() const {
  std::lock_guard lock(state_->mutex);
  return state_->status;
}

LiveSummary LiveStream::Finish() {
  State& s = *state_;
  {
    std::lock_guard lock(s.mutex);
    s.finishing = true;
  }
  s.wake.notify_all();
  if (s.thread.joinable()) s.thread.join();
  LiveSummary summary;
  summary.depth_sensor = s.depth_sensor;
  summary.color_sensor = s.color_sensor;
  summary.relit = s.relit;
  summary.relit_why = s.relit ? "" : s.unlit;
  summary.scan_light = s.scan_light;
  summary.frames = s.frames;
  std::sort(summary.frames.begin(), summary.frames.end(),
            [](const LiveFrame& a, const LiveFrame& b) { return a.set < b.set; });
  summary.seconds = std::chrono::duration<double>(Clock::now() - s.start).count();
  if (!s.failure.empty()) {
    summary.End(Termination::kFailure, Cat("live output '", s.out.string(), "': ", s.failure));
  } else if (s.status.offered == 0) {
    summary.End(Termination::kFailure, "no frame set arrived: nothing was composed");
  } else {
    live::Conclude(s.options, &summary);
  }
  summary.metrics = live::SummaryMetrics(summary);
  std::vector<double> latencies = s.latencies_s;
  std::sort(latencies.begin(), latencies.end());
  double mean = 0;
  for (double l : latencies) mean += l / static_cast<double>(latencies.size());
  summary.metrics["offered"] = s.status.offered;
  summary.metrics["skipped"] = s.status.skipped;
  summary.metrics["latency_s"] = {
      {"mean", mean},
      {"median", latencies.empty() ? 0.0 : latencies[latencies.size() / 2]},
      {"max", latencies.empty() ? 0.0 : latencies.back()}};
  summary.metrics["composed_per_second"] =
      summary.seconds > 0 ? static_cast<double>(s.status.composed) / summary.seconds : 0.0;
  if (s.report) {
    s.report->metrics() = summary.metrics;
    s.report->SetSummary(summary);
    try {
      s.report->Write(s.out / "report.json");
    } catch (const std::exception& e) {
      if (summary.termination != Termination::kFailure)
        summary.End(Termination::kFailure, Cat("writing the live report failed: ", e.what()));
    }
  }
  return summary;
}

}  // namespace holocap
