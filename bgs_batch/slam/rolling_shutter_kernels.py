"""Numba kernels of the rolling-shutter rectification (`rolling_shutter`): where each rectified
pixel's reading comes from, and the depth sampled there moved to the middle of the readout.

The NumPy version built a dozen full-frame float64 temporaries per frame (31 ms at 640×480,
a third of a global-stage visit). These loops do the same operations per pixel in the same
order, so the rectified images are bit for bit the NumPy version's (tested), on any number of
threads: every pixel is computed on its own.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, inline="always")
def _image_motion(u, v, z, rotation, shift, fx, fy, cx, cy):
    """The pixel motion (du, dv) of the point at pixel (u, v) and depth z, read with the row's
    `rotation` (3, 3) and `shift` (3,) to the middle of the readout."""
    x, y = (u - cx) / fx * z, (v - cy) / fy * z
    mx = x * rotation[0, 0] + y * rotation[0, 1] + z * rotation[0, 2] + shift[0]
    my = x * rotation[1, 0] + y * rotation[1, 1] + z * rotation[1, 2] + shift[1]
    mz = x * rotation[2, 0] + y * rotation[2, 1] + z * rotation[2, 2] + shift[2]
    return fx * mx / mz + cx - u, fy * my / mz + cy - v


@numba.njit(cache=True, inline="always")
def _clip_index(value, upper):
    return min(max(int(np.rint(value)), 0), upper)


@numba.njit(parallel=True, cache=True)
def source_maps(z_guess, rotations, shifts, fx, fy, cx, cy, map_u, map_v):
    """Fill `map_u`, `map_v` [H,W] float64: where each rectified pixel's reading came from.

    The motion is computed at the rectified pixel with its own depth guess, then once more with
    the depth guess at the source pixel that gives (one fixed-point step); `z_guess` [H,W] is
    the depth with the median reading where it is invalid."""
    height, width = z_guess.shape
    for row in numba.prange(height):
        v = float(row)
        for col in range(width):
            u = float(col)
            du, dv = _image_motion(u, v, float(z_guess[row, col]), rotations[row], shifts[row],
                                   fx, fy, cx, cy)  # fmt: skip
            near_u = _clip_index(u - du, width - 1)
            near_v = _clip_index(v - dv, height - 1)
            du, dv = _image_motion(u, v, float(z_guess[near_v, near_u]), rotations[row],
                                   shifts[row], fx, fy, cx, cy)  # fmt: skip
            map_u[row, col] = u - du
            map_v[row, col] = v - dv


@numba.njit(parallel=True, cache=True)
def moved_depth(depth, map_u, map_v, rotations, shifts, fx, fy, cx, cy, spread, out):
    """Fill `out` [H,W] float32: the depth reading at each source position (`sample_surface`)
    moved by its source row's motion to the middle of the readout; 0 where either is not in
    front of the camera."""
    height, width = depth.shape
    for row in numba.prange(height):
        for col in range(width):
            u, v = map_u[row, col], map_v[row, col]
            z_src = sample_surface(depth, u, v, spread)
            src_row = _clip_index(v, height - 1)
            third, shift = rotations[src_row, 2], shifts[src_row, 2]
            z_new = ((((u - cx) / fx * z_src) * third[0] + ((v - cy) / fy * z_src) * third[1]
                      + z_src * third[2]) + shift)  # fmt: skip
            out[row, col] = np.float32(z_new) if z_src > 0 and z_new > 0 else np.float32(0.0)


@numba.njit(cache=True, inline="always")
def sample_surface(depth, u, v, spread):
    """Depth at the sub-pixel position (u, v): bilinear where the four readings around are
    valid and within `spread` of the nearest, else the nearest reading; 0 outside the image."""
    height, width = depth.shape
    if not (u > -0.5 and u < width - 0.5 and v > -0.5 and v < height - 0.5):
        return 0.0
    u0 = min(max(int(np.floor(u)), 0), width - 2)
    v0 = min(max(int(np.floor(v)), 0), height - 2)
    fu = min(max(u - u0, 0.0), 1.0)
    fv = min(max(v - v0, 0.0), 1.0)
    c00, c01 = float(depth[v0, u0]), float(depth[v0, u0 + 1])
    c10, c11 = float(depth[v0 + 1, u0]), float(depth[v0 + 1, u0 + 1])
    low = min(min(c00, c01), min(c10, c11))
    high = max(max(c00, c01), max(c10, c11))
    if low > 0 and high - low <= spread * low:
        return ((1 - fu) * (1 - fv) * c00 + fu * (1 - fv) * c01 + (1 - fu) * fv * c10
                + fu * fv * c11)  # fmt: skip
    return float(depth[_clip_index(v, height - 1), _clip_index(u, width - 1)])
