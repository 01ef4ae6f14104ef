// holocap export web: the manifest, one chunk per stream and frame, the player's files, and the
// export's error against its size measured by decoding every chunk as the player does.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <map>
#include <numeric>
#include <set>

#include "core/error.h"
#include "core/fs.h"
#include "core/output.h"
#include "core/progress.h"
#include "core/take.h"
#include "core/take_plan.h"
#include "playback/playback.h"
#include "playback/web_stream.h"
#include "splat/splat.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;

std::string ChunkName(int64_t set) {
  char name[32];
  std::snprintf(name, sizeof(name), "%06lld.hcc", static_cast<long long>(set));
  return name;
}

nlohmann::json PoseJson(const Pose& pose) {
  nlohmann::json rows = nlohmann::json::array();
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) rows.push_back(pose.matrix()(r, c));
  return rows;
}

nlohmann::json CameraJson(const std::string& name, const CameraModel& camera) {
  nlohmann::json json = {{"name", name},
                         {"width", camera.width()},
                         {"height", camera.height()},
                         {"lensmodel", camera.lensmodel()},
                         {"intrinsics", camera.intrinsics()},
                         {"cam_from_world", PoseJson(camera.cam_from_world())}};
  if (camera.has_core()) {
    const auto& k = camera.intrinsics();
    json["pinhole"] = {k[0], k[1], k[2], k[3]};
  }
  return json;
}

// The frame sets of the reconstruction's meshes (recon/<set>.glb), in order.
std::map<int64_t, fs::path> MeshFiles(const fs::path& recon) {
  std::map<int64_t, fs::path> files;
  if (recon.empty() || !fs::is_directory(recon)) return files;
  for (const auto& entry : fs::directory_iterator(recon)) {
    const fs::path& file = entry.path();
    const std::string stem = file.stem().string();
    if (file.extension() != ".glb" || stem.empty() ||
        !std::all_of(stem.begin(), stem.end(), [](char c) { return c >= '0' && c <= '9'; }))
      continue;
    files[std::stoll(stem)] = file;
  }
  return files;
}

double Psnr(double squared_sum, int64_t count) {
  if (count == 0) return std::numeric_limits<double>::quiet_NaN();
  const double mse = squared_sum / count;
  return mse <= 1e-12 ? 99.0 : 10 * std::log10(1.0 / mse);
}

// Squared colour differences (premultiplied, over black) of two views, and their count.
void AccumulateError(const RenderedView& a, const RenderedView& b, double* squared,
                     int64_t* count) {
  for (int y = 0; y < a.color.rows; ++y) {
    for (int x = 0; x < a.color.cols; ++x) {
      const cv::Vec3f d = a.color.at<cv::Vec3f>(y, x) - b.color.at<cv::Vec3f>(y, x);
      *squared += d.dot(d);
      *count += 3;
    }
  }
}

class SiteWriter {
 public:
  SiteWriter(const fs::path& take_dir, const fs::path& site, const WebExportOptions& options,
             Report* report)
      : take_(Take::Open(take_dir)), site_(site), options_(options), report_(report) {}

  WebExportSummary Run();

 private:
  void PlanCameras();
  void WriteMeshStreams(const std::map<int64_t, fs::path>& files);
  void WriteVolumeStream(const fs::path& model_dir, const std::string& name);
  void WriteSplatStream(const fs::path& model_dir, const std::string& name);
  std::vector<int64_t> ModelFrames(const fs::path& model_dir, int64_t model_frame_count) const;
  // One stream being written: its chunks, their bytes and the squared error of its decoded
  // frames against the uncompressed ones.
  struct StreamTally {
    WebStreamMetrics metrics;
    std::string folder;
    nlohmann::json chunks = nlohmann::json::array();
    uint64_t bytes = 0;
    double squared = 0;
    int64_t count = 0;
  };
  StreamTally BeginStream(const std::string& name, const std::string& kind,
                          const std::string& level) const;
  // Writes timeline frame i's chunk (`entry`: more fields of its manifest entry).
  void WriteChunk(StreamTally* stream, size_t i, const std::string& chunk,
                  const nlohmann::json& entry = nlohmann::json::object()) const;
  void EndFrame(StreamTally* stream) const;  // after the frame's error was accumulated
  void EndStream(StreamTally* stream);       // its metrics and manifest entry
  // A splat frame: a key frame or a delta of the frame before as decoded (`decoded`, which
  // becomes this frame's).
  void WriteSplatChunk(StreamTally* stream, size_t i, const splat::Gaussians& gaussians,
                       const web::SplatEncoding& encoding, bool key,
                       const std::vector<int64_t>& origin, web::SplatCodes* decoded);
  std::vector<CameraModel> ErrorCameras(int64_t frame_index) const;
  void WriteManifest();

