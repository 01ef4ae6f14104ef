// holocap export web: the manifest, one chunk per stream and frame, the player's files, and the
// export's error against its size measured by decoding every chunk as the player does; a
// per-frame run whose tasks write groups of frames (playback.h ExportWebSite).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <map>
#include <memory>
#include <numeric>
#include <opencv2/imgcodecs.hpp>
#include <optional>
#include <set>
#include <tuple>

#include "avatar/camera_score.h"
#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/output.h"
#include "core/progress.h"
#include "core/take.h"
#include "core/take_plan.h"
#include "playback/internal/web_stream.h"
#include "playback/playback.h"
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

constexpr const char* kCommand = "export web";

// One stream of the site as the run's plan lists it.
struct SiteStream {
  std::string name;         // "mesh-medium", "splat-high"
  std::string kind;         // "mesh" | "volume" | "splats"
  std::string quality;      // the level
  std::string folder;       // its chunks, relative to the site
  int source = -1;          // -1: the meshes; else its model's index in options.models
  nlohmann::json encoding;  // splats: the stream's quantisation over the whole timeline
  // The capture cameras its source never saw (scored against), or why there are none.
  std::vector<std::string> heldout;
  std::string unscored;
  // Per capture camera, the picture behind the subject (relative to the plan folder and to the
  // site): the model's backgrounds or the take's clean plate, in the camera's pinhole core.
  nlohmann::json backgrounds = nlohmann::json::object();
  std::string level;       // the quality level (`quality` with its budget, if any)
  double budget_mbps = 0;  // splats: every segment's budget (0: none)

  nlohmann::json ToJson() const {
    return {{"name", name},
            {"kind", kind},
            {"quality", quality},
            {"path", folder},
            {"source", source},
            {"encoding", encoding},
            {"heldout", heldout},
            {"unscored", unscored},
            {"backgrounds", backgrounds},
            {"level", level},
            {"budget_mbps", budget_mbps}};
  }
  static SiteStream FromJson(const nlohmann::json& json) {
    return {json.at("name").get<std::string>(),
            json.at("kind").get<std::string>(),
            json.at("quality").get<std::string>(),
            json.at("path").get<std::string>(),
            json.at("source").get<int>(),
            json.at("encoding"),
            json.value("heldout", std::vector<std::string>{}),
            json.value("unscored", std::string()),
            json.value("backgrounds", nlohmann::json::object()),
            json.value("level", json.at("quality").get<std::string>()),
            json.value("budget_mbps", 0.0)};
  }
};

// The capture cameras a source was never trained on nor reconstructed from: its plan's
// "heldout" (a model's model.json, a reconstruction's report.json).
std::vector<std::string> HeldOutOf(const fs::path& file) {
  std::error_code ec;
  if (!fs::exists(file, ec)) return {};
  const nlohmann::json json = nlohmann::json::parse(ReadFileToString(file), nullptr, false);
  if (json.is_discarded() || !json.contains("plan") || !json["plan"].is_object()) return {};
  const nlohmann::json& heldout = json["plan"].value("heldout", nlohmann::json::array());
  std::vector<std::string> names;
  if (heldout.is_array())
    for (const auto& name : heldout)
      if (name.is_string()) names.push_back(name.get<std::string>());
  return names;
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
  const SplatRender render = RenderSplats(gaussians, camera);
  RenderedView view;
  view.color = render.color;
  view.alpha = render.alpha;
  return view;
}

// One hash of each file's name (relative to `root`) and bytes: what the run reads of an input.
std::string HashInputFiles(const fs::path& root, const std::vector<fs::path>& files) {
  std::string hashes;
  for (const fs::path& file : files)
    hashes += Cat(fs::relative(file, root).string(), " ", HashBytes(ReadFileToString(file)), "\n");
  return HashBytes(hashes);
}

// Every file of a model's folder but its reports (a merge rewrites them, not the model).
std::vector<fs::path> ModelFiles(const fs::path& dir) {
  std::vector<fs::path> files;
  for (const auto& entry : fs::recursive_directory_iterator(dir))
    if (entry.is_regular_file() && entry.path().filename() != "report.json")
      files.push_back(entry.path());
  std::sort(files.begin(), files.end());
  return files;
}

bool SelectsFrames(const TakeSelection& selection) {
  return !selection.frame_list.empty() || selection.first_frame != 0 || selection.last_frame >= 0;
}

// One task of an export web run (see ExportWebSite in playback.h): the plan, then the task's
// groups, each written or skipped as complete.
class SiteWriter {
 public:
  SiteWriter(const fs::path& take_dir, const fs::path& site, const WebExportOptions& options,
             Report* report)
      : take_(Take::Open(take_dir)), site_(site), options_(options), report_(report) {}

  WebExportSummary Run();

 private:
  void PlanCameras();
  bool ChooseTimeline();  // false (the summary DEGENERATE) when there is nothing to stream
  nlohmann::json ReportPlan() const;
  nlohmann::json Identity() const;
  void PlanSite();
  nlohmann::json MakePlan(std::vector<std::string>* files);
  std::vector<SiteStream> ListStreams() const;
  // Writes the stream's backgrounds into the plan folder (once per source) and lists them.
  void PlanBackgrounds(SiteStream* stream, std::vector<std::string>* files);
  // Timeline frame i of a stream against its held-out cameras' images (on every
  // camera_score_every-th frame): the native render of its source (`native`, the same for every
  // level), the decoded chunk drawn as the page draws it (`streamed`) and the background alone,
  // each over the stream's background, inside the subject's silhouette. Adds "camera" to `tally`.
  using ViewOf = std::function<RenderedView(const CameraModel&)>;
  void ScoreAgainstCameras(const SiteStream& stream, size_t i, const ViewOf& native,
                           const ViewOf& streamed, nlohmann::json* tally);
  nlohmann::json ManifestHead() const;
  web::SplatEncoding EncodingOver(int source, const std::string& level);
  void StartRecords();
  void WriteGroup(size_t group);
  // One group's frames [begin, end) of a stream: per frame, its manifest entry ("chunk", null
  // where the stream has no frame) and what the stream's metrics sum.
  nlohmann::json WriteStreamFrames(const SiteStream& stream, size_t begin, size_t end,
                                   std::vector<std::string>* outputs);
  nlohmann::json WriteMeshFrame(const SiteStream& stream, const web::QualityLevel& quality,
                                size_t i, std::vector<std::string>* outputs);
  nlohmann::json WriteVolumeFrame(const SiteStream& stream, const web::QualityLevel& quality,
                                  size_t i, std::vector<std::string>* outputs);
  nlohmann::json WriteSplatFrames(const SiteStream& stream, size_t begin, size_t end,
                                  std::vector<std::string>* outputs);
  // Under a budget (--splat-mbps), the encoding of each of a group's splat chunks [begin, end):
  // per segment (a key frame and its deltas) the finest rung (web::SplatDeltaRung) at which the
  // segment fits its frames' share of the budget.
  std::vector<web::SplatEncoding> BudgetedSplatEncodings(const SiteStream& stream, size_t begin,
                                                         size_t end);
  // A splat frame: a key frame or a delta of the frame before as decoded (`decoded`, which
  // becomes this frame's).
  // The model frame shown at timeline frame i of a group starting at `begin` (-1: none) and,
  // for a delta, where its Gaussians come from in the frame before (empty: a key frame).
  int64_t SplatChunkOf(int source, size_t i, size_t begin, std::vector<int64_t>* origin);
  nlohmann::json WriteSplatChunk(const SiteStream& stream, size_t i,
                                 const splat::Gaussians& gaussians,
                                 const web::SplatEncoding& encoding, bool key,
                                 const std::vector<int64_t>& origin, web::SplatCodes* decoded,
                                 std::vector<std::string>* outputs);
  // Writes timeline frame i's chunk durably (`entry`: more fields of its manifest entry).
  nlohmann::json WriteChunk(const SiteStream& stream, size_t i, const std::string& chunk,
                            const nlohmann::json& entry, std::vector<std::string>* outputs) const;
  std::vector<CameraModel> ErrorCameras(int64_t frame_index) const;
  // Per timeline frame, the frame of model `source` it shows (-1: none).
  const std::vector<int64_t>& FramesOf(int source);
  AvatarModel& VolumeModel(int source);
  SplatSequence& Sequence(int source);
  WebExportSummary FinishTask(size_t groups);

