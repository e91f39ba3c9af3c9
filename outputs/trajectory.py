"""The trajectory a user takes away: the estimate in TUM and KITTI files (`bgs_batch.
trajectory_files`), aligned to the ground truth where there is one, and its ATE.

Every KITTI file written together by `write_trajectories` lists the same frames, in order, and
``times.txt`` gives their timestamps (KITTI lines carry none).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bgs_batch.metrics import align_rigid, ate
from bgs_batch.trajectory_files import write_kitti, write_tum

GT_MATCH_TOLERANCE_S = 1e-4  # TUM files keep 6 decimals; looser than that is a different frame
MIN_ALIGNED_FRAMES = 3  # a rigid alignment needs three non-collinear positions


def match_timestamps(query: np.ndarray, reference: np.ndarray,
                     tolerance: float = GT_MATCH_TOLERANCE_S) -> np.ndarray:  # fmt: skip
    """Index into `reference` of the timestamp equal to each `query` one (within `tolerance`),
    −1 where there is none."""
    order = np.argsort(reference, kind="stable")
    ref = reference[order]
    pos = np.clip(np.searchsorted(ref, query), 1, max(len(ref) - 1, 1))
    left, right = pos - 1, np.minimum(pos, len(ref) - 1)
    nearest = np.where(np.abs(ref[left] - query) <= np.abs(ref[right] - query), left, right)
    close = np.abs(ref[nearest] - query) <= tolerance
    return np.where(close, order[nearest], -1)


def apply_alignment(c2w: np.ndarray, rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """Poses moved by the world transform (rot, trans): T' = [R t; 0 1] · T."""
    out = c2w.copy()
    out[:, :3, :3] = rot @ c2w[:, :3, :3]
    out[:, :3, 3] = c2w[:, :3, 3] @ rot.T + trans
    return out


@dataclass(frozen=True)
class Alignment:
    """An estimate aligned to its ground truth, and the ATE statistics (m) of both alignments."""

    rows: np.ndarray  # (N,) frames where estimate and ground truth are both finite
    aligned: np.ndarray  # (N, 4, 4) the estimate after the rigid alignment
    stats: dict[str, dict[str, float]]  # "rigid", "with_scale": `ate` statistics


def align_to_ground_truth(estimate: np.ndarray, ground_truth: np.ndarray) -> Alignment | None:
    """Rigid (rotation + translation, no scale; Horn/Umeyama) alignment of the positions over the
    frames where both poses are finite, as ``evo_ape tum gt.tum estimate.tum -a``, with the ATE
    after it and after a Sim(3) alignment (``-as``); None with fewer than three such frames."""
    rows = np.all(np.isfinite(estimate), axis=(1, 2)) & np.all(np.isfinite(ground_truth),
                                                                axis=(1, 2))  # fmt: skip
    if rows.sum() < MIN_ALIGNED_FRAMES:
        return None
    est_xyz, gt_xyz = estimate[rows, :3, 3], ground_truth[rows, :3, 3]
    rot, trans, _ = align_rigid(est_xyz, gt_xyz)
    stats = {"rigid": ate(est_xyz, gt_xyz), "with_scale": ate(est_xyz, gt_xyz, True)}
    return Alignment(rows, apply_alignment(estimate, rot, trans), stats)


def write_trajectories(out_dir: Path, timestamps: np.ndarray, estimate: np.ndarray,
                       ground_truth: np.ndarray | None = None
                       ) -> dict[str, dict[str, float]]:  # fmt: skip
    """Write the estimate, and with ground truth (same frames, NaN where unknown) the aligned
    estimate and the GT, in TUM and KITTI; returns ATE statistics (empty without GT).

    Files: estimate.{tum,kitti}, times.txt, and with GT estimate_aligned.{tum,kitti} and
    gt.{tum,kitti}. Alignment: rigid (rotation + translation, no scale; Horn/Umeyama) of the
    positions over frames where both poses are finite, as ``evo_ape tum gt.tum estimate.tum -a``.
    TUM files hold every frame with a finite pose; KITTI files and times.txt hold the frames
    where all written trajectories are finite.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = np.all(np.isfinite(estimate), axis=(1, 2))
    write_tum(out_dir / "estimate.tum", timestamps, estimate)
    trajectories = {"estimate": estimate}
    stats: dict[str, dict[str, float]] = {}
    if ground_truth is not None:
        alignment = align_to_ground_truth(estimate, ground_truth)
        if alignment is None:
            both = int((rows & np.all(np.isfinite(ground_truth), axis=(1, 2))).sum())
            raise ValueError(f"only {both} frames have both an estimate and ground truth")
        rows = alignment.rows
        trajectories["estimate_aligned"] = alignment.aligned
        trajectories["gt"] = ground_truth
        stats = alignment.stats
        write_tum(out_dir / "estimate_aligned.tum", timestamps, trajectories["estimate_aligned"])
        write_tum(out_dir / "gt.tum", timestamps, ground_truth)
    for name, poses in trajectories.items():
        write_kitti(out_dir / f"{name}.kitti", poses[rows])
    np.savetxt(out_dir / "times.txt", timestamps[rows], fmt="%.6f")
    return stats
