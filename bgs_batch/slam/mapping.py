"""Keyframe mapping of the active submap (paper §III-A, Eq. 12-14; docs/method.md §5).

A mapping call seeds new Gaussians from the keyframe, then optimises the submap and the
sensor-noise network jointly: each iteration renders one keyframe of the submap (the current
one with probability 0.4, else a uniformly chosen older one) at its fixed estimated pose and
takes a step on L_3DGS + γ(NLL_C + NLL_D). Gaussians with opacity below the pruning threshold
are removed half-way and at the end. (LoopSplat freezes colours for the first half of a round
as a side effect of its growth code; we optimise them throughout.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bgs_batch.config import Config
from bgs_batch.render import Gaussians, render
from bgs_batch.slam.adam import Adam
from bgs_batch.slam.frames import Level
from bgs_batch.slam.gaussian_map import UNCERTAINTY_KEY, GaussianMap
from bgs_batch.slam.loss_kernels import l1_nll_terms
from bgs_batch.slam.losses import mapping_loss, predictive_variances
from bgs_batch.slam.seeding import (
    backproject,
    far_from,
    keyframe_seed_pixels,
    submap_seed_pixels,
    surface_normals,
)
from bgs_batch.slam.sensor_noise import SensorNoiseNet


@dataclass
class Keyframe:
    """A mapped frame of the active submap at mapping resolution, with its fixed pose."""

    frame: int
    level: Level
    c2w: np.ndarray  # (4, 4) float64

    @property
    def w2c(self) -> torch.Tensor:
        return torch.from_numpy(np.linalg.inv(self.c2w)).float()


@dataclass(frozen=True)
class MappingStats:
    added: int
    pruned: int
    iterations: int
    loss: float  # last iteration's total


def intrinsics_of(level: Level) -> np.ndarray:
    c = level.camera
    return np.array([[c.fx, 0.0, c.cx], [0.0, c.fy, c.cy], [0.0, 0.0, 1.0]])


class Mapper:
    """Grows and optimises the active submap; owns the sensor network's training."""

    def __init__(self, cfg: Config, sensor: SensorNoiseNet, sensor_opt: Adam) -> None:
        self.cfg = cfg
        self.sensor = sensor
        self.sensor_opt = sensor_opt

    def seed(self, gmap: GaussianMap, keyframe: Keyframe, new_submap: bool,
             rng: np.random.Generator) -> int:  # fmt: skip
        """Add Gaussians where the keyframe shows something the submap lacks."""
        s = self.cfg.seeding
        rgb_u8 = (keyframe.level.rgb.numpy() * 255).round().astype(np.uint8)
        depth = keyframe.level.depth[..., 0].numpy()
        if new_submap or len(gmap) == 0:
            pixels = submap_seed_pixels(rgb_u8, depth, s, rng)
        else:
            with torch.no_grad():
                out = render(gmap.gaussians(), keyframe.w2c, keyframe.level.camera)
            pixels = keyframe_seed_pixels(out.alpha[..., 0].numpy(), out.depth[..., 0].numpy(),
                                          depth, s, rng)  # fmt: skip
        points = backproject(depth, pixels, intrinsics_of(keyframe.level), keyframe.c2w,
                             s.depth_push)  # fmt: skip
        keep = far_from(gmap.means.detach().numpy(), points, s.min_distance)
        colors = keyframe.level.rgb.reshape(-1, 3).numpy()[pixels[keep]]
        normals = surface_normals(depth, pixels[keep], intrinsics_of(keyframe.level), keyframe.c2w)
        return gmap.add(points[keep], colors, s.initial_opacity, self.cfg.uncertainty.initial_logit,
                        normals, s.flatness)  # fmt: skip

    def map(
        self,
        gmap: GaussianMap,
        keyframes: list[Keyframe],
        new_submap: bool,
        rng: np.random.Generator,
    ) -> MappingStats:
        """Seed from the newest keyframe, then optimise the submap over its keyframes."""
        m, u = self.cfg.mapping, self.cfg.uncertainty
        current = keyframes[-1]
        added = self.seed(gmap, current, new_submap, rng)
        iterations = m.new_submap_iterations if new_submap else m.iterations
        optimizer = gmap.optimizer(m)
        pruned = 0
        loss_value = float("nan")
        for it in range(iterations):
            keyframe = self._pick(keyframes, rng)
            level = keyframe.level
            out = render(gmap.gaussians(), keyframe.w2c, level.camera, full_grad=u.full_grad)
            sensor_c, sensor_d = self.sensor(level, u.sensor_downscale)
            var_c, var_d = predictive_variances(out, sensor_c, sensor_d, u)
            terms = mapping_loss(out.color, out.depth, level.rgb, level.depth, var_c, var_d,
                                 gmap.params["log_scales"], m.gamma, m.ssim_weight)  # fmt: skip
            optimizer.zero_grad(set_to_none=True)
            self.sensor_opt.zero_grad(set_to_none=True)
            terms.total.backward()
            optimizer.step()
            self.sensor_opt.step()
            loss_value = float(terms.total.detach())
            if it + 1 in (iterations // 2, iterations):
                pruned += gmap.keep(gmap.opacities() >= m.pruning_threshold, optimizer)
        return MappingStats(added, pruned, iterations, loss_value)

    def refine_uncertainty(self, gmap: GaussianMap, keyframes: list[Keyframe]) -> int:
        """Fit the opacity uncertainties r_i of a frozen submap (end of run, `Slam.finish`)
        and the sensor network; return the steps taken.

        `uncertainty.refine_passes` passes over the keyframes in order, one Adam step per
        keyframe on NLL_C + NLL_D (Eq. 13, 14; γ drops out of Adam's steps) with Σ the full
        predictive variance. Only the two uncertainty parts learn: r_i, and the sensor network
        as in mapping (its own optimiser and rate); the geometry and colours, and so the
        renders and residuals, are fixed. The map term thus learns the residuals the sensor
        term cannot explain, and σ² gives back what V explains.
        """
        u = self.cfg.uncertainty
        if u.refine_passes == 0 or not keyframes or len(gmap) == 0:
            return 0
        logits = gmap.params[UNCERTAINTY_KEY]
        fixed = {n: p.detach() for n, p in gmap.params.items() if n != UNCERTAINTY_KEY}
        gaussians = Gaussians(**fixed, uncertainty_logits=logits)
        optimizer = Adam([logits], lr=u.refine_lr)
        for _ in range(u.refine_passes):
            for keyframe in keyframes:
                level = keyframe.level
                out = render(gaussians, keyframe.w2c, level.camera, full_grad=u.full_grad)
                sensor_c, sensor_d = self.sensor(level, u.sensor_downscale)
                var_c, var_d = predictive_variances(out, sensor_c, sensor_d, u)
                nll_c, nll_d = l1_nll_terms(out.color, out.depth, level.rgb, level.depth,
                                            var_c, var_d)[2:]  # fmt: skip
                optimizer.zero_grad(set_to_none=True)
                self.sensor_opt.zero_grad(set_to_none=True)
                (nll_c + nll_d).backward()
                optimizer.step()
                self.sensor_opt.step()
        return u.refine_passes * len(keyframes)

    def _pick(self, keyframes: list[Keyframe], rng: np.random.Generator) -> Keyframe:
        """The current keyframe with probability `current_frame_share`, else an older one."""
        if len(keyframes) == 1 or rng.random() < self.cfg.mapping.current_frame_share:
            return keyframes[-1]
        return keyframes[int(rng.integers(len(keyframes) - 1))]