  Take take_;
  fs::path site_;
  WebExportOptions options_;
  Report* report_;
  TakePlan plan_;
  std::vector<std::string> camera_names_;
  std::vector<CameraModel> cameras_;
  fs::path recon_;
  std::map<int64_t, fs::path> mesh_files_;
  std::vector<int64_t> sets_;  // the timeline: frame sets shown, in order
  Box bounds_ = Box::Empty();
  double fps_ = 30;
  nlohmann::json identity_;
  std::vector<SiteStream> streams_;
  std::string plan_origin_;
  std::vector<int64_t> group_keys_;  // each group's first frame set (its record's name)
  std::optional<FrameRecords> records_;
  const std::string task_ = DescribeTask(options_.tasks.shard);
  std::map<int, std::vector<int64_t>> model_frames_;
  std::map<int, std::unique_ptr<AvatarModel>> volumes_;
  std::map<int, std::unique_ptr<SplatSequence>> sequences_;
  std::map<std::pair<size_t, std::string>, CameraTruth> truths_;  // by timeline frame, camera
  std::map<std::string, cv::Mat> background_images_;              // by path in the plan folder
  // Per source, timeline frame and camera: the native render's and the background's errors.
  std::map<std::tuple<int, size_t, std::string>, std::pair<SquaredError, SquaredError>> natives_;
  bool manifest_withdrawn_ = false;
  int64_t written_ = 0, skipped_ = 0;
  WebExportSummary summary_;
};

void SiteWriter::PlanCameras() {
  plan_ = PlanTake(take_, options_.take);
  camera_names_ = plan_.color_sensors;
  cameras_ = plan_.Cameras(camera_names_);
  bounds_ = plan_.bounds;
  fps_ = options_.fps > 0 ? options_.fps : (take_.rig().fps > 0 ? take_.rig().fps : 30);
}

bool SiteWriter::ChooseTimeline() {
  recon_ = options_.recon;
  if (recon_.empty() && options_.meshes && fs::is_directory(take_.dir() / "recon"))
    recon_ = take_.dir() / "recon";
  if (options_.meshes) mesh_files_ = MeshFiles(recon_);
  if (!options_.recon.empty() && mesh_files_.empty())
    Fail("--recon ", options_.recon.string(), " holds no meshes (<set>.glb)");
  std::set<int64_t> sets;
  for (const auto& [set, file] : mesh_files_) sets.insert(set);
  for (const fs::path& model_dir : options_.models) {
    const nlohmann::json json =
        nlohmann::json::parse(ReadFileToString(model_dir / "model.json"), nullptr, false);
    if (json.is_discarded()) Fail(model_dir.string(), "/model.json does not parse");
    for (int64_t set : json.value("frame_sets", std::vector<int64_t>{})) sets.insert(set);
  }
  for (int64_t set : sets)
    if (set < 0 || set >= static_cast<int64_t>(take_.size()))
      Fail("frame set ", set, " of the meshes or models is not in take ", take_.dir().string());
  const size_t available = sets.size();
  if (SelectsFrames(options_.take)) {
    // --frames: the timeline is the selected sets that the meshes or models show.
    const std::set<int64_t> selected(plan_.sets.begin(), plan_.sets.end());
    std::erase_if(sets, [&](int64_t set) { return !selected.contains(set); });
    std::erase_if(mesh_files_, [&](const auto& file) { return !sets.contains(file.first); });
  }
  sets_.assign(sets.begin(), sets.end());
  if (sets_.empty()) {
    summary_.End(Termination::kDegenerate,
                 available > 0
                     ? Cat("nothing to stream: --frames selects none of the ", available,
                           " frame sets of the meshes and models")
                     : "nothing to stream: no reconstruction (" +
                           (recon_.empty() ? (take_.dir() / "recon").string() : recon_.string()) +
                           ") and no --model");
    return false;
  }
  if (report_ != nullptr) report_->plan() = ReportPlan();
  return true;
}

nlohmann::json SiteWriter::ReportPlan() const {
  nlohmann::json plan = plan_.ToJson();
  plan["recon"] = recon_.string();
  plan["frame_sets"] = sets_;
  plan["group_frames"] = options_.splat_key_every;
  return plan;
}

// Everything that decides the site's bytes: the options (less how the task runs), the take's
// recording and cameras, and every input file's bytes.
nlohmann::json SiteWriter::Identity() const {
  nlohmann::json options = options_.ToJson();
  options.erase("tasks");
  options.erase("overwrite");
  std::string recording = ReadFileToString(take_.dir() / "take.json");
  std::error_code ec;
  if (fs::exists(take_.dir() / "index.jsonl", ec))
    recording += ReadFileToString(take_.dir() / "index.jsonl");
  std::string cameras;
  for (size_t i = 0; i < cameras_.size(); ++i) cameras += camera_names_[i] + cameras_[i].ToString();
  std::vector<fs::path> meshes;
  for (const auto& [set, file] : mesh_files_) meshes.push_back(file);
  nlohmann::json models = nlohmann::json::array();
  for (const fs::path& dir : options_.models)
    models.push_back(HashInputFiles(dir, ModelFiles(dir)));
  return {{"options", options},
          {"recording", HashBytes(recording)},
          {"cameras", HashBytes(cameras)},
          {"meshes", HashInputFiles(recon_, meshes)},
          {"models", models}};
}

