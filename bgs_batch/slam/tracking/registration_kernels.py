"""Numba kernels of the dense RGB-D registration (`registration`): one pyramid level's residuals
and their Gauss-Newton normal equations, each in one pass over the source points.

Per source point, with x = T p its position in the target camera:

- geometric: the point-to-plane distance n·(x − v) to the target surface point v at the pixel x
  projects to (rounded), with Jacobian (n, x × n) for the left twist ξ = (ρ, φ); not associated
  where that pixel has no depth or normal, or v is ``max_distance`` or more away;
- photometric: I_t(π(x)) − I_s(p), the target intensity sampled bilinearly where all four
  pixels have depth, with Jacobian (g, x × g), g = ∇I_t · ∂π/∂x.

The torch version of the same sums took ~40 small-tensor operations per Gauss-Newton step (8 %
of a run). The normal equations are summed over ``SUM_CHUNKS`` fixed runs of points in
parallel, each in point order (geometric, then photometric term of each point), then over the
runs in order: the same input gives the same bits on any number of threads.
"""

from __future__ import annotations

import math

import numba
import numpy as np

MIN_DEPTH = 1e-6
"""Points at or behind this camera depth (m) project nowhere."""
JACOBIAN = 6
SUM_CHUNKS = 8
"""Runs of points whose normal equations are summed in parallel: a constant, so the order of
the sums never depends on the thread count."""


@numba.njit(cache=True, inline="always")
def _moved(points, i, transform):
    """Source point i in the target camera: ``R p + t`` of the 4×4 `transform`."""
    p0, p1, p2 = points[i, 0], points[i, 1], points[i, 2]
    t = transform
    x = t[0, 0] * p0 + t[0, 1] * p1 + t[0, 2] * p2 + t[0, 3]
    y = t[1, 0] * p0 + t[1, 1] * p1 + t[1, 2] * p2 + t[1, 3]
    return x, y, t[2, 0] * p0 + t[2, 1] * p1 + t[2, 2] * p2 + t[2, 3]


@numba.njit(cache=True, inline="always")
def _twist_row(x, y, z, gx, gy, gz, jac):
    """``jac = (g, x × g)``: the row of ∂r/∂ξ of a residual whose gradient in x is g."""
    jac[0], jac[1], jac[2] = gx, gy, gz
    jac[3], jac[4], jac[5] = y * gz - z * gy, z * gx - x * gz, x * gy - y * gx


@numba.njit(cache=True)
def geometric_term(x, y, z, surface, normals, has_depth, camera, height, width, max_distance,
                   jac):  # fmt: skip
    """(associated, point-to-plane residual) of the target-camera point (x, y, z); its Jacobian
    row goes to `jac`. `camera` is (fx, fy, cx, cy); target images are flattened [H·W, ...]."""
    if not z > MIN_DEPTH:
        return False, 0.0
    col = np.rint(camera[0] * x / z + camera[2])
    row = np.rint(camera[1] * y / z + camera[3])
    if not (0 <= col < width and 0 <= row < height):
        return False, 0.0
    pixel = int(row) * width + int(col)
    nx, ny, nz = normals[pixel, 0], normals[pixel, 1], normals[pixel, 2]
    if not has_depth[pixel] or (nx == 0 and ny == 0 and nz == 0):
        return False, 0.0
    ox, oy, oz = x - surface[pixel, 0], y - surface[pixel, 1], z - surface[pixel, 2]
    if not math.sqrt(ox * ox + oy * oy + oz * oz) < max_distance:
        return False, 0.0
    _twist_row(x, y, z, nx, ny, nz, jac)
    return True, nx * ox + ny * oy + nz * oz


