"""Open3D's RGB-D tracking on the frames scan_bench wrote: the peers that scan_bench compares
holocap's scanner against. Run with /usr/bin/python3 (Debian python3-open3d 0.16), with
OMP_WAIT_POLICY=PASSIVE and OMP_NUM_THREADS set to the thread count holocap uses.

usage: open3d_odometry.py DIR PEERS VOXEL_M DEPTH_MAX_M
DIR/frames.json gives the pinhole intrinsics (fx, fy, cx, cy, width, height), the first
frame's world_from_cam (4x4, row-major) and the frames, each with its time_s, a raw float32
z-depth map in metres (0 = none) and a raw 8-bit RGB image registered to the depth pixels.
PEERS is a comma list of:
  "odometry": frame to frame, o3d.pipelines.odometry.compute_rgbd_odometry (hybrid: depth
              and intensity, Open3D's default pyramid), poses chained. The tensor versions
              (o3d.t.pipelines.odometry, o3d.t.pipelines.slam.Model) cannot run here: Debian's
              CPU build of Open3D 0.16 lacks IPP, and their depth pre-filter stops with
              "FilterBilateral with data type Float32 on device CPU:0 is not implemented"
              (RGBToGray likewise); "slam" stays for a build that has it.
  "slam":     frame to model, o3d.t.pipelines.slam.Model (Open3D's dense SLAM: point-to-plane
              ICP against the model's raycast, then integration), voxel VOXEL_M, 8 voxels'
              truncation as Open3D's example uses.
Each peer writes DIR/PEER.tum (world_from_cam, TUM format, the frames' time_s) and prints
  PEER seconds_per_frame frames cpu_seconds_per_frame (process CPU time, every thread)
timing tracking (and, for slam, the raycast and integration) after the images are loaded.
"""
import json
import sys
import time

import numpy as np
import open3d as o3d

CPU = o3d.core.Device("CPU:0")


def load(folder):
    meta = json.load(open(folder + "/frames.json"))
    w, h = meta["width"], meta["height"]
    k = np.array([[meta["fx"], 0, meta["cx"]], [0, meta["fy"], meta["cy"]], [0, 0, 1]])
    frames = []
    for f in meta["frames"]:
        depth = np.fromfile(folder + "/" + f["depth"], dtype=np.float32).reshape(h, w)
        # Millimetres as UInt16 (as the sensor gives them): Open3D 0.16's CPU build filters
        # only those (FilterBilateral of Float32 is "not implemented" without IPP).
        depth = np.round(np.nan_to_num(depth) * 1000).astype(np.uint16)
        color = np.fromfile(folder + "/" + f["color"], dtype=np.uint8).reshape(h, w, 3)
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


def rgbd(depth, color):
    return o3d.t.geometry.RGBDImage(
        o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(color))),
        o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(depth))))


def odometry(frames, k, first, w, h, depth_max):
    intrinsic = o3d.camera.PinholeCameraIntrinsic(w, h, k[0, 0], k[1, 1], k[0, 2], k[1, 2])
    images = [o3d.geometry.RGBDImage.create_from_color_and_depth(
        o3d.geometry.Image(np.ascontiguousarray(color)), o3d.geometry.Image(depth),
        depth_scale=1000.0, depth_trunc=depth_max, convert_rgb_to_intensity=True)
        for _, depth, color in frames]
    option = o3d.pipelines.odometry.OdometryOption()
    option.depth_max = depth_max
    jacobian = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()
    poses = [first]
    start, start_cpu = time.perf_counter(), time.process_time()
    for i in range(1, len(images)):
        # source = frame i, target = frame i - 1: the result maps i's frame into i - 1's.
        ok, transformation, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
            images[i], images[i - 1], intrinsic, np.eye(4), jacobian, option)
        poses.append(poses[-1] @ (transformation if ok else np.eye(4)))
    return poses, time.perf_counter() - start, time.process_time() - start_cpu


def slam(frames, k, first, w, h, voxel, depth_max):
    intrinsics = o3d.core.Tensor(k)
    model = o3d.t.pipelines.slam.Model(voxel, 16, 40000, o3d.core.Tensor(first), CPU)
    input_frame = o3d.t.pipelines.slam.Frame(h, w, intrinsics, CPU)
    raycast_frame = o3d.t.pipelines.slam.Frame(h, w, intrinsics, CPU)
    images = [(o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(depth))),
               o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(color))))
              for _, depth, color in frames]
    pose = o3d.core.Tensor(first)
    poses = []
    start, start_cpu = time.perf_counter(), time.process_time()
    for i, (depth, color) in enumerate(images):
        input_frame.set_data_from_image("depth", depth)
        input_frame.set_data_from_image("color", color)
        if i > 0:
            result = model.track_frame_to_model(input_frame, raycast_frame, 1000.0, depth_max)
            pose = pose @ result.transformation
        model.update_frame_pose(i, pose)
        model.integrate(input_frame, 1000.0, depth_max, 8.0)
        model.synthesize_model_frame(raycast_frame, 1000.0, 0.1, depth_max, 8.0, False)
        poses.append(pose.numpy())
    return poses, time.perf_counter() - start, time.process_time() - start_cpu


def main():
    folder, peers, voxel, depth_max = sys.argv[1], sys.argv[2].split(","), float(sys.argv[3]), \
        float(sys.argv[4])
    frames, k, first, w, h = load(folder)
    for peer in peers:
        if peer == "odometry":
            poses, seconds, cpu_seconds = odometry(frames, k, first, w, h, depth_max)
        elif peer == "slam":
            poses, seconds, cpu_seconds = slam(frames, k, first, w, h, voxel, depth_max)
        else:
            sys.exit("unknown peer " + peer)
        with open("%s/%s.tum" % (folder, peer), "w") as out:
            for (t, _, _), pose in zip(frames, poses):
                out.write(tum_line(t, pose))
        print(peer, seconds / max(1, len(frames)), len(frames), cpu_seconds / max(1, len(frames)),
              flush=True)


if __name__ == "__main__":
    main()
