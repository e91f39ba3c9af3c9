"""Numba kernels of the fused EWA projection and its analytic backward (pose included).

Per Gaussian: ``p = R μ + t`` (world-to-camera ``viewmat = [R t]``), ``M = R_q(q̂)·diag(e^s)``,
``K = J R M`` with the perspective Jacobian ``J`` at ``p``, screen covariance
``Σ₂ = K Kᵀ + 0.3·I``, conic ``Σ₂⁻¹`` and depth slope ``s = Σ_s⁻¹ q`` with ``q = K Mᵀ Rᵀ e_z``
= ``Cov(p, z)`` and ``Σ_s = K Kᵀ + ε·tr(K Kᵀ)·I`` (the screen gradient of the depth of the
Gaussian's plane: the mean of z given the pixel; ε = ``SLOPE_RIDGE``). The backward is the
hand-derived chain rule of these steps; the pose gradient is reduced serially over Gaussians,
so it is deterministic.
All floating-point constants enter through the typed ``params`` array (see
:func:`project_params`), which keeps float32 kernels in float32.
"""

import math

import numba
import numpy as np

from ._numba_raster import pixel_rect
from .camera import Camera
from .constants import FRUSTUM_MARGIN, LOWPASS, NEAR_PLANE, SLOPE_RIDGE

(P_FX, P_FY, P_CX, P_CY, P_LOWPASS, P_NEAR, P_CENTRE_X, P_CENTRE_Y, P_GUARD_X, P_GUARD_Y,
 P_ZERO, P_HALF, P_ONE, P_TWO, P_RIDGE) = range(15)  # fmt: skip

N_POSE = 12
"""Pose gradient entries: ∂L/∂R (row-major 3×3), then ∂L/∂t."""

SCRATCH_ROWS = 32
"""Rows of 3 floats of per-chunk scratch: 19 used, the rest keeps chunks on separate cache
lines (tiny per-thread arrays that share a cache line cost several times in false sharing)."""


GAUSS_BLOCK = 1024
"""Gaussians are dealt to chunks in blocks of this size, round-robin: blocks avoid false
sharing of output rows, dealing them balances maps whose visible part is not uniform in index."""


def project_params(camera: Camera | None, dtype: np.dtype) -> np.ndarray:
    """The typed parameter array of the projection kernels for ``camera`` (None: only the
    numeric constants, enough for :func:`shape_matrices`)."""
    values = [0.0] * 15
    values[P_HALF], values[P_ONE], values[P_TWO] = 0.5, 1.0, 2.0
    if camera is None:
        return np.array(values, dtype=dtype)
    values[P_FX], values[P_FY], values[P_CX], values[P_CY] = (
        camera.fx, camera.fy, camera.cx, camera.cy,
    )  # fmt: skip
    values[P_LOWPASS], values[P_NEAR], values[P_RIDGE] = LOWPASS, NEAR_PLANE, SLOPE_RIDGE
    values[P_CENTRE_X], values[P_CENTRE_Y] = (camera.width - 1) / 2, (camera.height - 1) / 2
    values[P_GUARD_X] = FRUSTUM_MARGIN * camera.width / 2
    values[P_GUARD_Y] = FRUSTUM_MARGIN * camera.height / 2
    return np.array(values, dtype=dtype)


@numba.njit(cache=True)
def _views(work):
    """Scratch views ``rot`` [3,3], ``m`` [3,3], ``t2`` [2,3], ``k`` [2,3] of :func:`_shape` and
    :func:`_view`."""
    return work[0:3], work[3:6], work[6:8], work[8:10]


@numba.njit(cache=True)
def _camera_point(mean, viewmat):
    """The camera-space centre ``(x, y, z) = R μ + t``."""
    x = viewmat[0, 0] * mean[0] + viewmat[0, 1] * mean[1] + viewmat[0, 2] * mean[2] + viewmat[0, 3]
    y = viewmat[1, 0] * mean[0] + viewmat[1, 1] * mean[1] + viewmat[1, 2] * mean[2] + viewmat[1, 3]
    z = viewmat[2, 0] * mean[0] + viewmat[2, 1] * mean[1] + viewmat[2, 2] * mean[2] + viewmat[2, 3]
    return x, y, z


