"""Dense pure-PyTorch reference renderer: the test oracle (tiny scenes, float64).

Every pixel is composited against every Gaussian with plain autograd, implementing exactly the
semantics of docs/method.md §1-2 that the fast backend must reproduce: ``α_i = min(0.99, o_i·G_i)``,
skip ``α_i < 1/255``, stop before ``T < 1e-4``, and the opacity-induced variances of paper
Eq. 3, 12 and 13.
"""

import torch

from .camera import Camera
from .constants import (
    ALPHA_MAX,
    ALPHA_MIN,
    FRUSTUM_MARGIN,
    LOWPASS,
    NEAR_PLANE,
    SLOPE_RIDGE,
    T_MIN,
)

PIXEL_CHUNK = 4096
"""Pixels composited at once by the dense reference (bounds its memory use)."""


def quat_wxyz_to_matrix(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [N,3,3] of (w, x, y, z) quaternions [N,4] (normalised here)."""
    w, x, y, z = (quats / quats.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)  # fmt: skip


def project_ref(
    means: torch.Tensor,
    log_scales: torch.Tensor,
    quats: torch.Tensor,
    opacity_logits: torch.Tensor,
    viewmat: torch.Tensor,
    camera: Camera,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """EWA projection: ``(means2d [N,2], conics [N,3], depths [N], depth_slopes [N,2],
    visible [N])`` of N Gaussians.

    ``conics = (a, b, c)`` is the inverse of the low-passed screen covariance
    ``J W Σ Wᵀ Jᵀ + 0.3·I``, so ``σ = ½(a·dx² + c·dy²) + b·dx·dy``. ``depth_slopes`` =
    ``(Σ₂ + ε·tr Σ₂·I)⁻¹ J W Σ Wᵀ e_z`` with the unfiltered ``Σ₂ = J W Σ Wᵀ Jᵀ``: the screen
    gradient of the Gaussian's plane, the mean depth given the pixel (ε = ``SLOPE_RIDGE``
    keeps it finite for a disc seen edge on). ``visible`` applies the
    near-plane, guard-band and opacity-aware screen-bounds culling of the fast backend.
    """
    rot_w, trans_w = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ rot_w.T + trans_w
    x, y, z = p.unbind(-1)
    m = quat_wxyz_to_matrix(quats) * log_scales.exp().unsqueeze(-2)
    cov_cam = rot_w @ (m @ m.transpose(-1, -2)) @ rot_w.T
    zero = torch.zeros_like(z)
    jac = torch.stack(
        [camera.fx / z, zero, -camera.fx * x / z**2, zero, camera.fy / z, -camera.fy * y / z**2],
        dim=-1,
    ).reshape(-1, 2, 3)
    cov2d = jac @ cov_cam @ jac.transpose(-1, -2)
    sxx, sxy, syy = cov2d[:, 0, 0] + LOWPASS, cov2d[:, 0, 1], cov2d[:, 1, 1] + LOWPASS
    det = sxx * syy - sxy * sxy
    conics = torch.stack([syy / det, -sxy / det, sxx / det], dim=-1)
    depth_cov = jac @ cov_cam[:, :, 2:]  # Cov(p, z) = J Σ_cam e_z
    ridge = SLOPE_RIDGE * (cov2d[:, 0, 0] + cov2d[:, 1, 1])
    eye = torch.eye(2, dtype=cov2d.dtype)
    slopes = torch.linalg.solve(cov2d + ridge[:, None, None] * eye, depth_cov).squeeze(-1)
    means2d = torch.stack([camera.fx * x / z + camera.cx, camera.fy * y / z + camera.cy], -1)
    visible = (
        (z > NEAR_PLANE)
        & in_guard_band(means2d, camera)
        & rect_in_image(means2d, conics, torch.sigmoid(opacity_logits), camera)
    ).detach()
    return means2d, conics, z, slopes, visible


def in_guard_band(means2d: torch.Tensor, camera: Camera) -> torch.Tensor:
    """Whether projected centres lie within ``FRUSTUM_MARGIN`` half-extents of the image centre."""
    half = means2d.new_tensor([camera.width / 2, camera.height / 2])
    centre = means2d.new_tensor([(camera.width - 1) / 2, (camera.height - 1) / 2])
    return ((means2d - centre).abs() <= FRUSTUM_MARGIN * half).all(-1)


def rect_in_image(
    means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, camera: Camera
) -> torch.Tensor:
    """Whether the opacity-aware bounding box of ``{σ ≤ ln(o/α_min)}`` holds a pixel centre."""
    a, b, c = conics.detach().unbind(-1)
    level = 2 * torch.log(opacities.detach() / ALPHA_MIN)
    det = a * c - b * b
    half = torch.stack([c / det, a / det], -1).mul(level.clamp_min(0).unsqueeze(-1)).sqrt()
    centre = means2d.detach()
    size = means2d.new_tensor([camera.width - 1, camera.height - 1])
    lo = torch.ceil(centre - half).clamp_min(0)
    hi = torch.minimum(torch.floor(centre + half), size)
    return (level > 0) & (lo <= hi).all(-1)


def rasterize_ref(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    depths: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    variances: torch.Tensor,
    depth_slopes: torch.Tensor,
    width: int,
    height: int,
    full_grad: bool = True,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Dense compositing into ``(color, depth, alpha, V_C, V_D)``, each [H,W,3] or [H,W,1].

    ``C = Σ c_i α_i T_i``, ``D = Σ d_i α_i T_i`` (unnormalised; ``d_i = depths_i + s_i·(p − μ_i)``
    at pixel p with ``s_i`` = ``depth_slopes``), ``A = Σ α_i T_i`` and, with
    ``v_i`` = ``variances``, ``V_C = Σ (c_i − C)² T_i² v_i`` (paper Eq. 3, 12) and
    ``V_D = Σ (d_i − D)² T_i² v_i`` (Eq. 13). ``full_grad=False`` treats ``T_i²`` as a constant
    in the backward, as the authors' CUDA kernel does; ``C`` and ``D`` keep their gradient.
    """
    order = torch.argsort(depths.detach(), stable=True)
    mean = means2d[order]
    a, b, c = conics[order].unbind(-1)
    feats = torch.cat([colors, depths.unsqueeze(-1)], -1)[order]
    opac, var, slopes = opacities[order], variances[order], depth_slopes[order]
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=means2d.dtype),
        torch.arange(width, dtype=means2d.dtype),
        indexing="ij",
    )
    pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)
    chunks = [
        _composite(pix[i : i + PIXEL_CHUNK], mean, a, b, c, opac, feats, slopes, var, full_grad)
        for i in range(0, pix.shape[0], PIXEL_CHUNK)
    ]
    out, alpha, out_var = (torch.cat(t, 0) for t in zip(*chunks, strict=True))
    out, alpha, out_var = (t.reshape(height, width, -1) for t in (out, alpha, out_var))
    return out[..., :3], out[..., 3:], alpha, out_var[..., :3], out_var[..., 3:]


