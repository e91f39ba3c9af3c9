"""Rigid corrections of submaps on disk and of camera poses.

A finished submap file keeps the Gaussians as they were mapped (``raw_params``, written once)
next to the corrected ones (``params``, what exports read) and the cumulative correction
(``correction``, 4×4). The SLAM always starts from ``raw_params`` and the correction held in
its own (checkpointed) state, never from the file's, so a run resumed from a checkpoint taken
before a correction gives bit for bit the result of an uninterrupted one. ``params`` is always
computed from ``raw_params`` in one step, so it does not depend on how many corrections there
were on the way.

The end-of-run uncertainty refinement (`Slam.finish`) rewrites only the r_i of ``params``; the
raw ones stay as mapped, so loop closure (which reads the raw Gaussians) is unaffected, and a
repeated refinement starts from the same values.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from bgs_batch.atomic import save_torch
from bgs_batch.geometry import interpolate_poses, matrix_to_quat_xyzw
from bgs_batch.slam.gaussian_map import UNCERTAINTY_KEY

RAW_KEY = "raw_params"
CORRECTION_KEY = "correction"


def quat_product(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p ⊗ q of w-first quaternions (broadcasting)."""
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack([pw * qw - px * qx - py * qy - pz * qz,
                     pw * qx + px * qw + py * qz - pz * qy,
                     pw * qy - px * qz + py * qw + pz * qx,
                     pw * qz + px * qy - py * qx + pz * qw], -1)  # fmt: skip


def transform_params(params: dict[str, torch.Tensor], transform: np.ndarray
                     ) -> dict[str, torch.Tensor]:  # fmt: skip
    """Gaussians moved by a rigid transform: μ ← Rμ + t, q ← q_R ⊗ q; the rest unchanged."""
    rot, trans = transform[:3, :3], transform[:3, 3]
    xyzw = matrix_to_quat_xyzw(rot)
    q_rot = np.concatenate([xyzw[3:], xyzw[:3]])
    out = dict(params)
    means = params["means"].numpy().astype(np.float64)
    out["means"] = torch.from_numpy((means @ rot.T + trans).astype(np.float32))
    quats = params["quats"].numpy().astype(np.float64)
    out["quats"] = torch.from_numpy(quat_product(q_rot, quats).astype(np.float32))
    return out


def load_raw(path: str | Path) -> dict[str, torch.Tensor]:
    """The Gaussians of a submap file as they were mapped (before any correction)."""
    data = torch.load(path, weights_only=True)
    return data.get(RAW_KEY, data["params"])


def write_correction(path: str | Path, correction: np.ndarray) -> None:
    """Rewrite a submap file with `correction` (cumulative) applied to its raw Gaussians
    (atomic; the r_i of the raw Gaussians, undoing any uncertainty refinement)."""
    path = Path(path)
    data = torch.load(path, weights_only=True)
    raw = data.get(RAW_KEY, data["params"])
    data[RAW_KEY] = raw
    data["params"] = transform_params(raw, correction)
    data[CORRECTION_KEY] = torch.from_numpy(np.array(correction, np.float64))
    save_torch(data, path)


def load_mapped(path: str | Path) -> dict[str, torch.Tensor]:
    """The Gaussians of a submap file as corrected, with the r_i as mapped (before any
    uncertainty refinement)."""
    data = torch.load(path, weights_only=True)
    raw = data.get(RAW_KEY, data["params"])
    return {**data["params"], UNCERTAINTY_KEY: raw[UNCERTAINTY_KEY]}


def write_uncertainty(path: str | Path, logits: torch.Tensor) -> None:
    """Rewrite a submap file's r_i in ``params`` (atomic), keeping the mapped ones as raw."""
    path = Path(path)
    data = torch.load(path, weights_only=True)
    data[RAW_KEY] = data.get(RAW_KEY, data["params"])
    data["params"] = {**data["params"], UNCERTAINTY_KEY: logits.clone()}
    save_torch(data, path)


def camera_shift(delta: np.ndarray, c2w: np.ndarray) -> float:
    """How far a world correction moves the camera centre of `c2w` (metres)."""
    return float(np.linalg.norm(delta[:3, :3] @ c2w[:3, 3] + delta[:3, 3] - c2w[:3, 3]))


def continuous_poses(poses: np.ndarray, spans: list[tuple[int, int]],
                     corrections: np.ndarray) -> np.ndarray:  # fmt: skip
    """Camera poses (N, 4, 4) whose loop correction varies continuously along the trajectory.

    The frames ``spans[k]`` (first, last) of submap k were all moved by one rigid correction
    ``corrections[k]`` (from the frame the tracked chain of poses lives in, left-multiplied), so
    where two neighbours' corrections differ, the whole difference lands between two frames: a
    jump of up to centimetres that no camera made. A pose graph over every frame would spread
    it along the chain of frames; this does so directly: the correction at a frame is
    interpolated between the submaps' centre frames (linear in translation, slerp in rotation)
    and held constant before the first centre and after the last, so each submap keeps about
    its own correction on average and no frame pair carries a step.
    """
    if len(corrections) < 2:
        return poses
    centres = np.array([(first + last) / 2 for first, last in spans], np.float64)
    frames = np.clip(np.arange(len(poses), dtype=np.float64), centres[0], centres[-1])
    quats = np.stack([matrix_to_quat_xyzw(c[:3, :3]) for c in corrections])
    smooth = interpolate_poses(centres, corrections[:, :3, 3], quats, frames, np.inf)
    submap_of = np.zeros(len(poses), np.int64)
    for k, (first, last) in enumerate(spans):
        submap_of[first : last + 1] = k
    chain = np.linalg.inv(corrections[submap_of]) @ poses  # the tracked chain, uncorrected
    return smooth @ chain
