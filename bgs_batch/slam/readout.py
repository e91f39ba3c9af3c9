"""The rolling-shutter readout estimated from the frames, for a camera the converter does not know.

A rolling shutter reads row y at ``t + (y/H − ½)·r``. Turning at angular velocity ω, the
camera sees the scene sheared by about ``f·ω·r`` pixels over the image height. Two frames
turning at the same velocity are sheared alike, so registering them tells nothing about r;
two frames turning at different velocities are sheared differently, and no rigid motion
explains both unless each is first rectified with the right r (`rolling_shutter.rectify`). So:

1. **Velocities.** The first ``frames`` frames are registered, each to the one before, as
   global-shutter images at the largest integer downscale that leaves ``min_width`` pixels
   (the warm start's `registration.register`), chaining
   a trajectory; each frame's angular velocity is the central difference of its neighbours.
2. **Pairs.** Frames up to ``max_gap`` apart whose angular velocities differ by at least
   ``min_turn_change`` rad/s, the most different first, no frame in two pairs.
3. **Costs.** For each of ``candidates`` readouts from 0 to one frame interval, both frames of
   a pair are rectified at that readout (with their own velocities) and registered; the cost is
   the mean Huber loss of the geometric and photometric residuals at the scales of the
   unrectified pair, so that every candidate is scored on the same scale.
4. **Estimate.** The minimum of the pairs' summed costs (each normalised by its own minimum),
   refined by a parabola through its neighbours. Its standard error is the spread of the
   pairs' own minima over √pairs. Too few pairs, or an error above ``max_standard_error`` of a
   frame interval, is no estimate: the camera did not turn enough to tell, and the run keeps
   a global shutter.

The estimate is made once, before the first frame is tracked, and kept for the whole run
(docs/method.md §6).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from bgs_batch.config import Config, ReadoutEstimationConfig
from bgs_batch.slam.depth_timing import interval_motion
from bgs_batch.slam.frames import downsample, prepare_frame
from bgs_batch.slam.tracking.registration import HUBER_K, MAD_TO_SIGMA, View, register, residuals
from bgs_batch.store import Frame

SCALE_FLOOR = 1e-9  # a residual scale of exactly zero (a perfect synthetic pair) divides nothing


@dataclass(frozen=True)
class ReadoutEstimate:
    """What `estimate_readout` found: ``seconds`` None when the frames cannot tell."""

    seconds: float | None
    standard_error: float | None  # s
    frames: int  # frames searched for turns, from the first
    pairs: list[tuple[int, int]]  # the frame pairs scored
    pair_minima: list[float]  # s, each pair's own best readout
    reason: str  # one line for the log and `bgs status`

    def as_dict(self) -> dict:
        """For JSON (``readout.json``, ``summary.json``): pairs as lists."""
        return dataclasses.asdict(self) | {"pairs": [list(p) for p in self.pairs]}

    @staticmethod
    def from_dict(data: dict) -> ReadoutEstimate:
        data = dict(data, pairs=[tuple(p) for p in data["pairs"]])
        return ReadoutEstimate(**data)


def estimate_readout(read: Callable[[int], Frame], timestamps: np.ndarray,
                     intrinsics: np.ndarray, cfg: Config) -> ReadoutEstimate:  # fmt: skip
    """Estimate the rolling-shutter readout (s) from the first frames of a sequence (module
    docstring); `read(i)` gives frame i, `timestamps` its time stamps (s). The readouts `cfg`
    leaves open (None) are estimated: both images' as one, or the colour image's alone when
    the depth image's is known (``depth_rolling_shutter_readout``)."""
    est = cfg.readout_estimation
    n = min(est.frames, len(timestamps))
    if n < 3:
        return _unknown(n, f"{n} frames: too few to see the camera turn")
    level = FrameViews(read, intrinsics, dataclasses.replace(cfg, rolling_shutter_readout=None),
                    est.min_width)  # fmt: skip
    poses = chain_poses(level, n, cfg)
    velocities = _angular_velocities(poses, timestamps[:n])
    pairs = _informative_pairs(velocities, est)
    if len(pairs) < est.min_pairs:
        return _unknown(n, f"the camera did not turn enough in the first {n} frames to tell "
                           f"({len(pairs)} of {est.min_pairs} frame pairs needed); kept a "
                           "global shutter")  # fmt: skip
    interval = float(np.median(np.diff(timestamps[:n])))
    candidates = np.linspace(0.0, interval, est.candidates)
    curves = [_pair_costs(level, poses, timestamps, k, j, candidates, cfg) for k, j in pairs]
    total = np.mean([c / c.min() for c in curves], axis=0)
    seconds = _parabola_minimum(candidates, total)
    if total.max() - total.min() < est.min_contrast:
        return ReadoutEstimate(None, None, n, pairs, [],
                               f"readout not determined: the frames' agreement changes by "
                               f"{100 * (total.max() - total.min()):.0f} % over the readouts "
                               f"(at least {100 * est.min_contrast:.0f} % needed); kept a global "
                               "shutter")  # fmt: skip
    minima = [_parabola_minimum(candidates, c) for c in curves]
    error = float(np.std(minima) / np.sqrt(len(minima)))
    if error > est.max_standard_error * interval:
        return ReadoutEstimate(None, error, n, pairs, minima,
                               f"readout not determined: the frame pairs disagree (standard "
                               f"error {1000 * error:.1f} ms); kept a global shutter")  # fmt: skip
    return ReadoutEstimate(seconds, error, n, pairs, minima,
                           f"rolling-shutter readout {1000 * seconds:.1f} ± {1000 * error:.1f} ms, "
                           f"estimated from {len(pairs)} frame pairs of the first {n} frames")