def _composite(pix, mean, a, b, c, opac, feats, slopes, var, full_grad):
    """Composite depth-sorted Gaussians at the pixel centres ``pix`` [P,2]."""
    dx = pix[:, :1] - mean[:, 0]
    dy = pix[:, 1:] - mean[:, 1]
    depth = feats[:, 3] + slopes[:, 0] * dx + slopes[:, 1] * dy  # [P,N] the planes at the pixels
    feats = torch.cat([feats[:, :3].expand(pix.shape[0], -1, -1), depth.unsqueeze(-1)], -1)
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = torch.clamp(opac * torch.exp(-sigma), max=ALPHA_MAX)
    alpha = torch.where(alpha >= ALPHA_MIN, alpha, torch.zeros_like(alpha))
    trans_after = torch.cumprod(1 - alpha.detach(), dim=1)
    alpha = torch.where(trans_after >= T_MIN, alpha, torch.zeros_like(alpha))
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], 1), 1)
    weight = alpha * trans
    out = (weight.unsqueeze(-1) * feats).sum(1)
    acc = weight.sum(1, keepdim=True)
    trans_sq = trans * trans if full_grad else (trans * trans).detach()
    u = torch.where(alpha > 0, trans_sq * var, torch.zeros_like(trans_sq))
    out_var = (u.unsqueeze(-1) * (feats - out.unsqueeze(1)) ** 2).sum(1)
    return out, acc, out_var
