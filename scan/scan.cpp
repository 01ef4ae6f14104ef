// holocap's scanner: one moving RGB-D sensor tracked and fused (see scan/scan.h).
#include "scan/scan.h"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <map>

#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/progress.h"
#include "core/projector.h"
#include "core/take.h"
#include "core/threads.h"
#include "scan/internal/pose_graph.h"
#include "scan/internal/track.h"
#include "scan/light.h"

namespace holocap {

using Json = nlohmann::json;

void ScanOptions::Check() const {
  HOLOCAP_CHECK_OPTION_GT(voxel_m, 0);
  HOLOCAP_CHECK_OPTION_LE(voxel_m, 0.1);
  HOLOCAP_CHECK_OPTION_GE(truncation_voxels, 1);
  HOLOCAP_CHECK_OPTION(!bounds || bounds->valid(), bounds, "max above min on every axis");
  HOLOCAP_CHECK_OPTION_GT(volume_side_m, 0);
  HOLOCAP_CHECK_OPTION_GE(depth_min_m, 0);
  HOLOCAP_CHECK_OPTION_GT(depth_max_m, depth_min_m);
  HOLOCAP_CHECK_OPTION_GE(depth_noise_k, 0);
  HOLOCAP_CHECK_OPTION_GE(floor_margin_m, 0);
  HOLOCAP_CHECK_OPTION_IN(pyramid_levels, 1, 5);
  HOLOCAP_CHECK_OPTION(!iterations.empty(), iterations, "one count per level, finest first");
  for (int count : iterations) {
    HOLOCAP_CHECK_OPTION(count >= 1 && count <= 100, iterations, "each in 1..100");
  }
  HOLOCAP_CHECK_OPTION_GT(max_correspondence_m, 0);
  HOLOCAP_CHECK_OPTION_GT(max_normal_angle_deg, 0);
  HOLOCAP_CHECK_OPTION_LE(max_normal_angle_deg, 90);
  HOLOCAP_CHECK_OPTION_IN(model_stride, 1, 8);
  HOLOCAP_CHECK_OPTION_GE(photometric_weight_m, 0);
  HOLOCAP_CHECK_OPTION_GT(huber_m, 0);
  HOLOCAP_CHECK_OPTION_IN(min_inlier_fraction, 0, 1);
  HOLOCAP_CHECK_OPTION_GT(max_residual_m, 0);
  HOLOCAP_CHECK_OPTION_GE(min_points, 6);
  HOLOCAP_CHECK_OPTION_GT(max_step_m, 0);
  HOLOCAP_CHECK_OPTION_GT(max_step_deg, 0);
  HOLOCAP_CHECK_OPTION_GE(min_condition, 0);
  HOLOCAP_CHECK_OPTION_LT(min_condition, 1);
  HOLOCAP_CHECK_OPTION_GE(max_lost_frames, 1);
  HOLOCAP_CHECK_OPTION_IN(max_degenerate_fraction, 0, 1);
  HOLOCAP_CHECK_OPTION_IN(max_lost_fraction, 0, 1);
  HOLOCAP_CHECK_OPTION_GE(keyframe_every, 1);
  HOLOCAP_CHECK_OPTION_GT(loop_max_distance_m, 0);
  HOLOCAP_CHECK_OPTION_GE(loop_min_angle_deg, 0);
  HOLOCAP_CHECK_OPTION_GE(texture_views, 1);
  HOLOCAP_CHECK_OPTION_GE(light_views, 2);
  HOLOCAP_CHECK_OPTION_GE(threads, 0, "0: all cores");
  meshing.Check();
  texture.Check();
}

Json ScanOptions::ToJson() const {
  Json json = {{"voxel_m", voxel_m},
               {"truncation_voxels", truncation_voxels},
               {"volume_side_m", volume_side_m},
               {"depth_min_m", depth_min_m},
               {"depth_max_m", depth_max_m},
               {"depth_noise_k", depth_noise_k},
               {"floor_margin_m", floor_margin_m},
               {"pyramid_levels", pyramid_levels},
               {"iterations", iterations},
               {"max_correspondence_m", max_correspondence_m},
               {"max_normal_angle_deg", max_normal_angle_deg},
               {"model_stride", model_stride},
               {"photometric_weight_m", photometric_weight_m},
               {"huber_m", huber_m},
               {"min_inlier_fraction", min_inlier_fraction},
               {"max_residual_m", max_residual_m},
               {"min_points", min_points},
               {"max_step_m", max_step_m},
               {"max_step_deg", max_step_deg},
               {"min_condition", min_condition},
               {"max_lost_frames", max_lost_frames},
               {"max_degenerate_fraction", max_degenerate_fraction},
               {"max_lost_fraction", max_lost_fraction},
               {"check_keyframes", check_keyframes},
               {"refine_poses", refine_poses},
               {"keyframe_every", keyframe_every},
               {"loop_min_angle_deg", loop_min_angle_deg},
               {"loop_max_distance_m", loop_max_distance_m},
               {"texture_views", texture_views},
               {"light_views", light_views},
               {"subject_turns", subject_turns},
               {"write_glb", write_glb},
               {"threads", threads}};
  if (bounds) {
    json["bounds"] = {bounds->min.x(), bounds->min.y(), bounds->min.z(),
                      bounds->max.x(), bounds->max.y(), bounds->max.z()};
  }
  return json;
}

const char* ToString(TrackingState state) {
  switch (state) {
    case TrackingState::kFirst:
      return "first";
    case TrackingState::kTracked:
      return "tracked";
    case TrackingState::kDegenerate:
      return "degenerate";
    case TrackingState::kLost:
      return "lost";
    case TrackingState::kSkipped:
      return "skipped";
  }
  return "?";
}

Json TrajectoryErrors::ToJson() const {
  return {{"matched", matched},
          {"ate_rmse_m", ate_rmse_m},
          {"ate_max_m", ate_max_m},
          {"rpe_trans_m", rpe_trans_m},
          {"rpe_rot_deg", rpe_rot_deg}};
}

TrajectoryErrors CompareTrajectories(const std::vector<StampedPose>& estimate,
                                     const std::vector<StampedPose>& truth) {
  TrajectoryErrors errors;
  if (estimate.empty() || truth.size() < 2) return errors;
  std::vector<double> steps;
  for (size_t i = 1; i < truth.size(); ++i)
    steps.push_back(std::abs(truth[i].time_s - truth[i - 1].time_s));
  std::nth_element(steps.begin(), steps.begin() + steps.size() / 2, steps.end());
  const double tolerance = 0.5 * steps[steps.size() / 2];
  std::vector<std::pair<Pose, Pose>> pairs;  // (estimate, truth)
  for (const StampedPose& e : estimate) {
    const auto nearest = std::min_element(
        truth.begin(), truth.end(), [&](const StampedPose& a, const StampedPose& b) {
          return std::abs(a.time_s - e.time_s) < std::abs(b.time_s - e.time_s);
        });
    if (std::abs(nearest->time_s - e.time_s) <= tolerance)
      pairs.emplace_back(e.world_from_cam, nearest->world_from_cam);
  }
  errors.matched = static_cast<int64_t>(pairs.size());
  if (pairs.empty()) return errors;
  Eigen::Matrix3Xd from(3, pairs.size()), to(3, pairs.size());
  for (size_t i = 0; i < pairs.size(); ++i) {
    from.col(i) = pairs[i].first.translation();
    to.col(i) = pairs[i].second.translation();
  }
  Pose truth_from_estimate = Pose::Identity();
  if (pairs.size() >= 3) truth_from_estimate.matrix() = Eigen::umeyama(from, to, false);
  double sum = 0;
  for (size_t i = 0; i < pairs.size(); ++i) {
    const double d = (truth_from_estimate * from.col(i) - to.col(i)).norm();
    sum += d * d;
    errors.ate_max_m = std::max(errors.ate_max_m, d);
  }
  errors.ate_rmse_m = std::sqrt(sum / static_cast<double>(pairs.size()));
  double trans = 0, rot = 0;
  for (size_t i = 1; i < pairs.size(); ++i) {
    const Pose estimated = pairs[i - 1].first.inverse() * pairs[i].first;
    const Pose actual = pairs[i - 1].second.inverse() * pairs[i].second;
    const Pose error = actual.inverse() * estimated;
    trans += error.translation().squaredNorm();
    rot += std::pow(RotationAngleDeg(error.linear()), 2);
  }
  if (pairs.size() > 1) {
    errors.rpe_trans_m = std::sqrt(trans / static_cast<double>(pairs.size() - 1));
    errors.rpe_rot_deg = std::sqrt(rot / static_cast<double>(pairs.size() - 1));
  }
  return errors;
}

std::vector<StampedPose> TrueTrajectory(const Take& take, const std::string& sensor) {
  const std::filesystem::path file = take.gt_dir() / "sim.json";
  std::vector<StampedPose> truth;
  if (!std::filesystem::exists(file)) return truth;
  std::map<int64_t, int64_t> timestamp_of_set;
  for (const FrameSetEntry& entry : take.entries()) {
    if (const FrameSetEntry::Item* item = entry.Find(sensor))
      timestamp_of_set[entry.index] = item->timestamp_ns;
  }
  try {
    const Json sim = Json::parse(ReadFileToString(file));
    for (const Json& frame : sim.at("frames")) {
      if (frame.at("sensor").get<std::string>() != sensor || !frame.contains("cam_from_world"))
        continue;
      const auto found = timestamp_of_set.find(frame.at("set").get<int64_t>());
      if (found == timestamp_of_set.end()) continue;
      StampedPose pose;
      pose.time_s = 1e-9 * static_cast<double>(found->second);
      pose.world_from_cam = PoseFromRt(frame.at("cam_from_world").at("rt").get<Rt>()).inverse();
      truth.push_back(pose);
    }
  } catch (const Json::exception& e) {
    Fail(file.string(), ": ", e.what());
  }
  return truth;
}

namespace {

using Clock = std::chrono::steady_clock;

double Since(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

// CPU time of the whole process (every thread), seconds.
double ProcessCpuSeconds() { return static_cast<double>(std::clock()) / CLOCKS_PER_SEC; }

cv::Mat Bgr(const cv::Mat& frame) {
  if (frame.channels() == 3) return frame;
  cv::Mat bgr;
  cv::cvtColor(frame, bgr, frame.channels() == 1 ? cv::COLOR_GRAY2BGR : cv::COLOR_BGRA2BGR);
  return bgr;
}

// The rigid motion `motion` scaled by `ratio` along its own screw (rotation angle and
// translation scaled alike): the motion of ratio times the interval it took. Its rotation is
// rebuilt from the angle and axis, so it is orthonormal whatever rounding `motion` carries.
Pose ScaleMotion(const Pose& motion, double ratio) {
  const Eigen::AngleAxisd rotation(NearestRotation(motion.linear()));
  Pose scaled = Pose::Identity();
  scaled.linear() = Eigen::AngleAxisd(ratio * rotation.angle(), rotation.axis()).toRotationMatrix();
  scaled.translation() = ratio * motion.translation();
  return scaled;
}

// What one frame's tracking concluded.
struct Verdict {
  TrackingState state = TrackingState::kTracked;
  std::string why;
};

// The tracking tests of ScanOptions, in the order a reader would check them.
Verdict Judge(const scan::AlignResult& aligned, const Pose& predicted, const ScanOptions& o) {
  char why[200];
  if (aligned.points < o.min_points) {
    std::snprintf(why, sizeof(why), "%lld valid depth points (< %d)",
                  static_cast<long long>(aligned.points), o.min_points);
    return {TrackingState::kLost, why};
  }
  if (aligned.inlier_fraction < o.min_inlier_fraction) {
    std::snprintf(why, sizeof(why), "%.0f%% of the points match the model (< %.0f%%)",
                  100 * aligned.inlier_fraction, 100 * o.min_inlier_fraction);
    return {TrackingState::kLost, why};
  }
  if (aligned.residual_m > o.max_residual_m) {
    std::snprintf(why, sizeof(why), "point-to-plane RMS %.1f mm (> %.1f mm)",
                  1e3 * aligned.residual_m, 1e3 * o.max_residual_m);
    return {TrackingState::kLost, why};
  }
  const Pose step = predicted.inverse() * aligned.world_from_cam;
  if (step.translation().norm() > o.max_step_m ||
      RotationAngleDeg(step.linear()) > o.max_step_deg) {
    std::snprintf(why, sizeof(why), "pose jumped %.2f m / %.1f deg from the prediction",
                  step.translation().norm(), RotationAngleDeg(step.linear()));
    return {TrackingState::kLost, why};
  }
  if (aligned.condition < o.min_condition) {
    const Eigen::Vector3d d = aligned.weak_direction.normalized();
    std::snprintf(why, sizeof(why),
                  "ICP degenerate: Hessian condition %.1e (< %.1e), weakest along "
                  "(%.2f, %.2f, %.2f) in the world",
                  aligned.condition, o.min_condition, d.x(), d.y(), d.z());
    return {TrackingState::kDegenerate, why};
  }
  return {};
}

struct Keyframe {
  size_t frame = 0;  // index into the scan's frames
  scan::TrackFrame track;
  cv::Mat color;  // BGR, for the texture
};

// One scan, step by step: sensors and volume, each frame tracked and fused, the pose graph,
// then the mesh, its texture and the outputs.
class Scanner {
 public:
  Scanner(const Take& take, const TakePlan& plan, const ScanOptions& options, Report* report)
      : take_(take),
        plan_(plan),
        options_(options),
        report_(report),
        threads_(ResolveThreads(options.threads)) {
    if (plan.depth_sensors.size() != 1) {
      Fail("scan: take '", take.dir().string(), "' has ", plan.depth_sensors.size(),
           " depth sensors; a scan needs exactly one");
    }
    depth_name_ = plan.depth_sensors.front();
    depth_lens_ = plan.cameras.at(depth_name_);
    color_name_ = take.stream(depth_name_).paired_with;
    if (!color_name_.empty() && plan.cameras.count(color_name_)) {
      color_lens_ = plan.cameras.at(color_name_);
      color_from_depth_ = color_lens_.cam_from_world() * depth_lens_.world_from_cam();
    } else {
      color_name_.clear();
    }
    rays_ = NormalisedRays(depth_lens_);
    // How the subject and sensor move is the user's to say (--turn), never the take's metadata.
    turntable_ = options.subject_turns;
  }

  ScanSummary Run(const std::filesystem::path& out) {
    const Clock::time_point start = Clock::now();
    Progress progress("scan", static_cast<int64_t>(plan_.sets.size()));
    for (int64_t set : plan_.sets) {
      ProcessSet(set);
      progress.Increment(ToString(summary_.frames.back().state));
      if (stopped_) break;
    }
    progress.Finish();
    for (size_t i = summary_.frames.size(); i < plan_.sets.size(); ++i) {
      ScanFrame skipped;
      skipped.set = plan_.sets[i];
      skipped.why = stop_reason_;
      summary_.frames.push_back(skipped);
    }
    if (volume_ && options_.refine_poses) Refine();
    if (volume_ && options_.check_keyframes) CheckKeyframes();
    Conclude(out);
    summary_.seconds = Since(start);
    WriteReport(out);
    return summary_;
  }

 private:
  // The volume's box: the user's, else a cube around what the first frame sees.
  Box VolumeBounds(const scan::TrackFrame& frame, const Pose& world_from_cam) const {
    if (options_.bounds) return *options_.bounds;
    if (plan_.bounds_source.rfind("user", 0) == 0) return plan_.bounds;
    const Eigen::Vector3d center = world_from_cam * Eigen::Vector3d(0, 0, frame.median_depth_m);
    const Eigen::Vector3d half = Eigen::Vector3d::Constant(0.5 * options_.volume_side_m);
    return {center - half, center + half};
  }

  // The depth map without what tracking and fusion must ignore: out of range, outside the
  // volume, and (turntable) the floor, each judged at the predicted pose.
  cv::Mat UsableDepth(const cv::Mat& depth_in, const Pose& world_from_cam) const {
    cv::Mat depth = depth_in.clone();
    const bool floor = turntable_ && std::isfinite(plan_.floor_m);
    for (int y = 0; y < depth.rows; ++y) {
      float* row = depth.ptr<float>(y);
      for (int x = 0; x < depth.cols; ++x) {
        const float d = row[x];
        const cv::Vec2f ray = rays_.at<cv::Vec2f>(y, x);
        if (!(d >= options_.depth_min_m && d <= options_.depth_max_m) || std::isnan(ray[0])) {
          row[x] = std::numeric_limits<float>::quiet_NaN();
          continue;
        }
        if (!volume_) continue;
        const Eigen::Vector3d p = world_from_cam * Eigen::Vector3d(ray[0] * d, ray[1] * d, d);
        if (!volume_->volume().bounds().Contains(p) ||
            (floor && plan_.up.dot(p) < plan_.floor_m + options_.floor_margin_m)) {
          row[x] = std::numeric_limits<float>::quiet_NaN();
        }
      }
    }
    return depth;
  }

  void ProcessSet(int64_t set) {
    ScanFrame frame;
    frame.set = set;
    const FrameSetEntry::Item* item = take_.entry(static_cast<size_t>(set)).Find(depth_name_);
    if (item == nullptr) {
      frame.why = "no depth frame in this set";
      summary_.frames.push_back(frame);
      return;
    }
    frame.time_s = 1e-9 * static_cast<double>(item->timestamp_ns);
    const cv::Mat raw = take_.ReadFrame(static_cast<size_t>(set), depth_name_);
    cv::Mat color;
    if (!color_name_.empty() && take_.entry(static_cast<size_t>(set)).Find(color_name_))
      color = Bgr(take_.ReadFrame(static_cast<size_t>(set), color_name_));
    // Timed from here: reading and decoding the take's files is not the tracker's work.
    const Clock::time_point start = Clock::now();
    const double cpu_start = ProcessCpuSeconds();
    const Pose predicted = Predict(frame.time_s);
    const cv::Mat depth = UsableDepth(raw, predicted);
    const cv::Mat gray =
        scan::RegisterIntensity(depth, rays_, color, color_lens_, color_from_depth_, threads_);
    scan::TrackFrame track = scan::PrepareFrame(depth, rays_, gray, options_.pyramid_levels,
                                                options_.depth_min_m, options_.depth_max_m);
    frame.points = track.valid;
    if (!volume_) {
      StartVolume(frame, track, raw, color);
    } else {
      Track(frame, track, depth, predicted);
    }
    if (frame.state == TrackingState::kTracked || frame.state == TrackingState::kDegenerate ||
        frame.state == TrackingState::kFirst) {
      const Clock::time_point fuse_start = Clock::now();
      const double fuse_cpu_start = ProcessCpuSeconds();
      Fuse(depth, color, frame.world_from_cam);
      frame.fused = true;
      summary_.fusion_seconds += Since(fuse_start);
      summary_.fusion_cpu_seconds_per_frame += ProcessCpuSeconds() - fuse_cpu_start;
      if (frame.state != TrackingState::kFirst) {
        previous_good_ = last_good_;
        previous_good_time_s_ = last_good_time_s_;
      }
      last_good_ = frame.world_from_cam;
      last_good_time_s_ = frame.time_s;
      has_velocity_ = frame.state != TrackingState::kFirst;
      lost_in_row_ = 0;
      if (tracked_since_keyframe_++ % options_.keyframe_every == 0)
        keyframes_.push_back({summary_.frames.size(), std::move(track), color});
    }
    frame.seconds = Since(start);
    frame.cpu_seconds = ProcessCpuSeconds() - cpu_start;
    busy_seconds_ += frame.seconds;
    summary_.cpu_seconds_per_frame += frame.cpu_seconds;
    summary_.frames.push_back(frame);
    if (report_ != nullptr && frame.fused && frame.state != TrackingState::kFirst) {
      report_->AddPoint("inlier_fraction", frame.inlier_fraction, set);
      report_->AddPoint("residual_mm", 1e3 * frame.residual_m, set);
    }
  }

  // Constant velocity from the last two good poses, carried over the time since the last one:
  // after lost frames the sensor has gone on moving, and the pose it left is frames behind.
  Pose Predict(double time_s) const {
    const double interval_s = last_good_time_s_ - previous_good_time_s_;
    if (!has_velocity_ || !(interval_s > 0)) return last_good_;
    const double ratio = (time_s - last_good_time_s_) / interval_s;
    return last_good_ * ScaleMotion(previous_good_.inverse() * last_good_, ratio);
  }

  void StartVolume(ScanFrame& frame, const scan::TrackFrame& track, const cv::Mat& raw,
                   const cv::Mat& color) {
    (void)color;
    if (track.valid < options_.min_points) {
      frame.state = TrackingState::kSkipped;
      frame.why = Cat("cannot start the model: ", track.valid, " valid depth points (< ",
                      options_.min_points, ")");
      return;
    }
    frame.state = TrackingState::kFirst;
    frame.world_from_cam = depth_lens_.world_from_cam();
    TsdfOptions tsdf;
    tsdf.voxel_m = options_.voxel_m;
    tsdf.truncation_voxels = options_.truncation_voxels;
    // The model is raycast from each new pose: its rays need the signed distances in front of
    // and behind the surface along other directions than the sensor's that fused them, so a
    // frame allocates the whole truncation band, not only the blocks at its surface.
    tsdf.band_voxels = options_.truncation_voxels;
    tsdf.bounds = VolumeBounds(track, frame.world_from_cam);
    tsdf.depth_min_m = options_.depth_min_m;
    tsdf.depth_max_m = options_.depth_max_m;
    tsdf.depth_noise_k = options_.depth_noise_k;
    tsdf.smoothing_radius_px = 2;
    tsdf.threads = threads_;
    tsdf_options_ = tsdf;
    volume_ = std::make_unique<TsdfVolume>(tsdf);
    last_good_ = frame.world_from_cam;
    (void)raw;
  }

  void Track(ScanFrame& frame, const scan::TrackFrame& track, const cv::Mat& depth,
             const Pose& predicted) {
    if (track.valid < options_.min_points) {
      frame.state = TrackingState::kLost;
      frame.why = Cat(track.valid, " valid depth points (< ", options_.min_points, ")");
    } else {
      const double window = 0.1 + 2 * volume_->volume().truncation_m();
      const scan::ModelView model = scan::RaycastModel(volume_->volume(), rays_, predicted, depth,
                                                       window, options_.model_stride, threads_);
      const scan::AlignResult aligned =
          scan::AlignToReference(track, model, depth_lens_, predicted, options_, threads_);
      frame.world_from_cam = aligned.world_from_cam;
      frame.inlier_fraction = aligned.inlier_fraction;
      frame.residual_m = aligned.residual_m;
      frame.condition = aligned.condition;
      frame.weak_direction = aligned.weak_direction;
      const Verdict verdict = Judge(aligned, predicted, options_);
      frame.state = verdict.state;
      frame.why = verdict.why;
    }
    if (frame.state == TrackingState::kLost) {
      frame.world_from_cam = last_good_;
      if (++lost_in_row_ >= options_.max_lost_frames) {
        stopped_ = true;
        stop_reason_ = Cat("scan stopped: tracking lost for ", lost_in_row_,
                           " frames in a row since set ", frame.set - lost_in_row_ + 1);
      }
    }
  }

  void Fuse(const cv::Mat& depth, const cv::Mat& color, const Pose& world_from_cam) {
    CameraModel depth_camera = depth_lens_;
    depth_camera.set_cam_from_world(world_from_cam.inverse());
    if (color.empty()) {
      volume_->Integrate(depth, depth_camera);
      return;
    }
    CameraModel color_camera = color_lens_;
    color_camera.set_cam_from_world(color_from_depth_ * world_from_cam.inverse());
    volume_->Integrate(depth, depth_camera, {}, color, &color_camera);
  }

  // Loop edges between keyframes that came back to a place seen before, then the graph.
  void Refine();
  void Refuse();
  // Each keyframe against the final model (ScanOptions::check_keyframes).
  void CheckKeyframes();
  void Conclude(const std::filesystem::path& out);
  void WriteOutputs(const std::filesystem::path& out, const Mesh& mesh);
  void WriteLight(const std::filesystem::path& out, const Mesh& mesh);
  void WriteReport(const std::filesystem::path& out);
  std::vector<StampedPose> EstimatedTrajectory() const;

  const Take& take_;
  const TakePlan& plan_;
  const ScanOptions& options_;
  Report* report_;
  const int threads_;
  std::string depth_name_, color_name_;
  CameraModel depth_lens_, color_lens_;
  Pose color_from_depth_ = Pose::Identity();
  cv::Mat rays_;
  bool turntable_ = false;
  TsdfOptions tsdf_options_;
  std::unique_ptr<TsdfVolume> volume_;
  Pose last_good_ = Pose::Identity();
  Pose previous_good_ = Pose::Identity();
  double last_good_time_s_ = 0, previous_good_time_s_ = 0;
  bool has_velocity_ = false;
  int lost_in_row_ = 0;
  bool stopped_ = false;
  std::string stop_reason_;
  int64_t tracked_since_keyframe_ = 0;
  std::vector<Keyframe> keyframes_;
  double busy_seconds_ = 0;  // tracking and fusion
  ScanSummary summary_;
  Json refinement_ = Json::object();
  Json consistency_ = Json::object();
  std::string inconsistency_;  // the first keyframe the final model contradicts, said why
};

void Scanner::Refine() {
  const Clock::time_point start = Clock::now();
  std::vector<Pose> poses;
  for (const Keyframe& k : keyframes_) poses.push_back(summary_.frames[k.frame].world_from_cam);
  std::vector<scan::PoseEdge> edges;
  for (size_t k = 1; k < keyframes_.size(); ++k)
    edges.push_back(
        {static_cast<int>(k - 1), static_cast<int>(k), poses[k - 1].inverse() * poses[k]});
  int loops = 0;
  for (size_t b = 0; b < keyframes_.size(); ++b) {
    double travelled_deg = 0;
    for (size_t a = b; a-- > 0;) {
      travelled_deg += RotationAngleDeg((poses[a].inverse() * poses[a + 1]).linear());
      if (b - a < 3 || travelled_deg < options_.loop_min_angle_deg) continue;
      const Pose relative = poses[a].inverse() * poses[b];
      if (relative.translation().norm() > options_.loop_max_distance_m ||
          RotationAngleDeg(relative.linear()) > 30)
        continue;
      const scan::ModelView reference = scan::ViewOfFrame(keyframes_[a].track, poses[a]);
      const scan::AlignResult aligned = scan::AlignToReference(
          keyframes_[b].track, reference, depth_lens_, poses[b], options_, threads_);
      if (Judge(aligned, poses[b], options_).state != TrackingState::kTracked) continue;
      edges.push_back(
          {static_cast<int>(a), static_cast<int>(b), poses[a].inverse() * aligned.world_from_cam});
      ++loops;
    }
  }
  summary_.keyframes = static_cast<int64_t>(keyframes_.size());
  summary_.loops = loops;
  refinement_ = {{"keyframes", keyframes_.size()}, {"loop_edges", loops}};
  if (loops == 0) {
    refinement_["message"] = "no loop edge: the tracked poses stand";
    refinement_["seconds"] = Since(start);
    return;
  }
  const scan::PoseGraphResult graph = scan::OptimizePoseGraph(poses, edges, threads_);
  refinement_["solver"] = graph.message;
  refinement_["initial_cost"] = graph.initial_cost;
  refinement_["final_cost"] = graph.final_cost;
  // Every frame moves with the keyframe before it.
  double largest_move = 0;
  size_t k = 0;
  for (size_t i = 0; i < summary_.frames.size(); ++i) {
    while (k + 1 < keyframes_.size() && keyframes_[k + 1].frame <= i) ++k;
    ScanFrame& frame = summary_.frames[i];
    if (!frame.fused || keyframes_.empty() || keyframes_[k].frame > i) continue;
    const Pose correction = graph.world_from_keyframe[k] * poses[k].inverse();
    frame.world_from_cam = correction * frame.world_from_cam;
    largest_move = std::max(largest_move, correction.translation().norm());
  }
  refinement_["largest_correction_m"] = largest_move;
  if (largest_move > options_.voxel_m) Refuse();
  refinement_["seconds"] = Since(start);
}

// The volume fused again from every fused frame at its refined pose.
void Scanner::Refuse() {
  volume_ = std::make_unique<TsdfVolume>(tsdf_options_);
  for (const ScanFrame& frame : summary_.frames) {
    if (!frame.fused) continue;
    const size_t set = static_cast<size_t>(frame.set);
    cv::Mat color;
    if (!color_name_.empty() && take_.entry(set).Find(color_name_))
      color = Bgr(take_.ReadFrame(set, color_name_));
    Fuse(UsableDepth(take_.ReadFrame(set, depth_name_), frame.world_from_cam), color,
         frame.world_from_cam);
  }
  refinement_["refused"] = true;
}

void Scanner::CheckKeyframes() {
  const Clock::time_point start = Clock::now();
  const double window = 0.1 + 2 * volume_->volume().truncation_m();
  double largest_move = 0;
  int64_t checked = 0, contradicted = 0;
  for (const Keyframe& k : keyframes_) {
    const ScanFrame& frame = summary_.frames[k.frame];
    if (frame.state == TrackingState::kFirst) continue;  // it started the model
    const scan::Level& finest = k.track.levels.front();
    cv::Mat hint(finest.height, finest.width, CV_32F);
    for (int i = 0; i < finest.width * finest.height; ++i)
      hint.at<float>(i / finest.width, i % finest.width) = finest.points[i].z();
    const scan::ModelView model = scan::RaycastModel(volume_->volume(), rays_, frame.world_from_cam,
                                                     hint, window, options_.model_stride, threads_);
    const scan::AlignResult aligned = scan::AlignToReference(
        k.track, model, depth_lens_, frame.world_from_cam, options_, threads_);
    const Pose move = frame.world_from_cam.inverse() * aligned.world_from_cam;
    // A rotation moves the surface by the angle times its distance.
    const double move_m = move.translation().norm() +
                          RotationAngleDeg(move.linear()) * M_PI / 180 * k.track.median_depth_m;
    largest_move = std::max(largest_move, move_m);
    ++checked;
    const Verdict verdict = Judge(aligned, frame.world_from_cam, options_);
    std::string why;
    if (verdict.state == TrackingState::kLost) {
      why = verdict.why;
    } else if (move_m > options_.max_correspondence_m) {
      why = Cat("it moves ", std::lround(1e3 * move_m), " mm to fit it (> the ",
                std::lround(1e3 * options_.max_correspondence_m), " mm association gate)");
    }
    if (why.empty()) continue;
    if (contradicted++ == 0)
      inconsistency_ = Cat("keyframe at set ", frame.set, " contradicts the final model: ", why);
  }
  consistency_ = {{"keyframes_checked", checked},
                  {"keyframes_contradicted", contradicted},
                  {"largest_move_m", largest_move},
                  {"seconds", Since(start)}};
}

std::vector<StampedPose> Scanner::EstimatedTrajectory() const {
  std::vector<StampedPose> trajectory;
  for (const ScanFrame& frame : summary_.frames) {
    if (frame.fused) trajectory.push_back({frame.time_s, frame.world_from_cam});
  }
  return trajectory;
}

void Scanner::Conclude(const std::filesystem::path& out) {
  for (const ScanFrame& frame : summary_.frames) {
    summary_.tracked += frame.state == TrackingState::kTracked;
    summary_.degenerate += frame.state == TrackingState::kDegenerate;
    summary_.lost += frame.state == TrackingState::kLost;
    summary_.fused += frame.fused;
  }
  summary_.tracking_seconds = busy_seconds_ - summary_.fusion_seconds;
  summary_.frames_per_second =
      busy_seconds_ > 0 ? static_cast<double>(summary_.frames.size()) / busy_seconds_ : 0;
  if (!summary_.frames.empty()) {
    summary_.cpu_seconds_per_frame /= static_cast<double>(summary_.frames.size());
    summary_.fusion_cpu_seconds_per_frame /= static_cast<double>(summary_.frames.size());
  }
  const std::vector<StampedPose> truth = TrueTrajectory(take_, depth_name_);
  if (!truth.empty()) summary_.errors = CompareTrajectories(EstimatedTrajectory(), truth);

  const auto first_of = [&](TrackingState state) -> const ScanFrame* {
    for (const ScanFrame& f : summary_.frames) {
      if (f.state == state) return &f;
    }
    return nullptr;
  };
  Mesh mesh;
  if (volume_) mesh = ExtractMesh(volume_->volume(), options_.meshing);
  summary_.vertices = static_cast<int64_t>(mesh.vertices.size());
  summary_.faces = static_cast<int64_t>(mesh.faces.size());
  const int64_t considered = summary_.tracked + summary_.degenerate;
  std::string lost_note;
  if (const ScanFrame* lost = first_of(TrackingState::kLost)) {
    lost_note = Cat("; ", summary_.lost, " frames lost (first: set ", lost->set, ", ", lost->why,
                    "), never fused");
  }
  if (!volume_) {
    summary_.End(Termination::kDegenerate, Cat("no frame had enough valid depth to start a model (",
                                               plan_.sets.size(), " frames of ", depth_name_, ")"));
  } else if (stopped_) {
    summary_.End(Termination::kDegenerate, stop_reason_ + "; the model so far is kept" + lost_note);
  } else if (summary_.lost >
             options_.max_lost_fraction * static_cast<double>(summary_.lost + considered)) {
    summary_.End(Termination::kDegenerate,
                 Cat(summary_.lost, " of ", summary_.lost + considered, " frames lost (more than ",
                     std::lround(100 * options_.max_lost_fraction),
                     "%): the trajectory across the gaps is the motion model's guess", lost_note));
  } else if (!inconsistency_.empty()) {
    summary_.End(Termination::kDegenerate, inconsistency_ + lost_note);
  } else if (considered > 0 && summary_.degenerate > options_.max_degenerate_fraction *
                                                         static_cast<double>(considered)) {
    const ScanFrame* d = first_of(TrackingState::kDegenerate);
    summary_.End(
        Termination::kDegenerate,
        Cat(summary_.degenerate, " of ", considered, " tracked frames degenerate (first: set ",
            d->set, ", ", d->why, "): the surface does not fix the sensor's pose"));
  } else if (mesh.faces.empty()) {
    summary_.End(Termination::kDegenerate, "the fused volume holds no surface" + lost_note);
  } else {
    summary_.End(Termination::kSuccess, Cat(summary_.fused, " of ", summary_.frames.size(),
                                            " frames tracked and fused", lost_note));
  }
  try {
    WriteOutputs(out, mesh);
  } catch (const Error& e) {
    summary_.End(Termination::kFailure, Cat("writing the outputs: ", e.what()));
  }
}

void Scanner::WriteOutputs(const std::filesystem::path& out, const Mesh& mesh) {
  std::string tum = "# world_from_cam of " + depth_name_ + ": time_s tx ty tz qx qy qz qw\n";
  for (const StampedPose& pose : EstimatedTrajectory())
    tum += TumLine(pose.time_s, pose.world_from_cam);
  WriteFileAtomic(out / "trajectory.tum", tum);
  Json frames = Json::array();
  for (const ScanFrame& f : summary_.frames) {
    frames.push_back({{"set", f.set},
                      {"time_s", f.time_s},
                      {"state", ToString(f.state)},
                      {"why", f.why},
                      {"fused", f.fused},
                      {"points", f.points},
                      {"inlier_fraction", f.inlier_fraction},
                      {"residual_m", f.residual_m},
                      {"condition", f.condition},
                      {"cam_from_world", RtFromPose(f.world_from_cam.inverse())}});
  }
  WriteFileAtomic(out / "trajectory.json", frames.dump(1) + "\n");
  if (mesh.faces.empty()) return;
  WritePly(out / "mesh.ply", mesh);
  if (!color_name_.empty()) WriteLight(out, mesh);
  if (!options_.write_glb || keyframes_.empty() || color_name_.empty()) return;
  // Keyframes spread over the scan colour the mesh.
  std::vector<View> views;
  const size_t count = std::min<size_t>(options_.texture_views, keyframes_.size());
  for (size_t v = 0; v < count; ++v) {
    const Keyframe& k = keyframes_[v * keyframes_.size() / count];
    if (k.color.empty()) continue;
    View view;
    view.name = Cat(color_name_, "@", summary_.frames[k.frame].set);
    view.camera = color_lens_;
    view.camera.set_cam_from_world(color_from_depth_ *
                                   summary_.frames[k.frame].world_from_cam.inverse());
    view.image = k.color;
    views.push_back(view);
  }
  const TexturedMesh textured = TextureMesh(mesh, views, options_.texture);
  WriteGlb(out / "mesh.glb", textured);
  summary_.metrics["texture"] = textured.Metrics();
}

// The scan's light and albedo (scan/light.h) from up to light_views fused frames
// spread over the scan: lighting.json, and albedo.ply when a light was found.
void Scanner::WriteLight(const std::filesystem::path& out, const Mesh& mesh) {
  std::vector<const ScanFrame*> fused;
  for (const ScanFrame& f : summary_.frames)
    if (f.fused) fused.push_back(&f);
  const size_t count = std::min<size_t>(options_.light_views, fused.size());
  std::vector<LitView> views;
  for (size_t k = 0; k < count; ++k) {
    const ScanFrame& f = *fused[k * fused.size() / count];
    LitView view;
    view.bgr = Bgr(take_.ReadFrame(static_cast<size_t>(f.set), color_name_));
    if (view.bgr.empty()) continue;
    view.camera = color_lens_;
    view.camera.set_cam_from_world(color_from_depth_ * f.world_from_cam.inverse());
    view.sensor_from_world = f.world_from_cam.linear().transpose();
    views.push_back(view);
  }
  ScanLight light;
  light.views = static_cast<int64_t>(views.size());
  if (!turntable_) {
    // A sensor moving through the room carries no light with it: the light cannot be told from
    // the colours, which are kept as seen.
    light.why =
        "the sensor moved: a light is found only when the subject turns before a still sensor "
        "(--turn)";
  } else {
    Mesh lit = mesh;
    if (lit.normals.size() != lit.vertices.size()) lit.ComputeNormals();
    // The floor does not turn with the subject: it is left out of the fit.
    std::vector<bool> fit(lit.vertices.size(), true);
    if (std::isfinite(plan_.floor_m)) {
      for (size_t v = 0; v < fit.size(); ++v) {
        fit[v] = plan_.up.dot(lit.vertices[v].cast<double>()) >
                 plan_.floor_m + options_.floor_margin_m + 0.02;
      }
    }
    Mesh albedo;
    light = EstimateScanLight(lit, views, fit, ScanLightOptions{}, &albedo);
    if (light.observed) WritePly(out / "albedo.ply", albedo);
  }
  WriteFileAtomic(out / "lighting.json", light.ToJson().dump(2) + "\n");
  summary_.metrics["lighting"] = light.ToJson();
}

void Scanner::WriteReport(const std::filesystem::path& out) {
  Json& m = summary_.metrics;
  m["frames"] = summary_.frames.size();
  m["tracked"] = summary_.tracked;
  m["degenerate"] = summary_.degenerate;
  m["lost"] = summary_.lost;
  m["fused"] = summary_.fused;
  m["seconds"] = summary_.seconds;
  m["tracking_seconds"] = summary_.tracking_seconds;
  m["fusion_seconds"] = summary_.fusion_seconds;
  m["frames_per_second"] = summary_.frames_per_second;
  m["cpu_seconds_per_frame"] = summary_.cpu_seconds_per_frame;
  m["fusion_cpu_seconds_per_frame"] = summary_.fusion_cpu_seconds_per_frame;
  m["vertices"] = summary_.vertices;
  m["faces"] = summary_.faces;
  m["refinement"] = refinement_;
  m["keyframe_check"] = consistency_;
  if (volume_) m["volume_blocks"] = volume_->volume().block_count();
  if (summary_.errors) m["gt"] = summary_.errors->ToJson();
  if (report_ == nullptr) return;
  report_->plan() = plan_.ToJson();
  report_->plan()["scan"] = {
      {"depth_sensor", depth_name_},
      {"color_sensor", color_name_},
      {"sensor_motion", turntable_ ? "still (the subject turns: --turn)" : "moving (the default)"},
      {"subject_turns", turntable_},
      {"floor_removed", turntable_ && std::isfinite(plan_.floor_m)}};
  if (volume_) {
    const Box& b = volume_->volume().bounds();
    report_->plan()["scan"]["volume"] = {b.min.x(), b.min.y(), b.min.z(),
                                         b.max.x(), b.max.y(), b.max.z()};
  }
  report_->options() = options_.ToJson();
  report_->metrics() = m;
  // Error against time: the trajectory's error at each fused frame, once aligned.
  if (summary_.errors) {
    const std::vector<StampedPose> truth = TrueTrajectory(take_, depth_name_);
    const std::vector<StampedPose> estimate = EstimatedTrajectory();
    for (size_t i = 0; i < estimate.size(); ++i) {
      const TrajectoryErrors prefix =
          CompareTrajectories({estimate.begin(), estimate.begin() + i + 1}, truth);
      report_->AddPoint("ate_m", prefix.ate_rmse_m, static_cast<int64_t>(i));
    }
  }
  report_->SetSummary(summary_);
  report_->Write(out / "report.json");
}

}  // namespace

ScanSummary ScanTake(const Take& take, const TakePlan& plan, const std::filesystem::path& out,
                     const ScanOptions& options, Report* report) {
  options.Check();
  CreateDirectories(out);
  Scanner scanner(take, plan, options, report);
  return scanner.Run(out);
}

ScanSummary ScanTake(const std::filesystem::path& take_dir, const TakeSelection& selection,
                     const std::filesystem::path& out, const ScanOptions& options, Report* report) {
  options.Check();
  const Take take = Take::Open(take_dir);
  const TakePlan plan = PlanTake(take, selection);
  return ScanTake(take, plan, out, options, report);
}

}  // namespace holocap