// The run's plan, made once for all its tasks (core/frame_tasks.h PlanOnce): the splat streams'
// quantisation decodes every frame of their models, which a task of a few groups would
// otherwise pay for the whole timeline.
void SiteWriter::PlanSite() {
  const StoredPlan stored =
      PlanOnce(site_, kCommand, HashBytes(identity_.dump()), task_,
               [this](std::vector<std::string>* files) { return MakePlan(files); });
  for (const auto& stream : stored.plan.at("streams"))
    streams_.push_back(SiteStream::FromJson(stream));
  plan_origin_ = stored.made ? Cat("made by this task (", stored.why, ")")
                             : Cat("read from ", (site_ / kPlanDir).string(), " (made by ",
                                   stored.made_by, ")");
  std::printf("export web: %zu frame(s) in groups of %d, %zu stream(s); plan: %s\n", sets_.size(),
              options_.splat_key_every, streams_.size(), plan_origin_.c_str());
}

nlohmann::json SiteWriter::MakePlan(std::vector<std::string>* files) {
  nlohmann::json streams = nlohmann::json::array();
  for (SiteStream& stream : ListStreams()) {
    if (stream.kind == "splats")
      stream.encoding = EncodingOver(stream.source, stream.level).ToJson();
    PlanBackgrounds(&stream, files);
    streams.push_back(stream.ToJson());
  }
  return {{"head", ManifestHead()},
          {"streams", streams},
          {"group_frames", options_.splat_key_every},
          {"sets", sets_}};
}

std::vector<SiteStream> SiteWriter::ListStreams() const {
  std::vector<SiteStream> streams;
  const bool silhouettes = take_.has_ground_truth() || plan_.has_clean_plate();
  // `described_by`: the source's model.json or report.json, whose plan names its held-out cameras.
  auto add = [&](const std::string& name, const std::string& kind, int source,
                 const fs::path& described_by) {
    std::vector<std::string> heldout;
    for (const std::string& camera : HeldOutOf(described_by))
      if (std::find(camera_names_.begin(), camera_names_.end(), camera) != camera_names_.end())
        heldout.push_back(camera);
    std::string unscored;
    if (heldout.empty()) {
      unscored = Cat("no capture camera of the take was held out of ", described_by.string());
    } else if (!silhouettes) {
      unscored = "the take has neither true silhouettes (gt/) nor a clean plate to find them";
      heldout.clear();
    }
    // Splats: a stream per level and budget (one budget: the level's name alone).
    std::vector<double> budgets = {0};
    if (kind == "splats" && !options_.splat_mbps.empty()) budgets = options_.splat_mbps;
    for (const std::string& level : options_.qualities) {
      for (const double budget : budgets) {
        const std::string quality =
            budgets.size() > 1 && budget > 0 ? Cat(level, "-", budget, "mbps") : level;
        const std::string stream = Cat(name, "-", quality);
        streams.push_back({stream, kind, quality, "streams/" + stream, source, nullptr, heldout,
                           unscored, nlohmann::json::object(), level, budget});
      }
    }
  };
  if (!mesh_files_.empty()) add("mesh", "mesh", -1, recon_ / "report.json");
  for (size_t m = 0; m < options_.models.size(); ++m) {
    const fs::path& model_dir = options_.models[m];
    const std::string kind = OpenModel(model_dir)->method();
    const std::string name = options_.models.size() > 1 ? model_dir.filename().string() : kind;
    add(name, kind == "splat" ? "splats" : "volume", static_cast<int>(m), model_dir / "model.json");
  }
  return streams;
}

void SiteWriter::PlanBackgrounds(SiteStream* stream, std::vector<std::string>* files) {
  const fs::path learned =
      stream->source >= 0 ? options_.models[stream->source] / "backgrounds" : fs::path();
  const bool has_learned = !learned.empty() && fs::is_directory(learned);
  if (!has_learned && !plan_.has_clean_plate()) return;  // black behind the subject
  const std::string label =
      has_learned ? stream->name.substr(0, stream->name.rfind('-')) : std::string("plate");
  for (size_t c = 0; c < camera_names_.size(); ++c) {
    const std::string& name = camera_names_[c];
    const std::string file = Cat("backgrounds/", label, "/", name, ".png");
    if (std::find(files->begin(), files->end(), file) == files->end()) {
      cv::Mat image;
      if (has_learned) {
        const fs::path source = learned / (name + ".png");
        if (!fs::exists(source)) continue;
        image = cv::imread(source.string(), cv::IMREAD_COLOR);
        if (image.empty()) Fail("cannot read the background ", source.string());
      } else {
        image = take_.ReadFrame(static_cast<size_t>(plan_.plate_set()), name);
      }
      std::vector<uint8_t> png;
      cv::imencode(".png", BackgroundInPinhole(image, cameras_[c]), png);
      CreateDirectories((site_ / kPlanDir / file).parent_path());
      WriteFileAtomic(site_ / kPlanDir / file,
                      std::string_view(reinterpret_cast<char*>(png.data()), png.size()),
                      /*durable=*/true);
      files->push_back(file);
    }
    stream->backgrounds[name] = file;
  }
}

void SiteWriter::ScoreAgainstCameras(const SiteStream& stream, size_t i, const ViewOf& native,
                                     const ViewOf& streamed, nlohmann::json* tally) {
  if (stream.heldout.empty() || i % static_cast<size_t>(options_.camera_score_every) != 0) return;
  SquaredError native_sum, streamed_sum, background_sum;
  std::vector<std::string> scored;
  for (const std::string& name : stream.heldout) {
    const size_t c = static_cast<size_t>(
        std::find(camera_names_.begin(), camera_names_.end(), name) - camera_names_.begin());
    auto [truth, read] = truths_.try_emplace({i, name});
    if (read) {
      truth->second = ReadCameraTruth(take_, name, cameras_[c], sets_[i],
                                      plan_.has_clean_plate() ? plan_.plate_set() : -1);
    }
    const CameraTruth& seen = truth->second;
    if (seen.subject.empty()) continue;
    cv::Mat background;
    if (stream.backgrounds.contains(name)) {
      const std::string file = stream.backgrounds[name].get<std::string>();
      cv::Mat& image = background_images_[file];
      if (image.empty()) image = cv::imread((site_ / kPlanDir / file).string(), cv::IMREAD_COLOR);
      if (image.empty())
        Fail("cannot read the plan's background ", (site_ / kPlanDir / file).string());
      background = image;
    }
    auto [cached, fresh] = natives_.try_emplace({stream.source, i, name});
    if (fresh) {
      cached->second.first.Add(OverBackground(native(seen.pinhole), background), seen.image,
                               seen.subject);
      const cv::Mat behind =
          background.empty() ? cv::Mat(seen.image.size(), CV_8UC3, cv::Scalar::all(0)) : background;
      cached->second.second.Add(behind, seen.image, seen.subject);
    }
    streamed_sum.Add(OverBackground(streamed(seen.pinhole), background), seen.image, seen.subject);
    native_sum.squared += cached->second.first.squared;
    native_sum.count += cached->second.first.count;
    background_sum.squared += cached->second.second.squared;
    background_sum.count += cached->second.second.count;
    scored.push_back(name);
  }
  if (scored.empty()) return;
  (*tally)["camera"] = {{"cameras", scored},
                        {"count", native_sum.count},
                        {"native", native_sum.squared},
                        {"streamed", streamed_sum.squared},
                        {"background", background_sum.squared}};
}