  Take take_;
  fs::path site_;
  WebExportOptions options_;
  Report* report_;
  TakePlan plan_;
  std::vector<std::string> camera_names_;
  std::vector<CameraModel> cameras_;
  std::vector<int64_t> sets_;  // the timeline: frame sets shown, in order
  nlohmann::json streams_ = nlohmann::json::array();
  WebExportSummary summary_;
  Eigen::AlignedBox3d bounds_;
  double fps_ = 30;
};

void SiteWriter::PlanCameras() {
  plan_ = PlanTake(take_, options_.take);
  camera_names_ = plan_.color_sensors;
  cameras_ = plan_.Cameras(camera_names_);
  bounds_ = plan_.bounds;
  fps_ = options_.fps > 0 ? options_.fps : (take_.rig().fps > 0 ? take_.rig().fps : 30);
}

std::vector<CameraModel> SiteWriter::ErrorCameras(int64_t frame_index) const {
  std::vector<CameraModel> chosen;
  const int n = static_cast<int>(cameras_.size());
  for (int k = 0; k < std::min(options_.error_cameras, n); ++k) {
    const CameraModel& camera = cameras_[(frame_index + k * std::max(1, n / 2)) % n];
    chosen.push_back(camera.Scaled(static_cast<double>(options_.error_width_px) / camera.width()));
  }
  return chosen;
}

SiteWriter::StreamTally SiteWriter::BeginStream(const std::string& name, const std::string& kind,
                                                const std::string& level) const {
  StreamTally stream;
  stream.metrics = {.name = name + "-" + level, .kind = kind, .quality = level};
  stream.folder = "streams/" + stream.metrics.name;
  CreateDirectories(site_ / stream.folder);
  return stream;
}

void SiteWriter::WriteChunk(StreamTally* stream, size_t i, const std::string& chunk,
                            const nlohmann::json& entry) const {
  WriteFileAtomic(site_ / stream->folder / ChunkName(sets_[i]), chunk);
  nlohmann::json listed = {{"file", ChunkName(sets_[i])}, {"bytes", chunk.size()}};
  listed.update(entry);
  stream->chunks.push_back(listed);
  stream->bytes += chunk.size();
}

void SiteWriter::EndFrame(StreamTally* stream) const {
  ++stream->metrics.frames;
  if (report_ != nullptr)
    report_->AddPoint(stream->metrics.name + ".psnr_db", Psnr(stream->squared, stream->count),
                      stream->metrics.frames);
}

void SiteWriter::EndStream(StreamTally* stream) {
  WebStreamMetrics& metrics = stream->metrics;
  const double frames = static_cast<double>(std::max<int64_t>(metrics.frames, 1));
  metrics.mb_per_frame = metrics.frames > 0 ? stream->bytes / 1e6 / metrics.frames : 0;
  metrics.mean_faces /= frames;
  metrics.mean_gaussians /= frames;
  metrics.mean_stored_gaussians /= frames;
  metrics.mbps = metrics.mb_per_frame * 8 * fps_;
  metrics.psnr_db = Psnr(stream->squared, stream->count);
  summary_.bytes += stream->bytes;
  summary_.streams.push_back(metrics);
  if (report_ != nullptr) report_->metrics()["streams"][metrics.name] = metrics.ToJson();
  streams_.push_back({{"name", metrics.name},
                      {"kind", metrics.kind},
                      {"quality", metrics.quality},
                      {"path", stream->folder},
                      {"chunks", stream->chunks},
                      {"mb_per_frame", metrics.mb_per_frame},
                      {"mbps", metrics.mbps},
                      {"psnr_db", metrics.psnr_db}});
}

