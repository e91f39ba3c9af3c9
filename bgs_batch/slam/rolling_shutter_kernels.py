"""Numba kernels of the rolling-shutter rectification (`rolling_shutter`): where each rectified
pixel's reading comes from, and the depth sampled there moved to the middle of the readout.

A NumPy version builds a dozen full-frame float64 temporaries per frame (31 ms at 640×480, a
third of a global-stage visit). These loops do the same operations per pixel in the same order,
so the rectified images are bit for bit the NumPy version's (the tests keep it as an oracle), on
any number of threads: every pixel is computed on its own.
"""

from __future__ import annotations

import numba
import numpy as np

# Fixed-point steps on the row that read a rectified pixel's source. With an image motion of a
# pixels over the readout of H rows, a row off by δ moves the source by δ·a/H pixels: the first
# step (the rectified pixel's own row) is off by up to a/2 rows, and each step shrinks that by
# a/H (a few %), so three leave the nearest row's rounding, ≤ a/2H pixels (0.04 at a = 20).
SOURCE_STEPS = 3


@numba.njit(cache=True, inline="always")
def _source(u, v, z, rotation, shift, fx, fy, cx, cy):
    """Where the raw image saw the point at rectified pixel (u, v) and depth z, when the row that
    read it has `rotation` (3, 3) and `shift` (3,) to the middle of the readout: that motion
    inverted, ``Rᵀ(p − t)``, and projected."""
    x = (u - cx) / fx * z - shift[0]
    y = (v - cy) / fy * z - shift[1]
    w = z - shift[2]
    mx = rotation[0, 0] * x + rotation[1, 0] * y + rotation[2, 0] * w
    my = rotation[0, 1] * x + rotation[1, 1] * y + rotation[2, 1] * w
    mz = rotation[0, 2] * x + rotation[1, 2] * y + rotation[2, 2] * w
    return fx * mx / mz + cx, fy * my / mz + cy


@numba.njit(cache=True, inline="always")
def _clip_index(value, upper):
    return min(max(int(np.rint(value)), 0), upper)


@numba.njit(parallel=True, cache=True)
def source_maps(z_guess, rotations, shifts, fx, fy, cx, cy, map_u, map_v):
    """Fill `map_u`, `map_v` [H,W] float64: where each rectified pixel's reading came from.

    The source depends on the row that read it, which depends on the source: the first step
    takes the rectified pixel's own row and depth guess, each further step (`SOURCE_STEPS`) the
    row and depth guess at the source the step before found. `z_guess` [H,W] is the depth with
    the median reading where it is invalid."""
    height, width = z_guess.shape
    for row in numba.prange(height):
        for col in range(width):
            map_u[row, col], map_v[row, col] = _fixed_point_source(
                row, col, z_guess, rotations, shifts, fx, fy, cx, cy)


@numba.njit(cache=True)
def _fixed_point_source(row, col, z_guess, rotations, shifts, fx, fy, cx, cy):
    """`source_maps` for one rectified pixel."""
    height, width = z_guess.shape
    u, v = float(col), float(row)
    src_u, src_v = u, v
    src_row, z = np.int64(row), float(z_guess[row, col])
    for _ in range(SOURCE_STEPS):
        src_u, src_v = _source(u, v, z, rotations[src_row], shifts[src_row], fx, fy, cx, cy)
        src_row = np.int64(_clip_index(src_v, height - 1))
        z = float(z_guess[src_row, _clip_index(src_u, width - 1)])
    return src_u, src_v


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
