"""Numba kernels of the tile rasterizer (forward, backward, per-Gaussian reduction).

Layout: ``feats[M, 4]`` holds RGB and the camera depth of each Gaussian, so colour and depth are
composited by the same loop; ``slopes[M, 2]`` tilt each Gaussian's depth into a plane across the
screen, so the depth feature at a pixel is ``d + s·(p − μ₂)`` (:func:`lane_feature`). Work is
split over screen tiles of ``TILE_SIZE`` pixels; within a tile the Gaussians (depth sorted) form
the outer loop. A tile's lanes are ordered by column block (``LANE_BLOCK`` columns, one SIMD
vector), then row, then column (:func:`lane_index`), so the rows of a Gaussian's opacity-aware
bounding box within one block are one contiguous span. For each block the box meets, both passes
run one fused, branch-free loop over that span that LLVM vectorises (:func:`blend_span`,
:func:`unblend_span`); the backward walks each tile back to front and writes one gradient slot
per (tile, Gaussian) intersection; :func:`reduce_slots` sums the slots of each Gaussian in a
fixed order, so results never depend on the thread count.

What keeps the fused loops vectorised (each was measured to stop it):
- every per-lane field of a tile lives in one flat array at constant offsets
  (:func:`lane_buffer`), so LLVM proves the accesses independent without run-time alias checks;
- lane ranges ``p0:p1`` are unsigned (``np.uint64``): numba wraps negative signed indices with a
  select, and a slice per range would cost two atomic reference-count updates;
- the loops live in serial functions with numpy's error model: Python's adds a zero-division
  check (an early exit) to every division, and a parallel kernel's body keeps Python's;
- every load is unconditional and every choice a select of computed values; the float32
  ``e^-σ`` is chosen at compile time (:func:`exp_neg`); no 64-bit reduction in the float32
  loops (it halves the vector width).

Work is dealt round-robin to ``n_chunks`` parallel chunks (pass ``numba.get_num_threads()``);
the chunking never changes a result. All floating-point constants enter through the typed
``consts`` array (see :func:`raster_consts`): numba types Python float literals as float64 and
would silently promote float32 kernels.
"""

import math

import numba
import numpy as np
from numba.extending import overload

from .constants import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE_SIZE

N_FEAT = 4
"""Composited features per Gaussian: R, G, B, depth (the backward spells the 4 out)."""

N_SLOT = 13
"""Gradient slot entries: mean x, y; conic a, b, c; opacity; 4 features; variance ``v``;
depth slope x, y."""

TILE_PIXELS = TILE_SIZE * TILE_SIZE
LANE_BLOCK = 8
"""Columns of a lane block: one 256-bit vector of float32. A span covers only the blocks that a
Gaussian's box meets: on a 270×190 mapping render that skips 29 % of the lanes of whole tile
rows, as the boxes are mostly narrower than a tile."""
BLOCK_LANES = TILE_SIZE * LANE_BLOCK
STEP_LANES = 2 * LANE_BLOCK
"""Lanes per step of the backward's loop, two block rows: a one-row loop was too short for
LLVM to vectorise beside its run-time alias checks. Each slot entry keeps one partial sum per
lane of a step."""
FIELD_STRIDE = TILE_PIXELS + TILE_SIZE
"""Entries between consecutive per-lane fields (:func:`lane_buffer`). With ``TILE_PIXELS`` the
fields were 1 KiB apart, so every fourth one shared its addresses modulo 4 KiB and a load waited
on another field's store (x86 "4K aliasing"): the forward's lane loop ran 20 % slower."""

(K_ALPHA_MAX, K_ALPHA_MIN, K_T_MIN, K_ZERO, K_HALF, K_ONE, K_TWO, K_SIGMA_MAX,
 K_EXP_SCALE) = range(9)  # fmt: skip