// The manifest but its streams.
nlohmann::json SiteWriter::ManifestHead() const {
  nlohmann::json frames = nlohmann::json::array();
  const int64_t first_ns = take_.entry(sets_.front()).items.front().timestamp_ns;
  for (int64_t set : sets_) {
    const auto& entry = take_.entry(set);
    frames.push_back(
        {{"set", set}, {"time_s", (entry.items.front().timestamp_ns - first_ns) * 1e-9}});
  }
  nlohmann::json cameras = nlohmann::json::array();
  for (size_t i = 0; i < cameras_.size(); ++i)
    cameras.push_back(CameraJson(camera_names_[i], cameras_[i]));
  return {{"format", "holocap-stream"},
          {"version", kWebStreamFormatVersion},
          {"take", take_.dir().filename().string()},
          {"fps", fps_},
          {"frames", frames},
          {"bounds",
           {{"min", {bounds_.min.x(), bounds_.min.y(), bounds_.min.z()}},
            {"max", {bounds_.max.x(), bounds_.max.y(), bounds_.max.z()}}}},
          {"up", {plan_.up.x(), plan_.up.y(), plan_.up.z()}},
          {"cameras", cameras}};
}

// A splat stream's quantisation: the same ranges for every chunk of the stream, over every
// frame the timeline shows (under a budget, each chunk's rung of it: BudgetedSplatEncodings).
web::SplatEncoding SiteWriter::EncodingOver(int source, const std::string& level) {
  SplatSequence& sequence = Sequence(source);
  web::SplatEncoding encoding =
      web::SplatEncoding::For(web::QualityByName(level), sequence.sh_degree());
  for (int64_t frame : FramesOf(source))
    if (frame >= 0) encoding.Include(sequence.Frame(frame));
  return encoding;
}

void SiteWriter::StartRecords() {
  for (size_t i = 0; i < sets_.size(); i += static_cast<size_t>(options_.splat_key_every))
    group_keys_.push_back(sets_[i]);
  records_.emplace(site_, kCommand, identity_, group_keys_);
  for (const SiteStream& stream : streams_) CreateDirectories(site_ / stream.folder);
  nlohmann::json options = options_.ToJson();
  options.erase("tasks");
  options.erase("overwrite");
  options["take_dir"] = take_.dir().string();
  options["out"] = site_.string();
  records_->WriteRun({{"options", options}, {"plan", ReportPlan()}});
}

void SiteWriter::WriteGroup(size_t group) {
  if (!manifest_withdrawn_) {
    std::error_code ec;
    fs::remove(site_ / "manifest.json", ec);
    manifest_withdrawn_ = true;
  }
  const size_t frames = static_cast<size_t>(options_.splat_key_every);
  const size_t begin = group * frames, end = std::min(sets_.size(), begin + frames);
  const double started = UnixSeconds();
  nlohmann::json streams = nlohmann::json::object();
  std::vector<std::string> outputs;
  for (const SiteStream& stream : streams_)
    streams[stream.name] = WriteStreamFrames(stream, begin, end, &outputs);
  // Its termination and seconds are what `submit status` shows (a group whose chunks are all
  // written succeeded).
  const nlohmann::json result = {
      {"termination", ToString(Termination::kSuccess)},
      {"seconds", UnixSeconds() - started},
      {"group", group},
      {"sets", std::vector<int64_t>(sets_.begin() + static_cast<std::ptrdiff_t>(begin),
                                    sets_.begin() + static_cast<std::ptrdiff_t>(end))},
      {"streams", streams}};
  records_->Record(group_keys_[group], result, outputs, started, task_);
}

nlohmann::json SiteWriter::WriteStreamFrames(const SiteStream& stream, size_t begin, size_t end,
                                             std::vector<std::string>* outputs) {
  if (stream.kind == "splats") return WriteSplatFrames(stream, begin, end, outputs);
  const web::QualityLevel quality = web::QualityByName(stream.quality);
  nlohmann::json frames = nlohmann::json::array();
  for (size_t i = begin; i < end; ++i) {
    frames.push_back(stream.kind == "mesh" ? WriteMeshFrame(stream, quality, i, outputs)
                                           : WriteVolumeFrame(stream, quality, i, outputs));
  }
  return frames;
}

nlohmann::json SiteWriter::WriteChunk(const SiteStream& stream, size_t i, const std::string& chunk,
                                      const nlohmann::json& entry,
                                      std::vector<std::string>* outputs) const {
  outputs->push_back(stream.folder + "/" + ChunkName(sets_[i]));
  WriteFileAtomic(site_ / outputs->back(), chunk, /*durable=*/true);
  nlohmann::json listed = {{"file", ChunkName(sets_[i])}, {"bytes", chunk.size()}};
  listed.update(entry);
  return {{"chunk", listed}};
}

std::vector<CameraModel> SiteWriter::ErrorCameras(int64_t frame_index) const {
  std::vector<CameraModel> chosen;
  const int n = static_cast<int>(cameras_.size());
  for (int k = 0; k < std::min(options_.error_cameras, n); ++k) {
    const CameraModel& camera =
        cameras_[(frame_index + static_cast<int64_t>(k) * std::max(1, n / 2)) % n];
    chosen.push_back(camera.Scaled(static_cast<double>(options_.error_width_px) / camera.width()));
  }
  return chosen;
}

nlohmann::json SiteWriter::WriteMeshFrame(const SiteStream& stream,
                                          const web::QualityLevel& quality, size_t i,
                                          std::vector<std::string>* outputs) {
  auto it = mesh_files_.find(sets_[i]);
  if (it == mesh_files_.end()) return {{"chunk", nullptr}};
  const TexturedMeshFrame mesh = ReadTexturedGlb(it->second);
  TexturedMeshFrame decoded;
  double max_error_m = 0;
  const std::string chunk =
      web::EncodeMesh(mesh, static_cast<int64_t>(i), quality, &decoded, &max_error_m).Serialise();
  nlohmann::json tally = WriteChunk(stream, i, chunk, nlohmann::json::object(), outputs);
  double squared = 0;
  int64_t count = 0;
  for (const CameraModel& camera : ErrorCameras(static_cast<int64_t>(i)))
    AccumulateError(RenderTexturedMesh(decoded, camera), RenderTexturedMesh(mesh, camera), &squared,
                    &count);
  tally.update({{"squared", squared},
                {"count", count},
                {"faces", decoded.faces()},
                {"max_position_error_mm", 1e3 * max_error_m}});
  ScoreAgainstCameras(
      stream, i, [&](const CameraModel& camera) { return RenderTexturedMesh(mesh, camera); },
      [&](const CameraModel& camera) { return RenderTexturedMesh(decoded, camera); }, &tally);
  return tally;
}

