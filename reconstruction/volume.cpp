// The hashed sparse voxel volume and TSDF fusion of depth maps into it.
#include <omp.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <map>
#include <mutex>

#include "core/check_option.h"
#include "core/error.h"
#include "core/projector.h"
#include "core/threads.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

namespace {

constexpr int kKeyBits = 21;
constexpr int64_t kKeyOffset = int64_t{1} << (kKeyBits - 1);
constexpr uint64_t kKeyMask = (uint64_t{1} << kKeyBits) - 1;

int FloorDiv(int a, int b) { return a >= 0 ? a / b : -((-a + b - 1) / b); }

}  // namespace

SparseVolume::SparseVolume(double voxel_m, Box bounds, double truncation_m)
    : voxel_m_(voxel_m), bounds_(bounds), truncation_m_(truncation_m) {
  if (!(voxel_m > 0)) Fail("voxel size must be > 0 (got ", voxel_m, ")");
  if (!bounds.valid()) Fail("volume bounds are empty (max must exceed min on every axis)");
  Eigen::Vector3d extent_voxels = (bounds.max - bounds.min) / voxel_m;
  double limit = static_cast<double>(kKeyOffset) * kBlockSide;
  if ((bounds.min.array().abs() / voxel_m >= limit).any() ||
      (bounds.max.array().abs() / voxel_m >= limit).any() || !extent_voxels.allFinite()) {
    Fail("volume bounds span too many voxels of ", voxel_m, " m for the block index");
  }
}

BlockStore::BlockStore(const BlockStore& other) { *this = other; }

BlockStore& BlockStore::operator=(const BlockStore& other) {
  if (this == &other) return *this;
  chunks_.clear();
  size_ = 0;
  Reserve(other.size_);
  for (size_t i = 0; i < other.size_; ++i) (*this)[i] = other[i];
  size_ = other.size_;
  return *this;
}

VoxelBlock& BlockStore::Add() {
  if (size_ == capacity()) chunks_.push_back(std::make_unique<VoxelBlock[]>(kChunk));
  return (*this)[size_++];
}

void BlockStore::Reserve(size_t blocks) {
  while (capacity() < blocks) chunks_.push_back(std::make_unique<VoxelBlock[]>(kChunk));
}

void SparseVolume::Reserve(size_t blocks) {
  blocks_.Reserve(blocks);
  index_.reserve(blocks);
  coordinates_.reserve(blocks);
}

size_t SparseVolume::memory_bytes() const {
  return blocks_.capacity() * sizeof(VoxelBlock) +
         index_.size() * (sizeof(uint64_t) + sizeof(size_t) + 2 * sizeof(void*)) +
         index_.bucket_count() * sizeof(void*) + coordinates_.capacity() * sizeof(Eigen::Vector3i);
}

Eigen::Vector3i SparseVolume::BlockOf(const Eigen::Vector3i& voxel) {
  return {FloorDiv(voxel.x(), kBlockSide), FloorDiv(voxel.y(), kBlockSide),
          FloorDiv(voxel.z(), kBlockSide)};
}

uint64_t SparseVolume::Key(const Eigen::Vector3i& block) {
  return (static_cast<uint64_t>(block.x() + kKeyOffset) & kKeyMask) |
         ((static_cast<uint64_t>(block.y() + kKeyOffset) & kKeyMask) << kKeyBits) |
         ((static_cast<uint64_t>(block.z() + kKeyOffset) & kKeyMask) << (2 * kKeyBits));
}

Eigen::Vector3i SparseVolume::Unkey(uint64_t key) {
  return {static_cast<int>(static_cast<int64_t>(key & kKeyMask) - kKeyOffset),
          static_cast<int>(static_cast<int64_t>((key >> kKeyBits) & kKeyMask) - kKeyOffset),
          static_cast<int>(static_cast<int64_t>((key >> (2 * kKeyBits)) & kKeyMask) - kKeyOffset)};
}

Eigen::Vector3i SparseVolume::VoxelOf(const Eigen::Vector3d& point_in_world) const {
  return (point_in_world / voxel_m_).array().round().cast<int>();
}

Eigen::Vector3d SparseVolume::CenterOf(const Eigen::Vector3i& voxel) const {
  return voxel.cast<double>() * voxel_m_;
}

bool SparseVolume::BlockInBounds(const Eigen::Vector3i& block) const {
  Eigen::Vector3d lo = (block * kBlockSide).cast<double>() * voxel_m_;
  Eigen::Vector3d hi = lo + Eigen::Vector3d::Constant((kBlockSide - 1) * voxel_m_);
  return (hi.array() >= bounds_.min.array()).all() && (lo.array() <= bounds_.max.array()).all();
}

VoxelBlock* SparseVolume::Find(const Eigen::Vector3i& block) {
  auto it = index_.find(Key(block));
  return it == index_.end() ? nullptr : &blocks_[it->second];
}

const VoxelBlock* SparseVolume::Find(const Eigen::Vector3i& block) const {
  auto it = index_.find(Key(block));
  return it == index_.end() ? nullptr : &blocks_[it->second];
}

VoxelBlock& SparseVolume::Allocate(const Eigen::Vector3i& block) {
  auto [it, inserted] = index_.try_emplace(Key(block), blocks_.size());
  if (inserted) {
    blocks_.Add();
    coordinates_.push_back(block);
  }
  return blocks_[it->second];
}

