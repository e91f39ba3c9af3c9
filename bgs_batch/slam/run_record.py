"""What a run records as it goes: the seconds each stage took (`Timings`, summed over the run
and per frame in ``log.jsonl``) and how a frame's pose and motions are written into its log
event (`logged_rows`, `log_motions`), from which the exports prepare the frame again."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from bgs_batch.slam.camera_motion import ReadoutMotions


@dataclass
class Timings:
    """Seconds spent per stage, summed over the run."""

    tracking: float = 0.0
    mapping: float = 0.0
    sensor: float = 0.0
    submaps: float = 0.0
    loop_closure: float = 0.0  # features, detection, registration, pose graph
    refinement: float = 0.0  # uncertainty refinement of the frozen submaps at the end
    global_map: float = 0.0  # the global stage: merge and optimisation (`global_map`)
    estimates: float = 0.0  # the readout and colour offset estimated from the first frames

    def add(self, stage: str, seconds: float) -> None:
        setattr(self, stage, getattr(self, stage) + seconds)

    @contextmanager
    def measure(self, stage: str) -> Iterator[None]:
        """Add the wall time of the ``with`` body to `stage`."""
        start = time.perf_counter()
        yield
        self.add(stage, time.perf_counter() - start)


def logged_rows(transform: np.ndarray) -> list[float]:
    """A 4×4 rigid transform as ``log.jsonl`` holds it: its top three rows (read back by
    `outputs.jobfiles`)."""
    return [float(x) for x in transform[:3].ravel()]


def log_motions(event: dict[str, Any], prefix: str, motions: dict[str, np.ndarray | None],
                 readouts: ReadoutMotions) -> None:  # fmt: skip
    """Put the motions that move a frame's images into its log event (for the exports)."""
    named = {**motions, "readout_motion": readouts[0], "depth_readout_motion": readouts[1]}
    for key, value in named.items():
        if value is not None:
            event[prefix + key] = logged_rows(value)
