"""Submap-to-submap registration: query keyframes localised in the candidate submap's Gaussians.

Each viewpoint (a keyframe of the query submap, with its real RGB-D images) is tracked in the
candidate submap by the SLAM's own `Tracker`, i.e. with the uncertainty-normalised L1 loss
Σ|r|/√Σ of paper Eq. 15-17: pixels the candidate map or the sensor is unsure about pull less
(LoopSplat's registration is unweighted). It starts from the RANSAC estimate. A viewpoint
counts when the candidate renders enough of its valid depth (alpha gate), when the rendered
depth agrees there, and when it stayed near the RANSAC estimate. Accepted viewpoints are fused
with weights Σ 1/Σ_D over their agreeing pixels (a Fisher-information proxy from our predictive
variance): rotation by projecting the weighted mean matrix onto SO(3), translation by the
weighted mean. Without an accepted viewpoint, point-to-plane ICP on the Gaussian centres is
the fallback. `loop_closure.weighting=uniform` replaces the variances by a constant, for
comparison with LoopSplat's unweighted registration.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from bgs_batch.config import Config
from bgs_batch.geometry import kd_tree, rotation_angle_deg
from bgs_batch.render import render
from bgs_batch.slam.frames import block_mean, downsample
from bgs_batch.slam.gaussian_map import GaussianMap
from bgs_batch.slam.loop_closure.icp import IcpResult, point_to_plane, subsample
from bgs_batch.slam.losses import predictive_variance
from bgs_batch.slam.mapping import Keyframe
from bgs_batch.slam.sensor_noise import SensorNoiseNet
from bgs_batch.slam.tracking import Tracker

UNIFORM_VARIANCE = 1.0  # ≫ any rendered map variance: Σ is then the same at every pixel


@dataclass(frozen=True)
class Viewpoint:
    """One localised keyframe: its transform estimate and gate measurements."""

    frame: int
    transform: np.ndarray  # query submap frame → candidate submap frame
    coverage: float  # share of valid-depth pixels the candidate renders (alpha ≥ threshold)
    agreement: float  # share of those whose rendered depth agrees
    weight: float  # Σ 1/Σ_D over agreeing pixels
    moved_m: float  # camera shift from the RANSAC estimate
    moved_deg: float
    accepted: bool


@dataclass(frozen=True)
class Registration:
    transform: np.ndarray | None  # query → candidate frame; None when registration failed
    method: str  # render | icp | failed
    viewpoints: list[Viewpoint]
    icp: IcpResult | None


def relative_motion(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Distance (m) and angle (deg) between two camera poses."""
    angle = rotation_angle_deg((np.linalg.inv(a) @ b)[:3, :3])
    return float(np.linalg.norm(a[:3, 3] - b[:3, 3])), angle


def fuse(transforms: list[np.ndarray], weights: list[float]) -> np.ndarray:
    """Weighted rigid mean: SVD projection of Σ w R, weighted mean of t."""
    w = np.asarray(weights, np.float64) / np.sum(weights)
    stack = np.stack(transforms)
    u, _, vt = np.linalg.svd(np.einsum("k,kij->ij", w, stack[:, :3, :3]))
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    out = np.eye(4)
    out[:3, :3] = u @ sign @ vt
    out[:3, 3] = np.einsum("k,ki->i", w, stack[:, :3, 3])
    return out


def overlap(source: np.ndarray, target: np.ndarray, transform: np.ndarray, radius: float
            ) -> float:  # fmt: skip
    """Share of `source` points (moved by `transform`) with a `target` point within `radius`."""
    if len(source) == 0 or len(target) == 0:
        return 0.0
    moved = source @ transform[:3, :3].T + transform[:3, 3]
    dist, _ = kd_tree(target).query(moved, distance_upper_bound=radius)
    return float(np.isfinite(dist).mean())


