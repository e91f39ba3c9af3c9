"""Synthetic scenes for the render tests and ``bench/raster.py`` (seeded, any dtype)."""

import math

import torch

from .camera import Camera
from .render import Gaussians

ROOM_HALF_EXTENT = (3.0, 1.5, 3.0)
"""Half sizes (x, y, z) in metres of the bench room; the camera sits at its centre."""
ROOM_BOX_FRACTION = 0.2
"""Fraction of the room's Gaussians on the six boxes (the rest on walls, floor, ceiling)."""
ROOM_SCALE_RANGE = (0.004, 0.02)
"""In-plane standard deviations (metres), sampled log-uniformly."""
ROOM_OPACITY_RANGE = (0.3, 1.0)
FLAT_SCALE = 1e-3
"""Standard deviation along the surface normal (metres)."""
INITIAL_UNCERTAINTY_LOGIT = -7.0
"""Raw opacity-uncertainty ``r_i`` of new Gaussians (docs/method.md §1)."""
ROOM_CAMERA_Z = -2.0
"""The bench camera stands at (0, 0, ROOM_CAMERA_Z) looking along +z: about 27% in view."""
VGA = Camera(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)
"""The bench camera at 640×480; use :meth:`Camera.scaled` for lower resolutions."""


def _uniform(gen: torch.Generator, shape, low: float, high: float, dtype) -> torch.Tensor:
    return torch.rand(shape, generator=gen, dtype=dtype) * (high - low) + low


def _logit(p: torch.Tensor) -> torch.Tensor:
    return torch.log(p / (1 - p))


def random_screen_gaussians(
    n: int,
    width: int,
    height: int,
    *,
    seed: int,
    dtype: torch.dtype = torch.float64,
    sigma_px: tuple[float, float] = (0.7, 3.0),
    opacity: tuple[float, float] = (0.2, 0.8),
    variance: tuple[float, float] = (1e-3, 0.05),
) -> tuple[torch.Tensor, ...]:
    """Random inputs of :func:`.rasterize.rasterize`: (means2d, conics, depths, opacities,
    colors, variances), centres spread a little beyond the image borders."""
    gen = torch.Generator().manual_seed(seed)
    size = torch.tensor([width, height], dtype=dtype)
    means2d = _uniform(gen, (n, 2), -0.1, 1.1, dtype) * size
    sx, sy = (_uniform(gen, n, *sigma_px, dtype) for _ in range(2))
    theta = _uniform(gen, n, 0.0, math.pi, dtype)
    cos, sin = theta.cos(), theta.sin()
    sxx = (cos * sx) ** 2 + (sin * sy) ** 2
    syy = (sin * sx) ** 2 + (cos * sy) ** 2
    sxy = cos * sin * (sx**2 - sy**2)
    det = sxx * syy - sxy**2
    conics = torch.stack([syy / det, -sxy / det, sxx / det], -1)
    depths = _uniform(gen, n, 0.5, 5.0, dtype)
    opacities = _uniform(gen, n, *opacity, dtype)
    colors = _uniform(gen, (n, 3), 0.0, 1.0, dtype)
    variances = _uniform(gen, n, *variance, dtype)
    return means2d, conics, depths, opacities, colors, variances


def random_gaussians(
    n: int,
    *,
    seed: int,
    dtype: torch.dtype = torch.float64,
    depth: tuple[float, float] = (1.5, 4.0),
    half_width: float = 1.5,
    scale: tuple[float, float] = (0.03, 0.12),
) -> Gaussians:
    """Random anisotropic Gaussians in front of an identity camera looking along +z."""
    gen = torch.Generator().manual_seed(seed)
    z = _uniform(gen, n, *depth, dtype)
    xy = _uniform(gen, (n, 2), -half_width, half_width, dtype) * z.unsqueeze(-1) / depth[1]
    return Gaussians(
        means=torch.cat([xy, z.unsqueeze(-1)], -1),
        log_scales=_uniform(gen, (n, 3), *scale, dtype).log(),
        quats=torch.randn((n, 4), generator=gen, dtype=dtype),
        opacity_logits=_logit(_uniform(gen, n, 0.2, 0.8, dtype)),
        colors=_uniform(gen, (n, 3), 0.0, 1.0, dtype),
        uncertainty_logits=_uniform(gen, n, -4.0, -1.0, dtype),
    )