const Voxel* SparseVolume::FindVoxel(const Eigen::Vector3i& voxel) const {
  Eigen::Vector3i block = BlockOf(voxel);
  const VoxelBlock* data = Find(block);
  if (data == nullptr) return nullptr;
  Eigen::Vector3i local = voxel - block * kBlockSide;
  return &data->at(local.x(), local.y(), local.z());
}

void SparseVolume::ForEachBlock(
    const std::function<void(const Eigen::Vector3i&, const VoxelBlock&)>& fn) const {
  for (size_t i = 0; i < blocks_.size(); ++i) fn(coordinates_[i], blocks_[i]);
}

std::vector<Eigen::Vector3i> SparseVolume::BlockCoordinates() const { return coordinates_; }

bool SparseVolume::Sample(const Eigen::Vector3d& point_in_world, double* sdf) const {
  Eigen::Vector3d g = point_in_world / voxel_m_;
  Eigen::Vector3i base = g.array().floor().cast<int>();
  Eigen::Vector3d f = g - base.cast<double>();
  double value = 0;
  for (int corner = 0; corner < 8; ++corner) {
    Eigen::Vector3i offset(corner & 1, (corner >> 1) & 1, (corner >> 2) & 1);
    const Voxel* voxel = FindVoxel(base + offset);
    if (voxel == nullptr || voxel->weight <= 0) return false;
    double w = (offset.x() ? f.x() : 1 - f.x()) * (offset.y() ? f.y() : 1 - f.y()) *
               (offset.z() ? f.z() : 1 - f.z());
    value += w * voxel->sdf;
  }
  *sdf = value;
  return true;
}

void TsdfOptions::Check() const {
  HOLOCAP_CHECK_OPTION_GT(voxel_m, 0);
  HOLOCAP_CHECK_OPTION_LT(voxel_m, 1);
  HOLOCAP_CHECK_OPTION_GE(truncation_voxels, 1);
  HOLOCAP_CHECK_OPTION_GT(max_weight, 0);
  HOLOCAP_CHECK_OPTION(bounds.valid(), bounds, "an empty box");
  HOLOCAP_CHECK_OPTION_GE(depth_min_m, 0);
  HOLOCAP_CHECK_OPTION_GT(depth_max_m, depth_min_m);
  HOLOCAP_CHECK_OPTION_GE(depth_noise_k, 0);
  HOLOCAP_CHECK_OPTION_IN(smoothing_radius_px, 0, 10);
  HOLOCAP_CHECK_OPTION_GT(max_incidence_deg, 0);
  HOLOCAP_CHECK_OPTION_LE(max_incidence_deg, 90);
  HOLOCAP_CHECK_OPTION_GT(carve_weight, 0);
  HOLOCAP_CHECK_OPTION_LE(carve_weight, 1);
  HOLOCAP_CHECK_OPTION_GT(band_voxels, 0);
  HOLOCAP_CHECK_OPTION_GE(threads, 0);
}

