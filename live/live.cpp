// holocap live: a take of one fixed RGB-D sensor, frame by frame, completed by a scan.
#include "live/live.h"

#include <chrono>
#include <cmath>
#include <cstdio>
#include <opencv2/imgproc.hpp>

#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/progress.h"
#include "core/take.h"
#include "live/internal/live.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

namespace fs = std::filesystem;
using Json = nlohmann::json;

void LiveOptions::Check() const {
  HOLOCAP_CHECK_OPTION_GT(depth_min_m, 0);
  HOLOCAP_CHECK_OPTION_GT(depth_max_m, depth_min_m);
  HOLOCAP_CHECK_OPTION_GE(alignment_samples, 100);
  HOLOCAP_CHECK_OPTION_GE(rigid_iterations, 1);
  HOLOCAP_CHECK_OPTION_GT(gate_m, 0);
  HOLOCAP_CHECK_OPTION_LE(gate_m, coarse_gate_m);
  HOLOCAP_CHECK_OPTION_GT(max_normal_angle_deg, 0);
  HOLOCAP_CHECK_OPTION_LE(max_normal_angle_deg, 90);
  HOLOCAP_CHECK_OPTION_GT(huber_m, 0);
  HOLOCAP_CHECK_OPTION_GT(node_spacing_m, 0);
  HOLOCAP_CHECK_OPTION_IN(node_neighbours, 1, 4);
  HOLOCAP_CHECK_OPTION_GE(nonrigid_iterations, 0);
  HOLOCAP_CHECK_OPTION_GT(arap_weight, 0);
  HOLOCAP_CHECK_OPTION_IN(min_inlier_fraction, 0, 1);
  HOLOCAP_CHECK_OPTION_GT(max_residual_m, 0);
  HOLOCAP_CHECK_OPTION_IN(min_rigid_inlier_fraction, 0, 1);
  HOLOCAP_CHECK_OPTION_IN(min_explained_fraction, 0, 1);
  HOLOCAP_CHECK_OPTION_GT(max_deformation_rms_m, 0);
  HOLOCAP_CHECK_OPTION_IN(max_refused_fraction, 0, 1);
  HOLOCAP_CHECK_OPTION_GT(subject_gate_m, 0);
  HOLOCAP_CHECK_OPTION_GT(observed_gate_m, 0);
  HOLOCAP_CHECK_OPTION_GT(max_depth_jump_m, 0);
  HOLOCAP_CHECK_OPTION_GE(floor_margin_m, 0);
  HOLOCAP_CHECK_OPTION_GE(subject_reach_m, 0);
  HOLOCAP_CHECK_OPTION_GE(threads, 0);
}

Json LiveOptions::ToJson() const {
  return {{"depth_min_m", depth_min_m},
          {"depth_max_m", depth_max_m},
          {"alignment_samples", alignment_samples},
          {"rigid_iterations", rigid_iterations},
          {"coarse_gate_m", coarse_gate_m},
          {"gate_m", gate_m},
          {"max_normal_angle_deg", max_normal_angle_deg},
          {"huber_m", huber_m},
          {"nonrigid", nonrigid},
          {"node_spacing_m", node_spacing_m},
          {"node_neighbours", node_neighbours},
          {"nonrigid_iterations", nonrigid_iterations},
          {"arap_weight", arap_weight},
          {"carry_deformation", carry_deformation},
          {"relight", relight},
          {"min_inlier_fraction", min_inlier_fraction},
          {"max_residual_m", max_residual_m},
          {"min_rigid_inlier_fraction", min_rigid_inlier_fraction},
          {"min_explained_fraction", min_explained_fraction},
          {"max_deformation_rms_m", max_deformation_rms_m},
          {"max_refused_fraction", max_refused_fraction},
          {"subject_gate_m", subject_gate_m},
          {"subject_reach_m", subject_reach_m},
          {"observed_gate_m", observed_gate_m},
          {"max_depth_jump_m", max_depth_jump_m},
          {"floor_margin_m", floor_margin_m},
          {"write_glb", write_glb},
          {"threads", threads}};
}