@numba.njit(cache=True)
def _shape(log_scale, quat, params, rot, m):
    """The view-independent part of one Gaussian's covariance: fills ``rot`` = R_q(q̂) and
    ``m`` = R_q·diag(e^s)."""
    one, two = params[P_ONE], params[P_TWO]
    norm = math.sqrt(quat[0] ** 2 + quat[1] ** 2 + quat[2] ** 2 + quat[3] ** 2)
    w, qx, qy, qz = quat[0] / norm, quat[1] / norm, quat[2] / norm, quat[3] / norm
    rot[0, 0] = one - two * (qy * qy + qz * qz)
    rot[0, 1] = two * (qx * qy - w * qz)
    rot[0, 2] = two * (qx * qz + w * qy)
    rot[1, 0] = two * (qx * qy + w * qz)
    rot[1, 1] = one - two * (qx * qx + qz * qz)
    rot[1, 2] = two * (qy * qz - w * qx)
    rot[2, 0] = two * (qx * qz - w * qy)
    rot[2, 1] = two * (qy * qz + w * qx)
    rot[2, 2] = one - two * (qx * qx + qy * qy)
    for j in range(3):
        scale = math.exp(log_scale[j])
        for i in range(3):
            m[i, j] = rot[i, j] * scale


@numba.njit(cache=True)
def _view(x, y, z, viewmat, params, m, t2, k):
    """The view-dependent part for a Gaussian centred at camera point ``(x, y, z)``: fills
    ``t2`` = J·R (perspective Jacobian J, camera rotation R) and ``k`` = J·R·M."""
    zero = params[P_ZERO]
    fx, fy = params[P_FX], params[P_FY]
    j00, j02 = fx / z, -fx * x / (z * z)
    j11, j12 = fy / z, -fy * y / (z * z)
    for c in range(3):
        t2[0, c] = j00 * viewmat[0, c] + j02 * viewmat[2, c]
        t2[1, c] = j11 * viewmat[1, c] + j12 * viewmat[2, c]
    for r in range(2):
        for j in range(3):
            k[r, j] = zero
            for c in range(3):
                k[r, j] += t2[r, c] * m[c, j]


@numba.njit(cache=True)
def _depth_row(m, viewmat):
    """``w = Mᵀ Rᵀ e_z``, the camera z row of ``R M``."""
    w0 = viewmat[2, 0] * m[0, 0] + viewmat[2, 1] * m[1, 0] + viewmat[2, 2] * m[2, 0]
    w1 = viewmat[2, 0] * m[0, 1] + viewmat[2, 1] * m[1, 1] + viewmat[2, 2] * m[2, 1]
    w2 = viewmat[2, 0] * m[0, 2] + viewmat[2, 1] * m[1, 2] + viewmat[2, 2] * m[2, 2]
    return w0, w1, w2


@numba.njit(cache=True)
def _depth_slope(k, m, viewmat, params):
    """The depth slope ``s = Σ_s⁻¹ q`` (see the module docstring) and the ridge's share
    ``ε``, the inverse ``(a, b, c)`` of ``Σ_s`` and ``q``, which the backward needs."""
    w0, w1, w2 = _depth_row(m, viewmat)
    q0 = k[0, 0] * w0 + k[0, 1] * w1 + k[0, 2] * w2
    q1 = k[1, 0] * w0 + k[1, 1] * w1 + k[1, 2] * w2
    sxx = k[0, 0] ** 2 + k[0, 1] ** 2 + k[0, 2] ** 2
    sxy = k[0, 0] * k[1, 0] + k[0, 1] * k[1, 1] + k[0, 2] * k[1, 2]
    syy = k[1, 0] ** 2 + k[1, 1] ** 2 + k[1, 2] ** 2
    ridge = params[P_RIDGE] * (sxx + syy)
    sxx, syy = sxx + ridge, syy + ridge
    det = sxx * syy - sxy * sxy
    a, b, c = syy / det, -sxy / det, sxx / det
    return a * q0 + b * q1, b * q0 + c * q1, a, b, c, q0, q1


