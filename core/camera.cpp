#include "core/camera.h"

#include <cctype>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>

#include "core/error.h"
#include "core/fs.h"

extern "C" {
#include <mrcal/mrcal.h>
}

namespace holocap {
namespace {

static_assert(sizeof(mrcal_lensmodel_t) <= 64, "parsed_lensmodel_ storage too small");

const mrcal_lensmodel_t* AsMrcal(const unsigned char* storage) {
  return reinterpret_cast<const mrcal_lensmodel_t*>(storage);
}

}  // namespace

CameraModel::CameraModel(std::string lensmodel, std::vector<double> intrinsics, int width,
                         int height, const Pose& cam_from_world)
    : lensmodel_(std::move(lensmodel)),
      intrinsics_(std::move(intrinsics)),
      width_(width),
      height_(height),
      cam_from_world_(cam_from_world) {
  ParseLensmodel();
  Validate();
}

// Every model is checked here, wherever it comes from (a .cameramodel, an importer, a solver),
// so no stage ever sees a lens that cannot be a camera's:
//  - the imager size is positive (and at most kMaxImagerSide a side) and every intrinsic and
//    pose entry finite, the camera within kMaxCameraTranslationM of the rig's origin (a
//    translation of 1e300 is a corrupt file, and no float computation survives it);
//  - with an intrinsics core, fx and fy are positive (a negative focal length mirrors the image
//    and projects the scene behind the camera onto it);
//  - the principal point lies within one imager size of the image, cx in [-w, 2w] and cy in
//    [-h, 2h]: real lenses put it within a few percent of the centre, shifted lenses and crops
//    of an image still well inside that margin, while a point further out means the axis misses
//    the imager entirely, i.e. a corrupt or mis-scaled model.
void CameraModel::Validate() const {
  if (width_ <= 0 || height_ <= 0)
    Fail("camera model: imagersize ", width_, "x", height_, " is not positive");
  const bool core = has_core();
  static const char* kCoreNames[] = {"fx", "fy", "cx", "cy"};
  auto field = [&](size_t i) {
    return core && i < 4 ? Cat("intrinsics[", i, "] (", kCoreNames[i], ")")
                         : Cat("intrinsics[", i, "]");
  };
  for (size_t i = 0; i < intrinsics_.size(); ++i) {
    if (!std::isfinite(intrinsics_[i]))
      Fail("camera model: ", field(i), " is ", intrinsics_[i], ", not a finite number");
  }
  if (!cam_from_world_.matrix().allFinite())
    Fail("camera model: extrinsics contain a non-finite value");
  if (const double far = cam_from_world_.translation().cwiseAbs().maxCoeff();
      far > kMaxCameraTranslationM) {
    Fail("camera model: its translation reaches ", far, " m, more than the ",
         kMaxCameraTranslationM,
         " m a rig's camera may lie from its origin (a corrupt or mis-scaled model)");
  }
  if (width_ > kMaxImagerSide || height_ > kMaxImagerSide) {
    Fail("camera model: imagersize ", width_, "x", height_, " is larger than ", kMaxImagerSide,
         " on a side");
  }
  if (!core) return;
  for (size_t i : {0, 1}) {
    if (!(intrinsics_[i] > 0))
      Fail("camera model: ", field(i), " is ", intrinsics_[i], ": a focal length must be positive");
  }
  for (size_t i : {2, 3}) {
    const double size = i == 2 ? width_ : height_;
    if (intrinsics_[i] < -size || intrinsics_[i] > 2 * size) {
      Fail("camera model: ", field(i), " is ", intrinsics_[i], ", outside [", -size, ", ", 2 * size,
           "] (the ", width_, "x", height_, " image widened by its size on each side)");
    }
  }
}

void CameraModel::ParseLensmodel() {
  mrcal_lensmodel_t parsed;
  if (!mrcal_lensmodel_from_name(&parsed, lensmodel_.c_str()) ||
      !mrcal_lensmodel_type_is_valid(parsed.type)) {
    Fail("unknown or unconfigured lens model '", lensmodel_, "'");
  }
  int expected = mrcal_lensmodel_num_params(&parsed);
  if (static_cast<int>(intrinsics_.size()) != expected) {
    Fail("lens model ", lensmodel_, " takes ", expected, " intrinsics, got ", intrinsics_.size());
  }
  std::memcpy(parsed_lensmodel_, &parsed, sizeof(parsed));
}

namespace {

// libmrcal 2.2's .cameramodel parser reads past the end of malformed text (an unterminated
// comment or string is enough to crash it), so the text is checked here first: one Python
// dict literal of strings, numbers, names, lists, tuples and dicts, with '#' comments, and
// nothing after it but whitespace and comments. Returns an empty string when well formed,
// else what is wrong.
class LiteralChecker {
 public:
  explicit LiteralChecker(const std::string& text) : text_(text) {}

