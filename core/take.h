// The take: holocap's on-disk recording.
//
//   TAKE/take.json          manifest (format version, rig, sensors, state, counts); replaced
//                           atomically whenever it changes
//   TAKE/index.jsonl        one line per complete frame set, appended and flushed after the
//                           set's frames are on disk
//   TAKE/frames/<sensor>/<set:06d>.png|.zst|.exr
//   TAKE/calib/<sensor>.cameramodel   once calibrated
//   TAKE/gt/                only for simulated takes (true models, meshes, masks, depth)
//
// Frames are written first (each atomically), then the index line, so a take cut short by a
// crash or a full disk opens with every complete frame set.
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <vector>

#include "core/camera.h"
#include "core/fs.h"
#include "core/image.h"
#include "core/output.h"
#include "core/rig.h"

namespace holocap {

inline constexpr int kTakeFormatVersion = 1;

// How one sensor's frames are stored.
struct StreamInfo {
  std::string name;
  std::string uri;
  SensorRole role = SensorRole::kColor;
  int width = 0;
  int height = 0;
  // "mono8", "bgr8", "mono16", "bgr16", "depth_m" (CV_32F metres, NaN = none).
  std::string pixel_format = "bgr8";
  ImageCodec codec = ImageCodec::kPng;
  std::string clock = "unknown";  // the clock its timestamps are in, e.g. "CLOCK_MONOTONIC"
  std::string paired_with;        // depth sensors: their colour sensor

  nlohmann::json ToJson() const;
  static StreamInfo FromJson(const nlohmann::json& json);
  // The cv::Mat type frames of this stream must have.
  int cv_type() const;
  // Size and type its frame files must declare in their headers.
  ImageShape shape() const { return {width, height, cv_type()}; }
};

struct Frame {
  std::string sensor;
  cv::Mat image;
  int64_t timestamp_ns = 0;  // in the stream's clock
  uint64_t sequence = 0;     // the sensor's own frame counter (gaps = drops)
};

struct FrameSet {
  int64_t index = 0;          // frame-set number within the take
  std::vector<Frame> frames;  // one per sensor present
  // Largest minus smallest timestamp of its frames (0 for fewer than two).
  int64_t SpreadNs() const;
  const Frame* Find(const std::string& sensor) const;
};

// What the index says of one frame set.
struct FrameSetEntry {
  int64_t index = 0;
  struct Item {
    std::string sensor;
    std::string file;  // relative to the take
    int64_t timestamp_ns = 0;
    uint64_t sequence = 0;
  };
  std::vector<Item> items;
  int64_t spread_ns = 0;
  const Item* Find(const std::string& sensor) const;
};

struct TakeWriterOptions {
  bool durable = false;     // fsync frames and index lines (power-loss safety, slower)
  int png_compression = 1;  // 0..9
  int manifest_every = 30;  // rewrite take.json every N sets (drop counts stay current)
  bool overwrite = false;   // replace an existing take made by import or sim (never a capture)
  std::string command = "write";              // named in messages and the take's lock
  std::vector<std::filesystem::path> inputs;  // never under the take (core/output.h)
};

class TakeWriter {
 public:
  // Creates the take directory and writes the first manifest. Throws Error where
  // ClaimTakeDirectory (core/output.h) refuses the directory or it cannot be written. A take
  // being replaced (options.overwrite) is moved aside to DIR.replaced-PID, locked, and removed
  // only when Close() completes the new take; it is moved back if the new one is abandoned by
  // an exception.
  TakeWriter(const std::filesystem::path& dir, const RigDescription& rig,
             std::vector<StreamInfo> streams, nlohmann::json metadata = nlohmann::json::object(),
             TakeWriterOptions options = {});
  // Closes if still open (errors are swallowed there: call Close()); while an exception
  // unwinds, the take is left "recording" instead, and a replaced take is put back.
  ~TakeWriter();
  TakeWriter(const TakeWriter&) = delete;
  TakeWriter& operator=(const TakeWriter&) = delete;

  // Writes the set's frames then its index line. Frames must match their StreamInfo. Safe to
  // call from several threads (sets may arrive out of order). Throws Error on failure; the
  // take on disk then still holds every earlier complete set.
  void Append(const FrameSet& set);
  // Records frames a sensor lost (dropped, incomplete, not delivered).
  void CountDropped(const std::string& sensor, int64_t count);
  // Final manifest (state "complete"). Idempotent.
  void Close();

  const std::filesystem::path& dir() const { return dir_; }
  bool replacing() const { return !replaced_.empty(); }  // an older take waits aside
  int64_t sets_written() const;
  uint64_t bytes_written() const;
  const std::vector<StreamInfo>& streams() const { return streams_; }