const char* ToString(LiveState state) {
  switch (state) {
    case LiveState::kComposed:
      return "composed";
    case LiveState::kNoDepth:
      return "no_depth";
    case LiveState::kRefused:
      return "refused";
    case LiveState::kSkipped:
      return "skipped";
  }
  return "?";
}

Json LiveFrame::ToJson() const {
  auto number = [](double value) { return std::isfinite(value) ? Json(value) : Json(nullptr); };
  const Eigen::Matrix4d m = world_from_scan.matrix();
  Json rows = Json::array();
  for (int r = 0; r < 3; ++r) rows.push_back({m(r, 0), m(r, 1), m(r, 2), m(r, 3)});
  return {{"set", set},
          {"state", ToString(state)},
          {"why", why},
          {"world_from_scan", rows},
          {"relocalised", relocalised},
          {"live_points", live_points},
          {"rigid_inlier_fraction", rigid_inlier_fraction},
          {"rigid_residual_m", number(rigid_residual_m)},
          {"inlier_fraction", inlier_fraction},
          {"residual_m", number(residual_m)},
          {"deformation_rms_m", deformation_rms_m},
          {"deformation_max_m", deformation_max_m},
          {"subject_pixels", subject_pixels},
          {"explained_fraction", number(explained_fraction)},
          {"live_faces", live_faces},
          {"scan_faces", scan_faces},
          {"seconds", seconds}};
}

Mesh ReadScan(const fs::path& scan_dir) {
  if (!fs::is_directory(scan_dir)) Fail("live: scan '", scan_dir.string(), "' is not a directory");
  const fs::path mesh_file = scan_dir / "mesh.ply";
  if (!fs::is_regular_file(mesh_file))
    Fail("live: scan '", scan_dir.string(), "' holds no mesh.ply (a `holocap scan` output)");
  const fs::path report_file = scan_dir / "report.json";
  if (fs::exists(report_file)) {
    Json report;
    try {
      report = Json::parse(ReadFileToString(report_file));
    } catch (const Json::exception&) {
      Fail("live: scan report '", report_file.string(), "' is damaged (not JSON)");
    }
    const Json* summary = report.contains("summary") ? &report["summary"] : nullptr;
    if (summary != nullptr && summary->contains("termination") &&
        (*summary)["termination"].is_string()) {
      const std::string state = (*summary)["termination"].get<std::string>();
      if (state == "DEGENERATE" || state == "FAILURE") {
        Fail("live: scan '", scan_dir.string(), "' ended ", state,
             " (its report.json); scan the subject again");
      }
    }
  }
  Mesh scan = ReadPly(mesh_file);
  if (scan.faces.empty() || scan.vertices.size() < 100)
    Fail("live: scan mesh '", mesh_file.string(), "' has ", scan.vertices.size(), " vertices and ",
         scan.faces.size(), " triangles: nothing to complete a frame with");
  for (const Eigen::Vector3i& face : scan.faces) {
    if ((face.array() < 0).any() || (face.array() >= static_cast<int>(scan.vertices.size())).any())
      Fail("live: scan mesh '", mesh_file.string(), "' is damaged (a face indexes no vertex)");
  }
  for (const Eigen::Vector3f& v : scan.vertices) {
    if (!v.allFinite()) Fail("live: scan mesh '", mesh_file.string(), "' has non-finite vertices");
  }
  return scan;
}

std::optional<ScanAlbedo> ReadScanAlbedo(const fs::path& scan_dir, const Mesh& scan,
                                         std::string* why) {
  auto none = [&](std::string reason) -> std::optional<ScanAlbedo> {
    if (why != nullptr) *why = std::move(reason);
    return std::nullopt;
  };
  const fs::path light_file = scan_dir / "lighting.json";
  const fs::path albedo_file = scan_dir / "albedo.ply";
  if (!fs::is_regular_file(light_file))
    return none("the scan holds no lighting.json (a scan without colour)");
  ScanAlbedo out;
  try {
    out.light = ScanLight::FromJson(Json::parse(ReadFileToString(light_file)));
  } catch (const Json::exception&) {
    Fail("live: scan light '", light_file.string(), "' is damaged (not JSON)");
  } catch (const Error& e) {
    Fail("live: scan light '", light_file.string(), "' is damaged: ", e.what());
  }
  if (!out.light.observed) return none("the scan found no light: " + out.light.why);
  if (!fs::is_regular_file(albedo_file))
    Fail("live: scan '", scan_dir.string(), "' found a light but holds no albedo.ply");
  Mesh albedo = ReadPly(albedo_file);
  if (albedo.vertices.size() != scan.vertices.size() ||
      albedo.colors.size() != scan.vertices.size())
    Fail("live: scan albedo '", albedo_file.string(), "' has ", albedo.vertices.size(),
         " vertices with ", albedo.colors.size(), " colours; the scan has ", scan.vertices.size());
  out.colors = std::move(albedo.colors);
  return out;
}

