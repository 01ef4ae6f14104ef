"""Open3D's ScalableTSDFVolume on the depth maps and poses recon_bench wrote: the peer that
recon_bench compares holocap's TSDF against. Run with /usr/bin/python3 (Debian python3-open3d).

usage: open3d_tsdf.py DIR VOXEL_M OUT_PLY
DIR/frames.json lists the depth maps (raw float32 z-depth in metres, 0 = none), their pinhole
intrinsics and cam_from_world (4x4, row-major). Prints one line: integrate_s mesh_s triangles.
"""
import json
import sys
import time

import numpy as np
import open3d as o3d


def main():
    folder, voxel, out = sys.argv[1], float(sys.argv[2]), sys.argv[3]
    spec = json.load(open(folder + "/frames.json"))
    volume = o3d.pipelines.integration.ScalableTSDFVolume(
        voxel_length=voxel, sdf_trunc=4 * voxel,
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.NoColor)
    inputs = []
    for frame in spec["frames"]:
        w, h = frame["width"], frame["height"]
        depth = np.fromfile(folder + "/" + frame["file"], dtype=np.float32).reshape(h, w)
        color = o3d.geometry.Image(np.zeros((h, w, 3), dtype=np.uint8))
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            color, o3d.geometry.Image(depth), depth_scale=1.0, depth_trunc=8.0,
            convert_rgb_to_intensity=False)
        fx, fy, cx, cy = frame["fx"], frame["fy"], frame["cx"], frame["cy"]
        intrinsic = o3d.camera.PinholeCameraIntrinsic(w, h, fx, fy, cx, cy)
        extrinsic = np.array(frame["cam_from_world"], dtype=np.float64).reshape(4, 4)
        inputs.append((rgbd, intrinsic, extrinsic))
    start = time.perf_counter()
    for rgbd, intrinsic, extrinsic in inputs:
        volume.integrate(rgbd, intrinsic, extrinsic)
    integrate_s = time.perf_counter() - start
    start = time.perf_counter()
    mesh = volume.extract_triangle_mesh()
    mesh_s = time.perf_counter() - start
    o3d.io.write_triangle_mesh(out, mesh, write_ascii=True, write_vertex_normals=False,
                               write_vertex_colors=False)
    print("open3d %.6f %.6f %d" % (integrate_s, mesh_s, len(mesh.triangles)))


if __name__ == "__main__":
    main()
