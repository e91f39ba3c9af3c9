"""Numba kernels of the tile rasterizer (forward, backward, per-Gaussian reduction).

Layout: ``feats[M, 4]`` holds RGB and the camera depth of each Gaussian, so colour and depth are
composited by the same loop. Work is split over screen tiles of ``TILE_SIZE`` pixels; within a
tile the Gaussians (depth sorted) form the outer loop. Both passes visit the tile-wide rows of
each Gaussian's opacity-aware bounding box with branch-free loops that LLVM vectorises; the
backward walks each tile back to front and writes one gradient slot per (tile, Gaussian)
intersection; :func:`reduce_slots` sums the slots of each Gaussian in a fixed order, so results
never depend on the thread count.

Lane ranges ``p0:p1`` are unsigned (``np.uint64``) and index the per-tile arrays directly:
numba wraps negative signed indices with a select that stops LLVM from vectorising, and a slice
per range would cost two atomic reference-count updates.

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
"""Composited features per Gaussian: R, G, B, depth (the backward spells the 4 out)."""

N_SLOT = 11
"""Gradient slot entries: mean x, y; conic a, b, c; opacity; 4 features; variance ``v``."""

TILE_PIXELS = TILE_SIZE * TILE_SIZE

(K_ALPHA_MAX, K_ALPHA_MIN, K_T_MIN, K_ZERO, K_HALF, K_ONE, K_TWO, K_SIGMA_MAX,
 K_EXP_SCALE) = range(9)  # fmt: skip
K_INV = 9
"""``consts[K_INV + k] = 1/k`` for k = 0..EXP_DEGREE (entry 0 unused)."""
EXP_DEGREE = 7
"""Taylor degree of the float32 ``e^-σ`` at ``σ / 2^EXP_SQUARINGS`` (≤ 0.35)."""
EXP_SQUARINGS = 4
"""Squarings that turn ``e^(-σ/16)`` into ``e^-σ`` (measured relative error < 2e-6)."""
SIGMA_MAX = math.log(1 / ALPHA_MIN) + 1e-3
"""Beyond this ``σ``, ``α ≤ e^-σ < 1/255`` for any opacity ≤ 1: the pixel is skipped exactly."""

FASTMATH = {"contract", "arcp", "nsz"}
"""LLVM fast-math flags of the hot kernels: FMA contraction and reciprocal rewrites only (about
25% off the backward). No reassociation, so sums keep their order (determinism)."""

S_MEAN, S_CONIC, S_OPACITY, S_FEAT, S_VAR = 0, 2, 5, 6, 10
"""Offsets of the parameter groups in a gradient slot."""


def raster_consts(dtype: np.dtype) -> np.ndarray:
    """The typed constants array of the kernels in ``dtype``."""
    values = [ALPHA_MAX, ALPHA_MIN, T_MIN, 0.0, 0.5, 1.0, 2.0, SIGMA_MAX, 2.0**-EXP_SQUARINGS]
    values += [0.0] + [1.0 / k for k in range(1, EXP_DEGREE + 1)]
    return np.array(values, dtype=dtype)


@numba.njit(cache=True, fastmath=FASTMATH)
def exp_neg(sigma, fast, consts):
    """``e^-σ`` for ``0 ≤ σ ≤ SIGMA_MAX``: libm, or with ``fast`` (the float32 path) a
    degree-7 Taylor polynomial at ``σ/16`` squared four times: branch and table free, so loops
    over pixels vectorise (the libm call took ~40% of the scalar forward)."""
    if not fast:
        return math.exp(-sigma)
    one = consts[K_ONE]
    x = -sigma * consts[K_EXP_SCALE]
    p = one
    for k in range(EXP_DEGREE, 0, -1):
        p = one + x * consts[K_INV + k] * p
    for _ in range(EXP_SQUARINGS):
        p = p * p
    return p


@numba.njit(cache=True, fastmath=FASTMATH)
def exp_neg_rows(values, p0, p1, fast, consts):
    """``values[p0:p1] = e^-values[p0:p1]`` (see :func:`exp_neg`); the dtype test is outside
    the loop, so the float32 loop vectorises."""
    if fast:
        for j in range(p0, p1):
            values[j] = exp_neg(values[j], True, consts)
    else:
        for j in range(p0, p1):
            values[j] = math.exp(-values[j])


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


@numba.njit(cache=True, inline="always")
def tile_grid(height, width):
    """(tiles per row, tiles) of the ``TILE_SIZE`` squares that cover a height × width image."""
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    return tiles_x, tiles_x * ((height + TILE_SIZE - 1) // TILE_SIZE)


@numba.njit(cache=True, inline="always")
def tile_box(tile, tiles_x, height, width):
    """The tile's pixels ``px0:px1``, ``py0:py1``, clipped to the image."""
    px0 = (tile % tiles_x) * TILE_SIZE
    py0 = (tile // tiles_x) * TILE_SIZE
    return px0, py0, min(px0 + TILE_SIZE, width), min(py0 + TILE_SIZE, height)


@numba.njit(cache=True, inline="always")
def lanes_like(values):
    """Scratch for one value per lane of a tile, of `values`' dtype."""
    return np.empty(TILE_PIXELS, values.dtype)


@numba.njit(cache=True, inline="always")
def feature_lanes_like(values):
    """Scratch for ``N_FEAT`` values per lane of a tile, of `values`' dtype."""
    return np.empty((N_FEAT, TILE_PIXELS), values.dtype)


@numba.njit(cache=True, inline="always")
def index_lanes():
    """Scratch for one intersection index per lane of a tile."""
    return np.empty(TILE_PIXELS, np.int32)


@numba.njit(cache=True)
def tile_lanes(xs, ys, px0, py0, lane_x, lane_y):
    """Pixel coordinates of the ``TILE_PIXELS`` lanes (row major) of the tile at ``(px0, py0)``;
    ``xs``, ``ys`` cover whole tiles, so lanes past the image border get coordinates too."""
    for p in range(TILE_PIXELS):
        lane_x[p] = xs[px0 + p % TILE_SIZE]
        lane_y[p] = ys[py0 + p // TILE_SIZE]


@numba.njit(cache=True)
def lane_span(rects, g, py0, py1):
    """Lanes ``p0:p1`` (unsigned, whole tile rows) of Gaussian g's box rows in the tile whose
    pixel rows are ``py0:py1``."""
    p0 = np.uint64((max(rects[g, 2], py0) - py0) * TILE_SIZE)
    p1 = np.uint64((min(rects[g, 3] + 1, py1) - py0) * TILE_SIZE)
    return p0, p1


@numba.njit(cache=True, fastmath=FASTMATH)
def sigma_rows(lane_x, lane_y, p0, p1, mx, my, a, b, c, sigma_max, half, out):
    """``out = min(σ, σ_max)`` with ``σ = ½(a dx² + c dy²) + b dx dy`` on lanes ``p0:p1``."""
    for j in range(p0, p1):
        dx = lane_x[j] - mx
        dy = lane_y[j] - my
        out[j] = min(half * (a * dx * dx + c * dy * dy) + b * dx * dy, sigma_max)


@numba.njit(parallel=True, cache=True, fastmath=FASTMATH)
def raster_fwd(
    means2d, conics, opacities, feats, variances, rects, tile_start, isect_gauss,
    xs, ys, consts, n_chunks, out_feat, out_trans, out_var, out_dvdf, out_last,
):  # fmt: skip
    """Front-to-back compositing of features, alpha and opacity-induced variances.

    Per pixel: ``out_feat = Σ f_i α_i T_i``, ``out_trans = T_final = 1 − A``,
    ``out_var = max(0, Σ v_i T_i² (f_i − F)²)`` via shifted moments about the first contributor,
    ``out_dvdf = Σ v_i T_i² (f_i − F)`` (for the backward) and ``out_last`` = index of the last
    contributing intersection (−1 if none). ``xs``, ``ys`` are the pixel coordinates, padded to
    whole tiles.

    Per Gaussian, the rows of its bounding box form one contiguous span of the tile's row-major
    lanes, processed by branch-free loops (masks as selects) that LLVM vectorises; lanes outside
    the box contribute exact zeros. Each loop writes few arrays: more defeats the vectoriser's
    alias checks.
    """
    height, width = out_trans.shape
    tiles_x, n_tiles = tile_grid(height, width)
    alpha_max, alpha_min, t_min = consts[K_ALPHA_MAX], consts[K_ALPHA_MIN], consts[K_T_MIN]
    sigma_max, fast_exp = consts[K_SIGMA_MAX], feats.itemsize == 4
    half, one, two, zero = consts[K_HALF], consts[K_ONE], consts[K_TWO], consts[K_ZERO]
    for chunk in numba.prange(n_chunks):
        lane_x = lanes_like(feats)
        lane_y = lanes_like(feats)
        trans = lanes_like(feats)
        done = index_lanes()
        last = index_lanes()
        s0 = lanes_like(feats)
        acc = feature_lanes_like(feats)
        ref = feature_lanes_like(feats)
        s1 = feature_lanes_like(feats)
        s2 = feature_lanes_like(feats)
        alphas = lanes_like(feats)  # σ, then e^-σ, then the masked α
        weights = lanes_like(feats)  # α T, 0 where not blended
        moments = lanes_like(feats)  # v T², 0 where not blended
        for tile in range(chunk, n_tiles, n_chunks):
            px0, py0, px1, py1 = tile_box(tile, tiles_x, height, width)
            tile_lanes(xs, ys, px0, py0, lane_x, lane_y)
            trans[:] = one
            done[:] = 0
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
                o, v = opacities[g], variances[g]
                x0, x1 = xs[rects[g, 0]], xs[rects[g, 1]]
                p0, p1 = lane_span(rects, g, py0, py1)
                sigma_rows(
                    lane_x, lane_y, p0, p1, means2d[g, 0], means2d[g, 1],
                    conics[g, 0], conics[g, 1], conics[g, 2], sigma_max, half, alphas,
                )  # fmt: skip
                exp_neg_rows(alphas, p0, p1, fast_exp, consts)
                for j in range(p0, p1):
                    alpha = min(alpha_max, o * alphas[j])
                    hit = ((lane_x[j] >= x0) & (lane_x[j] <= x1) & (done[j] == 0)
                           & (alpha >= alpha_min))  # fmt: skip
                    alphas[j] = alpha if hit else zero
                for j in range(p0, p1):  # blend unless it would bring T below T_MIN
                    t_old = trans[j]
                    blend = (alphas[j] > zero) & (t_old * (one - alphas[j]) >= t_min)
                    weights[j] = alphas[j] * t_old if blend else zero
                    moments[j] = v * t_old * t_old if blend else zero
                n_stop = 0
                for j in range(p0, p1):
                    stop = (alphas[j] > zero) & (trans[j] * (one - alphas[j]) < t_min)
                    done[j] = 1 if stop else done[j]
                    n_stop += 1 if stop else 0
                n_active -= n_stop
                for ch in range(feats.shape[1]):  # a runtime bound: no unrolling, less JIT
                    f = feats[g, ch]
                    for j in range(p0, p1):  # the first contributor is the shift of the moments
                        ref[ch, j] = f if (weights[j] > zero) & (last[j] < 0) else ref[ch, j]
                    for j in range(p0, p1):
                        acc[ch, j] += f * weights[j]
                    for j in range(p0, p1):
                        d = f - ref[ch, j]
                        s1[ch, j] += moments[j] * d
                        s2[ch, j] += moments[j] * d * d
                kk = np.int32(k)
                for j in range(p0, p1):
                    last[j] = kk if weights[j] > zero else last[j]
                for j in range(p0, p1):
                    trans[j] = trans[j] * (one - alphas[j]) if weights[j] > zero else trans[j]
                for j in range(p0, p1):
                    s0[j] += moments[j]
            for py in range(py0, py1):
                for px in range(px0, px1):
                    p = (py - py0) * TILE_SIZE + px - px0
                    out_trans[py, px] = trans[p]
                    out_last[py, px] = last[p]
                    for ch in range(N_FEAT):
                        delta = acc[ch, p] - ref[ch, p]
                        var = s2[ch, p] - two * delta * s1[ch, p] + delta * delta * s0[p]
                        out_feat[py, px, ch] = acc[ch, p]
                        out_var[py, px, ch] = max(var, zero)
                        out_dvdf[py, px, ch] = s1[ch, p] - delta * s0[p]


@numba.njit(cache=True, fastmath=FASTMATH)
def lane_sum(values, p0, p1, partial):
    """``Σ values[p0:p1]`` in a fixed order that vectorises without reassociation.

    ``p0:p1`` are whole tile rows: each of the ``TILE_SIZE`` lanes of a row accumulates over the
    rows in ``partial``, then the lanes are added pairwise (a tree). The order depends only on
    the span, never on the compiled code, so every process gets the same bits (fast-math
    ``reassoc`` did not guarantee that).
    """
    for lane in range(TILE_SIZE):
        partial[lane] = values[p0 + np.uint64(lane)]
    for row in range(p0 + np.uint64(TILE_SIZE), p1, np.uint64(TILE_SIZE)):
        for lane in range(TILE_SIZE):
            partial[lane] += values[row + np.uint64(lane)]
    width = TILE_SIZE // 2
    while width > 0:
        for lane in range(width):
            partial[lane] += partial[lane + width]
        width //= 2
    return partial[0]


@numba.njit(parallel=True, cache=True, fastmath=FASTMATH)
def raster_bwd(
    means2d, conics, opacities, feats, variances, rects, tile_start, isect_gauss,
    xs, ys, consts, n_chunks, full_grad, want_appearance, variance_only, out_feat, out_trans,
    out_dvdf, out_last, grad_feat, grad_alpha, grad_var, slots,
):  # fmt: skip
    """Back-to-front vector-Jacobian product of :func:`raster_fwd`, one slot per intersection.

    ``slots[k]`` receives the gradient of intersection ``k`` with respect to
    (mean x, mean y, conic a, b, c, opacity, features ×4, v). ``full_grad`` adds the dependence
    of ``T_i²`` in the variances on the alphas in front of Gaussian i (dropped by the authors).
    Without ``want_appearance`` (pose-only tracking) the colour, opacity and ``v`` entries are
    left at zero: only the geometry entries and the depth feature reach the pose. With
    ``variance_only`` (the end-of-run refinement: only ``v`` learns) every entry but ``v`` is
    left at zero, and ``v``'s is the one the full pass computes, bit for bit.

    Like the forward, each Gaussian is processed over the tile-wide rows of its bounding box by
    branch-free loops over lanes (masks as selects; masked lanes contribute exact zeros); each
    slot entry is first written per lane, then summed by :func:`lane_sum` (vectorised, in a
    fixed order).
    """
    height, width = out_trans.shape
    tiles_x, n_tiles = tile_grid(height, width)
    alpha_max, alpha_min = consts[K_ALPHA_MAX], consts[K_ALPHA_MIN]
    sigma_max, fast_exp = consts[K_SIGMA_MAX], feats.itemsize == 4
    half, one, two, zero = consts[K_HALF], consts[K_ONE], consts[K_TWO], consts[K_ZERO]
    r_weight = two if full_grad else zero  # ∂T_i²/∂α_j enters ∂L/∂α_j only in the full gradient
    # q = Σ_ch ∂L/∂V (f − F)² feeds ∂L/∂v and the full gradient's r_sum only: pose-only tracking
    # with the authors' gradient skips it (r_sum then stays 0)
    need_q = want_appearance or full_grad
    for chunk in numba.prange(n_chunks):
        lane_x = lanes_like(feats)
        lane_y = lanes_like(feats)
        trans = lanes_like(feats)  # T_{i+1}, then T_i while walking back
        last = index_lanes()
        g_final = lanes_like(feats)  # ∂L/∂A · T_final
        g_behind = lanes_like(feats)  # Σ_{j behind} w_j ⟨∂L/∂F, f_j⟩
        r_sum = lanes_like(feats)  # Σ_{j behind} q_j u_j
        fin = feature_lanes_like(feats)
        g_fin = feature_lanes_like(feats)
        g_v = feature_lanes_like(feats)
        gauss = lanes_like(feats)  # σ, then e^-σ
        alphas = lanes_like(feats)  # masked α
        inverse = lanes_like(feats)  # 1 / (1 − α)
        weights = lanes_like(feats)  # w = α T_i
        moments = lanes_like(feats)  # u = v T_i², 0 where not blended
        squares = lanes_like(feats)  # T_i², 0 where not blended
        q_var = lanes_like(feats)  # q = Σ_ch ∂L/∂V (f − F)²
        g_dot_f = lanes_like(feats)  # ⟨∂L/∂F, f_i⟩
        d_alphas = lanes_like(feats)  # ∂L/∂α_i, 0 where not blended
        d_sigmas = lanes_like(feats)  # ∂L/∂σ_i
        terms = lanes_like(feats)  # one slot entry per lane, then summed
        partial = np.empty(TILE_SIZE, feats.dtype)
        for tile in range(chunk, n_tiles, n_chunks):
            px0, py0, px1, py1 = tile_box(tile, tiles_x, height, width)
            tile_lanes(xs, ys, px0, py0, lane_x, lane_y)
            trans[:] = one
            last[:] = -1  # lanes past the image border never match
            g_final[:] = zero
            g_behind[:] = zero
            r_sum[:] = zero
            fin[:] = zero
            g_fin[:] = zero
            g_v[:] = zero
            k_end = tile_start[tile]  # one past the last contributor of the tile
            for py in range(py0, py1):
                for px in range(px0, px1):
                    p = (py - py0) * TILE_SIZE + px - px0
                    trans[p] = out_trans[py, px]
                    last[p] = out_last[py, px]
                    k_end = max(k_end, out_last[py, px] + 1)
                    g_final[p] = grad_alpha[py, px] * out_trans[py, px]
                    for ch in range(N_FEAT):
                        fin[ch, p] = out_feat[py, px, ch]
                        g_v[ch, p] = grad_var[py, px, ch]
                        # V depends on F: ∂V/∂F = −2 Σ v_i T_i² (f_i − F).
                        g_fin[ch, p] = (
                            grad_feat[py, px, ch] - two * g_v[ch, p] * out_dvdf[py, px, ch]
                        )
            for k in range(k_end, tile_start[tile + 1]):  # behind every pixel's last contributor
                for e in range(N_SLOT):
                    slots[k, e] = zero
            for k in range(k_end - 1, tile_start[tile] - 1, -1):
                g = isect_gauss[k]
                mx, my = means2d[g, 0], means2d[g, 1]
                a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
                o, v = opacities[g], variances[g]
                x0, x1 = xs[rects[g, 0]], xs[rects[g, 1]]
                p0, p1 = lane_span(rects, g, py0, py1)
                sigma_rows(lane_x, lane_y, p0, p1, mx, my, a, b, c, sigma_max, half, gauss)
                exp_neg_rows(gauss, p0, p1, fast_exp, consts)
                kk = np.int32(k)
                for j in range(p0, p1):
                    alpha = min(alpha_max, o * gauss[j])
                    hit = ((lane_x[j] >= x0) & (lane_x[j] <= x1) & (last[j] >= kk)
                           & (alpha >= alpha_min))  # fmt: skip
                    alphas[j] = alpha if hit else zero
                for j in range(p0, p1):  # T_i = T_{i+1} / (1 − α_i); unchanged where not blended
                    inverse[j] = one / (one - alphas[j])
                    trans[j] = trans[j] * inverse[j]
                for j in range(p0, p1):
                    weights[j] = alphas[j] * trans[j]
                    squares[j] = trans[j] * trans[j] if alphas[j] > zero else zero
                if variance_only:  # ∂L/∂v_i = Σ T_i² q_i, summed as below
                    for j in range(p0, p1):
                        q_var[j] = zero
                    for ch in range(N_FEAT):
                        f = feats[g, ch]
                        for j in range(p0, p1):
                            d = f - fin[ch, j]
                            q_var[j] += g_v[ch, j] * d * d
                    for j in range(p0, p1):
                        terms[j] = squares[j] * q_var[j]
                    for e in range(N_SLOT):
                        slots[k, e] = zero
                    slots[k, S_VAR] = lane_sum(terms, p0, p1, partial)
                    continue
                for j in range(p0, p1):
                    moments[j] = v * squares[j]
                    q_var[j] = zero
                    g_dot_f[j] = zero
                for ch in range(N_FEAT):  # a runtime bound: no unrolling, less JIT
                    f = feats[g, ch]
                    if need_q:
                        for j in range(p0, p1):
                            d = f - fin[ch, j]
                            q_var[j] += g_v[ch, j] * d * d
                            g_dot_f[j] += g_fin[ch, j] * f
                    else:
                        for j in range(p0, p1):
                            g_dot_f[j] += g_fin[ch, j] * f
                    s_f = zero
                    if want_appearance or ch == N_FEAT - 1:
                        for j in range(p0, p1):
                            d = f - fin[ch, j]
                            terms[j] = weights[j] * g_fin[ch, j] + two * g_v[ch, j] * moments[j] * d
                        s_f = lane_sum(terms, p0, p1, partial)
                    slots[k, S_FEAT + ch] = s_f
                for j in range(p0, p1):
                    # ∂F/∂α_i = f_i T_i − (Σ_{j>i} f_j w_j)/(1 − α_i), dotted with ∂L/∂F.
                    d_alpha = trans[j] * g_dot_f[j] + (
                        g_final[j] - g_behind[j] - r_weight * r_sum[j]
                    ) * inverse[j]
                    blended = (alphas[j] > zero) & (o * gauss[j] < alpha_max)
                    d_alphas[j] = d_alpha if blended else zero
                if full_grad:
                    for j in range(p0, p1):
                        g_behind[j] += weights[j] * g_dot_f[j]
                        r_sum[j] += q_var[j] * moments[j]
                else:
                    for j in range(p0, p1):
                        g_behind[j] += weights[j] * g_dot_f[j]
                for j in range(p0, p1):
                    d_sigmas[j] = -d_alphas[j] * o * gauss[j]
                s_opacity = s_var = zero
                if want_appearance:
                    for j in range(p0, p1):
                        terms[j] = d_alphas[j] * gauss[j]
                    s_opacity = lane_sum(terms, p0, p1, partial)
                    for j in range(p0, p1):
                        terms[j] = squares[j] * q_var[j]
                    s_var = lane_sum(terms, p0, p1, partial)
                slots[k, S_OPACITY], slots[k, S_VAR] = s_opacity, s_var
                for j in range(p0, p1):
                    terms[j] = -d_sigmas[j] * (a * (lane_x[j] - mx) + b * (lane_y[j] - my))
                slots[k, S_MEAN] = lane_sum(terms, p0, p1, partial)
                for j in range(p0, p1):
                    terms[j] = -d_sigmas[j] * (b * (lane_x[j] - mx) + c * (lane_y[j] - my))
                slots[k, S_MEAN + 1] = lane_sum(terms, p0, p1, partial)
                for j in range(p0, p1):
                    terms[j] = d_sigmas[j] * half * (lane_x[j] - mx) * (lane_x[j] - mx)
                slots[k, S_CONIC] = lane_sum(terms, p0, p1, partial)
                for j in range(p0, p1):
                    terms[j] = d_sigmas[j] * (lane_x[j] - mx) * (lane_y[j] - my)
                slots[k, S_CONIC + 1] = lane_sum(terms, p0, p1, partial)
                for j in range(p0, p1):
                    terms[j] = d_sigmas[j] * half * (lane_y[j] - my) * (lane_y[j] - my)
                slots[k, S_CONIC + 2] = lane_sum(terms, p0, p1, partial)


@numba.njit(parallel=True, cache=True)
def reduce_slots(slots, isect_slot, gauss_start, out):
    """``out[g] = Σ slots`` over Gaussian g's intersections, in a fixed (tile) order."""
    for g in numba.prange(out.shape[0]):
        for e in range(N_SLOT):
            out[g, e] = 0
        for j in range(gauss_start[g], gauss_start[g + 1]):
            k = isect_slot[j]
            for e in range(N_SLOT):
                out[g, e] += slots[k, e]
