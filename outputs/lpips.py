"""LPIPS (Zhang et al., CVPR 2018, v0.1) in plain PyTorch, from user-supplied weights only.

Nothing is downloaded (docs/outputs.md): the user passes state-dict files holding the
backbone and the linear heads, in any of these key layouts (several files are merged):

- a whole ``lpips.LPIPS(net=...)`` model: ``net.sliceK.I.weight|bias`` and ``linK.model.1.weight``
  (e.g. ``torch.save(lpips.LPIPS(net='alex').state_dict(), 'lpips_alex.pth')``, done once on a
  machine with internet);
- torchvision's ImageNet backbone (``alexnet-owt-7be5be79.pth``, ``vgg16-397923af.pth``:
  ``features.I.weight|bias``) together with lpips's head file (``weights/v0.1/alex.pth``:
  ``linK.model.1.weight``).

The backbone (AlexNet or VGG-16, told apart by the first convolution's kernel) is torchvision's
``features`` stack; LPIPS taps it after the ReLUs that end lpips's five slices. The distance:
inputs in [0,1] → [−1,1] → (x − shift)/scale; per tap, features unit-normalised over channels,
squared difference, 1×1 linear head, spatial mean; summed over taps (lpips ``spatial=False``).
"""

from __future__ import annotations

import re
from pathlib import Path

import torch
from torch import nn

from bgs_batch.errors import InputError

SHIFT = (-0.030, -0.088, -0.188)  # lpips ScalingLayer, version 0.1
SCALE = (0.458, 0.448, 0.450)
NORM_EPS = 1e-10  # lpips normalize_tensor
# torchvision `features`: ("conv", in, out, kernel, stride, padding) | ("relu",) | ("pool",)
ALEX_LAYERS = [
    ("conv", 3, 64, 11, 4, 2), ("relu",), ("pool",),
    ("conv", 64, 192, 5, 1, 2), ("relu",), ("pool",),
    ("conv", 192, 384, 3, 1, 1), ("relu",),
    ("conv", 384, 256, 3, 1, 1), ("relu",),
    ("conv", 256, 256, 3, 1, 1), ("relu",),
]  # fmt: skip
ALEX_TAPS = (2, 5, 8, 10, 12)  # lpips slices end after these many layers
VGG_WIDTHS = (64, 64, "pool", 128, 128, "pool", 256, 256, 256, "pool", 512, 512, 512, "pool",
              512, 512, 512)  # fmt: skip
VGG_TAPS = (4, 9, 16, 23, 30)
POOL_ALEX = (3, 2)  # kernel, stride
POOL_VGG = (2, 2)
ALEX_FIRST_KERNEL = 11


def _vgg_layers() -> list[tuple]:
    layers, channels = [], 3
    for width in VGG_WIDTHS:
        if width == "pool":
            layers.append(("pool",))
        else:
            layers += [("conv", channels, width, 3, 1, 1), ("relu",)]
            channels = width
    return layers


class Lpips(nn.Module):
    """LPIPS distance of two [H,W,3] images in [0,1]; `net` is "alex" or "vgg"."""

    def __init__(self, net: str) -> None:
        super().__init__()
        if net not in ("alex", "vgg"):
            raise ValueError(f"net must be 'alex' or 'vgg', got {net!r}")
        self.net = net
        specs, self.taps = (ALEX_LAYERS, ALEX_TAPS) if net == "alex" else (_vgg_layers(), VGG_TAPS)
        pool = POOL_ALEX if net == "alex" else POOL_VGG
        modules: list[nn.Module] = []
        for spec in specs:
            if spec[0] == "conv":
                _, cin, cout, kernel, stride, padding = spec
                modules.append(nn.Conv2d(cin, cout, kernel, stride, padding))
            elif spec[0] == "relu":
                modules.append(nn.ReLU())
            else:
                modules.append(nn.MaxPool2d(*pool))
        self.features = nn.Sequential(*modules)
        widths = [self._width(end) for end in self.taps]
        self.heads = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in widths)
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))
        self.eval()

    def _width(self, end: int) -> int:
        convs = [m for m in list(self.features)[:end] if isinstance(m, nn.Conv2d)]
        return convs[-1].out_channels

    @torch.no_grad()
    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Distance (0-d tensor) of [H,W,3] images in [0,1]."""
        x = torch.stack([a, b]).permute(0, 3, 1, 2).float() * 2 - 1
        x = (x - self.shift) / self.scale
        total = x.new_zeros(())
        start = 0
        for head, end in zip(self.heads, self.taps, strict=True):
            x = self.features[start:end](x)
            start = end
            unit = x / (x.pow(2).sum(1, keepdim=True).sqrt() + NORM_EPS)
            total = total + head((unit[0:1] - unit[1:2]) ** 2).mean()
        return total


_LPIPS_BACKBONE = re.compile(r"^net\.slice\d+\.(\d+)\.(weight|bias)$")
_TORCHVISION_BACKBONE = re.compile(r"^features\.(\d+)\.(weight|bias)$")
_HEAD = re.compile(r"^lin(\d+)\.model\.\d+\.weight$")


def _translate(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Keys of the recognised layouts → this module's (`features.I.*`, `heads.K.weight`)."""
    out = {}
    for key, value in state.items():
        if match := _LPIPS_BACKBONE.match(key) or _TORCHVISION_BACKBONE.match(key):
            out[f"features.{match[1]}.{match[2]}"] = value
        elif match := _HEAD.match(key):
            out[f"heads.{match[1]}.weight"] = value
    return out


def load_lpips(paths: list[Path]) -> Lpips:
    """An `Lpips` from one or more weight files (see the module's layouts); clear errors."""
    state: dict[str, torch.Tensor] = {}
    for path in paths:
        try:
            loaded = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as err:  # missing, truncated, not a torch file
            raise InputError(f"--lpips-weights {path}: not a readable PyTorch state dict "
                             f"({err})") from err  # fmt: skip
        if not isinstance(loaded, dict):
            raise InputError(f"--lpips-weights {path}: expected a state dict, got "
                             f"{type(loaded).__name__}")  # fmt: skip
        state |= _translate(loaded)
    first = state.get("features.0.weight")
    if first is None:
        raise InputError(
            "--lpips-weights: no backbone found (keys net.sliceK.I.* of an lpips "
            "model or features.I.* of torchvision's AlexNet/VGG-16)"
        )
    model = Lpips("alex" if first.shape[-1] == ALEX_FIRST_KERNEL else "vgg")
    expected = set(model.state_dict()) - {"shift", "scale"}
    missing = sorted(expected - set(state))
    if missing:
        raise InputError(
            f"--lpips-weights: the {model.net} LPIPS weights lack {', '.join(missing)}"
            " (the linear heads linK.model.1.weight come with the lpips package)"
        )
    try:
        model.load_state_dict({k: state[k] for k in expected}, strict=False)
    except RuntimeError as err:  # shape mismatch
        raise InputError(f"--lpips-weights: the weights do not fit {model.net} LPIPS ({err})"
                         ) from err  # fmt: skip
    return model


def lpips_distance(model: Lpips, rendered: torch.Tensor, target: torch.Tensor) -> float:
    """LPIPS of two [H,W,3] images in [0,1] (lpips ``normalize=True`` convention)."""
    return float(model(rendered, target))
