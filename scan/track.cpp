// The scanner's tracker: depth pyramids, the model's raycast, and frame-to-reference alignment
// (point-to-plane ICP with projective association plus a photometric term).
#include <omp.h>

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <limits>

#include "scan/internal/track.h"

namespace holocap::scan {
namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
const Eigen::Vector3f kNoPoint = Eigen::Vector3f::Constant(kNaN);

using Vector6d = Eigen::Matrix<double, 6, 1>;
using Matrix6d = Eigen::Matrix<double, 6, 6>;

// Fewer points than this per thread: one thread (waking another costs more than it saves).
constexpr size_t kMinPointsPerThread = 8192;

int FloorDiv(int a, int b) { return a >= 0 ? a / b : -((-a + b - 1) / b); }

// Trilinear reads of the TSDF with the last block looked up kept at hand (neighbouring samples
// along a ray mostly fall in one block).
class VolumeSampler {
 public:
  explicit VolumeSampler(const SparseVolume& volume)
      : volume_(volume), inv_voxel_(static_cast<float>(1.0 / volume.voxel_m())) {}

  const Voxel* VoxelAt(const Eigen::Vector3i& index) {
    const Eigen::Vector3i block(FloorDiv(index.x(), kBlockSide), FloorDiv(index.y(), kBlockSide),
                                FloorDiv(index.z(), kBlockSide));
    if (block != cached_block_ || !has_cached_) {
      cached_ = volume_.Find(block);
      cached_block_ = block;
      has_cached_ = true;
    }
    if (cached_ == nullptr) return nullptr;
    const Eigen::Vector3i local = index - block * kBlockSide;
    const Voxel& voxel = cached_->at(local.x(), local.y(), local.z());
    return voxel.weight > 0 ? &voxel : nullptr;
  }

  // Signed distance (and colour, 0..255) at a world point; false when a corner is unobserved.
  bool Sample(const Eigen::Vector3f& point, float* sdf, Eigen::Vector3f* rgb = nullptr) {
    const Eigen::Vector3f g = point * inv_voxel_;
    const Eigen::Vector3f base = g.array().floor();
    const Eigen::Vector3f f = g - base;
    const Eigen::Vector3i i0 = base.cast<int>();
    const Eigen::Vector3i block(FloorDiv(i0.x(), kBlockSide), FloorDiv(i0.y(), kBlockSide),
                                FloorDiv(i0.z(), kBlockSide));
    const Eigen::Vector3i local = i0 - block * kBlockSide;
    if ((local.array() < kBlockSide - 1).all()) return SampleInBlock(block, local, f, sdf, rgb);
    float value = 0;
    Eigen::Vector3f colour = Eigen::Vector3f::Zero();
    for (int c = 0; c < 8; ++c) {
      const Eigen::Vector3i offset(c & 1, (c >> 1) & 1, (c >> 2) & 1);
      const Voxel* voxel = VoxelAt(i0 + offset);
      if (voxel == nullptr) return false;
      const float w = (offset.x() ? f.x() : 1 - f.x()) * (offset.y() ? f.y() : 1 - f.y()) *
                      (offset.z() ? f.z() : 1 - f.z());
      value += w * voxel->sdf;
      if (rgb != nullptr) colour += w * Eigen::Vector3f(voxel->r, voxel->g, voxel->b);
    }
    *sdf = value;
    if (rgb != nullptr) *rgb = colour;
    return true;
  }

  // Sample's common case: all eight corners in one block (7 in 8 along each axis), read
  // without a lookup per corner.
  bool SampleInBlock(const Eigen::Vector3i& block, const Eigen::Vector3i& local,
                     const Eigen::Vector3f& f, float* sdf, Eigen::Vector3f* rgb) {
    if (block != cached_block_ || !has_cached_) {
      cached_ = volume_.Find(block);
      cached_block_ = block;
      has_cached_ = true;
    }
    if (cached_ == nullptr) return false;
    const Voxel* origin = &cached_->at(local.x(), local.y(), local.z());
    constexpr int kStepY = kBlockSide, kStepZ = kBlockSide * kBlockSide;
    constexpr int kOffsets[8] = {0,      1,          kStepY,          kStepY + 1,
                                 kStepZ, kStepZ + 1, kStepZ + kStepY, kStepZ + kStepY + 1};
    const float wx[2] = {1 - f.x(), f.x()}, wy[2] = {1 - f.y(), f.y()}, wz[2] = {1 - f.z(), f.z()};
    float value = 0;
    for (int c = 0; c < 8; ++c) {
      const Voxel& voxel = origin[kOffsets[c]];
      if (!(voxel.weight > 0)) return false;
      value += wx[c & 1] * wy[(c >> 1) & 1] * wz[c >> 2] * voxel.sdf;
    }
    *sdf = value;
    if (rgb != nullptr) {
      Eigen::Vector3f colour = Eigen::Vector3f::Zero();
      for (int c = 0; c < 8; ++c) {
        const Voxel& voxel = origin[kOffsets[c]];
        colour +=
            wx[c & 1] * wy[(c >> 1) & 1] * wz[c >> 2] * Eigen::Vector3f(voxel.r, voxel.g, voxel.b);
      }
      *rgb = colour;
    }
    return true;
  }