namespace {

constexpr float kFar = std::numeric_limits<float>::infinity();

struct CameraTables {
  FastProjector projector;
  cv::Mat rays;  // normalised rays per pixel
};

std::shared_ptr<const CameraTables> TablesFor(const CameraModel& camera) {
  return std::make_shared<const CameraTables>(
      CameraTables{FastProjector(camera), NormalisedRays(camera)});
}

bool ValidDepth(float d, const TsdfOptions& options) {
  return std::isfinite(d) && d > 0 && d >= options.depth_min_m && d <= options.depth_max_m;
}

// Valid measurements (within `foreground` when given), each replaced by the mean of the valid
// depths within options.smoothing_radius_px that lie within 3 sigma(z) of it (edge-preserving);
// NaN elsewhere. Counts the error codes (0, negative, infinite, out of range) in `rejected`.
cv::Mat SmoothedDepth(const cv::Mat& depth_in, const cv::Mat& foreground,
                      const TsdfOptions& options, int threads, int64_t* rejected_out) {
  const int w = depth_in.cols, h = depth_in.rows;
  const float k = static_cast<float>(options.depth_noise_k);
  cv::Mat depth(h, w, CV_32F, cv::Scalar(std::numeric_limits<float>::quiet_NaN()));
  int64_t rejected = 0;
  const int r = options.smoothing_radius_px;
#pragma omp parallel for num_threads(threads) reduction(+ : rejected) schedule(static)
  for (int y = 0; y < h; ++y) {
    const float* in = depth_in.ptr<float>(y);
    float* out = depth.ptr<float>(y);
    for (int x = 0; x < w; ++x) {
      float d = in[x];
      if (std::isnan(d)) continue;  // no measurement
      if (!ValidDepth(d, options)) {
        ++rejected;  // 0, negative, infinite or out of range: a sensor's error code
        continue;
      }
      if (!foreground.empty() && foreground.at<uint8_t>(y, x) == 0) continue;
      if (r > 0) {
        float sigma = std::max(k * d * d, 1e-4f);
        float range = 3 * sigma, sum = 0;
        int count = 0;
        for (int dy = -r; dy <= r; ++dy) {
          int yy = y + dy;
          if (yy < 0 || yy >= h) continue;
          const float* row = depth_in.ptr<float>(yy);
          for (int dx = -r; dx <= r; ++dx) {
            int xx = x + dx;
            if (xx < 0 || xx >= w) continue;
            float e = row[xx];
            if (ValidDepth(e, options) && std::abs(e - d) <= range) sum += e, ++count;
          }
        }
        d = sum / count;
      }
      out[x] = d;
    }
  }
  if (rejected_out != nullptr) *rejected_out += rejected;
  return depth;
}

// Integrate's checks: sizes and types of the depth map, the mask and the colour image.
// Returns whether colour is fused.
bool CheckFrame(const cv::Mat& depth_in, const CameraModel& depth_camera, const cv::Mat& foreground,
                const cv::Mat& color, const CameraModel* color_camera) {
  if (depth_in.type() != CV_32FC1) Fail("depth map must be CV_32F metres");
  if (depth_in.cols != depth_camera.width() || depth_in.rows != depth_camera.height()) {
    Fail("depth map is ", depth_in.cols, "x", depth_in.rows, " but its camera model is ",
         depth_camera.width(), "x", depth_camera.height());
  }
  if (!foreground.empty() &&
      (foreground.size() != depth_in.size() || foreground.type() != CV_8UC1)) {
    Fail("foreground mask must be CV_8U and the depth map's size");
  }
  const bool use_color = !color.empty() && color_camera != nullptr;
  if (use_color) {
    if (color.type() != CV_8UC3) Fail("colour image must be CV_8UC3");
    if (color.cols != color_camera->width() || color.rows != color_camera->height()) {
      Fail("colour image size does not match its camera model");
    }
  }
  return use_color;
}

// One depth map fused into a volume: its valid, smoothed, non-grazing depths; the blocks
// within the truncation band of them; then every voxel of those blocks updated.
class FrameIntegrator {
 public:
  FrameIntegrator(const TsdfOptions& options, SparseVolume& volume, const cv::Mat& depth_in,
                  const CameraModel& depth_camera, const cv::Mat& foreground, const cv::Mat& color,
                  const CameraModel* color_camera)
      : options_(options),
        volume_(volume),
        depth_in_(depth_in),
        depth_camera_(depth_camera),
        foreground_(foreground),
        color_(color),
        use_color_(CheckFrame(depth_in, depth_camera, foreground, color, color_camera)),
        threads_(ResolveThreads(options.threads)),
        tables_(TablesFor(depth_camera)),
        color_tables_(use_color_ ? TablesFor(*color_camera) : nullptr),
        w_(depth_in.cols),
        h_(depth_in.rows),
        k_(static_cast<float>(options.depth_noise_k)),
        voxel_(static_cast<float>(volume.voxel_m())),
        truncation_(static_cast<float>(volume.truncation_m())),
        carve_weight_(static_cast<float>(options.carve_weight)) {}

  TsdfFrameStats Run() {
    auto start = std::chrono::steady_clock::now();
    auto lap = [&start] {
      auto now = std::chrono::steady_clock::now();
      double seconds = std::chrono::duration<double>(now - start).count();
      start = now;
      return seconds;
    };
    PrepareDepth();
    stats_.prepare_seconds = lap();
    AllocateBlocks(TouchedBlocks());
    stats_.allocate_seconds = lap();
    FuseBlocks();
    stats_.fuse_seconds = lap();
    return stats_;
  }

 private:
  // 1. Valid, foreground, smoothed depth; grazing measurements removed; then, where free space
  // is carved, the background's pixels negated: its measurement, or -kFar where it has none (the
  // mask says the subject is not on that ray: free all along it).
  void PrepareDepth() {
    int64_t rejected = 0;
    depth_ = SmoothedDepth(depth_in_, foreground_, options_, threads_, &rejected);
    if (options_.max_incidence_deg < 90) depth_ = WithoutGrazing(&rejected);
    const bool carve = options_.carve_background && !foreground_.empty();
    measured_.clear();
    for (int y = 0; y < h_; ++y) {
      const float* row = depth_.ptr<float>(y);
      for (int x = 0; x < w_; ++x) {
        if (row[x] > 0) measured_.push_back(y * w_ + x);
      }
    }
    if (carve) {
#pragma omp parallel for num_threads(threads_) schedule(static)
      for (int y = 0; y < h_; ++y) {
        float* row = depth_.ptr<float>(y);
        const float* raw = depth_in_.ptr<float>(y);
        const uint8_t* mask = foreground_.ptr<uint8_t>(y);
        for (int x = 0; x < w_; ++x) {
          if (mask[x] == 0) row[x] = ValidDepth(raw[x], options_) ? -raw[x] : -kFar;
        }
      }
    }
    stats_.valid_pixels = static_cast<int64_t>(measured_.size());
    stats_.rejected_pixels = rejected;
  }

