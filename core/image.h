// Image files: 8/16-bit PNG and raw+zstd for colour, OpenEXR (float metres) for depth.
// Readers throw Error naming the file when it is missing, truncated or corrupt; writers are
// atomic (temporary + rename) so a crash never leaves a half-written frame under its name.
#pragma once

#include <filesystem>
#include <opencv2/core.hpp>

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

// Reads any of the three, by extension, with the depth/channels as stored (BGR order for PNG
// colour, as OpenCV).
cv::Mat ReadImage(const std::filesystem::path& file);
// Writes by extension.
void WriteImage(const std::filesystem::path& file, const cv::Mat& image);

}  // namespace holocap
