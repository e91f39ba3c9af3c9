"""Closed-form checks of the compositing rules and variances (docs/method.md §1-2, paper Eq. 3, 12,
13), of the projection and of the se(3) pose map, on both backends."""

import math

import pytest
import torch

from bgs_batch.render import Camera, project, rasterize, se3_exp
from bgs_batch.render.constants import ALPHA_MAX, LOWPASS

BACKENDS = ["numba", "torch"]
SIZE = 9
"""Side of the tiny test images (pixels)."""
CENTRE = 4.0
"""A pixel centre in the middle of the image."""


def _stack(opacities, colors, depths, variances, sigma_px=1.0):
    """Gaussians all centred on pixel (CENTRE, CENTRE), listed front to back."""
    n = len(opacities)
    t = torch.tensor
    conic = [1 / sigma_px**2, 0.0, 1 / sigma_px**2]
    return (
        t([[CENTRE, CENTRE]] * n, dtype=torch.float64),
        t([conic] * n, dtype=torch.float64),
        t(depths, dtype=torch.float64),
        t(opacities, dtype=torch.float64),
        t(colors, dtype=torch.float64),
        t(variances, dtype=torch.float64),
    )


def _at_centre(out):
    c = int(CENTRE)
    return [o[c, c] for o in out]


@pytest.mark.parametrize("backend", BACKENDS)
def test_two_gaussians_closed_form(backend):
    o1, o2, v1, v2 = 0.6, 0.5, 0.02, 0.07
    c1, c2, d1, d2 = [0.9, 0.2, 0.1], [0.1, 0.5, 1.0], 2.0, 3.0
    # Listed back to front: the renderer must sort by depth.
    inputs = _stack([o2, o1], [c2, c1], [d2, d1], [v2, v1])
    color, depth, alpha, var_color, var_depth = _at_centre(
        rasterize(*inputs, SIZE, SIZE, backend=backend)
    )
    c1, c2 = torch.tensor(c1, dtype=torch.float64), torch.tensor(c2, dtype=torch.float64)
    t2 = 1 - o1
    expected_c = c1 * o1 + c2 * o2 * t2
    expected_d = d1 * o1 + d2 * o2 * t2
    torch.testing.assert_close(color, expected_c, rtol=1e-12, atol=0)
    torch.testing.assert_close(depth.item(), expected_d, rtol=1e-12, atol=0)
    torch.testing.assert_close(alpha.item(), o1 + o2 * t2, rtol=1e-12, atol=0)
    # Eq. 3/12/13: Σ (f_i − F)² T_i² v_i, with the final F and v_i without a G_i factor.
    expected_vc = (c1 - expected_c) ** 2 * v1 + (c2 - expected_c) ** 2 * t2**2 * v2
    expected_vd = (d1 - expected_d) ** 2 * v1 + (d2 - expected_d) ** 2 * t2**2 * v2
    torch.testing.assert_close(var_color, expected_vc, rtol=1e-12, atol=0)
    torch.testing.assert_close(var_depth.item(), expected_vd, rtol=1e-12, atol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_off_centre_pixel_uses_gaussian_falloff(backend):
    inputs = _stack([0.8], [[1.0, 1.0, 1.0]], [2.0], [0.1], sigma_px=2.0)
    out = rasterize(*inputs, SIZE, SIZE, backend=backend)
    c = int(CENTRE)
    alpha = 0.8 * math.exp(-0.5 * (1 + 4) / 4)  # pixel offset (1, 2), σ = 2 px
    torch.testing.assert_close(out.alpha[c + 2, c + 1].item(), alpha, rtol=1e-12, atol=0)
    # A single Gaussian: V = (f − α f)² v.
    expected = (2.0 * (1 - alpha)) ** 2 * 0.1
    torch.testing.assert_close(out.var_depth[c + 2, c + 1].item(), expected, rtol=1e-12, atol=0)
    torch.testing.assert_close(out.normalized_depth()[c + 2, c + 1].item(), 2.0, rtol=1e-12, atol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_alpha_clamp_skip_and_termination(backend):
    # A nearly opaque Gaussian is clamped to α = 0.99.
    out = rasterize(*_stack([0.999], [[1.0, 0.0, 0.0]], [1.0], [0.1]), SIZE, SIZE, backend=backend)
    assert _at_centre(out)[2].item() == pytest.approx(ALPHA_MAX, rel=1e-12)
    # o < 1/255 can never reach the skip threshold: nothing is rendered.
    out = rasterize(*_stack([0.003], [[1.0, 0.0, 0.0]], [1.0], [0.1]), SIZE, SIZE, backend=backend)
    assert all((o == 0).all() for o in out)
    # α = 0.95: T = 0.05, 2.5e-3, 1.25e-4, then 6.25e-6 < 1e-4, so the 4th is not blended.
    colors = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [100.0, 100.0, 100.0]]
    inputs = _stack([0.95] * 4, colors, [1.0, 2.0, 3.0, 4.0], [0.1] * 4)
    color, depth, alpha, _, var_depth = _at_centre(rasterize(*inputs, SIZE, SIZE, backend=backend))
    weights = torch.tensor([0.95, 0.95 * 0.05, 0.95 * 0.05**2], dtype=torch.float64)
    torch.testing.assert_close(color, weights, rtol=1e-12, atol=0)
    torch.testing.assert_close(alpha.item(), 1 - 0.05**3, rtol=1e-12, atol=0)
    d = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    trans_sq = torch.tensor([1.0, 0.05**2, 0.05**4], dtype=torch.float64)
    expected_vd = ((d - depth) ** 2 * trans_sq * 0.1).sum()
    torch.testing.assert_close(var_depth.item(), expected_vd.item(), rtol=1e-12, atol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_projection_closed_form(backend):
    camera = Camera(fx=100.0, fy=90.0, cx=31.5, cy=23.5, width=64, height=48)
    scale, depth = 0.05, 2.0
    means = torch.tensor([[0.0, 0.0, depth], [0.4, -0.2, depth]], dtype=torch.float64)
    log_scales = torch.full((2, 3), math.log(scale), dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.3, -0.2, 0.5, 0.1]], dtype=torch.float64)
    logits = torch.zeros(2, dtype=torch.float64)
    proj = project(
        means, log_scales, quats, logits, torch.eye(4, dtype=torch.float64), camera,
        backend=backend,
    )  # fmt: skip
    assert proj.ids.tolist() == [0, 1]
    expected_uv = [[31.5, 23.5], [100 * 0.2 + 31.5, -90 * 0.1 + 23.5]]
    torch.testing.assert_close(proj.means2d, torch.tensor(expected_uv, dtype=torch.float64))
    torch.testing.assert_close(proj.depths, torch.tensor([depth, depth], dtype=torch.float64))
    # On the optical axis an isotropic Gaussian has σ² = (f·s/z)² + low-pass per axis.
    sx, sy = (100 * scale / depth) ** 2 + LOWPASS, (90 * scale / depth) ** 2 + LOWPASS
    expected = torch.tensor([1 / sx, 0.0, 1 / sy], dtype=torch.float64)
    torch.testing.assert_close(proj.conics[0], expected, rtol=1e-12, atol=1e-15)