  // depth_ less the measurements whose surface normal (from the neighbours' points) is more
  // than max_incidence_deg from the ray; counts them in `rejected`.
  cv::Mat WithoutGrazing(int64_t* rejected_out) const {
    const float cos_max = static_cast<float>(std::cos(options_.max_incidence_deg * M_PI / 180));
    const cv::Mat& depth = depth_;
    const cv::Mat& rays = tables_->rays;
    cv::Mat kept = depth.clone();
    int64_t rejected = *rejected_out;
#pragma omp parallel for num_threads(threads_) reduction(+ : rejected) schedule(static)
    for (int y = 1; y < h_ - 1; ++y) {
      for (int x = 1; x < w_ - 1; ++x) {
        float d = depth.at<float>(y, x);
        if (!std::isfinite(d)) continue;
        auto point = [&](int xx, int yy, Eigen::Vector3f* p) {
          float e = depth.at<float>(yy, xx);
          cv::Vec2f ray = rays.at<cv::Vec2f>(yy, xx);
          if (!std::isfinite(e) || !std::isfinite(ray[0])) return false;
          *p = Eigen::Vector3f(ray[0] * e, ray[1] * e, e);
          return true;
        };
        Eigen::Vector3f c, px0, px1, py0, py1;
        point(x, y, &c);
        bool hx0 = point(x - 1, y, &px0), hx1 = point(x + 1, y, &px1);
        bool hy0 = point(x, y - 1, &py0), hy1 = point(x, y + 1, &py1);
        if (!(hx0 || hx1) || !(hy0 || hy1)) continue;
        Eigen::Vector3f dx = (hx1 ? px1 : c) - (hx0 ? px0 : c);
        Eigen::Vector3f dy = (hy1 ? py1 : c) - (hy0 ? py0 : c);
        Eigen::Vector3f normal = dx.cross(dy);
        float norm = normal.norm();
        if (norm <= 0) continue;
        float cos_incidence = std::abs(normal.dot(c)) / (norm * c.norm());
        if (cos_incidence < cos_max) {
          kept.at<float>(y, x) = std::numeric_limits<float>::quiet_NaN();
          ++rejected;
        }
      }
    }
    *rejected_out = rejected;
    return kept;
  }

  // 2. Blocks within options_.band_voxels (at most the truncation) of every measurement along
  // its ray, sorted and unique.
  std::vector<uint64_t> TouchedBlocks() const {
    const Pose world_from_cam = depth_camera_.world_from_cam();
    const Eigen::Matrix3f rotation = world_from_cam.rotation().cast<float>();
    const Eigen::Vector3f translation = world_from_cam.translation().cast<float>();
    const Eigen::Vector3f lo = volume_.bounds().min.cast<float>();
    const Eigen::Vector3f hi = volume_.bounds().max.cast<float>();
    const float block_m = voxel_ * kBlockSide;
    const float band = std::min(truncation_, static_cast<float>(options_.band_voxels) * voxel_);
    // The whole truncation band along the ray (the samples below reach every block it crosses)
    // closes the surface by itself; a narrower band adds the blocks around each measured point.
    const bool whole_band = band >= truncation_;
    // Within one voxel the blocks around the measured point (below) hold the whole band.
    const int band_steps =
        band <= voxel_ ? 0 : std::max(1, static_cast<int>(std::ceil(band / (0.5f * block_m))));
    // Voxel i sits at i * voxel, block j holds voxels 8j..8j+7: a point's block is
    // floor((p / voxel + 0.5) / 8).
    const float to_block = 1.0f / block_m, half_voxel = 0.5f / kBlockSide;
    auto floor_int = [](float f) {
      int i = static_cast<int>(f);
      return i - (f < static_cast<float>(i));
    };
    const float to_voxel = 1.0f / voxel_;
    std::vector<std::vector<uint64_t>> per_thread(threads_);
    const int count = static_cast<int>(measured_.size());
#pragma omp parallel num_threads(threads_)
    {
      auto& keys = per_thread[omp_get_thread_num()];
      // Neighbouring pixels touch the same blocks: a small cache of recent keys keeps most
      // repeats out of the list that is sorted.
      uint64_t recent[64];
      std::fill(std::begin(recent), std::end(recent), ~uint64_t{0});
      auto add = [&](const Eigen::Vector3i& block) {
        const uint64_t key = SparseVolume::Key(block);
        uint64_t& slot = recent[(key ^ (key >> 21) ^ (key >> 42)) & 63];
        if (slot != key) keys.push_back(key), slot = key;
      };
#pragma omp for schedule(static)
      for (int i = 0; i < count; ++i) {
        const int pixel = measured_[i];
        const float d = depth_.ptr<float>()[pixel];
        const cv::Vec2f ray = tables_->rays.ptr<cv::Vec2f>()[pixel];
        const Eigen::Vector3f direction(ray[0], ray[1], 1);
        const float length = direction.norm();
        for (int s = -band_steps; s <= band_steps; ++s) {
          const float along = d * length + (band_steps > 0 ? s * band / band_steps : 0.0f);
          const Eigen::Vector3f p = rotation * (direction * (along / length)) + translation;
          if (!((p.array() >= lo.array()).all() && (p.array() <= hi.array()).all())) continue;
          if (s != 0 || whole_band) {
            add(Eigen::Vector3i(floor_int(p.x() * to_block + half_voxel),
                                floor_int(p.y() * to_block + half_voxel),
                                floor_int(p.z() * to_block + half_voxel)));
            continue;
          }
          // The measured point itself: every block holding a voxel within one voxel of the
          // cell around it (voxels floor(p) - 1 .. floor(p) + 1 on each axis), so that the
          // surface there is meshed whole even where the narrow band along the ray stays inside
          // one block (with the cell's own corners alone a sphere's mesh has open edges).
          const Eigen::Vector3i cell(floor_int(p.x() * to_voxel), floor_int(p.y() * to_voxel),
                                     floor_int(p.z() * to_voxel));
          const Eigen::Vector3i first = SparseVolume::BlockOf(cell - Eigen::Vector3i::Ones());
          const Eigen::Vector3i last = SparseVolume::BlockOf(cell + Eigen::Vector3i::Ones());
          for (int z = first.z(); z <= last.z(); ++z)
            for (int y = first.y(); y <= last.y(); ++y)
              for (int x = first.x(); x <= last.x(); ++x) add(Eigen::Vector3i(x, y, z));
        }
      }
      std::sort(keys.begin(), keys.end());
      keys.erase(std::unique(keys.begin(), keys.end()), keys.end());
    }
    std::vector<uint64_t> touched;
    for (auto& keys : per_thread) touched.insert(touched.end(), keys.begin(), keys.end());
    if (threads_ > 1) {
      std::sort(touched.begin(), touched.end());
      touched.erase(std::unique(touched.begin(), touched.end()), touched.end());
    }
    return touched;
  }

