"""Open3D's TSDF volumes on the depth maps and poses recon_bench wrote: the peers that
recon_bench compares holocap's TSDF against. Run with /usr/bin/python3 (Debian python3-open3d).

usage: open3d_tsdf.py DIR VOXEL_M TRUNCATION_VOXELS DEPTH_MAX_M PEERS OUT_PREFIX [BLOCK_COUNT]
DIR/frames.json lists frames, each a list of depth maps (raw float32 z-depth in metres, 0 =
none) with their pinhole intrinsics and cam_from_world (4x4, row-major). PEERS is a comma list
of "vbg" (o3d.t.geometry.VoxelBlockGrid, CPU, 8^3 blocks like holocap's), "legacy"
(o3d.pipelines.integration.ScalableTSDFVolume) and "vbg-nan": VoxelBlockGrid given NaN where
the maps have 0. Open3D 0.16's VoxelBlockGrid does not reject NaN depth (its checks compare
false), so a NaN pixel's voxels take +truncation: with NaN outside the subject it carves the
free space around the subject's silhouette. "vbg-dense" is VoxelBlockGrid with the blocks of
every pixel: Open3D 0.16 finds a depth map's blocks from every 4th pixel across and down, which
leaves blocks of the surface out once a block spans fewer than 4 pixels (2 mm at 3 m). Each peer fuses every frame into a fresh volume
and meshes it (frame i's mesh to OUT_PREFIX-PEER-i.ply). VoxelBlockGrid is made with
BLOCK_COUNT blocks (default 50000), which it allocates and zeroes when it is made. Prints one line
per peer:
  PEER integrate_s_per_frame mesh_s_per_frame triangles_of_frame_0 peak_rss_growth_mb blocks
"vbg-sequence" and "legacy-sequence" fuse every frame into one volume, in order, and mesh it
once; they print "PEER-times" and the seconds of each frame first.
where peak_rss_growth_mb is the process's peak RSS less its RSS before the first volume (Linux
ru_maxrss) and blocks the most blocks one volume held (VoxelBlockGrid's hash map, its one far
block included; 0 for the legacy volume): what a reservation sized to the scene must hold.
Both peers fuse with the same voxel, truncation (voxels) and depth limit as holocap, weight 1
per measurement, and mesh every voxel observed at least once (weight > 0, as holocap does).
"""
import json
import resource
import sys
import time

import numpy as np
import open3d as o3d


def rss_mb():
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * resource.getpagesize() / 2**20


def load(folder):
    frames = []
    for frame in json.load(open(folder + "/frames.json"))["frames"]:
        maps = []
        for m in frame:
            w, h = m["width"], m["height"]
            depth = np.fromfile(folder + "/" + m["file"], dtype=np.float32).reshape(h, w)
            k = np.array([[m["fx"], 0, m["cx"]], [0, m["fy"], m["cy"]], [0, 0, 1]])
            extrinsic = np.array(m["cam_from_world"], dtype=np.float64).reshape(4, 4)
            maps.append((depth, k, extrinsic))
        frames.append(maps)
    return frames


class Vbg:
    def __init__(self, voxel, trunc_voxels, depth_max):
        self.grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"), attr_dtypes=(o3d.core.float32, o3d.core.float32),
            attr_channels=((1), (1)), voxel_size=voxel, block_resolution=8,
            block_count=Vbg.block_count, device=o3d.core.Device("CPU:0"))
        # Open3D 0.16's mesh extraction asserts that a voxel's buffer index is > 0, so a
        # surface crossing the first block allocated aborts it: an empty block far away takes
        # index 0 (weight 0: it never meshes and is never integrated).
        far = o3d.core.Tensor([[1 << 20] * 3], dtype=o3d.core.int32)
        zeros = o3d.core.Tensor(np.zeros((1, 8, 8, 8, 1), dtype=np.float32))
        self.grid.hashmap().insert(far, [zeros, zeros])
        self.trunc_voxels, self.depth_max = trunc_voxels, depth_max

    nan_for_zero = False
    block_count = 50000

    def blocks_held(self):
        return self.grid.hashmap().size()

    def prepare(self, maps, depth_max):
        def image(depth):
            return np.where(depth > 0, depth, np.float32(np.nan)) if self.nan_for_zero else depth
        return [(o3d.t.geometry.Image(o3d.core.Tensor(image(depth))), o3d.core.Tensor(k),
                 o3d.core.Tensor(extrinsic)) for depth, k, extrinsic in maps]

    def blocks(self, depth, k, extrinsic):
        # Open3D 0.16 finds a depth map's blocks from every 4th pixel across and down.
        return self.grid.compute_unique_block_coordinates(
            depth, k, extrinsic, depth_scale=1.0, depth_max=self.depth_max,
            trunc_voxel_multiplier=self.trunc_voxels)

    def integrate(self, inputs):
        for depth, k, extrinsic in inputs:
            blocks = self.blocks(depth, k, extrinsic)
            self.grid.integrate(blocks, depth, k, extrinsic, depth_scale=1.0,
                                depth_max=self.depth_max,
                                trunc_voxel_multiplier=self.trunc_voxels)

    def mesh(self):
        return self.grid.extract_triangle_mesh(weight_threshold=0.0).to_legacy()