def test_se3_exp_matches_matrix_exponential():
    gen = torch.Generator().manual_seed(0)
    for xi in [*torch.randn((4, 6), generator=gen, dtype=torch.float64), torch.zeros(6)]:
        xi = xi.double()
        twist = torch.zeros(4, 4, dtype=torch.float64)
        rho, phi = xi[:3], xi[3:]
        twist[:3, :3] = torch.tensor(
            [[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]]
        )
        twist[:3, 3] = rho
        torch.testing.assert_close(se3_exp(xi), torch.linalg.matrix_exp(twist), rtol=0, atol=1e-12)


def test_se3_exp_is_smooth_across_the_small_angle_switch():
    base = torch.tensor([0.1, -0.2, 0.3, 0.0, 0.0, 1.0], dtype=torch.float64)
    below, above = base.clone(), base.clone()
    below[5], above[5] = 0.99e-4, 1.01e-4  # θ² = 0.98e-8 and 1.02e-8 around the 1e-8 switch
    slope = (se3_exp(above) - se3_exp(below)) / 2e-6
    xi = base.clone()
    xi[5] = 1e-4
    jac = torch.autograd.functional.jacobian(se3_exp, xi)[..., 5]
    torch.testing.assert_close(slope, jac, rtol=0, atol=1e-6)


def test_reference_gradcheck():
    inputs = [
        t.requires_grad_() for t in _stack([0.6, 0.4], [[0.2] * 3, [0.9] * 3], [1, 2], [0.1] * 2)
    ]

    def fn(*args):
        return tuple(rasterize(*args, SIZE, SIZE, backend="torch"))

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)
