"""Trajectory files: TUM (``timestamp tx ty tz qx qy qz qw``) and KITTI (3×4 row-major).

Poses are camera-to-world (T_world←cam), as evo and the TUM/KITTI tools expect. TUM lines carry
their own timestamps; KITTI lines do not, so every KITTI file written together by
`write_trajectories` lists the same frames, in order, and ``times.txt`` gives their timestamps.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bgs_batch.geometry import matrix_to_quat_xyzw, pose_matrix
from bgs_batch.metrics import align_rigid, ate

TUM_HEADER = "# timestamp tx ty tz qx qy qz qw\n"
TUM_COLUMNS = 8
KITTI_VALUES = 12  # the first three rows of the 4×4 pose, row-major
GT_MATCH_TOLERANCE_S = 1e-4  # TUM files keep 6 decimals; looser than that is a different frame
MIN_ALIGNED_FRAMES = 3  # a rigid alignment needs three non-collinear positions


def write_tum(path: Path, timestamps: np.ndarray, c2w: np.ndarray) -> None:
    """Write poses (N, 4, 4) with their timestamps; rows with NaN poses are left out."""
    known = np.all(np.isfinite(c2w), axis=(1, 2))
    quats = matrix_to_quat_xyzw(c2w[known, :3, :3])
    with open(path, "w") as fh:
        fh.write(TUM_HEADER)
        for t, pose, q in zip(timestamps[known], c2w[known], quats, strict=True):
            values = " ".join(f"{v:.9f}" for v in (*pose[:3, 3], *q))
            fh.write(f"{t:.6f} {values}\n")


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (N,) and camera-to-world poses (N, 4, 4) of a TUM trajectory file."""
    data = np.loadtxt(path, comments="#", ndmin=2)
    if data.size and data.shape[1] != TUM_COLUMNS:
        raise ValueError(f"{path} has {data.shape[1]} columns, TUM has {TUM_COLUMNS}")
    data = data.reshape(-1, TUM_COLUMNS)
    return data[:, 0], pose_matrix(data[:, 1:4], data[:, 4:8])


def write_kitti(path: Path, c2w: np.ndarray) -> None:
    """Write poses (N, 4, 4), one line of 12 numbers each; all must be finite (lines are frames)."""
    if not np.all(np.isfinite(c2w)):
        raise ValueError("KITTI files have no timestamps: select frames with finite poses first")
    np.savetxt(path, c2w[:, :3, :].reshape(-1, KITTI_VALUES), fmt="%.9f")


def read_kitti(path: Path) -> np.ndarray:
    """Camera-to-world poses (N, 4, 4) of a KITTI trajectory file."""
    rows = np.loadtxt(path, ndmin=2)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    return poses


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
