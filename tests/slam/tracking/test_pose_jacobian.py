"""The image-motion Jacobians of a render against finite differences of the renderer."""

import pytest
import torch

from bgs_batch.config import load_config
from bgs_batch.render import render, se3_exp
from bgs_batch.slam import Slam
from bgs_batch.slam.tracking.pose_jacobian import (
    ALPHA_MIN,
    image_motion_jacobians,
    image_motion_normal_matrix,
    irls_weights,
    l1_normal_matrix,
)
from bgs_batch.store import FrameStore
from converters.synthetic import SynthConfig, synthesize
from converters.tum import convert_tum


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """The map of frame 0 of a synthetic room, its camera and frame 0's pose."""
    root = tmp_path_factory.mktemp("jacobian")
    folder = synthesize(root / "seq", SynthConfig(frames=2, width=160, height=120, seed=3))
    store = FrameStore(convert_tum(folder, root / "seq.h5"))
    slam = Slam(load_config("cpu", ["mapping.downscale=1"]), store.intrinsics, root / "submaps")
    slam.process(store[0])
    # the map's world frame is the first camera's
    camera = slam.prepare(store[0])[0].camera
    return slam.gmap.gaussians(), camera, torch.eye(4, dtype=torch.float64)


@pytest.mark.parametrize("axis", range(6))
def test_each_twist_axis_predicts_the_rendered_change(scene, axis):
    gaussians, camera, w2c = scene
    size = 2e-3  # m or rad: a fraction of a pixel at the room's depth
    twist = torch.zeros(6, dtype=torch.float64)
    twist[axis] = size
    with torch.no_grad():
        base = render(gaussians, w2c.float(), camera)
        moved = render(gaussians, (se3_exp(twist) @ w2c).float(), camera)
        back = render(gaussians, (se3_exp(-twist) @ w2c).float(), camera)
    j_color, j_depth, surface = image_motion_jacobians(base, camera)
    inner = surface.clone()
    inner[:3], inner[-3:], inner[:, :3], inner[:, -3:] = False, False, False, False
    inner &= base.alpha[..., 0] > 0.99
    for image, jacobian in ((lambda o: o.color, j_color[..., axis]),
                            (lambda o: o.depth[..., 0], j_depth[..., axis])):  # fmt: skip
        measured = ((image(moved) - image(back)) / (2 * size)).double()[inner]
        predicted = jacobian[inner]
        # the first-order model explains most of the change, not all (occluding edges: a
        # sideways shift changes depth only there; measured 0.88-0.99)
        cosine = torch.nn.functional.cosine_similarity(measured.flatten(), predicted.flatten(), 0)
        assert cosine > 0.85, (axis, float(cosine))
        ratio = float(predicted.norm() / measured.norm())
        assert 0.7 < ratio < 1.4, (axis, ratio)


def test_the_l1_normal_matrix_is_the_reweighted_sum_with_a_median_floor():
    generator = torch.Generator().manual_seed(0)
    jacobian = torch.randn(50, 1, 6, generator=generator, dtype=torch.float64)
    residual = torch.randn(50, 1, generator=generator, dtype=torch.float64)
    weight = torch.rand(50, 1, generator=generator, dtype=torch.float64)
    weight[:10] = 0  # not in the loss
    floor = residual[10:].abs().median()
    irls = weight / residual.abs().clamp_min(floor)
    expected = sum(irls[k, 0] * torch.outer(jacobian[k, 0], jacobian[k, 0]) for k in range(50))
    assert torch.allclose(l1_normal_matrix(residual, weight, jacobian), expected)
    assert not l1_normal_matrix(residual, torch.zeros_like(weight), jacobian).any()


def test_the_fused_normal_matrix_equals_the_spelled_out_one(scene):
    gaussians, camera, w2c = scene
    with torch.no_grad():
        out = render(gaussians, (se3_exp(torch.tensor([0.01, 0, 0, 0, 0.02, 0],
                                                       dtype=torch.float64)) @ w2c).float(), camera)
        target = render(gaussians, w2c.float(), camera)
    generator = torch.Generator().manual_seed(1)
    surface = out.alpha.to(torch.float64) >= ALPHA_MIN
    weight_c = torch.rand(out.color.shape, generator=generator, dtype=torch.float64) * surface
    weight_d = torch.rand(out.depth.shape, generator=generator, dtype=torch.float64) * surface
    weight_d[:40] = 0  # pixels out of the loss
    irls_c = irls_weights(out.color - target.color, weight_c)
    irls_d = irls_weights(out.depth - target.depth, weight_d)
    j_color, j_depth, _ = image_motion_jacobians(out, camera)
    expected = (l1_normal_matrix(out.color - target.color, weight_c, j_color)
                + l1_normal_matrix(out.depth - target.depth, weight_d, j_depth[..., None, :]))
    fused = image_motion_normal_matrix(out, camera, irls_c, irls_d)
    assert torch.allclose(fused, expected, rtol=1e-10, atol=0), (fused - expected).abs().max()
    assert torch.equal(fused, fused.T)
    colour_only = image_motion_normal_matrix(out, camera, irls_c, torch.zeros_like(irls_d))
    assert torch.allclose(colour_only, l1_normal_matrix(out.color - target.color, weight_c,
                                                        j_color), rtol=1e-10, atol=0)