namespace live {

cv::Mat ThreeChannels(const cv::Mat& frame) {
  if (frame.empty() || frame.channels() == 3) return frame;
  cv::Mat bgr;
  cv::cvtColor(frame, bgr, frame.channels() == 4 ? cv::COLOR_BGRA2BGR : cv::COLOR_GRAY2BGR);
  return bgr;
}

void WriteComposed(const fs::path& recon, int64_t set, const Mesh& mesh, bool glb) {
  char name[32];
  std::snprintf(name, sizeof(name), "%06lld", static_cast<long long>(set));
  WritePly(recon / (std::string(name) + ".ply"), mesh);
  if (glb) {
    TexturedMesh textured;
    textured.mesh = mesh;
    WriteGlb(recon / (std::string(name) + ".glb"), textured);
  }
}

void Conclude(const LiveOptions& options, LiveSummary* summary) {
  for (const LiveFrame& frame : summary->frames) {
    if (frame.state == LiveState::kComposed) ++summary->composed;
    if (frame.state == LiveState::kNoDepth) ++summary->no_depth;
    if (frame.state == LiveState::kRefused) ++summary->refused;
  }
  const int64_t with_depth = summary->composed + summary->refused;
  std::string first_refusal;
  for (const LiveFrame& frame : summary->frames) {
    if (frame.state == LiveState::kRefused) {
      first_refusal = Cat("set ", frame.set, ": ", frame.why);
      break;
    }
  }
  std::string counts = Cat(summary->composed, " of ", summary->frames.size(), " frames composed");
  if (summary->no_depth > 0) counts += Cat(", ", summary->no_depth, " without usable depth");
  if (summary->refused > 0) counts += Cat(", ", summary->refused, " refused");
  if (summary->composed == 0 && summary->refused == 0) {
    summary->End(Termination::kDegenerate, Cat("no frame has usable depth (", counts, ")"));
  } else if (summary->composed == 0 ||
             summary->refused > options.max_refused_fraction * static_cast<double>(with_depth)) {
    summary->End(Termination::kDegenerate, Cat("the scan does not match the live subject (", counts,
                                               "; first ", first_refusal, ")"));
  } else if (summary->refused > 0) {
    // A refused frame has no composition: the output misses it, whatever the others show.
    summary->End(Termination::kDegenerate,
                 Cat(summary->refused, " of ", with_depth,
                     " frames with depth were refused and are missing from the output (", counts,
                     "; first ", first_refusal, ")"));
  } else {
    summary->End(Termination::kSuccess, counts);
  }
}

void RecordFrame(Report* report, const LiveFrame& frame) {
  if (report == nullptr || frame.state != LiveState::kComposed) return;
  report->AddPoint("inlier_fraction", frame.inlier_fraction, frame.set);
  report->AddPoint("residual_m", frame.residual_m, frame.set);
  report->AddPoint("deformation_rms_m", frame.deformation_rms_m, frame.set);
}

Json SummaryMetrics(const LiveSummary& summary) {
  Json frames = Json::array();
  for (const LiveFrame& frame : summary.frames) frames.push_back(frame.ToJson());
  return {{"frames", summary.frames.size()},
          {"composed", summary.composed},
          {"no_depth", summary.no_depth},
          {"refused", summary.refused},
          {"seconds", summary.seconds},
          {"depth_sensor", summary.depth_sensor},
          {"color_sensor", summary.color_sensor},
          {"relit", summary.relit},
          {"relit_why", summary.relit_why},
          {"scan_light", {summary.scan_light.x(), summary.scan_light.y(), summary.scan_light.z()}},
          {"per_frame", frames}};
}

}  // namespace live

