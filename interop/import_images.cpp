// Photographs and videos as a take: sources resolved and checked, frames paired into frame
// sets, then written through TakeWriter like every other import (see interop.h).
#include <glob.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <map>
#include <opencv2/videoio.hpp>
#include <set>
#include <sstream>

#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/take.h"
#include "interop/internal/import_frames.h"
#include "interop/interop.h"

namespace holocap {
namespace {

using interop_internal::ImageFilesIn;
using interop_internal::IsImageFile;
using interop_internal::PixelFormatOf;
using interop_internal::ReadSourceImage;

constexpr const char* kTimestampsFile = "timestamps.txt";

bool IsVideoFile(const fs::path& file) {
  static const std::set<std::string> known = {".mp4", ".mov",  ".m4v", ".mkv",
                                              ".avi", ".webm", ".mpg", ".mpeg"};
  return known.count(interop_internal::LowerExtension(file)) > 0;
}

// One frame of a camera's source: an image file, or frame `video_index` of a video.
struct SourceFrame {
  fs::path file;
  int64_t video_index = -1;
  std::optional<int64_t> number;
  std::optional<double> time_s;

  std::string Name() const {
    return video_index < 0 ? file.string() : Cat(file.string(), "#", video_index);
  }
};

struct CameraFrames {
  std::string camera;
  std::string source;
  bool video = false;
  std::vector<SourceFrame> frames;  // images by name, a video's frames in order
  std::vector<fs::path> inputs;     // what the take may not lie under
  int width = 0;
  int height = 0;
  std::string pixel_format;
};

// timestamps.txt: "<file name> <seconds>" per line, '#' comments.
std::map<std::string, double> ReadTimestamps(const fs::path& file) {
  std::map<std::string, double> times;
  std::istringstream text(ReadFileToString(file));
  std::string line;
  for (int number = 1; std::getline(text, line); ++number) {
    const size_t hash = line.find('#');
    if (hash != std::string::npos) line.resize(hash);
    std::istringstream fields(line);
    std::string name, seconds, extra;
    if (!(fields >> name)) continue;
    double value = 0;
    size_t used = 0;
    try {
      if (fields >> seconds) value = std::stod(seconds, &used);
    } catch (const std::exception&) {
      used = 0;
    }
    if (seconds.empty() || used != seconds.size() || !std::isfinite(value) || (fields >> extra))
      Fail(file.string(), ":", number, ": expected '<file name> <seconds>', got '", line, "'");
    if (!times.emplace(name, value).second)
      Fail(file.string(), ":", number, ": '", name, "' is listed twice");
  }
  return times;
}

// Each image's number and, where its folder has a timestamps.txt that lists it, its time.
std::vector<SourceFrame> ImageFrames(const std::vector<fs::path>& files) {
  std::map<fs::path, std::map<std::string, double>> sidecars;
  std::vector<SourceFrame> frames;
  for (const auto& file : files) {
    const fs::path folder = file.parent_path();
    auto sidecar = sidecars.find(folder);
    if (sidecar == sidecars.end()) {
      const fs::path list = folder / kTimestampsFile;
      sidecar = sidecars
                    .emplace(folder, fs::is_regular_file(list) ? ReadTimestamps(list)
                                                               : std::map<std::string, double>{})
                    .first;
    }
    SourceFrame frame;
    frame.file = file;
    frame.number = interop_internal::TrailingNumber(file);
    auto time = sidecar->second.find(file.filename().string());
    if (time != sidecar->second.end()) frame.time_s = time->second;
    frames.push_back(frame);
  }
  return frames;
}

std::vector<fs::path> GlobImages(const std::string& pattern) {
  glob_t matches{};
  const int status = glob(pattern.c_str(), 0, nullptr, &matches);
  std::vector<fs::path> files;
  if (status == 0) {
    for (size_t i = 0; i < matches.gl_pathc; ++i) {
      const fs::path file = matches.gl_pathv[i];
      if (fs::is_regular_file(file) && IsImageFile(file)) files.push_back(file);
    }
  }
  globfree(&matches);
  std::sort(files.begin(), files.end());
  return files;
}

cv::VideoCapture OpenVideo(const fs::path& file) {
  // FFmpeg's own log lines would stand beside the one error line; what it cannot read is said
  // there. OpenCV reads the level when it first opens a video (a user's setting is kept).
  setenv("OPENCV_FFMPEG_LOGLEVEL", "-8", 0);
  cv::VideoCapture video;
  try {
    video.open(file.string(), cv::CAP_FFMPEG);
  } catch (const cv::Exception&) {
  }
  if (!video.isOpened())
    Fail("video '", file.string(), "' cannot be opened (FFmpeg: truncated, or not a video)");
  return video;
}

// Decodes the whole video once: its frames' count, times and size. A video that ends before
// the frame count its container declares is truncated.
void ReadVideo(CameraFrames* camera) {
  const fs::path file = camera->source;
  cv::VideoCapture video = OpenVideo(file);
  const auto declared = static_cast<int64_t>(video.get(cv::CAP_PROP_FRAME_COUNT));
  cv::Mat image;
  for (int64_t index = 0; video.read(image); ++index) {
    SourceFrame frame;
    frame.file = file;
    frame.video_index = index;
    frame.number = index;
    frame.time_s = video.get(cv::CAP_PROP_POS_MSEC) / 1000.0;
    if (camera->frames.empty()) {
      camera->width = image.cols;
      camera->height = image.rows;
      camera->pixel_format = PixelFormatOf(image, frame.Name()).name;
    }
    camera->frames.push_back(frame);
  }
  if (camera->frames.empty()) Fail("video '", file.string(), "' holds no frame that decodes");
  if (declared > static_cast<int64_t>(camera->frames.size())) {
    Fail("video '", file.string(), "' is truncated: ", camera->frames.size(),
         " frame(s) decode of the ", declared, " it declares");
  }
}

// Every image decoded once: each must be whole and of the camera's one size and format.
void CheckImages(CameraFrames* camera) {
  const SourceFrame* first = nullptr;
  for (const auto& frame : camera->frames) {
    const cv::Mat image = ReadSourceImage(frame.file);
    const std::string format = PixelFormatOf(image, frame.Name()).name;
    if (first == nullptr) {
      first = &frame;
      camera->width = image.cols;
      camera->height = image.rows;
      camera->pixel_format = format;
      continue;
    }
    if (image.cols != camera->width || image.rows != camera->height) {
      Fail("camera '", camera->camera, "': image '", frame.Name(), "' is ", image.cols, "x",
           image.rows, " but '", first->Name(), "' is ", camera->width, "x", camera->height,
           " (one camera's images share one size)");
    }
    if (format != camera->pixel_format) {
      Fail("camera '", camera->camera, "': image '", frame.Name(), "' is ", format, " but '",
           first->Name(), "' is ", camera->pixel_format, " (one camera's images share one format)");
    }
  }
}

CameraFrames ResolveCamera(const CameraSource& source) {
  CameraFrames camera;
  camera.camera = source.camera;
  camera.source = source.source;
  const fs::path path = source.source;
  std::error_code ec;
  if (fs::is_directory(path, ec)) {
    camera.frames = ImageFrames(ImageFilesIn(path));
    if (camera.frames.empty())
      Fail("camera '", source.camera, "': folder '", source.source, "' holds no images");
    camera.inputs = {path};
  } else if (fs::is_regular_file(path, ec) && !IsImageFile(path)) {
    camera.video = true;
    camera.inputs = {path};
    ReadVideo(&camera);
    return camera;
  } else if (fs::is_regular_file(path, ec)) {
    camera.frames = ImageFrames({path});
    camera.inputs = {path};
  } else if (source.source.find_first_of("*?[") != std::string::npos) {
    const std::vector<fs::path> files = GlobImages(source.source);
    if (files.empty())
      Fail("camera '", source.camera, "': '", source.source, "' matches no image file");
    camera.frames = ImageFrames(files);
    camera.inputs = files;
  } else {
    Fail("camera '", source.camera, "': '", source.source,
         "' does not exist (a folder, a glob of images or a video)");
  }
  CheckImages(&camera);
  return camera;
}

// One frame set: for each camera the index of its frame, or -1.
struct PairedSet {
  std::vector<int64_t> frame_of;
  std::optional<double> time_s;  // pairing by time: its earliest frame's
};

struct Pairing {
  FramePairing rule = FramePairing::kOrder;
  std::string reason;
  std::vector<PairedSet> sets;
};

// A frame without a number, or a number used twice in one camera, as a reason; "" if none.
std::string NumberProblem(const std::vector<CameraFrames>& cameras) {
  for (const auto& camera : cameras) {
    std::map<int64_t, const SourceFrame*> seen;
    for (const auto& frame : camera.frames) {
      if (!frame.number) return Cat("'", frame.Name(), "' has no number in its name");
      auto [it, inserted] = seen.emplace(*frame.number, &frame);
      if (!inserted) {
        return Cat("'", it->second->Name(), "' and '", frame.Name(), "' carry the same number ",
                   *frame.number);
      }
    }
  }
  return "";
}

std::string TimeProblem(const std::vector<CameraFrames>& cameras) {
  for (const auto& camera : cameras) {
    for (const auto& frame : camera.frames) {
      if (!frame.time_s) {
        return Cat("'", frame.Name(), "' has no timestamp (no ", kTimestampsFile,
                   " beside it lists it)");
      }
    }
  }
  return "";
}

std::vector<PairedSet> PairByNumber(const std::vector<CameraFrames>& cameras) {
  std::map<int64_t, PairedSet> by_number;
  for (size_t c = 0; c < cameras.size(); ++c) {
    for (size_t f = 0; f < cameras[c].frames.size(); ++f) {
      PairedSet& set = by_number[*cameras[c].frames[f].number];
      set.frame_of.resize(cameras.size(), -1);
      set.frame_of[c] = static_cast<int64_t>(f);
    }
  }
  std::vector<PairedSet> sets;
  sets.reserve(by_number.size());
  for (auto& [number, set] : by_number) sets.push_back(std::move(set));
  return sets;
}

std::vector<PairedSet> PairByOrder(const std::vector<CameraFrames>& cameras) {
  size_t most = 0;
  for (const auto& camera : cameras) most = std::max(most, camera.frames.size());
  std::vector<PairedSet> sets(most);
  for (size_t i = 0; i < most; ++i) {
    sets[i].frame_of.assign(cameras.size(), -1);
    for (size_t c = 0; c < cameras.size(); ++c) {
      if (i < cameras[c].frames.size()) sets[i].frame_of[c] = static_cast<int64_t>(i);
    }
  }
  return sets;
}

// Half the shortest interval between two frames of one camera (infinite for single frames).
double DefaultTimeTolerance(const std::vector<CameraFrames>& cameras) {
  double shortest = std::numeric_limits<double>::infinity();
  for (const auto& camera : cameras) {
    std::vector<double> times;
    for (const auto& frame : camera.frames) times.push_back(*frame.time_s);
    std::sort(times.begin(), times.end());
    for (size_t i = 1; i < times.size(); ++i) {
      if (times[i] > times[i - 1]) shortest = std::min(shortest, times[i] - times[i - 1]);
    }
  }
  return 0.5 * shortest;
}

// In time order, each frame not yet taken opens a set and takes, from every other camera, its
// nearest frame not yet taken within the tolerance.
std::vector<PairedSet> PairByTime(const std::vector<CameraFrames>& cameras, double tolerance_s) {
  struct Event {
    double time_s;
    size_t camera;
    size_t frame;
  };
  std::vector<Event> events;
  std::vector<std::vector<bool>> taken(cameras.size());
  for (size_t c = 0; c < cameras.size(); ++c) {
    taken[c].assign(cameras[c].frames.size(), false);
    for (size_t f = 0; f < cameras[c].frames.size(); ++f)
      events.push_back({*cameras[c].frames[f].time_s, c, f});
  }
  std::sort(events.begin(), events.end(), [](const Event& a, const Event& b) {
    return std::tie(a.time_s, a.camera, a.frame) < std::tie(b.time_s, b.camera, b.frame);
  });
  std::vector<PairedSet> sets;
  for (const Event& open : events) {
    if (taken[open.camera][open.frame]) continue;
    PairedSet set;
    set.frame_of.assign(cameras.size(), -1);
    set.frame_of[open.camera] = static_cast<int64_t>(open.frame);
    set.time_s = open.time_s;
    taken[open.camera][open.frame] = true;
    for (size_t c = 0; c < cameras.size(); ++c) {
      if (c == open.camera) continue;
      int64_t best = -1;
      double best_gap = tolerance_s;
      for (size_t f = 0; f < cameras[c].frames.size(); ++f) {
        const double gap = std::abs(*cameras[c].frames[f].time_s - open.time_s);
        if (!taken[c][f] && gap <= best_gap) {
          best_gap = gap;
          best = static_cast<int64_t>(f);
        }
      }
      if (best >= 0) {
        set.frame_of[c] = best;
        taken[c][best] = true;
      }
    }
    sets.push_back(std::move(set));
  }
  return sets;
}

int64_t PairedFrames(const std::vector<PairedSet>& sets, size_t camera) {
  int64_t paired = 0;
  for (const auto& set : sets) {
    if (set.frame_of[camera] < 0) continue;
    int64_t present = 0;
    for (int64_t f : set.frame_of) present += f >= 0;
    paired += present > 1;
  }
  return paired;
}

Pairing PairFrames(const std::vector<CameraFrames>& cameras, const ImageImportOptions& options) {
  Pairing pairing;
  const std::string number_problem = NumberProblem(cameras);
  const std::string time_problem = TimeProblem(cameras);
  switch (options.pairing) {
    case FramePairing::kNumber:
      if (!number_problem.empty()) Fail("cannot pair by number: ", number_problem);
      pairing.rule = FramePairing::kNumber;
      pairing.reason = "asked (--pair-by number)";
      break;
    case FramePairing::kTime:
      if (!time_problem.empty()) Fail("cannot pair by time: ", time_problem);
      pairing.rule = FramePairing::kTime;
      pairing.reason = "asked (--pair-by time)";
      break;
    case FramePairing::kOrder:
      pairing.rule = FramePairing::kOrder;
      pairing.reason = "asked (--pair-by order)";
      break;
    case FramePairing::kAuto: {
      std::string why_not_number = number_problem;
      if (why_not_number.empty() && cameras.size() > 1) {
        const std::vector<PairedSet> sets = PairByNumber(cameras);
        for (size_t c = 0; c < cameras.size() && why_not_number.empty(); ++c) {
          const int64_t paired = PairedFrames(sets, c);
          if (2 * paired < static_cast<int64_t>(cameras[c].frames.size())) {
            why_not_number = Cat("only ", paired, " of camera '", cameras[c].camera, "''s ",
                                 cameras[c].frames.size(),
                                 " frames share a number with another "
                                 "camera's");
          }
        }
      }
      if (why_not_number.empty()) {
        pairing.rule = FramePairing::kNumber;
        pairing.reason = "every frame carries a number (in its file name, or its place in a video)";
      } else if (time_problem.empty()) {
        pairing.rule = FramePairing::kTime;
        pairing.reason = Cat("not by number (", why_not_number, "); every frame has a timestamp");
      } else {
        pairing.rule = FramePairing::kOrder;
        pairing.reason =
            Cat("not by number (", why_not_number, "), not by time (", time_problem, ")");
      }
      break;
    }
  }
  switch (pairing.rule) {
    case FramePairing::kNumber:
      pairing.sets = PairByNumber(cameras);
      break;
    case FramePairing::kTime: {
      const double tolerance =
          options.time_tolerance_s > 0 ? options.time_tolerance_s : DefaultTimeTolerance(cameras);
      pairing.reason += Cat("; tolerance ", tolerance, " s");
      pairing.sets = PairByTime(cameras, tolerance);
      break;
    }
    default:
      pairing.sets = PairByOrder(cameras);
      break;
  }
  return pairing;
}

// A video read frame by frame in order; an earlier frame reopens it.
class VideoFrames {
 public:
  explicit VideoFrames(fs::path file) : file_(std::move(file)) {}
  cv::Mat Read(int64_t index) {
    if (!video_.isOpened() || index < next_) {
      video_ = OpenVideo(file_);
      next_ = 0;
    }
    cv::Mat image;
    while (next_ <= index) {
      if (!video_.read(image))
        Fail("video '", file_.string(), "' ended before its frame ", index, " on a second read");
      ++next_;
    }
    return image;
  }

