"""Predictive-surprise keyframe selection (paper §III-C, §III-D; authors' rule, docs/method.md §7).

A frame is a keyframe when its colour or depth surprise exceeds K, when it is the first frame of
a submap, or when N frames have passed since the last keyframe (the periodic fallback). In mode
``every`` all frames are keyframes (the LoopSplat baseline).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from bgs_batch.config import KeyframeConfig


@dataclass(frozen=True)
class KeyframeDecision:
    """One frame's decision, with both scores and the reason (logged per frame)."""

    frame: int
    keyframe: bool
    reason: str  # first-of-submap | surprise-color | surprise-depth | fallback | every | skip
    score_color: float | None
    score_depth: float | None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class KeyframeSelector:
    """Stateful selector: remembers how many frames passed since the last keyframe."""

    def __init__(self, cfg: KeyframeConfig) -> None:
        self.cfg = cfg
        self.since_last = 0

    def decide(
        self,
        frame: int,
        score_color: float | None,
        score_depth: float | None,
        first_of_submap: bool,
    ) -> KeyframeDecision:
        """Decide for `frame` given its surprise scores (None when the frame was not tracked)."""
        self.since_last += 1
        k = self.cfg.threshold
        if first_of_submap:
            reason = "first-of-submap"
        elif self.cfg.mode == "every":
            reason = "every"
        elif score_color is not None and score_color > k:
            reason = "surprise-color"
        elif score_depth is not None and score_depth > k:
            reason = "surprise-depth"
        elif self.since_last >= self.cfg.max_gap:
            reason = "fallback"
        else:
            reason = "skip"
        keyframe = reason != "skip"
        if keyframe:
            self.since_last = 0
        return KeyframeDecision(frame, keyframe, reason, score_color, score_depth)

    def state_dict(self) -> dict[str, int]:
        return {"since_last": self.since_last}

    def load_state_dict(self, state: dict[str, int]) -> None:
        self.since_last = int(state["since_last"])