class Legacy:
    def __init__(self, voxel, trunc_voxels, depth_max):
        self.volume = o3d.pipelines.integration.ScalableTSDFVolume(
            voxel_length=voxel, sdf_trunc=trunc_voxels * voxel,
            color_type=o3d.pipelines.integration.TSDFVolumeColorType.NoColor)

    @staticmethod
    def prepare(maps, depth_max):
        inputs = []
        for depth, k, extrinsic in maps:
            h, w = depth.shape
            color = o3d.geometry.Image(np.zeros((h, w, 3), dtype=np.uint8))
            rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
                color, o3d.geometry.Image(depth), depth_scale=1.0, depth_trunc=depth_max,
                convert_rgb_to_intensity=False)
            intrinsic = o3d.camera.PinholeCameraIntrinsic(w, h, k[0, 0], k[1, 1], k[0, 2],
                                                          k[1, 2])
            inputs.append((rgbd, intrinsic, extrinsic))
        return inputs

    def integrate(self, inputs):
        for rgbd, intrinsic, extrinsic in inputs:
            self.volume.integrate(rgbd, intrinsic, extrinsic)

    def mesh(self):
        return self.volume.extract_triangle_mesh()

    @staticmethod
    def blocks_held():
        return 0


class VbgNan(Vbg):
    nan_for_zero = True


class VbgDense(Vbg):
    """Blocks from every pixel: the blocks within the truncation of each pixel's point (the
    point-cloud overload), so that no block of the surface is left out."""

    def blocks(self, depth, k, extrinsic):
        points = o3d.t.geometry.PointCloud.create_from_depth_image(
            depth, k, extrinsic, depth_scale=1.0, depth_max=self.depth_max)
        return self.grid.compute_unique_block_coordinates(
            points, trunc_voxel_multiplier=self.trunc_voxels)


PEERS = {"vbg": Vbg, "vbg-nan": VbgNan, "vbg-dense": VbgDense, "legacy": Legacy}


def run(peer, frames, voxel, trunc_voxels, depth_max, out_prefix):
    """A fresh volume per frame: seconds per frame to integrate and to mesh."""
    integrate_s = mesh_s = 0.0
    triangles = blocks = 0
    for i, maps in enumerate(frames):
        volume = PEERS[peer](voxel, trunc_voxels, depth_max)
        inputs = volume.prepare(maps, depth_max)
        start = time.perf_counter()
        volume.integrate(inputs)
        integrate_s += time.perf_counter() - start
        blocks = max(blocks, volume.blocks_held())
        start = time.perf_counter()
        mesh = volume.mesh()
        mesh_s += time.perf_counter() - start
        triangles = triangles or len(mesh.triangles)
        o3d.io.write_triangle_mesh("%s-%s-%d.ply" % (out_prefix, peer, i), mesh,
                                   write_ascii=False, write_vertex_normals=False,
                                   write_vertex_colors=False)
    return integrate_s / len(frames), mesh_s / len(frames), triangles, blocks


def run_sequence(peer, frames, voxel, trunc_voxels, depth_max):
    """Every frame into one volume: the seconds of each frame, and of meshing the last."""
    volume = PEERS[peer](voxel, trunc_voxels, depth_max)
    times = []
    for maps in frames:
        inputs = volume.prepare(maps, depth_max)
        start = time.perf_counter()
        volume.integrate(inputs)
        times.append(time.perf_counter() - start)
    start = time.perf_counter()
    mesh = volume.mesh()
    return times, time.perf_counter() - start, len(mesh.triangles), volume.blocks_held()


def main():
    folder, voxel, trunc_voxels, depth_max = (sys.argv[1], float(sys.argv[2]),
                                              float(sys.argv[3]), float(sys.argv[4]))
    peers, out_prefix = sys.argv[5].split(","), sys.argv[6]
    if len(sys.argv) > 7:
        Vbg.block_count = int(sys.argv[7])
    frames = load(folder)
    base_mb = rss_mb()
    for peer in peers:
        if peer.endswith("-sequence"):
            times, mesh_s, triangles, blocks = run_sequence(peer[:-9], frames, voxel,
                                                            trunc_voxels, depth_max)
            print("%s-times %s" % (peer, " ".join("%.6f" % t for t in times)))
            integrate_s = sum(times) / len(times)
        else:
            integrate_s, mesh_s, triangles, blocks = run(peer, frames, voxel, trunc_voxels,
                                                         depth_max, out_prefix)
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - base_mb
        print("%s %.6f %.6f %d %.1f %d" % (peer, integrate_s, mesh_s, triangles, peak_mb, blocks),
              flush=True)


if __name__ == "__main__":
    main()
