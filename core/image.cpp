#include "core/image.h"

#include <ImfChannelList.h>
#include <ImfFrameBuffer.h>
#include <ImfHeader.h>
#include <ImfInputFile.h>
#include <ImfOutputFile.h>
#include <unistd.h>
#include <zstd.h>

#include <cstring>
#include <opencv2/imgcodecs.hpp>
#include <random>

#include "core/error.h"
#include "core/fs.h"

namespace holocap {
namespace {

constexpr char kZstdMagic[4] = {'H', 'C', 'Z', '1'};

struct ZstdHeader {
  char magic[4];
  int32_t rows;
  int32_t cols;
  int32_t type;
};

}  // namespace

const char* ExtensionOf(ImageCodec codec) {
  switch (codec) {
    case ImageCodec::kPng:
      return ".png";
    case ImageCodec::kZstd:
      return ".zst";
    case ImageCodec::kExr:
      return ".exr";
  }
  return "";
}

ImageCodec CodecOfFile(const std::filesystem::path& file) {
  std::string ext = file.extension().string();
  if (ext == ".png") return ImageCodec::kPng;
  if (ext == ".zst") return ImageCodec::kZstd;
  if (ext == ".exr") return ImageCodec::kExr;
  Fail("'", file.string(), "': unknown image file type '", ext, "'");
}

void WritePng(const std::filesystem::path& file, const cv::Mat& image, int compression) {
  if (image.empty()) Fail("cannot write an empty image to '", file.string(), "'");
  if (image.depth() != CV_8U && image.depth() != CV_16U) {
    Fail("PNG holds 8- or 16-bit images only ('", file.string(), "')");
  }
  std::vector<uchar> bytes;
  if (!cv::imencode(".png", image, bytes, {cv::IMWRITE_PNG_COMPRESSION, compression})) {
    Fail("cannot encode PNG for '", file.string(), "'");
  }
  WriteFileAtomic(file,
                  std::string_view(reinterpret_cast<const char*>(bytes.data()), bytes.size()));
}

void WriteZstd(const std::filesystem::path& file, const cv::Mat& image, int level) {
  if (image.empty()) Fail("cannot write an empty image to '", file.string(), "'");
  cv::Mat contiguous = image.isContinuous() ? image : image.clone();
  size_t raw_size = contiguous.total() * contiguous.elemSize();
  ZstdHeader header;
  std::memcpy(header.magic, kZstdMagic, 4);
  header.rows = contiguous.rows;
  header.cols = contiguous.cols;
  header.type = contiguous.type();
  std::string bytes(sizeof(header) + ZSTD_compressBound(raw_size), '\0');
  std::memcpy(bytes.data(), &header, sizeof(header));
  size_t n = ZSTD_compress(bytes.data() + sizeof(header), bytes.size() - sizeof(header),
                           contiguous.data, raw_size, level);
  if (ZSTD_isError(n))
    Fail("zstd compression failed for '", file.string(), "': ", ZSTD_getErrorName(n));
  bytes.resize(sizeof(header) + n);
  WriteFileAtomic(file, bytes);
}

void WriteExrDepth(const std::filesystem::path& file, const cv::Mat& depth_m) {
  if (depth_m.type() != CV_32FC1) Fail("depth for '", file.string(), "' must be CV_32FC1 metres");
  cv::Mat contiguous = depth_m.isContinuous() ? depth_m : depth_m.clone();
  thread_local std::mt19937_64 random{std::random_device{}()};
  std::filesystem::path temp = file;
  temp += ".tmp" + std::to_string(::getpid()) + "_" + std::to_string(random() % 1000000007);
  try {
    Imf::Header header(contiguous.cols, contiguous.rows);
    header.channels().insert("Z", Imf::Channel(Imf::FLOAT));
    header.compression() = Imf::ZIP_COMPRESSION;
    Imf::OutputFile out(temp.c_str(), header);
    Imf::FrameBuffer buffer;
    buffer.insert("Z", Imf::Slice(Imf::FLOAT, reinterpret_cast<char*>(contiguous.ptr<float>()),
                                  sizeof(float), sizeof(float) * contiguous.cols));
    out.setFrameBuffer(buffer);
    out.writePixels(contiguous.rows);
  } catch (const std::exception& e) {
    std::filesystem::remove(temp);
    Fail("cannot write '", file.string(), "': ", e.what());
  }
  std::error_code ec;
  std::filesystem::rename(temp, file, ec);
  if (ec) {
    std::filesystem::remove(temp);
    Fail("cannot replace '", file.string(), "': ", ec.message());
  }
}

namespace {

const char* DepthName(int depth) {
  switch (depth) {
    case CV_8U:
      return "8-bit";
    case CV_16U:
      return "16-bit";
    case CV_32F:
      return "32-bit float";
  }
  return "other";
}

// Refuses, before any pixel is decoded, a header whose size (or depth) is not the declared one,
// or, with nothing declared, one of more than kMaxUndeclaredImagePixels pixels.
void CheckHeader(const std::filesystem::path& file, const char* kind, int64_t width, int64_t height,
                 int depth, const ImageShape* declared) {
  const std::string what =
      Cat("'", file.string(), "': its ", kind, " header says ", width, "x", height);
  if (declared == nullptr) {
    if (width <= 0 || height <= 0 || width * height > kMaxUndeclaredImagePixels)
      Fail(what, ", more than the ", kMaxUndeclaredImagePixels, " pixels an image may have");
    return;
  }
  const int declared_depth = CV_MAT_DEPTH(declared->type);
  if (width != declared->width || height != declared->height ||
      (declared->type >= 0 && depth != declared_depth)) {
    Fail(what, " ", DepthName(depth), " but its stream's frames are ", declared->width, "x",
         declared->height, " ", DepthName(declared_depth));
  }
}

cv::Mat ReadExr(const std::filesystem::path& file, const ImageShape* declared) {
  if (!std::filesystem::exists(file)) Fail("'", file.string(), "' does not exist");
  try {
    Imf::InputFile in(file.c_str());
    const Imath::Box2i window = in.header().dataWindow();
    const int64_t wide = int64_t{window.max.x} - window.min.x + 1;
    const int64_t high = int64_t{window.max.y} - window.min.y + 1;
    CheckHeader(file, "OpenEXR", wide, high, CV_32F, declared);
    int width = static_cast<int>(wide);
    int height = static_cast<int>(high);
    const char* channel = in.header().channels().findChannel("Z") ? "Z" : nullptr;
    if (channel == nullptr) {
      for (auto it = in.header().channels().begin(); it != in.header().channels().end(); ++it) {
        channel = it.name();
        break;
      }
    }
    if (channel == nullptr) Fail("'", file.string(), "' has no channels");
    cv::Mat depth(height, width, CV_32FC1);
    Imf::FrameBuffer buffer;
    char* base = reinterpret_cast<char*>(depth.ptr<float>()) -
                 (window.min.x + static_cast<ptrdiff_t>(window.min.y) * width) * sizeof(float);
    buffer.insert(channel, Imf::Slice(Imf::FLOAT, base, sizeof(float), sizeof(float) * width));
    in.setFrameBuffer(buffer);
    if (!in.isComplete()) Fail("'", file.string(), "' is truncated");
    in.readPixels(window.min.y, window.max.y);
    return depth;
  } catch (const Error&) {
    throw;
  } catch (const std::exception& e) {
    Fail("'", file.string(), "' is not a readable OpenEXR file: ", e.what());
  }
}

cv::Mat ReadZstd(const std::filesystem::path& file, const ImageShape* declared) {
  std::string bytes = ReadFileToString(file);
  ZstdHeader header;
  if (bytes.size() < sizeof(header)) Fail("'", file.string(), "' is truncated");
  std::memcpy(&header, bytes.data(), sizeof(header));
  if (std::memcmp(header.magic, kZstdMagic, 4) != 0)
    Fail("'", file.string(), "' is not a holocap zstd frame");
  if (header.rows <= 0 || header.cols <= 0 || header.rows > 1 << 16 || header.cols > 1 << 16) {
    Fail("'", file.string(), "' has a corrupt header");
  }
  CheckHeader(file, "zstd frame", header.cols, header.rows, CV_MAT_DEPTH(header.type), declared);
  cv::Mat image;
  try {
    image.create(header.rows, header.cols, header.type);
  } catch (const cv::Exception&) {
    Fail("'", file.string(), "' has a corrupt header");
  }
  size_t raw_size = image.total() * image.elemSize();
  size_t n = ZSTD_decompress(image.data, raw_size, bytes.data() + sizeof(header),
                             bytes.size() - sizeof(header));
  if (ZSTD_isError(n) || n != raw_size) Fail("'", file.string(), "' is truncated or corrupt");
  return image;
}

// Walks a PNG's chunk structure (signature, then length/type/data/CRC up to IEND) so that a
// truncated or damaged file is refused before the decoder sees it; libpng would otherwise
// print its own diagnostics to stderr before failing.
bool PngStructureIsComplete(const std::string& bytes) {
  static constexpr unsigned char kSignature[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  if (bytes.size() < 8 || std::memcmp(bytes.data(), kSignature, 8) != 0) return false;
  size_t at = 8;
  while (at + 12 <= bytes.size()) {
    const auto* p = reinterpret_cast<const unsigned char*>(bytes.data() + at);
    uint64_t length =
        (uint64_t{p[0]} << 24) | (uint64_t{p[1]} << 16) | (uint64_t{p[2]} << 8) | p[3];
    if (length > 0x7fffffffu || at + 12 + length > bytes.size()) return false;
    if (std::memcmp(p + 4, "IEND", 4) == 0) return true;
    at += 12 + length;
  }
  return false;
}

uint32_t BigEndian32(const unsigned char* p) {
  return (uint32_t{p[0]} << 24) | (uint32_t{p[1]} << 16) | (uint32_t{p[2]} << 8) | p[3];
}

// The PNG's IHDR (the first chunk, which PngStructureIsComplete has found complete).
void CheckPngHeader(const std::filesystem::path& file, const std::string& bytes,
                    const ImageShape* declared) {
  const auto* p = reinterpret_cast<const unsigned char*>(bytes.data()) + 8;
  if (bytes.size() < 8 + 8 + 13 || BigEndian32(p) != 13 || std::memcmp(p + 4, "IHDR", 4) != 0)
    Fail("'", file.string(), "' is not a PNG image: it does not start with its IHDR header");
  const int bit_depth = p[16];
  const int64_t width = BigEndian32(p + 8), height = BigEndian32(p + 12);
  CheckHeader(file, "PNG", width, height, bit_depth == 16 ? CV_16U : CV_8U, declared);
  // Deflate shrinks data at most 1032 times: a header asking for more pixels than the file's
  // bytes can hold is refused before the decoder allocates them.
  constexpr int64_t kMostDeflateRatio = 1032;
  const int64_t raw = height * (1 + width * 4 * (bit_depth == 16 ? 2 : 1));
  const auto size = static_cast<int64_t>(bytes.size());
  if (raw / 4 > kMostDeflateRatio * size + (int64_t{1} << 16)) {
    Fail("'", file.string(), "': its PNG header says ", width, "x", height, ", more than its ",
         size, " bytes can hold");
  }
}

}  // namespace

cv::Mat DecodeImageBytes(const std::string& bytes) {
  cv::Mat image;
  try {
    image = cv::imdecode(
        cv::Mat(1, static_cast<int>(bytes.size()), CV_8UC1, const_cast<char*>(bytes.data())),
        cv::IMREAD_UNCHANGED);
  } catch (const cv::Exception&) {
  }
  return image;
}

namespace {

cv::Mat DecodePngBytes(const std::filesystem::path& file, const std::string& bytes,
                       const ImageShape* declared) {
  cv::Mat image;
  if (!PngStructureIsComplete(bytes)) Fail("'", file.string(), "' is truncated or not a PNG image");
  CheckPngHeader(file, bytes, declared);
  image = DecodeImageBytes(bytes);
  if (image.empty()) Fail("'", file.string(), "' is truncated or not a PNG image");
  return image;
}

cv::Mat ReadPng(const std::filesystem::path& file, const ImageShape* declared) {
  return DecodePngBytes(file, ReadFileToString(file), declared);
}

cv::Mat ReadImage(const std::filesystem::path& file, const ImageShape* declared) {
  switch (CodecOfFile(file)) {
    case ImageCodec::kExr:
      return ReadExr(file, declared);
    case ImageCodec::kZstd:
      return ReadZstd(file, declared);
    case ImageCodec::kPng:
      return ReadPng(file, declared);
  }
  Fail("unreachable");
}

}  // namespace

cv::Mat DecodePng(const std::string& bytes, const std::string& origin) {
  return DecodePngBytes(origin, bytes, nullptr);
}

void CheckImageFileEnds(const std::filesystem::path& file) {
  const ImageCodec codec = CodecOfFile(file);
  if (codec == ImageCodec::kExr) return;  // OpenEXR's reader checks its own chunk table
  const std::string bytes = ReadFileToString(file);
  size_t end = 0;
  if (codec == ImageCodec::kPng) {
    size_t at = 8;
    while (at + 12 <= bytes.size()) {
      const auto* p = reinterpret_cast<const unsigned char*>(bytes.data() + at);
      const uint64_t length = BigEndian32(p);
      at += 12 + length;
      if (std::memcmp(p + 4, "IEND", 4) == 0) {
        end = at;
        break;
      }
    }
  } else {
    const size_t frame = bytes.size() < sizeof(ZstdHeader)
                             ? 0
                             : ZSTD_findFrameCompressedSize(bytes.data() + sizeof(ZstdHeader),
                                                            bytes.size() - sizeof(ZstdHeader));
    if (!ZSTD_isError(frame)) end = sizeof(ZstdHeader) + frame;
  }
  if (end == 0 || end > bytes.size()) Fail("'", file.string(), "' is truncated or corrupt");
  if (end < bytes.size()) {
    Fail("'", file.string(), "' has ", bytes.size() - end, " bytes after the end of its image");
  }
}

cv::Mat ReadImage(const std::filesystem::path& file) { return ReadImage(file, nullptr); }

cv::Mat ReadImage(const std::filesystem::path& file, const ImageShape& declared) {
  return ReadImage(file, &declared);
}

void WriteImage(const std::filesystem::path& file, const cv::Mat& image) {
  switch (CodecOfFile(file)) {
    case ImageCodec::kExr:
      return WriteExrDepth(file, image);
    case ImageCodec::kZstd:
      return WriteZstd(file, image);
    case ImageCodec::kPng:
      return WritePng(file, image);
  }
}

}  // namespace holocap
