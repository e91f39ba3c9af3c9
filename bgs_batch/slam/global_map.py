"""The global stage at the end of a run: one map from the corrected submaps, optimised on the
run's frames at the reported poses (docs/method.md §8c).

Each submap was fitted to its own keyframes only. Concatenated, overlapping submaps interleave
two layers of the same surface, each right from its own views, and a user who opens the merged
file sees doubled edges and speckles. A batch run has every frame and its final pose before it
writes anything, so it can do what the reference systems do in their evaluation scripts:

1. split (`split_frames`): every N-th frame that is not a keyframe is held out, to score the
   map on views it never trained on; the rest are the training frames;
2. merge (`Ownership`): where two submaps show the same surface, the submap that saw it
   nearer the centre of one of its keyframes keeps its Gaussians there;
3. optimise (`GlobalMapStage`): the merged map is fitted at the poses of ``trajectory.txt``
   to the training frames, streamed from the store in a seeded random order, at input
   resolution, by the mapping loss L_3DGS + γ(NLL_C + NLL_D) with Σ as the reports compute it
   (Eq. 10-14); the opacity variances r_i learn at the refinement's rate, so the NLL refits
   them; at the end Gaussians of negligible opacity are pruned.

The stage is resumable: `GlobalMapStage.state_dict` holds the map, Adam's moments, the visits
done and the poses, and the order of the visits follows from the seed alone.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from bgs_batch.config import Config, GlobalMapConfig
from bgs_batch.render import Camera, render
from bgs_batch.slam.adam import Adam
from bgs_batch.slam.frames import Level, between_levels, downsample
from bgs_batch.slam.gaussian_map import PARAMS, UNCERTAINTY_KEY, GaussianMap
from bgs_batch.slam.losses import mapping_loss, predictive_variances
from bgs_batch.slam.mapping import Keyframe
from bgs_batch.slam.sensor_noise import SensorNoiseNet
from bgs_batch.slam.submaps import SubmapRecord, submap_params

MIN_DEPTH = 1e-6  # m: points at or behind the camera project nowhere
ORDER_STREAM = 0x610BA1  # the stage's own random stream, apart from the SLAM's (`Slam.rng`)

Params = dict[str, torch.Tensor]
PrepareFrame = Callable[[int], tuple[Level, Level]]  # frame index → (input, mapping) levels


@dataclass(frozen=True)
class FrameSplit:
    """Which frames the global stage trains on and which it holds out for scoring."""

    training: list[int]
    held_out: list[int]


def split_frames(frames: int, keyframes: set[int], every: int) -> FrameSplit:
    """Hold out frames ``every``, 2·every, … that are not keyframes (0: none held out)."""
    held = [i for i in range(every, frames, every) if i not in keyframes] if every else []
    held_set = set(held)
    return FrameSplit([i for i in range(frames) if i not in held_set], held)


@dataclass(frozen=True)
class SubmapView:
    """A submap rendered at one of its keyframes (mapping resolution): what the merge knows of
    where that submap has a surface."""

    submap: int
    w2c: np.ndarray  # (4, 4) float64
    camera: Camera
    alpha: np.ndarray  # [H,W]
    depth: np.ndarray  # [H,W] m, alpha-normalised


def submap_views(index: int, params: Params, keyframes: list[Keyframe]) -> Iterator[SubmapView]:
    """Submap `index` rendered at each of its `keyframes`, one at a time."""
    gaussians = GaussianMap(params).gaussians()
    for keyframe in keyframes:
        with torch.no_grad():
            out = render(gaussians, keyframe.w2c, keyframe.level.camera, full_grad=False)
        alpha = out.alpha[..., 0].numpy()
        depth = out.depth[..., 0].numpy() / np.maximum(alpha, MIN_DEPTH)
        yield SubmapView(index, np.linalg.inv(keyframe.c2w), keyframe.level.camera, alpha, depth)


def _project(means: np.ndarray, view: SubmapView
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The Gaussians whose centres fall into `view`'s image: their indices, depths, pixels
    (rows, columns) and centrality (1 at the image centre, 0 at its border)."""
    camera = view.camera
    points = means @ view.w2c[:3, :3].T + view.w2c[:3, 3]
    z = points[:, 2]
    safe = np.maximum(z, MIN_DEPTH)
    x = camera.fx * points[:, 0] / safe + camera.cx
    y = camera.fy * points[:, 1] / safe + camera.cy
    col, row = np.rint(x).astype(np.intp), np.rint(y).astype(np.intp)
    inside = (z > MIN_DEPTH) & (col >= 0) & (col < camera.width) & (row >= 0)
    inside &= row < camera.height
    index = np.flatnonzero(inside)
    half_w, half_h = camera.width / 2, camera.height / 2
    centrality = 1 - np.maximum(np.abs(x[index] - half_w) / half_w,
                                np.abs(y[index] - half_h) / half_h)  # fmt: skip
    return index, z[index], row[index], col[index], centrality


