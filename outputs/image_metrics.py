"""Rendering metrics on one frame; images are channels-last float tensors in [0, 1].

Conventions (docs/outputs.md, as LoopSplat/BayesianGS-SLAM report them):
- PSNR: 10·log10(1 / MSE) over the whole [H,W,3] image, data range 1; identical images give inf.
- SSIM: the 3DGS Gaussian-window SSIM (11×11, σ 1.5, zero padding) of `bgs_batch.slam.losses.ssim`.
- MS-SSIM: Wang et al. 2003 as in pytorch-msssim (valid 11×11 Gaussian windows, σ 1.5, five
  scales with weights 0.0448, 0.2856, 0.3001, 0.2363, 0.1333, 2×2 average pooling between scales,
  negative terms clamped to 0, mean over channels); the smaller image side must exceed 160 px.
- Depth L1: mean |D̂ − D| in metres over pixels with valid (finite, > 0) measured depth.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from bgs_batch.slam.blur import gaussian_window
from bgs_batch.slam.losses import SSIM_C1, SSIM_C2, SSIM_SIGMA, SSIM_WINDOW, ssim

MS_SSIM_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)
MS_SSIM_MIN_SIDE = (SSIM_WINDOW - 1) * 2 ** (len(MS_SSIM_WEIGHTS) - 1)  # 160 px


def psnr(rendered: torch.Tensor, target: torch.Tensor) -> float:
    """Peak signal-to-noise ratio in dB of two [H,W,C] images in [0, 1]."""
    mse = float(torch.mean((rendered.double() - target.double()) ** 2))
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def ssim_index(rendered: torch.Tensor, target: torch.Tensor) -> float:
    """Mean SSIM of two [H,W,C] images in [0, 1] (the training loss's SSIM)."""
    return float(ssim(rendered.double(), target.double()))


def _ssim_terms(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-channel mean SSIM and mean contrast-structure term of [1,C,H,W] images (valid)."""
    channels = a.shape[1]
    g = gaussian_window(SSIM_WINDOW, SSIM_SIGMA, a.dtype)
    rows, cols = g.view(1, 1, -1, 1), g.view(1, 1, 1, -1)

    def blur(img: torch.Tensor) -> torch.Tensor:
        img = F.conv2d(img, rows.expand(channels, 1, -1, 1), groups=channels)
        return F.conv2d(img, cols.expand(channels, 1, 1, -1), groups=channels)

    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2
    cov = blur(a * b) - mu_a * mu_b
    cs = (2 * cov + SSIM_C2) / (var_a + var_b + SSIM_C2)
    luminance = (2 * mu_a * mu_b + SSIM_C1) / (mu_a**2 + mu_b**2 + SSIM_C1)
    return (luminance * cs).mean((0, 2, 3)), cs.mean((0, 2, 3))


def ms_ssim(rendered: torch.Tensor, target: torch.Tensor) -> float:
    """Multi-scale SSIM of two [H,W,C] images in [0, 1] (see the module's conventions)."""
    if min(rendered.shape[:2]) <= MS_SSIM_MIN_SIDE:
        raise ValueError(f"MS-SSIM needs images larger than {MS_SSIM_MIN_SIDE} px on each side, "
                         f"got {tuple(rendered.shape[:2])}")  # fmt: skip
    a = rendered.double().permute(2, 0, 1)[None]
    b = target.double().permute(2, 0, 1)[None]
    terms = []
    for level in range(len(MS_SSIM_WEIGHTS)):
        if level:
            padding = [side % 2 for side in a.shape[2:]]
            a, b = (F.avg_pool2d(img, kernel_size=2, padding=padding) for img in (a, b))
        full, cs = _ssim_terms(a, b)
        terms.append(torch.relu(cs))
    terms[-1] = torch.relu(full)
    weights = torch.tensor(MS_SSIM_WEIGHTS, dtype=a.dtype)[:, None]
    return float(torch.prod(torch.stack(terms) ** weights, dim=0).mean())


def depth_l1(rendered: torch.Tensor, measured: torch.Tensor) -> float:
    """Mean absolute depth error (m) over pixels with valid measured depth; NaN if none."""
    valid = torch.isfinite(measured) & (measured > 0)
    if not valid.any():
        return math.nan
    return float(torch.mean(torch.abs(rendered.double()[valid] - measured.double()[valid])))
