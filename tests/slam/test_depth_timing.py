"""Moving a depth image to its colour image's time (`bgs_batch.slam.depth_timing`)."""

import numpy as np
import pytest
from conftest import rigid_pose

from bgs_batch.slam.depth_timing import depth_motion, interval_motion, warp_depth
from converters.synthetic import RoomRenderer, SynthConfig, camera_path

K = np.array([[100.0, 0.0, 31.5], [0.0, 100.0, 23.5], [0.0, 0.0, 1.0]])


def test_interval_motion_scales_the_turn_and_the_shift_of_the_interval():
    before = rigid_pose([1.0, -2.0, 0.5], [0.3, 0.1, -0.2])
    motion = rigid_pose([0.0, 3.0, 0.0], [0.02, 0.0, -0.01])
    after = before @ motion
    np.testing.assert_allclose(interval_motion(before, after, 1.0), motion, atol=1e-12)
    np.testing.assert_allclose(interval_motion(before, after, 0.0), np.eye(4), atol=1e-12)
    back = interval_motion(before, after, -0.5)
    np.testing.assert_allclose(back, rigid_pose([0.0, -1.5, 0.0], [-0.01, 0.0, 0.005]), atol=1e-12)


def test_depth_motion_is_none_when_there_is_nothing_to_move():
    a, b = np.eye(4), rigid_pose([0, 1, 0], [0.01, 0, 0])
    assert depth_motion(a, b, 1 / 30, 0.0) is None
    assert depth_motion(a, b, 0.0, 0.01) is None
    half = depth_motion(a, b, 1 / 30, 1 / 60)
    np.testing.assert_allclose(half, rigid_pose([0, 0.5, 0], [0.005, 0, 0]), atol=1e-12)


def test_identity_warp_returns_the_image_and_keeps_holes():
    depth = np.random.default_rng(0).uniform(1, 2, (48, 64)).astype(np.float32)
    depth[10:20, 5:9] = 0
    np.testing.assert_array_equal(warp_depth(depth, K, np.eye(4)), depth)


def test_a_sideways_shift_moves_a_step_edge_by_the_closed_form_pixels():
    depth = np.full((48, 64), 2.0, np.float32)
    depth[:, 40:] = 1.0  # a nearer box on the right
    shift = 3 * 2.0 / K[0, 0]  # 3 px at 2 m, 6 px at 1 m
    warped = warp_depth(depth, K, rigid_pose([0, 0, 0], [shift, 0, 0]))
    assert np.all(warped[:, 3:43] == 2.0) and np.all(warped[:, 46:] == 1.0)
    assert np.all(warped[:, :3] == 0) and np.all(warped[:, 43:46] == 0)  # nothing seen there


def test_the_nearer_surface_wins_where_two_land_on_one_pixel():
    depth = np.full((48, 64), 2.0, np.float32)
    depth[:, 30:34] = 1.0
    shift = 4 * 1.0 / K[0, 0]  # the near strip moves 4 px, the far wall 2 px
    warped = warp_depth(depth, K, rigid_pose([0, 0, 0], [shift, 0, 0]))
    assert np.all(warped[:, 34:38] == 1.0)  # the strip covers the wall it moved over
    assert np.all(warped[:, 32:34] == 0)  # and uncovers wall nobody saw


def test_a_warped_render_matches_the_render_at_the_otherrigid_pose():
    """Float64 oracle: the room seen from pose A, moved by 1.2° and 1 cm, equals the room
    rendered from pose B wherever both see a surface (up to rounding to the nearest pixel)."""
    config = SynthConfig(width=160, height=120, frames=10, seed=3)
    renderer = RoomRenderer(config)
    c2w_a = camera_path(config)(np.array([4.0]))[0]
    c2w_b = c2w_a @ rigid_pose([0.4, -1.0, 0.5], [0.01, -0.004, 0.006])
    _, z_a, valid_a = renderer._shade(c2w_a)
    _, z_b, valid_b = renderer._shade(c2w_b)
    depth_a = np.where(valid_a, z_a, 0).astype(np.float32)
    fx, fy, cx, cy = config.intrinsics
    k = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    warped = warp_depth(depth_a, k, np.linalg.inv(c2w_b) @ c2w_a)
    both = (warped > 0) & valid_b
    assert both.sum() > 0.9 * valid_b.sum()
    error = np.abs(warped[both] - z_b[both])
    assert np.median(error) < 2e-3
    assert np.mean(error < 0.02) > 0.97  # the rest: pixels at depth edges
    # without the warp, the two images disagree far more
    unwarped = np.abs(depth_a - z_b)[valid_a & valid_b]
    assert np.median(unwarped) > 5 * np.median(error)


@pytest.mark.parametrize("offset", [0.004, -0.015])
def test_depth_motion_moves_the_depth_image_to_the_colour_time(offset):
    """On a camera moving at constant velocity, the depth taken `offset` s off the colour
    image and moved by `depth_motion` matches the depth at the colour image's time."""
    config = SynthConfig(width=160, height=120, frames=10, seed=3)
    renderer = RoomRenderer(config)
    step = rigid_pose([0.6, 1.8, -0.3], [0.004, 0.0, 0.006])  # per frame interval, 30 fps
    c2w = [camera_path(config)(np.array([4.0]))[0]]
    c2w += [c2w[0] @ step, c2w[0] @ step @ step]
    c2w_depth = c2w[2] @ interval_motion(np.eye(4), step, offset * 30)
    _, z_colour, valid_colour = renderer._shade(c2w[2])
    _, z_depth, valid_depth = renderer._shade(c2w_depth)
    fx, fy, cx, cy = config.intrinsics
    k = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    motion = depth_motion(c2w[0], c2w[1], 1 / 30, offset)
    warped = warp_depth(np.where(valid_depth, z_depth, 0).astype(np.float32), k, motion)
    both = (warped > 0) & valid_colour
    assert np.median(np.abs(warped[both] - z_colour[both])) < 2e-3
