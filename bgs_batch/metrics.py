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


def rpe(estimated: np.ndarray, ground_truth: np.ndarray, delta: int = 1) -> dict[str, float]:
    """Relative pose error over `delta` frames (Sturm et al. 2012, as TUM's evaluate_rpe): for
    each pair i, i+delta with both poses known, the motion E_i = (Q_i⁻¹ Q_{i+δ})⁻¹ (P_i⁻¹ P_{i+δ})
    between the estimate P and ground truth Q; RMSE of its translation (m) and mean of its
    rotation angle (degrees). `estimated`, `ground_truth`: camera-to-world poses (N, 4, 4).

    No alignment is needed: the error of a relative motion does not depend on the world frame.
    """
    known = np.all(np.isfinite(estimated), (1, 2)) & np.all(np.isfinite(ground_truth), (1, 2))
    pairs = np.flatnonzero(known[:-delta] & known[delta:])
    if pairs.size == 0:
        raise ValueError(f"no pair of frames {delta} apart has both poses")
    est = np.linalg.inv(estimated[pairs]) @ estimated[pairs + delta]
    gt = np.linalg.inv(ground_truth[pairs]) @ ground_truth[pairs + delta]
    error = np.linalg.inv(gt) @ est
    translation = np.linalg.norm(error[:, :3, 3], axis=1)
    cos = np.clip((np.trace(error[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    return {"translation_rmse": float(np.sqrt(np.mean(translation**2))),
            "rotation_mean_deg": float(np.degrees(np.arccos(cos)).mean()),
            "pairs": int(pairs.size)}  # fmt: skip


def path_length(positions: np.ndarray) -> float:
    """Length (m) of the polyline through the finite positions (N, 3), in order."""
    finite = positions[np.all(np.isfinite(positions), 1)]
    return float(np.linalg.norm(np.diff(finite, axis=0), axis=1).sum())