  std::string Check() {
    SkipSpace();
    if (Peek() != '{') return Where("does not start with '{'");
    if (!Value(0)) return error_;
    SkipSpace();
    if (at_ != text_.size()) return Where("has text after the closing '}'");
    return {};
  }

 private:
  static constexpr int kMaxDepth = 32;

  char Peek() const { return at_ < text_.size() ? text_[at_] : '\0'; }
  std::string Where(const std::string& what) const {
    return what + " (at byte " + std::to_string(at_) + ")";
  }
  bool Error(const std::string& what) {
    error_ = Where(what);
    return false;
  }
  void SkipSpace() {
    while (at_ < text_.size()) {
      char c = text_[at_];
      if (c == '#') {
        while (at_ < text_.size() && text_[at_] != '\n') ++at_;
      } else if (std::isspace(static_cast<unsigned char>(c))) {
        ++at_;
      } else {
        return;
      }
    }
  }
  bool String() {
    char quote = text_[at_++];
    while (at_ < text_.size() && text_[at_] != quote) {
      if (text_[at_] == '\n') return Error("has a string broken by a newline");
      if (text_[at_] == '\\') ++at_;
      ++at_;
    }
    if (at_ >= text_.size()) return Error("ends inside a string");
    ++at_;
    return true;
  }
  bool Scalar() {
    size_t start = at_;
    while (at_ < text_.size() && (std::isalnum(static_cast<unsigned char>(text_[at_])) ||
                                  std::strchr("+-._", text_[at_]) != nullptr)) {
      ++at_;
    }
    if (at_ == start) return Error(std::string("has an unexpected character '") + Peek() + "'");
    return true;
  }
  // A '{...}', '[...]' or '(...)' whose items are separated by commas (a trailing comma is
  // allowed, as in Python); a dict's items are 'key: value'.
  bool Container(int depth) {
    const char open = text_[at_++];
    const char close = open == '{' ? '}' : open == '[' ? ']' : ')';
    for (;;) {
      SkipSpace();
      if (at_ >= text_.size()) return Error(std::string("ends before its closing '") + close + "'");
      if (Peek() == close) {
        ++at_;
        return true;
      }
      if (!Value(depth + 1)) return false;
      SkipSpace();
      if (open == '{') {
        if (Peek() != ':') return Error("has a dict key without ':'");
        ++at_;
        SkipSpace();
        if (!Value(depth + 1)) return false;
        SkipSpace();
      }
      if (Peek() == ',') {
        ++at_;
      } else if (Peek() != close) {
        return Error(at_ >= text_.size() ? std::string("ends before its closing '") + close + "'"
                                         : std::string("lacks a ',' or '") + close + "'");
      }
    }
  }
  bool Value(int depth) {
    if (depth > kMaxDepth) return Error("nests too deeply");
    SkipSpace();
    char c = Peek();
    if (c == '{' || c == '[' || c == '(') return Container(depth);
    if (c == '\'' || c == '"') return String();
    // Python's bytes literal, as in the optimization_inputs mrcal's own tools write.
    if (c == 'b' && at_ + 1 < text_.size() && (text_[at_ + 1] == '\'' || text_[at_ + 1] == '"')) {
      ++at_;
      return String();
    }
    if (c == '\0' && at_ >= text_.size()) return Error("ends where a value was expected");
    return Scalar();
  }