void SiteWriter::WriteMeshStreams(const std::map<int64_t, fs::path>& files) {
  for (const std::string& level : options_.qualities) {
    const web::QualityLevel quality = web::QualityByName(level);
    StreamTally stream = BeginStream("mesh", "mesh", level);
    WebStreamMetrics& metrics = stream.metrics;
    for (size_t i = 0; i < sets_.size(); ++i) {
      auto it = files.find(sets_[i]);
      if (it == files.end()) {
        stream.chunks.push_back(nullptr);
        continue;
      }
      const TexturedMeshFrame mesh = ReadTexturedGlb(it->second);
      TexturedMeshFrame decoded;
      double max_error_m = 0;
      const std::string chunk =
          web::EncodeMesh(mesh, static_cast<int64_t>(i), quality, &decoded, &max_error_m)
              .Serialise();
      WriteChunk(&stream, i, chunk);
      metrics.max_position_error_mm = std::max(metrics.max_position_error_mm, 1e3 * max_error_m);
      metrics.mean_faces += static_cast<double>(decoded.faces());
      for (const CameraModel& camera : ErrorCameras(static_cast<int64_t>(i)))
        AccumulateError(RenderTexturedMesh(decoded, camera), RenderTexturedMesh(mesh, camera),
                        &stream.squared, &stream.count);
      EndFrame(&stream);
    }
    EndStream(&stream);
  }
}

std::vector<int64_t> SiteWriter::ModelFrames(const fs::path& model_dir,
                                             int64_t model_frame_count) const {
  const nlohmann::json model_json =
      nlohmann::json::parse(ReadFileToString(model_dir / "model.json"));
  const std::vector<int64_t> model_sets = model_json.value("frame_sets", std::vector<int64_t>{});
  std::vector<int64_t> frames(sets_.size(), 0);  // a static model shows its one frame throughout
  if (model_frame_count <= 1) return frames;
  for (size_t i = 0; i < sets_.size(); ++i) {
    auto it = std::find(model_sets.begin(), model_sets.end(), sets_[i]);
    frames[i] = it == model_sets.end() || it - model_sets.begin() >= model_frame_count
                    ? -1
                    : it - model_sets.begin();
  }
  return frames;
}

void SiteWriter::WriteVolumeStream(const fs::path& model_dir, const std::string& name) {
  auto model = OpenModel(model_dir);
  const std::vector<int64_t> model_frames = ModelFrames(model_dir, model->frame_count());
  ViewRenderOptions render;
  render.step_voxels = options_.step_voxels;
  for (const std::string& level : options_.qualities) {
    const web::QualityLevel quality = web::QualityByName(level);
    StreamTally stream = BeginStream(name, "volume", level);
    for (size_t i = 0; i < sets_.size(); ++i) {
      const int64_t frame = model_frames[i];
      if (frame < 0) {
        stream.chunks.push_back(nullptr);
        continue;
      }
      BakedFrame baked, decoded;
      if (!model->Bake(frame, render, &baked))
        Fail("model ", model_dir.string(), " (", model->method(),
             ") is not a volume: the web stream carries meshes and volumes");
      const std::string chunk = web::EncodeVolume(baked, static_cast<int64_t>(i), quality,
                                                  render.min_transmittance, &decoded)
                                    .Serialise();
      WriteChunk(&stream, i, chunk);
      for (const CameraModel& camera : ErrorCameras(static_cast<int64_t>(i)))
        AccumulateError(web::RenderBakedFrame(decoded, camera, render.min_transmittance),
                        web::RenderBakedFrame(baked, camera, render.min_transmittance),
                        &stream.squared, &stream.count);
      EndFrame(&stream);
    }
    EndStream(&stream);
  }
}

// A splat model's frames, each from its delta's base (the frame before, or frame 0 where a
// per-frame run's segment starts), with where each Gaussian of the frame came from in its base.
class SplatSequence {
 public:
  explicit SplatSequence(const fs::path& dir) : dir_(dir), model_(SplatModel::Load(dir)) {}
  int64_t frames() const { return model_.frames; }
  int sh_degree() const { return model_.gaussians.sh_degree; }
  int64_t Base(int64_t frame) const { return model_.Base(frame); }
  // Frame `frame`: from the last one asked for when that is on its way from frame 0.
  const splat::Gaussians& Frame(int64_t frame) {
    if (frame == current_frame_) return current_;
    current_ = current_frame_ < 0 ? model_.Frame(dir_, frame)
                                  : model_.Frame(dir_, frame, &current_, current_frame_);
    origin_.clear();
    if (frame > 0) origin_ = SplatDeltaOrigins(ReadFileToString(SplatDeltaFile(dir_, frame)));
    current_frame_ = frame;
    return current_;
  }
  // Where the last frame's Gaussians continue its base's (after Frame(k) with k > 0).
  const std::vector<int64_t>& origin() const { return origin_; }

 private:
  fs::path dir_;
  SplatModel model_;
  splat::Gaussians current_;
  int64_t current_frame_ = -1;
  std::vector<int64_t> origin_;
};

