"""The sensor-noise model (paper §III-D; docs/method.md §3): per-pixel RGB-D noise variances.

A small fully convolutional net on the frame itself, input ``[depth m, R, G, B]``: 4 conv 3×3
layers and 4 per-pixel fully connected (1×1 conv) layers, 32 channels, ReLU, two output maps.
The colour variance (shared by R, G, B) is softplus of the first plus a floor. The depth
variance is, as in the paper, softplus of the second plus the floor, or, with a physical prior
(`NguyenDepthNoise`), the frame's mean of that map plus the prior: the network learns the
frame's noise level as the paper's does, and the sensor's known physics ranks its pixels.
Trained with the map during mapping only; in tracking it is evaluated once per frame and
detached.
(The authors' code has 3 rather than 4 per-pixel layers; the paper describes 4.)
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from bgs_batch.config import UncertaintyConfig
from bgs_batch.render import Camera
from bgs_batch.slam.frames import Level, block_mean, repeat_blocks

CONV_LAYERS = 4
PIXEL_LAYERS = 4  # the last one maps to the 2 outputs
INPUT_CHANNELS = 4  # depth, R, G, B
OUTPUT_CHANNELS = 2  # colour variance, depth variance (with a prior: its frame mean)
DEPTH_OUTPUT = 1


@dataclass(frozen=True)
class DepthGains:
    """Multipliers of the map term V_D and of σ²_sensor,D's per-pixel part in the reported Σ_D."""

    map: float = 1.0
    sensor: float = 1.0


@dataclass(frozen=True)
class NguyenDepthNoise:
    """Axial noise of a structured-light depth camera: Nguyen, Izadi, Lovell, "Modeling Kinect
    Sensor Noise for Improved 3D Reconstruction and Tracking", 3DIMPVT 2012, Eq. 3:

        σ_z(z, θ) = a + b (z − z0)² + c/√z · θ² / (π/2 − θ)²   (m)

    with z the depth and θ the surface's tilt away from facing the camera, here estimated from
    the measured depth's slope (central differences over valid neighbours). A pixel's σ is at
    most half its 3×3 neighbourhood's depth range where that exceeds the axial term: a mixed
    pixel at a depth edge lies between its neighbours, and there θ → π/2 is an artefact.
    """

    a: float = 0.0012
    b: float = 0.0019
    z0: float = 0.4
    c: float = 0.0001

    @classmethod
    def from_config(cls, u: UncertaintyConfig) -> NguyenDepthNoise:
        return cls(u.nguyen_a, u.nguyen_b, u.nguyen_z0, u.nguyen_c)

    def variance(self, depth: torch.Tensor, camera: Camera) -> torch.Tensor:
        """σ_z² [H,W,1] (m²) of a depth image [H,W,1] (m, 0 invalid) seen by `camera`;
        invalid pixels get the model's value at z0, so every variance is finite and positive."""
        d = depth[..., 0]
        valid = d > 0
        z = torch.where(valid, d, torch.full_like(d, self.z0))
        slope_x = _central_difference(d, valid, dim=1) * camera.fx
        slope_y = _central_difference(d, valid, dim=0) * camera.fy
        theta = torch.atan(torch.hypot(slope_x, slope_y) / z)
        axial = self.a + self.b * (z - self.z0) ** 2
        grazing = self.c / z.sqrt() * theta**2 / (math.pi / 2 - theta).clamp_min(1e-6) ** 2
        mixed = 0.5 * _local_range(d, valid)
        sigma = torch.minimum(axial + grazing, torch.maximum(axial, mixed))
        return (sigma**2)[..., None]


def _central_difference(d: torch.Tensor, valid: torch.Tensor, dim: int) -> torch.Tensor:
    """(d[+1] − d[−1]) / 2 along `dim` where both neighbours are valid, else 0 (edges: 0)."""
    out = torch.zeros_like(d)
    n = d.shape[dim]
    ahead, behind = d.narrow(dim, 2, n - 2), d.narrow(dim, 0, n - 2)
    both = valid.narrow(dim, 2, n - 2) & valid.narrow(dim, 0, n - 2)
    out.narrow(dim, 1, n - 2).copy_(torch.where(both, 0.5 * (ahead - behind), 0.0))
    return out