nlohmann::json SiteWriter::WriteVolumeFrame(const SiteStream& stream,
                                            const web::QualityLevel& quality, size_t i,
                                            std::vector<std::string>* outputs) {
  const int64_t frame = FramesOf(stream.source)[i];
  if (frame < 0) return {{"chunk", nullptr}};
  ViewRenderOptions render;
  render.step_voxels = options_.step_voxels;
  BakedFrame baked, decoded;
  if (!VolumeModel(stream.source).Bake(frame, render, &baked))
    Fail("model ", options_.models[stream.source].string(), " (",
         VolumeModel(stream.source).method(),
         ") is not a volume: the web stream carries meshes and volumes");
  const std::string chunk =
      web::EncodeVolume(baked, static_cast<int64_t>(i), quality, render.min_transmittance, &decoded)
          .Serialise();
  nlohmann::json tally = WriteChunk(stream, i, chunk, nlohmann::json::object(), outputs);
  double squared = 0;
  int64_t count = 0;
  for (const CameraModel& camera : ErrorCameras(static_cast<int64_t>(i)))
    AccumulateError(web::RenderBakedFrame(decoded, camera, render.min_transmittance),
                    web::RenderBakedFrame(baked, camera, render.min_transmittance), &squared,
                    &count);
  tally.update({{"squared", squared}, {"count", count}});
  ScoreAgainstCameras(
      stream, i,
      [&](const CameraModel& camera) {
        return VolumeModel(stream.source).Render(camera, frame, render);
      },
      [&](const CameraModel& camera) {
        return web::RenderBakedFrame(decoded, camera, render.min_transmittance);
      },
      &tally);
  return tally;
}

nlohmann::json SiteWriter::WriteSplatFrames(const SiteStream& stream, size_t begin, size_t end,
                                            std::vector<std::string>* outputs) {
  SplatSequence& sequence = Sequence(stream.source);
  const std::vector<int64_t>& model_frames = FramesOf(stream.source);
  const web::SplatEncoding level = web::SplatEncoding::FromJson(stream.encoding);
  const std::vector<web::SplatEncoding> encodings =
      stream.budget_mbps > 0 && !level.float32
          ? BudgetedSplatEncodings(stream, begin, end)
          : std::vector<web::SplatEncoding>(end - begin, level);
  nlohmann::json frames = nlohmann::json::array();
  web::SplatCodes previous;
  for (size_t i = begin; i < end; ++i) {
    const web::SplatEncoding& encoding = encodings[i - begin];
    const int64_t frame = model_frames[i];
    if (frame < 0) {
      frames.push_back({{"chunk", nullptr}});
      continue;
    }
    std::vector<int64_t> origin;
    SplatChunkOf(stream.source, i, begin, &origin);
    const bool key = origin.empty();
    frames.push_back(WriteSplatChunk(stream, i, sequence.Frame(frame), encoding, key, origin,
                                     &previous, outputs));
  }
  return frames;
}

std::vector<web::SplatEncoding> SiteWriter::BudgetedSplatEncodings(const SiteStream& stream,
                                                                   size_t begin, size_t end) {
  SplatSequence& sequence = Sequence(stream.source);
  const web::SplatEncoding level = web::SplatEncoding::FromJson(stream.encoding);
  const double budget_bytes = stream.budget_mbps * 1e6 / 8 / fps_;
  constexpr int kCoarsest = web::kSplatRungs - 1;
  std::vector<web::SplatEncoding> chosen(end - begin, level);
  web::SplatCodes previous;
  // The chunk's size at `encoding`; its codes (what the next delta follows) in `codes`.
  auto encoded_bytes = [&](size_t i, const web::SplatEncoding& encoding, bool key,
                           const std::vector<int64_t>& origin, web::SplatCodes* codes) {
    return static_cast<double>(web::EncodeSplats(sequence.Frame(FramesOf(stream.source)[i]),
                                                 static_cast<int64_t>(i), encoding,
                                                 key ? nullptr : &previous, origin, codes)
                                   .Serialise()
                                   .size());
  };
  // Each segment (a key frame and the deltas that follow it, up to the next key frame) at the
  // finest rung at which the segment's bytes fit its frames' share of the budget, the key frame
  // and its deltas at one rung (a delta's records are byte differences from the frame before,
  // so it keeps its key frame's bits); the coarsest rung where none does (the segment over the
  // budget ends the export DEGENERATE).
  size_t key = begin;
  while (key < end) {
    size_t next = end;
    for (size_t i = key + 1; i < end && next == end; ++i) {
      std::vector<int64_t> origin;
      if (SplatChunkOf(stream.source, i, begin, &origin) >= 0 && origin.empty()) next = i;
    }
    const double segment_budget = budget_bytes * static_cast<double>(next - key);
    for (int rung = 0; rung <= kCoarsest; ++rung) {
      const web::SplatEncoding encoding = web::SplatDeltaRung(level, rung, rung);
      double bytes = 0;
      for (size_t i = key; i < next; ++i) {
        std::vector<int64_t> origin;
        if (SplatChunkOf(stream.source, i, begin, &origin) < 0) continue;
        web::SplatCodes codes;
        bytes += encoded_bytes(i, encoding, origin.empty(), origin, &codes);
        chosen[i - begin] = encoding;
        previous = std::move(codes);
      }
      if (bytes <= segment_budget) break;
    }
    key = next;
  }
  return chosen;
}

int64_t SiteWriter::SplatChunkOf(int source, size_t i, size_t begin, std::vector<int64_t>* origin) {
  const std::vector<int64_t>& model_frames = FramesOf(source);
  const int64_t frame = model_frames[i];
  origin->clear();
  if (frame < 0) return frame;
  SplatSequence& sequence = Sequence(source);
  const int64_t previous_frame = i > begin ? model_frames[i - 1] : -1;
  const splat::Gaussians& gaussians = sequence.Frame(frame);
  // A delta follows the frame before when that shows the same model frame or the base of
  // this frame's delta (where a segment of a per-frame run starts, frame 0: a key frame); a
  // group starts with a key frame, so no delta reaches into the group before.
  const bool follows =
      previous_frame >= 0 && (frame == previous_frame || sequence.Base(frame) == previous_frame);
  if (!follows || i % static_cast<size_t>(options_.splat_key_every) == 0) return frame;
  if (frame == previous_frame) {
    origin->resize(gaussians.size());
    std::iota(origin->begin(), origin->end(), int64_t{0});
  } else {
    *origin = sequence.origin();
  }
  return frame;
}

