"""The classical baseline every SLAM bench runs beside bgs: Open3D's dense RGB-D SLAM.

Frame-to-model tracking against a TSDF volume (voxel 1 cm), with the settings of Open3D's own
``t_reconstruction_system`` example, on the frames of a bgs frame store (so both systems read the
same undistorted images).
"""

from __future__ import annotations

import multiprocessing
import time
from pathlib import Path

import numpy as np

from bgs_batch.store import FrameStore

# Open3D dense SLAM settings (its t_reconstruction_system defaults, voxel 1 cm)
O3D_VOXEL = 0.01
O3D_BLOCK_RESOLUTION = 16
O3D_BLOCK_COUNT = 40_000
O3D_DEPTH_MAX = 3.0
O3D_DEPTH_MIN = 0.1
O3D_DEPTH_DIFF = 0.07
O3D_TRUNC_MULTIPLIER = 8.0


def open3d_dense_slam(store_path: Path, frames: int) -> tuple[np.ndarray, float, float]:
    """Camera-to-world poses (frames, 4, 4), wall seconds and CPU seconds (all threads) of
    Open3D's frame-to-model TSDF SLAM over the first `frames` frames of a store. It runs in a
    child process: its TSDF volume (GBs) and thread pools stay out of the bgs runs' process,
    whose speed and peak RSS the benches report."""
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        return pool.apply(_open3d_dense_slam, (store_path, frames))


def _open3d_dense_slam(store_path: Path, frames: int) -> tuple[np.ndarray, float, float]:
    import open3d as o3d  # in the child only
    import open3d.core as o3c

    device = o3c.Device("CPU:0")
    with FrameStore(store_path) as store:
        intrinsics = o3c.Tensor(store.intrinsics, o3c.float64)
        pose = o3c.Tensor(np.eye(4), o3c.float64)
        model = o3d.t.pipelines.slam.Model(O3D_VOXEL, O3D_BLOCK_RESOLUTION, O3D_BLOCK_COUNT,
                                           pose, device)  # fmt: skip
        current = o3d.t.pipelines.slam.Frame(store.height, store.width, intrinsics, device)
        raycast = o3d.t.pipelines.slam.Frame(store.height, store.width, intrinsics, device)
        scale = store.depth_scale
        poses = []
        start, start_cpu = time.perf_counter(), time.process_time()
        for i in range(frames):
            current.set_data_from_image("depth", o3d.t.geometry.Image(store.read_depth_raw(i)))
            current.set_data_from_image("color", o3d.t.geometry.Image(store.read_rgb(i)))
            if i > 0:
                result = model.track_frame_to_model(current, raycast, scale, O3D_DEPTH_MAX,
                                                    O3D_DEPTH_DIFF)  # fmt: skip
                pose = pose @ result.transformation
            poses.append(pose.cpu().numpy())
            model.update_frame_pose(i, pose)
            model.integrate(current, scale, O3D_DEPTH_MAX, O3D_TRUNC_MULTIPLIER)
            model.synthesize_model_frame(raycast, scale, O3D_DEPTH_MIN, O3D_DEPTH_MAX,
                                         O3D_TRUNC_MULTIPLIER, False)  # fmt: skip
        return np.stack(poses), time.perf_counter() - start, time.process_time() - start_cpu