@numba.njit(cache=True)
def photometric_term(x, y, z, intensity, gray, gradient, has_depth, camera, height, width, jac):
    """(sampled, intensity residual) of the target-camera point (x, y, z) whose source intensity
    is `intensity`; its Jacobian row goes to `jac`. Sampled where the four pixels around its
    projection all have depth."""
    if not z > MIN_DEPTH:
        return False, 0.0
    fx, fy = camera[0], camera[1]
    u, v = fx * x / z + camera[2], fy * y / z + camera[3]
    u0, v0 = math.floor(u), math.floor(v)
    if not (0 <= u0 < width - 1 and 0 <= v0 < height - 1):
        return False, 0.0
    k = int(v0) * width + int(u0)
    corners = (k, k + 1, k + width, k + width + 1)
    for c in corners:
        if not has_depth[c]:
            return False, 0.0
    fu, fv = u - u0, v - v0
    weights = ((1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv)
    sample = grad_u = grad_v = 0.0
    for q in range(4):
        c, weight = corners[q], weights[q]
        sample += weight * gray[c]
        grad_u += weight * gradient[c, 0]
        grad_v += weight * gradient[c, 1]
    inv_z = 1.0 / z
    # ∂I/∂x through the pinhole: (g_u fx / z, g_v fy / z, −(g_u fx x + g_v fy y) / z²)
    g_u, g_v = grad_u * fx * inv_z, grad_v * fy * inv_z
    _twist_row(x, y, z, g_u, g_v, -(g_u * x + g_v * y) * inv_z, jac)
    return True, sample - intensity


@numba.njit(cache=True)
def residuals(points, intensities, transform, surface, normals, has_depth, gray, gradient,
              camera, height, width, max_distance):  # fmt: skip
    """The geometric and the photometric residuals [M_g], [M_p] of the associated points, in
    point order, at `transform`."""
    n = points.shape[0]
    geometric, photometric = np.empty(n), np.empty(n)
    n_geometric = n_photometric = 0
    jac = np.empty(JACOBIAN)
    for i in range(n):
        x, y, z = _moved(points, i, transform)
        ok, r = geometric_term(x, y, z, surface, normals, has_depth, camera, height, width,
                               max_distance, jac)  # fmt: skip
        if ok:
            geometric[n_geometric] = r
            n_geometric += 1
        ok, r = photometric_term(x, y, z, intensities[i], gray, gradient, has_depth, camera,
                                 height, width, jac)  # fmt: skip
        if ok:
            photometric[n_photometric] = r
            n_photometric += 1
    return geometric[:n_geometric], photometric[:n_photometric]


UPPER = JACOBIAN * (JACOBIAN + 1) // 2
"""Entries of the normal matrix's upper triangle, row by row: a chunk's sums are kept flat."""


@numba.njit(cache=True, inline="always")
def _add_huber_term(r, scale, huber_k, jac, sums):
    """Add one residual, divided by its term's `scale` and Huber-weighted, to ``Jᵀ W J``'s
    upper triangle (``sums[:UPPER]``, row by row) and ``Jᵀ W r`` (``sums[UPPER:]``)."""
    scaled = r / scale
    magnitude = abs(scaled)
    weight = 1.0 if magnitude <= huber_k else huber_k / max(magnitude, 1e-30)
    j0, j1, j2 = jac[0] / scale, jac[1] / scale, jac[2] / scale
    j3, j4, j5 = jac[3] / scale, jac[4] / scale, jac[5] / scale
    rows = (j0, j1, j2, j3, j4, j5)
    weighted = (weight * j0, weight * j1, weight * j2, weight * j3, weight * j4, weight * j5)
    k = 0
    for a in range(JACOBIAN):
        sums[UPPER + a] += rows[a] * (weight * scaled)
        for b in range(a, JACOBIAN):
            sums[k] += rows[a] * weighted[b]
            k += 1


@numba.njit(parallel=True, cache=True)
def normal_equations(points, intensities, transform, surface, normals, has_depth, gray,
                     gradient, camera, height, width, max_distance, geometric_scale,
                     photometric_scale, huber_k):  # fmt: skip
    """``(Jᵀ W J [6, 6], Jᵀ W r [6], residuals used)`` at `transform`, each term's residuals
    divided by its scale and weighted by Huber's function (threshold `huber_k`).

    Each chunk sums into an array of its own and writes it out once at its end, so that no two
    threads write to one cache line point by point; the sums and their order are unchanged."""
    n = points.shape[0]
    chunk_sums = np.zeros((SUM_CHUNKS, UPPER + JACOBIAN))
    chunk_used = np.zeros(SUM_CHUNKS, np.int64)
    for chunk in numba.prange(SUM_CHUNKS):
        sums = np.zeros(UPPER + JACOBIAN)
        jac = np.empty(JACOBIAN)
        used = 0
        for i in range(chunk * n // SUM_CHUNKS, (chunk + 1) * n // SUM_CHUNKS):
            x, y, z = _moved(points, i, transform)
            ok, r = geometric_term(x, y, z, surface, normals, has_depth, camera, height, width,
                                   max_distance, jac)  # fmt: skip
            if ok:
                _add_huber_term(r, geometric_scale, huber_k, jac, sums)
                used += 1
            ok, r = photometric_term(x, y, z, intensities[i], gray, gradient, has_depth,
                                     camera, height, width, jac)  # fmt: skip
            if ok:
                _add_huber_term(r, photometric_scale, huber_k, jac, sums)
                used += 1
        chunk_sums[chunk] = sums
        chunk_used[chunk] = used
    total = chunk_sums[0].copy()
    for chunk in range(1, SUM_CHUNKS):
        total += chunk_sums[chunk]
    normal = np.empty((JACOBIAN, JACOBIAN))
    k = 0
    for a in range(JACOBIAN):
        for b in range(a, JACOBIAN):
            normal[a, b] = normal[b, a] = total[k]
            k += 1
    return normal, total[UPPER:].copy(), chunk_used.sum()