K_TAYLOR = 9
"""``consts[K_TAYLOR + k] = 1/k!`` for k = 0..EXP_DEGREE."""
EXP_DEGREE = 7
"""Taylor degree of the float32 ``e^-σ`` at ``σ / 2^EXP_SQUARINGS`` (≤ 0.35)."""
EXP_SQUARINGS = 4
"""Squarings that turn ``e^(-σ/16)`` into ``e^-σ`` (measured relative error < 2e-6)."""
SIGMA_MAX = math.log(1 / ALPHA_MIN) + 1e-3
"""Beyond this ``σ``, ``α ≤ e^-σ < 1/255`` for any opacity ≤ 1: the pixel is skipped exactly."""

FASTMATH = {"contract", "arcp", "nsz"}
"""LLVM fast-math flags of the entry kernels (`raster_fwd`, `raster_bwd`): FMA contraction and
reciprocal rewrites, no reassociation, so sums keep their order (determinism)."""
CALLEE_FASTMATH = {"nsz"}
"""The flags of every function the entry kernels call (declared, or a callee would take its
caller's): none that changes a value. Numba links a callee into each caller as a
``linkonce_odr`` copy and a call may run any loaded copy, assuming they all compute the same;
contraction and reciprocal rewrites depend on where a copy was inlined, so a process that had
just compiled the backward ran other code than the cache it wrote (tests/test_kernel_cache.py).
The hot loops vectorise as before: measured within noise of the contracted ones."""

S_MEAN, S_CONIC, S_OPACITY, S_FEAT, S_VAR, S_SLOPE = 0, 2, 5, 6, 10, 11
"""Offsets of the parameter groups in a gradient slot."""


def raster_consts(dtype: np.dtype) -> np.ndarray:
    """The typed constants array of the kernels in ``dtype``."""
    values = [ALPHA_MAX, ALPHA_MIN, T_MIN, 0.0, 0.5, 1.0, 2.0, SIGMA_MAX, 2.0**-EXP_SQUARINGS]
    values += [1.0 / math.factorial(k) for k in range(EXP_DEGREE + 1)]
    return np.array(values, dtype=dtype)


def exp_neg(sigma, consts):
    """``e^-σ`` for ``0 ≤ σ ≤ SIGMA_MAX``, chosen by σ's type when compiled: libm in float64, in
    float32 a degree-7 Taylor polynomial at ``σ/16`` squared four times, branch and table free,
    so loops over pixels vectorise (the libm call took ~40% of the scalar forward). A run-time
    flag instead would keep both paths in the vectorised loops."""
    return math.exp(-sigma)


def _exp_neg_polynomial(sigma, consts):
    """The Taylor polynomial by Estrin's scheme: three levels of multiply-adds rather than
    Horner's seven in a row, the fused loops' longest dependency chain."""
    x = -sigma * consts[K_EXP_SCALE]
    x2 = x * x
    c = K_TAYLOR
    low = (consts[c] + consts[c + 1] * x) + (consts[c + 2] + consts[c + 3] * x) * x2
    high = (consts[c + 4] + consts[c + 5] * x) + (consts[c + 6] + consts[c + 7] * x) * x2
    p = low + high * (x2 * x2)
    for _ in range(EXP_SQUARINGS):
        p = p * p
    return p


@overload(exp_neg, jit_options={"fastmath": CALLEE_FASTMATH})
def _exp_neg_typed(sigma, consts):
    if sigma == numba.types.float32:
        return _exp_neg_polynomial
    return exp_neg


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


RADIX_BITS = 11
"""Bits per pass of :func:`radix_order`: three passes cover a 32-bit key with 2048 buckets each."""