nlohmann::json SiteWriter::WriteSplatChunk(const SiteStream& stream, size_t i,
                                           const splat::Gaussians& gaussians,
                                           const web::SplatEncoding& encoding, bool key,
                                           const std::vector<int64_t>& origin,
                                           web::SplatCodes* decoded,
                                           std::vector<std::string>* outputs) {
  const web::SplatCodes* previous = key ? nullptr : decoded;
  web::SplatCodes codes;
  const std::string chunk =
      web::EncodeSplats(gaussians, static_cast<int64_t>(i), encoding, previous, origin, &codes)
          .Serialise();
  nlohmann::json tally = WriteChunk(stream, i, chunk, {{"key", key}}, outputs);
  // Decoded again as the page decodes it, from the frame before as decoded.
  const web::Chunk parsed = web::ParseChunk(chunk);
  *decoded = web::DecodeSplats(parsed, previous);
  if (decoded->records != codes.records)
    Fail("splat frame ", i, " of ", stream.name, " decodes to other codes than its encoder held");
  decoded->order = std::move(codes.order);
  const splat::Gaussians drawn = web::SplatsFromCodes(*decoded, encoding);
  double squared = 0;
  int64_t count = 0;
  for (const CameraModel& camera : ErrorCameras(static_cast<int64_t>(i)))
    AccumulateError(SplatView(drawn, camera), SplatView(gaussians, camera), &squared, &count);
  tally.update({{"squared", squared},
                {"count", count},
                {"gaussians", gaussians.size()},
                {"stored", parsed.header.at("stored")}});
  ScoreAgainstCameras(
      stream, i, [&](const CameraModel& camera) { return SplatView(gaussians, camera); },
      [&](const CameraModel& camera) { return SplatView(drawn, camera); }, &tally);
  return tally;
}

const std::vector<int64_t>& SiteWriter::FramesOf(int source) {
  auto found = model_frames_.find(source);
  if (found != model_frames_.end()) return found->second;
  const fs::path& model_dir = options_.models[source];
  const int64_t model_frame_count = OpenModel(model_dir)->frame_count();
  const nlohmann::json model_json =
      nlohmann::json::parse(ReadFileToString(model_dir / "model.json"));
  const std::vector<int64_t> model_sets = model_json.value("frame_sets", std::vector<int64_t>{});
  std::vector<int64_t> frames(sets_.size(), 0);  // a static model shows its one frame throughout
  for (size_t i = 0; i < sets_.size() && model_frame_count > 1; ++i) {
    auto it = std::find(model_sets.begin(), model_sets.end(), sets_[i]);
    frames[i] = it == model_sets.end() || it - model_sets.begin() >= model_frame_count
                    ? -1
                    : it - model_sets.begin();
  }
  return model_frames_[source] = std::move(frames);
}

AvatarModel& SiteWriter::VolumeModel(int source) {
  auto& model = volumes_[source];
  if (!model) model = OpenModel(options_.models[source]);
  return *model;
}

SplatSequence& SiteWriter::Sequence(int source) {
  auto& sequence = sequences_[source];
  if (!sequence) sequence = std::make_unique<SplatSequence>(options_.models[source]);
  return *sequence;
}

WebExportSummary SiteWriter::Run() {
  const auto start = std::chrono::steady_clock::now();
  PlanCameras();
  if (!ChooseTimeline()) {
    if (report_ != nullptr) {
      report_->SetSummary(summary_);
      report_->Write(TaskReportPath(site_, options_.tasks.shard));
    }
    return summary_;
  }
  identity_ = Identity();
  PlanSite();
  StartRecords();
  const std::vector<int64_t> mine = options_.tasks.shard.Of(group_keys_);
  Progress progress("export web", static_cast<int64_t>(mine.size()));
  for (int64_t key : mine) {
    const size_t group = static_cast<size_t>(
        std::find(group_keys_.begin(), group_keys_.end(), key) - group_keys_.begin());
    if (!options_.tasks.redo && records_->Complete(key)) {
      ++skipped_;
    } else {
      WriteGroup(group);
      ++written_;
    }
    progress.Increment();
  }
  progress.Finish();
  WebExportSummary summary = FinishTask(mine.size());
  summary.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return summary;
}

// A whole run's report is the one merged from its records (as a sharded run's is); a shard
// writes its own, and merges the site when its groups complete the run.
WebExportSummary SiteWriter::FinishTask(size_t groups) {
  const Shard& shard = options_.tasks.shard;
  if (skipped_ > 0) {
    std::printf("export web: %lld of %zu group(s) skipped: complete from an earlier run\n",
                static_cast<long long>(skipped_), groups);
  }
  if (shard.whole()) {
    Report local(kCommand);
    return MergeWebSite(site_, report_ != nullptr ? report_ : &local);
  }
  const RunState run = ReadRunState(site_);
  std::printf("export web: shard %s wrote %lld and skipped %lld of its %zu group(s); the run: %s\n",
              shard.ToString().c_str(), static_cast<long long>(written_),
              static_cast<long long>(skipped_), groups, run.Describe().c_str());
  if (run.done()) {
    Report merged(kCommand);
    const WebExportSummary all = MergeWebSite(site_, &merged);
    std::printf("export web: the run is complete: %s (%s)\n", (site_ / "manifest.json").c_str(),
                ToString(all.termination));
  }
  WebExportSummary summary;
  summary.End(Termination::kSuccess,
              Cat("shard ", shard.ToString(), ": ", written_, " group(s) written, ", skipped_,
                  " complete from an earlier run (", group_keys_.size(), " group(s) of up to ",
                  options_.splat_key_every, " frames in the run)"));
  if (report_ == nullptr) return summary;
  report_->metrics()["groups_written"] = written_;
  report_->metrics()["groups_skipped"] = skipped_;
  report_->metrics()["plan"] = plan_origin_;
  report_->metrics()["run"] = run.Describe();
  report_->metrics()["peak_rss_mb"] = PeakRssMb();
  report_->SetSummary(summary);
  report_->Write(TaskReportPath(site_, shard));
  return summary;
}

// A stream's metrics and manifest entry summed from its frames in the groups' records.
class StreamSum {
 public:
  StreamSum(const SiteStream& stream, fs::path site, Report* report)
      : stream_(stream), site_(std::move(site)), report_(report) {
    metrics_ = {.name = stream.name, .kind = stream.kind, .quality = stream.quality};
  }

  // Adds frame set `set`'s frame, once CheckWebFrameRecord has found it believable.
  void Add(int64_t set, const nlohmann::json& frame) {
    CheckWebFrameRecord(frame, site_, stream_.folder, stream_.name, set);
    const nlohmann::json& chunk = frame["chunk"];
    chunks_.push_back(chunk);
    // A segment: a key frame (every mesh and volume chunk is one) and the frames up to the next.
    if (!chunk.is_null() && chunk.value("key", true)) CloseSegment();
    ++segment_frames_;
    if (chunk.is_null()) return;
    segment_bytes_ += chunk.at("bytes").get<uint64_t>();
    bytes_ += frame.at("chunk").at("bytes").get<uint64_t>();
    max_chunk_bytes_ = std::max(max_chunk_bytes_, frame.at("chunk").at("bytes").get<uint64_t>());
    squared_ += frame.at("squared").get<double>();
    count_ += frame.at("count").get<int64_t>();
    ++metrics_.frames;
    metrics_.max_position_error_mm =
        std::max(metrics_.max_position_error_mm, frame.value("max_position_error_mm", 0.0));
    metrics_.mean_faces += frame.value("faces", 0.0);
    metrics_.mean_gaussians += frame.value("gaussians", 0.0);
    metrics_.mean_stored_gaussians += frame.value("stored", 0.0);
    metrics_.key_frames += frame.at("chunk").value("key", false) ? 1 : 0;
    if (frame.contains("camera")) {
      const nlohmann::json& camera = frame["camera"];
      camera_count_ += camera.at("count").get<int64_t>();
      native_.squared += camera.at("native").get<double>();
      streamed_.squared += camera.at("streamed").get<double>();
      background_.squared += camera.at("background").get<double>();
    }
    report_->AddPoint(metrics_.name + ".psnr_db", Psnr(squared_, count_), metrics_.frames);
  }

