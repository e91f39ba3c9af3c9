"""A rolling-shutter frame moved to one instant (`bgs_batch.slam.rolling_shutter`)."""

import dataclasses

import numpy as np
from conftest import rigid_pose

from bgs_batch.config import Config, separate_readouts
from bgs_batch.slam.depth_timing import interval_motion
from bgs_batch.slam.frames import prepare_frame
from bgs_batch.slam.rolling_shutter import (
    SURFACE_SPREAD,
    _Sources,
    rectify,
    rectify_colour,
    rectify_depth,
    row_motions,
)
from bgs_batch.store import Frame
from converters.synthetic import RoomRenderer, SynthConfig, camera_path


def test_row_motions_span_the_readout_about_its_middle():
    motion = rigid_pose([1.0, -2.0, 0.5], [0.01, 0.0, -0.02])
    rotations, shifts = row_motions(motion, 5)
    middle, first, last = 2, 0, 4
    assert np.allclose(rotations[middle], np.eye(3)) and np.allclose(shifts[middle], 0)
    # the last row is half the readout's motion ahead, the first half of it behind
    half = interval_motion(np.eye(4), motion, 0.5)
    assert np.allclose(rotations[last], half[:3, :3]) and np.allclose(shifts[last], half[:3, 3])
    assert np.allclose(rotations[first], half[:3, :3].T)
    assert np.allclose(shifts[first], -half[:3, 3])


def test_no_motion_leaves_the_frame_as_it_is():
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 3.0, (24, 32)).astype(np.float32)
    depth[3:6, 4:9] = 0  # holes stay holes
    k = np.array([[40.0, 0, 15.5], [0, 40.0, 11.5], [0, 0, 1]])
    out_rgb, out_depth = rectify(rgb, depth, k, np.eye(4))
    assert np.array_equal(out_rgb, rgb)
    assert np.allclose(out_depth, depth, atol=1e-6) and np.array_equal(out_depth == 0, depth == 0)


def rolling_and_global():
    """A room rendered row by row while the camera turns 2.4° and moves 1 cm over the readout,
    and at the readout's middle by one pose: (readout motion, K, rolling (colour, z, valid),
    global (colour, z, valid))."""
    config = SynthConfig(width=160, height=120, frames=10, seed=3)
    renderer = RoomRenderer(config)
    middle = camera_path(config)(np.array([4.0]))[0]
    readout = rigid_pose([1.2, -2.0, 0.6], [0.008, -0.002, 0.005])
    rotations, shifts = row_motions(readout, config.height)
    rows = np.tile(np.eye(4), (config.height, 1, 1))
    rows[:, :3, :3], rows[:, :3, 3] = rotations, shifts
    rows = (middle @ rows)[:, None]  # (H, 1, 4, 4): one camera-to-world pose per row
    fx, fy, cx, cy = config.intrinsics
    k = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    return readout, k, renderer._shade(rows), renderer._shade(middle)


def test_a_rolling_shutter_render_rectified_matches_the_global_shutter_render():
    """Float64 oracle: the room rendered row by row while the camera turns 2.4° and moves 1 cm
    over the readout, rectified with that motion, equals the room rendered at the readout's
    middle by one pose, in depth and in colour, far better than the raw rows do."""
    readout, k, (colour_rs, z_rs, valid_rs), (colour_gs, z_gs, valid_gs) = rolling_and_global()
    rgb_rs = np.clip(np.rint(colour_rs), 0, 255).astype(np.uint8)
    rgb_gs = np.clip(np.rint(colour_gs), 0, 255).astype(np.float64)
    rgb, depth = rectify(rgb_rs, np.where(valid_rs, z_rs, 0).astype(np.float32), k, readout)

    both = (depth > 0) & valid_gs
    assert both.sum() > 0.9 * valid_gs.sum()
    error = np.abs(depth[both] - z_gs[both])
    raw = np.abs(z_rs - z_gs)[valid_rs & valid_gs]
    assert np.median(error) < 1e-3 and np.median(raw) > 10 * np.median(error)
    assert np.mean(error < 0.02) > 0.99  # the rest: pixels at depth edges
    inner = np.zeros_like(both)
    inner[8:-8, 8:-8] = True  # away from the borders the rows moved past
    colour_error = np.abs(rgb.astype(np.float64) - rgb_gs)[inner].mean()
    colour_raw = np.abs(rgb_rs.astype(np.float64) - rgb_gs)[inner].mean()
    assert colour_error < 0.35 * colour_raw


def test_the_two_images_apart_equal_them_together_bit_for_bit():
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 3.0, (24, 32)).astype(np.float32)
    k = np.array([[40.0, 0, 15.5], [0, 40.0, 11.5], [0, 0, 1]])
    motion = rigid_pose([1.5, -1.0, 0.4], [0.01, 0.0, 0.004])
    together = rectify(rgb, depth, k, motion)
    assert np.array_equal(rectify_colour(rgb, depth, k, motion), together[0])
    assert np.array_equal(rectify_depth(depth, k, motion), together[1])