LiveSummary LiveTake(const fs::path& take_dir, const TakeSelection& selection,
                     const fs::path& scan_dir, const fs::path& out, const LiveOptions& options,
                     Report* report) {
  options.Check();
  const auto start = std::chrono::steady_clock::now();
  Mesh scan = ReadScan(scan_dir);
  std::string unlit = "relight is off";
  std::optional<ScanAlbedo> albedo =
      options.relight ? ReadScanAlbedo(scan_dir, scan, &unlit) : std::nullopt;
  const Take take = Take::Open(take_dir);
  TakePlan plan = PlanTake(take, selection);
  if (plan.depth_sensors.size() != 1) {
    Fail("live: take '", take_dir.string(), "' has ", plan.depth_sensors.size(),
         " depth sensors; live needs exactly one");
  }
  LiveSummary summary;
  summary.depth_sensor = plan.depth_sensors.front();
  summary.color_sensor = take.stream(summary.depth_sensor).paired_with;
  if (summary.color_sensor.empty() || !plan.cameras.count(summary.color_sensor)) {
    Fail("live: depth sensor '", summary.depth_sensor, "' of take '", take_dir.string(),
         "' has no paired colour camera with a model");
  }
  std::vector<std::string> ignored;
  for (const std::string& name : plan.color_sensors)
    if (name != summary.color_sensor) ignored.push_back(name);
  if (!ignored.empty()) {
    std::string names;
    for (const std::string& name : ignored) names += (names.empty() ? "" : ", ") + name;
    plan.LeaveOut(Cat("colour cameras ", names), Cat("live reads only ", summary.depth_sensor,
                                                     " and its paired ", summary.color_sensor));
  }
  const CameraModel& depth_camera = plan.cameras.at(summary.depth_sensor);
  const CameraModel& color_camera = plan.cameras.at(summary.color_sensor);
  if (report != nullptr) {
    report->options() = options.ToJson();
    report->options()["scan"] = scan_dir.string();
    report->plan() = plan.ToJson();
  }
  summary.relit = albedo.has_value();
  summary.relit_why = albedo ? "" : unlit;
  if (albedo) summary.scan_light = albedo->light.light;
  LiveCompositor compositor(std::move(scan), options, plan.up,
                            plan.floor_m + plan.floor_tolerance_m, std::move(albedo));
  const fs::path recon = out / "recon";
  CreateDirectories(recon);
  Progress progress("live", static_cast<int64_t>(plan.sets.size()));
  for (int64_t set : plan.sets) {
    const FrameSetEntry& entry = take.entry(static_cast<size_t>(set));
    LiveFrame frame;
    frame.set = set;
    if (entry.Find(summary.depth_sensor) == nullptr) {
      frame.state = LiveState::kNoDepth;
      frame.why = "no depth frame in this set";
    } else {
      const cv::Mat depth = take.ReadFrame(static_cast<size_t>(set), summary.depth_sensor);
      cv::Mat color;
      if (entry.Find(summary.color_sensor) != nullptr)
        color = live::ThreeChannels(take.ReadFrame(static_cast<size_t>(set), summary.color_sensor));
      LiveResult result = compositor.Process(set, depth, depth_camera, color, color_camera);
      frame = result.frame;
      if (frame.state == LiveState::kComposed)
        live::WriteComposed(recon, set, result.composed, options.write_glb);
    }
    live::RecordFrame(report, frame);
    summary.frames.push_back(frame);
    progress.Increment(ToString(frame.state));
  }
  progress.Finish();
  live::Conclude(options, &summary);
  summary.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  summary.metrics = live::SummaryMetrics(summary);
  if (report != nullptr) {
    report->metrics() = summary.metrics;
    report->SetSummary(summary);
    report->Write(out / "report.json");
  }
  return summary;
}

}  // namespace holocap
