"""Submaps: when the camera has moved far enough to start a new one, and a frozen submap on disk
(its file and its record; LoopSplat's submaps: a new one after 0.5 m or 50°)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from bgs_batch.atomic import save_torch
from bgs_batch.config import SubmapConfig
from bgs_batch.geometry import euler_zyx_deg, rotation_angle_deg


def exceeds_motion(first_c2w: np.ndarray, c2w: np.ndarray, cfg: SubmapConfig) -> bool:
    """True when the camera moved more than the thresholds from the submap's first frame
    (the motion expressed in that frame's camera coordinates)."""
    rel = np.linalg.inv(first_c2w) @ c2w
    if cfg.rotation_measure == "angle":
        angle = rotation_angle_deg(rel[:3, :3])
    else:  # LoopSplat: any of roll, pitch, yaw
        angle = float(np.abs(euler_zyx_deg(rel[:3, :3])).max())
    return bool(np.linalg.norm(rel[:3, 3]) > cfg.max_translation or angle > cfg.max_rotation_deg)


@dataclass
class SubmapRecord:
    """A finished, frozen submap on disk."""

    index: int
    path: str
    first_frame: int
    last_frame: int
    keyframes: list[int]
    gaussians: int


def freeze_submap(path: Path, index: int, params: dict[str, torch.Tensor], keyframes: list[int],
                  first_frame: int, last_frame: int) -> SubmapRecord:  # fmt: skip
    """Write a finished submap's Gaussians and keyframes to `path` (atomic); its record."""
    path.parent.mkdir(parents=True, exist_ok=True)
    save_torch({"params": params, "keyframes": torch.tensor(keyframes),
                "first_frame": first_frame}, path)  # fmt: skip
    return SubmapRecord(index, str(path), first_frame, last_frame, keyframes,
                        len(params["means"]))  # fmt: skip


def submap_params(record: SubmapRecord) -> dict[str, torch.Tensor]:
    """The Gaussians of a frozen submap as corrected and refined (its file's ``params``)."""
    return torch.load(record.path, weights_only=True)["params"]
