"""The Gauss-Newton curvature of the tracking loss: how a render moves when the camera does.

The renderer gives the exact pose gradient of the tracking loss (Eq. 15-17) but not per-pixel
Jacobians. Their first-order image-motion form is cheap: under the left perturbation
``w2c' = exp(ξ) · w2c`` a surface point seen at pixel u (camera point X, from the render's
alpha-normalised depth) moves to ``X + ρ + φ × X``; the render follows it, so

    Ĉ'(u) ≈ Ĉ(u) − ∇Ĉ(u) · Δu,          D̂'(u) ≈ D̂(u) + A(u) ΔZ − ∇D̂(u) · Δu,

with ``Δu = ∂π/∂X · (ρ + φ × X)`` and ``ΔZ`` its depth component (docs/method.md §6). The L1
terms ``w |r|`` are majorised by quadratics (iteratively reweighted least squares,
`l1_normal_matrix`). `tracking.Tracker` combines this normal matrix with the
renderer's exact gradient in trust-region steps, which also correct the majoriser's
curvature where the loss is flatter or steeper than it says.
"""

from __future__ import annotations

import torch

from bgs_batch.render import Camera, RasterOutput

ALPHA_MIN = 0.5  # pixels with less rendered alpha have no surface to move with the camera
RESIDUAL_FLOOR = 1e-12  # of the median: a frame fitted exactly


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


def l1_normal_matrix(residual: torch.Tensor, weight: torch.Tensor,
                     jacobian: torch.Tensor) -> torch.Tensor:  # fmt: skip
    """``Σ (w/|r|) J Jᵀ`` (6, 6) of an L1 term ``Σ w |r|``: the Hessian of its iteratively
    reweighted least-squares majoriser, with |r| floored at its median over the pixels in the
    loss (an exactly fitted pixel would otherwise weigh without bound).

    `residual` and `weight` are [..., C] (zero weight: not in the loss), `jacobian` [..., C, 6].
    """
    magnitude = residual.detach().to(torch.float64).abs()
    weight = weight.detach().to(torch.float64)
    used = weight > 0
    if not bool(used.any()):
        return torch.zeros(6, 6, dtype=torch.float64)
    floor = magnitude[used].median().clamp_min(RESIDUAL_FLOOR)
    irls = torch.where(used, weight / magnitude.clamp_min(floor), 0.0)
    j = jacobian.reshape(-1, 6)
    return j.T @ (irls.reshape(-1, 1) * j)