  bool Normal(const Eigen::Vector3f& point, Eigen::Vector3f* normal) {
    const float h = 1.0f / inv_voxel_;
    Eigen::Vector3f gradient;
    float centre = 0;
    int has_centre = -1;  // read only when a side is missing
    for (int axis = 0; axis < 3; ++axis) {
      Eigen::Vector3f step = Eigen::Vector3f::Zero();
      step[axis] = h;
      float plus = 0, minus = 0;
      const bool has_plus = Sample(point + step, &plus), has_minus = Sample(point - step, &minus);
      if (!(has_plus && has_minus) && has_centre < 0) has_centre = Sample(point, &centre);
      // Central where both sides are observed, one-sided at the edge of the observed band.
      if (has_plus && has_minus) {
        gradient[axis] = 0.5f * (plus - minus);
      } else if (has_centre > 0 && (has_plus || has_minus)) {
        gradient[axis] = has_plus ? plus - centre : centre - minus;
      } else {
        return false;
      }
    }
    const float norm = gradient.norm();
    if (!(norm > 1e-9f)) return false;
    *normal = gradient / norm;
    return true;
  }

 private:
  const SparseVolume& volume_;
  float inv_voxel_;
  Eigen::Vector3i cached_block_ = Eigen::Vector3i::Zero();
  bool has_cached_ = false;
  const VoxelBlock* cached_ = nullptr;
};

float Intensity(const Eigen::Vector3f& rgb_255) {
  return (0.299f * rgb_255.x() + 0.587f * rgb_255.y() + 0.114f * rgb_255.z()) / 255.0f;
}

// Normals from the cross product of the differences along the rows and the columns. Along each,
// the neighbour up to `reach` pixels away on either side (the farthest valid one, within
// max_jump_m of the point's depth: the same surface), or the point itself where one side has
// none, so that the edges of a surface get normals too.
void ComputeNormals(Level& level, int reach, float max_jump_m = 0.05f) {
  const int w = level.width, h = level.height;
  level.normals.assign(level.points.size(), kNoPoint);
  const auto neighbour = [&](int x, int y, int dx, int dy, const Eigen::Vector3f& p) {
    for (int k = reach; k >= 1; --k) {
      const int xx = x + k * dx, yy = y + k * dy;
      if (xx < 0 || yy < 0 || xx >= w || yy >= h) continue;
      const Eigen::Vector3f& q = level.points[static_cast<size_t>(yy) * w + xx];
      if (!std::isnan(q.z()) && std::abs(q.z() - p.z()) <= max_jump_m) return q;
    }
    return p;
  };
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const Eigen::Vector3f& p = level.points[static_cast<size_t>(y) * w + x];
      if (std::isnan(p.z())) continue;
      const Eigen::Vector3f along_x = neighbour(x, y, 1, 0, p) - neighbour(x, y, -1, 0, p);
      const Eigen::Vector3f along_y = neighbour(x, y, 0, 1, p) - neighbour(x, y, 0, -1, p);
      Eigen::Vector3f n = along_x.cross(along_y);
      const float norm = n.norm();
      // Both differences must exist and must not be (nearly) parallel.
      if (!(norm > 0.1f * along_x.norm() * along_y.norm())) continue;
      n /= norm;
      if (n.dot(p) > 0) n = -n;  // facing the camera
      level.normals[static_cast<size_t>(y) * w + x] = n;
    }
  }
}