class Ownership:
    """Which submap keeps a surface that several show (module docstring, step 2).

    A Gaussian of submap k is dropped where another submap renders a surface through it (its
    depth within ``merge_depth_tolerance`` of the Gaussian's, alpha at least
    ``merge_min_alpha``) in one of its keyframes more centrally than any keyframe of k sees the
    Gaussian unoccluded: the better-seen copy of a surface stays, whichever submap made it,
    and a surface that only one submap shows stays whole. Views are added one at a time, so
    only the Gaussians' centres are held, never every keyframe's render.
    """

    def __init__(self, means: list[np.ndarray], cfg: GlobalMapConfig) -> None:
        self.means = [np.asarray(m, np.float64) for m in means]  # per submap
        self.cfg = cfg
        self.own = [np.full(len(m), -np.inf) for m in means]  # best centrality, own keyframes
        self.other = [np.full(len(m), -np.inf) for m in means]  # ... where another submap has it

    def add(self, view: SubmapView) -> None:
        """Score every submap's Gaussians in one keyframe's view."""
        for submap, means in enumerate(self.means):
            index, z, row, col, centrality = _project(means, view)
            rendered = view.depth[row, col]
            tolerance = self.cfg.merge_depth_tolerance * z
            if view.submap == submap:  # seen: not behind its own submap's surface
                hit = z <= rendered + tolerance
                best = self.own[submap]
            else:  # the other submap has this surface too
                hit = (view.alpha[row, col] >= self.cfg.merge_min_alpha) & (
                    np.abs(z - rendered) < tolerance)
                best = self.other[submap]
            best[index[hit]] = np.maximum(best[index[hit]], centrality[hit])

    def keep(self, submap: int) -> np.ndarray:
        """The Gaussians of `submap` that stay (bool mask)."""
        return self.own[submap] >= self.other[submap]


def merge_submaps(submaps: list[SubmapRecord], keyframe: Callable[[int], Keyframe],
                  cfg: GlobalMapConfig) -> tuple[Params, list[int]]:  # fmt: skip
    """The frozen submaps merged where each owns the surface (`Ownership`, seen from every
    submap's keyframes as `keyframe(i)` re-reads them): the merged Gaussians, and how many each
    submap gave."""
    means = [submap_params(record)["means"].numpy() for record in submaps]
    ownership = Ownership(means, cfg)
    for k, record in enumerate(submaps):
        keyframes = [keyframe(i) for i in record.keyframes]
        for view in submap_views(k, submap_params(record), keyframes):
            ownership.add(view)
    masks = [torch.from_numpy(ownership.keep(k)) for k in range(len(submaps))]
    parts = [submap_params(record) for record in submaps]
    merged = {name: torch.cat([p[name][m] for p, m in zip(parts, masks, strict=True)])
              for name in PARAMS}  # fmt: skip
    return merged, [int(mask.sum()) for mask in masks]


def visit_order(training: list[int], passes: float, seed: int) -> list[int]:
    """``round(passes · len(training))`` visits: whole seeded permutations of the training
    frames, one after another, the last one cut short."""
    if not training:
        return []
    rng = np.random.default_rng([seed, ORDER_STREAM])
    total = round(passes * len(training))
    order: list[int] = []
    for _ in range(math.ceil(total / len(training))):
        order.extend(int(i) for i in rng.permutation(training))
    return order[:total]


