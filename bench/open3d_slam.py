"""Open3D's dense RGB-D SLAM (o3d.t.pipelines.slam.Model, frame to model) on the frames that
scan_bench wrote: the peer scan_bench compares holocap's scanner against. Run with
/usr/bin/python3 (Debian python3-open3d 0.16), with OMP_WAIT_POLICY=PASSIVE and OMP_NUM_THREADS
set to the thread count holocap uses.

usage: open3d_slam.py DIR VOXEL_M TRUNC_VOXELS DEPTH_MIN_M DEPTH_MAX_M BLOCK_COUNT DEPTH_DIFF_M

DIR/frames.json gives the pinhole intrinsics (fx, fy, cx, cy, width, height), the first frame's
world_from_cam (4x4, row-major) and the frames, each with its time_s, a raw float32 z-depth map
in metres exactly as the take holds it (0 = no measurement) and a raw float32 RGB image in [0, 1]
registered to the depth pixels.

The loop is Open3D 0.16's examples/python/t_reconstruction_system/dense_slam.py: each frame is
tracked against the model's raycast from the previous pose (track_frame_to_model: point-to-plane
ICP, projective association, 3 pyramid levels of 6/3/1 iterations, depth_diff 0.07), its pose
chained, integrate(), synthesize_model_frame(). Depth goes in as float metres (depth_scale 1).

One step is rebuilt here from Open3D's own public kernels: Debian's CPU build of Open3D 0.16 has
no IPP, and Model.track_frame_to_model stops in it with "FilterBilateral with data type Float32
on device CPU:0 is not implemented" (the point-to-plane path smooths the raycast depth before
taking its normals; RGBToGray, FilterSobel and FilterGaussian, which the other methods need, are
missing likewise). track() below is RGBDOdometryMultiScalePointToPlane of Open3D 0.16
(cpp/open3d/t/pipelines/odometry/RGBDOdometry.cpp) step by step: ClipTransform, the vertex and
normal maps and each Gauss-Newton step (compute_odometry_result_point_to_plane) are Open3D's;
the 5x5 bilateral filter (value sigma 5, distance sigma 10, invalid pixels left out) and the
depth pyramid (Open3D's PyrDownDepth kernel, not exposed to Python) are numpy versions of the
same arithmetic. Both count in the peer's time.

Writes DIR/slam.tum (world_from_cam of every frame, TUM format, the frames' time_s) and prints
  slam seconds_per_frame frames cpu_seconds_per_frame standin_cpu_seconds_per_frame
timing the loop (tracking, integration, raycast) after the images are loaded; the last is the
process CPU time of the two numpy stand-ins (a build with IPP does that work in its own kernels).
"""
import json
import sys
import time

import numpy as np
import open3d as o3d

CPU = o3d.core.Device("CPU:0")
STANDIN_CPU_S = [0.0]  # process CPU time spent in the numpy stand-ins
NAN = float("nan")
# track_frame_to_model's defaults in Open3D 0.16.
CRITERIA = (6, 3, 1)
RELATIVE = 1e-6
DEPTH_HUBER_DELTA = 0.05


def load(folder):
    meta = json.load(open(folder + "/frames.json"))
    w, h = meta["width"], meta["height"]
    k = np.array([[meta["fx"], 0, meta["cx"]], [0, meta["fy"], meta["cy"]], [0, 0, 1]])
    frames = []
    for f in meta["frames"]:
        depth = np.fromfile(folder + "/" + f["depth"], dtype=np.float32).reshape(h, w)
        color = np.fromfile(folder + "/" + f["color"], dtype=np.float32).reshape(h, w, 3)
        frames.append((f["time_s"], depth, color))
    first = np.array(meta["world_from_cam"], dtype=np.float64).reshape(4, 4)
    return frames, k, first, w, h


def tum_line(t, pose):
    q = quaternion(pose[:3, :3])
    p = pose[:3, 3]
    return "%.6f %.9f %.9f %.9f %.9f %.9f %.9f %.9f\n" % (t, p[0], p[1], p[2], q[0], q[1], q[2], q[3])