Level Downsample(const Level& fine) {
  Level coarse;
  coarse.width = fine.width / 2;
  coarse.height = fine.height / 2;
  coarse.points.assign(static_cast<size_t>(coarse.width) * coarse.height, kNoPoint);
  coarse.intensity.assign(coarse.points.size(), kNaN);
  for (int y = 0; y < coarse.height; ++y) {
    for (int x = 0; x < coarse.width; ++x) {
      float nearest = std::numeric_limits<float>::infinity();
      for (int k = 0; k < 4; ++k) {
        const float z = fine.points[(2 * y + k / 2) * fine.width + 2 * x + k % 2].z();
        if (z < nearest) nearest = z;
      }
      if (!std::isfinite(nearest)) continue;
      Eigen::Vector3f sum = Eigen::Vector3f::Zero();
      float intensity = 0;
      int count = 0, lit = 0;
      for (int k = 0; k < 4; ++k) {
        const size_t i = static_cast<size_t>(2 * y + k / 2) * fine.width + 2 * x + k % 2;
        const Eigen::Vector3f& p = fine.points[i];
        if (!(p.z() <= nearest + 0.03f)) continue;
        sum += p;
        ++count;
        if (!std::isnan(fine.intensity[i])) {
          intensity += fine.intensity[i];
          ++lit;
        }
      }
      coarse.points[y * coarse.width + x] = sum / static_cast<float>(count);
      if (lit > 0) coarse.intensity[y * coarse.width + x] = intensity / static_cast<float>(lit);
    }
  }
  return coarse;
}

// Bilinear intensity and its gradient (per pixel) at (u, v); false near missing values.
bool IntensityAt(const cv::Mat& image, float u, float v, float* value, Eigen::Vector2f* gradient) {
  const int x = static_cast<int>(std::floor(u)), y = static_cast<int>(std::floor(v));
  if (x < 1 || y < 1 || x + 2 >= image.cols || y + 2 >= image.rows) return false;
  const float fx = u - x, fy = v - y;
  float grid[4][4];
  for (int j = 0; j < 4; ++j) {
    const float* row = image.ptr<float>(y - 1 + j) + x - 1;
    for (int i = 0; i < 4; ++i) {
      grid[j][i] = row[i];
      if (std::isnan(row[i])) return false;
    }
  }
  const auto lerp = [&](float a, float b, float c, float d) {
    return (1 - fy) * ((1 - fx) * a + fx * b) + fy * ((1 - fx) * c + fx * d);
  };
  *value = lerp(grid[1][1], grid[1][2], grid[2][1], grid[2][2]);
  const float gx = lerp(grid[1][2] - grid[1][0], grid[1][3] - grid[1][1], grid[2][2] - grid[2][0],
                        grid[2][3] - grid[2][1]);
  const float gy = lerp(grid[2][1] - grid[0][1], grid[2][2] - grid[0][2], grid[3][1] - grid[1][1],
                        grid[3][2] - grid[1][2]);
  *gradient = 0.5f * Eigen::Vector2f(gx, gy);
  return true;
}

struct NormalEquations {
  Matrix6d geometric = Matrix6d::Zero();
  Matrix6d photometric = Matrix6d::Zero();
  Vector6d gradient = Vector6d::Zero();
  double squared_residuals = 0;
  int64_t pairs = 0;
  // w j j^T into the upper triangle of `h` (Symmetrize completes it once the sums are done).
  static void AddOuter(const Vector6d& j, double w, Matrix6d* h) {
    for (int c = 0; c < 6; ++c) {
      const double wj = w * j[c];
      for (int r = 0; r <= c; ++r) (*h)(r, c) += wj * j[r];
    }
  }
  void Symmetrize() {
    geometric.triangularView<Eigen::StrictlyLower>() = geometric.transpose();
    photometric.triangularView<Eigen::StrictlyLower>() = photometric.transpose();
  }
  void Add(const NormalEquations& other) {
    geometric += other.geometric;
    photometric += other.photometric;
    gradient += other.gradient;
    squared_residuals += other.squared_residuals;
    pairs += other.pairs;
  }
};

// One Gauss-Newton linearisation of the level's points against the reference.
class Linearizer {
 public:
  Linearizer(const ModelView& reference, const FastProjector& projector, const ScanOptions& options)
      : reference_(reference),
        projector_(projector),
        options_(options),
        cos_normal_(static_cast<float>(std::cos(options.max_normal_angle_deg * M_PI / 180))),
        photometric_(options.photometric_weight_m > 0 && !reference.intensity.empty()) {}

