"""Trajectory metrics: absolute trajectory error after rigid alignment (docs/outputs.md)."""

from __future__ import annotations

import numpy as np


def align_rigid(source: np.ndarray, target: np.ndarray, with_scale: bool = False
                ) -> tuple[np.ndarray, np.ndarray, float]:  # fmt: skip
    """Rotation R, translation t (and scale s) minimising Σ‖s R x + t − y‖² (Umeyama 1991).

    `source`, `target`: (N, 3) corresponding positions. Without scale this is Horn's rigid
    alignment, the convention of TUM's evaluate_ate and of `evo_ape -a`.
    """
    mu_x, mu_y = source.mean(0), target.mean(0)
    x, y = source - mu_x, target - mu_y
    cov = y.T @ x / len(source)
    u, d, vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1
    rot = u @ sign @ vt
    scale = float(np.trace(np.diag(d) @ sign) / x.var(0).sum()) if with_scale else 1.0
    return rot, mu_y - scale * rot @ mu_x, scale


def ate(estimated: np.ndarray, ground_truth: np.ndarray, with_scale: bool = False
        ) -> dict[str, float]:  # fmt: skip
    """ATE statistics in metres over frames where both positions are finite."""
    ok = np.all(np.isfinite(estimated), 1) & np.all(np.isfinite(ground_truth), 1)
    est, gt = estimated[ok], ground_truth[ok]
    rot, trans, scale = align_rigid(est, gt, with_scale)
    errors = np.linalg.norm(scale * est @ rot.T + trans - gt, axis=1)
    return {"rmse": float(np.sqrt(np.mean(errors**2))), "mean": float(errors.mean()),
            "median": float(np.median(errors)), "max": float(errors.max()), "frames": int(ok.sum())}
