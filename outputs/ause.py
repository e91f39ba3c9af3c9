"""Area under the sparsification error (AUSE-MAE) of predicted uncertainty vs true error.

Conventions (docs/outputs.md, metrics.json conventions):
- elements: the pixels of one frame with valid measured depth (finite, > 0);
- colour: per-pixel error = |Ĉ − C| averaged over channels, uncertainty = the channel mean of Σ_C;
  depth: error = |D̂ − D| (m), uncertainty = Σ_D;
- 100 fractions r_k = k/100, k = 0..99: keep the ⌊(100 − k)·N/100⌋ elements (at least one)
  with the lowest uncertainty (stable sort: among ties the earlier pixel is kept longer) and, for
  the oracle, the lowest error; each curve value is the MAE of the kept elements;
- AUSE = trapezoid rule of (uncertainty curve − oracle curve) over r ∈ [0, 0.99];
- "raw": curves in the error's units, no normalisation (as BayesianGS-SLAM reports);
  "normalised": both curves divided by the largest value of either (Bayes' Rays convention);
- one value per frame; the reported value is the mean over frames.
AUSE depends on the uncertainty only through its order: variance, std or log-variance agree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FRACTIONS = np.arange(100) / 100.0  # share of elements removed at each step


@dataclass(frozen=True)
class Sparsification:
    """Sparsification curves of one frame (or their mean over frames) and the two AUSE values."""

    oracle: np.ndarray  # MAE of the kept elements, removing by true error; per fraction
    by_uncertainty: np.ndarray  # the same, removing by descending uncertainty
    ause_raw: float
    ause_normalised: float


def _kept_mae(sorted_errors: np.ndarray) -> np.ndarray:
    """MAE of the first ⌊(100 − k)·N/100⌋ (≥ 1) of `sorted_errors` for each fraction k."""
    n = len(sorted_errors)
    kept = np.maximum((n * (100 - np.arange(len(FRACTIONS)))) // 100, 1)
    return np.cumsum(sorted_errors)[kept - 1] / kept


def _area(oracle: np.ndarray, by_uncertainty: np.ndarray) -> tuple[float, float]:
    """AUSE raw and max-normalised of a pair of curves."""
    raw = float(np.trapezoid(by_uncertainty - oracle, FRACTIONS))
    peak = max(oracle.max(), by_uncertainty.max())
    return raw, raw / peak if peak > 0 else 0.0


def sparsification(uncertainty: np.ndarray, error: np.ndarray) -> Sparsification:
    """Curves and AUSE of paired 1-D arrays of per-element uncertainty and absolute error."""
    uncertainty, error = np.ravel(uncertainty), np.ravel(error).astype(np.float64)
    if len(error) == 0 or len(uncertainty) != len(error):
        raise ValueError(f"need equal, non-empty arrays, got {len(uncertainty)} and {len(error)}")
    oracle = _kept_mae(np.sort(error))
    by_uncertainty = _kept_mae(error[np.argsort(uncertainty, kind="stable")])
    return Sparsification(oracle, by_uncertainty, *_area(oracle, by_uncertainty))


def _valid_depth(measured_depth: np.ndarray) -> np.ndarray:
    depth = np.asarray(measured_depth, np.float64).reshape(measured_depth.shape[:2])
    return np.isfinite(depth) & (depth > 0)


def colour_sparsification(rendered: np.ndarray, target: np.ndarray, variance: np.ndarray,
                          measured_depth: np.ndarray) -> Sparsification:  # fmt: skip
    """Colour AUSE of one frame: images [H,W,3]; Σ_C [H,W,3] or [H,W,1]; depth [H,W(,1)]."""
    error = np.abs(np.asarray(rendered, np.float64) - np.asarray(target, np.float64)).mean(-1)
    uncertainty = np.asarray(variance, np.float64).mean(-1)
    valid = _valid_depth(measured_depth)
    return sparsification(uncertainty[valid], error[valid])


def depth_sparsification(rendered: np.ndarray, measured: np.ndarray, variance: np.ndarray
                         ) -> Sparsification:  # fmt: skip
    """Depth AUSE of one frame: rendered depth, measured depth and Σ_D, each [H,W] or [H,W,1]."""
    shape = measured.shape[:2]
    error = np.abs(np.asarray(rendered, np.float64).reshape(shape)
                   - np.asarray(measured, np.float64).reshape(shape))  # fmt: skip
    valid = _valid_depth(measured)
    return sparsification(np.asarray(variance, np.float64).reshape(shape)[valid], error[valid])


def depth_sparsifications(
    rendered: np.ndarray, measured: np.ndarray, variances: dict[str, np.ndarray]
) -> dict[str, Sparsification]:
    """`depth_sparsification` of several uncertainties of one frame, sharing the oracle curve."""
    shape = measured.shape[:2]
    error = np.abs(np.asarray(rendered, np.float64).reshape(shape)
                   - np.asarray(measured, np.float64).reshape(shape))  # fmt: skip
    valid = _valid_depth(measured)
    error = error[valid]
    if len(error) == 0:
        raise ValueError("no pixel with valid measured depth")
    oracle = _kept_mae(np.sort(error))
    out = {}
    for name, variance in variances.items():
        uncertainty = np.asarray(variance, np.float64).reshape(shape)[valid]
        by_uncertainty = _kept_mae(error[np.argsort(uncertainty, kind="stable")])
        out[name] = Sparsification(oracle, by_uncertainty, *_area(oracle, by_uncertainty))
    return out


def mean_over_frames(frames: list[Sparsification]) -> Sparsification:
    """The mean curves and the mean of the per-frame AUSE values."""
    if not frames:
        raise ValueError("no frames to average")
    return Sparsification(
        oracle=np.mean([f.oracle for f in frames], axis=0),
        by_uncertainty=np.mean([f.by_uncertainty for f in frames], axis=0),
        ause_raw=float(np.mean([f.ause_raw for f in frames])),
        ause_normalised=float(np.mean([f.ause_normalised for f in frames])),
    )
