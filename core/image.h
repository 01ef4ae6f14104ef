// Image files: 8/16-bit PNG and raw+zstd for colour, OpenEXR (float metres) for depth.
// Readers throw Error naming the file when it is missing, truncated or corrupt; writers are
// atomic (temporary + rename) so a crash never leaves a half-written frame under its name.
#pragma once

#include <cstdint>
#include <filesystem>
#include <opencv2/core.hpp>
#include <string>

namespace holocap {

enum class ImageCodec { kPng, kZstd, kExr };

// The file extension for a codec: ".png", ".zst", ".exr".
const char* ExtensionOf(ImageCodec codec);
ImageCodec CodecOfFile(const std::filesystem::path& file);

// PNG: CV_8UC1/3/4 or CV_16UC1/3. compression 0..9 (1 is fast and still lossless).
void WritePng(const std::filesystem::path& file, const cv::Mat& image, int compression = 1);
// Raw pixels compressed with zstd behind a small self-describing header; any cv::Mat type.
void WriteZstd(const std::filesystem::path& file, const cv::Mat& image, int level = 1);
// Single-channel CV_32F image (depth in metres; NaN = no measurement) as a FLOAT "Z" channel.
void WriteExrDepth(const std::filesystem::path& file, const cv::Mat& depth_m);

// What a file is declared to hold (a take stream's frame size and cv::Mat type).
struct ImageShape {
  int width = 0;
  int height = 0;
  int type = -1;  // CV_8UC3, ...; only its depth is compared before decoding
};

// The most pixels an image read without a declared shape may have (about 134 megapixels, more
// than any camera's imager): a header asking for more is refused before anything is decoded.
inline constexpr int64_t kMaxUndeclaredImagePixels = int64_t{1} << 27;

// Reads any of the three, by extension, with the depth/channels as stored (BGR order for PNG
// colour, as OpenCV). The file's header (PNG IHDR, EXR data window, zstd frame header) is
// checked before decoding: against `declared` where given (size and depth), else against
// kMaxUndeclaredImagePixels, so a small file that claims a huge image costs no memory.
cv::Mat ReadImage(const std::filesystem::path& file);
// Decodes PNG bytes (as stored) once their structure is complete and their header asks for no
// more than kMaxUndeclaredImagePixels pixels and what the bytes can hold; `origin` names them in
// errors. Throws Error.
cv::Mat DecodePng(const std::string& bytes, const std::string& origin);
// Bytes of any format OpenCV reads, decoded as stored (IMREAD_UNCHANGED); an empty Mat when
// they do not decode.
cv::Mat DecodeImageBytes(const std::string& bytes);
// Throws Error naming `file` when bytes follow the end of its image (after a PNG's IEND chunk,
// a zstd frame's end); no writer leaves them, so they are damage or something hidden.
void CheckImageFileEnds(const std::filesystem::path& file);
cv::Mat ReadImage(const std::filesystem::path& file, const ImageShape& declared);
// Writes by extension.
void WriteImage(const std::filesystem::path& file, const cv::Mat& image);

}  // namespace holocap