  void AllocateBlocks(const std::vector<uint64_t>& touched) {
    blocks_.resize(touched.size());
    coordinates_.resize(touched.size());
    for (size_t i = 0; i < touched.size(); ++i) {
      coordinates_[i] = SparseVolume::Unkey(touched[i]);
      blocks_[i] = &volume_.Allocate(coordinates_[i]);
    }
    stats_.blocks_touched = static_cast<int64_t>(touched.size());
  }

  // 3. Projective signed distances, noise-weighted running averages with capped weights. One
  // parallel region over the blocks, statically scheduled: blocks cost about the same.
  void FuseBlocks() {
    int64_t updated = 0, carved = 0;
#pragma omp parallel for num_threads(threads_) reduction(+ : updated, carved) schedule(static)
    for (size_t b = 0; b < blocks_.size(); ++b) FuseBlock(b, &updated, &carved);
    stats_.voxels_updated = updated;
    stats_.voxels_carved = carved;
  }

  // Whether every voxel centre of the block at `base` (voxel coordinates) lies in the bounds.
  bool BlockInsideBounds(const Eigen::Vector3i& base) const {
    const Box& bounds = volume_.bounds();
    Eigen::Vector3d lo = base.cast<double>() * volume_.voxel_m();
    Eigen::Vector3d hi =
        (base + Eigen::Vector3i::Constant(kBlockSide - 1)).cast<double>() * volume_.voxel_m();
    return bounds.Contains(lo) && bounds.Contains(hi);
  }

  // The lens over one block: the table's projection made affine in the normalised coordinates
  // (x/z, y/z) around the block's centre (central differences over the block's extent), used
  // where it agrees with the table at the block's eight corners to kAffineTolerancePx (the
  // error is quadratic, largest at the corners); elsewhere the table, voxel by voxel.
  struct BlockLens {
    bool affine = false;
    float a0 = 0, b0 = 0, u0 = 0, v0 = 0, du_da = 0, du_db = 0, dv_da = 0, dv_db = 0;
  };
  static constexpr float kAffineTolerancePx = 0.02f;

  BlockLens LensOver(const Eigen::Vector3f& origin, const Eigen::Matrix3f& steps) const {
    const auto& projector = tables_->projector;
    BlockLens lens;
    const Eigen::Vector3f centre =
        origin + steps * Eigen::Vector3f::Constant(0.5f * (kBlockSide - 1));
    if (!(centre.z() > 1e-6f)) return lens;
    lens.a0 = centre.x() / centre.z();
    lens.b0 = centre.y() / centre.z();
    Eigen::Vector2f corners_ab[8], corners_uv[8];
    float half_a = 0, half_b = 0;
    for (int c = 0; c < 8; ++c) {
      Eigen::Vector3f corner = origin + steps * Eigen::Vector3f(c & 1, (c >> 1) & 1, (c >> 2) & 1) *
                                            static_cast<float>(kBlockSide - 1);
      if (!projector.Project(corner, &corners_uv[c].x(), &corners_uv[c].y())) return lens;
      corners_ab[c] = corner.head<2>() / corner.z();
      half_a = std::max(half_a, std::abs(corners_ab[c].x() - lens.a0));
      half_b = std::max(half_b, std::abs(corners_ab[c].y() - lens.b0));
    }
    float u[5], v[5];
    const Eigen::Vector3f samples[5] = {{lens.a0, lens.b0, 1},
                                        {lens.a0 - half_a, lens.b0, 1},
                                        {lens.a0 + half_a, lens.b0, 1},
                                        {lens.a0, lens.b0 - half_b, 1},
                                        {lens.a0, lens.b0 + half_b, 1}};
    for (int i = 0; i < 5; ++i) {
      if (!projector.Project(samples[i], &u[i], &v[i])) return lens;
    }
    if (!(half_a > 0 && half_b > 0)) return lens;
    lens.u0 = u[0];
    lens.v0 = v[0];
    lens.du_da = (u[2] - u[1]) / (2 * half_a);
    lens.dv_da = (v[2] - v[1]) / (2 * half_a);
    lens.du_db = (u[4] - u[3]) / (2 * half_b);
    lens.dv_db = (v[4] - v[3]) / (2 * half_b);
    for (int c = 0; c < 8; ++c) {
      const float da = corners_ab[c].x() - lens.a0, db = corners_ab[c].y() - lens.b0;
      if (std::abs(lens.u0 + lens.du_da * da + lens.du_db * db - corners_uv[c].x()) >
              kAffineTolerancePx ||
          std::abs(lens.v0 + lens.dv_da * da + lens.dv_db * db - corners_uv[c].y()) >
              kAffineTolerancePx)
        return lens;
    }
    lens.affine = true;
    return lens;
  }

