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
from bgs_batch.geometry import matrix_to_quat_xyzw
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
