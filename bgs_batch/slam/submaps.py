"""Submaps: when the camera has moved far enough to start a new one, and the record of a frozen
submap on disk (LoopSplat's submaps: a new one after 0.5 m or 50°)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