RenderedView SplatView(const splat::Gaussians& gaussians, const CameraModel& camera) {
  RenderedView view;
  view.color = RenderSplats(gaussians, camera).color;
  return view;
}

void SiteWriter::WriteSplatStream(const fs::path& model_dir, const std::string& name) {
  SplatSequence sequence(model_dir);
  const std::vector<int64_t> model_frames = ModelFrames(model_dir, sequence.frames());
  for (const std::string& level : options_.qualities) {
    web::SplatEncoding encoding =
        web::SplatEncoding::For(web::QualityByName(level), sequence.sh_degree());
    for (int64_t frame : model_frames)
      if (frame >= 0) encoding.Include(sequence.Frame(frame));
    StreamTally stream = BeginStream(name, "splats", level);
    int64_t since_key = 0, previous_frame = -1;
    web::SplatCodes previous;
    for (size_t i = 0; i < sets_.size(); ++i) {
      const int64_t frame = model_frames[i];
      if (frame < 0) {
        stream.chunks.push_back(nullptr);
        previous_frame = -1;
        continue;
      }
      const splat::Gaussians& gaussians = sequence.Frame(frame);
      // A delta follows the frame before when that shows the same model frame or the base of
      // this frame's delta (where a segment of a per-frame run starts, frame 0: a key frame).
      const bool follows = previous_frame >= 0 &&
                           (frame == previous_frame || sequence.Base(frame) == previous_frame);
      const bool key = !follows || since_key >= options_.splat_key_every;
      std::vector<int64_t> origin;
      if (!key && frame == previous_frame) {
        origin.resize(gaussians.size());
        std::iota(origin.begin(), origin.end(), int64_t{0});
      } else if (!key) {
        origin = sequence.origin();
      }
      WriteSplatChunk(&stream, i, gaussians, encoding, key, origin, &previous);
      since_key = key ? 1 : since_key + 1;
      previous_frame = frame;
    }
    EndStream(&stream);
  }
}

void SiteWriter::WriteSplatChunk(StreamTally* stream, size_t i, const splat::Gaussians& gaussians,
                                 const web::SplatEncoding& encoding, bool key,
                                 const std::vector<int64_t>& origin, web::SplatCodes* decoded) {
  const web::SplatCodes* previous = key ? nullptr : decoded;
  web::SplatCodes codes;
  const std::string chunk =
      web::EncodeSplats(gaussians, static_cast<int64_t>(i), encoding, previous, origin, &codes)
          .Serialise();
  WriteChunk(stream, i, chunk, {{"key", key}});
  // Decoded again as the page decodes it, from the frame before as decoded.
  const web::Chunk parsed = web::ParseChunk(chunk);
  *decoded = web::DecodeSplats(parsed, previous);
  const splat::Gaussians drawn = web::SplatsFromCodes(*decoded, encoding);
  for (const CameraModel& camera : ErrorCameras(static_cast<int64_t>(i)))
    AccumulateError(SplatView(drawn, camera), SplatView(gaussians, camera), &stream->squared,
                    &stream->count);
  WebStreamMetrics& metrics = stream->metrics;
  metrics.key_frames += key;
  metrics.mean_gaussians += static_cast<double>(gaussians.size());
  metrics.mean_stored_gaussians += parsed.header.at("stored").get<double>();
  EndFrame(stream);
}

void SiteWriter::WriteManifest() {
  nlohmann::json frames = nlohmann::json::array();
  const int64_t first_ns = take_.entry(sets_.front()).items.front().timestamp_ns;
  for (size_t i = 0; i < sets_.size(); ++i) {
    const auto& entry = take_.entry(sets_[i]);
    frames.push_back(
        {{"set", sets_[i]}, {"time_s", (entry.items.front().timestamp_ns - first_ns) * 1e-9}});
  }
  nlohmann::json cameras = nlohmann::json::array();
  for (size_t i = 0; i < cameras_.size(); ++i)
    cameras.push_back(CameraJson(camera_names_[i], cameras_[i]));
  const nlohmann::json manifest = {
      {"format", "holocap-stream"},
      {"version", kWebStreamFormatVersion},
      {"take", take_.dir().filename().string()},
      {"fps", fps_},
      {"frames", frames},
      {"bounds",
       {{"min", {bounds_.min().x(), bounds_.min().y(), bounds_.min().z()}},
        {"max", {bounds_.max().x(), bounds_.max().y(), bounds_.max().z()}}}},
      {"up", {plan_.up.x(), plan_.up.y(), plan_.up.z()}},
      {"cameras", cameras},
      {"streams", streams_}};
  WriteFileAtomic(site_ / "manifest.json", manifest.dump(1) + "\n");
}