  // Block b's voxels that project onto a measurement (or onto the background, in front of it),
  // row by row of eight voxels, each step over the eight branch-free so that the compiler
  // vectorises it: the voxels' pixels and ray lengths (camera coordinates stepped voxel by voxel
  // through the block's lens), the depths at those pixels, the signed distances and weights
  // (weight 0: no update), then the running averages.
  void FuseBlock(size_t b, int64_t* updated_out, int64_t* carved_out) const {
    const auto& projector = tables_->projector;
    VoxelBlock& block = *blocks_[b];
    const Eigen::Vector3i base = coordinates_[b] * kBlockSide;
    const bool inside = BlockInsideBounds(base);
    const Eigen::Vector3f origin = projector.ToCamera(base.cast<float>() * voxel_);
    const Eigen::Vector3f zero = projector.ToCamera(Eigen::Vector3f::Zero());
    Eigen::Matrix3f steps;  // columns: camera coordinates of one voxel along x, y, z
    for (int axis = 0; axis < 3; ++axis)
      steps.col(axis) = projector.ToCamera(Eigen::Vector3f::Unit(axis) * voxel_) - zero;
    const BlockLens lens = LensOver(origin, steps);
    int64_t updated = 0, carved = 0;
    for (int z = 0; z < kBlockSide; ++z) {
      for (int y = 0; y < kBlockSide; ++y) {
        const Eigen::Vector3f row =
            origin + static_cast<float>(z) * steps.col(2) + static_cast<float>(y) * steps.col(1);
        float us[kBlockSide], vs[kBlockSide], zs[kBlockSide], along_squared[kBlockSide];
        for (int x = 0; x < kBlockSide; ++x) {
          const float px = row.x() + x * steps(0, 0), py = row.y() + x * steps(1, 0),
                      pz = row.z() + x * steps(2, 0);
          const float inverse_z = 1.0f / pz;
          const float da = px * inverse_z - lens.a0, db = py * inverse_z - lens.b0;
          us[x] = lens.u0 + lens.du_da * da + lens.du_db * db;
          vs[x] = lens.v0 + lens.dv_da * da + lens.dv_db * db;
          zs[x] = pz;
          along_squared[x] = (px * px + py * py) * (inverse_z * inverse_z) + 1;
        }
        if (!lens.affine) {
          for (int x = 0; x < kBlockSide; ++x) {
            const Eigen::Vector3f p = row + static_cast<float>(x) * steps.col(0);
            if (!projector.Project(p, &us[x], &vs[x])) us[x] = -1;  // outside: no depth below
          }
        }
        float depths[kBlockSide];
        MeasurementsAt(us, vs, depths);
        if (!inside) WithoutOutOfBounds(base + Eigen::Vector3i(0, y, z), depths);
        bool measured = false;  // rows that see no measurement (beside the subject) are left be
        for (int x = 0; x < kBlockSide; ++x) measured |= depths[x] == depths[x];
        if (!measured) continue;
        float sdfs[kBlockSide], weights[kBlockSide];
        carved += Observations(depths, zs, along_squared, sdfs, weights);
        updated += UpdateRow(base, y, z, sdfs, weights, &block.at(0, y, z));
      }
    }
    *updated_out += updated;
    *carved_out += carved;
  }

  // The depth map at each of eight pixel positions (nearest pixel); NaN outside the image.
  void MeasurementsAt(const float* us, const float* vs, float* depths) const {
    const float max_u = w_ - 0.5f, max_v = h_ - 0.5f;
    const float* depth = depth_.ptr<float>();
    for (int x = 0; x < kBlockSide; ++x) {
      const float u = us[x], v = vs[x];
      const bool in_image = u >= -0.5f && v >= -0.5f && u < max_u && v < max_v;
      const int pixel = in_image ? static_cast<int>(v + 0.5f) * w_ + static_cast<int>(u + 0.5f) : 0;
      depths[x] = in_image ? depth[pixel] : std::numeric_limits<float>::quiet_NaN();
    }
  }

  // NaN for the voxels of the row from `first` (voxel coordinates) whose centre is outside the
  // bounds.
  void WithoutOutOfBounds(const Eigen::Vector3i& first, float* depths) const {
    for (int x = 0; x < kBlockSide; ++x) {
      if (!volume_.bounds().Contains((first + Eigen::Vector3i(x, 0, 0)).cast<double>() *
                                     volume_.voxel_m()))
        depths[x] = std::numeric_limits<float>::quiet_NaN();
    }
  }

