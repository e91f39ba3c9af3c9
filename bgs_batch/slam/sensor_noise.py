"""The sensor-noise network (paper §III-D; docs/method.md §3): per-pixel RGB-D noise variances.

A small fully convolutional net on the frame itself, input ``[depth m, R, G, B]``: 4 conv 3×3
layers and 4 per-pixel fully connected (1×1 conv) layers, 32 channels, ReLU, two output maps
(colour variance shared by R, G, B; depth variance) through softplus plus a floor. Trained with
the map during mapping only; in tracking it is evaluated once per frame and detached.
(The authors' code has 3 rather than 4 per-pixel layers; the paper describes 4.)
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from bgs_batch.slam.frames import block_mean, repeat_blocks

CONV_LAYERS = 4
PIXEL_LAYERS = 4  # the last one maps to the 2 outputs
INPUT_CHANNELS = 4  # depth, R, G, B
OUTPUT_CHANNELS = 2  # colour variance, depth variance


class SensorNoiseNet(nn.Module):
    """Predicts σ²_sensor for colour and depth at every pixel of an RGB-D frame."""

    def __init__(self, hidden: int = 32, floor: float = 1e-4, initial: float = 0.0) -> None:
        """`initial` > `floor`: the head's bias starts at softplus⁻¹(initial − floor), so the
        untrained network predicts about `initial` everywhere (0: PyTorch's default bias)."""
        super().__init__()
        self.floor = floor
        convs = [nn.Conv2d(INPUT_CHANNELS, hidden, 3, padding=1)]
        convs += [nn.Conv2d(hidden, hidden, 3, padding=1) for _ in range(CONV_LAYERS - 1)]
        pixels = [nn.Conv2d(hidden, hidden, 1) for _ in range(PIXEL_LAYERS - 1)]
        self.hidden = nn.ModuleList(convs + pixels)
        self.head = nn.Conv2d(hidden, OUTPUT_CHANNELS, 1)
        if initial:
            if initial <= floor:
                raise ValueError(f"initial sensor variance {initial} must exceed the floor {floor}")
            with torch.no_grad():
                self.head.bias.fill_(math.log(math.expm1(initial - floor)))

    def forward(self, rgb: torch.Tensor, depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Variances ([H,W,1] colour, [H,W,1] depth) from rgb [H,W,3] in [0,1], depth [H,W,1] m."""
        x = torch.cat([depth, rgb], dim=-1).permute(2, 0, 1)[None]
        for layer in self.hidden:
            x = F.relu(layer(x))
        out = F.softplus(self.head(x)) + self.floor
        out = out[0].permute(1, 2, 0)
        return out[..., :1], out[..., 1:]

    def at_scale(self, rgb: torch.Tensor, depth: torch.Tensor, downscale: int
                 ) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
        """The variances for a full-size frame, evaluating the network `downscale` times coarser.

        A CPU lever (the network dominates a mapping iteration at full resolution): the input is
        block-averaged, the output repeated back to every pixel of its block.
        """
        if downscale == 1:
            return self(rgb, depth)
        h, w = rgb.shape[:2]
        coarse = [block_mean(t, downscale) for t in (rgb, depth)]
        return tuple(repeat_blocks(v, downscale, h, w) for v in self(*coarse))