  const std::string& text_;
  size_t at_ = 0;
  std::string error_;
};

}  // namespace

CameraModel CameraModel::Parse(const std::string& original_text, const std::string& origin) {
  // Older mrcal files call the key 'lens_model'; mrcal's Python accepts both, its C parser
  // only the new name.
  std::string text = original_text;
  for (const char* old_key : {"'lens_model'", "\"lens_model\""}) {
    size_t at = text.find(old_key);
    if (at != std::string::npos) text.replace(at + 1, 10, "lensmodel");
  }
  std::string malformed = LiteralChecker(text).Check();
  if (!malformed.empty()) Fail("'", origin, "' is not a valid mrcal .cameramodel: it ", malformed);
  // A final newline keeps mrcal's comment skipping inside the buffer.
  text += '\n';
  // libmrcal says why it refuses a file on stderr only: that text becomes part of the error.
  mrcal_cameramodel_t* model = nullptr;
  std::string mrcal_says = CaptureStderr(
      [&] { model = mrcal_read_cameramodel_string(text.c_str(), static_cast<int>(text.size())); });
  if (model == nullptr) {
    Fail("'", origin, "' is not a valid mrcal .cameramodel",
         mrcal_says.empty() ? "" : ": libmrcal says: ", mrcal_says);
  }
  char name[1024];
  bool named = mrcal_lensmodel_name(name, sizeof(name), &model->lensmodel);
  int count = mrcal_lensmodel_num_params(&model->lensmodel);
  std::vector<double> intrinsics(model->intrinsics, model->intrinsics + count);
  Rt rt;
  std::copy(model->rt_cam_ref, model->rt_cam_ref + 6, rt.begin());
  int width = static_cast<int>(model->imagersize[0]);
  int height = static_cast<int>(model->imagersize[1]);
  mrcal_free_cameramodel(&model);
  if (!named) Fail("'", origin, "': cannot name its lens model");
  try {
    return CameraModel(name, std::move(intrinsics), width, height, PoseFromRt(rt));
  } catch (const Error& e) {
    Fail("'", origin, "': ", e.what());
  }
}

CameraModel CameraModel::Read(const std::filesystem::path& file) {
  return Parse(ReadFileToString(file), file.string());
}

std::string CameraModel::ToString() const {
  // %.17g round-trips every double exactly, so a written model projects bit-identically.
  auto number = [](double value) {
    char buffer[40];
    std::snprintf(buffer, sizeof(buffer), "%.17g", value);
    return std::string(buffer);
  };
  std::string out = "# generated by holocap\n{\n    'lensmodel':  '" + lensmodel_ + "',\n";
  out += "\n    # intrinsics are fx,fy,cx,cy,distortion0,distortion1,....\n    'intrinsics': [ ";
  for (double value : intrinsics_) out += number(value) + ", ";
  out += "],\n\n    # extrinsics are rt_fromref\n    'extrinsics': [ ";
  for (double value : RtFromPose(cam_from_world_)) out += number(value) + ", ";
  out += "],\n\n    'imagersize': [ " + std::to_string(width_) + ", " + std::to_string(height_) +
         " ],\n}\n";
  return out;
}

void CameraModel::Write(const std::filesystem::path& file) const {
  WriteFileAtomic(file, ToString());
}

CameraModel CameraModel::Pinhole(double focal_px, int width, int height,
                                 const Pose& cam_from_world) {
  return CameraModel("LENSMODEL_PINHOLE",
                     {focal_px, focal_px, (width - 1) / 2.0, (height - 1) / 2.0}, width, height,
                     cam_from_world);
}

bool CameraModel::has_core() const {
  return mrcal_lensmodel_metadata(AsMrcal(parsed_lensmodel_)).has_core;
}

bool CameraModel::can_project_behind_camera() const {
  return mrcal_lensmodel_metadata(AsMrcal(parsed_lensmodel_)).can_project_behind_camera;
}

bool CameraModel::Project(const Eigen::Vector3d& point_in_cam, Eigen::Vector2d* pixel,
                          Eigen::Matrix<double, 2, 3>* dpixel_dpoint,
                          Eigen::MatrixXd* dpixel_dintrinsics) const {
  if (!point_in_cam.allFinite()) return false;
  if (point_in_cam.z() <= 0 && !can_project_behind_camera()) return false;
  mrcal_point3_t p;
  p.x = point_in_cam.x();
  p.y = point_in_cam.y();
  p.z = point_in_cam.z();
  mrcal_point2_t q;
  mrcal_point3_t dq_dp[2];
  std::vector<double> dq_dintrinsics;
  if (dpixel_dintrinsics != nullptr) dq_dintrinsics.resize(2 * intrinsics_.size());
  bool ok = mrcal_project(&q, dpixel_dpoint ? dq_dp : nullptr,
                          dpixel_dintrinsics ? dq_dintrinsics.data() : nullptr, &p, 1,
                          AsMrcal(parsed_lensmodel_), intrinsics_.data());
  if (!ok || !std::isfinite(q.x) || !std::isfinite(q.y)) return false;
  (*pixel) << q.x, q.y;
  if (dpixel_dpoint != nullptr) {
    for (int row = 0; row < 2; ++row) {
      for (int col = 0; col < 3; ++col) (*dpixel_dpoint)(row, col) = dq_dp[row].xyz[col];
    }
  }
  if (dpixel_dintrinsics != nullptr) {
    const int n = static_cast<int>(intrinsics_.size());
    dpixel_dintrinsics->resize(2, n);
    for (int row = 0; row < 2; ++row) {
      for (int col = 0; col < n; ++col)
        (*dpixel_dintrinsics)(row, col) = dq_dintrinsics[row * n + col];
    }
  }
  return true;
}

bool CameraModel::ProjectWorld(const Eigen::Vector3d& point_in_world,
                               Eigen::Vector2d* pixel) const {
  return Project(cam_from_world_ * point_in_world, pixel);
}

Eigen::Matrix2Xd CameraModel::ProjectMany(const Eigen::Matrix3Xd& points_in_cam) const {
  const int n = static_cast<int>(points_in_cam.cols());
  Eigen::Matrix2Xd pixels(2, n);
  if (n == 0) return pixels;
  static_assert(sizeof(mrcal_point3_t) == 3 * sizeof(double));
  static_assert(sizeof(mrcal_point2_t) == 2 * sizeof(double));
  bool ok = mrcal_project(reinterpret_cast<mrcal_point2_t*>(pixels.data()), nullptr, nullptr,
                          reinterpret_cast<const mrcal_point3_t*>(points_in_cam.data()), n,
                          AsMrcal(parsed_lensmodel_), intrinsics_.data());
  if (!ok) Fail("mrcal_project failed for lens model ", lensmodel_);
  if (!can_project_behind_camera()) {
    for (int i = 0; i < n; ++i) {
      if (!(points_in_cam(2, i) > 0))
        pixels.col(i).setConstant(std::numeric_limits<double>::quiet_NaN());
    }
  }
  return pixels;
}

Eigen::Vector3d CameraModel::Unproject(const Eigen::Vector2d& pixel) const {
  mrcal_point2_t q;
  q.x = pixel.x();
  q.y = pixel.y();
  mrcal_point3_t v;
  if (!mrcal_unproject(&v, &q, 1, AsMrcal(parsed_lensmodel_), intrinsics_.data()) ||
      !std::isfinite(v.x) || !std::isfinite(v.y) || !std::isfinite(v.z)) {
    Fail("cannot unproject pixel (", pixel.x(), ", ", pixel.y(), ") through ", lensmodel_);
  }
  Eigen::Vector3d direction(v.x, v.y, v.z);
  return direction.normalized();
}

Eigen::Matrix3Xd CameraModel::UnprojectMany(const Eigen::Matrix2Xd& pixels) const {
  const int n = static_cast<int>(pixels.cols());
  Eigen::Matrix3Xd directions(3, n);
  if (n == 0) return directions;
  bool ok = mrcal_unproject(reinterpret_cast<mrcal_point3_t*>(directions.data()),
                            reinterpret_cast<const mrcal_point2_t*>(pixels.data()), n,
                            AsMrcal(parsed_lensmodel_), intrinsics_.data());
  if (!ok) {
    // One bad pixel fails the batch: redo one by one so only the bad ones become NaN.
    for (int i = 0; i < n; ++i) {
      mrcal_point3_t v;
      mrcal_point2_t q;
      q.x = pixels(0, i);
      q.y = pixels(1, i);
      if (mrcal_unproject(&v, &q, 1, AsMrcal(parsed_lensmodel_), intrinsics_.data())) {
        directions.col(i) << v.x, v.y, v.z;
      } else {
        directions.col(i).setConstant(std::numeric_limits<double>::quiet_NaN());
      }
    }
  }
  for (int i = 0; i < n; ++i) {
    double norm = directions.col(i).norm();
    if (std::isfinite(norm) && norm > 0) {
      directions.col(i) /= norm;
    } else {
      directions.col(i).setConstant(std::numeric_limits<double>::quiet_NaN());
    }
  }
  return directions;
}

CameraModel CameraModel::Scaled(double scale) const {
  if (!has_core()) Fail("cannot rescale lens model ", lensmodel_, ": it has no intrinsics core");
  if (!(scale > 0)) Fail("rescaling a camera model needs a positive scale, got ", scale);
  std::vector<double> intrinsics = intrinsics_;
  intrinsics[0] *= scale;
  intrinsics[1] *= scale;
  // Pixel centres sit at integers: a continuous coordinate x maps to (x + 0.5) * s - 0.5.
  intrinsics[2] = (intrinsics[2] + 0.5) * scale - 0.5;
  intrinsics[3] = (intrinsics[3] + 0.5) * scale - 0.5;
  int width = static_cast<int>(std::lround(width_ * scale));
  int height = static_cast<int>(std::lround(height_ * scale));
  return CameraModel(lensmodel_, std::move(intrinsics), width, height, cam_from_world_);
}

bool CameraModel::InImage(const Eigen::Vector2d& pixel, double margin) const {
  return pixel.x() >= -0.5 + margin && pixel.y() >= -0.5 + margin &&
         pixel.x() <= width_ - 0.5 - margin && pixel.y() <= height_ - 0.5 - margin;
}

}  // namespace holocap