 private:
  void WriteManifest(const std::string& state);

  void PutBackReplacedTake();

  std::filesystem::path dir_;
  std::filesystem::path replaced_;  // the take this one replaces, moved aside until Close()
  TakeLock replaced_lock_;
  int exceptions_at_start_ = 0;
  RigDescription rig_;
  std::vector<StreamInfo> streams_;
  nlohmann::json metadata_;
  TakeWriterOptions options_;
  mutable std::mutex mutex_;
  LineAppender index_;
  std::map<std::string, int64_t> dropped_;
  int64_t sets_written_ = 0;
  uint64_t bytes_written_ = 0;
  int64_t first_timestamp_ns_ = 0;
  int64_t last_timestamp_ns_ = 0;
  bool closed_ = false;
};

class Take {
 public:
  // Opens a take; throws Error for a missing/corrupt manifest or unknown format version, and for
  // an index that names a frame file outside the take (an absolute path, a '..' step), a frame
  // set twice or a sensor twice in one set. Index lines that are truncated or name missing
  // frame files are skipped and counted (a take cut short still opens): Verify refuses them.
  static Take Open(const std::filesystem::path& dir);
  // Open's parser on the text of take.json and index.jsonl (empty: no index). `dir` names the
  // take in errors; `frame_exists` says whether a file an index line names (relative to the
  // take) is there.
  static Take Parse(const std::filesystem::path& dir, const std::string& manifest_text,
                    const std::string& index_text,
                    const std::function<bool(const std::string& file)>& frame_exists);

  const std::filesystem::path& dir() const { return dir_; }
  int format_version() const { return format_version_; }
  const std::string& state() const { return state_; }  // "recording" (cut short) | "complete"
  const RigDescription& rig() const { return rig_; }
  const std::vector<StreamInfo>& streams() const { return streams_; }
  const StreamInfo& stream(const std::string& name) const;  // throws Error if absent
  bool has_stream(const std::string& name) const;
  const nlohmann::json& metadata() const { return metadata_; }
  const std::map<std::string, int64_t>& dropped() const { return dropped_; }
  int64_t skipped_index_lines() const { return skipped_index_lines_; }
  // Why each skipped index line was skipped ("line 4: ..."), in file order.
  const std::vector<std::string>& index_problems() const { return index_problems_; }
  // The number of frame sets take.json counts (-1 where it does not say).
  int64_t manifest_frame_sets() const { return manifest_frame_sets_; }

  // Checks that nothing the take recorded is lost: no index line skipped (but the torn last
  // line a writer cut short leaves), as many frame sets as take.json counts (at least as many
  // while still "recording", whose manifest lags), every frame present, decodable and of its
  // stream's size and format, every calibration and ground-truth model readable and valid.
  // Throws Error naming the first damage: the file and, for the index, the line.
  void Verify() const;
  size_t size() const { return entries_.size(); }  // complete frame sets
  const FrameSetEntry& entry(size_t i) const { return entries_.at(i); }
  const std::vector<FrameSetEntry>& entries() const { return entries_; }

  // Reads set i (all sensors, or those named). Throws Error naming the file on a bad frame.
  FrameSet Read(size_t i, const std::vector<std::string>& sensors = {}) const;
  cv::Mat ReadFrame(size_t i, const std::string& sensor) const;

  std::filesystem::path calib_dir() const { return dir_ / "calib"; }
  std::filesystem::path gt_dir() const { return dir_ / "gt"; }
  bool has_calibration() const;  // every colour/depth stream has calib/<name>.cameramodel
  bool has_ground_truth() const;
  // calib/<sensor>.cameramodel, or gt/cameras/<sensor>.cameramodel with `ground_truth`.
  CameraModel Camera(const std::string& sensor, bool ground_truth = false) const;

 private:
  // Throws Error when the index's frame file `file` leads outside the take through a symbolic
  // link.
  void CheckFrameInsideTake(const std::string& file) const;
  void ParseIndex(const std::string& index_text,
                  const std::function<bool(const std::string& file)>& frame_exists);

  std::filesystem::path dir_;
  int format_version_ = 0;
  std::string state_;
  RigDescription rig_;
  std::vector<StreamInfo> streams_;
  nlohmann::json metadata_;
  std::map<std::string, int64_t> dropped_;
  std::vector<FrameSetEntry> entries_;
  int64_t skipped_index_lines_ = 0;
  std::vector<std::string> index_problems_;
  bool torn_last_line_ = false;
  int64_t manifest_frame_sets_ = -1;
  bool index_present_ = false;
};

}  // namespace holocap
