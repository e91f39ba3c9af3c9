"""Trajectory files: TUM (``timestamp tx ty tz qx qy qz qw``) and KITTI (3×4 row-major).

Poses are camera-to-world (T_world←cam), as evo and the TUM/KITTI tools expect. TUM lines carry
their own timestamps; KITTI lines do not, so the frames a KITTI file lists are given beside it
(`outputs.trajectory.write_trajectories` writes ``times.txt``). `bgs run` writes
``trajectory.txt`` with `write_tum`; the exports read it back with `read_tum`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bgs_batch.geometry import matrix_to_quat_xyzw, pose_matrix

TUM_HEADER = "# timestamp tx ty tz qx qy qz qw\n"
TUM_COLUMNS = 8
KITTI_VALUES = 12  # the first three rows of the 4×4 pose, row-major


def write_tum(path: Path, timestamps: np.ndarray, c2w: np.ndarray) -> None:
    """Write poses (N, 4, 4) with their timestamps; rows with NaN poses are left out."""
    known = np.all(np.isfinite(c2w), axis=(1, 2))
    quats = matrix_to_quat_xyzw(c2w[known, :3, :3])
    with open(path, "w") as fh:
        fh.write(TUM_HEADER)
        for t, pose, q in zip(timestamps[known], c2w[known], quats, strict=True):
            # + 0.0 turns a value that rounds to −0 into 0: a file read back and written again
            # must not flip the sign of a zero (tiny components differ in the last bits)
            values = " ".join(f"{round(float(v), 9) + 0.0:.9f}" for v in (*pose[:3, 3], *q))
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
