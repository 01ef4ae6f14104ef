// Camera models: an mrcal lens model with its intrinsics, the imager size and the camera's
// pose. Projection goes through libmrcal itself, so a model here projects exactly as mrcal's
// tools do, and `.cameramodel` files are mrcal's own format.
//
// Pixel convention (mrcal's and OpenCV's): integer coordinates are pixel centres; pixel (0,0)
// covers [-0.5, 0.5]².
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <filesystem>
#include <string>
#include <vector>

#include "core/pose.h"

namespace holocap {

// The farthest a camera may lie from its rig's origin, and the largest imager side a model may
// have: past them a model is corrupt or in the wrong units.
inline constexpr double kMaxCameraTranslationM = 1e6;
inline constexpr int kMaxImagerSide = 1 << 16;

class CameraModel {
 public:
  CameraModel() = default;
  // `lensmodel` is mrcal's configured name, e.g. "LENSMODEL_OPENCV8" or
  // "LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=16_Ny=12_fov_x_deg=120". Throws Error when the
  // name is unknown, the intrinsics count does not match it, or the model cannot be a camera's
  // (a value not finite, a focal length not positive, the principal point more than an image
  // size outside the image: see Validate in camera.cpp); the message names the field.
  CameraModel(std::string lensmodel, std::vector<double> intrinsics, int width, int height,
              const Pose& cam_from_world = Pose::Identity());

  // Reads/writes mrcal's .cameramodel; extrinsics there are rt_cam_ref = cam_from_world.
  static CameraModel Read(const std::filesystem::path& file);
  static CameraModel Parse(const std::string& text, const std::string& origin = "<string>");
  void Write(const std::filesystem::path& file) const;  // atomic
  std::string ToString() const;

  // A pinhole model with focal length `focal_px` and the principal point at the imager centre.
  static CameraModel Pinhole(double focal_px, int width, int height,
                             const Pose& cam_from_world = Pose::Identity());

  const std::string& lensmodel() const { return lensmodel_; }
  const std::vector<double>& intrinsics() const { return intrinsics_; }
  std::vector<double>& mutable_intrinsics() { return intrinsics_; }
  int width() const { return width_; }
  int height() const { return height_; }
  const Pose& cam_from_world() const { return cam_from_world_; }
  void set_cam_from_world(const Pose& pose) { cam_from_world_ = pose; }
  Pose world_from_cam() const { return cam_from_world_.inverse(); }
  Eigen::Vector3d center_in_world() const { return world_from_cam().translation(); }
  bool has_core() const;  // fx, fy, cx, cy lead the intrinsics
  bool can_project_behind_camera() const;

  // Projects a point in camera coordinates. Returns false when mrcal fails or the point is
  // behind a camera that cannot see behind itself (the pixel is then unspecified).
  // Jacobians are optional; dpixel_dintrinsics is 2 x intrinsics().size().
  bool Project(const Eigen::Vector3d& point_in_cam, Eigen::Vector2d* pixel,
               Eigen::Matrix<double, 2, 3>* dpixel_dpoint = nullptr,
               Eigen::MatrixXd* dpixel_dintrinsics = nullptr) const;
  // Same for a point in world coordinates (through cam_from_world).
  bool ProjectWorld(const Eigen::Vector3d& point_in_world, Eigen::Vector2d* pixel) const;
  // Many points at once (3xN camera coordinates -> 2xN pixels); one mrcal call.
  Eigen::Matrix2Xd ProjectMany(const Eigen::Matrix3Xd& points_in_cam) const;

  // Unit-norm viewing direction in camera coordinates of a pixel. Throws Error if mrcal fails.
  Eigen::Vector3d Unproject(const Eigen::Vector2d& pixel) const;
  // Many at once; a pixel mrcal cannot unproject gets a NaN column.
  Eigen::Matrix3Xd UnprojectMany(const Eigen::Matrix2Xd& pixels) const;

  // The same lens for an image resized by `scale` (pixel-centre convention kept); the pose is
  // unchanged. Needs an intrinsics core. Throws Error otherwise.
  CameraModel Scaled(double scale) const;

  bool InImage(const Eigen::Vector2d& pixel, double margin = 0) const;

 private:
  void ParseLensmodel();
  void Validate() const;

  std::string lensmodel_;
  // mrcal_lensmodel_t, parsed once (kept opaque so this header does not pull in mrcal).
  alignas(8) unsigned char parsed_lensmodel_[64] = {};
  std::vector<double> intrinsics_;
  int width_ = 0;
  int height_ = 0;
  Pose cam_from_world_ = Pose::Identity();
};

}  // namespace holocap