WebExportSummary SiteWriter::Run() {
  const auto start = std::chrono::steady_clock::now();
  PlanCameras();
  fs::path recon = options_.recon;
  if (recon.empty() && options_.meshes && fs::is_directory(take_.dir() / "recon"))
    recon = take_.dir() / "recon";
  const auto mesh_files = options_.meshes ? MeshFiles(recon) : std::map<int64_t, fs::path>{};
  if (!options_.recon.empty() && mesh_files.empty())
    Fail("--recon ", options_.recon.string(), " holds no meshes (<set>.glb)");
  std::set<int64_t> sets;
  for (const auto& [set, file] : mesh_files) sets.insert(set);
  for (const fs::path& model_dir : options_.models) {
    const nlohmann::json json =
        nlohmann::json::parse(ReadFileToString(model_dir / "model.json"), nullptr, false);
    if (json.is_discarded()) Fail(model_dir.string(), "/model.json does not parse");
    for (int64_t set : json.value("frame_sets", std::vector<int64_t>{})) sets.insert(set);
  }
  for (int64_t set : sets)
    if (set < 0 || set >= static_cast<int64_t>(take_.size()))
      Fail("frame set ", set, " of the meshes or models is not in take ", take_.dir().string());
  sets_.assign(sets.begin(), sets.end());
  if (sets_.empty()) {
    summary_.End(Termination::kDegenerate,
                 "nothing to stream: no reconstruction (" +
                     (recon.empty() ? (take_.dir() / "recon").string() : recon.string()) +
                     ") and no --model");
    return summary_;
  }
  if (report_ != nullptr) {
    report_->plan() = plan_.ToJson();
    report_->plan()["recon"] = recon.string();
    report_->plan()["frame_sets"] = sets_;
  }
  CreateDirectories(site_ / "streams");
  if (!mesh_files.empty()) WriteMeshStreams(mesh_files);
  for (const fs::path& model_dir : options_.models) {
    const std::string kind = OpenModel(model_dir)->method();
    const std::string name = options_.models.size() > 1 ? model_dir.filename().string() : kind;
    if (kind == "splat")
      WriteSplatStream(model_dir, name);
    else
      WriteVolumeStream(model_dir, name);
  }
  WriteManifest();
  for (const auto& [path, bytes] : web::PlayerFiles()) {
    CreateDirectories((site_ / path).parent_path());
    WriteFileAtomic(site_ / path, bytes);
  }
  summary_.frames = static_cast<int64_t>(sets_.size());
  summary_.seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::string message = std::to_string(sets_.size()) + " frame(s), " +
                        std::to_string(summary_.streams.size()) + " stream(s)";
  summary_.End(Termination::kSuccess, message);
  return summary_;
}

}  // namespace

void WebExportOptions::Check() const {
  if (qualities.empty()) Fail("--quality needs at least one level");
  for (const auto& q : qualities) web::QualityByName(q);
  if (!(fps >= 0)) Fail("--fps must be >= 0, got ", fps);
  if (!(step_voxels > 0)) Fail("--step must be positive, got ", step_voxels);
  if (error_width_px < 8) Fail("error_width_px must be at least 8, got ", error_width_px);
  if (error_cameras < 0) Fail("error_cameras must be >= 0, got ", error_cameras);
  if (splat_key_every < 1) Fail("--key-every must be at least 1, got ", splat_key_every);
  take.Check();
}

nlohmann::json WebExportOptions::ToJson() const {
  std::vector<std::string> model_dirs;
  for (const auto& m : models) model_dirs.push_back(m.string());
  return {{"qualities", qualities},
          {"recon", recon.string()},
          {"meshes", meshes},
          {"models", model_dirs},
          {"fps", fps},
          {"step_voxels", step_voxels},
          {"error_width_px", error_width_px},
          {"error_cameras", error_cameras},
          {"splat_key_every", splat_key_every},
          {"take", take.ToJson()},
          {"overwrite", overwrite}};
}

nlohmann::json WebStreamMetrics::ToJson() const {
  nlohmann::json json = {
      {"kind", kind},
      {"quality", quality},
      {"frames", frames},
      {"mb_per_frame", mb_per_frame},
      {"mbps", mbps},
      {"psnr_db", std::isfinite(psnr_db) ? nlohmann::json(psnr_db) : nlohmann::json()},
      {"max_position_error_mm", max_position_error_mm},
      {"mean_faces", mean_faces}};
  if (kind == "splats") {
    json["mean_gaussians"] = mean_gaussians;
    json["mean_stored_gaussians"] = mean_stored_gaussians;
    json["key_frames"] = key_frames;
  }
  return json;
}

