"""Trajectory files in the TUM format (``timestamp tx ty tz qx qy qz qw``, camera-to-world)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bgs_batch.geometry import matrix_to_quat, pose_matrix

TUM_HEADER = "# timestamp tx ty tz qx qy qz qw\n"


def write_tum(path: Path, timestamps: np.ndarray, c2w: np.ndarray) -> None:
    """Write poses (N, 4, 4) with their timestamps; rows with NaN poses are left out."""
    known = np.all(np.isfinite(c2w), axis=(1, 2))
    quats = matrix_to_quat(c2w[known, :3, :3])
    with open(path, "w") as fh:
        fh.write(TUM_HEADER)
        for t, pose, q in zip(timestamps[known], c2w[known], quats, strict=True):
            values = " ".join(f"{v:.9f}" for v in (*pose[:3, 3], *q))
            fh.write(f"{t:.6f} {values}\n")


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (N,) and camera-to-world poses (N, 4, 4) of a TUM trajectory file."""
    data = np.loadtxt(path, comments="#", ndmin=2)
    return data[:, 0], pose_matrix(data[:, 1:4], data[:, 4:8])
