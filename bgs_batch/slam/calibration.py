"""The gains of Σ_D's two parts, fitted at the end of a run (docs/method.md §4).

Σ_D = σ²_sensor,D + V_D + floor (Eq. 11) adds two variances that are learned apart: the sensor
network in mapping, the rᵢ behind V_D in mapping and the end-of-run refinement. Their floors
(1e-3 on the map term, 1e-4 on the network) sit above most depth residuals of a good sensor
(3 cm against a few millimetres), so the NLL they are trained by sees every smaller residual as
"below the floor" and never sets the two parts' scales against each other; their sum then ranks
the errors by whichever part happens to be larger. With the geometry final, the gains a, b of

    s = c + a·V_D + b·P,  P = the per-pixel part of σ²_sensor,D (the physics with the Nguyen
                           prior, whose network mean is a constant; else the network's map)

are fitted by the paper's Gaussian NLL (Eq. 14), mean(r²/s + log s), over the keyframes' depth
residuals r where the map is observed, without the floors (c, fitted alongside, stands for the
residual level neither part explains). The reported Σ_D is then σ²_sensor,D + a·V_D + floor
with P times b: a constant changes no pixel's rank, so the floor keeps its role and the gains
set the order.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.optimize import minimize

from bgs_batch.config import UncertaintyConfig
from bgs_batch.render import Gaussians, render
from bgs_batch.slam.mapping import Keyframe
from bgs_batch.slam.sensor_noise import DepthGains, SensorNoiseNet

# starts of the fit, as (log10 a, log10 b): its NLL can have more than one minimum, and the
# lowest of these starts' ends is kept
STARTS = ((0.0, 0.0), (2.0, 0.0), (0.0, 2.0))
LOG_BOUND = 30.0  # |ln c|, |ln a|, |ln b| at most: a part absent from the data cannot run away


def _nll(theta: np.ndarray, r2: np.ndarray, map_var: np.ndarray, sensor_var: np.ndarray
         ) -> tuple[float, np.ndarray]:  # fmt: skip
    """mean(r²/s + log s) and its gradient in θ = (ln c, ln a, ln b)."""
    c, a, b = np.exp(theta)
    s = c + a * map_var + b * sensor_var
    ds = (1.0 - r2 / s) / s  # d/ds of r²/s + log s
    grad = np.array([c * ds.mean(), a * (ds * map_var).mean(), b * (ds * sensor_var).mean()])
    return float(np.mean(r2 / s + np.log(s))), grad


def fit_depth_gains(residual: np.ndarray, map_var: np.ndarray, sensor_var: np.ndarray
                    ) -> DepthGains:  # fmt: skip
    """Maximum-likelihood gains a (map) and b (sensor) of s = c + a·V + b·σ² for residuals r
    (1-D arrays over the same pixels, in m and m²); `DepthGains()` when there is nothing to fit.
    Deterministic: L-BFGS in float64 from fixed starts."""
    r2 = np.square(np.asarray(residual, np.float64))
    map_var = np.asarray(map_var, np.float64)
    sensor_var = np.asarray(sensor_var, np.float64)
    mean_r2 = float(r2.mean()) if r2.size else 0.0
    if not mean_r2 > 0 or not np.isfinite(mean_r2):
        return DepthGains()
    bounds = [(-LOG_BOUND, LOG_BOUND)] * 3
    ends = []
    for log_a, log_b in STARTS:
        # c starts at a tenth of the mean square residual: the parts explain the rest
        start = np.array([np.log(0.1 * mean_r2), log_a * np.log(10), log_b * np.log(10)])
        ends.append(minimize(_nll, start, args=(r2, map_var, sensor_var), jac=True,
                             method="L-BFGS-B", bounds=bounds))  # fmt: skip
    best = min(ends, key=lambda end: end.fun)
    _, a, b = np.exp(best.x)
    return DepthGains(map=float(a), sensor=float(b))


def depth_samples(
    gaussians: Gaussians,
    keyframe: Keyframe,
    sensor: SensorNoiseNet,
    u: UncertaintyConfig,
    limit: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(residual, V_D, the per-pixel part of σ²_sensor,D) for `fit_depth_gains`, at up to
    `limit` pixels of a keyframe where its depth is valid and the map is observed, evenly
    spread over them. The per-pixel part is the physics with a prior (the network's frame mean
    is a constant, which the fit's c takes), else the network's map; `sensor`'s gains must be 1.
    """
    level = keyframe.level
    with torch.no_grad():
        out = render(gaussians, keyframe.w2c, level.camera, full_grad=u.full_grad)
        if sensor.prior is not None:
            sensor_part = sensor.depth_physics(level)
        else:
            sensor_part = sensor(level, u.sensor_downscale)[1]
    keep = ((level.depth > 0) & (out.alpha >= u.unobserved_alpha)).reshape(-1)
    pixels = torch.nonzero(keep)[:, 0]
    pixels = pixels[:: max(1, -(-len(pixels) // max(1, limit)))]  # a ceil: at most `limit`

    def at_pixels(image: torch.Tensor) -> np.ndarray:
        return image.reshape(-1)[pixels].double().numpy()

    return at_pixels(out.depth - level.depth), at_pixels(out.var_depth), at_pixels(sensor_part)