@numba.njit(parallel=True, cache=True)
def shape_matrices(log_scales, quats, params, n_chunks, out):
    """``out[i]`` = R_q(q̂_i)·diag(e^{s_i}) for every Gaussian (a fixed map's :func:`_shape`)."""
    n = log_scales.shape[0]
    scratch = np.empty((n_chunks, SCRATCH_ROWS, 3), log_scales.dtype)
    for chunk in numba.prange(n_chunks):
        rot = scratch[chunk][0:3]
        for block in range(chunk, (n + GAUSS_BLOCK - 1) // GAUSS_BLOCK, n_chunks):
            for i in range(block * GAUSS_BLOCK, min((block + 1) * GAUSS_BLOCK, n)):
                _shape(log_scales[i], quats[i], params, rot, out[i])


@numba.njit(parallel=True, cache=True)
def project_fwd(
    means, log_scales, quats, opacity_logits, viewmat, params, width, height, shapes,
    use_shapes, n_chunks, out_means2d, out_conics, out_depths, out_slopes, out_visible,
):  # fmt: skip
    """Project all Gaussians; ``out_visible`` applies near, guard-band and screen-bounds culling.

    With ``use_shapes``, M = R_q·diag(e^s) is read from ``shapes`` [N,3,3] (:func:`shape_matrices`)
    instead of being computed from ``log_scales`` and ``quats``: the same numbers, once per map."""
    n = means.shape[0]
    low, one = params[P_LOWPASS], params[P_ONE]
    scratch = np.empty((n_chunks, SCRATCH_ROWS, 3), means.dtype)
    for chunk in numba.prange(n_chunks):
        rot, m, t2, k = _views(scratch[chunk])
        for block in range(chunk, (n + GAUSS_BLOCK - 1) // GAUSS_BLOCK, n_chunks):
            for i in range(block * GAUSS_BLOCK, min((block + 1) * GAUSS_BLOCK, n)):
                x, y, z = _camera_point(means[i], viewmat)
                out_visible[i] = False
                out_depths[i] = z
                if not z > params[P_NEAR]:
                    continue
                u = params[P_FX] * x / z + params[P_CX]
                v = params[P_FY] * y / z + params[P_CY]
                out_means2d[i, 0], out_means2d[i, 1] = u, v
                if (abs(u - params[P_CENTRE_X]) > params[P_GUARD_X]
                        or abs(v - params[P_CENTRE_Y]) > params[P_GUARD_Y]):  # fmt: skip
                    continue
                shape = shapes[i] if use_shapes else m
                if not use_shapes:
                    _shape(log_scales[i], quats[i], params, rot, m)
                _view(x, y, z, viewmat, params, shape, t2, k)
                sxx = k[0, 0] ** 2 + k[0, 1] ** 2 + k[0, 2] ** 2 + low
                sxy = k[0, 0] * k[1, 0] + k[0, 1] * k[1, 1] + k[0, 2] * k[1, 2]
                syy = k[1, 0] ** 2 + k[1, 1] ** 2 + k[1, 2] ** 2 + low
                det = sxx * syy - sxy * sxy
                a, b, c = syy / det, -sxy / det, sxx / det
                out_conics[i, 0], out_conics[i, 1], out_conics[i, 2] = a, b, c
                out_slopes[i, 0], out_slopes[i, 1] = _depth_slope(k, shape, viewmat, params)[:2]
                opacity = one / (one + math.exp(-opacity_logits[i]))
                x0, x1, y0, y1 = pixel_rect(u, v, a, b, c, opacity, width, height)
                out_visible[i] = x0 <= x1 and y0 <= y1


@numba.njit(parallel=True, cache=True)
def project_bwd(
    means, log_scales, quats, viewmat, params, ids, conics,
    grad_means2d, grad_conics, grad_depths, grad_slopes, want_gaussians, shapes, use_shapes,
    n_chunks, out_means, out_log_scales, out_quats, out_pose,
):  # fmt: skip
    """VJP of :func:`project_fwd` for the visible Gaussians ``ids``.

    Writes ∂L/∂means, ∂L/∂log_scales, ∂L/∂quats at rows ``ids`` when ``want_gaussians`` (rows of
    the outputs are not cleared here), and always ``out_pose[12]`` = (∂L/∂R, ∂L/∂t).
    ``use_shapes`` (pose only, without ``want_gaussians``) reads M from ``shapes``.
    """
    n = ids.shape[0]
    zero, half, two = params[P_ZERO], params[P_HALF], params[P_TWO]
    fx, fy = params[P_FX], params[P_FY]
    contrib = np.empty((n, N_POSE), means.dtype)
    scratch = np.empty((n_chunks, SCRATCH_ROWS, 3), means.dtype)
    for chunk in numba.prange(n_chunks):
        work = scratch[chunk]
        rot, m, t2, k = _views(work)
        g2, dk, dt2, dm = work[10:12], work[12:14], work[14:16], work[16:19]
        for block in range(chunk, (n + GAUSS_BLOCK - 1) // GAUSS_BLOCK, n_chunks):
            for i in range(block * GAUSS_BLOCK, min((block + 1) * GAUSS_BLOCK, n)):
                g = ids[i]
                mean, quat = means[g], quats[g]
                x, y, z = _camera_point(mean, viewmat)
                if use_shapes:
                    m[:, :] = shapes[g]
                else:
                    _shape(log_scales[g], quat, params, rot, m)
                _view(x, y, z, viewmat, params, m, t2, k)
                # Conic (a, b, c) = Σ₂⁻¹ = P: ∂L/∂Σ₂ = −P·G·P with G = [[ga, gb/2], [gb/2, gc]].
                a, b, c = conics[i, 0], conics[i, 1], conics[i, 2]
                ga, gb, gc = grad_conics[i, 0], half * grad_conics[i, 1], grad_conics[i, 2]
                pg00, pg01 = a * ga + b * gb, a * gb + b * gc
                pg10, pg11 = b * ga + c * gb, b * gb + c * gc
                g2[0, 0] = -(pg00 * a + pg01 * b)
                g2[0, 1] = -(pg00 * b + pg01 * c)
                g2[1, 0] = -(pg10 * a + pg11 * b)
                g2[1, 1] = -(pg10 * b + pg11 * c)
                # Slope s = Σ_s⁻¹ q: ∂L/∂q = Σ_s⁻¹ ∂L/∂s, ∂L/∂Σ_s = −sym(∂L/∂q sᵀ), and
                # Σ_s = K Kᵀ + ε tr(K Kᵀ) I adds it, plus ε times its trace on the diagonal.
                s0, s1, sa, sb, sc, q0, q1 = _depth_slope(k, m, viewmat, params)
                gs0, gs1 = grad_slopes[i, 0], grad_slopes[i, 1]
                gq0, gq1 = sa * gs0 + sb * gs1, sb * gs0 + sc * gs1
                h00, h11 = -gq0 * s0, -gq1 * s1
                h01 = -half * (gq0 * s1 + gq1 * s0)
                spread = params[P_RIDGE] * (h00 + h11)
                g2[0, 0] += h00 + spread
                g2[0, 1] += h01
                g2[1, 0] += h01
                g2[1, 1] += h11 + spread
                # Σ₂, Σ_s from K Kᵀ and q = K w, K = T₂ M, T₂ = J R.
                w, gq = _depth_row(m, viewmat), (gq0, gq1)
                for r in range(2):
                    for j in range(3):
                        dk[r, j] = two * (g2[r, 0] * k[0, j] + g2[r, 1] * k[1, j]) + gq[r] * w[j]
                # ∂L/∂w, then w = Mᵀ R₂ᵀ (R₂ the camera rotation's z row)
                gw = (gq0 * k[0, 0] + gq1 * k[1, 0], gq0 * k[0, 1] + gq1 * k[1, 1],
                      gq0 * k[0, 2] + gq1 * k[1, 2])  # fmt: skip
                for r in range(2):
                    for c_ in range(3):
                        dt2[r, c_] = zero
                        for j in range(3):
                            dt2[r, c_] += dk[r, j] * m[c_, j]
                for c_ in range(3):
                    for j in range(3):
                        dm[c_, j] = (t2[0, c_] * dk[0, j] + t2[1, c_] * dk[1, j]
                                     + viewmat[2, c_] * gw[j])  # fmt: skip
                z2 = z * z
                j00, j02 = fx / z, -fx * x / z2
                j11, j12 = fy / z, -fy * y / z2
                dj00, dj02, dj11, dj12 = zero, zero, zero, zero
                for c_ in range(3):
                    dj00 += dt2[0, c_] * viewmat[0, c_]
                    dj02 += dt2[0, c_] * viewmat[2, c_]
                    dj11 += dt2[1, c_] * viewmat[1, c_]
                    dj12 += dt2[1, c_] * viewmat[2, c_]
                gu, gv = grad_means2d[i, 0], grad_means2d[i, 1]
                dx = gu * fx / z - dj02 * fx / z2
                dy = gv * fy / z - dj12 * fy / z2
                dz = (grad_depths[i] - (gu * fx * x + gv * fy * y + dj00 * fx + dj11 * fy) / z2
                      + two * (dj02 * fx * x + dj12 * fy * y) / (z2 * z))  # fmt: skip
                for c_ in range(3):
                    contrib[i, c_] = j00 * dt2[0, c_] + dx * mean[c_]
                    contrib[i, 3 + c_] = j11 * dt2[1, c_] + dy * mean[c_]
                    contrib[i, 6 + c_] = (j02 * dt2[0, c_] + j12 * dt2[1, c_] + dz * mean[c_]
                                          + m[c_, 0] * gw[0] + m[c_, 1] * gw[1] + m[c_, 2] * gw[2])
                contrib[i, 9], contrib[i, 10], contrib[i, 11] = dx, dy, dz
                if not want_gaussians:
                    continue
                for c_ in range(3):
                    out_means[g, c_] = (viewmat[0, c_] * dx + viewmat[1, c_] * dy
                                        + viewmat[2, c_] * dz)  # fmt: skip
                for j in range(3):
                    out_log_scales[g, j] = (
                        dm[0, j] * m[0, j] + dm[1, j] * m[1, j] + dm[2, j] * m[2, j]
                    )
                    scale = math.exp(log_scales[g, j])
                    for r in range(3):
                        dm[r, j] *= scale  # now ∂L/∂R_q
                _quat_vjp(quat, dm, two, out_quats[g])
    for j in range(N_POSE):  # scalar loops: an array expression here would become a parfor
        out_pose[j] = zero
    for i in range(n):  # row by row (contiguous); each entry still sums i = 0, 1, ... in order
        for j in range(N_POSE):
            out_pose[j] += contrib[i, j]


@numba.njit(cache=True)
def _quat_vjp(quat, g, two, out):
    """``out`` = ∂L/∂q for the raw quaternion ``q`` given ``g`` = ∂L/∂R_q(q/|q|)."""
    norm = math.sqrt(quat[0] ** 2 + quat[1] ** 2 + quat[2] ** 2 + quat[3] ** 2)
    w, x, y, z = quat[0] / norm, quat[1] / norm, quat[2] / norm, quat[3] / norm
    dw = two * (-z * g[0, 1] + y * g[0, 2] + z * g[1, 0] - x * g[1, 2] - y * g[2, 0] + x * g[2, 1])
    dx = two * (y * g[0, 1] + z * g[0, 2] + y * g[1, 0] - two * x * g[1, 1] - w * g[1, 2]
                + z * g[2, 0] + w * g[2, 1] - two * x * g[2, 2])  # fmt: skip
    dy = two * (-two * y * g[0, 0] + x * g[0, 1] + w * g[0, 2] + x * g[1, 0] + z * g[1, 2]
                - w * g[2, 0] + z * g[2, 1] - two * y * g[2, 2])  # fmt: skip
    dz = two * (-two * z * g[0, 0] - w * g[0, 1] + x * g[0, 2] + w * g[1, 0] - two * z * g[1, 1]
                + y * g[1, 2] + x * g[2, 0] + y * g[2, 1])  # fmt: skip
    radial = w * dw + x * dx + y * dy + z * dz
    out[0] = (dw - w * radial) / norm
    out[1] = (dx - x * radial) / norm
    out[2] = (dy - y * radial) / norm
    out[3] = (dz - z * radial) / norm