@numba.njit(cache=True)
def radix_order(keys):
    """Indices that sort the uint32 ``keys`` ascending, ties by index (an LSD radix sort: each
    pass is stable, so equal keys keep their index order, exactly as a stable argsort)."""
    n = keys.shape[0]
    buckets = 1 << RADIX_BITS
    order = np.arange(n)
    scratch = np.empty(n, np.int64)
    counts = np.empty(buckets + 1, np.int64)
    for shift in range(0, 32, RADIX_BITS):
        counts[:] = 0
        for i in range(n):
            counts[((keys[i] >> shift) & (buckets - 1)) + 1] += 1
        for b in range(buckets):
            counts[b + 1] += counts[b]
        for i in range(n):
            g = order[i]
            digit = (keys[g] >> shift) & (buckets - 1)
            scratch[counts[digit]] = g
            counts[digit] += 1
        order, scratch = scratch, order
    return order


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
def lane_buffer(n_fields, values):
    """Scratch for ``n_fields`` per-lane fields of a tile, of `values`' dtype, in one flat array.

    Field f of lane j is entry ``f·FIELD_STRIDE + j``: one base pointer and constant distances,
    so LLVM proves a fused loop's accesses independent and vectorises it without run-time
    alias checks (a loop over many separate arrays gets too many checks and stays scalar).
    """
    return np.empty(n_fields * FIELD_STRIDE, values.dtype)


@numba.njit(cache=True, inline="always")
def index_lanes():
    """Scratch for one intersection index per lane of a tile."""
    return np.empty(TILE_PIXELS, np.int32)


@numba.njit(cache=True, inline="always")
def lane_index(dx, dy):
    """The lane of the pixel at column `dx`, row `dy` of a tile: block, row, column order."""
    block, column = divmod(dx, LANE_BLOCK)
    return block * BLOCK_LANES + dy * LANE_BLOCK + column


@numba.njit(cache=True, fastmath=CALLEE_FASTMATH)
def tile_lanes(xs, ys, px0, py0, buf):
    """Pixel coordinates of the ``TILE_PIXELS`` lanes (:func:`lane_index` order) of the tile at
    ``(px0, py0)`` into fields 0 (x) and 1 (y) of `buf`; ``xs``, ``ys`` cover whole tiles, so
    lanes past the image border get coordinates too."""
    for dy in range(TILE_SIZE):
        for dx in range(TILE_SIZE):
            p = lane_index(dx, dy)
            buf[p] = xs[px0 + dx]
            buf[FIELD_STRIDE + p] = ys[py0 + dy]


