"""Numba kernels of the tile rasterizer (forward, backward, per-Gaussian reduction).

Layout: ``feats[M, 4]`` holds RGB and the camera depth of each Gaussian, so colour and depth are
composited by the same loop. Work is split over screen tiles of ``TILE_SIZE`` pixels; within a
tile the Gaussians (depth sorted) form the outer loop and only the pixels of their opacity-aware
bounding box are visited. The backward walks each tile back to front and writes one gradient
slot per (tile, Gaussian) intersection; :func:`reduce_slots` sums the slots of each Gaussian in a
fixed order, so results never depend on the thread count.

Work is dealt round-robin to ``n_chunks`` parallel chunks (pass ``numba.get_num_threads()``);
the chunking never changes a result. All floating-point constants enter through the typed
``consts`` array (see :func:`raster_consts`): numba types Python float literals as float64 and
would silently promote float32 kernels.
"""

import math

import numba
import numpy as np

from .constants import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE_SIZE

N_FEAT = 4
"""Composited features per Gaussian: R, G, B, depth."""

N_SLOT = 11
"""Gradient slot entries: mean x, y; conic a, b, c; opacity; 4 features; variance ``v``."""

TILE_PIXELS = TILE_SIZE * TILE_SIZE

(K_ALPHA_MAX, K_ALPHA_MIN, K_T_MIN, K_ZERO, K_HALF, K_ONE, K_TWO, K_SIGMA_MAX, K_LOG2E, K_LN2,
 K_ROUND) = range(11)  # fmt: skip
FLOAT32_ROUND = 1.5 * 2.0**23
"""Adding and subtracting it rounds a float32 to the nearest integer."""
K_INV = 11
"""``consts[K_INV + k] = 1/k`` for k = 0..EXP_DEGREE (entry 0 unused)."""
EXP_DEGREE = 6
"""Taylor degree of the float32 ``e^x`` on ``|x| ≤ ln2/2`` (measured relative error < 5e-7)."""
K_POW2 = K_INV + EXP_DEGREE + 1
"""``consts[K_POW2 + n] = 2^-n`` for the table-and-polynomial float32 ``exp``."""
SIGMA_MAX = math.log(1 / ALPHA_MIN) + 1e-3
"""Beyond this ``σ``, ``α ≤ e^-σ < 1/255`` for any opacity ≤ 1: the pixel is skipped exactly."""
POW2_ENTRIES = round(SIGMA_MAX / math.log(2)) + 1

FASTMATH = {"contract", "arcp", "nsz"}
"""LLVM fast-math flags of the hot kernels: FMA contraction and reciprocal rewrites only (about
25% off the backward). No reassociation, so sums keep their order (determinism) and the float32
rounding trick of :func:`exp_neg` survives."""

SLOT_STRIDE = 4 * N_SLOT
"""Row stride of the per-chunk slot accumulators (padding against false sharing)."""

S_MEAN, S_CONIC, S_OPACITY, S_FEAT, S_VAR = 0, 2, 5, 6, 10
"""Offsets of the parameter groups in a gradient slot."""


def raster_consts(dtype: np.dtype) -> np.ndarray:
    """The typed constants array of the kernels in ``dtype``."""
    values = [ALPHA_MAX, ALPHA_MIN, T_MIN, 0.0, 0.5, 1.0, 2.0, SIGMA_MAX, 1 / math.log(2)]
    values += [math.log(2), FLOAT32_ROUND, 0.0] + [1.0 / k for k in range(1, EXP_DEGREE + 1)]
    values += [2.0**-n for n in range(POW2_ENTRIES)]
    return np.array(values, dtype=dtype)


