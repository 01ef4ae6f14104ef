// What a site's files claim, checked before they are believed: its manifest (IsWebSite) and the
// frame records a sharded export merges (CheckWebFrameRecord).
#include <cmath>
#include <nlohmann/json.hpp>

#include "core/error.h"
#include "core/fs.h"
#include "playback/playback.h"

namespace holocap {

namespace fs = std::filesystem;

bool IsWebSite(const fs::path& dir, std::string* why) {
  const fs::path manifest = dir / "manifest.json";
  if (!fs::is_regular_file(manifest) || !fs::is_regular_file(dir / "index.html")) {
    *why = "'" + dir.string() + "' is not a site made by holocap export web (no manifest.json " +
           "and index.html)";
    return false;
  }
  const nlohmann::json json = nlohmann::json::parse(ReadFileToString(manifest), nullptr, false);
  if (json.is_discarded() || !json.is_object() || !json.contains("format") ||
      json["format"] != "holocap-stream") {
    *why = manifest.string() + " is not a holocap stream manifest";
    return false;
  }
  const int version = json.contains("version") && json["version"].is_number_integer() &&
                              json["version"].get<int64_t>() >= 0 &&
                              json["version"].get<int64_t>() <= 1000
                          ? json["version"].get<int>()
                          : -1;
  if (version < kOldestWebStreamFormatVersion || version > kWebStreamFormatVersion) {
    *why = manifest.string() + " is stream format version " +
           Printable(json.value("version", nlohmann::json())
                         .dump(-1, ' ', false, nlohmann::json::error_handler_t::replace)) +
           "; this holocap plays versions " + std::to_string(kOldestWebStreamFormatVersion) +
           " to " + std::to_string(kWebStreamFormatVersion);
    return false;
  }
  return true;
}

void CheckWebFrameRecord(const nlohmann::json& frame, const fs::path& site,
                         const std::string& folder, const std::string& stream, int64_t set) {
  const auto refuse = [&](const std::string& why) {
    Fail("'", site.string(), "': the frame record of set ", set, " for stream '", Printable(stream),
         "' ", why, "; run the export's group again (--redo)");
  };
  if (!frame.is_object() || !frame.contains("chunk")) refuse("has no chunk");
  const nlohmann::json& chunk = frame["chunk"];
  if (!chunk.is_null()) {
    if (!chunk.is_object() || !chunk.contains("file") || !chunk["file"].is_string() ||
        !chunk.contains("bytes") || !chunk["bytes"].is_number_unsigned())
      refuse("lists a chunk without its file name and size");
    const std::string file = chunk["file"].get<std::string>();
    const bool plain =
        !file.empty() && file.size() <= 64 &&
        file.find_first_not_of("0123456789abcdefghijklmnopqrstuvwxyz_-.") == std::string::npos &&
        file.find("..") == std::string::npos && file.front() != '.';
    if (!plain) refuse(Cat("names the chunk '", Printable(file), "', which is no plain file name"));
    const fs::path path = site / folder / file;
    std::error_code ec;
    const bool regular = fs::is_regular_file(fs::symlink_status(path, ec));
    if (!regular || fs::file_size(path, ec) != chunk["bytes"].get<uint64_t>()) {
      refuse(Cat("counts ", chunk["bytes"].get<uint64_t>(), " bytes in '", path.string(),
                 "', which ", regular ? "holds another size" : "is no regular file"));
    }
    if (chunk.contains("key") && !chunk["key"].is_boolean())
      refuse("marks its chunk a key frame with no true or false");
    for (const char* field : {"squared", "count"})
      if (!frame.contains(field) || !frame[field].is_number())
        refuse(Cat("has no number '", field, "'"));
    const double squared = frame["squared"].get<double>();
    const double count = frame["count"].get<double>();
    if (!std::isfinite(squared) || squared < 0 || !(count >= 0) || count > 1e12 ||
        count != std::floor(count) || squared > count)
      refuse(Cat("holds a squared error of ", squared, " over ", count,
                 " values, which no image gives (0 to 1 a value)"));
    if (frame.contains("camera")) {
      // Against the camera: squared errors of 0..1 values over `count` values each.
      const nlohmann::json& camera = frame["camera"];
      const bool numbers = camera.is_object() && camera.contains("count") &&
                           camera["count"].is_number() && camera.contains("cameras") &&
                           camera["cameras"].is_array();
      if (!numbers) refuse("holds a score against the camera without its cameras and count");
      const double values = camera["count"].get<double>();
      if (!(values >= 0) || values > 1e12 || values != std::floor(values))
        refuse(Cat("scores ", values, " values against the camera, not a count"));
      for (const char* field : {"native", "streamed", "background"}) {
        if (!camera.contains(field) || !camera[field].is_number() ||
            !std::isfinite(camera[field].get<double>()) || camera[field].get<double>() < 0 ||
            camera[field].get<double>() > values)
          refuse(Cat("holds a squared error '", field, "' against the camera that no image gives"));
      }
    }
    for (const char* field : {"max_position_error_mm", "faces", "gaussians", "stored"}) {
      if (!frame.contains(field)) continue;
      if (!frame[field].is_number() || !std::isfinite(frame[field].get<double>()) ||
          frame[field].get<double>() < 0)
        refuse(Cat("holds '", field, "' ", frame[field].dump(), ", not a finite count"));
    }
  }
}

}  // namespace holocap
