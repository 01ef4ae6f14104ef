#include "core/take.h"

#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <limits>
#include <type_traits>

#include "core/error.h"

namespace holocap {
namespace {

constexpr const char* kManifest = "take.json";
constexpr const char* kIndex = "index.jsonl";

std::string NowIso8601() {
  std::time_t now = std::time(nullptr);
  char buffer[32];
  std::strftime(buffer, sizeof(buffer), "%Y-%m-%dT%H:%M:%SZ", std::gmtime(&now));
  return buffer;
}

std::string FrameFileName(const StreamInfo& stream, int64_t index) {
  char buffer[32];
  std::snprintf(buffer, sizeof(buffer), "%06lld", static_cast<long long>(index));
  return "frames/" + stream.name + "/" + buffer + ExtensionOf(stream.codec);
}

const char* CodecName(ImageCodec codec) {
  switch (codec) {
    case ImageCodec::kPng:
      return "png";
    case ImageCodec::kZstd:
      return "zstd";
    case ImageCodec::kExr:
      return "exr";
  }
  return "?";
}

ImageCodec CodecFromName(const std::string& name) {
  if (name == "png") return ImageCodec::kPng;
  if (name == "zstd") return ImageCodec::kZstd;
  if (name == "exr") return ImageCodec::kExr;
  Fail("unknown frame codec '", name, "'");
}

// An integer field in T's range. nlohmann's get<T>() casts a float such as 1e100 to T, which
// is undefined, and wraps an integer out of range; an integral float (64.0) is taken.
template <typename T>
T JsonInteger(const nlohmann::json& value, const char* field) {
  constexpr T lo = std::numeric_limits<T>::min(), hi = std::numeric_limits<T>::max();
  if (value.is_number_unsigned()) {
    uint64_t integer = value.get<uint64_t>();
    if (integer <= static_cast<uint64_t>(hi)) return static_cast<T>(integer);
  } else if (value.is_number_integer()) {
    int64_t integer = value.get<int64_t>();
    bool in_range = integer >= 0 ? static_cast<uint64_t>(integer) <= static_cast<uint64_t>(hi)
                                 : std::is_signed_v<T> && integer >= static_cast<int64_t>(lo);
    if (in_range) return static_cast<T>(integer);
  } else if (value.is_number_float()) {
    double number = value.get<double>();
    // hi + 1 is 2^31, 2^63 or 2^64, all exact as doubles (hi itself rounds up for 64 bits).
    if (number == std::floor(number) && number >= static_cast<double>(lo) &&
        number < static_cast<double>(hi) + 1)
      return static_cast<T>(number);
  }
  Fail("'", field, "' must be an integer in [", lo, ", ", hi, "], got ",
       value.is_number() ? value.dump() : value.type_name());
}

// Why `file` (as an index line names it) would lead outside the take, or "" when it stays in.
std::string OutsideTake(const std::string& file) {
  if (file.empty()) return "is empty";
  if (file.find('\0') != std::string::npos) return "holds a NUL byte";
  const std::filesystem::path path(file);
  if (path.has_root_directory() || path.has_root_name()) return "is an absolute path";
  for (const auto& part : path) {
    if (part == "..") return "climbs out of the take through '..'";
  }
  return {};
}

// One index line into `entry`; `damage` says what no writer leaves (a file outside the take, a
// sensor twice). Throws nlohmann's exceptions or Error for a line that does not parse.
void ParseIndexLine(const std::string& line, FrameSetEntry* entry, std::string* damage) {
  auto json = nlohmann::json::parse(line);
  entry->index = JsonInteger<int64_t>(json.at("set"), "set");
  if (entry->index < 0) {
    *damage = Cat("frame set ", entry->index, " is negative: sets count from 0");
    return;
  }
  if (json.contains("spread_ns"))
    entry->spread_ns = JsonInteger<int64_t>(json["spread_ns"], "spread_ns");
  for (const auto& frame : json.at("frames")) {
    FrameSetEntry::Item item;
    item.sensor = frame.at("sensor").get<std::string>();
    item.file = frame.at("file").get<std::string>();
    item.timestamp_ns = JsonInteger<int64_t>(frame.at("t_ns"), "t_ns");
    if (item.timestamp_ns < 0) {
      *damage = Cat("frame of '", item.sensor, "' in set ", entry->index, " has time ",
                    item.timestamp_ns, " ns, before its clock's start");
      return;
    }
    if (frame.contains("seq")) item.sequence = JsonInteger<uint64_t>(frame["seq"], "seq");
    if (std::string why = OutsideTake(item.file); !why.empty()) {
      *damage = Cat("frame file '", item.file, "' ", why, ": frames must lie inside the take");
      return;
    }
    if (entry->Find(item.sensor) != nullptr) {
      *damage = Cat("frame set ", entry->index, " holds sensor '", item.sensor, "' twice");
      return;
    }
    entry->items.push_back(std::move(item));
  }
}

}  // namespace

nlohmann::json StreamInfo::ToJson() const {
  nlohmann::json json{{"name", name},
                      {"uri", uri},
                      {"role", ToString(role)},
                      {"width", width},
                      {"height", height},
                      {"pixel_format", pixel_format},
                      {"codec", CodecName(codec)},
                      {"clock", clock}};
  if (!paired_with.empty()) json["paired_with"] = paired_with;
  return json;
}

StreamInfo StreamInfo::FromJson(const nlohmann::json& json) {
  StreamInfo stream;
  stream.name = json.at("name").get<std::string>();
  stream.uri = json.value("uri", "");
  stream.role = SensorRoleFromString(json.value("role", "color"));
  stream.width = JsonInteger<int>(json.at("width"), "width");
  stream.height = JsonInteger<int>(json.at("height"), "height");
  if (stream.width <= 0 || stream.height <= 0 ||
      int64_t{stream.width} * stream.height > kMaxUndeclaredImagePixels) {
    Fail("stream '", stream.name, "' declares ", stream.width, "x", stream.height,
         " frames; a frame has 1 to ", kMaxUndeclaredImagePixels, " pixels");
  }
  stream.pixel_format = json.at("pixel_format").get<std::string>();
  stream.codec = CodecFromName(json.value("codec", "png"));
  stream.clock = json.value("clock", "unknown");
  stream.paired_with = json.value("paired_with", "");
  stream.cv_type();  // validates the pixel format
  return stream;
}

int StreamInfo::cv_type() const {
  if (pixel_format == "mono8") return CV_8UC1;
  if (pixel_format == "bgr8") return CV_8UC3;
  if (pixel_format == "bgra8") return CV_8UC4;
  if (pixel_format == "mono16") return CV_16UC1;
  if (pixel_format == "bgr16") return CV_16UC3;
  if (pixel_format == "depth_m") return CV_32FC1;
  Fail("stream '", name, "': unknown pixel format '", pixel_format,
       "' (mono8, bgr8, bgra8, mono16, bgr16, depth_m)");
}

int64_t FrameSet::SpreadNs() const {
  if (frames.size() < 2) return 0;
  int64_t lo = std::numeric_limits<int64_t>::max(), hi = std::numeric_limits<int64_t>::min();
  for (const auto& frame : frames) {
    lo = std::min(lo, frame.timestamp_ns);
    hi = std::max(hi, frame.timestamp_ns);
  }
  return hi - lo;
}

const Frame* FrameSet::Find(const std::string& sensor) const {
  for (const auto& frame : frames) {
    if (frame.sensor == sensor) return &frame;
  }
  return nullptr;
}

const FrameSetEntry::Item* FrameSetEntry::Find(const std::string& sensor) const {
  for (const auto& item : items) {
    if (item.sensor == sensor) return &item;
  }
  return nullptr;
}

TakeWriter::TakeWriter(const std::filesystem::path& dir, const RigDescription& rig,
                       std::vector<StreamInfo> streams, nlohmann::json metadata,
                       TakeWriterOptions options)
    : dir_(dir),
      rig_(rig),
      streams_(std::move(streams)),
      metadata_(std::move(metadata)),
      options_(options) {
  if (streams_.empty()) Fail("a take needs at least one stream");
  for (auto& stream : streams_) {
    stream.cv_type();
    if (stream.width <= 0 || stream.height <= 0) Fail("stream '", stream.name, "' has no size");
    if (stream.pixel_format == "depth_m") stream.codec = ImageCodec::kExr;
    if (stream.codec == ImageCodec::kExr && stream.pixel_format != "depth_m") {
      Fail("stream '", stream.name, "': EXR frames hold depth_m only");
    }
  }
  exceptions_at_start_ = std::uncaught_exceptions();
  replaced_lock_ =
      ClaimTakeDirectory(dir_, {options_.command, options_.overwrite, options_.inputs});
  if (replaced_lock_.held()) {
    // The old take stays whole, aside, until the new one is complete.
    replaced_ = dir_;
    replaced_ += ".replaced-" + std::to_string(::getpid());
    std::error_code ec;
    std::filesystem::rename(dir_, replaced_, ec);
    if (ec) Fail("cannot move the take '", dir_.string(), "' aside: ", ec.message());
  }
  CreateDirectories(dir_);
  for (const auto& stream : streams_) CreateDirectories(dir_ / "frames" / stream.name);
  for (const auto& stream : streams_) dropped_[stream.name] = 0;
  WriteManifest("recording");
  index_ = LineAppender(dir_ / kIndex, options_.durable);
}

TakeWriter::~TakeWriter() {
  if (std::uncaught_exceptions() > exceptions_at_start_) {
    index_.Close();  // the manifest stays "recording": this take was not finished
    PutBackReplacedTake();
    return;
  }
  try {
    Close();
  } catch (...) {
    // The index already holds every complete set; a manifest left at "recording" is readable.
  }
}

void TakeWriter::PutBackReplacedTake() {
  if (replaced_.empty()) return;
  std::error_code ec;
  std::filesystem::remove_all(dir_, ec);
  if (!ec) std::filesystem::rename(replaced_, dir_, ec);
  // Where either step failed, the old take is still whole at replaced_.
  replaced_.clear();
}

void TakeWriter::WriteManifest(const std::string& state) {
  nlohmann::json manifest;
  manifest["format"] = "holocap-take";
  manifest["format_version"] = kTakeFormatVersion;
  if (!options_.command.empty()) manifest["made_by"] = options_.command;  // --overwrite's check
  manifest["state"] = state;
  manifest["updated"] = NowIso8601();
  manifest["rig"] = rig_.ToJson();
  manifest["streams"] = nlohmann::json::array();
  for (const auto& stream : streams_) manifest["streams"].push_back(stream.ToJson());
  manifest["metadata"] = metadata_;
  manifest["dropped"] = dropped_;
  manifest["frame_sets"] = sets_written_;
  manifest["first_timestamp_ns"] = first_timestamp_ns_;
  manifest["last_timestamp_ns"] = last_timestamp_ns_;
  manifest["index"] = kIndex;
  WriteFileAtomic(dir_ / kManifest, manifest.dump(2) + "\n", options_.durable);
}

void TakeWriter::Append(const FrameSet& set) {
  {
    std::lock_guard lock(mutex_);
    if (closed_) Fail("take '", dir_.string(), "' is closed");
  }
  nlohmann::json line;
  line["set"] = set.index;
  line["spread_ns"] = set.SpreadNs();
  line["frames"] = nlohmann::json::array();
  uint64_t bytes = 0;
  for (const auto& frame : set.frames) {
    auto it = std::find_if(streams_.begin(), streams_.end(),
                           [&](const StreamInfo& s) { return s.name == frame.sensor; });
    if (it == streams_.end())
      Fail("frame from '", frame.sensor, "', which is not a stream of this take");
    const StreamInfo& stream = *it;
    if (frame.image.type() != stream.cv_type() || frame.image.cols != stream.width ||
        frame.image.rows != stream.height) {
      Fail("frame from '", frame.sensor, "' is ", frame.image.cols, "x", frame.image.rows, " type ",
           frame.image.type(), ", the stream is ", stream.width, "x", stream.height, " ",
           stream.pixel_format);
    }
    std::string relative = FrameFileName(stream, set.index);
    std::filesystem::path file = dir_ / relative;
    switch (stream.codec) {
      case ImageCodec::kPng:
        WritePng(file, frame.image, options_.png_compression);
        break;
      case ImageCodec::kZstd:
        WriteZstd(file, frame.image);
        break;
      case ImageCodec::kExr:
        WriteExrDepth(file, frame.image);
        break;
    }
    std::error_code ec;
    bytes += std::filesystem::file_size(file, ec);
    line["frames"].push_back({{"sensor", frame.sensor},
                              {"file", relative},
                              {"t_ns", frame.timestamp_ns},
                              {"seq", frame.sequence}});
  }
  std::lock_guard lock(mutex_);
  index_.Append(line.dump());
  ++sets_written_;
  bytes_written_ += bytes;
  for (const auto& frame : set.frames) {
    if (first_timestamp_ns_ == 0 || frame.timestamp_ns < first_timestamp_ns_)
      first_timestamp_ns_ = frame.timestamp_ns;
    last_timestamp_ns_ = std::max(last_timestamp_ns_, frame.timestamp_ns);
  }
  if (options_.manifest_every > 0 && sets_written_ % options_.manifest_every == 0)
    WriteManifest("recording");
}

void TakeWriter::CountDropped(const std::string& sensor, int64_t count) {
  std::lock_guard lock(mutex_);
  dropped_[sensor] += count;
}

void TakeWriter::Close() {
  std::lock_guard lock(mutex_);
  if (closed_) return;
  closed_ = true;
  index_.Close();
  WriteManifest("complete");
  if (!replaced_.empty()) {
    std::error_code ec;
    std::filesystem::remove_all(replaced_, ec);
    replaced_.clear();
    replaced_lock_ = TakeLock();
  }
}

int64_t TakeWriter::sets_written() const {
  std::lock_guard lock(mutex_);
  return sets_written_;
}

uint64_t TakeWriter::bytes_written() const {
  std::lock_guard lock(mutex_);
  return bytes_written_;
}

Take Take::Open(const std::filesystem::path& dir) {
  std::error_code ec;
  if (!std::filesystem::is_directory(dir, ec)) Fail("take '", dir.string(), "' does not exist");
  if (!std::filesystem::exists(dir / kManifest)) {
    Fail("'", dir.string(), "' is not a holocap take: ", kManifest, " is missing");
  }
  std::string index_text;
  if (std::filesystem::exists(dir / kIndex)) index_text = ReadFileToString(dir / kIndex);
  return Parse(dir, ReadFileToString(dir / kManifest), index_text, [&](const std::string& file) {
    std::error_code ec;  // a name the file system refuses (too long) is a missing frame
    return std::filesystem::exists(dir / file, ec);
  });
}

Take Take::Parse(const std::filesystem::path& dir, const std::string& manifest_text,
                 const std::string& index_text,
                 const std::function<bool(const std::string& file)>& frame_exists) {
  Take take;
  take.dir_ = dir;
  nlohmann::json manifest;
  try {
    manifest = nlohmann::json::parse(manifest_text);
  } catch (const nlohmann::json::exception& e) {
    Fail("'", (dir / kManifest).string(), "' is corrupt: ", e.what());
  }
  try {
    if (manifest.value("format", "") != "holocap-take") Fail("not a holocap take manifest");
    take.format_version_ = JsonInteger<int>(manifest.at("format_version"), "format_version");
    if (take.format_version_ < 1 || take.format_version_ > kTakeFormatVersion) {
      Fail("format version ", take.format_version_, " is not supported (this holocap reads 1..",
           kTakeFormatVersion, ")");
    }
    take.state_ = manifest.value("state", "recording");
    take.rig_ = RigDescription::FromJson(manifest.at("rig"), "take.json rig");
    for (const auto& stream : manifest.at("streams")) {
      take.streams_.push_back(StreamInfo::FromJson(stream));
      const std::string& name = take.streams_.back().name;
      if (std::count_if(take.streams_.begin(), take.streams_.end(),
                        [&](const StreamInfo& s) { return s.name == name; }) > 1)
        Fail("stream '", name, "' is listed twice");
    }
    take.metadata_ = manifest.value("metadata", nlohmann::json::object());
    if (manifest.contains("dropped")) {
      if (!manifest["dropped"].is_object()) Fail("'dropped' must be an object of counts");
      for (const auto& [sensor, count] : manifest["dropped"].items())
        take.dropped_[sensor] = JsonInteger<int64_t>(count, "dropped");
    }
    if (manifest.contains("frame_sets"))
      take.manifest_frame_sets_ = JsonInteger<int64_t>(manifest["frame_sets"], "frame_sets");
  } catch (const nlohmann::json::exception& e) {
    Fail("'", (dir / kManifest).string(), "' is corrupt: ", e.what());
  } catch (const Error& e) {
    Fail("'", (dir / kManifest).string(), "': ", e.what());
  }
  take.index_present_ = !index_text.empty();
  take.ParseIndex(index_text, frame_exists);
  return take;
}

void Take::ParseIndex(const std::string& index_text,
                      const std::function<bool(const std::string& file)>& frame_exists) {
  const std::string index_file = (dir_ / kIndex).string();
  std::map<int64_t, int64_t> line_of_set;
  std::map<std::string, int64_t> line_of_file;
  int64_t line_number = 0;
  size_t start = 0;
  while (start < index_text.size()) {
    size_t end = index_text.find('\n', start);
    bool torn = end == std::string::npos;  // the last line of a killed writer
    std::string line = index_text.substr(start, torn ? std::string::npos : end - start);
    start = torn ? index_text.size() : end + 1;
    ++line_number;
    if (line.empty()) continue;
    const std::string where = Cat("'", index_file, "' line ", line_number, ": ");
    FrameSetEntry entry;
    std::string problem = torn ? "torn (it has no end of line)" : "";
    std::string damage;  // what no writer ever leaves: refused outright
    if (!torn) {
      try {
        ParseIndexLine(line, &entry, &damage);
        if (damage.empty() && problem.empty()) {
          for (const auto& item : entry.items) {
            if (!has_stream(item.sensor)) {
              problem = Cat("sensor '", item.sensor, "' is not a stream of the take");
            } else if (!frame_exists(item.file)) {
              problem = Cat("frame file '", item.file, "' is missing");
            }
            if (!problem.empty()) break;
          }
        }
      } catch (const nlohmann::json::exception& e) {
        problem = Cat("not a valid index line: ", e.what());
      } catch (const Error& e) {  // a number out of range
        problem = e.what();
      }
    }
    if (damage.empty() && problem.empty()) {
      auto [it, first] = line_of_set.emplace(entry.index, line_number);
      if (!first)
        damage =
            Cat("frame set ", entry.index, " is listed again (first on line ", it->second, ")");
    }
    for (const auto& item : entry.items) {
      if (!damage.empty()) break;
      // One file is one frame: a file named twice would be read as two frames.
      const std::string name = std::filesystem::path(item.file).lexically_normal().string();
      auto [it, first] = line_of_file.emplace(name, line_number);
      if (!first)
        damage =
            Cat("frame file '", item.file, "' is listed again (first on line ", it->second, ")");
    }
    if (!damage.empty()) Fail(where, damage);
    if (problem.empty()) {
      entries_.push_back(std::move(entry));
    } else {
      ++skipped_index_lines_;
      index_problems_.push_back(where + problem);
      torn_last_line_ = torn;
    }
  }
  std::stable_sort(
      entries_.begin(), entries_.end(),
      [](const FrameSetEntry& a, const FrameSetEntry& b) { return a.index < b.index; });
}

const StreamInfo& Take::stream(const std::string& name) const {
  for (const auto& s : streams_) {
    if (s.name == name) return s;
  }
  Fail("take '", dir_.string(), "' has no sensor named '", name, "'");
}

bool Take::has_stream(const std::string& name) const {
  return std::any_of(streams_.begin(), streams_.end(),
                     [&](const StreamInfo& s) { return s.name == name; });
}

FrameSet Take::Read(size_t i, const std::vector<std::string>& sensors) const {
  if (i >= entries_.size())
    Fail("take '", dir_.string(), "' has ", entries_.size(), " frame sets; asked for set ", i);
  for (const auto& name : sensors) stream(name);
  const FrameSetEntry& entry = entries_[i];
  FrameSet set;
  set.index = entry.index;
  for (const auto& item : entry.items) {
    if (!sensors.empty() && std::find(sensors.begin(), sensors.end(), item.sensor) == sensors.end())
      continue;
    Frame frame;
    frame.sensor = item.sensor;
    frame.timestamp_ns = item.timestamp_ns;
    frame.sequence = item.sequence;
    const StreamInfo& info = stream(item.sensor);
    CheckFrameInsideTake(item.file);
    frame.image = ReadImage(dir_ / item.file, info.shape());
    if (frame.image.type() != info.cv_type() || frame.image.cols != info.width ||
        frame.image.rows != info.height) {
      Fail("'", (dir_ / item.file).string(), "' does not match its stream (", info.width, "x",
           info.height, " ", info.pixel_format, ")");
    }
    set.frames.push_back(std::move(frame));
  }
  return set;
}

void Take::Verify() const {
  const bool cut_short = state_ != "complete";
  for (size_t i = 0; i < index_problems_.size(); ++i) {
    const bool tolerated = cut_short && torn_last_line_ && i + 1 == index_problems_.size();
    if (!tolerated) Fail(index_problems_[i]);
  }
  const auto count = static_cast<int64_t>(entries_.size());
  if (manifest_frame_sets_ >= 0 &&
      (cut_short ? count < manifest_frame_sets_ : count != manifest_frame_sets_)) {
    Fail("'", (dir_ / kManifest).string(), "' counts ", manifest_frame_sets_, " frame sets but '",
         (dir_ / kIndex).string(), "' ",
         index_present_ ? Cat("lists ", count) : std::string("is missing or empty"));
  }
  std::map<std::string, std::pair<int64_t, int64_t>> last_time;  // sensor -> set, t_ns
  for (size_t i = 0; i < entries_.size(); ++i) {
    Read(i);  // throws naming a bad frame file
    for (const auto& item : entries_[i].items) {
      CheckImageFileEnds(dir_ / item.file);
      auto [it, first] = last_time.try_emplace(item.sensor, entries_[i].index, item.timestamp_ns);
      if (!first && item.timestamp_ns < it->second.second) {
        Fail("'", (dir_ / kIndex).string(), "': the frame of '", item.sensor, "' in set ",
             entries_[i].index, " has time ", item.timestamp_ns, " ns, before set ",
             it->second.first, "'s ", it->second.second, " ns");
      }
      it->second = {entries_[i].index, item.timestamp_ns};
    }
  }
  for (const auto& s : streams_) {
    for (const auto& dir : {calib_dir(), gt_dir() / "cameras"}) {
      const std::filesystem::path file = dir / (s.name + ".cameramodel");
      if (std::filesystem::exists(file)) CameraModel::Read(file);  // throws naming the file
    }
  }
}

void Take::CheckFrameInsideTake(const std::string& file) const {
  // Without a symbolic link on the way, the index's checks (no '..', no absolute path) keep a
  // frame inside the take; with one, where it leads is checked.
  std::filesystem::path at = dir_;
  bool linked = false;
  std::error_code ec;
  for (const auto& part : std::filesystem::path(file)) {
    at /= part;
    if (std::filesystem::is_symlink(at, ec)) {
      linked = true;
      break;
    }
  }
  if (!linked) return;
  const auto root = std::filesystem::weakly_canonical(dir_, ec);
  const auto target = std::filesystem::weakly_canonical(dir_ / file, ec);
  const auto relative = target.lexically_relative(root);
  if (ec || relative.empty() || *relative.begin() == "..") {
    Fail("'", (dir_ / file).string(), "' is a symbolic link to '", target.string(),
         "', outside the take: a take's frames lie inside it");
  }
}

cv::Mat Take::ReadFrame(size_t i, const std::string& sensor) const {
  FrameSet set = Read(i, {sensor});
  if (set.frames.empty())
    Fail("frame set ", i, " of '", dir_.string(), "' has no frame from '", sensor, "' (dropped)");
  return set.frames.front().image;
}

bool Take::has_calibration() const {
  for (const auto& s : streams_) {
    if (s.role != SensorRole::kWitness &&
        !std::filesystem::exists(calib_dir() / (s.name + ".cameramodel")))
      return false;
  }
  return !streams_.empty();
}

bool Take::has_ground_truth() const { return std::filesystem::is_directory(gt_dir()); }

CameraModel Take::Camera(const std::string& sensor, bool ground_truth) const {
  stream(sensor);
  std::filesystem::path file =
      (ground_truth ? gt_dir() / "cameras" : calib_dir()) / (sensor + ".cameramodel");
  if (!std::filesystem::exists(file)) {
    Fail("take '", dir_.string(), "' has no ", ground_truth ? "ground-truth model" : "calibration",
         " for '", sensor, "' (", file.string(), " is missing)",
         ground_truth ? "" : ": run holocap calibrate");
  }
  return CameraModel::Read(file);
}

}  // namespace holocap