  // The stream's manifest entry; its metrics go to `summary` and the report.
  nlohmann::json End(double fps, WebExportSummary* summary) {
    WebStreamMetrics& metrics = metrics_;
    const double frames = static_cast<double>(std::max<int64_t>(metrics.frames, 1));
    metrics.mb_per_frame = metrics.frames > 0 ? bytes_ / 1e6 / metrics.frames : 0;
    metrics.mean_faces /= frames;
    metrics.mean_gaussians /= frames;
    metrics.mean_stored_gaussians /= frames;
    metrics.mbps = metrics.mb_per_frame * 8 * fps;
    metrics.max_chunk_mbps = static_cast<double>(max_chunk_bytes_) * 8 * fps / 1e6;
    CloseSegment();
    metrics.max_segment_mbps = max_segment_bytes_per_frame_ * 8 * fps / 1e6;
    metrics.budget_mbps = stream_.budget_mbps;
    metrics.psnr_db = Psnr(squared_, count_);
    metrics.heldout = stream_.heldout;
    metrics.unscored = stream_.unscored;
    native_.count = streamed_.count = background_.count = camera_count_;
    metrics.camera_native_psnr_db = native_.PsnrDb();
    metrics.camera_streamed_psnr_db = streamed_.PsnrDb();
    metrics.camera_background_psnr_db = background_.PsnrDb();
    metrics.camera_pixels = camera_count_ / 3;
    if (camera_count_ == 0 && metrics.unscored.empty())
      metrics.unscored = "no subject pixel in the held-out cameras' frames scored";
    summary->bytes += bytes_;
    summary->streams.push_back(metrics);
    report_->metrics()["streams"][metrics.name] = metrics.ToJson();
    nlohmann::json entry = {{"name", metrics.name},       {"kind", metrics.kind},
                            {"quality", metrics.quality}, {"path", stream_.folder},
                            {"chunks", chunks_},          {"mb_per_frame", metrics.mb_per_frame},
                            {"mbps", metrics.mbps},       {"psnr_db", metrics.psnr_db}};
    if (!stream_.backgrounds.empty()) entry["backgrounds"] = stream_.backgrounds;
    return entry;
  }

 private:
  SiteStream stream_;
  fs::path site_;
  Report* report_;
  WebStreamMetrics metrics_;
  nlohmann::json chunks_ = nlohmann::json::array();
  void CloseSegment() {
    if (segment_frames_ > 0) {
      max_segment_bytes_per_frame_ =
          std::max(max_segment_bytes_per_frame_,
                   static_cast<double>(segment_bytes_) / static_cast<double>(segment_frames_));
    }
    segment_bytes_ = 0;
    segment_frames_ = 0;
  }
  uint64_t bytes_ = 0, max_chunk_bytes_ = 0;
  uint64_t segment_bytes_ = 0;  // the segment being summed
  int64_t segment_frames_ = 0;
  double max_segment_bytes_per_frame_ = 0;
  double squared_ = 0;
  int64_t count_ = 0;
  SquaredError native_, streamed_, background_;  // against the camera
  int64_t camera_count_ = 0;
};

// Finite values as numbers, NaN as null.
nlohmann::json Number(double value) {
  return std::isfinite(value) ? nlohmann::json(value) : nlohmann::json();
}

// Why a stream that was scored against the camera is no better there than its background
// alone; empty when it is (or was not scored).
// Why a budgeted stream is over its budget (empty: it is not): a segment at the coarsest rung
// still needs more (rounded to the report's precision).
std::string OverBudget(const WebStreamMetrics& s) {
  if (s.budget_mbps <= 0 || s.max_segment_mbps <= s.budget_mbps * (1 + 1e-9)) return "";
  return Cat(s.name, ": its largest segment needs ", s.max_segment_mbps,
             " Mbps at the coarsest encoding, over its budget of ", s.budget_mbps,
             " Mbps (raise --splat-mbps, or export fewer Gaussians)");
}

std::string NoBetterThanBackground(const WebStreamMetrics& s) {
  if (s.camera_pixels == 0) return "";
  std::string why;
  for (const auto& [what, db] :
       {std::pair<const char*, double>{"native render", s.camera_native_psnr_db},
        {"streamed picture", s.camera_streamed_psnr_db}}) {
    if (db > s.camera_background_psnr_db) continue;
    why += Cat(why.empty() ? "" : ", ", "its ", what, " scores ", db, " dB");
  }
  if (why.empty()) return "";
  std::string cameras;
  for (const std::string& c : s.heldout) cameras += (cameras.empty() ? "" : ", ") + c;
  return Cat(s.name, ": ", why, " against held-out ", cameras,
             " inside the subject, no better than the background alone (",
             s.camera_background_psnr_db, " dB)");
}

// The ladders: per source (mesh, each model), its streams' levels from the fewest Mbps up, which
// the page chooses among by the throughput and decode time it measures. A stream's source is its
// name without the level ("nvol-high": "nvol").
nlohmann::json Ladders(const nlohmann::json& streams) {
  nlohmann::json ladders = nlohmann::json::array();
  for (const auto& stream : streams) {
    const std::string name = stream.at("name").get<std::string>();
    const std::string quality = stream.at("quality").get<std::string>();
    const std::string source =
        name.substr(0, name.size() - std::min(name.size(), quality.size() + 1));
    auto ladder = std::find_if(ladders.begin(), ladders.end(),
                               [&](const nlohmann::json& l) { return l.at("name") == source; });
    if (ladder == ladders.end()) {
      ladders.push_back(
          {{"name", source}, {"kind", stream.at("kind")}, {"levels", nlohmann::json::array()}});
      ladder = ladders.end() - 1;
    }
    (*ladder)["levels"].push_back(
        {{"stream", name}, {"quality", quality}, {"mbps", stream.at("mbps")}});
  }
  for (auto& ladder : ladders) {
    auto& levels = ladder["levels"];
    std::stable_sort(levels.begin(), levels.end(), [](const auto& a, const auto& b) {
      return a.at("mbps").template get<double>() < b.at("mbps").template get<double>();
    });
  }
  return ladders;
}

}  // namespace