@numba.njit(cache=True, fastmath=FASTMATH)
def exp_neg(sigma, fast, consts):
    """``e^-σ`` for ``0 ≤ σ ≤ SIGMA_MAX``: libm, or with ``fast`` (the float32 path) a
    ``2^-n`` table times a degree-6 Taylor polynomial on ``|x| ≤ ln2/2``: a few float32 ulps,
    and about 1.6× cheaper than the libm call (which took ~40% of the forward)."""
    if not fast:
        return math.exp(-sigma)
    t = sigma * consts[K_LOG2E]
    n = (t + consts[K_ROUND]) - consts[K_ROUND]  # round to nearest (float32, |t| < 2^22)
    y = (n - t) * consts[K_LN2]
    p = consts[K_ONE]
    for k in range(EXP_DEGREE, 0, -1):
        p = consts[K_ONE] + y * consts[K_INV + k] * p
    return p * consts[K_POW2 + int(n)]


@numba.njit(cache=True)
def pixel_rect(mx, my, a, b, c, opacity, width, height):
    """Inclusive pixel range ``(x0, x1, y0, y1)`` of the ellipse ``{σ ≤ ln(o/α_min)}``.

    Outside it ``α < 1/255``, so the Gaussian is skipped there anyway; ``x0 > x1`` means empty.
    Computed in float64 on purpose: the result is an integer range, not a rendered value.
    """
    level = 2.0 * math.log(float(opacity) / ALPHA_MIN)
    if not level > 0.0:
        return 0, -1, 0, -1
    a, b, c = float(a), float(b), float(c)
    det = a * c - b * b
    half_w = math.sqrt(c / det * level)
    half_h = math.sqrt(a / det * level)
    x0 = max(math.ceil(float(mx) - half_w), 0)
    x1 = min(math.floor(float(mx) + half_w), width - 1)
    y0 = max(math.ceil(float(my) - half_h), 0)
    y1 = min(math.floor(float(my) + half_h), height - 1)
    return x0, x1, y0, y1


@numba.njit(parallel=True, cache=True)
def compute_rects(means2d, conics, opacities, width, height):
    """Pixel rectangles [M, 4] = (x0, x1, y0, y1) of all Gaussians (see :func:`pixel_rect`)."""
    n = means2d.shape[0]
    rects = np.empty((n, 4), np.int64)
    for g in numba.prange(n):
        rects[g, 0], rects[g, 1], rects[g, 2], rects[g, 3] = pixel_rect(
            means2d[g, 0], means2d[g, 1], conics[g, 0], conics[g, 1], conics[g, 2],
            opacities[g], width, height,
        )  # fmt: skip
    return rects