  // Projective signed distances along the ray (not along z: not stretched at the image border)
  // and noise weights of eight voxels from their depths; weight 0 where there is no update (no
  // measurement, more than the truncation behind it, or a background pixel's free space at or
  // behind the room's surface: not the subject). Returns how many are background free space.
  int64_t Observations(const float* depths, const float* zs, const float* along_squared,
                       float* sdfs, float* weights) const {
    int carved = 0;
    const float truncation = truncation_, carve_weight = carve_weight_;
    const float noise = k_ > 0 ? 1.0f : 0.0f;
#pragma omp simd reduction(+ : carved)
    for (int x = 0; x < kBlockSide; ++x) {
      const float d = depths[x];
      const float sdf = (std::abs(d) - zs[x]) * std::sqrt(along_squared[x]);
      const bool background = d < 0;  // negated: free space up to its measurement
      const bool keep = sdf >= -truncation && !(background && sdf < truncation);  // false: NaN
      const float depth = background ? zs[x] : d;
      // sigma(1 m) / sigma(d), squared
      const float ratio = noise / (depth * depth) + (1.0f - noise);
      const float weight =
          std::min(std::max(ratio * ratio, 1e-3f), 1.0f) * (background ? carve_weight : 1.0f);
      sdfs[x] = keep ? std::min(sdf, truncation) : 0.0f;
      weights[x] = keep ? weight : 0.0f;
      carved += keep && background ? 1 : 0;
    }
    return carved;
  }

  // Noise-weighted running averages of eight voxels (row y, z of the block at `base`) with
  // capped weights; colour where fused, near the surface. Returns how many were updated.
  int64_t UpdateRow(const Eigen::Vector3i& base, int y, int z, const float* sdfs,
                    const float* weights, Voxel* voxels) const {
    if (use_color_) {
      for (int x = 0; x < kBlockSide; ++x) {
        if (!(weights[x] > 0 && std::abs(sdfs[x]) < 0.5f * truncation_)) continue;
        const Eigen::Vector3f world = (base + Eigen::Vector3i(x, y, z)).cast<float>() * voxel_;
        BlendColor(world, weights[x], voxels[x].weight + weights[x], &voxels[x]);
      }
    }
    bool observed = false;
    for (int x = 0; x < kBlockSide; ++x) observed |= weights[x] > 0;
    if (!observed) return 0;
    // Through arrays of eight so that the arithmetic vectorises (the voxels interleave colour).
    float old_sdfs[kBlockSide], old_weights[kBlockSide];
    for (int x = 0; x < kBlockSide; ++x)
      old_sdfs[x] = voxels[x].sdf, old_weights[x] = voxels[x].weight;
    int updated = 0;
    const float max_weight = options_.max_weight;
#pragma omp simd reduction(+ : updated)
    for (int x = 0; x < kBlockSide; ++x) {
      const float weight = weights[x];
      const float total = old_weights[x] + weight;
      old_sdfs[x] += (sdfs[x] - old_sdfs[x]) * (weight / std::max(total, 1e-30f));
      old_weights[x] = std::min(total, max_weight);
      updated += weight > 0 ? 1 : 0;
    }
    for (int x = 0; x < kBlockSide; ++x)
      voxels[x].sdf = old_sdfs[x], voxels[x].weight = old_weights[x];
    return updated;
  }

  // The colour image's pixel at `world`, averaged into the voxel with the measurement's
  // weight (the voxel's weight not yet updated).
  void BlendColor(const Eigen::Vector3f& world, float weight, float total,
                  Voxel* voxel_data) const {
    float cu, cv_;
    Eigen::Vector3f pc = color_tables_->projector.ToCamera(world);
    if (!color_tables_->projector.Project(pc, &cu, &cv_) ||
        !color_tables_->projector.InImage(cu, cv_, 0.5f)) {
      return;
    }
    cv::Vec3b bgr =
        color_.at<cv::Vec3b>(static_cast<int>(std::lround(cv_)), static_cast<int>(std::lround(cu)));
    float old = voxel_data->weight;
    voxel_data->r = static_cast<uint8_t>((voxel_data->r * old + bgr[2] * weight) / total + 0.5f);
    voxel_data->g = static_cast<uint8_t>((voxel_data->g * old + bgr[1] * weight) / total + 0.5f);
    voxel_data->b = static_cast<uint8_t>((voxel_data->b * old + bgr[0] * weight) / total + 0.5f);
  }

  const TsdfOptions& options_;
  SparseVolume& volume_;
  const cv::Mat& depth_in_;
  const CameraModel& depth_camera_;
  const cv::Mat& foreground_;
  const cv::Mat& color_;
  const bool use_color_;
  const int threads_;
  const std::shared_ptr<const CameraTables> tables_, color_tables_;
  const int w_, h_;
  const float k_;  // depth_noise_k
  const float voxel_, truncation_;
  const float carve_weight_;  // of free space, relative to a measurement at the voxel's depth

  cv::Mat depth_;              // the depths fused: valid, smoothed, not grazing; NaN elsewhere
  std::vector<int> measured_;  // the pixels (y * width + x) with a depth fused
  std::vector<VoxelBlock*> blocks_;  // the blocks touched, and their coordinates
  std::vector<Eigen::Vector3i> coordinates_;
  TsdfFrameStats stats_;
};

}  // namespace

TsdfVolume::TsdfVolume(const TsdfOptions& options)
    : options_((options.Check(), options)),
      volume_(options.voxel_m, options.bounds, options.voxel_m * options.truncation_voxels) {
  if (options.reserve_blocks > 0) volume_.Reserve(options.reserve_blocks);
}