  NormalEquations Run(const Level& level, const Pose& world_from_cam, double gate_m,
                      int threads) const {
    const Eigen::Matrix3f rotation = world_from_cam.linear().cast<float>();
    const Eigen::Vector3f translation = world_from_cam.translation().cast<float>();
    const Eigen::Matrix3d ref_from_world = reference_.world_from_cam.linear().transpose();
    const float inv_stride = 1.0f / static_cast<float>(reference_.stride);
    // Small levels are not worth waking a second thread for.
    const int used_threads = level.points.size() >= kMinPointsPerThread * 2 ? threads : 1;
    std::vector<NormalEquations> partial(used_threads);
#pragma omp parallel num_threads(used_threads)
    {
      NormalEquations& eq = partial[omp_get_thread_num()];
#pragma omp for schedule(static)
      for (int i = 0; i < static_cast<int>(level.points.size()); ++i) {
        const Eigen::Vector3f& p = level.points[i];
        if (std::isnan(p.z()) || std::isnan(level.normals[i].z())) continue;
        const Eigen::Vector3f p_world = rotation * p + translation;
        float u = 0, v = 0, z = 0;
        if (!projector_.ProjectWorld(p_world, &u, &v, &z)) continue;
        // The reference pixel nearest the projection (the reference may be a coarser grid).
        u *= inv_stride;
        v *= inv_stride;
        if (!(u > -0.5f && v > -0.5f)) continue;
        const int px = static_cast<int>(u + 0.5f), py = static_cast<int>(v + 0.5f);
        if (px >= reference_.width || py >= reference_.height) continue;
        const size_t r = static_cast<size_t>(py) * reference_.width + px;
        const Eigen::Vector3f& q = reference_.points[r];
        if (std::isnan(q.z())) continue;
        const Eigen::Vector3f& n = reference_.normals[r];
        const Eigen::Vector3f diff = p_world - q;
        if (diff.squaredNorm() > gate_m * gate_m) continue;
        if ((rotation * level.normals[i]).dot(n) < cos_normal_) continue;
        const double residual = n.dot(diff);
        const double weight =
            std::abs(residual) <= options_.huber_m ? 1.0 : options_.huber_m / std::abs(residual);
        Vector6d j;
        j.head<3>() = n.cast<double>();
        j.tail<3>() = p_world.cast<double>().cross(n.cast<double>());
        NormalEquations::AddOuter(j, weight, &eq.geometric);
        eq.gradient += weight * j * residual;
        eq.squared_residuals += residual * residual;
        ++eq.pairs;
        if (photometric_ && !std::isnan(level.intensity[i])) {
          AddPhotometric(level.intensity[i], p_world, u, v, inv_stride, ref_from_world, &eq);
        }
      }
    }
    NormalEquations total;
    for (const NormalEquations& eq : partial) total.Add(eq);
    total.Symmetrize();
    return total;
  }

 private:
  // (u, v): the point's position on the reference's grid; inv_stride turns that grid's
  // intensity gradient into one per pixel of the lens.
  void AddPhotometric(float intensity, const Eigen::Vector3f& p_world, float u, float v,
                      float inv_stride, const Eigen::Matrix3d& ref_from_world,
                      NormalEquations* eq) const {
    float reference = 0;
    Eigen::Vector2f gradient;
    if (!IntensityAt(reference_.intensity, u, v, &reference, &gradient)) return;
    gradient *= inv_stride;
    const Eigen::Vector3d p_ref =
        ref_from_world * (p_world.cast<double>() - reference_.world_from_cam.translation());
    if (!(p_ref.z() > 1e-3)) return;
    const double f = projector_.focal(), iz = 1.0 / p_ref.z();
    // d intensity / d world point: the image gradient through the projection, into the world.
    const Eigen::Vector3d along_ref(
        f * iz * gradient.x(), f * iz * gradient.y(),
        -f * iz * iz * (gradient.x() * p_ref.x() + gradient.y() * p_ref.y()));
    const Eigen::Vector3d b = ref_from_world.transpose() * along_ref;
    // A left twist (t, w) moves the point by t + w x p: the same shape as the geometric row.
    const double lambda = options_.photometric_weight_m;
    Vector6d j;
    j.head<3>() = lambda * b;
    j.tail<3>() = lambda * p_world.cast<double>().cross(b);
    const double residual = lambda * (reference - intensity);
    // Robust to what the model's averaged colour cannot predict (specular, blur).
    const double weight =
        std::abs(residual) <= options_.huber_m ? 1.0 : options_.huber_m / std::abs(residual);
    NormalEquations::AddOuter(j, weight, &eq->photometric);
    eq->gradient += weight * j * residual;
  }

