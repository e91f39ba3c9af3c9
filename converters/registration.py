"""Register a depth image into the colour camera (forward projection with a z-buffer).

Every valid depth pixel is lifted to 3-D with the depth intrinsics, moved into the colour camera
by the depth→colour extrinsic and projected with the colour intrinsics. Each pixel is splatted
over its projected footprint (so a magnifying projection leaves no holes) and the nearest
surface wins where several land on one colour pixel. The stored value is the point's depth
*in the colour camera*, so values are exact up to the output's quantisation.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

# A depth pixel covers ±0.5 px around its centre; splatting it 10 % wider closes the hairline gaps
# that rounding and slanted surfaces would leave between neighbouring footprints.
FOOTPRINT_HALF_WIDTH = 0.55


@dataclass(frozen=True)
class DepthRegistration:
    """Maps depth images of one camera into the pixel grid of another.

    `color_from_depth` is the 4x4 rigid transform taking points in the depth camera's optical
    frame to the colour camera's. `units_per_metre` is the scale of uint16 input (1 for float
    metres); the output has the input's dtype and units, 0 where no depth landed.
    """

    depth_k: np.ndarray
    depth_size: tuple[int, int]  # (width, height)
    color_k: np.ndarray
    color_size: tuple[int, int]  # (width, height)
    color_from_depth: np.ndarray
    units_per_metre: float = 1.0

    @cached_property
    def _rotated_rays(self) -> np.ndarray:
        """Viewing rays of every depth pixel (z = 1), rotated into the colour frame: (3, H*W)."""
        width, height = self.depth_size
        u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        pixels = np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
        rays = np.linalg.inv(self.depth_k) @ pixels
        return (self.color_from_depth[:3, :3] @ rays).astype(np.float32)

    @cached_property
    def _footprint_scale(self) -> tuple[float, float]:
        """Half-size of a depth pixel in colour pixels, times z_colour / z_depth."""
        fx = self.color_k[0, 0] / self.depth_k[0, 0]
        fy = self.color_k[1, 1] / self.depth_k[1, 1]
        return FOOTPRINT_HALF_WIDTH * fx, FOOTPRINT_HALF_WIDTH * fy

    def __call__(self, depth: np.ndarray) -> np.ndarray:
        """The depth image re-projected into the colour camera (same dtype and units)."""
        width, height = self.color_size
        targets, depths = self._splat(*self._project(depth))
        out = np.full(width * height, np.inf, np.float32)
        np.minimum.at(out, targets, depths)  # z-buffer: the nearest surface wins
        out[np.isinf(out)] = 0.0
        out = out.reshape(height, width)
        if depth.dtype == np.float32:
            return out
        most = np.iinfo(depth.dtype).max
        return np.clip(np.rint(out * self.units_per_metre), 0, most).astype(depth.dtype)

    def _project(self, depth: np.ndarray) -> tuple[np.ndarray, ...]:
        """Colour-image position (u, v), footprint half-sizes and colour-camera depth of every
        valid depth pixel whose footprint touches the colour image."""
        if depth.shape != self.depth_size[::-1]:
            raise ValueError(
                f"depth image is {depth.shape[1]}x{depth.shape[0]}, its CameraInfo says "
                f"{self.depth_size[0]}x{self.depth_size[1]}"
            )
        flat = depth.reshape(-1)
        valid = np.flatnonzero(flat > 0)
        z = flat[valid].astype(np.float32) / np.float32(self.units_per_metre)
        translation = self.color_from_depth[:3, 3].astype(np.float32)
        x, y, z_color = self._rotated_rays[:, valid] * z + translation[:, None]
        k = self.color_k
        with np.errstate(divide="ignore", invalid="ignore"):  # points behind: culled below
            u, v = k[0, 0] * x / z_color + k[0, 2], k[1, 1] * y / z_color + k[1, 2]
            scale_u, scale_v = self._footprint_scale
            half_u, half_v = scale_u * z / z_color, scale_v * z / z_color
        width, height = self.color_size
        inside = (z_color > 0) & (u + half_u >= 0) & (u - half_u <= width - 1)
        inside &= (v + half_v >= 0) & (v - half_v <= height - 1)  # reaches a pixel centre
        return u[inside], v[inside], half_u[inside], half_v[inside], z_color[inside]

    def _splat(
        self, u: np.ndarray, v: np.ndarray, half_u: np.ndarray, half_v: np.ndarray, z: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Flat indices of the colour pixels whose centres each footprint covers, with the
        point's depth.

        Loops over the few columns and rows one footprint can span (2x2 for magnifications up to
        about 1.8), each step vectorised over all points.
        """
        width, height = self.color_size
        col_lo, col_hi = np.ceil(u - half_u).astype(np.int64), np.floor(u + half_u).astype(np.int64)
        row_lo, row_hi = np.ceil(v - half_v).astype(np.int64), np.floor(v + half_v).astype(np.int64)
        span_u = int((col_hi - col_lo).max(initial=0)) + 1
        span_v = int((row_hi - row_lo).max(initial=0)) + 1
        targets, depths = [], []
        for dv in range(span_v):
            rows = row_lo + dv
            row_ok = (rows <= row_hi) & (rows >= 0) & (rows < height)
            for du in range(span_u):
                cols = col_lo + du
                hit = row_ok & (cols <= col_hi) & (cols >= 0) & (cols < width)
                targets.append(rows[hit] * width + cols[hit])
                depths.append(z[hit])
        return np.concatenate(targets), np.concatenate(depths)