def test_a_rolling_colour_beside_a_global_depth_is_rectified_colour_only():
    """A RealSense D435-like camera (`bgs synth --rolling-shutter --global-shutter-depth`): with
    the depth readout 0, `prepare_frame` moves the colour rows alone; the depth image, taken at
    once, stays as measured, and the colour comes close to the global-shutter render."""
    readout, k, (colour_rs, _, _), (colour_gs, z_gs, valid_gs) = rolling_and_global()
    frame = Frame(0, np.clip(np.rint(colour_rs), 0, 255).astype(np.uint8),
                  np.where(valid_gs, z_gs, 0).astype(np.float32), 0.0, None)
    cfg = dataclasses.replace(Config(), rolling_shutter_readout=0.03,
                              depth_rolling_shutter_readout=0.0)  # fmt: skip
    assert separate_readouts(cfg)
    full, _ = prepare_frame(frame, k, cfg, None, readout, None)
    assert np.array_equal(full.depth[..., 0].numpy(), frame.depth)
    inner = np.zeros(frame.depth.shape, bool)
    inner[8:-8, 8:-8] = True
    rgb = (full.rgb.numpy() * 255).astype(np.float64)
    colour_error = np.abs(rgb - colour_gs)[inner].mean()
    colour_raw = np.abs(frame.rgb.astype(np.float64) - colour_gs)[inner].mean()
    assert colour_error < 0.35 * colour_raw
    alike = dataclasses.replace(cfg, depth_rolling_shutter_readout=0.03)
    shared, _ = prepare_frame(frame, k, alike, None, readout, None)
    assert not np.array_equal(shared.depth[..., 0].numpy(), frame.depth)  # both moved: wrong here


def _numpy_source_maps(depth, k, motion):
    """The rectification's source positions and moved depth, written with whole-image NumPy
    arrays (the implementation before the kernels): the kernels must give the same bits."""
    height, width = depth.shape
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    rotations, shifts = row_motions(motion, height)
    v, u = np.mgrid[:height, :width].astype(np.float64)
    ray_x, ray_y = (u - cx) / fx, (v - cy) / fy

    def image_motion(z):
        x, y = ray_x * z, ray_y * z
        moved = [x * rotations[:, i, 0:1] + y * rotations[:, i, 1:2] + z * rotations[:, i, 2:3]
                 + shifts[:, i : i + 1] for i in range(3)]  # fmt: skip
        return fx * moved[0] / moved[2] + cx - u, fy * moved[1] / moved[2] + cy - v

    valid = depth > 0
    z_guess = np.where(valid, depth, np.median(depth[valid]))
    du, dv = image_motion(z_guess)
    near_u = np.clip(np.rint(u - du), 0, width - 1).astype(np.intp)
    near_v = np.clip(np.rint(v - dv), 0, height - 1).astype(np.intp)
    du, dv = image_motion(z_guess[near_v, near_u])
    map_u, map_v = u - du, v - dv
    inside = (map_u > -0.5) & (map_u < width - 0.5) & (map_v > -0.5) & (map_v < height - 0.5)
    u0 = np.clip(np.floor(map_u), 0, width - 2).astype(np.intp)
    v0 = np.clip(np.floor(map_v), 0, height - 2).astype(np.intp)
    fu, fv = np.clip(map_u - u0, 0, 1), np.clip(map_v - v0, 0, 1)
    corners = np.stack([depth[v0, u0], depth[v0, u0 + 1], depth[v0 + 1, u0],
                        depth[v0 + 1, u0 + 1]]).astype(np.float64)  # fmt: skip
    weights = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv])
    low, high = corners.min(0), corners.max(0)
    smooth = (low > 0) & (high - low <= SURFACE_SPREAD * low)
    nearest = depth[np.clip(np.rint(map_v), 0, height - 1).astype(np.intp),
                    np.clip(np.rint(map_u), 0, width - 1).astype(np.intp)]  # fmt: skip
    z_src = np.where(inside, np.where(smooth, (weights * corners).sum(0), nearest), 0.0)
    src_row = np.clip(np.rint(map_v), 0, height - 1).astype(np.intp)
    third = rotations[src_row, 2]
    z_new = (((map_u - cx) / fx * z_src) * third[..., 0] + ((map_v - cy) / fy * z_src)
             * third[..., 1] + z_src * third[..., 2]) + shifts[src_row, 2]  # fmt: skip
    return map_u, map_v, np.where((z_src > 0) & (z_new > 0), z_new, 0.0).astype(np.float32)


def test_the_kernels_give_the_numpy_rectification_bit_for_bit():
    """Depth with steps (surfaces apart), holes and readings at the border, under a turn and a
    shift large enough to move rows past the image's edges."""
    rng = np.random.default_rng(7)
    depth = np.repeat(rng.uniform(0.4, 4.0, (6, 8)), 8, 0).repeat(8, 1).astype(np.float32)
    depth += rng.normal(0, 0.01, depth.shape).astype(np.float32)
    depth[rng.random(depth.shape) < 0.1] = 0
    k = np.array([[55.0, 0, 31.7], [0, 54.0, 23.2], [0, 0, 1]])
    for rotation_deg, shift in (([2.0, -3.0, 1.0], [0.02, -0.01, 0.03]),
                                ([-0.3, 0.1, 4.0], [0.0, 0.0, -0.05])):  # fmt: skip
        motion = rigid_pose(rotation_deg, shift)
        map_u, map_v, moved = _numpy_source_maps(depth, k, motion)
        sources = _Sources(depth, k, motion)
        assert np.array_equal(sources.map_u, map_u) and np.array_equal(sources.map_v, map_v)
        assert np.array_equal(sources.depth(depth), moved)
        assert 0.5 < np.mean(moved > 0) < 0.95  # holes, and rows moved out of the image
