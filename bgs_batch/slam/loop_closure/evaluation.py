"""After a run: the loops a job's log reports, checked against ground truth (tests, bench).

Never used while running (SLAM does not read ground truth). A loop between two submaps is
true when some frame of one was taken near some frame of the other, looking the same way.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import numpy as np

TRUE_LOOP_DISTANCE_M = 0.3  # camera centres at most this far apart ...
TRUE_LOOP_ANGLE_DEG = 30.0  # ... and viewing directions at most this different


def accepted_loops(events: list[dict[str, Any]]) -> list[tuple[int, int, int]]:
    """(frame of the event, query submap, candidate submap) of every loop edge in the log."""
    return [(e["frame"], e["loop_closure"]["query"], loop["submap"])
            for e in events if "loop_closure" in e
            for loop in e["loop_closure"]["loops"]]  # fmt: skip


def submap_frames(events: list[dict[str, Any]]) -> dict[int, list[int]]:
    """The frames of every submap, from the log's per-frame ``submap`` field."""
    out: dict[int, list[int]] = defaultdict(list)
    for e in events:
        out[e["submap"]].append(e["frame"])
    return dict(out)


def is_true_loop(gt_c2w: np.ndarray, frames_a: list[int], frames_b: list[int],
                 max_distance: float = TRUE_LOOP_DISTANCE_M,
                 max_angle_deg: float = TRUE_LOOP_ANGLE_DEG) -> bool:  # fmt: skip
    """Whether ground truth has a frame of `frames_a` near one of `frames_b` (both views)."""
    a, b = gt_c2w[frames_a], gt_c2w[frames_b]
    dist = np.linalg.norm(a[:, None, :3, 3] - b[None, :, :3, 3], axis=2)
    cos = np.einsum("ai,bi->ab", a[:, :3, 2], b[:, :3, 2])  # optical axes
    return bool(np.any((dist <= max_distance) & (cos >= np.cos(np.radians(max_angle_deg)))))