class SubmapRegistration:
    """Registers a query submap to a candidate submap (render-based, ICP fallback)."""

    def __init__(self, cfg: Config) -> None:
        self.cfg = cfg
        lc = cfg.loop_closure
        # LoopSplat's rates and budget, which are Adam's (whatever tracking itself uses)
        tracking = dataclasses.replace(
            cfg.tracking, iterations=lc.iterations, rot_lr=lc.rot_lr, trans_lr=lc.trans_lr,
            downscale=lc.downscale, coarse_levels=lc.coarse_levels,
            coarse_fraction=lc.coarse_fraction, early_stop_rel=lc.early_stop_rel,
            early_stop_patience=lc.early_stop_patience, init_err_ratio=0.0,
            warm_start=False, optimizer="adam")  # fmt: skip
        # keyframes are already at mapping resolution: their levels are the tracker's input
        mapping = dataclasses.replace(cfg.mapping, downscale=1)
        self.tracker = Tracker(dataclasses.replace(cfg, tracking=tracking, mapping=mapping))

    def localise(self, gmap: GaussianMap, keyframe: Keyframe, sensor: SensorNoiseNet,
                 init: np.ndarray) -> Viewpoint:  # fmt: skip
        """Track `keyframe` in `gmap` from `init` (query → candidate frame) and gate it."""
        lc, u = self.cfg.loop_closure, self.cfg.uncertainty
        level = keyframe.level
        with torch.no_grad():
            sensor_c, sensor_d = sensor(level, u.sensor_downscale)
        if lc.weighting == "uniform":  # swamps the per-pixel variances: every pixel alike
            sensor_c = torch.full_like(sensor_c, UNIFORM_VARIANCE)
            sensor_d = torch.full_like(sensor_d, UNIFORM_VARIANCE)
        start = init @ keyframe.c2w
        result = self.tracker.track(gmap, level, sensor_c, sensor_d,
                                    torch.from_numpy(np.linalg.inv(start)))  # fmt: skip
        c2w = np.linalg.inv(result.w2c.numpy())
        transform = c2w @ np.linalg.inv(keyframe.c2w)
        coarse = downsample(level, lc.downscale)
        with torch.no_grad():
            out = render(gmap.gaussians(), result.w2c.float(), coarse.camera)
            var_d = predictive_variance(out.var_depth, block_mean(sensor_d, lc.downscale),
                                        out.alpha, u)  # fmt: skip
        valid = coarse.depth > 0
        covered = valid & (out.alpha >= u.unobserved_alpha)
        agree = covered & ((out.normalized_depth() - coarse.depth).abs() <= lc.inlier_depth)
        coverage = float(covered.sum()) / max(int(valid.sum()), 1)
        agreement = float(agree.sum()) / max(int(covered.sum()), 1)
        weight = float((1.0 / var_d)[agree].double().sum())
        moved_m, moved_deg = relative_motion(start, c2w)
        accepted = (coverage >= lc.min_coverage and agreement >= lc.min_depth_inliers
                    and moved_m <= lc.max_disagreement_m
                    and moved_deg <= lc.max_disagreement_deg and weight > 0)  # fmt: skip
        return Viewpoint(keyframe.frame, transform, coverage, agreement, weight, moved_m,
                         moved_deg, accepted)  # fmt: skip

    def register(
        self,
        viewpoints: list[Keyframe],
        sensor: SensorNoiseNet,
        candidate: dict[str, torch.Tensor],
        query_centres: np.ndarray,
        init: np.ndarray,
    ) -> Registration:
        """Query → candidate transform from `viewpoints` (query keyframes), starting at `init`."""
        lc = self.cfg.loop_closure
        gmap = GaussianMap(candidate)
        results = [self.localise(gmap, kf, sensor, init) for kf in viewpoints]
        good = [r for r in results if r.accepted]
        if good:
            fused = fuse([r.transform for r in good], [r.weight for r in good])
            return Registration(fused, "render", results, None)
        icp = point_to_plane(subsample(query_centres, lc.max_points),
                             subsample(candidate["means"].numpy().astype(np.float64),
                                       lc.max_points),
                             init, lc.icp_max_distance, lc.icp_iterations,
                             lc.icp_normal_neighbours)  # fmt: skip
        moved_m, moved_deg = relative_motion(init, icp.transform)
        ok = (icp.fitness >= lc.icp_min_fitness and icp.rmse <= lc.icp_max_rmse
              and moved_deg <= lc.max_disagreement_deg)  # fmt: skip
        return Registration(icp.transform if ok else None, "icp" if ok else "failed", results,
                            icp)  # fmt: skip