class GlobalMapStage:
    """Optimises the merged map on the training frames (module docstring, step 3).

    `run` takes one visit at a time and yields the visits done, so that the job can checkpoint
    between visits and stop on a signal; `params` gives the finished, pruned map.
    """

    def __init__(self, cfg: Config, merged: Params, poses: np.ndarray, split: FrameSplit,
                 sensor: SensorNoiseNet, merged_from: list[int]) -> None:  # fmt: skip
        """`merged_from`: how many Gaussians each submap gave the merged map."""
        self.cfg = cfg
        self.gmap = GaussianMap(merged)
        self.merged_from = list(merged_from)
        self.poses = np.ascontiguousarray(poses, np.float64)  # camera-to-world, every frame
        self.split = split
        self.sensor = sensor
        self.optimizer = self._optimizer()
        self.order = visit_order(split.training, cfg.global_map.passes, cfg.seed)
        self.visits = 0
        self.visit_counts = np.zeros(len(poses), np.int64)  # the stage's record of its frames

    def _optimizer(self) -> Adam:
        """Mapping's Adam, with the r_i at the end-of-run refinement's rate: only the NLL moves
        them, and Adam's steps do not depend on γ, so the stage refits them by the NLL."""
        optimizer = self.gmap.optimizer(self.cfg.mapping)
        for group in optimizer.param_groups:
            if group["name"] == UNCERTAINTY_KEY:
                group["lr"] = self.cfg.uncertainty.refine_lr
        return optimizer

    def run(self, prepare: PrepareFrame) -> Iterator[int]:
        """Take the remaining visits; after each, yield how many are done."""
        while self.visits < len(self.order):
            index = self.order[self.visits]
            self._step(index, *prepare(index))
            self.visit_counts[index] += 1
            self.visits += 1
            yield self.visits

    def _step(self, index: int, full: Level, mapping: Level) -> None:
        """One Adam step on the mapping loss of frame `index` at its reported pose."""
        cfg, u = self.cfg, self.cfg.uncertainty
        level = downsample(full, cfg.global_map.downscale)
        height, width = level.rgb.shape[:2]
        with torch.no_grad():
            sensor = self.sensor(mapping, u.sensor_downscale)
        sensor_c, sensor_d = (between_levels(v, cfg.mapping.downscale, cfg.global_map.downscale,
                                             height, width) for v in sensor)  # fmt: skip
        w2c = torch.from_numpy(np.linalg.inv(self.poses[index])).float()
        out = render(self.gmap.gaussians(), w2c, level.camera, full_grad=u.full_grad)
        var_c, var_d = predictive_variances(out, sensor_c, sensor_d, u, self.sensor.gains.map)
        terms = mapping_loss(out.color, out.depth, level.rgb, level.depth, var_c, var_d,
                             self.gmap.params["log_scales"], cfg.mapping.gamma,
                             cfg.mapping.ssim_weight)  # fmt: skip
        self.optimizer.zero_grad(set_to_none=True)
        terms.total.backward()
        self.optimizer.step()

    def params(self) -> Params:
        """The map as optimised so far, without the Gaussians below the pruning opacity."""
        keep = self.gmap.opacities() >= self.cfg.global_map.pruning_threshold
        return {name: value[keep] for name, value in self.gmap.state_dict().items()}

    def record(self) -> dict[str, Any]:
        """What the stage did, for the job's files: the merge, its frames and how often each
        was visited."""
        return {"merged_from": list(self.merged_from),
                "training_frames": list(self.split.training),
                "held_out_frames": list(self.split.held_out),
                "visits": self.visits, "visits_per_frame": self.visit_counts.tolist()}  # fmt: skip

    def summary(self) -> dict[str, Any]:
        """The record in numbers (``summary.json``)."""
        return {"gaussians_merged": sum(self.merged_from), "gaussians": len(self.params()["means"]),
                "training_frames": len(self.split.training),
                "held_out_frames": len(self.split.held_out), "visits": self.visits}  # fmt: skip

    def state_dict(self) -> dict[str, Any]:
        return {"params": self.gmap.state_dict(), "optimizer": self.optimizer.state_dict(),
                "visits": self.visits, "visit_counts": torch.from_numpy(self.visit_counts),
                "poses": torch.from_numpy(self.poses), "merged_from": list(self.merged_from),
                "training": list(self.split.training),
                "held_out": list(self.split.held_out)}  # fmt: skip

    @classmethod
    def from_state_dict(cls, cfg: Config, state: dict[str, Any],
                        sensor: SensorNoiseNet) -> GlobalMapStage:  # fmt: skip
        split = FrameSplit([int(i) for i in state["training"]],
                           [int(i) for i in state["held_out"]])  # fmt: skip
        stage = cls(cfg, state["params"], state["poses"].numpy(), split, sensor,
                    [int(k) for k in state["merged_from"]])  # fmt: skip
        stage.optimizer.load_state_dict(state["optimizer"])
        stage.visits = int(state["visits"])
        stage.visit_counts = state["visit_counts"].numpy().copy()
        return stage
