"""The camera's motion as the SLAM knows it after each frame (constant velocity), and the motions
each frame was prepared with.

From the last two poses, `CameraMotion` gives the next frame's start (`initial_pose`), how far the
camera moved between its depth and colour images (`next_depth_motion`, `depth_timing`) and over
its rows' readout (`next_readout_motions`, `rolling_shutter`). It keeps, per frame, the motions
the frame was prepared with (`keep`, `of_frame`), so that the end of a run, a resumed job and the
exports prepare a frame re-read from the store exactly as it was tracked.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from bgs_batch.config import Config, separate_readouts
from bgs_batch.slam.depth_timing import depth_motion, interval_motion
from bgs_batch.slam.tracking import constant_velocity
from bgs_batch.store import Frame

# the camera's motion over a frame's colour readout, and over its depth readout when the two
# are read out apart (`separate_readouts`); None: nothing to move
ReadoutMotions = tuple[np.ndarray | None, np.ndarray | None]
MOTION_KEYS = ("depth_motions", "readout_motions", "depth_readout_motions")


class CameraMotion:
    """Constant-velocity motion from the poses so far (`poses`, `timestamps`: the frames
    tracked so far, camera-to-world, s) and the motions each frame was prepared with."""

    def __init__(self, cfg: Config) -> None:
        self.cfg = cfg
        # per frame, the warp that moved its depth image to its colour image's time
        self.depth_motions: dict[int, np.ndarray] = {}
        # per frame, the camera's motion over its rows' readout (`rolling_shutter`) ...
        self.readout_motions: dict[int, np.ndarray] = {}
        # ... and over its depth image's, when the two are read out apart (`separate_readouts`)
        self.depth_readout_motions: dict[int, np.ndarray] = {}
        # the previous pose moved with an injected drift: the next constant-velocity step's
        # reference, so that the drift moves the new submap rigidly instead of adding a jump to
        # the velocity (None: the previous pose itself)
        self.drifted_prev: np.ndarray | None = None

    def initial_pose(self, poses: list[np.ndarray]) -> torch.Tensor:
        """The next frame's constant-velocity start (camera-to-world). After an injected drift it
        starts from the drifted reference (the drift moved the new submap, not the camera's
        velocity) and consumes it: call once per tracked frame."""
        prev2 = poses[-2] if len(poses) > 1 else None
        if self.drifted_prev is not None:
            prev2, self.drifted_prev = self.drifted_prev, None
        return constant_velocity(torch.from_numpy(poses[-1]),
                                 None if prev2 is None else torch.from_numpy(prev2))  # fmt: skip

    def drifted(self, before: np.ndarray, after: np.ndarray, previous: np.ndarray) -> None:
        """The current pose was moved from `before` to `after` by an injected drift: the next
        step's reference is the `previous` pose moved with it."""
        self.drifted_prev = after @ np.linalg.inv(before) @ previous

    def next_depth_motion(self, frame: Frame, poses: list[np.ndarray], timestamps: list[float]
                     ) -> np.ndarray | None:  # fmt: skip
        """The warp of `frame`'s depth image to its colour image's time, from the velocity of
        the last frame interval and the stamps' gap less ``depth_time_lag``
        (``align_depth_time``; None: nothing to move)."""
        cfg = self.cfg
        if not cfg.align_depth_time or frame.depth_timestamp is None or len(timestamps) < 2:
            return None
        return depth_motion(self._before_last(poses), poses[-1], timestamps[-1] - timestamps[-2],
                            frame.depth_time_offset - cfg.depth_time_lag)  # fmt: skip

    def readouts(self) -> tuple[float, float]:
        """The colour and the depth image's readouts (s; None: no store resolved them, 0); the
        depth's only when it is read out apart (`separate_readouts`), else 0."""
        cfg = self.cfg
        depth = cfg.depth_rolling_shutter_readout if separate_readouts(cfg) else None
        return cfg.rolling_shutter_readout or 0.0, depth or 0.0

    def readout_active(self) -> bool:
        return max(self.readouts()) > 0

    def next_readout_motions(self, poses: list[np.ndarray], timestamps: list[float]
                        ) -> ReadoutMotions:  # fmt: skip
        """The camera's motion over the next frame's colour readout and, when read out apart,
        its depth readout, at the last interval's velocity (None: a global shutter, or no
        velocity yet)."""
        if not self.readout_active() or len(timestamps) < 2:
            return None, None
        interval = timestamps[-1] - timestamps[-2]
        if not interval > 0:
            return None, None
        before = self._before_last(poses)
        colour, depth = (interval_motion(before, poses[-1], readout / interval)
                         if readout > 0 else None for readout in self.readouts())  # fmt: skip
        return colour, depth

    def _before_last(self, poses: list[np.ndarray]) -> np.ndarray:
        return poses[-2] if self.drifted_prev is None else self.drifted_prev

    def keep(self, index: int, depth: np.ndarray | None = None,
             readouts: ReadoutMotions = (None, None)) -> None:  # fmt: skip
        """Record the motions frame `index` was prepared with (None: nothing moved)."""
        for kept, motion in zip((self.depth_motions, self.readout_motions,
                                 self.depth_readout_motions), (depth, *readouts),
                                strict=True):  # fmt: skip
            if motion is not None:
                kept[index] = motion

    def of_frame(self, index: int) -> tuple[np.ndarray | None, ReadoutMotions]:
        """The depth motion and readout motions frame `index` was prepared with."""
        return self.depth_motions.get(index), (self.readout_motions.get(index),
                                               self.depth_readout_motions.get(index))

    def state_dict(self) -> dict[str, Any]:
        state: dict[str, Any] = {
            key: {i: torch.from_numpy(m) for i, m in getattr(self, key).items()}
            for key in MOTION_KEYS}  # fmt: skip
        state["drifted_prev"] = (None if self.drifted_prev is None
                                 else torch.from_numpy(self.drifted_prev))  # fmt: skip
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for key in MOTION_KEYS:
            setattr(self, key, {int(i): np.ascontiguousarray(m.numpy())
                                for i, m in state[key].items()})  # fmt: skip
        drifted = state["drifted_prev"]
        self.drifted_prev = None if drifted is None else np.ascontiguousarray(drifted.numpy())
