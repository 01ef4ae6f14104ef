#include "core/video.h"

#include <sys/wait.h>

#include "core/error.h"

namespace holocap {

Mp4Writer::Mp4Writer(const std::filesystem::path& file, int width, int height, double fps, int crf)
    : file_(file), temp_(file) {
  temp_ += ".partial.mp4";
  const std::string command =
      Cat("ffmpeg -hide_banner -loglevel error -y -f rawvideo -pix_fmt bgr24 -s ", width, "x",
          height, " -r ", fps, " -i - -c:v libx264 -preset veryfast -crf ", crf,
          " -pix_fmt yuv420p -movflags +faststart '", temp_.string(), "'");
  pipe_ = popen(command.c_str(), "w");
  if (pipe_ == nullptr) Fail("cannot start ffmpeg for ", file.string());
}

Mp4Writer::~Mp4Writer() {
  if (pipe_ != nullptr) {
    pclose(pipe_);
    std::error_code ec;
    std::filesystem::remove(temp_, ec);
  }
}

void Mp4Writer::Write(const cv::Mat& bgr) {
  const cv::Mat contiguous = bgr.isContinuous() ? bgr : bgr.clone();
  const size_t bytes = contiguous.total() * contiguous.elemSize();
  if (std::fwrite(contiguous.data, 1, bytes, pipe_) != bytes)
    Fail("ffmpeg stopped reading frames for ", file_.string());
}

void Mp4Writer::Close() {
  const int status = pclose(pipe_);
  pipe_ = nullptr;
  if (status != 0) {
    std::error_code ec;
    std::filesystem::remove(temp_, ec);
    Fail("ffmpeg failed writing ", file_.string(), " (exit status ",
         WIFEXITED(status) ? WEXITSTATUS(status) : status, ")");
  }
  std::filesystem::rename(temp_, file_);
}

}  // namespace holocap