  const ModelView& reference_;
  const FastProjector& projector_;
  const ScanOptions& options_;
  float cos_normal_;
  bool photometric_;
};

// Rotations scaled to metres at `length_m` so that eigenvalues compare.
Matrix6d Scaled(const Matrix6d& h, double length_m) {
  Vector6d s;
  s << 1, 1, 1, 1 / length_m, 1 / length_m, 1 / length_m;
  return s.asDiagonal() * h * s.asDiagonal();
}

double Condition(const Matrix6d& scaled, Eigen::Vector3d* weak_translation = nullptr) {
  Eigen::SelfAdjointEigenSolver<Matrix6d> solver(scaled);
  const double largest = solver.eigenvalues()(5);
  if (!(largest > 0)) return 0;
  if (weak_translation != nullptr) *weak_translation = solver.eigenvectors().col(0).head<3>();
  return std::max(0.0, solver.eigenvalues()(0)) / largest;
}

}  // namespace

Pose ExpTwist(const Vector6d& twist) {
  Pose step = Pose::Identity();
  const Eigen::Vector3d omega = twist.tail<3>();
  const double angle = omega.norm();
  if (angle > 0) step.linear() = Eigen::AngleAxisd(angle, omega / angle).toRotationMatrix();
  step.translation() = twist.head<3>();
  return step;
}

cv::Mat RegisterIntensity(const cv::Mat& depth_m, const cv::Mat& rays, const cv::Mat& color_bgr,
                          const CameraModel& color_lens, const Pose& color_from_depth,
                          int threads) {
  cv::Mat gray(depth_m.size(), CV_32F, cv::Scalar(kNaN));
  if (color_bgr.empty()) return gray;
  CameraModel color = color_lens;
  color.set_cam_from_world(color_from_depth);
  const FastProjector projector(color);
  const int channels = color_bgr.channels();
#pragma omp parallel for num_threads(threads) schedule(static)
  for (int y = 0; y < depth_m.rows; ++y) {
    for (int x = 0; x < depth_m.cols; ++x) {
      const float d = depth_m.at<float>(y, x);
      const cv::Vec2f ray = rays.at<cv::Vec2f>(y, x);
      if (!(d > 0) || std::isnan(ray[0])) continue;
      float u = 0, v = 0, z = 0;
      if (!projector.ProjectWorld(Eigen::Vector3f(ray[0] * d, ray[1] * d, d), &u, &v, &z)) continue;
      const int cx = static_cast<int>(std::floor(u)), cy = static_cast<int>(std::floor(v));
      if (cx < 0 || cy < 0 || cx + 1 >= color_bgr.cols || cy + 1 >= color_bgr.rows) continue;
      const float fx = u - cx, fy = v - cy;
      float value = 0;
      for (int k = 0; k < 4; ++k) {
        const uint8_t* px = color_bgr.ptr<uint8_t>(cy + k / 2) + (cx + k % 2) * channels;
        const float w = (k % 2 ? fx : 1 - fx) * (k / 2 ? fy : 1 - fy);
        value += w * (0.114f * px[0] + 0.587f * px[1] + 0.299f * px[2]);
      }
      gray.at<float>(y, x) = value / 255.0f;
    }
  }
  return gray;
}