def _local_range(d: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """max − min of the valid depths in each pixel's 3×3 neighbourhood (0 at invalid pixels)."""
    far = torch.finfo(d.dtype).max
    high = F.max_pool2d(torch.where(valid, d, -far)[None, None], 3, 1, 1)[0, 0]
    low = -F.max_pool2d(torch.where(valid, -d, -far)[None, None], 3, 1, 1)[0, 0]
    return torch.where(valid, high - low, 0.0)


class SensorNoiseNet(nn.Module):
    """Predicts σ²_sensor for colour and depth at every pixel of an RGB-D frame."""

    def __init__(self, hidden: int = 32, floor: float = 1e-4, initial: float = 0.0,
                 prior: NguyenDepthNoise | None = None) -> None:  # fmt: skip
        """`initial` > `floor`: the head's bias starts at softplus⁻¹(initial − floor), so the
        untrained network predicts about `initial` everywhere (0: PyTorch's default bias)."""
        super().__init__()
        self.floor = floor
        self.prior = prior
        convs = [nn.Conv2d(INPUT_CHANNELS, hidden, 3, padding=1)]
        convs += [nn.Conv2d(hidden, hidden, 3, padding=1) for _ in range(CONV_LAYERS - 1)]
        pixels = [nn.Conv2d(hidden, hidden, 1) for _ in range(PIXEL_LAYERS - 1)]
        self.hidden = nn.ModuleList(convs + pixels)
        self.head = nn.Conv2d(hidden, OUTPUT_CHANNELS, 1)
        self._physics: dict[int, torch.Tensor] = {}  # id(depth tensor) -> its prior variance
        # Σ_D's gains (map, sensor), fitted at the end of a run (`slam.calibration`); the sensor
        # gain multiplies the depth variance's per-pixel part, the map gain is the reports'
        self.register_buffer("depth_gains", torch.ones(2))
        if initial:
            if initial <= floor:
                raise ValueError(f"initial sensor variance {initial} must exceed the floor {floor}")
            with torch.no_grad():
                self.head.bias.fill_(math.log(math.expm1(initial - floor)))

    def depth_physics(self, level: Level) -> torch.Tensor:
        """The prior's σ_z² of `level`'s measured depth, computed once per depth tensor: it
        depends on nothing learned, and mapping evaluates each keyframe at every iteration. An
        entry lives as long as its depth tensor (which no stage changes in place)."""
        key = id(level.depth)
        physics = self._physics.get(key)
        if physics is None:
            physics = self.prior.variance(level.depth, level.camera)
            self._physics[key] = physics
            weakref.finalize(level.depth, self._physics.pop, key, None)
        return physics

    @property
    def gains(self) -> DepthGains:
        return DepthGains(*(float(g) for g in self.depth_gains))

    def set_gains(self, gains: DepthGains) -> None:
        self.depth_gains.copy_(torch.tensor([gains.map, gains.sensor]))

    def load_state_dict(self, state: dict[str, torch.Tensor], strict: bool = True) -> Any:
        """As `nn.Module`'s; a state saved before the gains existed has gains 1."""
        return super().load_state_dict({"depth_gains": torch.ones(2), **state}, strict)

    def _gained(self, part: torch.Tensor) -> torch.Tensor:
        """The per-pixel part of σ²_sensor,D times the sensor gain (untouched at gain 1)."""
        gain = self.depth_gains[1]
        return part if gain == 1.0 else gain * part

    @classmethod
    def from_config(cls, u: UncertaintyConfig) -> SensorNoiseNet:
        """The network a run with these settings trains (`uncertainty.sensor_*`)."""
        prior = NguyenDepthNoise.from_config(u) if u.sensor_prior == "nguyen" else None
        return cls(u.sensor_hidden, u.sensor_min, u.sensor_initial, prior)

    def raw(self, rgb: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """The head's two output maps [1,2,H,W] before their activations."""
        x = torch.cat([depth, rgb], dim=-1).permute(2, 0, 1)[None]
        for layer in self.hidden:
            x = F.relu(layer(x))
        return self.head(x)

    def forward(self, level: Level, downscale: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        """Variances ([H,W,1] colour, [H,W,1] depth) of a frame `level` (rgb in [0,1], depth m).

        `downscale` > 1 is a CPU lever (the network dominates a mapping iteration at full
        resolution): the network sees the block-averaged frame and its outputs are repeated back
        to every pixel of their block; the depth prior is evaluated at full resolution.

        With a depth prior, σ²_sensor,D = mean(network's depth map) + σ_z²: the mean follows the
        NLL at the pace of the paper's network (which on a synthetic room falls from its start
        to its floor within a run), so Σ_D keeps the plain network's scale, and with it the
        surprise's keyframes and tracking's weights; a constant changes no pixel's rank.
        """
        h, w = level.rgb.shape[:2]
        raw = self.raw(*(block_mean(t, downscale) for t in (level.rgb, level.depth)))
        variances = (F.softplus(raw) + self.floor)[0].permute(1, 2, 0)
        colour, depth_part = variances[..., :DEPTH_OUTPUT], variances[..., DEPTH_OUTPUT:]
        if self.prior is not None:
            depth_part = depth_part.mean() + self._gained(self.depth_physics(level))
        else:
            if downscale > 1:
                depth_part = repeat_blocks(depth_part, downscale, h, w)
            depth_part = self._gained(depth_part)
        if downscale > 1:
            colour = repeat_blocks(colour, downscale, h, w)
        return colour, depth_part
