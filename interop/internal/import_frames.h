// What the importers share (interop/ only): which files are images, the number in a file's
// name, reading a source image, and turning the images of one camera into one stream of a take
// with every frame checked against it.
#pragma once

#include <cstdint>
#include <filesystem>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <vector>

#include "core/take.h"

namespace holocap::interop_internal {

// The file's extension in lower case (".jpg").
std::string LowerExtension(const std::filesystem::path& file);
// By extension: the formats an import reads (.png .jpg .jpeg .bmp .tif .tiff .ppm .pgm).
bool IsImageFile(const std::filesystem::path& file);
// The image files directly in `folder`, sorted by name (none when it cannot be read).
std::vector<std::filesystem::path> ImageFilesIn(const std::filesystem::path& folder);
// The trailing number of a file's stem ("image0042" -> 42), if any.
std::optional<int64_t> TrailingNumber(const std::filesystem::path& file);
// The image as stored (8/16-bit, grey, colour or with alpha). Throws Error naming the file when
// it is missing, cannot be decoded, or is cut short (a PNG without its end, a JPEG whose last
// scan has no end-of-image marker: libjpeg would fill the rest with grey).
cv::Mat ReadSourceImage(const std::filesystem::path& file);
// Letters, digits, '_', '-', '.' kept, anything else '_' ("cam" for an empty text).
std::string SanitizedName(const std::string& text);

// The pixel format a take stores `image` in ("mono8", "bgr8", "bgra8", "mono16", "bgr16"):
// 16-bit alpha is dropped (takes hold alpha at 8 bits). Throws Error naming `origin` for
// other types.
struct PixelFormat {
  std::string name;
  bool drops_alpha = false;
};
PixelFormat PixelFormatOf(const cv::Mat& image, const std::string& origin);

// Alpha channels met while conforming frames, for the import's notes.
struct AlphaCounts {
  int64_t dropped = 0;  // 16-bit images whose alpha was dropped
  int64_t kept = 0;     // bgra8 images kept with their alpha
  void AddNotes(std::vector<std::string>* notes) const;
};

// `image` as a frame of `stream`: its size and pixel format must be the stream's (`expected`
// says where the stream's came from, e.g. "is calibrated for"), 16-bit alpha is dropped.
// Throws Error naming `origin` and the camera.
cv::Mat ConformedFrame(cv::Mat image, const StreamInfo& stream, const std::string& origin,
                       const std::string& expected, AlphaCounts* alpha);

// A colour sensor `sensor` of an imported take (URI "import:<format>#<sensor>", PNG frames)
// added to the rig and its streams.
void AddImportedStream(const std::string& sensor, const std::string& format, int width, int height,
                       const std::string& pixel_format, const std::string& clock,
                       RigDescription* rig, std::vector<StreamInfo>* streams);

// The writer settings of an import: PNG frames (lossless), replacing only an imported take,
// and the inputs that may not lie under the take.
TakeWriterOptions ImportWriterOptions(int png_compression, bool overwrite,
                                      std::vector<std::filesystem::path> inputs);

}  // namespace holocap::interop_internal