TrackFrame PrepareFrame(const cv::Mat& depth_m, const cv::Mat& rays, const cv::Mat& gray,
                        int levels, double depth_min_m, double depth_max_m) {
  TrackFrame frame;
  Level finest;
  finest.width = depth_m.cols;
  finest.height = depth_m.rows;
  finest.points.assign(static_cast<size_t>(finest.width) * finest.height, kNoPoint);
  finest.intensity.assign(finest.points.size(), kNaN);
  std::vector<float> depths;
  for (int y = 0; y < finest.height; ++y) {
    for (int x = 0; x < finest.width; ++x) {
      const float d = depth_m.at<float>(y, x);
      const cv::Vec2f ray = rays.at<cv::Vec2f>(y, x);
      if (!(d >= depth_min_m && d <= depth_max_m) || std::isnan(ray[0])) continue;
      const size_t i = static_cast<size_t>(y) * finest.width + x;
      finest.points[i] = Eigen::Vector3f(ray[0] * d, ray[1] * d, d);
      if (!gray.empty()) finest.intensity[i] = gray.at<float>(y, x);
      depths.push_back(d);
    }
  }
  frame.valid = static_cast<int64_t>(depths.size());
  if (!depths.empty()) {
    std::nth_element(depths.begin(), depths.begin() + depths.size() / 2, depths.end());
    frame.median_depth_m = depths[depths.size() / 2];
  }
  frame.levels.push_back(std::move(finest));
  for (int l = 1; l < levels; ++l) frame.levels.push_back(Downsample(frame.levels.back()));
  // Every level has its own normals, the finest too, so that every point with a neighbour on
  // the same surface can pair: noisy as they are there (7 mm at 2.4 m over a 3 cm baseline),
  // against the model they only gate the pairs (the residual is along the model's normal).
  for (size_t l = 0; l < frame.levels.size(); ++l) ComputeNormals(frame.levels[l], l <= 1 ? 2 : 1);
  return frame;
}

ModelView RaycastModel(const SparseVolume& volume, const cv::Mat& rays, const Pose& world_from_cam,
                       const cv::Mat& hint_depth_m, double window_m, int stride, int threads) {
  ModelView view;
  view.stride = stride;
  view.width = (rays.cols + stride - 1) / stride;
  view.height = (rays.rows + stride - 1) / stride;
  view.world_from_cam = world_from_cam;
  view.points.assign(static_cast<size_t>(view.width) * view.height, kNoPoint);
  view.normals.assign(view.points.size(), kNoPoint);
  view.intensity = cv::Mat(view.height, view.width, CV_32F, cv::Scalar(kNaN));
  const Eigen::Matrix3f rotation = world_from_cam.linear().cast<float>();
  const Eigen::Vector3f origin = world_from_cam.translation().cast<float>();
  const float voxel = static_cast<float>(volume.voxel_m());
  const float window = static_cast<float>(window_m);
  const float truncation = static_cast<float>(volume.truncation_m());
  int64_t hits = 0;
#pragma omp parallel num_threads(threads) reduction(+ : hits)
  {
    VolumeSampler sampler(volume);
#pragma omp for schedule(dynamic, 4)
    for (int y = 0; y < view.height; ++y) {
      for (int x = 0; x < view.width; ++x) {
        const float hint = hint_depth_m.at<float>(y * stride, x * stride);
        const cv::Vec2f ray = rays.at<cv::Vec2f>(y * stride, x * stride);
        if (!(hint > 0) || std::isnan(ray[0])) continue;
        // t runs along z (depth), the point is origin + t * direction with direction.z = 1.
        const Eigen::Vector3f direction = rotation * Eigen::Vector3f(ray[0], ray[1], 1);
        const float step_scale = direction.norm();
        float t = std::max(0.05f, hint - window);
        const float t_end = hint + window;
        float previous_t = -1, previous_sdf = 0;
        while (t <= t_end) {
          float sdf = 0;
          if (!sampler.Sample(origin + t * direction, &sdf)) {
            previous_t = -1;
            t += voxel / step_scale;
            continue;
          }
          if (sdf < 0) {
            // A crossing between the last two samples; or, entering the band behind the
            // surface (its front voxels unobserved), the surface |sdf| back along the ray.
            float hit_t = -1;
            if (previous_t >= 0 && previous_sdf > 0) {
              hit_t = previous_t + (t - previous_t) * previous_sdf / (previous_sdf - sdf);
            } else if (previous_t < 0 && sdf > -truncation) {
              hit_t = t + sdf / step_scale;
            }
            const Eigen::Vector3f point = origin + hit_t * direction;
            Eigen::Vector3f normal, rgb;
            float ignored = 0;
            if (hit_t > 0 && sampler.Normal(point, &normal) &&
                sampler.Sample(point, &ignored, &rgb)) {
              const size_t i = static_cast<size_t>(y) * view.width + x;
              view.points[i] = point;
              view.normals[i] = -normal.dot(direction) >= 0 ? normal : -normal;
              if (rgb.maxCoeff() > 0) view.intensity.at<float>(y, x) = Intensity(rgb);
              ++hits;
            }
            break;
          }
          previous_t = t;
          previous_sdf = sdf;
          t += std::max(0.5f * voxel, 0.8f * sdf) / step_scale;
        }
      }
    }
  }
  view.hits = hits;
  return view;
}

