"""Seeding, Gaussian-map bookkeeping, image pyramids, submap switching and ATE."""

import dataclasses

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from bgs_batch.config import MappingConfig, SeedingConfig, SubmapConfig, load_config
from bgs_batch.geometry import pose_matrix
from bgs_batch.metrics import align_rigid, ate
from bgs_batch.render import Camera, project, rasterize, render
from bgs_batch.render.reference import quat_wxyz_to_matrix
from bgs_batch.slam.frames import Level, block_mean, downsample, repeat_blocks
from bgs_batch.slam.gaussian_map import GaussianMap
from bgs_batch.slam.mapping import Keyframe, Mapper
from bgs_batch.slam.seeding import (
    backproject,
    far_from,
    keyframe_seed_pixels,
    submap_seed_pixels,
    surface_normals,
)
from bgs_batch.slam.submaps import exceeds_motion

K = np.array([[50.0, 0, 15.5], [0, 50.0, 11.5], [0, 0, 1]])


def unit(q):
    return np.asarray(q) / np.linalg.norm(q)


def test_backproject_inverts_projection():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 3, (24, 32)).astype(np.float32)
    c2w = pose_matrix([0.3, -0.2, 1.0], unit([0.1, 0.2, 0.3, 0.927]))
    pixels = np.array([0, 17, 24 * 32 - 1, 400])
    points = backproject(depth, pixels, K, c2w, 1.0)
    cam = (points - c2w[:3, 3]) @ c2w[:3, :3]
    uv = cam[:, :2] / cam[:, 2:] * [50, 50] + [15.5, 11.5]
    assert np.allclose(uv, np.stack([pixels % 32, pixels // 32], 1))
    assert np.allclose(cam[:, 2], depth.ravel()[pixels])
    pushed = backproject(depth, pixels, K, c2w, 1.005)
    assert np.allclose(np.linalg.norm(pushed - c2w[:3, 3], axis=1),
                       1.005 * np.linalg.norm(points - c2w[:3, 3], axis=1))  # fmt: skip


def test_surface_normals_of_a_slanted_plane():
    """The depth image of the plane n·X = 2 (camera frame) gives n at every pixel whose four
    neighbours have depth, turned into the world frame; NaN at the border and beside a hole."""
    normal = unit([0.3, -0.2, -1.0])
    v, u = np.mgrid[0:24, 0:32]
    rays = np.stack([(u - 15.5) / 50, (v - 11.5) / 50, np.ones_like(u, float)], -1)
    depth = (-2.0 / (rays @ normal)).astype(np.float32)  # n·(z·ray) = −2: the plane in front
    depth[10, 10] = 0.0
    c2w = pose_matrix([0.3, -0.2, 1.0], unit([0.1, 0.2, 0.3, 0.927]))
    pixels = np.array([5 * 32 + 5, 11 * 32 + 20, 10 * 32 + 11, 0, 23 * 32 + 7])
    got = surface_normals(depth, pixels, K, c2w)
    expected = c2w[:3, :3] @ normal
    for n in got[:2]:
        assert abs(abs(n @ expected) - 1) < 1e-4  # a plane's normal, either side
    assert np.isnan(got[2:]).all()  # beside the hole, on the border


def test_gaussian_map_adds_discs_across_the_given_normals():
    rng = np.random.default_rng(1)
    normals = rng.normal(size=(6, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[2] = [0.0, 0.0, -1.0]  # the rotation's antipode: flipped, a disc has no side
    normals[5] = np.nan  # no normal: a ball, as without normals
    gmap = GaussianMap()
    gmap.add(rng.normal(size=(6, 3)), np.full((6, 3), 0.5), 0.5, -7.0, normals, 0.1)
    rot = quat_wxyz_to_matrix(gmap.params["quats"].detach().double()).numpy()
    scales = gmap.params["log_scales"].detach().exp().numpy()
    for i in range(5):
        assert abs(abs(rot[i, :, 2] @ normals[i]) - 1) < 1e-6  # the thin axis along the normal
        assert scales[i, 2] == pytest.approx(0.1 * scales[i, 0], rel=1e-5)
        assert scales[i, 0] == scales[i, 1]
    assert np.allclose(rot[5], np.eye(3)) and np.ptp(scales[5]) == 0


def test_discs_on_a_slanted_surface_render_its_depth():
    """Seeds on the surface, flat across its normal: each one's depth plane is the surface, so
    the blended depth is the measured one (docs/method.md §1). Blending the centres' depths
    instead weighs the nearer Gaussians of a slanted surface more: the map renders in front."""
    camera = Camera(fx=60.0, fy=60.0, cx=31.5, cy=23.5, width=64, height=48)
    x, y = np.meshgrid(np.arange(-1.6, 1.6, 0.02), np.arange(-1.2, 1.2, 0.02))
    points = np.stack([x, y, 2 + 0.6 * x], -1).reshape(-1, 3)  # z = 2 + 0.6 x, 31° of slant
    normals = np.tile(unit([-0.6, 0.0, 1.0, 0.0])[:3], (len(points), 1))
    gmap = GaussianMap()
    gmap.add(points, np.full((len(points), 3), 0.5), 0.9, -7.0, normals, 0.1)
    g = gmap.gaussians()
    v, u = np.mgrid[0:48, 0:64]
    truth = torch.from_numpy(2 / (1 - 0.6 * (u - 31.5) / 60))  # where each pixel's ray meets it
    with torch.no_grad():
        out = render(g, torch.eye(4), camera)
        proj = project(g.means, g.log_scales, g.quats, g.opacity_logits, torch.eye(4), camera)
        centres = rasterize(proj.means2d, proj.conics, proj.depths,
                            torch.sigmoid(g.opacity_logits[proj.ids]), g.colors[proj.ids],
                            F.softplus(g.uncertainty_logits[proj.ids]), 64, 48)  # fmt: skip
    assert (out.alpha > 0.99).all()
    error = out.normalized_depth()[..., 0] / truth - 1
    assert error.abs().median() < 5e-4 and error.abs().max() < 3e-3
    biased = centres.normalized_depth()[..., 0] / truth - 1
    assert biased.median() < -5e-3


def test_submap_seeding_covers_edges_and_skips_invalid_depth():
    rgb = np.zeros((40, 40, 3), np.uint8)
    rgb[:, 20:] = 255  # one vertical edge
    depth = np.ones((40, 40), np.float32)
    depth[:5] = 0
    cfg = SeedingConfig(new_submap_points=50, new_submap_gradient_points=30)
    pixels = submap_seed_pixels(rgb, depth, cfg, np.random.default_rng(0))
    assert len(np.unique(pixels)) == len(pixels)
    assert np.all(depth.ravel()[pixels] > 0)
    cols = pixels % 40
    edge_rows = pixels[(cols == 19) | (cols == 20)] // 40
    assert set(range(5, 39)) <= set(edge_rows.tolist())  # every valid row's edge pixel
    again = submap_seed_pixels(rgb, depth, cfg, np.random.default_rng(0))
    assert np.array_equal(pixels, again)


def test_keyframe_seeding_where_thin_or_in_front():
    depth = np.full((10, 10), 2.0, np.float32)
    alpha = np.ones((10, 10))
    rendered = np.full((10, 10), 2.0) + np.random.default_rng(1).normal(0, 0.01, (10, 10))
    alpha[0, 0] = 0.3  # thin map
    rendered[5, 5] = 3.0  # map surface far behind... rendered > measured: something in front
    depth[9, 9] = 0  # invalid: never seeded
    alpha[9, 9] = 0.0
    pixels = keyframe_seed_pixels(alpha, rendered, depth, SeedingConfig(), np.random.default_rng(0))
    assert pixels.tolist() == [0, 55]
    capped = keyframe_seed_pixels(np.zeros((10, 10)), rendered, np.ones((10, 10)),
                                  SeedingConfig(new_frame_points=7), np.random.default_rng(0))
    assert len(capped) == 7


def test_far_from_uses_the_radius():
    existing = np.zeros((1, 3))
    candidates = np.array([[0.005, 0, 0], [0.02, 0, 0], [0, 0, -0.0099]])
    assert far_from(existing, candidates, 0.01).tolist() == [False, True, False]
    assert far_from(np.empty((0, 3)), candidates, 0.01).all()


def test_gaussian_map_add_keep_and_optimizer_state():
    gmap = GaussianMap()
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.0]])
    assert gmap.add(pts, np.full((5, 3), 0.5), 0.5, -7.0) == 5
    scales = torch.exp(gmap.params["log_scales"][:, 0]).detach().numpy()
    assert scales[0] == pytest.approx(1.0)  # 3 nearest at distance 1
    assert torch.allclose(torch.sigmoid(gmap.params["opacity_logits"]), torch.tensor(0.5))
    assert torch.allclose(torch.nn.functional.softplus(gmap.params["uncertainty_logits"]),
                          torch.tensor(9.1147e-4), rtol=1e-3)  # fmt: skip
    opt = gmap.optimizer(MappingConfig())
    out = sum(p.sum() for p in gmap.params.values())
    out.backward()
    opt.step()
    before = opt.state[gmap.params["means"]]["exp_avg"].clone()
    removed = gmap.keep(torch.tensor([True, False, True, True, False]), opt)
    assert removed == 2 and len(gmap) == 3
    state = opt.state[gmap.params["means"]]
    assert torch.equal(state["exp_avg"], before[[0, 2, 3]])
    assert opt.param_groups[0]["params"][0] is gmap.params["means"]
    restored = GaussianMap.from_state_dict(gmap.state_dict())
    assert all(torch.equal(restored.params[n], gmap.params[n]) for n in gmap.params)


def test_downsample_blocks_and_camera():
    rgb = torch.arange(4 * 6 * 3, dtype=torch.float32).reshape(4, 6, 3)
    depth = torch.ones(4, 6, 1)
    depth[0, 0] = 0  # an invalid reading does not pull the block's depth down
    depth[1, 1] = 3.0
    level = Level(rgb, depth, Camera(10, 10, 2.5, 1.5, 6, 4))
    half = downsample(level, 2)
    assert half.rgb.shape == (2, 3, 3) and torch.equal(half.rgb, block_mean(rgb, 2))
    assert half.depth[0, 0, 0] == pytest.approx((1 + 1 + 3) / 3)
    assert (half.camera.width, half.camera.height, half.camera.fx) == (3, 2, 5)
    assert half.camera.cx == pytest.approx(1.0)  # (2.5 + 0.5) / 2 - 0.5


@pytest.mark.parametrize("factor", [2, 3])
def test_block_mean_averages_blocks_and_drops_the_remainder(factor):
    image = torch.rand(7, 11, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    pooled = F.avg_pool2d(image.permute(2, 0, 1)[None], factor)[0].permute(1, 2, 0)
    assert torch.allclose(block_mean(image, factor), pooled, rtol=0, atol=1e-15)


def test_repeat_blocks_pads_to_the_full_size():
    coarse = torch.arange(6.0).reshape(2, 3, 1)
    fine = repeat_blocks(coarse, 2, 5, 7)
    assert fine.shape == (5, 7, 1)
    assert fine[0, 0, 0] == fine[1, 1, 0] == 0 and fine[4, 6, 0] == 5  # edge rows repeated


def test_repeat_blocks_cuts_to_the_full_size_and_undoes_block_mean():
    coarse = torch.arange(6.0).reshape(2, 3, 1)
    fine = repeat_blocks(coarse, 2, 3, 5)  # smaller than 4×6: cut
    assert fine.shape == (3, 5, 1) and fine[2, 4, 0] == 5
    assert torch.equal(block_mean(repeat_blocks(coarse, 2, 4, 6), 2), coarse)


def test_submap_motion_thresholds():
    cfg = SubmapConfig()
    eye = np.eye(4)
    assert not exceeds_motion(eye, pose_matrix([0.4, 0, 0], [0, 0, 0, 1.0]), cfg)
    assert exceeds_motion(eye, pose_matrix([0.4, 0.4, 0], [0, 0, 0, 1.0]), cfg)
    q49, q51 = (np.array([0, np.sin(np.radians(a) / 2), 0, np.cos(np.radians(a) / 2)])
                for a in (49, 51))  # fmt: skip
    assert not exceeds_motion(eye, pose_matrix([0, 0, 0], q49), cfg)
    assert exceeds_motion(eye, pose_matrix([0, 0, 0], q51), cfg)
    # 55° about (1, 1, 0)/√2: roll, pitch, yaw are all below 50° (LoopSplat keeps the submap),
    # the rotation angle is not
    axis = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    diagonal = pose_matrix([0, 0, 0], np.append(axis * np.sin(np.radians(27.5)),
                                                np.cos(np.radians(27.5))))  # fmt: skip
    assert cfg.rotation_measure == "angle" and exceeds_motion(eye, diagonal, cfg)
    assert not exceeds_motion(eye, diagonal, SubmapConfig(rotation_measure="euler"))
    # relative to the submap's first frame, not to the world
    first = pose_matrix([1, 2, 3], q49)
    assert not exceeds_motion(first, first @ pose_matrix([0.1, 0, 0], q49), cfg)


def test_ate_closed_forms():
    rng = np.random.default_rng(0)
    gt = rng.normal(size=(50, 3))
    rot = pose_matrix([0, 0, 0], unit([0.2, -0.4, 0.1, 0.89]))[:3, :3]
    moved = gt @ rot.T + [1, 2, 3]
    assert ate(moved, gt)["rmse"] == pytest.approx(0, abs=1e-12)  # rigid motion: aligned away
    noise = rng.normal(size=(50, 3))
    noise -= noise.mean(0)
    stats = ate(gt + 0.01 * noise, gt)
    assert stats["rmse"] <= 0.01 * np.sqrt((noise**2).sum(1).mean()) + 1e-12
    r, t, s = align_rigid(2 * moved, gt, with_scale=True)
    assert s == pytest.approx(0.5) and np.allclose(s * (2 * moved) @ r.T + t, gt)
    gt_nan = gt.copy()
    gt_nan[3] = np.nan
    assert ate(moved, gt_nan)["frames"] == 49


@pytest.mark.parametrize(("preset", "readouts", "push", "flatness"), [
    ("cpu", (0.0, 0.0), 1.0, 0.1),  # discs on the surface, whatever the shutters
    ("cpu", (0.03, 0.03), 1.0, 0.1),
    ("paper", (0.0, 0.0), 1.005, 1.0),  # LoopSplat's: balls 0.5 % behind it
])  # fmt: skip
def test_seeds_sit_at_the_presets_push_and_shape(preset, readouts, push, flatness):
    cfg = dataclasses.replace(load_config(preset), rolling_shutter_readout=readouts[0],
                              depth_rolling_shutter_readout=readouts[1])  # fmt: skip
    height, width = 24, 32
    rgb = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(0))
    depth = torch.full((height, width, 1), 2.0)
    level = Level(rgb, depth, Camera(fx=50.0, fy=50.0, cx=15.5, cy=11.5, width=width,
                                     height=height))  # fmt: skip
    gmap = GaussianMap()
    added = Mapper(cfg, None, None).seed(gmap, Keyframe(0, level, np.eye(4)), True,
                                         np.random.default_rng(0))  # fmt: skip
    assert added > 0
    np.testing.assert_allclose(gmap.means.detach().numpy()[:, 2], 2.0 * push, rtol=1e-6)
    inner = np.isfinite(surface_normals(depth[..., 0].numpy(), np.arange(height * width), K,
                                        np.eye(4))).all(1)  # fmt: skip
    scales = gmap.params["log_scales"].detach().exp().numpy()
    rot = quat_wxyz_to_matrix(gmap.params["quats"].detach().double()).numpy()
    discs = scales[:, 2] < scales[:, 0]
    assert discs.sum() == (inner.sum() if flatness < 1 else 0)  # a wall facing the camera
    np.testing.assert_allclose(scales[discs, 2], flatness * scales[discs, 0], rtol=1e-5)
    np.testing.assert_allclose(np.abs(rot[discs, 2, 2]), 1.0, atol=1e-6)