void WebExportOptions::Check() const {
  HOLOCAP_CHECK_OPTION(!qualities.empty(), qualities, "at least one level");
  for (const auto& q : qualities) web::QualityByName(q);
  HOLOCAP_CHECK_OPTION_GE(fps, 0);
  HOLOCAP_CHECK_OPTION_GT(step_voxels, 0);
  HOLOCAP_CHECK_OPTION_GE(error_width_px, 8);
  HOLOCAP_CHECK_OPTION_GE(error_cameras, 0);
  HOLOCAP_CHECK_OPTION_GE(camera_score_every, 1);
  HOLOCAP_CHECK_OPTION_GE(splat_key_every, 1);
  HOLOCAP_CHECK_OPTION(std::ranges::all_of(splat_mbps, [](double b) { return b >= 0; }), splat_mbps,
                       "budgets of 0 Mbps (the level's own encoding) or more");
  HOLOCAP_CHECK_OPTION(
      std::set<double>(splat_mbps.begin(), splat_mbps.end()).size() == splat_mbps.size(),
      splat_mbps, "each budget once");
  take.Check();
  tasks.Check();
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
          {"camera_score_every", camera_score_every},
          {"splat_key_every", splat_key_every},
          {"splat_mbps", splat_mbps},
          {"take", take.ToJson()},
          {"overwrite", overwrite},
          {"tasks", tasks.ToJson()}};
}

nlohmann::json WebStreamMetrics::ToJson() const {
  nlohmann::json json = {
      {"kind", kind},
      {"quality", quality},
      {"frames", frames},
      {"mb_per_frame", mb_per_frame},
      {"mbps", mbps},
      {"max_chunk_mbps", max_chunk_mbps},
      {"max_segment_mbps", max_segment_mbps},
      {"psnr_db", std::isfinite(psnr_db) ? nlohmann::json(psnr_db) : nlohmann::json()},
      {"max_position_error_mm", max_position_error_mm},
      {"mean_faces", mean_faces}};
  json["camera"] = {{"heldout", heldout},
                    {"native_psnr_db", Number(camera_native_psnr_db)},
                    {"streamed_psnr_db", Number(camera_streamed_psnr_db)},
                    {"background_psnr_db", Number(camera_background_psnr_db)},
                    {"pixels", camera_pixels}};
  if (!unscored.empty()) json["camera"]["unscored"] = unscored;
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
  OutputRequest request{
      kCommand, options.overwrite, {take_dir}, !options.tasks.shard.whole(), take_dir};
  for (const auto& model : options.models) request.inputs.push_back(model);
  if (!options.recon.empty()) request.inputs.push_back(options.recon);
  const OutputDirectory claimed = OutputDirectory::Claim(site_dir, request);
  if (report != nullptr) {
    report->options() = options.ToJson();
    report->SetFailureDestination(TaskReportPath(site_dir, options.tasks.shard));
  }
  SiteWriter writer(take_dir, site_dir, options, report);
  WebExportSummary summary = writer.Run();
  return summary;
}

WebExportSummary MergeWebSite(const fs::path& site_dir, Report* report) {
  const RunState run = ReadRunState(site_dir);
  if (run.command != kCommand)
    Fail("'", site_dir.string(), "' holds a run of holocap ", run.command, ", not of ", kCommand);
  const fs::path plan_file = site_dir / kPlanDir / "plan.json";
  nlohmann::json plan;
  try {
    plan = nlohmann::json::parse(ReadFileToString(plan_file)).at("plan");
  } catch (const nlohmann::json::exception& e) {
    Fail("cannot read the run's plan ", plan_file.string(), ": ", e.what());
  }
  report->options() = run.header.value("options", nlohmann::json::object());
  report->plan() = run.header.value("plan", nlohmann::json::object());
  report->metrics()["run"] = run.Describe();
  report->metrics()["timing"] = {{"groups_by_task", run.frames_by_task},
                                 {"cpu_s_by_task", run.cpu_s_by_task}};
  WebExportSummary summary;
  summary.frames = static_cast<int64_t>(plan.at("sets").size());
  if (!run.done()) {
    summary.End(Termination::kFailure, Cat("the run is incomplete: ", run.Describe()));
    report->SetSummary(summary);
    report->Write(site_dir / "report.json");
    return summary;
  }
  nlohmann::json streams = nlohmann::json::array();
  for (const auto& planned : plan.at("streams")) {
    const SiteStream stream = SiteStream::FromJson(planned);
    StreamSum sum(stream, site_dir, report);
    for (const auto& [set, record] : run.complete)
      for (const auto& frame : record.at("result").at("streams").at(stream.name))
        sum.Add(set, frame);
    streams.push_back(sum.End(plan.at("head").at("fps").get<double>(), &summary));
  }
  for (const auto& [path, bytes] : web::PlayerFiles()) {
    CreateDirectories((site_dir / path).parent_path());
    WriteFileAtomic(site_dir / path, bytes, /*durable=*/true);
  }
  // The streams' backgrounds, from the plan folder to where the manifest names them.
  std::set<std::string> backgrounds;
  for (const auto& planned : plan.at("streams")) {
    const nlohmann::json listed = planned.value("backgrounds", nlohmann::json::object());
    for (const auto& [camera, file] : listed.items()) backgrounds.insert(file.get<std::string>());
  }
  for (const std::string& file : backgrounds) {
    CreateDirectories((site_dir / file).parent_path());
    WriteFileAtomic(site_dir / file, ReadFileToString(site_dir / kPlanDir / file),
                    /*durable=*/true);
  }
  // Last: a player opens the site only once every chunk it lists is in place.
  nlohmann::json manifest = plan.at("head");
  manifest["streams"] = streams;
  manifest["ladders"] = Ladders(streams);
  WriteFileAtomic(site_dir / "manifest.json", manifest.dump(1) + "\n", /*durable=*/true);
  summary.seconds = report->ElapsedSeconds();
  std::string degenerate;
  for (const WebStreamMetrics& s : summary.streams) {
    const std::string why = NoBetterThanBackground(s) + OverBudget(s);
    if (!why.empty()) degenerate += (degenerate.empty() ? "" : "; ") + why;
  }
  if (degenerate.empty()) {
    summary.End(Termination::kSuccess,
                Cat(summary.frames, " frame(s), ", summary.streams.size(), " stream(s)"));
  } else {
    summary.End(Termination::kDegenerate, Cat("the site is written, but ", degenerate));
  }
  report->metrics()["frames"] = summary.frames;
  report->metrics()["bytes"] = summary.bytes;
  report->metrics()["seconds"] = summary.seconds;
  report->SetSummary(summary);
  report->Write(site_dir / "report.json");
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
                       const Box& box, int64_t* pixels) {
  if (picture.size() != reference.size())
    Fail("PSNR inside the box: pictures of ", picture.cols, "x", picture.rows, " and ",
         reference.cols, "x", reference.rows);
  double x0 = 1e9, y0 = 1e9, x1 = -1e9, y1 = -1e9;
  for (int k = 0; k < 8; ++k) {
    const Eigen::Vector3d corner = box.Corner(k);
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

}  // namespace holocap