TsdfFrameStats TsdfVolume::Integrate(const cv::Mat& depth_in, const CameraModel& depth_camera,
                                     const cv::Mat& foreground, const cv::Mat& color,
                                     const CameraModel* color_camera) {
  auto start = std::chrono::steady_clock::now();
  TsdfFrameStats stats =
      FrameIntegrator(options_, volume_, depth_in, depth_camera, foreground, color, color_camera)
          .Run();
  stats.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return stats;
}

CompletionStats TsdfVolume::CompleteFromHull(
    const VisualHull& hull, const std::vector<std::pair<CameraModel, cv::Mat>>& depth_maps,
    float weight) {
  auto start = std::chrono::steady_clock::now();
  if (hull.volume == nullptr) Fail("completion needs a computed visual hull");
  if (!(weight > 0)) Fail("completion weight must be > 0 (got ", weight, ")");
  const int threads = ResolveThreads(options_.threads);
  struct FreeSpace {
    std::shared_ptr<const CameraTables> tables;
    cv::Mat depth;
  };
  std::vector<FreeSpace> free_space;
  for (const auto& [camera, depth] : depth_maps) {
    if (depth.type() != CV_32FC1 || depth.cols != camera.width() || depth.rows != camera.height()) {
      Fail("completion: depth map must be CV_32F metres of its camera's size (", camera.width(),
           "x", camera.height(), ")");
    }
    // Background included: a point in front of the wall a sensor measured is outside too.
    free_space.push_back(
        {TablesFor(camera), SmoothedDepth(depth, cv::Mat(), options_, threads, nullptr)});
  }

  // The blocks around the hull's surface, on this volume's grid, and the volume's own.
  std::vector<uint64_t> keys;
  const SparseVolume& hull_volume = *hull.volume;
  const double voxel = volume_.voxel_m();
  hull_volume.ForEachBlock([&](const Eigen::Vector3i& block, const VoxelBlock&) {
    Eigen::Vector3d lo = (block * kBlockSide).cast<double>() * hull_volume.voxel_m();
    Eigen::Vector3d hi = lo + Eigen::Vector3d::Constant((kBlockSide - 1) * hull_volume.voxel_m());
    Eigen::Vector3i first = SparseVolume::BlockOf((lo / voxel).array().floor().cast<int>());
    Eigen::Vector3i last = SparseVolume::BlockOf((hi / voxel).array().ceil().cast<int>());
    for (int z = first.z(); z <= last.z(); ++z)
      for (int y = first.y(); y <= last.y(); ++y)
        for (int x = first.x(); x <= last.x(); ++x) keys.push_back(SparseVolume::Key({x, y, z}));
  });
  std::sort(keys.begin(), keys.end());
  keys.erase(std::unique(keys.begin(), keys.end()), keys.end());
  CompletionStats stats;
  for (uint64_t key : keys) {
    Eigen::Vector3i block = SparseVolume::Unkey(key);
    if (volume_.Find(block) != nullptr || !volume_.BlockInBounds(block)) continue;
    volume_.Allocate(block);
    ++stats.blocks_added;
  }
  std::vector<Eigen::Vector3i> coordinates = volume_.BlockCoordinates();
  std::vector<VoxelBlock*> blocks;
  for (const auto& block : coordinates) blocks.push_back(volume_.Find(block));

  const float truncation = static_cast<float>(volume_.truncation_m());
  const Box& bounds = volume_.bounds();
  int64_t filled = 0, carved = 0;
#pragma omp parallel for num_threads(threads) reduction(+ : filled, carved) schedule(dynamic, 16)
  for (size_t b = 0; b < blocks.size(); ++b) {
    const Eigen::Vector3i base = coordinates[b] * kBlockSide;
    for (int z = 0; z < kBlockSide; ++z) {
      for (int y = 0; y < kBlockSide; ++y) {
        for (int x = 0; x < kBlockSide; ++x) {
          Voxel& out = blocks[b]->at(x, y, z);
          if (out.weight > 0) continue;  // a depth map saw it
          const Eigen::Vector3d world = (base + Eigen::Vector3i(x, y, z)).cast<double>() * voxel;
          if (!bounds.Contains(world)) continue;
          const double hull_field = hull.Field(world);
          float field = static_cast<float>(std::clamp(hull_field, -1e3, 1e3));
          for (const FreeSpace& sensor : free_space) {
            const auto& projector = sensor.tables->projector;
            Eigen::Vector3f p = projector.ToCamera(world.cast<float>());
            float u, v;
            if (!projector.Project(p, &u, &v)) continue;
            int px = static_cast<int>(std::lround(u)), py = static_cast<int>(std::lround(v));
            if (px < 0 || py < 0 || px >= sensor.depth.cols || py >= sensor.depth.rows) continue;
            float d = sensor.depth.at<float>(py, px);
            if (!std::isfinite(d)) continue;
            float sdf = (d - p.z()) * (p.norm() / p.z());  // as Integrate measures it
            if (sdf < -truncation) continue;               // behind the surface: not seen
            field = std::max(field, sdf);
          }
          carved += field > 0 && hull_field <= 0;
          out.sdf = std::clamp(field, -truncation, truncation);
          out.weight = weight;
          ++filled;
        }
      }
    }
  }
  stats.voxels_filled = filled;
  stats.voxels_carved = carved;
  stats.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return stats;
}

}  // namespace holocap
