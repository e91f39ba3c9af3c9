"""Per-frame predictive uncertainty re-rendered from a finished job (docs/outputs.md).

For a frame, `UncertaintyRenderer.frame` renders the frame's submap at the pose that submap was
fitted at (the frame's tracked pose moved by its submap's loop-closure correction, as the submap
files' parameters are), or the global map at the pose of ``trajectory.txt``, and evaluates the
saved sensor-noise network on the measured frame, then assembles the variances with the SLAM's
own `predictive_variance` (paper Eq. 10, 11):

- Σ_C = σ²_sensor,C + map_C and Σ_D = σ²_sensor,D + map_D, where the map term is the rendered
  opacity-induced variance V (Eq. 3) plus its floor, replaced by the large "unobserved" value
  where the rendered alpha is below the threshold (all from the run's config);
- "map only" is that map term (the same call with a zero sensor term), "sensor only" σ²_sensor;
- after a calibrated run (`uncertainty.calibrate`), the map term of Σ_D is a·V_D + floor and
  the sensor term's per-pixel part is times b, with the gains a, b saved in the sensor
  network's state (`slam.calibration`).

Everything follows the run: crop and depth clipping as `Slam.prepare`, the sensor network
evaluated exactly as `Slam.process` does it (at the mapping resolution, `sensor_downscale`
times coarser), the frame's own submap (the one active when the frame was processed, in its
final, frozen state), the rasterizer's gradient setting. The images are rendered at
input resolution / `downscale` (default: the run's mapping resolution, where the SLAM computed
Σ for keyframes); the sensor variance is block-averaged to coarser levels (as tracking does)
or repeated onto finer ones. Colour variances are reported as the mean over the R, G, B
channels; the rendered colour is clamped to [0, 1] (as the evaluation of BayesianGS-SLAM).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch

from bgs_batch.errors import InputError
from bgs_batch.render import Camera, Gaussians, render
from bgs_batch.slam.frames import Level, between_levels, downsample, prepare_frame
from bgs_batch.slam.losses import predictive_variances
from bgs_batch.slam.mapping import Keyframe
from bgs_batch.slam.sensor_noise import SensorNoiseNet
from bgs_batch.store import FrameStore
from outputs.jobfiles import FinishedJob

# the depth variances whose depth AUSE the benchmark compares (see `FrameUncertainty`)
DEPTH_VARIANCES = ("predictive", "map", "sensor", "varsplat")


@dataclass(frozen=True)
class FrameUncertainty:
    """One frame's renders, variances and residuals; float32 [H,W] images unless noted."""

    frame: int
    timestamp: float
    keyframe: bool
    submap: int
    downscale: int  # images are input resolution / downscale
    camera: Camera  # pinhole camera of the images
    measured_rgb: np.ndarray  # [H,W,3] in [0,1]
    measured_depth: np.ndarray  # m, 0 where invalid
    rendered_rgb: np.ndarray  # [H,W,3] Ĉ clamped to [0,1]
    rendered_depth: np.ndarray  # D̂, m
    alpha: np.ndarray  # accumulated opacity A
    var_color: np.ndarray  # Σ_C, channel mean (Eq. 10)
    var_color_map: np.ndarray  # map term of Σ_C, channel mean
    var_color_sensor: np.ndarray  # σ²_sensor,C
    var_depth: np.ndarray  # Σ_D, m² (Eq. 11)
    var_depth_map: np.ndarray
    var_depth_sensor: np.ndarray

    @cached_property
    def valid(self) -> np.ndarray:
        """Pixels with a valid measured depth (the evaluation mask)."""
        return np.isfinite(self.measured_depth) & (self.measured_depth > 0)

    @cached_property
    def error_color(self) -> np.ndarray:
        """|Ĉ − C| averaged over the channels, at every pixel."""
        return np.abs(self.rendered_rgb - self.measured_rgb).mean(-1)

    @cached_property
    def error_depth(self) -> np.ndarray:
        """|D̂ − D| in m where the measured depth is valid, NaN elsewhere."""
        error = np.abs(self.rendered_depth - self.measured_depth)
        return np.where(self.valid, error, np.float32(np.nan)).astype(np.float32)

    def depth_variances(self) -> dict[str, np.ndarray]:
        """Four candidate uncertainties for the depth error, by name (`DEPTH_VARIANCES`).

        predictive: Σ_D; map: its map term only; sensor: σ²_sensor,D only; varsplat: the map
        term of the colour variance reused for depth, as VarSplat's depth NLL does (VarSplat
        has no sensor term; docs/method.md §9).
        """
        return {"predictive": self.var_depth, "map": self.var_depth_map,
                "sensor": self.var_depth_sensor, "varsplat": self.var_color_map}  # fmt: skip