 private:
  fs::path file_;
  cv::VideoCapture video_;
  int64_t next_ = 0;
};

}  // namespace

const char* ToString(FramePairing pairing) {
  switch (pairing) {
    case FramePairing::kAuto:
      return "auto";
    case FramePairing::kNumber:
      return "number";
    case FramePairing::kTime:
      return "time";
    case FramePairing::kOrder:
      return "order";
  }
  return "?";
}

FramePairing FramePairingFromString(const std::string& text) {
  for (FramePairing pairing :
       {FramePairing::kAuto, FramePairing::kNumber, FramePairing::kTime, FramePairing::kOrder}) {
    if (text == ToString(pairing)) return pairing;
  }
  Fail("unknown pairing '", text, "' (known: auto, number, time, order)");
}

void ImageImportOptions::Check() const {
  HOLOCAP_CHECK_OPTION_GE(time_tolerance_s, 0, "0: half the shortest interval");
  HOLOCAP_CHECK_OPTION(std::isfinite(time_tolerance_s), time_tolerance_s);
  HOLOCAP_CHECK_OPTION_GT(fps, 0);
  HOLOCAP_CHECK_OPTION_LE(fps, 10000);
  HOLOCAP_CHECK_OPTION_IN(png_compression, 0, 9);
}

std::vector<CameraSource> CameraSourcesInFolder(const fs::path& folder) {
  if (!fs::is_directory(folder)) Fail("'", folder.string(), "' is not a folder");
  std::vector<CameraSource> cameras;
  for (const auto& entry : fs::directory_iterator(folder)) {
    const std::string name = entry.path().filename().string();
    if (name.empty() || name[0] == '.') continue;
    if (entry.is_directory()) {
      if (ImageFilesIn(entry.path()).empty())
        Fail("'", entry.path().string(), "' holds no images (one sub-folder of images a camera)");
      cameras.push_back({name, entry.path().string()});
    } else if (entry.is_regular_file() && IsVideoFile(entry.path())) {
      cameras.push_back({entry.path().stem().string(), entry.path().string()});
    }
  }
  if (cameras.empty()) {
    Fail("'", folder.string(),
         "' holds no camera: a sub-folder of images or a video file per camera");
  }
  std::sort(cameras.begin(), cameras.end(),
            [](const CameraSource& a, const CameraSource& b) { return a.camera < b.camera; });
  return cameras;
}

std::string ImageImportSummary::PairingLine() const {
  std::string line =
      Cat("paired by ", ToString(pairing), " (", pairing_reason, "): ", frame_sets,
          " frame set(s) of ", cameras, " camera(s); ", unpaired.size(), " frame(s) unpaired");
  for (size_t i = 0; i < unpaired.size() && i < 5; ++i)
    line += Cat(i == 0 ? ": " : ", ", unpaired[i]);
  if (unpaired.size() > 5) line += Cat(", ... (", unpaired.size() - 5, " more in report.json)");
  return line;
}

ImageImportSummary ImportImages(const std::vector<CameraSource>& sources, const fs::path& take_dir,
                                const ImageImportOptions& options, Report* report) {
  options.Check();
  if (sources.empty()) Fail("no camera given (--camera NAME=SOURCE, or a folder)");
  std::set<std::string> names;
  for (const auto& source : sources) {
    if (!names.insert(source.camera).second)
      Fail("camera '", source.camera, "' is given twice (each camera has one source)");
  }
  if (report != nullptr) {
    report->options() = {{"format", "images"},
                         {"pair_by", ToString(options.pairing)},
                         {"time_tolerance_s", options.time_tolerance_s},
                         {"fps", options.fps},
                         {"png_compression", options.png_compression},
                         {"overwrite", options.overwrite}};
    for (const auto& source : sources) report->options()["cameras"][source.camera] = source.source;
  }
  // Everything is read and checked before the take's folder is made.
  std::vector<CameraFrames> cameras;
  cameras.reserve(sources.size());
  for (const auto& source : sources) cameras.push_back(ResolveCamera(source));
  Pairing pairing = PairFrames(cameras, options);

  RigDescription description;
  description.name = "images";
  description.fps = options.fps;
  std::vector<StreamInfo> streams;
  const bool timed = pairing.rule == FramePairing::kTime;
  for (const auto& camera : cameras) {
    interop_internal::AddImportedStream(
        camera.camera, "images", camera.width, camera.height, camera.pixel_format,
        timed ? (camera.video ? "video position (s from the earliest frame)"
                              : Cat(kTimestampsFile, " (s from the earliest frame)"))
              : "none (imported: set index / fps)",
        &description, &streams);
  }
  description.Check();

  ImageImportSummary summary;
  summary.cameras = static_cast<int>(cameras.size());
  summary.pairing = pairing.rule;
  summary.pairing_reason = pairing.reason;
  double earliest_s = std::numeric_limits<double>::infinity();
  for (const auto& set : pairing.sets) {
    if (set.time_s) earliest_s = std::min(earliest_s, *set.time_s);
    int64_t present = 0;
    for (int64_t f : set.frame_of) present += f >= 0;
    if (cameras.size() < 2 || present > 1) continue;
    for (size_t c = 0; c < cameras.size(); ++c) {
      if (set.frame_of[c] >= 0)
        summary.unpaired.push_back(cameras[c].frames[set.frame_of[c]].Name());
    }
  }

  nlohmann::json metadata;
  nlohmann::json& interop = metadata["interop"];
  interop["format"] = "images";
  interop["pair_by"] = ToString(pairing.rule);
  interop["pairing_reason"] = pairing.reason;
  interop["unpaired"] = summary.unpaired;
  std::vector<fs::path> inputs;
  for (const auto& camera : cameras) {
    interop["sources"][camera.camera] = camera.source;
    inputs.insert(inputs.end(), camera.inputs.begin(), camera.inputs.end());
  }
  TakeWriter writer(
      take_dir, description, streams, metadata,
      interop_internal::ImportWriterOptions(options.png_compression, options.overwrite, inputs));
  if (report != nullptr && !writer.replacing())
    report->SetFailureDestination(take_dir / "report.json");
  std::vector<std::unique_ptr<VideoFrames>> videos;
  videos.reserve(cameras.size());
  for (const auto& camera : cameras) {
    videos.push_back(camera.video ? std::make_unique<VideoFrames>(camera.source) : nullptr);
  }
  const auto period_ns = static_cast<int64_t>(std::llround(1e9 / options.fps));
  interop_internal::AlphaCounts alpha;
  for (const auto& paired : pairing.sets) {
    FrameSet set;
    set.index = summary.frame_sets;
    for (size_t c = 0; c < cameras.size(); ++c) {
      if (paired.frame_of[c] < 0) continue;
      const SourceFrame& frame = cameras[c].frames[paired.frame_of[c]];
      cv::Mat image = videos[c] ? videos[c]->Read(frame.video_index) : ReadSourceImage(frame.file);
      image = interop_internal::ConformedFrame(image, streams[c], frame.Name(), "has images of",
                                               &alpha);
      const int64_t timestamp_ns =
          timed ? std::llround((*frame.time_s - earliest_s) * 1e9) : set.index * period_ns;
      const uint64_t sequence =
          frame.number ? static_cast<uint64_t>(*frame.number) : static_cast<uint64_t>(set.index);
      set.frames.push_back({cameras[c].camera, image, timestamp_ns, sequence});
    }
    writer.Append(set);
    summary.frames += static_cast<int64_t>(set.frames.size());
    ++summary.frame_sets;
  }
  writer.Close();

  std::vector<std::string> notes;
  alpha.AddNotes(&notes);
  summary.metrics = {{"unpaired_frames", summary.unpaired.size()},
                     {"alpha_channels_dropped", alpha.dropped},
                     {"alpha_channels_kept", alpha.kept}};
  for (const auto& camera : cameras) {
    summary.metrics["cameras"][camera.camera] = {{"frames", camera.frames.size()},
                                                 {"width", camera.width},
                                                 {"height", camera.height},
                                                 {"pixel_format", camera.pixel_format},
                                                 {"video", camera.video}};
  }
  std::string message = Cat("imported ", summary.cameras, " camera(s), ", summary.frames,
                            " frame(s) in ", summary.frame_sets, " frame set(s) from images");
  for (const auto& note : notes) message += "; " + note;
  summary.End(Termination::kSuccess, std::move(message));
  if (report != nullptr) {
    report->plan() = {{"sensors", summary.cameras},       {"frame_sets", summary.frame_sets},
                      {"frames", summary.frames},         {"pair_by", ToString(pairing.rule)},
                      {"pairing_reason", pairing.reason}, {"unpaired", summary.unpaired}};
    report->metrics() = summary.metrics;
    report->SetSummary(summary);
  }
  return summary;
}

}  // namespace holocap
