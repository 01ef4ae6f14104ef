// H.264 MP4 files written through ffmpeg: BGR frames are piped raw to `ffmpeg` (libx264,
// yuv420p, +faststart), into FILE.partial.mp4, renamed to FILE only when ffmpeg succeeds, so a
// failed or abandoned video never stands under the asked name.
#pragma once

#include <cstdio>
#include <filesystem>
#include <opencv2/core.hpp>

namespace holocap {

class Mp4Writer {
 public:
  // Starts ffmpeg; throws Error when it cannot. Width and height must be even (yuv420p).
  Mp4Writer(const std::filesystem::path& file, int width, int height, double fps, int crf);
  // Without Close(): ffmpeg is stopped and the partial file removed.
  ~Mp4Writer();
  Mp4Writer(const Mp4Writer&) = delete;
  Mp4Writer& operator=(const Mp4Writer&) = delete;

  // One 8-bit BGR frame of the size given. Throws Error when ffmpeg stopped reading.
  void Write(const cv::Mat& bgr);
  // Waits for ffmpeg and renames the file; throws Error (the partial file removed) when ffmpeg
  // failed.
  void Close();

 private:
  std::filesystem::path file_, temp_;
  FILE* pipe_ = nullptr;
};

}  // namespace holocap
