// A take's colour frames as image folders or one MP4 per camera (see interop.h).
#include <cstdio>
#include <memory>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <set>

#include "core/check_option.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/image.h"
#include "core/output.h"
#include "core/take.h"
#include "core/video.h"
#include "interop/interop.h"

namespace holocap {
namespace {

// The frame as 8 bits (JPEG and H.264 hold no more), and for a video as BGR; each conversion
// counted once per camera in `notes`.
cv::Mat EightBit(const cv::Mat& frame, bool bgr, const std::string& sensor,
                 std::set<std::string>* notes) {
  cv::Mat image = frame;
  if (image.depth() == CV_16U) {
    image.convertTo(image, CV_8U, 1.0 / 257.0);
    notes->insert(Cat(sensor, ": 16-bit frames written as 8-bit (value / 257)"));
  }
  if (image.channels() == 4) {
    cv::cvtColor(image, image, cv::COLOR_BGRA2BGR);
    notes->insert(Cat(sensor, ": alpha dropped"));
  }
  if (bgr && image.channels() == 1) {
    cv::cvtColor(image, image, cv::COLOR_GRAY2BGR);
    notes->insert(Cat(sensor, ": grey frames written as colour video"));
  }
  return image;
}

}  // namespace

std::string ExportedImageName(int64_t set_index, const std::string& format) {
  char buffer[32];
  std::snprintf(buffer, sizeof(buffer), "%06lld.", static_cast<long long>(set_index));
  return buffer + format;
}

void ImageExportOptions::Check() const {
  HOLOCAP_CHECK_OPTION(format == "jpg" || format == "png", format, "jpg or png");
  HOLOCAP_CHECK_OPTION_IN(jpeg_quality, 1, 100);
  HOLOCAP_CHECK_OPTION_IN(crf, 0, 51);
  HOLOCAP_CHECK_OPTION_GE(fps, 0, "0: the take's");
}

ImageExportSummary ExportImages(const fs::path& take_dir, const fs::path& out_dir,
                                const ImageExportOptions& options, Report* report) {
  options.Check();
  const Take take = Take::Open(take_dir);
  std::vector<const StreamInfo*> streams;
  if (options.sensors.empty()) {
    for (const auto& stream : take.streams()) {
      if (stream.role == SensorRole::kColor) streams.push_back(&stream);
    }
  } else {
    for (const auto& sensor : options.sensors) {
      const StreamInfo& stream = take.stream(sensor);
      if (stream.role != SensorRole::kColor)
        Fail("sensor '", sensor, "' is ", ToString(stream.role), ", not a colour camera");
      streams.push_back(&stream);
    }
  }
  if (streams.empty()) Fail("take '", take_dir.string(), "' has no colour camera to export");
  const double fps = options.fps > 0 ? options.fps : take.rig().fps;
  if (options.video) {
    for (const StreamInfo* stream : streams) {
      if (stream->width % 2 != 0 || stream->height % 2 != 0) {
        Fail("camera '", stream->name, "' is ", stream->width, "x", stream->height,
             "; H.264 video needs an even width and height (export it as images)");
      }
    }
  }
  OutputRequest request;
  request.command = "export";
  request.overwrite = options.overwrite;
  request.inputs = {take_dir};
  request.source = take_dir;
  const OutputDirectory claimed = OutputDirectory::Claim(out_dir, request);
  if (report != nullptr) {
    report->SetFailureDestination(out_dir / "report.json");
    report->options() = {{"format", options.video ? "mp4" : options.format},
                         {"take", take_dir.string()},
                         {"jpeg_quality", options.jpeg_quality},
                         {"crf", options.crf},
                         {"fps", fps}};
  }
  ImageExportSummary summary;
  std::set<std::string> notes;
  if (options.video) {
    std::vector<std::unique_ptr<Mp4Writer>> writers;
    writers.reserve(streams.size());
    for (const StreamInfo* stream : streams) {
      writers.push_back(std::make_unique<Mp4Writer>(
          out_dir / (stream->name + ".mp4"), stream->width, stream->height, fps, options.crf));
    }
    for (size_t i = 0; i < take.size(); ++i) {
      bool complete = true;
      for (const StreamInfo* stream : streams)
        complete = complete && take.entry(i).Find(stream->name) != nullptr;
      if (!complete) {
        ++summary.sets_left_out;
        continue;
      }
      for (size_t s = 0; s < streams.size(); ++s) {
        writers[s]->Write(
            EightBit(take.ReadFrame(i, streams[s]->name), true, streams[s]->name, &notes));
        ++summary.images;
      }
    }
    for (auto& writer : writers) writer->Close();
    if (summary.sets_left_out > 0) {
      notes.insert(Cat(summary.sets_left_out,
                       " frame set(s) missing a camera left out (a video has no gaps)"));
    }
  } else {
    const std::vector<int> jpeg = {cv::IMWRITE_JPEG_QUALITY, options.jpeg_quality};
    for (size_t i = 0; i < take.size(); ++i) {
      for (const StreamInfo* stream : streams) {
        if (take.entry(i).Find(stream->name) == nullptr) continue;
        const fs::path file =
            out_dir / stream->name / ExportedImageName(take.entry(i).index, options.format);
        CreateDirectories(file.parent_path());
        const cv::Mat frame = take.ReadFrame(i, stream->name);
        if (options.format == "png") {
          WritePng(file, frame);
        } else {
          std::vector<uint8_t> bytes;
          cv::imencode(".jpg", EightBit(frame, false, stream->name, &notes), bytes, jpeg);
          WriteFileAtomic(
              file, std::string_view(reinterpret_cast<const char*>(bytes.data()), bytes.size()));
        }
        ++summary.images;
      }
    }
  }
  summary.cameras = static_cast<int>(streams.size());
  summary.notes.assign(notes.begin(), notes.end());
  std::string message = Cat(
      "exported ", summary.cameras, " camera(s), ", summary.images, " frame(s) as ",
      options.video ? Cat("MP4 (H.264, crf ", options.crf, ", ", fps, " fps)")
                    : (options.format == "jpg" ? Cat("JPEG (quality ", options.jpeg_quality, ")")
                                               : std::string("PNG")));
  for (const auto& note : summary.notes) message += "; " + note;
  summary.End(Termination::kSuccess, std::move(message));
  if (report != nullptr) {
    report->plan() = {{"cameras", summary.cameras},
                      {"frames", summary.images},
                      {"sets_left_out", summary.sets_left_out},
                      {"notes", summary.notes}};
    report->SetSummary(summary);
  }
  return summary;
}

}  // namespace holocap