ModelView ViewOfFrame(const TrackFrame& frame, const Pose& world_from_cam) {
  const Level& level = frame.levels.front();
  ModelView view;
  view.width = level.width;
  view.height = level.height;
  view.world_from_cam = world_from_cam;
  view.points.assign(level.points.size(), kNoPoint);
  view.normals.assign(level.points.size(), kNoPoint);
  view.intensity = cv::Mat(level.height, level.width, CV_32F, cv::Scalar(kNaN));
  const Eigen::Isometry3f pose = world_from_cam.cast<float>();
  for (size_t i = 0; i < level.points.size(); ++i) {
    if (std::isnan(level.points[i].z()) || std::isnan(level.normals[i].z())) continue;
    view.points[i] = pose * level.points[i];
    view.normals[i] = pose.linear() * level.normals[i];
    view.intensity.at<float>(static_cast<int>(i) / level.width, static_cast<int>(i) % level.width) =
        level.intensity[i];
    ++view.hits;
  }
  return view;
}

AlignResult AlignToReference(const TrackFrame& frame, const ModelView& reference,
                             const CameraModel& lens, const Pose& initial,
                             const ScanOptions& options, int threads) {
  CameraModel at_reference = lens;
  at_reference.set_cam_from_world(reference.world_from_cam.inverse());
  const FastProjector projector(at_reference);
  const Linearizer linearizer(reference, projector, options);
  const double length_m = std::max(0.3, static_cast<double>(frame.median_depth_m));
  AlignResult result;
  result.world_from_cam = initial;
  result.points = frame.valid;
  NormalEquations last;
  for (int l = static_cast<int>(frame.levels.size()) - 1; l >= 0; --l) {
    const double gate = options.max_correspondence_m * std::pow(2.0, l);
    const int iterations = options.iterations[std::min<size_t>(l, options.iterations.size() - 1)];
    for (int it = 0; it < iterations; ++it) {
      last = linearizer.Run(frame.levels[l], result.world_from_cam, gate, threads);
      ++result.iterations;
      if (last.pairs < 6) break;
      const Matrix6d hessian = Scaled(last.geometric + last.photometric, length_m);
      Eigen::SelfAdjointEigenSolver<Matrix6d> solver(hessian);
      const double largest = solver.eigenvalues()(5);
      if (!(largest > 0)) break;
      // Solve in the eigenbasis, leaving the directions the data do not fix where they are.
      Vector6d s;
      s << 1, 1, 1, 1 / length_m, 1 / length_m, 1 / length_m;
      const Vector6d scaled_gradient = s.asDiagonal() * last.gradient;
      Vector6d step = Vector6d::Zero();
      for (int k = 0; k < 6; ++k) {
        const double lambda = solver.eigenvalues()(k);
        if (lambda < options.min_condition * largest) continue;
        const Eigen::Matrix<double, 6, 1> e = solver.eigenvectors().col(k);
        step -= e * (e.dot(scaled_gradient) / lambda);
      }
      step = s.asDiagonal() * step;
      result.world_from_cam = ExpTwist(step) * result.world_from_cam;
      if (step.head<3>().norm() < 1e-5 && step.tail<3>().norm() < 1e-5) break;
    }
  }
  // Each step multiplies the pose by a rotation, and the constant-velocity prediction it starts
  // from multiplies poses and their inverses (Isometry3d inverts by transposing): left alone,
  // rounding away from orthonormal compounds from frame to frame (1e-15 at the first frame,
  // 1e-2 by the 36th of an orbit, scaling every depth by a percent), so it is removed here.
  result.world_from_cam.linear() = NearestRotation(result.world_from_cam.linear());
  // The finest level's pairs at the final pose decide.
  last = linearizer.Run(frame.levels.front(), result.world_from_cam, options.max_correspondence_m,
                        threads);
  result.inliers = last.pairs;
  result.inlier_fraction =
      frame.valid > 0 ? static_cast<double>(last.pairs) / static_cast<double>(frame.valid) : 0;
  result.residual_m =
      last.pairs > 0 ? std::sqrt(last.squared_residuals / static_cast<double>(last.pairs)) : 0;
  result.geometric_condition = Condition(Scaled(last.geometric, length_m));
  result.condition =
      Condition(Scaled(last.geometric + last.photometric, length_m), &result.weak_direction);
  return result;
}

}  // namespace holocap::scan
