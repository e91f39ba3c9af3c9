"""The colour camera's offset from the depth camera, estimated from the frames and undone.

An RGB-D camera whose colour and depth images come from two sensors shows each surface point at
different pixels of the two images unless the driver registers them. When it does not, or does
it with a wrong calibration, the colour a map stores for a point is another point's, and the
photometric term of tracking pulls the pose towards the colour camera's. Hand-held motion makes
the offset visible: frame k's colour, sampled through its depth at a point, must equal frame j's
colour sampled at the same point moved by the camera's motion, and a wrong offset breaks this
differently for every motion. So (docs/method.md §6):

1. **Poses.** The first ``frames`` frames are registered each to the one before by the
   point-to-plane term alone (`registration.register` without its photometric term: the colour
   must not move them), at the estimator's resolution, the rows moved to one instant by the
   rolling-shutter readout the run uses (`rolling_shutter`);
2. **Pairs.** Frames ``pair_gap`` apart, every ``pair_stride`` frames;
3. **Fit.** The colour camera's rotation (a rotation vector) and focal ratio that make the pairs'
   colours agree best, by Nelder-Mead on the Huber cost of their intensity differences, over all
   pairs and over each pair alone; the spread of the pairs' own fits gives standard errors.
4. **Gate.** A fit beyond ``max_rotation_deg`` or ``max_focal_change`` is no mounting offset
   (the fit ran to views that hide most samples) and no estimate. The estimate is kept where
   the pairs agree (standard errors below ``max_standard_error_deg`` and
   ``max_focal_standard_error``) and it stands out of their spread (above ``significance``
   standard errors and ``min_rotation_deg`` / ``min_focal_change``); otherwise the colour
   images stay as they are.

The shift between the two sensors (millimetres) is not modelled: at the distances of a room it
moves a pixel or two, where a degree of rotation moves ten.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from bgs_batch.config import Config
from bgs_batch.slam.readout import FrameViews, chain_poses, chain_views, readout_motion_at
from bgs_batch.slam.tracking.registration import View
from bgs_batch.store import Frame

PARAMETERS = 4  # three rotation angles (°) and the focal ratio's logarithm
INTENSITY_HUBER = 0.05  # intensity in [0, 1]: a residual beyond this weighs linearly
PAIR_PIXEL_STEP = 2  # every second pixel of a pair's first frame in each direction
REMAP_ROW = 512  # cv2.remap takes maps below 32767 a side: samples are laid out in rows of this
OUTSIDE = -1e4  # a sample position outside every image
# the simplex's first steps: one degree about each axis and 2 % of focal length
SIMPLEX_STEPS = (1.0, 1.0, 1.0, 0.02)
ANGLE_TOLERANCE_DEG = 0.01
MAX_EVALUATIONS = 400


@dataclass(frozen=True)
class ColourOffsetEstimate:
    """What `estimate_colour_offset` found: ``rotation_deg`` None when the frames cannot tell
    or show no offset (the colour images are then used as they are)."""

    rotation_deg: tuple[float, float, float] | None
    focal_ratio: float | None
    standard_error_deg: float | None  # the largest of the three angles'
    focal_standard_error: float | None
    frames: int
    pairs: list[tuple[int, int]]
    reason: str  # one line for the log and `bgs status`

    def as_dict(self) -> dict:
        """For JSON (``colour_offset.json``, ``summary.json``)."""
        rotation = None if self.rotation_deg is None else list(self.rotation_deg)
        return dataclasses.asdict(self) | {"pairs": [list(p) for p in self.pairs],
                                           "rotation_deg": rotation}  # fmt: skip

    @staticmethod
    def from_dict(data: dict) -> ColourOffsetEstimate:
        rotation = data["rotation_deg"]
        return ColourOffsetEstimate(**dict(data, pairs=[tuple(p) for p in data["pairs"]],
                                           rotation_deg=None if rotation is None
                                           else tuple(rotation)))  # fmt: skip

    def applied_to(self, cfg: Config) -> Config:
        """`cfg` with this estimate as its colour offset (unchanged without one)."""
        if self.rotation_deg is None:
            return cfg
        x, y, z = self.rotation_deg
        offset = dataclasses.replace(cfg.colour_offset, rotation_x_deg=x, rotation_y_deg=y,
                                     rotation_z_deg=z, focal_ratio=self.focal_ratio)  # fmt: skip
        return dataclasses.replace(cfg, colour_offset=offset)


def estimate_colour_offset(read: Callable[[int], Frame], timestamps: np.ndarray,
                           intrinsics: np.ndarray, cfg: Config
                           ) -> ColourOffsetEstimate:  # fmt: skip
    """Estimate the colour camera's rotation and focal ratio from the first frames (module
    docstring); `read(i)` gives frame i, `timestamps` its time stamps (s), `cfg` the run's
    settings with its readout resolved."""
    est = cfg.colour_offset
    n = min(est.frames, len(timestamps))
    pairs = [(k, k + est.pair_gap) for k in range(1, n - est.pair_gap - 1, est.pair_stride)]
    if len(pairs) < est.min_pairs:
        return _none(n, pairs, f"{n} frames: too few to compare the colour and depth images "
                               f"({len(pairs)} of {est.min_pairs} frame pairs)")  # fmt: skip
    views = _rectified_views(read, timestamps, intrinsics, cfg, n)
    poses = chain_views(views, cfg, photometric=False)
    problems = [_PairCost(views[k], views[j], np.linalg.inv(poses[j]) @ poses[k])
                for k, j in pairs]  # fmt: skip
    together = _fit(problems)
    each = np.array([_fit([p]) for p in problems])
    error = each.std(0) / np.sqrt(len(each))
    rotation_error, focal_error = float(error[:3].max()), float(np.exp(error[3]) - 1)
    rotation, focal = together[:3], float(np.exp(together[3]))
    summary = (f"({', '.join(f'{a:.2f}' for a in rotation)})° ± {rotation_error:.2f}°, focal "
               f"ratio {focal:.4f} ± {focal_error:.4f}, from {len(pairs)} frame pairs of the "
               f"first {n} frames")  # fmt: skip
    found = ColourOffsetEstimate(tuple(float(a) for a in rotation), focal, rotation_error,
                                 focal_error, n, pairs, "")  # fmt: skip
    if np.abs(rotation).max() > est.max_rotation_deg or abs(focal - 1) > est.max_focal_change:
        return dataclasses.replace(found, rotation_deg=None, focal_ratio=None, reason=(
            f"colour camera offset not determined: the best fit is no mounting offset (beyond "
            f"±{est.max_rotation_deg:g}° or ±{100 * est.max_focal_change:g} % focal length: "
            f"{summary}); the colour images are used as they are"))  # fmt: skip
    if rotation_error > est.max_standard_error_deg or focal_error > est.max_focal_standard_error:
        return dataclasses.replace(found, rotation_deg=None, focal_ratio=None, reason=(
            f"colour camera offset not determined: the frame pairs disagree ({summary}); the "
            "colour images are used as they are"))  # fmt: skip
    turned = np.abs(rotation).max() > max(est.min_rotation_deg, est.significance * rotation_error)
    zoomed = abs(focal - 1) > max(est.min_focal_change, est.significance * focal_error)
    if not (turned or zoomed):
        return dataclasses.replace(found, rotation_deg=None, focal_ratio=None, reason=(
            f"the colour camera sits on the depth camera ({summary})"))  # fmt: skip
    return dataclasses.replace(found, reason=f"colour camera offset {summary}")


def _none(frames: int, pairs: list[tuple[int, int]], reason: str) -> ColourOffsetEstimate:
    return ColourOffsetEstimate(None, None, None, None, frames, pairs, reason)


def _rectified_views(read: Callable[[int], Frame], timestamps: np.ndarray,
                     intrinsics: np.ndarray, cfg: Config, n: int) -> list[View]:  # fmt: skip
    """The first n frames as registration views at the estimator's resolution, their rows moved
    to one instant at the run's readouts (colour and depth, each its own) by the velocities of a
    first, unrectified chain: a depth image left as read beside a rectified colour image would
    look like a colour camera turned away from the depth camera."""
    level = FrameViews(read, intrinsics, cfg, cfg.colour_offset.min_width)
    readouts = (cfg.rolling_shutter_readout or 0.0, cfg.depth_rolling_shutter_readout or 0.0)
    if not any(readouts):
        return [level.view(read(i)) for i in range(n)]
    poses = chain_poses(level, n, cfg, photometric=False)

    def motions(i: int) -> tuple[np.ndarray | None, np.ndarray | None]:
        if not 0 < i < n - 1:
            return None, None
        colour = readout_motion_at(poses, timestamps, i, readouts[0])
        depth = readout_motion_at(poses, timestamps, i, readouts[1])
        return colour, depth

    return [level.view(read(i), *motions(i)) for i in range(n)]


class _PairCost:
    """The Huber cost of two frames' colours sampled at the same surface points through a
    candidate colour camera: the points of the first frame's depth (every `PAIR_PIXEL_STEP`-th
    pixel), and the same points moved into the second frame."""

    def __init__(self, first: View, second: View, second_from_first: np.ndarray) -> None:
        camera = first.camera
        depth = first.depth.numpy()
        v, u = np.mgrid[0:depth.shape[0]:PAIR_PIXEL_STEP, 0:depth.shape[1]:PAIR_PIXEL_STEP]
        z = depth[v, u]
        valid = z > 0
        u, v, z = u[valid], v[valid], z[valid]
        self.points = np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z,
                                z])  # fmt: skip
        self.moved = second_from_first[:3, :3] @ self.points + second_from_first[:3, 3:]
        self.images = (first.gray.numpy().astype(np.float32),
                       second.gray.numpy().astype(np.float32))  # fmt: skip
        self.camera = camera

    def __call__(self, rotation: np.ndarray, focal_ratio: float) -> tuple[float, int]:
        """(summed Huber cost, samples) of the candidate colour camera."""
        a = self._sample(self.images[0], rotation @ self.points, focal_ratio)
        b = self._sample(self.images[1], rotation @ self.moved, focal_ratio)
        residual = a - b
        residual = np.abs(residual[np.isfinite(residual)])
        cost = np.where(residual < INTENSITY_HUBER, 0.5 * residual**2,
                        INTENSITY_HUBER * (residual - 0.5 * INTENSITY_HUBER))  # fmt: skip
        return float(cost.sum()), residual.size

    def _sample(self, image: np.ndarray, points: np.ndarray, focal_ratio: float) -> np.ndarray:
        c = self.camera
        with np.errstate(divide="ignore", invalid="ignore"):
            u = focal_ratio * c.fx * points[0] / points[2] + c.cx
            v = focal_ratio * c.fy * points[1] / points[2] + c.cy
        count = u.size
        pad = (-count) % REMAP_ROW

        def rows(x: np.ndarray) -> np.ndarray:
            x = np.where(np.isfinite(x), x, OUTSIDE).astype(np.float32)
            return np.pad(x, (0, pad), constant_values=OUTSIDE).reshape(-1, REMAP_ROW)

        sampled = cv2.remap(image, rows(u), rows(v), cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)  # fmt: skip
        return sampled.reshape(-1)[:count]


def _fit(problems: list[_PairCost]) -> np.ndarray:
    """The colour camera (rotation vector in degrees, log focal ratio) that makes the pairs'
    colours agree best: Nelder-Mead from the depth camera itself."""

    def cost(theta: np.ndarray) -> float:
        rotation = Rotation.from_rotvec(np.radians(theta[:3])).as_matrix()
        total, count = 0.0, 0
        for problem in problems:
            c, m = problem(rotation, float(np.exp(theta[3])))
            total, count = total + c, count + m
        return total / max(count, 1)

    simplex = np.vstack([np.zeros(PARAMETERS), np.diag(SIMPLEX_STEPS)])
    result = minimize(cost, np.zeros(PARAMETERS), method="Nelder-Mead",
                      options={"xatol": ANGLE_TOLERANCE_DEG, "fatol": 0.0,
                               "maxiter": MAX_EVALUATIONS, "initial_simplex": simplex})  # fmt: skip
    return result.x