WebExportSummary ExportWebSite(const fs::path& take_dir, const fs::path& site_dir,
                               const WebExportOptions& options, Report* report) {
  options.Check();
  OutputRequest request{"export web", options.overwrite, {take_dir}};
  for (const auto& model : options.models) request.inputs.push_back(model);
  if (!options.recon.empty()) request.inputs.push_back(options.recon);
  const OutputDirectory claimed = OutputDirectory::Claim(site_dir, request);
  if (report != nullptr) {
    report->options() = options.ToJson();
    report->SetFailureDestination(site_dir / "report.json");
  }
  SiteWriter writer(take_dir, site_dir, options, report);
  WebExportSummary summary = writer.Run();
  if (report != nullptr) {
    report->metrics()["frames"] = summary.frames;
    report->metrics()["bytes"] = summary.bytes;
    report->metrics()["seconds"] = summary.seconds;
    report->SetSummary(summary);
    report->Write(site_dir / "report.json");
  }
  return summary;
}

namespace {

cv::Mat UnitFloat(const cv::Mat& image) {
  cv::Mat out;
  const double scale = image.depth() == CV_8U    ? 1.0 / 255
                       : image.depth() == CV_16U ? 1.0 / 65535
                                                 : 1;
  image.convertTo(out, CV_32F, scale);
  if (out.channels() != 3) Fail("PSNR inside the box needs 3-channel images");
  return cv::min(cv::max(out, 0.0), 1.0);
}

}  // namespace

double PsnrInsideBoxDb(const cv::Mat& picture, const cv::Mat& reference, const CameraModel& camera,
                       const Eigen::AlignedBox3d& box, int64_t* pixels) {
  if (picture.size() != reference.size())
    Fail("PSNR inside the box: pictures of ", picture.cols, "x", picture.rows, " and ",
         reference.cols, "x", reference.rows);
  double x0 = 1e9, y0 = 1e9, x1 = -1e9, y1 = -1e9;
  for (int k = 0; k < 8; ++k) {
    const Eigen::Vector3d corner = box.corner(static_cast<Eigen::AlignedBox3d::CornerType>(k));
    Eigen::Vector2d p;
    camera.ProjectWorld(corner, &p);
    x0 = std::min(x0, p.x()), y0 = std::min(y0, p.y());
    x1 = std::max(x1, p.x()), y1 = std::max(y1, p.y());
  }
  const cv::Mat a = UnitFloat(picture), b = UnitFloat(reference);
  double squared = 0;
  int64_t count = 0;
  for (int y = std::max(0, static_cast<int>(y0)); y <= std::min(a.rows - 1, static_cast<int>(y1));
       ++y) {
    for (int x = std::max(0, static_cast<int>(x0)); x <= std::min(a.cols - 1, static_cast<int>(x1));
         ++x) {
      const cv::Vec3f d = a.at<cv::Vec3f>(y, x) - b.at<cv::Vec3f>(y, x);
      squared += d.dot(d);
      count += 3;
    }
  }
  if (pixels != nullptr) *pixels = count / 3;
  return Psnr(squared, count);
}

bool IsWebSite(const fs::path& dir, std::string* why) {
  const fs::path manifest = dir / "manifest.json";
  if (!fs::is_regular_file(manifest) || !fs::is_regular_file(dir / "index.html")) {
    *why = "'" + dir.string() + "' is not a site made by holocap export web (no manifest.json " +
           "and index.html)";
    return false;
  }
  const nlohmann::json json = nlohmann::json::parse(ReadFileToString(manifest), nullptr, false);
  if (json.is_discarded() || json.value("format", "") != "holocap-stream") {
    *why = manifest.string() + " is not a holocap stream manifest";
    return false;
  }
  const int version = json.value("version", -1);
  if (version < kOldestWebStreamFormatVersion || version > kWebStreamFormatVersion) {
    *why = manifest.string() + " is stream format version " +
           json.value("version", nlohmann::json()).dump() + "; this holocap plays versions " +
           std::to_string(kOldestWebStreamFormatVersion) + " to " +
           std::to_string(kWebStreamFormatVersion);
    return false;
  }
  return true;
}

}  // namespace holocap