def quaternion(r):
    # (x, y, z, w) of a rotation matrix (Shepperd's method).
    trace = np.trace(r)
    if trace > 0:
        s = 2 * np.sqrt(trace + 1)
        return ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4)
    i = int(np.argmax(np.diag(r)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = 2 * np.sqrt(1 + r[i, i] - r[j, j] - r[k, k])
    q = [0.0, 0.0, 0.0, 0.0]
    q[i] = s / 4
    q[j] = (r[j, i] + r[i, j]) / s
    q[k] = (r[k, i] + r[i, k]) / s
    q[3] = (r[k, j] - r[j, k]) / s
    return tuple(q)


def windows(depth, radius):
    """The (dy, dx, shifted) views of a NaN-padded map over a (2 radius + 1)^2 window."""
    padded = np.pad(depth, radius, constant_values=np.nan)
    h, w = depth.shape
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            yield dy, dx, padded[radius + dy:radius + dy + h, radius + dx:radius + dx + w]


def filter_bilateral(depth, kernel_size=5, value_sigma=5.0, distance_sigma=10.0):
    """Image::FilterBilateral(5, 5, 10) on a float depth map; NaN neighbours weigh nothing and a
    NaN pixel stays NaN."""
    start = time.process_time()
    total = np.zeros_like(depth)
    weight = np.zeros_like(depth)
    for dy, dx, v in windows(depth, kernel_size // 2):
        w = np.exp(-(dx * dx + dy * dy) / (2 * distance_sigma ** 2)) * \
            np.exp(-np.square(v - depth) / (2 * value_sigma ** 2))
        w = np.where(np.isnan(w), 0, w).astype(np.float32)
        total += w * np.nan_to_num(v)
        weight += w
    out = np.where(np.isnan(depth) | (weight == 0), np.float32(np.nan),
                   total / np.maximum(weight, 1e-30)).astype(np.float32)
    STANDIN_CPU_S[0] += time.process_time() - start
    return out


def pyrdown_depth(depth, depth_diff):
    """Open3D 0.16's PyrDownDepth kernel: every second pixel, the Gaussian (1 4 6 4 1)/16 mean of
    its 5x5 neighbours within depth_diff of it (NaN: none)."""
    start = time.process_time()
    gauss = (0.375, 0.25, 0.0625)
    total = np.zeros_like(depth)
    weight = np.zeros_like(depth)
    for dy, dx, v in windows(depth, 2):
        near = np.abs(v - depth) < depth_diff  # false where either is NaN
        w = np.float32(gauss[abs(dx)] * gauss[abs(dy)])
        total += np.where(near, w * v, 0)
        weight += np.where(near, w, 0)
    h, w = depth.shape
    total, weight = total[0:h // 2 * 2:2, 0:w // 2 * 2:2], weight[0:h // 2 * 2:2, 0:w // 2 * 2:2]
    out = np.where(weight == 0, np.float32(np.nan), total / np.maximum(weight, 1e-30)) \
        .astype(np.float32)
    STANDIN_CPU_S[0] += time.process_time() - start
    return out


def image(array):
    return o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(array)))


def relative_change(before, after):
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.abs(np.float64(before) - np.float64(after)) / np.float64(before)


def track(input_depth, raycast_depth, k, depth_max, depth_diff):
    """Model.track_frame_to_model(input, raycast, depth_scale=1, depth_max, depth_diff) with the
    point-to-plane method: the 4x4 transformation of the input frame into the raycast's."""
    source = input_depth.clip_transform(1.0, 0, depth_max, NAN).as_tensor().numpy()[:, :, 0]
    target = raycast_depth.clip_transform(1.0, 0, depth_max, NAN).as_tensor().numpy()[:, :, 0]
    levels = len(CRITERIA)
    source_vertex, target_vertex, target_normal, intrinsics = [], [], [], []
    k_level = k.copy()
    for i in range(levels):
        kt = o3d.core.Tensor(k_level)
        source_vertex.insert(0, image(source).create_vertex_map(kt, NAN).as_tensor())
        target_vertex.insert(0, image(target).create_vertex_map(kt, NAN).as_tensor())
        smooth = image(filter_bilateral(target)).create_vertex_map(kt, NAN)
        target_normal.insert(0, smooth.create_normal_map(NAN).as_tensor())
        intrinsics.insert(0, kt)
        if i != levels - 1:
            source = pyrdown_depth(source, 2 * depth_diff)
            target = pyrdown_depth(target, 2 * depth_diff)
            k_level = k_level / 2
            k_level[2, 2] = 1
    transformation = o3d.core.Tensor(np.eye(4))
    rmse, fitness = 0.0, 1.0
    for i in range(levels):
        for _ in range(CRITERIA[i]):
            delta = o3d.t.pipelines.odometry.compute_odometry_result_point_to_plane(
                source_vertex[i], target_vertex[i], target_normal[i], intrinsics[i],
                transformation, depth_diff, DEPTH_HUBER_DELTA)
            transformation = delta.transformation @ transformation
            if relative_change(fitness, delta.fitness) < RELATIVE and \
                    relative_change(rmse, delta.inlier_rmse) < RELATIVE:
                break
            rmse, fitness = delta.inlier_rmse, delta.fitness
    return transformation


def slam(frames, k, first, w, h, voxel, trunc_voxels, depth_min, depth_max, block_count,
         depth_diff):
    intrinsics = o3d.core.Tensor(k)
    model = o3d.t.pipelines.slam.Model(voxel, 16, block_count, o3d.core.Tensor(first), CPU)
    input_frame = o3d.t.pipelines.slam.Frame(h, w, intrinsics, CPU)
    raycast_frame = o3d.t.pipelines.slam.Frame(h, w, intrinsics, CPU)
    images = [(image(depth), image(color)) for _, depth, color in frames]
    pose = o3d.core.Tensor(first)
    poses = []
    start, start_cpu = time.perf_counter(), time.process_time()
    for i, (depth, color) in enumerate(images):
        input_frame.set_data_from_image("depth", depth)
        input_frame.set_data_from_image("color", color)
        if i > 0:
            pose = pose @ track(depth, raycast_frame.get_data_as_image("depth"), k, depth_max,
                                depth_diff)
        poses.append(pose.numpy())
        model.update_frame_pose(i, pose)
        model.integrate(input_frame, 1.0, depth_max, trunc_voxels)
        model.synthesize_model_frame(raycast_frame, 1.0, depth_min, depth_max, trunc_voxels, False)
    return poses, time.perf_counter() - start, time.process_time() - start_cpu


def main():
    folder = sys.argv[1]
    voxel, trunc_voxels, depth_min, depth_max = (float(v) for v in sys.argv[2:6])
    block_count, depth_diff = int(sys.argv[6]), float(sys.argv[7])
    frames, k, first, w, h = load(folder)
    poses, seconds, cpu_seconds = slam(frames, k, first, w, h, voxel, trunc_voxels, depth_min,
                                       depth_max, block_count, depth_diff)
    with open(folder + "/slam.tum", "w") as out:
        for (t, _, _), pose in zip(frames, poses):
            out.write(tum_line(t, pose))
    n = max(1, len(frames))
    print("slam", seconds / n, len(frames), cpu_seconds / n, STANDIN_CPU_S[0] / n, flush=True)


if __name__ == "__main__":
    main()