@numba.njit(cache=True)
def bin_tiles(rects, order, tiles_x, n_tiles):
    """Counting sort of (tile, Gaussian) intersections by tile, depth ordered within a tile.

    Returns ``tile_start[n_tiles+1]`` and ``isect_gauss`` (the tile lists), plus the per-Gaussian
    CSR ``gauss_start[M+1]`` / ``isect_slot`` that lists each Gaussian's intersections.
    """
    n = rects.shape[0]
    tile_start = np.zeros(n_tiles + 1, np.int64)
    gauss_start = np.zeros(n + 1, np.int64)
    for g in range(n):
        count = 0
        if rects[g, 0] <= rects[g, 1] and rects[g, 2] <= rects[g, 3]:
            for ty in range(rects[g, 2] // TILE_SIZE, rects[g, 3] // TILE_SIZE + 1):
                for tx in range(rects[g, 0] // TILE_SIZE, rects[g, 1] // TILE_SIZE + 1):
                    tile_start[ty * tiles_x + tx + 1] += 1
                    count += 1
        gauss_start[g + 1] = gauss_start[g] + count
    for t in range(n_tiles):
        tile_start[t + 1] += tile_start[t]
    cursor = tile_start[:-1].copy()
    isect_gauss = np.empty(tile_start[n_tiles], np.int64)
    isect_slot = np.empty(tile_start[n_tiles], np.int64)
    for g in order:
        j = gauss_start[g]
        if j == gauss_start[g + 1]:
            continue
        for ty in range(rects[g, 2] // TILE_SIZE, rects[g, 3] // TILE_SIZE + 1):
            for tx in range(rects[g, 0] // TILE_SIZE, rects[g, 1] // TILE_SIZE + 1):
                t = ty * tiles_x + tx
                isect_gauss[cursor[t]] = g
                isect_slot[j] = cursor[t]
                cursor[t] += 1
                j += 1
    return tile_start, isect_gauss, isect_slot, gauss_start


@numba.njit(parallel=True, cache=True, fastmath=FASTMATH)
def raster_fwd(
    means2d, conics, opacities, feats, variances, rects, tile_start, isect_gauss,
    xs, ys, consts, n_chunks, out_feat, out_trans, out_var, out_dvdf, out_last,
):  # fmt: skip
    """Front-to-back compositing of features, alpha and opacity-induced variances.

    Per pixel: ``out_feat = Σ f_i α_i T_i``, ``out_trans = T_final = 1 − A``,
    ``out_var = max(0, Σ v_i T_i² (f_i − F)²)`` via shifted moments about the first contributor,
    ``out_dvdf = Σ v_i T_i² (f_i − F)`` (for the backward) and ``out_last`` = index of the last
    contributing intersection (−1 if none).
    """
    height, width = out_trans.shape
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    n_tiles = tiles_x * ((height + TILE_SIZE - 1) // TILE_SIZE)
    alpha_max, alpha_min, t_min = consts[K_ALPHA_MAX], consts[K_ALPHA_MIN], consts[K_T_MIN]
    sigma_max, fast_exp = consts[K_SIGMA_MAX], feats.itemsize == 4
    half, one, two, zero = consts[K_HALF], consts[K_ONE], consts[K_TWO], consts[K_ZERO]
    for chunk in numba.prange(n_chunks):
        trans = np.empty(TILE_PIXELS, feats.dtype)
        done = np.empty(TILE_PIXELS, np.bool_)
        last = np.empty(TILE_PIXELS, np.int64)
        s0 = np.empty(TILE_PIXELS, feats.dtype)
        acc = np.empty((TILE_PIXELS, N_FEAT), feats.dtype)
        ref = np.empty((TILE_PIXELS, N_FEAT), feats.dtype)
        s1 = np.empty((TILE_PIXELS, N_FEAT), feats.dtype)
        s2 = np.empty((TILE_PIXELS, N_FEAT), feats.dtype)
        for tile in range(chunk, n_tiles, n_chunks):
            px0 = (tile % tiles_x) * TILE_SIZE
            py0 = (tile // tiles_x) * TILE_SIZE
            px1 = min(px0 + TILE_SIZE, width)
            py1 = min(py0 + TILE_SIZE, height)
            trans[:] = one
            done[:] = False
            last[:] = -1
            s0[:] = zero
            acc[:] = zero
            ref[:] = zero
            s1[:] = zero
            s2[:] = zero
            n_active = (px1 - px0) * (py1 - py0)
            for k in range(tile_start[tile], tile_start[tile + 1]):
                if n_active == 0:  # every pixel of the tile has terminated
                    break
                g = isect_gauss[k]
                mx, my = means2d[g, 0], means2d[g, 1]
                a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
                o, v = opacities[g], variances[g]
                for py in range(max(rects[g, 2], py0), min(rects[g, 3] + 1, py1)):
                    dy = ys[py] - my
                    row = (py - py0) * TILE_SIZE - px0
                    for px in range(max(rects[g, 0], px0), min(rects[g, 1] + 1, px1)):
                        p = row + px
                        if done[p]:
                            continue
                        dx = xs[px] - mx
                        sigma = half * (a * dx * dx + c * dy * dy) + b * dx * dy
                        if sigma > sigma_max:
                            continue
                        alpha = min(alpha_max, o * exp_neg(sigma, fast_exp, consts))
                        if alpha < alpha_min:
                            continue
                        t_old = trans[p]
                        t_new = t_old * (one - alpha)
                        if t_new < t_min:
                            done[p] = True
                            n_active -= 1
                            continue
                        if last[p] < 0:
                            ref[p, :] = feats[g, :]
                        w = alpha * t_old
                        u = v * t_old * t_old
                        s0[p] += u
                        for ch in range(N_FEAT):
                            f = feats[g, ch]
                            d = f - ref[p, ch]
                            acc[p, ch] += f * w
                            s1[p, ch] += u * d
                            s2[p, ch] += u * d * d
                        trans[p] = t_new
                        last[p] = k
            for py in range(py0, py1):
                for px in range(px0, px1):
                    p = (py - py0) * TILE_SIZE + px - px0
                    out_trans[py, px] = trans[p]
                    out_last[py, px] = last[p]
                    for ch in range(N_FEAT):
                        delta = acc[p, ch] - ref[p, ch]
                        var = s2[p, ch] - two * delta * s1[p, ch] + delta * delta * s0[p]
                        out_feat[py, px, ch] = acc[p, ch]
                        out_var[py, px, ch] = max(var, zero)
                        out_dvdf[py, px, ch] = s1[p, ch] - delta * s0[p]


@numba.njit(parallel=True, cache=True, fastmath=FASTMATH)
def raster_bwd(
    means2d, conics, opacities, feats, variances, rects, tile_start, isect_gauss,
    xs, ys, consts, n_chunks, full_grad, out_feat, out_trans, out_dvdf, out_last,
    grad_feat, grad_alpha, grad_var, slots,
):  # fmt: skip
    """Back-to-front vector-Jacobian product of :func:`raster_fwd`, one slot per intersection.

    ``slots[k]`` receives the gradient of intersection ``k`` with respect to
    (mean x, mean y, conic a, b, c, opacity, features ×4, v). ``full_grad`` adds the dependence
    of ``T_i²`` in the variances on the alphas in front of Gaussian i (dropped by the authors).
    """
    height, width = out_trans.shape
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    n_tiles = tiles_x * ((height + TILE_SIZE - 1) // TILE_SIZE)
    alpha_max, alpha_min = consts[K_ALPHA_MAX], consts[K_ALPHA_MIN]
    sigma_max, fast_exp = consts[K_SIGMA_MAX], feats.itemsize == 4
    half, one, two, zero = consts[K_HALF], consts[K_ONE], consts[K_TWO], consts[K_ZERO]
    slot_acc = np.empty((n_chunks, SLOT_STRIDE), feats.dtype)
    for chunk in numba.prange(n_chunks):
        trans = np.empty(TILE_PIXELS, feats.dtype)
        t_final = np.empty(TILE_PIXELS, feats.dtype)
        last = np.empty(TILE_PIXELS, np.int64)
        g_alpha = np.empty(TILE_PIXELS, feats.dtype)
        r_sum = np.empty(TILE_PIXELS, feats.dtype)
        fin = np.empty((TILE_PIXELS, N_FEAT), feats.dtype)
        g_fin = np.empty((TILE_PIXELS, N_FEAT), feats.dtype)
        g_v = np.empty((TILE_PIXELS, N_FEAT), feats.dtype)
        g_behind = np.empty(TILE_PIXELS, feats.dtype)  # Σ_{j behind} w_j ⟨∂L/∂F, f_j⟩
        acc = slot_acc[chunk, :N_SLOT]
        for tile in range(chunk, n_tiles, n_chunks):
            px0 = (tile % tiles_x) * TILE_SIZE
            py0 = (tile // tiles_x) * TILE_SIZE
            px1 = min(px0 + TILE_SIZE, width)
            py1 = min(py0 + TILE_SIZE, height)
            k_end = tile_start[tile]  # one past the last contributor of the tile
            for py in range(py0, py1):
                for px in range(px0, px1):
                    p = (py - py0) * TILE_SIZE + px - px0
                    trans[p] = out_trans[py, px]
                    t_final[p] = out_trans[py, px]
                    last[p] = out_last[py, px]
                    k_end = max(k_end, last[p] + 1)
                    g_alpha[p] = grad_alpha[py, px]
                    r_sum[p] = zero
                    g_behind[p] = zero
                    for ch in range(N_FEAT):
                        fin[p, ch] = out_feat[py, px, ch]
                        g_v[p, ch] = grad_var[py, px, ch]
                        # V depends on F: ∂V/∂F = −2 Σ v_i T_i² (f_i − F).
                        g_fin[p, ch] = (
                            grad_feat[py, px, ch] - two * g_v[p, ch] * out_dvdf[py, px, ch]
                        )
            for k in range(k_end, tile_start[tile + 1]):  # behind every pixel's last contributor
                slots[k, :] = zero
            for k in range(k_end - 1, tile_start[tile] - 1, -1):
                g = isect_gauss[k]
                mx, my = means2d[g, 0], means2d[g, 1]
                a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
                o, v = opacities[g], variances[g]
                acc[:] = zero
                for py in range(max(rects[g, 2], py0), min(rects[g, 3] + 1, py1)):
                    dy = ys[py] - my
                    row = (py - py0) * TILE_SIZE - px0
                    for px in range(max(rects[g, 0], px0), min(rects[g, 1] + 1, px1)):
                        p = row + px
                        if k > last[p]:
                            continue
                        dx = xs[px] - mx
                        sigma = half * (a * dx * dx + c * dy * dy) + b * dx * dy
                        if sigma > sigma_max:
                            continue
                        gauss = exp_neg(sigma, fast_exp, consts)
                        raw = o * gauss
                        alpha = min(alpha_max, raw)
                        if alpha < alpha_min:
                            continue
                        inv = one / (one - alpha)
                        t_i = trans[p] * inv
                        w = alpha * t_i
                        u = v * t_i * t_i
                        q = zero
                        g_dot_f = zero
                        for ch in range(N_FEAT):
                            f = feats[g, ch]
                            diff = f - fin[p, ch]
                            acc[S_FEAT + ch] += w * g_fin[p, ch] + two * g_v[p, ch] * u * diff
                            q += g_v[p, ch] * diff * diff
                            g_dot_f += g_fin[p, ch] * f
                        # ∂F/∂α_i = f_i T_i − (Σ_{j>i} f_j w_j)/(1 − α_i), dotted with ∂L/∂F.
                        d_alpha = t_i * g_dot_f + (g_alpha[p] * t_final[p] - g_behind[p]) * inv
                        g_behind[p] += w * g_dot_f
                        if full_grad:
                            d_alpha -= two * r_sum[p] * inv
                        acc[S_VAR] += t_i * t_i * q
                        r_sum[p] += q * u
                        trans[p] = t_i
                        if raw < alpha_max:
                            acc[S_OPACITY] += d_alpha * gauss
                            d_sigma = -d_alpha * raw
                            acc[S_MEAN] -= d_sigma * (a * dx + b * dy)
                            acc[S_MEAN + 1] -= d_sigma * (b * dx + c * dy)
                            acc[S_CONIC] += d_sigma * half * dx * dx
                            acc[S_CONIC + 1] += d_sigma * dx * dy
                            acc[S_CONIC + 2] += d_sigma * half * dy * dy
                slots[k, :] = acc


@numba.njit(parallel=True, cache=True)
def reduce_slots(slots, isect_slot, gauss_start, out):
    """``out[g] = Σ slots`` over Gaussian g's intersections, in a fixed (tile) order."""
    for g in numba.prange(out.shape[0]):
        out[g, :] = 0
        for j in range(gauss_start[g], gauss_start[g + 1]):
            out[g, :] += slots[isect_slot[j], :]