def _unknown(frames: int, reason: str) -> ReadoutEstimate:
    return ReadoutEstimate(None, None, frames, [], [], reason)


class FrameViews:
    """Frames as registration views at the estimator's resolution, optionally rectified."""

    def __init__(self, read: Callable[[int], Frame], intrinsics: np.ndarray, cfg: Config,
                 min_width: int) -> None:  # fmt: skip
        self.read, self.intrinsics, self.cfg, self.min_width = read, intrinsics, cfg, min_width

    def view(self, frame: Frame, readout_motion: np.ndarray | None = None,
             depth_readout_motion: np.ndarray | None = None) -> View:  # fmt: skip
        full, _ = prepare_frame(frame, self.intrinsics, self.cfg, None, readout_motion,
                                depth_readout_motion)  # fmt: skip
        level = downsample(full, max(1, full.camera.width // self.min_width))
        return View.of(level.rgb, level.depth, level.camera)


def chain_poses(level: FrameViews, n: int, cfg: Config, photometric: bool = True) -> np.ndarray:
    """Camera-to-world poses [n, 4, 4] of the first n frames, each registered to the one before
    (streamed: two frames in memory); by geometry alone when not `photometric`."""
    return chain_views((level.view(level.read(i)) for i in range(n)), cfg, photometric)


def chain_views(views: Iterable[View], cfg: Config, photometric: bool = True) -> np.ndarray:
    """Camera-to-world poses [n, 4, 4] of a sequence of views, each registered to the one
    before (`chain_poses`), the first at the identity."""
    poses = [np.eye(4)]
    relative = torch.eye(4, dtype=torch.float64)
    previous = None
    for current in views:
        if previous is not None:
            relative = register(current, previous, cfg.registration, relative,
                                photometric).transform  # fmt: skip
            poses.append(poses[-1] @ relative.numpy())
        previous = current
    return np.stack(poses)


def _angular_velocities(poses: np.ndarray, timestamps: np.ndarray) -> np.ndarray:
    """Angular velocity (rad/s, camera axes) at each frame by central differences [n, 3]; the
    first and last frames, which have one neighbour, get NaN."""
    velocities = np.full((len(poses), 3), np.nan)
    for i in range(1, len(poses) - 1):
        relative = np.linalg.inv(poses[i - 1]) @ poses[i + 1]
        rotvec = Rotation.from_matrix(relative[:3, :3]).as_rotvec()
        velocities[i] = rotvec / (timestamps[i + 1] - timestamps[i - 1])
    return velocities


def _informative_pairs(velocities: np.ndarray, est: ReadoutEstimationConfig
                       ) -> list[tuple[int, int]]:  # fmt: skip
    """Frame pairs (k, j), 2 ≤ j − k ≤ ``max_gap``, whose angular velocities differ by at least
    ``min_turn_change``: the most different first, each frame in one pair at most."""
    scored = []
    for j in range(len(velocities)):
        for k in range(max(0, j - est.max_gap), j - 1):
            change = float(np.linalg.norm(velocities[j] - velocities[k]))
            if change >= est.min_turn_change:  # False for NaN: an end frame
                scored.append((-change, k, j))
    pairs: list[tuple[int, int]] = []
    used: set[int] = set()
    for _, k, j in sorted(scored):
        if k not in used and j not in used:
            pairs.append((k, j))
            used |= {k, j}
            if len(pairs) == est.pairs:
                break
    return pairs


def _pair_costs(level: FrameViews, poses: np.ndarray, timestamps: np.ndarray, k: int, j: int,
                candidates: np.ndarray, cfg: Config) -> np.ndarray:  # fmt: skip
    """The registration cost of frames j and k, both rectified at each candidate readout."""
    initial = torch.from_numpy(np.linalg.inv(poses[k]) @ poses[j])
    frame_j, frame_k = level.read(j), level.read(k)
    depth = level.cfg.depth_rolling_shutter_readout  # known, or None: the candidate's
    depth_motions = [None if depth is None else readout_motion_at(poses, timestamps, i, depth)
                     for i in (j, k)]  # fmt: skip
    costs, scales = [], None
    for readout in candidates:
        source = level.view(frame_j, readout_motion_at(poses, timestamps, j, readout),
                            depth_motions[0])  # fmt: skip
        target = level.view(frame_k, readout_motion_at(poses, timestamps, k, readout),
                            depth_motions[1])  # fmt: skip
        transform = register(source, target, cfg.registration, initial).transform
        geometric, photometric = residuals(source, target, cfg.registration, transform)
        if scales is None:  # the unrectified pair's, for every candidate
            scales = [max(MAD_TO_SIGMA * float(np.median(np.abs(r))), SCALE_FLOOR) if r.size
                      else 1.0 for r in (geometric, photometric)]  # fmt: skip
        terms = zip((geometric, photometric), scales, strict=True)
        costs.append(sum(_huber(r / s).mean() if r.size else np.inf for r, s in terms))
    return np.array(costs)


def readout_motion_at(poses: np.ndarray, timestamps: np.ndarray, i: int, readout: float
                    ) -> np.ndarray | None:  # fmt: skip
    """The camera's motion over frame i's readout at its central-difference velocity."""
    if readout == 0:
        return None
    span = timestamps[i + 1] - timestamps[i - 1]
    return interval_motion(poses[i - 1], poses[i + 1], readout / span)


def _huber(scaled: np.ndarray) -> np.ndarray:
    a = np.abs(scaled)
    return np.where(a < HUBER_K, 0.5 * a * a, HUBER_K * (a - 0.5 * HUBER_K))


def _parabola_minimum(x: np.ndarray, y: np.ndarray) -> float:
    """The minimum of y over the evenly spaced x, refined by the parabola through it and its
    neighbours (the grid's end when the minimum is there)."""
    best = int(np.argmin(y))
    if best in (0, len(y) - 1):
        return float(x[best])
    before, at, after = y[best - 1], y[best], y[best + 1]
    curvature = before - 2 * at + after
    offset = 0.5 * (before - after) / curvature if curvature > 0 else 0.0
    return float(x[best] + offset * (x[1] - x[0]))