def check_downscale(downscale: int, mapping_downscale: int) -> None:
    """`downscale` must be a multiple or a divisor of the run's mapping downscale."""
    if downscale < 1 or (downscale % mapping_downscale and mapping_downscale % downscale):
        raise InputError(f"--downscale {downscale}: must be a multiple or a divisor of the "
                         f"run's mapping.downscale ({mapping_downscale})")  # fmt: skip


def _numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().numpy().astype(np.float32)


class UncertaintyRenderer:
    """Renders `FrameUncertainty` for frames of a finished job, one frame at a time: from each
    frame's own submap at the pose that submap was made with (the default), or with
    `global_map` from the global map (``global_map.pt``, what ``global.ply`` holds) at the
    pose of ``trajectory.txt``, which is where the global stage fitted it."""

    def __init__(self, job: FinishedJob, store: FrameStore, downscale: int | None = None,
                 global_map: bool = False) -> None:  # fmt: skip
        self.job, self.store, self.cfg = job, store, job.config
        self.downscale = self.cfg.mapping.downscale if downscale is None else downscale
        check_downscale(self.downscale, self.cfg.mapping.downscale)
        u = self.cfg.uncertainty
        self.sensor = SensorNoiseNet.from_config(u)
        try:
            self.sensor.load_state_dict(job.sensor_state())
        except RuntimeError as err:  # shapes or names differ from the run's config
            raise InputError(f"{job.job_dir}/sensor_net.pt does not fit the run's sensor "
                             f"network ({err})") from err  # fmt: skip
        self.sensor.eval()
        self.global_map = Gaussians(**job.global_map.params) if global_map else None
        self.poses = job.trajectory()[1] if global_map else job.mapped_poses()
        if len(self.poses) != len(job.events):
            raise InputError(f"{job.job_dir}: trajectory.txt holds {len(self.poses)} poses for "
                             f"{len(job.events)} frames; the job is damaged")  # fmt: skip
        self._submap: tuple[int, Gaussians] | None = None

    def _gaussians(self, submap: int) -> Gaussians:
        """The submap's Gaussians (the last one used is kept: frames come in submap order)."""
        if self._submap is None or self._submap[0] != submap:  # `mapped_poses` checked `submap`
            paths = self.job.submap_paths()
            self._submap = (submap, Gaussians(**self.job.submap_params(paths[submap])))
        return self._submap[1]

    def _sensor(self, mapping: Level, height: int, width: int
                ) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
        """σ²_sensor (colour, depth) as `Slam.process` computes it, at the render resolution."""
        u, m = self.cfg.uncertainty, self.cfg.mapping.downscale
        sensor = self.sensor(mapping, u.sensor_downscale)
        return tuple(between_levels(v, m, self.downscale, height, width) for v in sensor)

    def frame(self, index: int) -> FrameUncertainty:
        """Everything of frame `index` (see the module's conventions)."""
        event = self.job.events[index]
        full, mapping = prepare_frame(self.store[index], self.store.intrinsics, self.cfg,
                                      event.depth_motion, *event.readouts)  # fmt: skip
        level = downsample(full, self.downscale)
        height, width = level.rgb.shape[:2]
        u = self.cfg.uncertainty
        with torch.no_grad():
            sensor_c, sensor_d = self._sensor(mapping, height, width)
            w2c = Keyframe(index, level, self.poses[index]).w2c  # as the SLAM's view matrices
            gaussians = (self._gaussians(event.submap) if self.global_map is None
                         else self.global_map)  # fmt: skip
            out = render(gaussians, w2c, level.camera, full_grad=u.full_grad)
            zero = torch.zeros(())
            gain = self.sensor.gains.map
            var_c, var_d = predictive_variances(out, sensor_c, sensor_d, u, gain)
            map_c, map_d = predictive_variances(out, zero, zero, u, gain)
        return FrameUncertainty(
            frame=index,
            timestamp=event.timestamp,
            keyframe=event.keyframe,
            submap=event.submap,
            downscale=self.downscale,
            camera=level.camera,
            measured_rgb=_numpy(level.rgb),
            measured_depth=_numpy(level.depth[..., 0]),
            rendered_rgb=_numpy(out.color.clamp(0.0, 1.0)),
            rendered_depth=_numpy(out.depth[..., 0]),
            alpha=_numpy(out.alpha[..., 0]),
            var_color=_numpy(var_c.mean(-1)),
            var_color_map=_numpy(map_c.mean(-1)),
            var_color_sensor=_numpy(sensor_c[..., 0]),
            var_depth=_numpy(var_d[..., 0]),
            var_depth_map=_numpy(map_d[..., 0]),
            var_depth_sensor=_numpy(sensor_d[..., 0]),
        )


def select_frames(job: FinishedJob, which: str = "keyframes", stride: int = 1) -> list[int]:
    """Frame indices: the keyframes or all frames (`which`), then every `stride`-th of those."""
    if which not in ("keyframes", "all"):
        raise ValueError(f"which must be 'keyframes' or 'all', got {which!r}")
    frames = [e.frame for e in job.events if which == "all" or e.keyframe]
    return frames[::stride]