@numba.njit(cache=True, fastmath=CALLEE_FASTMATH)
def box_blocks(rects, g, px0, py0, py1, align):
    """The lane blocks ``b0..b1`` that Gaussian g's box meets in the tile at ``(px0, py0)``
    (pixel rows ``py0:py1``), and the lane range ``r0:r1`` (unsigned) of its rows within a block,
    widened to multiples of `align` lanes (which divides ``BLOCK_LANES``): block b's span is
    ``b·BLOCK_LANES + r0 : b·BLOCK_LANES + r1``."""
    b0 = (max(rects[g, 0], px0) - px0) // LANE_BLOCK
    b1 = (min(rects[g, 1], px0 + TILE_SIZE - 1) - px0) // LANE_BLOCK
    r0 = (max(rects[g, 2], py0) - py0) * LANE_BLOCK // align * align
    r1 = -((py0 - min(rects[g, 3] + 1, py1)) * LANE_BLOCK // align) * align
    return b0, b1, np.uint64(r0), np.uint64(r1)


@numba.njit(cache=True, inline="always")
def block_base(block):
    """Unsigned first lane of lane block `block`."""
    return np.uint64(block * BLOCK_LANES)


def field(k):
    """Unsigned offset of per-lane field k in a :func:`lane_buffer` (a compile-time constant)."""
    return np.uint64(k * FIELD_STRIDE)


LANE_Y = field(1)
"""Fields 0 and 1 of both passes: the lanes' pixel x and y (:func:`tile_lanes`)."""
CH = field(1)
"""Distance between the fields of consecutive features."""

# The forward's other fields: transmittance, Σ v T², and per feature the composite, the shift
# of the moments (the first contributor's feature) and the two shifted moments.
FT, FS0 = field(2), field(3)
FACC, FREF, FS1, FS2 = (field(4 + N_FEAT * k) for k in range(4))
FWD_FIELDS = 4 + 4 * N_FEAT

# The backward's: transmittance, ∂L/∂A · T_final, Σ_{j behind} w_j ⟨∂L/∂F, f_j⟩,
# Σ_{j behind} q_j u_j, and per feature the final composite F, ∂L/∂F (with V's dependence on F)
# and ∂L/∂V.
BT, BFINAL, BBEHIND, BRSUM = (field(k) for k in range(2, 6))
BFIN, BGFIN, BGV = (field(6 + N_FEAT * k) for k in range(3))
BWD_FIELDS = 6 + 3 * N_FEAT


def slot_lanes(e):
    """Unsigned offset of slot entry e's partial sums (``STEP_LANES``) in the backward's
    accumulator."""
    return np.uint64(e * STEP_LANES)


A_MEAN_X, A_MEAN_Y, A_CONIC_A, A_CONIC_B, A_CONIC_C, A_OPACITY = (
    slot_lanes(S_MEAN + e) for e in range(6)
)
A_FEAT, A_VAR = slot_lanes(S_FEAT), slot_lanes(S_VAR)
A_SLOPE_X, A_SLOPE_Y = slot_lanes(S_SLOPE), slot_lanes(S_SLOPE + 1)


@numba.njit(cache=True, fastmath=CALLEE_FASTMATH)
def gaussian_weight(dx, dy, a, b, c, consts):
    """``e^-σ`` (see :func:`exp_neg`), ``σ = ½(a dx² + c dy²) + b dx dy`` capped at ``SIGMA_MAX``.

    The one evaluation of a splat at a lane, shared by the forward's and backward's loops.
    """
    half = consts[K_HALF]
    sigma = min(half * (a * dx * dx + c * dy * dy) + b * dx * dy, consts[K_SIGMA_MAX])
    return exp_neg(sigma, consts)


@numba.njit(cache=True, fastmath=CALLEE_FASTMATH, inline="always")
def lane_feature(fs, ch, sx, sy, dx, dy):
    """Feature ``ch`` of a Gaussian at a lane ``(dx, dy)`` from its centre: its colour, or the
    depth of its plane ``d + sx·dx + sy·dy`` (where the pixel's ray meets it). A select on the
    channel, not a tuple built per lane: indexing that by the channel kept the loops scalar."""
    return fs[ch] + sx * dx + sy * dy if ch == N_FEAT - 1 else fs[ch]


@numba.njit(cache=True, fastmath=CALLEE_FASTMATH, error_model="numpy")
def blend_span(buf, done, last, p0, p1, kk, o, v, mx, my, a, b, c, fs, sx, sy, x0, x1, consts):
    """Forward, one intersection: blend Gaussian ``kk`` (opacity ``o``, variance ``v``, mean,
    conic, features ``fs``, depth slopes ``sx, sy``, box columns ``x0..x1``) into lanes
    ``p0:p1`` of a tile, front to back; returns how many lanes stopped (their transmittance
    would fall below ``T_MIN``).

    One fused branch-free loop (masks as selects) that LLVM vectorises: lanes outside the box
    contribute exact zeros. A function of its own for the error model: a parallel kernel's
    loops keep Python's, whose division checks stop the vectoriser.
    """
    alpha_max, alpha_min, t_min = consts[K_ALPHA_MAX], consts[K_ALPHA_MIN], consts[K_T_MIN]
    one, zero = consts[K_ONE], consts[K_ZERO]
    mark = kk + 1  # done[j]: 0 while blending, else 1 + the intersection that stopped it
    for j in range(p0, p1):
        x = buf[j]
        # every load unconditional, every choice a select of computed values
        was_done, last_j, t_old = done[j], last[j], buf[FT + j]
        dx, dy = x - mx, buf[LANE_Y + j] - my
        e = gaussian_weight(dx, dy, a, b, c, consts)
        alpha = min(alpha_max, o * e)
        hit = (x >= x0) & (x <= x1) & (was_done == 0) & (alpha >= alpha_min)
        alpha = alpha if hit else zero
        t_new = t_old * (one - alpha)
        # blend unless it would bring T below T_MIN; there the pixel stops
        blend = (alpha > zero) & (t_new >= t_min)
        stop = (alpha > zero) & (t_new < t_min)
        done[j] = mark if stop else was_done
        w = alpha * t_old if blend else zero  # α T, 0 where not blended
        m = v * t_old * t_old if blend else zero  # v T², 0 where not blended
        # the first contributor's feature is the shift of the moments; the shift is 0 before
        # it, so adding f once (exactly) sets it
        first = one if (w > zero) & (last_j < 0) else zero
        for ch in range(N_FEAT):
            f, at = lane_feature(fs, ch, sx, sy, dx, dy), CH * np.uint64(ch) + j
            ref = buf[FREF + at] + f * first
            buf[FREF + at] = ref
            buf[FACC + at] += f * w
            d = f - ref
            buf[FS1 + at] += m * d
            buf[FS2 + at] += m * d * d
        last[j] = kk if w > zero else last_j
        buf[FT + j] = t_new if w > zero else t_old
        buf[FS0 + j] += m
    n_stop = 0
    for j in range(p0, p1):
        n_stop += 1 if done[j] == mark else 0
    return n_stop


@numba.njit(parallel=True, cache=True, fastmath=FASTMATH)
def raster_fwd(
    means2d, conics, opacities, feats, slopes, variances, rects, tile_start, isect_gauss,
    xs, ys, consts, n_chunks, out_feat, out_trans, out_var, out_dvdf, out_last,
):  # fmt: skip
    """Front-to-back compositing of features, alpha and opacity-induced variances.

    Per pixel: ``out_feat = Σ f_i α_i T_i``, ``out_trans = T_final = 1 − A``,
    ``out_var = max(0, Σ v_i T_i² (f_i − F)²)`` via shifted moments about the first contributor,
    ``out_dvdf = Σ v_i T_i² (f_i − F)`` (for the backward) and ``out_last`` = index of the last
    contributing intersection (−1 if none). ``xs``, ``ys`` are the pixel coordinates, padded to
    whole tiles.

    Per Gaussian and lane block, the rows of its bounding box form one contiguous span of lanes,
    processed by one fused branch-free loop (masks as selects) that LLVM vectorises; lanes
    outside the box contribute exact zeros.
    """
    height, width = out_trans.shape
    tiles_x, n_tiles = tile_grid(height, width)
    one, two, zero = consts[K_ONE], consts[K_TWO], consts[K_ZERO]
    for chunk in numba.prange(n_chunks):
        buf = lane_buffer(FWD_FIELDS, feats)
        done = index_lanes()
        last = index_lanes()
        for tile in range(chunk, n_tiles, n_chunks):
            px0, py0, px1, py1 = tile_box(tile, tiles_x, height, width)
            tile_lanes(xs, ys, px0, py0, buf)
            buf[FT:] = zero
            buf[FT : FT + TILE_PIXELS] = one
            done[:] = 0
            last[:] = -1
            n_active = (px1 - px0) * (py1 - py0)
            for k in range(tile_start[tile], tile_start[tile + 1]):
                if n_active == 0:  # every pixel of the tile has terminated
                    break
                g = isect_gauss[k]
                o, v = opacities[g], variances[g]
                mx, my = means2d[g, 0], means2d[g, 1]
                a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
                fs = (feats[g, 0], feats[g, 1], feats[g, 2], feats[g, 3])
                sx, sy = slopes[g, 0], slopes[g, 1]
                x0, x1 = xs[rects[g, 0]], xs[rects[g, 1]]
                b0, b1, r0, r1 = box_blocks(rects, g, px0, py0, py1, LANE_BLOCK)
                kk = np.int32(k)
                for block in range(b0, b1 + 1):
                    base = block_base(block)
                    n_active -= blend_span(
                        buf, done, last, base + r0, base + r1, kk, o, v, mx, my, a, b, c, fs,
                        sx, sy, x0, x1, consts,
                    )  # fmt: skip
            for py in range(py0, py1):
                for px in range(px0, px1):
                    p = lane_index(px - px0, py - py0)
                    out_trans[py, px] = buf[FT + p]
                    out_last[py, px] = last[p]
                    for ch in range(N_FEAT):
                        at = CH * np.uint64(ch) + p
                        acc, s0, s1 = buf[FACC + at], buf[FS0 + p], buf[FS1 + at]
                        delta = acc - buf[FREF + at]
                        var = buf[FS2 + at] - two * delta * s1 + delta * delta * s0
                        out_feat[py, px, ch] = acc
                        out_var[py, px, ch] = max(var, zero)
                        out_dvdf[py, px, ch] = s1 - delta * s0


@numba.njit(cache=True, fastmath=CALLEE_FASTMATH)
def lane_total(acc, e):
    """Sum of the ``STEP_LANES`` partials of slot entry e, pairwise (a fixed tree), so the
    order never depends on the compiled code."""
    base = e * STEP_LANES
    width = STEP_LANES // 2
    while width > 0:
        for lane in range(width):
            acc[base + lane] += acc[base + lane + width]
        width //= 2
    return acc[base]


@numba.njit(cache=True, fastmath=CALLEE_FASTMATH, error_model="numpy")
def unblend_lane(buf, last, j, kk, mx, my, a, b, c, o, x0, x1, y0, y1, consts):
    """Backward, lane j: undo intersection kk's blend (box ``x0..x1`` × ``y0..y1``),
    ``T_i = T_{i+1} / (1 − α_i)`` (unchanged where it was not blended), and return
    ``dx, dy, e^-σ, α_i, 1/(1 − α_i), T_i`` and ``T_i²`` (0 where not blended)."""
    alpha_max, alpha_min = consts[K_ALPHA_MAX], consts[K_ALPHA_MIN]
    one, zero = consts[K_ONE], consts[K_ZERO]
    x, y = buf[j], buf[LANE_Y + j]
    dx, dy = x - mx, y - my
    e = gaussian_weight(dx, dy, a, b, c, consts)
    alpha = min(alpha_max, o * e)
    inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    hit = inside & (last[j] >= kk) & (alpha >= alpha_min)
    alpha = alpha if hit else zero
    inverse = one / (one - alpha)
    t = buf[BT + j] * inverse
    buf[BT + j] = t
    return dx, dy, e, alpha, inverse, t, (t * t if alpha > zero else zero)


@numba.njit(cache=True, fastmath=CALLEE_FASTMATH)
def variance_residual(buf, j, fs, sx, sy, dx, dy, zero):
    """``q = Σ_ch ∂L/∂V (f − F)²`` at lane j (offset ``dx, dy``) for the features ``fs`` and
    depth slopes ``sx, sy`` (:func:`lane_feature`)."""
    q = zero
    for ch in range(N_FEAT):
        at = CH * np.uint64(ch) + j
        d = lane_feature(fs, ch, sx, sy, dx, dy) - buf[BFIN + at]
        q += buf[BGV + at] * d * d
    return q


@numba.njit(cache=True, fastmath=CALLEE_FASTMATH, error_model="numpy")
def unblend_span(buf, last, acc, p0, p1, kk, o, v, mx, my, a, b, c, fs, sx, sy, x0, x1, y0, y1,
                 r_weight, variance_only, consts):  # fmt: skip
    """Backward, one intersection and lane block (see :func:`blend_span`): undo Gaussian
    ``kk``'s blend in lanes ``p0:p1`` (whole steps of ``STEP_LANES``, box ``x0..x1`` ×
    ``y0..y1``), update the lanes' running sums and add to ``acc`` its slot entries' partial
    sums, one per lane of a step.

    Lanes of a step outside the box are masked (exact no-ops), so the loop's length is a
    constant that LLVM vectorises. ``r_weight`` is 2 for the full gradient (the dependence of
    ``T_i²`` on the alphas in front), else 0. With ``variance_only`` only ``v``'s entry is
    computed, as the full pass does.
    """
    half, two, zero = consts[K_HALF], consts[K_TWO], consts[K_ZERO]
    step = np.uint64(STEP_LANES)
    if variance_only:  # ∂L/∂v_i = Σ T_i² q_i
        for r0 in range(p0, p1, step):
            for lane in range(step):
                j = r0 + lane
                dx, dy, _, _, _, _, square = unblend_lane(
                    buf, last, j, kk, mx, my, a, b, c, o, x0, x1, y0, y1, consts
                )  # fmt: skip
                q = variance_residual(buf, j, fs, sx, sy, dx, dy, zero)
                acc[A_VAR + lane] += square * q
        return
    for r0 in range(p0, p1, step):
        for lane in range(step):
            j = r0 + lane
            dx, dy, e, alpha, inverse, t, square = unblend_lane(
                buf, last, j, kk, mx, my, a, b, c, o, x0, x1, y0, y1, consts
            )
            w = alpha * t
            mom = v * square
            q = variance_residual(buf, j, fs, sx, sy, dx, dy, zero)
            g_dot_f = zero  # ⟨∂L/∂F, f_i⟩
            g_lane = zero  # ∂L/∂f of the last feature, the depth at this lane
            for ch in range(N_FEAT):
                f, at = lane_feature(fs, ch, sx, sy, dx, dy), CH * np.uint64(ch) + j
                g_f = buf[BGFIN + at]
                g_dot_f += g_f * f
                d = f - buf[BFIN + at]
                g_lane = w * g_f + two * buf[BGV + at] * mom * d
                acc[A_FEAT + step * np.uint64(ch) + lane] += g_lane
            acc[A_VAR + lane] += square * q
            # the depth plane d + s·(p − μ₂): ∂/∂s = p − μ₂, ∂/∂μ₂ = −s
            acc[A_SLOPE_X + lane] += g_lane * dx
            acc[A_SLOPE_Y + lane] += g_lane * dy
            # ∂F/∂α_i = f_i T_i − (Σ_{j>i} f_j w_j)/(1 − α_i), dotted with ∂L/∂F.
            d_alpha = (
                t * g_dot_f
                + (buf[BFINAL + j] - buf[BBEHIND + j] - r_weight * buf[BRSUM + j]) * inverse
            )
            blended = (alpha > zero) & (o * e < consts[K_ALPHA_MAX])
            d_alpha = d_alpha if blended else zero
            buf[BBEHIND + j] += w * g_dot_f
            buf[BRSUM + j] += q * mom
            d_sigma = -d_alpha * o * e
            acc[A_OPACITY + lane] += d_alpha * e
            acc[A_MEAN_X + lane] += -d_sigma * (a * dx + b * dy) - sx * g_lane
            acc[A_MEAN_Y + lane] += -d_sigma * (b * dx + c * dy) - sy * g_lane
            acc[A_CONIC_A + lane] += d_sigma * half * dx * dx
            acc[A_CONIC_B + lane] += d_sigma * dx * dy
            acc[A_CONIC_C + lane] += d_sigma * half * dy * dy


@numba.njit(parallel=True, cache=True, fastmath=FASTMATH)
def raster_bwd(
    means2d, conics, opacities, feats, slopes, variances, rects, tile_start, isect_gauss,
    xs, ys, consts, n_chunks, full_grad, want_appearance, variance_only, out_feat, out_trans,
    out_dvdf, out_last, grad_feat, grad_alpha, grad_var, slots,
):  # fmt: skip
    """Back-to-front vector-Jacobian product of :func:`raster_fwd`, one slot per intersection.

    ``slots[k]`` receives the gradient of intersection ``k`` with respect to
    (mean x, mean y, conic a, b, c, opacity, features ×4, v, depth slope x, y). ``full_grad``
    adds the dependence of ``T_i²`` in the variances on the alphas in front of Gaussian i
    (dropped by the authors).
    Without ``want_appearance`` (pose-only tracking) the colour, opacity and ``v`` entries are
    left at zero: only the geometry entries and the depth feature reach the pose. With
    ``variance_only`` (the end-of-run refinement: only ``v`` learns) every entry but ``v`` is
    left at zero. Every mode runs the same loop, so every entry is bitwise the full pass's.

    Like the forward, each Gaussian is processed per lane block over the rows of its bounding
    box by one fused branch-free loop (masks as selects; masked lanes contribute exact zeros).
    Each slot entry is accumulated per lane of a step (:func:`unblend_span`), over the steps,
    then the lanes are summed by :func:`lane_total`: a fixed order, so every process gets the
    same bits.
    """
    height, width = out_trans.shape
    tiles_x, n_tiles = tile_grid(height, width)
    one, two, zero = consts[K_ONE], consts[K_TWO], consts[K_ZERO]
    r_weight = two if full_grad else zero  # ∂T_i²/∂α_j enters ∂L/∂α_j only in the full gradient
    for chunk in numba.prange(n_chunks):
        buf = lane_buffer(BWD_FIELDS, feats)
        last = index_lanes()
        acc = np.empty(N_SLOT * STEP_LANES, feats.dtype)  # per slot entry and step lane
        for tile in range(chunk, n_tiles, n_chunks):
            px0, py0, px1, py1 = tile_box(tile, tiles_x, height, width)
            tile_lanes(xs, ys, px0, py0, buf)
            buf[BT:] = zero
            buf[BT : BT + TILE_PIXELS] = one
            last[:] = -1  # lanes past the image border never match
            k_end = tile_start[tile]  # one past the last contributor of the tile
            for py in range(py0, py1):
                for px in range(px0, px1):
                    p = lane_index(px - px0, py - py0)
                    buf[BT + p] = out_trans[py, px]
                    last[p] = out_last[py, px]
                    k_end = max(k_end, out_last[py, px] + 1)
                    buf[BFINAL + p] = grad_alpha[py, px] * out_trans[py, px]
                    for ch in range(N_FEAT):
                        at = CH * np.uint64(ch) + p
                        g_v = grad_var[py, px, ch]
                        buf[BFIN + at] = out_feat[py, px, ch]
                        buf[BGV + at] = g_v
                        # V depends on F: ∂V/∂F = −2 Σ v_i T_i² (f_i − F).
                        buf[BGFIN + at] = grad_feat[py, px, ch] - two * g_v * out_dvdf[py, px, ch]
            for k in range(k_end, tile_start[tile + 1]):  # behind every pixel's last contributor
                for e in range(N_SLOT):
                    slots[k, e] = zero
            for k in range(k_end - 1, tile_start[tile] - 1, -1):
                g = isect_gauss[k]
                mx, my = means2d[g, 0], means2d[g, 1]
                a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
                o, v = opacities[g], variances[g]
                fs = (feats[g, 0], feats[g, 1], feats[g, 2], feats[g, 3])
                sx, sy = slopes[g, 0], slopes[g, 1]
                x0, x1 = xs[rects[g, 0]], xs[rects[g, 1]]
                y0, y1 = ys[rects[g, 2]], ys[rects[g, 3]]
                b0, b1, r0, r1 = box_blocks(rects, g, px0, py0, py1, STEP_LANES)
                kk = np.int32(k)
                acc[:] = zero
                for block in range(b0, b1 + 1):
                    base = block_base(block)
                    unblend_span(
                        buf, last, acc, base + r0, base + r1, kk, o, v, mx, my, a, b, c, fs,
                        sx, sy, x0, x1, y0, y1, r_weight, variance_only, consts,
                    )  # fmt: skip
                for e in range(N_SLOT):
                    if variance_only:
                        keep = e == S_VAR
                    else:  # pose-only: the geometry entries and the depth feature
                        keep = (want_appearance or e < S_OPACITY or e == S_FEAT + N_FEAT - 1
                                or e >= S_SLOPE)  # fmt: skip
                    slots[k, e] = lane_total(acc, e) if keep else zero


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
