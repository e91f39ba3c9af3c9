"""The Gauss-Newton curvature of the tracking loss: how a render moves when the camera does.

The renderer gives the exact pose gradient of the tracking loss (Eq. 15-17) but not per-pixel
Jacobians. Their first-order image-motion form is cheap: under the left perturbation
``w2c' = exp(ξ) · w2c`` a surface point seen at pixel u (camera point X, from the render's
alpha-normalised depth) moves to ``X + ρ + φ × X``; the render follows it, so

    Ĉ'(u) ≈ Ĉ(u) − ∇Ĉ(u) · Δu,          D̂'(u) ≈ D̂(u) + A(u) ΔZ − ∇D̂(u) · Δu,

with ``Δu = ∂π/∂X · (ρ + φ × X)`` and ``ΔZ`` its depth component (docs/method.md §6). The L1
terms ``w |r|`` are majorised by quadratics (iteratively reweighted least squares,
`irls_weights`). `tracker.Tracker` combines this normal matrix with the
renderer's exact gradient in trust-region steps, which also correct the majoriser's
curvature where the loss is flatter or steeper than it says.

`image_motion_normal_matrix` computes ``Σ w J Jᵀ`` in one numba pass over the pixels without
materialising the Jacobians (about 1 MB of float64 per colour channel at tracking resolution,
and a dozen full-image temporaries); `image_motion_jacobians` and `l1_normal_matrix` are the
same quantities spelled out, which the tests check the kernel and the renderer against.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from bgs_batch.render import Camera, RasterOutput

ALPHA_MIN = 0.5  # pixels with less rendered alpha have no surface to move with the camera
RESIDUAL_FLOOR = 1e-12  # of the median: a frame fitted exactly

_UPPER = [(a, b) for a in range(6) for b in range(a, 6)]  # the 21 entries of a symmetric 6×6
_UPPER_A = np.array([a for a, _ in _UPPER])
_UPPER_B = np.array([b for _, b in _UPPER])


def image_motion_jacobians(out: RasterOutput, camera: Camera
                           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # fmt: skip
    """First-order Jacobians of the rendered colour [H,W,3,6] and depth [H,W,6] with respect
    to the left twist ξ = (ρ, φ) at ξ = 0, and where they hold ([H,W] bool: enough alpha)."""
    color = out.color.detach().to(torch.float64)
    depth = out.depth.detach().to(torch.float64)[..., 0]
    alpha = out.alpha.detach().to(torch.float64)[..., 0]
    surface = alpha >= ALPHA_MIN
    z = torch.where(surface, depth / alpha.clamp_min(ALPHA_MIN), 1.0)
    h, w = z.shape
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64),
                          torch.arange(w, dtype=torch.float64), indexing="ij")  # fmt: skip
    point = torch.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], -1)
    inv_z = 1.0 / z
    zeros = torch.zeros_like(z)
    # rows ∂u/∂X and ∂v/∂X of the pinhole projection, [H,W,3] each
    du = torch.stack([camera.fx * inv_z, zeros, -camera.fx * point[..., 0] * inv_z**2], -1)
    dv = torch.stack([zeros, camera.fy * inv_z, -camera.fy * point[..., 1] * inv_z**2], -1)
    gy_c, gx_c = torch.gradient(color, dim=(0, 1))
    gy_d, gx_d = torch.gradient(depth, dim=(0, 1))
    # ∂(render)/∂X for a point moving by δX: colour −∇Ĉ·∂π/∂X, depth A e_z − ∇D̂·∂π/∂X
    d_color = -(gx_c[..., None] * du[..., None, :] + gy_c[..., None] * dv[..., None, :])
    d_depth = -(gx_d[..., None] * du + gy_d[..., None] * dv)
    d_depth[..., 2] += alpha
    # δX = ρ + φ × X, so ∂/∂φ of g·δX is X × g
    j_color = torch.cat([d_color, torch.linalg.cross(point[..., None, :].expand_as(d_color),
                                                     d_color)], -1)  # fmt: skip
    j_depth = torch.cat([d_depth, torch.linalg.cross(point, d_depth)], -1)
    return j_color, j_depth, surface


def irls_weights(residual: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """``w/|r|`` (float64, the shape of `residual`): the weights of the iteratively reweighted
    least-squares majoriser of an L1 term ``Σ w |r|``, with |r| floored at its median over the
    pixels in the loss (an exactly fitted pixel would otherwise weigh without bound); zero
    where `weight` is (not in the loss)."""
    magnitude = residual.detach().to(torch.float64).abs()
    weight = weight.detach().to(torch.float64)
    used = weight > 0
    if not bool(used.any()):
        return torch.zeros_like(magnitude)
    floor = magnitude[used].median().clamp_min(RESIDUAL_FLOOR)
    return torch.where(used, weight / magnitude.clamp_min(floor), 0.0)


def l1_normal_matrix(residual: torch.Tensor, weight: torch.Tensor,
                     jacobian: torch.Tensor) -> torch.Tensor:  # fmt: skip
    """``Σ (w/|r|) J Jᵀ`` (6, 6) of an L1 term ``Σ w |r|`` (`irls_weights`): the Hessian of its
    majoriser. `residual` and `weight` are [..., C], `jacobian` [..., C, 6]."""
    irls = irls_weights(residual, weight)
    j = jacobian.reshape(-1, 6)
    return j.T @ (irls.reshape(-1, 1) * j)


def image_motion_normal_matrix(out: RasterOutput, camera: Camera, irls_color: torch.Tensor,
                               irls_depth: torch.Tensor) -> torch.Tensor:  # fmt: skip
    """``Σ w_C J_C J_Cᵀ + Σ w_D J_D J_Dᵀ`` (6, 6) over the pixels and colour channels, with the
    Jacobians of `image_motion_jacobians` and the weights `irls_color` [H,W,3] and
    `irls_depth` [H,W,1] (`irls_weights`; pixels without a surface must weigh zero)."""
    arrays = [np.ascontiguousarray(t.detach().to(torch.float64).numpy())
              for t in (out.color, out.depth, out.alpha, irls_color, irls_depth)]  # fmt: skip
    rows = np.zeros((arrays[0].shape[0], len(_UPPER)), np.float64)
    _normal_rows(*arrays, camera.fx, camera.fy, camera.cx, camera.cy, ALPHA_MIN, rows)
    upper = rows.sum(0)  # rows in order: the same bits for any thread count
    normal = torch.zeros(6, 6, dtype=torch.float64)
    for k, (a, b) in enumerate(_UPPER):
        normal[a, b] = normal[b, a] = float(upper[k])
    return normal


@numba.njit(cache=True, inline="always")
def _gradient(image, ch, y, x):
    """(∂/∂x, ∂/∂y) of channel `ch` of `image` [H,W,C] at a pixel as `torch.gradient`: central
    differences inside, one-sided at the border."""
    height, width = image.shape[0], image.shape[1]
    if x == 0:
        gx = image[y, 1, ch] - image[y, 0, ch]
    elif x == width - 1:
        gx = image[y, x, ch] - image[y, x - 1, ch]
    else:
        gx = (image[y, x + 1, ch] - image[y, x - 1, ch]) * 0.5
    if y == 0:
        gy = image[1, x, ch] - image[0, x, ch]
    elif y == height - 1:
        gy = image[y, x, ch] - image[y - 1, x, ch]
    else:
        gy = (image[y + 1, x, ch] - image[y - 1, x, ch]) * 0.5
    return gx, gy


@numba.njit(parallel=True, cache=True)
def _normal_rows(color, depth, alpha, irls_color, irls_depth, fx, fy, cx, cy, alpha_min, rows):
    """Per image row, the 21 upper entries of ``Σ w j jᵀ`` with ``j = [g, X × g]``: g the
    change of a rendered value for a surface point moving by δX (`image_motion_jacobians`)."""
    height, width, channels = color.shape
    for y in numba.prange(height):
        j = np.empty(6)
        for x in range(width):
            a = alpha[y, x, 0]
            weighed = irls_depth[y, x, 0] != 0.0
            for ch in range(channels):
                weighed = weighed or irls_color[y, x, ch] != 0.0
            if a < alpha_min or not weighed:
                continue
            z = depth[y, x, 0] / a
            px, py = (x - cx) / fx * z, (y - cy) / fy * z
            inv_z = 1.0 / z
            # rows ∂u/∂X and ∂v/∂X of the pinhole projection
            du0, du2 = fx * inv_z, -fx * px * inv_z * inv_z
            dv1, dv2 = fy * inv_z, -fy * py * inv_z * inv_z
            for ch in range(channels + 1):
                if ch < channels:
                    w = irls_color[y, x, ch]
                    gx, gy = _gradient(color, ch, y, x)
                else:
                    w = irls_depth[y, x, 0]
                    gx, gy = _gradient(depth, 0, y, x)
                if w == 0.0:
                    continue
                g0, g1, g2 = -gx * du0, -gy * dv1, -(gx * du2 + gy * dv2)
                if ch == channels:
                    g2 += a  # the depth also moves with the point along the axis
                j[0], j[1], j[2] = g0, g1, g2
                j[3], j[4], j[5] = py * g2 - z * g1, z * g0 - px * g2, px * g1 - py * g0
                for k in range(_UPPER_A.shape[0]):
                    rows[y, k] += w * j[_UPPER_A[k]] * j[_UPPER_B[k]]
