"""Losses and scores of the method; images are channels-last tensors ([H,W,3] colour, [H,W,1]).

- `predictive_variance`: Σ = σ²_sensor + V_render with the floors of docs/method.md §2 (Eq. 10, 11)
- `mapping_loss`: L_3DGS + γ(NLL_C + NLL_D) (Eq. 12-14; LoopSplat's L_3DGS)
- `tracking_loss`: the uncertainty-normalised L1 surrogate (Eq. 15-17)
- `surprise_scores`: the Gaussian predictive NLL used for keyframe selection (Eq. 9)

Equation numbers follow their order in ``paper/BayesianGS-SLAM.tex``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from bgs_batch.config import TrackingConfig, UncertaintyConfig
from bgs_batch.render import RasterOutput
from bgs_batch.slam.blur import gaussian_window
from bgs_batch.slam.loss_kernels import fused_ssim, l1_nll_terms, weighted_normalised_l1

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2
HALF_LOG_WEIGHT = 0.5  # NLL = 0.5 r²/Σ + 0.5 log Σ


def predictive_variance(
    rendered: torch.Tensor, sensor: torch.Tensor, alpha: torch.Tensor, cfg: UncertaintyConfig
) -> torch.Tensor:
    """Σ = σ²_sensor + (V_render + floor), with V := large where A < threshold (no gradient).

    `rendered` is V_C [H,W,3] or V_D [H,W,1]; `sensor` broadcasts to it ([H,W,1]).
    """
    unobserved = (alpha < cfg.unobserved_alpha).expand_as(rendered)
    map_part = torch.where(
        unobserved, rendered.new_tensor(cfg.unobserved_variance), rendered + cfg.map_floor
    )
    return sensor + map_part


def predictive_variances(
    out: RasterOutput, sensor_color: torch.Tensor, sensor_depth: torch.Tensor,
    cfg: UncertaintyConfig, depth_map_gain: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """Σ_C and Σ_D of a render (Eq. 10, 11): `predictive_variance` of its V_C and V_D, the
    latter times the calibrated map gain in reports (`slam.calibration`; 1 within the SLAM)."""
    var_depth = out.var_depth if depth_map_gain == 1.0 else depth_map_gain * out.var_depth
    return (predictive_variance(out.var_color, sensor_color, out.alpha, cfg),
            predictive_variance(var_depth, sensor_depth, out.alpha, cfg))  # fmt: skip


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two [H,W,C] images in [0,1] (11×11 Gaussian window, σ 1.5, zero padding);
    differentiable with respect to `a` (the render)."""
    window = gaussian_window(SSIM_WINDOW, SSIM_SIGMA, a.dtype)
    return fused_ssim(a, b, window, SSIM_C1, SSIM_C2)


def isotropy_loss(log_scales: torch.Tensor) -> torch.Tensor:
    """Mean |s − mean_axis(s)| over activated scales: keeps Gaussians from becoming needles."""
    scales = torch.exp(log_scales)
    return (scales - scales.mean(dim=1, keepdim=True)).abs().mean()


@dataclass(frozen=True)
class MappingTerms:
    """The parts of the mapping loss, for logging."""

    total: torch.Tensor
    color: torch.Tensor
    depth: torch.Tensor
    isotropy: torch.Tensor
    nll_color: torch.Tensor
    nll_depth: torch.Tensor


def mapping_loss(
    color: torch.Tensor,
    depth: torch.Tensor,
    target_color: torch.Tensor,
    target_depth: torch.Tensor,
    var_color: torch.Tensor,
    var_depth: torch.Tensor,
    log_scales: torch.Tensor,
    gamma: float,
    ssim_weight: float,
) -> MappingTerms:
    """L_map = L_3DGS + γ(NLL_C + NLL_D) on one keyframe (Eq. 12-14).

    L_3DGS = (1−w)·mean|Ĉ−C| + w·(1−SSIM) + mean|D̂−D| + isotropy, with means over pixels with
    valid depth (LoopSplat); `var_*` are the total predictive variances Σ_C, Σ_D.
    """
    l1_color, depth_term, nll_c, nll_d = l1_nll_terms(
        color, depth, target_color, target_depth, var_color, var_depth
    ).unbind()
    color_term = (1 - ssim_weight) * l1_color + ssim_weight * (1 - ssim(color, target_color))
    iso = isotropy_loss(log_scales)
    total = color_term + depth_term + iso + gamma * (nll_c + nll_d)
    return MappingTerms(total, color_term, depth_term, iso, nll_c, nll_d)


def tracking_loss(
    color: torch.Tensor,
    depth: torch.Tensor,
    alpha: torch.Tensor,
    target_color: torch.Tensor,
    target_depth: torch.Tensor,
    var_color: torch.Tensor,
    var_depth: torch.Tensor,
    cfg: TrackingConfig,
) -> torch.Tensor:
    """Uncertainty-normalised L1 (Eq. 15-17), summed over pixels with valid depth, weighted α³.

    ``paper``:   λ_c Σ|Ĉ−C|/√Σ_C + λ_d Σ|D̂−D|/√Σ_D
    ``authors``: w Σ|Ĉ−C|/√(λ_c Σ_C) + (1−w) Σ|D̂−D|/√(λ_d Σ_D), w = 0.6
    Per term the two differ by the constant factor λ^{3/2}/w; the optimum is the same when
    λ_c = λ_d and w = 0.5. Pass variances whose sensor part is detached (the network is frozen).
    """
    # α³: LoopSplat's soft mask (not detached)
    return weighted_normalised_l1(color, depth, alpha, target_color, target_depth, var_color,
                                  var_depth, tracking_weights(cfg))  # fmt: skip


def tracking_weights(cfg: TrackingConfig) -> tuple[float, float]:
    """The factors (w_C, w_D) of `tracking_loss`'s two sums for its ``loss_form``."""
    if cfg.loss_form == "paper":
        return cfg.lambda_color, cfg.lambda_depth
    w = cfg.authors_color_weight
    return w / cfg.lambda_color**0.5, (1 - w) / cfg.lambda_depth**0.5


def surprise_scores(
    color: torch.Tensor,
    depth: torch.Tensor,
    target_color: torch.Tensor,
    target_depth: torch.Tensor,
    var_color: torch.Tensor,
    var_depth: torch.Tensor,
) -> tuple[float, float]:
    """Predictive surprise S_C, S_D: Σ 0.5·[(Ĉ−C)²/Σ + log Σ] over valid-depth pixels (Eq. 9).

    Sums (not means) with the unscaled total variance; only their sign against K matters.
    """
    with torch.no_grad():
        mask = target_depth > 0
        s_c = HALF_LOG_WEIGHT * ((color - target_color) ** 2 / var_color + torch.log(var_color))
        s_d = HALF_LOG_WEIGHT * ((depth - target_depth) ** 2 / var_depth + torch.log(var_depth))
        return float(s_c[mask.expand_as(s_c)].sum()), float(s_d[mask].sum())
