// Camera conventions of the foreign formats, converted exactly. Two conventions differ from
// holocap's in every tool that uses them:
//  - COLMAP and nerfstudio put the image origin at the top-left corner of the top-left pixel,
//    so that pixel's centre is (0.5, 0.5); mrcal and holocap put it at (0, 0).
//  - NeRF/Blender cameras look down -z with y up (OpenGL); holocap's look down +z with y down.
// Everything else (which distortion terms exist) either maps term for term or is refused.
#include <Eigen/Eigenvalues>
#include <Eigen/SVD>
#include <cmath>

#include "core/error.h"
#include "interop/interop.h"

namespace holocap {
namespace {

constexpr double kHalfPixel = 0.5;

bool AllZero(const std::vector<double>& values, size_t from = 0) {
  for (size_t i = from; i < values.size(); ++i) {
    if (values[i] != 0) return false;
  }
  return true;
}

// cv_from_gl: the same camera with y and z flipped.
const Eigen::Matrix4d& FlipYZ() {
  static const Eigen::Matrix4d flip = Eigen::Vector4d(1, -1, -1, 1).asDiagonal();
  return flip;
}

}  // namespace

const char* ToString(InteropFormat format) {
  switch (format) {
    case InteropFormat::kMiddlebury:
      return "middlebury";
    case InteropFormat::kKrt:
      return "krt";
    case InteropFormat::kColmap:
      return "colmap";
    case InteropFormat::kNerf:
      return "nerf";
    case InteropFormat::kPanoptic:
      return "panoptic";
    case InteropFormat::kMrcal:
      return "mrcal";
  }
  return "?";
}

InteropFormat InteropFormatFromString(const std::string& text) {
  for (InteropFormat format :
       {InteropFormat::kMiddlebury, InteropFormat::kKrt, InteropFormat::kColmap,
        InteropFormat::kNerf, InteropFormat::kPanoptic, InteropFormat::kMrcal}) {
    if (text == ToString(format)) return format;
  }
  Fail("unknown format '", text, "' (middlebury, krt, colmap, nerf, panoptic or mrcal)");
}

CameraModel CameraFromKrt(const KrtCamera& camera, const Pose& cam_from_world) {
  const std::string who = "camera '" + camera.name + "'";
  const Eigen::Matrix3d& K = camera.K;
  if (K(1, 0) != 0 || K(2, 0) != 0 || K(2, 1) != 0 || !(K(2, 2) != 0)) {
    Fail(who, ": K must be upper triangular with K33 != 0, got [", K.row(0), "; ", K.row(1), "; ",
         K.row(2), "]");
  }
  Eigen::Matrix3d k = K / K(2, 2);
  if (k(0, 1) != 0) {
    Fail(who, ": K has skew ", k(0, 1),
         "; no mrcal lens model has a skew term, so it cannot be imported exactly");
  }
  if (!(k(0, 0) > 0) || !(k(1, 1) > 0))
    Fail(who, ": K's focal lengths must be positive, got ", k(0, 0), ", ", k(1, 1));
  if (camera.width <= 0 || camera.height <= 0) Fail(who, ": image size unknown");
  std::vector<double> intrinsics = {k(0, 0), k(1, 1), k(0, 2), k(1, 2)};
  const std::vector<double>& d = camera.distortion;
  std::string lensmodel;
  if (AllZero(d)) {
    lensmodel = "LENSMODEL_PINHOLE";
  } else if (d.size() == 4 || d.size() == 5 || d.size() == 8 || d.size() == 12) {
    // OpenCV's coefficient order is mrcal's OPENCVn order.
    lensmodel = "LENSMODEL_OPENCV" + std::to_string(d.size());
    intrinsics.insert(intrinsics.end(), d.begin(), d.end());
  } else {
    Fail(who, ": ", d.size(),
         " distortion coefficients; mrcal holds OpenCV's 4, 5, 8 or 12 (no tilted-sensor 14)");
  }
  return CameraModel(lensmodel, intrinsics, camera.width, camera.height, cam_from_world);
}

CameraModel CameraFromColmap(const ColmapCamera& camera, const Pose& cam_from_world) {
  const std::vector<double>& p = camera.params;
  auto expect = [&](size_t count) {
    if (p.size() != count)
      Fail("COLMAP camera ", camera.id, " (", camera.model, ") needs ", count, " parameters, has ",
           p.size());
  };
  std::string lensmodel;
  std::vector<double> intrinsics;
  if (camera.model == "SIMPLE_PINHOLE") {
    expect(3);
    lensmodel = "LENSMODEL_PINHOLE";
    intrinsics = {p[0], p[0], p[1] - kHalfPixel, p[2] - kHalfPixel};
  } else if (camera.model == "PINHOLE") {
    expect(4);
    lensmodel = "LENSMODEL_PINHOLE";
    intrinsics = {p[0], p[1], p[2] - kHalfPixel, p[3] - kHalfPixel};
  } else if (camera.model == "SIMPLE_RADIAL") {
    expect(4);
    lensmodel = "LENSMODEL_OPENCV4";
    intrinsics = {p[0], p[0], p[1] - kHalfPixel, p[2] - kHalfPixel, p[3], 0, 0, 0};
  } else if (camera.model == "RADIAL") {
    expect(5);
    lensmodel = "LENSMODEL_OPENCV4";
    intrinsics = {p[0], p[0], p[1] - kHalfPixel, p[2] - kHalfPixel, p[3], p[4], 0, 0};
  } else if (camera.model == "OPENCV") {
    expect(8);
    lensmodel = "LENSMODEL_OPENCV4";
    intrinsics = {p[0], p[1], p[2] - kHalfPixel, p[3] - kHalfPixel, p[4], p[5], p[6], p[7]};
  } else if (camera.model == "FULL_OPENCV") {
    expect(12);
    // k1 k2 p1 p2 k3 k4 k5 k6, OpenCV's order as mrcal's; without the rational part it is OPENCV5.
    const bool rational = p[9] != 0 || p[10] != 0 || p[11] != 0;
    lensmodel = rational ? "LENSMODEL_OPENCV8" : "LENSMODEL_OPENCV5";
    intrinsics = {p[0], p[1], p[2] - kHalfPixel, p[3] - kHalfPixel};
    intrinsics.insert(intrinsics.end(), p.begin() + 4, p.begin() + (rational ? 12 : 9));
  } else {
    Fail("COLMAP camera ", camera.id, " uses model ", camera.model,
         ", which no mrcal 2.2 lens model represents exactly (mrcal has no Kannala-Brandt or FOV "
         "fisheye); undistort the images with COLMAP's image_undistorter and import that PINHOLE "
         "model");
  }
  if (!(intrinsics[0] > 0) || !(intrinsics[1] > 0))
    Fail("COLMAP camera ", camera.id, ": focal length must be positive");
  return CameraModel(lensmodel, intrinsics, camera.width, camera.height, cam_from_world);
}

ColmapCamera ColmapFromCamera(const CameraModel& camera, int64_t id) {
  ColmapCamera out;
  out.id = id;
  out.width = camera.width();
  out.height = camera.height();
  const std::vector<double>& in = camera.intrinsics();
  const std::string& lens = camera.lensmodel();
  if (lens == "LENSMODEL_PINHOLE" || lens == "LENSMODEL_OPENCV4" || lens == "LENSMODEL_OPENCV5" ||
      lens == "LENSMODEL_OPENCV8") {
    out.params = {in[0], in[1], in[2] + kHalfPixel, in[3] + kHalfPixel};
  }
  if (lens == "LENSMODEL_PINHOLE") {
    out.model = "PINHOLE";
  } else if (lens == "LENSMODEL_OPENCV4") {
    out.model = "OPENCV";
    out.params.insert(out.params.end(), in.begin() + 4, in.end());
  } else if (lens == "LENSMODEL_OPENCV5" || lens == "LENSMODEL_OPENCV8") {
    out.model = "FULL_OPENCV";
    out.params.insert(out.params.end(), in.begin() + 4, in.end());
    out.params.resize(12, 0.0);
  } else {
    Fail("lens model ", lens,
         " has no exact COLMAP camera model (COLMAP holds PINHOLE, OPENCV4, "
         "OPENCV5 and OPENCV8 exactly)");
  }
  return out;
}

CameraModel CameraFromNerf(const NerfIntrinsics& in, const Eigen::Matrix4d& world_from_cam_gl,
                           int image_width, int image_height, const std::string& origin) {
  const int width = in.w.value_or(image_width);
  const int height = in.h.value_or(image_height);
  if (width <= 0 || height <= 0) Fail(origin, ": image size unknown (no w/h and no image)");
  if (image_width > 0 && (image_width != width || image_height != height)) {
    Fail(origin, ": w x h = ", width, "x", height, " but the image is ", image_width, "x",
         image_height);
  }
  const std::string model = in.camera_model.value_or("OPENCV");
  if (model != "OPENCV" && model != "PINHOLE" && model != "SIMPLE_PINHOLE") {
    Fail(origin, ": camera_model ", model,
         " has no exact mrcal 2.2 lens model (only OPENCV and PINHOLE import)");
  }
  double fx = 0;
  if (in.fl_x) {
    fx = *in.fl_x;
  } else if (in.camera_angle_x) {
    fx = 0.5 * width / std::tan(0.5 * *in.camera_angle_x);
  } else {
    Fail(origin, ": neither fl_x nor camera_angle_x is given");
  }
  double fy = fx;
  if (in.fl_y) {
    fy = *in.fl_y;
  } else if (in.camera_angle_y) {
    fy = 0.5 * height / std::tan(0.5 * *in.camera_angle_y);
  }
  if (!(fx > 0) || !(fy > 0) || !std::isfinite(fx) || !std::isfinite(fy)) {
    Fail(origin, ": focal lengths ", fx, ", ", fy, " are not positive");
  }
  // Blender renders with the optical axis through the image's geometric centre; in the corner
  // convention that is (w/2, h/2), the default nerfstudio also uses.
  const double cx = in.cx.value_or(0.5 * width) - kHalfPixel;
  const double cy = in.cy.value_or(0.5 * height) - kHalfPixel;
  auto term = [&](const char* key) {
    auto it = in.distortion.find(key);
    return it == in.distortion.end() ? 0.0 : it->second;
  };
  if (term("k4") != 0) {
    Fail(origin, ": k4 (nerfstudio's r^8 radial term) is ", term("k4"),
         "; mrcal's OPENCV models have no such term, so it cannot be imported exactly");
  }
  std::string lensmodel = "LENSMODEL_PINHOLE";
  std::vector<double> intrinsics = {fx, fy, cx, cy};
  const std::vector<double> distortion = {term("k1"), term("k2"), term("p1"), term("p2"),
                                          term("k3")};
  if (!AllZero(distortion)) {
    const bool k3 = distortion[4] != 0;
    lensmodel = k3 ? "LENSMODEL_OPENCV5" : "LENSMODEL_OPENCV4";
    intrinsics.insert(intrinsics.end(), distortion.begin(), distortion.begin() + (k3 ? 5 : 4));
  }
  Eigen::Matrix4d world_from_cam_cv = world_from_cam_gl * FlipYZ();
  Pose world_from_cam = Pose::Identity();
  // Files written in single precision are orthonormal to ~1e-7; the nearest rotation is the
  // camera they describe. Scaled or mirrored poses cannot be imported.
  world_from_cam.linear() =
      CheckRotation(world_from_cam_cv.topLeftCorner<3, 3>(), origin + ": transform_matrix")
          .rotation;
  world_from_cam.translation() = world_from_cam_cv.topRightCorner<3, 1>();
  return CameraModel(lensmodel, intrinsics, width, height, world_from_cam.inverse());
}

NerfIntrinsics NerfFromCamera(const CameraModel& camera) {
  const std::vector<double>& in = camera.intrinsics();
  const std::string& lens = camera.lensmodel();
  const bool opencv8_without_rational =
      lens == "LENSMODEL_OPENCV8" && in[9] == 0 && in[10] == 0 && in[11] == 0;
  if (lens != "LENSMODEL_PINHOLE" && lens != "LENSMODEL_OPENCV4" && lens != "LENSMODEL_OPENCV5" &&
      !opencv8_without_rational) {
    Fail("lens model ", lens,
         " has no exact transforms.json form (nerfstudio's OPENCV holds k1 k2 k3 "
         "p1 p2: mrcal's PINHOLE, OPENCV4 and OPENCV5; OPENCV8's rational terms k4..k6 are not "
         "representable)");
  }
  NerfIntrinsics out;
  out.fl_x = in[0];
  out.fl_y = in[1];
  out.cx = in[2] + kHalfPixel;
  out.cy = in[3] + kHalfPixel;
  out.w = camera.width();
  out.h = camera.height();
  out.camera_model = "OPENCV";
  const char* keys[] = {"k1", "k2", "p1", "p2", "k3"};
  for (size_t i = 4; i < std::min<size_t>(in.size(), 9); ++i) out.distortion[keys[i - 4]] = in[i];
  return out;
}

Eigen::Matrix4d NerfWorldFromCamGl(const Pose& cam_from_world) {
  return cam_from_world.inverse().matrix() * FlipYZ();
}

RigidWorld SplitRigidWorld(const std::vector<Eigen::Matrix3d>& rotations) {
  RigidWorld out;
  if (rotations.empty()) return out;
  std::vector<Eigen::Matrix3d> parts;
  Eigen::Matrix3d mean = Eigen::Matrix3d::Zero();
  for (const auto& r : rotations) {
    Eigen::Matrix3d gram = r.transpose() * r;
    out.non_orthonormality = std::max(out.non_orthonormality,
                                      (gram - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff());
    // R = Q S with S = sqrt(R^T R) symmetric positive definite (the polar decomposition).
    Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> solver(gram);
    parts.push_back(solver.operatorSqrt());
    mean += parts.back();
  }
  mean /= static_cast<double>(rotations.size());
  for (const auto& part : parts)
    out.residual = std::max(out.residual, (part - mean).cwiseAbs().maxCoeff());
  // Rotations orthonormal to rounding need no world change at all.
  const bool rigid = (mean - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff() < 1e-14;
  out.world_from_source = rigid ? Eigen::Matrix3d::Identity() : mean;
  const Eigen::Matrix3d source_from_world = out.world_from_source.inverse();
  for (const auto& r : rotations) out.rotations.push_back(NearestRotation(r * source_from_world));
  return out;
}

}  // namespace holocap