def _box_faces(gen: torch.Generator, dtype) -> list[tuple[int, float, torch.Tensor, torch.Tensor]]:
    """Axis-aligned faces (normal axis, coordinate, low corner, high corner) of room and boxes."""
    half = torch.tensor(ROOM_HALF_EXTENT, dtype=dtype)
    faces = [(axis, sign * float(half[axis]), -half, half) for axis in range(3) for sign in (-1, 1)]
    for _ in range(6):
        size = _uniform(gen, 3, 0.4, 1.0, dtype)
        low = _uniform(gen, 3, 0.0, 1.0, dtype) * (2 * half - size) - half
        low[1] = -half[1]  # standing on the floor
        high = low + size
        faces += [(axis, float(c[axis]), low, high) for axis in range(3) for c in (low, high)]
    return faces


def room_gaussians(n: int, *, seed: int, dtype: torch.dtype = torch.float32) -> Gaussians:
    """The bench scene of docs/method.md §10: Gaussians lying flat on the walls of a
    6×3×6 m room (80%) and on six boxes (20%); view it with :func:`room_viewmat`."""
    gen = torch.Generator().manual_seed(seed)
    faces = _box_faces(gen, dtype)
    n_box = round(n * ROOM_BOX_FRACTION)
    counts = [round((n - n_box) / 6)] * 5
    counts.append(n - n_box - sum(counts))
    n_box_faces = len(faces) - 6
    counts += [n_box // n_box_faces] * (n_box_faces - 1)
    counts.append(n - sum(counts))
    means, log_scales, quats = [], [], []
    for (axis, coord, low, high), count in zip(faces, counts, strict=True):
        p = torch.rand((count, 3), generator=gen, dtype=dtype) * (high - low) + low
        p[:, axis] = coord
        means.append(p)
        s = _uniform(gen, (count, 3), *(math.log(v) for v in ROOM_SCALE_RANGE), dtype)
        s[:, axis] = math.log(FLAT_SCALE)
        log_scales.append(s)
        angle = _uniform(gen, count, 0.0, math.pi, dtype)  # in-plane rotation about the normal
        q = torch.zeros((count, 4), dtype=dtype)
        q[:, 0], q[:, 1 + axis] = (angle / 2).cos(), (angle / 2).sin()
        quats.append(q)
    return Gaussians(
        means=torch.cat(means),
        log_scales=torch.cat(log_scales),
        quats=torch.cat(quats),
        opacity_logits=_logit(_uniform(gen, n, *ROOM_OPACITY_RANGE, dtype).clamp_max(0.999)),
        colors=_uniform(gen, (n, 3), 0.0, 1.0, dtype),
        uncertainty_logits=torch.full((n,), INITIAL_UNCERTAINTY_LOGIT, dtype=dtype),
    )


def room_viewmat(dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """World-to-camera pose of the bench camera (see :data:`ROOM_CAMERA_Z`)."""
    viewmat = torch.eye(4, dtype=dtype)
    viewmat[2, 3] = -ROOM_CAMERA_Z
    return viewmat


def max_rel_error(actual: torch.Tensor, expected: torch.Tensor) -> float:
    """``max|actual − expected| / max|expected|`` (0 when both are all zero)."""
    scale = expected.abs().max().item() if expected.numel() else 0.0
    err = (actual.to(expected.dtype) - expected).abs().max().item() if expected.numel() else 0.0
    return err / scale if scale > 0 else err


def random_vjp(
    outputs: tuple[torch.Tensor, ...], inputs: list[torch.Tensor], *, seed: int
) -> tuple[torch.Tensor, ...]:
    """Gradients of ``Σ ⟨outputs, G⟩`` for seeded random upstream gradients ``G``."""
    gen = torch.Generator().manual_seed(seed)
    upstream = [
        torch.randn(o.shape, generator=gen, dtype=torch.float64).to(o.dtype) for o in outputs
    ]
    loss = sum((o * g).sum() for o, g in zip(outputs, upstream, strict=True))
    return torch.autograd.grad(loss, inputs, allow_unused=True)
