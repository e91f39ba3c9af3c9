"""Fused numba kernels of the per-pixel losses, with their analytic gradients.

A mapping or tracking step evaluates its loss on whole images; as chains of PyTorch ops
(masks, boolean indexing, a dozen element-wise ops and their backward) the loss took as long as
the render itself. Each kernel here makes one pass over the pixels (rows in parallel) and its
backward one more. Sums are accumulated per image row in float64 and the rows are added in
order, so results never depend on the thread count.

The formulas are those of :mod:`bgs_batch.slam.losses`, which documents them with the paper's
equation numbers; ``tests/slam/test_loss_kernels.py`` checks every value and gradient against
float64 PyTorch autograd of the plain formulas.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from bgs_batch.slam.blur import blur_planes

HALF = 0.5


# --- L1 and Gaussian NLL terms of the mapping loss (Eq. 12-14) ------------------------------
@numba.njit(parallel=True, cache=True)
def _l1_nll_fwd(color, depth, target_c, target_d, var_c, var_d, rows):
    """Per row: Σ|r_C|, Σ|r_D|, Σ NLL_C, Σ NLL_D and the masked pixel count (mask: D > 0 and a
    finite render); NLL = ½(r²/Σ + log Σ)."""
    height, width, channels = color.shape
    for y in numba.prange(height):
        l1c = l1d = nllc = nlld = count = 0.0
        for x in range(width):
            d = depth[y, x, 0]
            if not (target_d[y, x, 0] > 0 and np.isfinite(d)):
                continue
            count += 1.0
            for ch in range(channels):
                r = float(color[y, x, ch]) - target_c[y, x, ch]
                v = float(var_c[y, x, ch])
                l1c += abs(r)
                nllc += HALF * (r * r / v + np.log(v))
            r = float(d) - target_d[y, x, 0]
            v = float(var_d[y, x, 0])
            l1d += abs(r)
            nlld += HALF * (r * r / v + np.log(v))
        rows[y, 0], rows[y, 1], rows[y, 2], rows[y, 3], rows[y, 4] = l1c, l1d, nllc, nlld, count


@numba.njit(parallel=True, cache=True)
def _l1_nll_bwd(color, depth, target_c, target_d, var_c, var_d, coef,
                g_color, g_depth, g_var_c, g_var_d):  # fmt: skip
    """Gradients of ``coef · (Σ|r_C|, Σ|r_D|, Σ NLL_C, Σ NLL_D)`` (zero outside the mask)."""
    height, width, channels = color.shape
    for y in numba.prange(height):
        for x in range(width):
            d = depth[y, x, 0]
            inside = target_d[y, x, 0] > 0 and np.isfinite(d)
            for ch in range(channels):
                r = color[y, x, ch] - target_c[y, x, ch]
                v = var_c[y, x, ch]
                if inside:
                    g_color[y, x, ch] = coef[0] * np.sign(r) + coef[2] * r / v
                    g_var_c[y, x, ch] = coef[2] * HALF * (1 / v - r * r / (v * v))
                else:
                    g_color[y, x, ch] = 0
                    g_var_c[y, x, ch] = 0
            r = d - target_d[y, x, 0]
            v = var_d[y, x, 0]
            if inside:
                g_depth[y, x, 0] = coef[1] * np.sign(r) + coef[3] * r / v
                g_var_d[y, x, 0] = coef[3] * HALF * (1 / v - r * r / (v * v))
            else:
                g_depth[y, x, 0] = 0
                g_var_d[y, x, 0] = 0


class _L1Nll(torch.autograd.Function):
    @staticmethod
    def forward(ctx, color, depth, target_c, target_d, var_c, var_d):
        arrays = [t.detach().contiguous().numpy() for t in
                  (color, depth, target_c, target_d, var_c, var_d)]  # fmt: skip
        rows = np.empty((color.shape[0], 5))
        _l1_nll_fwd(*arrays, rows)
        sums = rows.sum(0)
        count = sums[4]
        norm = np.array([color.shape[2], 1.0, color.shape[2], 1.0]) * max(count, 1.0)
        ctx.arrays, ctx.norm = arrays, norm
        return torch.tensor(sums[:4] / norm, dtype=color.dtype)

    @staticmethod
    def backward(ctx, grad):
        color, depth, _, _, var_c, var_d = ctx.arrays
        coef = (grad.double().numpy() / ctx.norm).astype(color.dtype)
        out = [np.empty_like(a) for a in (color, depth, var_c, var_d)]
        _l1_nll_bwd(*ctx.arrays, coef, *out)
        g_color, g_depth, g_var_c, g_var_d = map(torch.from_numpy, out)
        return g_color, g_depth, None, None, g_var_c, g_var_d


def l1_nll_terms(
    color: torch.Tensor,
    depth: torch.Tensor,
    target_color: torch.Tensor,
    target_depth: torch.Tensor,
    var_color: torch.Tensor,
    var_depth: torch.Tensor,
) -> torch.Tensor:
    """Means over pixels with valid measured depth (and a finite render), as a [4] tensor:
    mean|Ĉ−C|, mean|D̂−D|, mean NLL_C, mean NLL_D (colour means over pixels × channels).

    Differentiable with respect to the render and the total variances Σ_C [H,W,3], Σ_D
    [H,W,1]; the targets are constants. No valid pixel: all four are 0.
    """
    return _L1Nll.apply(color, depth, target_color, target_depth, var_color, var_depth)


# --- uncertainty-normalised L1 of tracking (Eq. 15-17) ---------------------------------------
@numba.njit(parallel=True, cache=True)
def _tracking_fwd(color, depth, alpha, target_c, target_d, var_c, var_d, rows):
    """Per row: Σ α³|r_C|/√Σ_C and Σ α³|r_D|/√Σ_D over pixels with D > 0."""
    height, width, channels = color.shape
    for y in numba.prange(height):
        err_c = err_d = 0.0
        for x in range(width):
            if not target_d[y, x, 0] > 0:
                continue
            a = float(alpha[y, x, 0])
            w = a * a * a
            for ch in range(channels):
                err_c += w * abs(float(color[y, x, ch]) - target_c[y, x, ch]) / np.sqrt(
                    float(var_c[y, x, ch]))  # fmt: skip
            err_d += w * abs(float(depth[y, x, 0]) - target_d[y, x, 0]) / np.sqrt(
                float(var_d[y, x, 0]))  # fmt: skip
        rows[y, 0], rows[y, 1] = err_c, err_d


@numba.njit(parallel=True, cache=True)
def _tracking_bwd(color, depth, alpha, target_c, target_d, var_c, var_d, coef,
                  g_color, g_depth, g_alpha, g_var_c, g_var_d):  # fmt: skip
    """Gradients of ``coef[0]·err_C + coef[1]·err_D`` (zero where D = 0)."""
    height, width, channels = color.shape
    three = 3
    for y in numba.prange(height):
        for x in range(width):
            inside = target_d[y, x, 0] > 0
            a = alpha[y, x, 0]
            w = a * a * a
            dw = three * a * a
            weighted = 0.0
            for ch in range(channels):
                r = color[y, x, ch] - target_c[y, x, ch]
                inv_sd = 1 / np.sqrt(var_c[y, x, ch])
                if inside:
                    g_color[y, x, ch] = coef[0] * w * np.sign(r) * inv_sd
                    g_var_c[y, x, ch] = -coef[0] * w * HALF * abs(r) * inv_sd / var_c[y, x, ch]
                    weighted += coef[0] * abs(r) * inv_sd
                else:
                    g_color[y, x, ch] = 0
                    g_var_c[y, x, ch] = 0
            r = depth[y, x, 0] - target_d[y, x, 0]
            inv_sd = 1 / np.sqrt(var_d[y, x, 0])
            if inside:
                g_depth[y, x, 0] = coef[1] * w * np.sign(r) * inv_sd
                g_var_d[y, x, 0] = -coef[1] * w * HALF * abs(r) * inv_sd / var_d[y, x, 0]
                g_alpha[y, x, 0] = dw * (weighted + coef[1] * abs(r) * inv_sd)
            else:
                g_depth[y, x, 0] = 0
                g_var_d[y, x, 0] = 0
                g_alpha[y, x, 0] = 0


class _TrackingL1(torch.autograd.Function):
    @staticmethod
    def forward(ctx, color, depth, alpha, target_c, target_d, var_c, var_d, weights):
        arrays = [t.detach().contiguous().numpy() for t in
                  (color, depth, alpha, target_c, target_d, var_c, var_d)]  # fmt: skip
        rows = np.empty((color.shape[0], 2))
        _tracking_fwd(*arrays, rows)
        ctx.arrays, ctx.weights = arrays, weights
        return torch.tensor(float(np.dot(rows.sum(0), weights)), dtype=color.dtype)

    @staticmethod
    def backward(ctx, grad):
        color, depth, alpha, _, _, var_c, var_d = ctx.arrays
        coef = (float(grad) * np.asarray(ctx.weights)).astype(color.dtype)
        out = [np.empty_like(a) for a in (color, depth, alpha, var_c, var_d)]
        _tracking_bwd(*ctx.arrays, coef, *out)
        g_color, g_depth, g_alpha, g_var_c, g_var_d = map(torch.from_numpy, out)
        return g_color, g_depth, g_alpha, None, None, g_var_c, g_var_d, None


def weighted_normalised_l1(
    color: torch.Tensor,
    depth: torch.Tensor,
    alpha: torch.Tensor,
    target_color: torch.Tensor,
    target_depth: torch.Tensor,
    var_color: torch.Tensor,
    var_depth: torch.Tensor,
    weights: tuple[float, float],
) -> torch.Tensor:
    """``w_C Σ α³|Ĉ−C|/√Σ_C + w_D Σ α³|D̂−D|/√Σ_D`` over pixels with valid measured depth.

    Differentiable with respect to the render (colour, depth, alpha; α³ is not detached) and
    the total variances; the targets are constants.
    """
    return _TrackingL1.apply(color, depth, alpha, target_color, target_depth, var_color,
                             var_depth, weights)  # fmt: skip


# --- SSIM (3DGS: 11×11 Gaussian window, zero padding) ---------------------------------------
@numba.njit(parallel=True, cache=True)
def _ssim_moments(a, b, planes):
    """``planes[5C,H,W]`` = a, b, a², b², ab per channel (channels-last inputs [H,W,C])."""
    height, width, channels = a.shape
    for y in numba.prange(height):
        for x in range(width):
            for ch in range(channels):
                va, vb = a[y, x, ch], b[y, x, ch]
                planes[ch, y, x] = va
                planes[channels + ch, y, x] = vb
                planes[2 * channels + ch, y, x] = va * va
                planes[3 * channels + ch, y, x] = vb * vb
                planes[4 * channels + ch, y, x] = va * vb


@numba.njit(parallel=True, cache=True)
def _ssim_map(blurred, channels, c1, c2, rows, grads):
    """Per row the sum of the SSIM map; with ``grads`` of 3C planes (not empty), also ∂S/∂μ_a,
    ∂S/∂E[a²] and ∂S/∂E[ab] per pixel (before the adjoint blur)."""
    _, height, width = blurred.shape
    want = grads.shape[0] > 0
    two = 2
    for y in numba.prange(height):
        total = 0.0
        for ch in range(channels):
            for x in range(width):
                mu_a = blurred[ch, y, x]
                mu_b = blurred[channels + ch, y, x]
                var_a = blurred[2 * channels + ch, y, x] - mu_a * mu_a
                var_b = blurred[3 * channels + ch, y, x] - mu_b * mu_b
                cov = blurred[4 * channels + ch, y, x] - mu_a * mu_b
                a1 = two * mu_a * mu_b + c1
                a2 = two * cov + c2
                b1 = mu_a * mu_a + mu_b * mu_b + c1
                b2 = var_a + var_b + c2
                s = a1 * a2 / (b1 * b2)
                total += s
                if want:
                    den = b1 * b2
                    grads[ch, y, x] = (two * mu_b * (a2 - a1)) / den - s * two * mu_a * (
                        1 / b1 - 1 / b2)  # fmt: skip
                    grads[channels + ch, y, x] = -s / b2
                    grads[2 * channels + ch, y, x] = two * a1 / den
        rows[y] = total


@numba.njit(parallel=True, cache=True)
def _ssim_chain(a, b, blurred_grads, scale, out):
    """``∂(scale·mean S)/∂a = scale·(B[∂μ_a] + 2a·B[∂E a²] + b·B[∂E ab])`` (B: the blur)."""
    height, width, channels = a.shape
    two = 2
    for y in numba.prange(height):
        for x in range(width):
            for ch in range(channels):
                out[y, x, ch] = scale * (
                    blurred_grads[ch, y, x]
                    + two * a[y, x, ch] * blurred_grads[channels + ch, y, x]
                    + b[y, x, ch] * blurred_grads[2 * channels + ch, y, x]
                )


class _Ssim(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a, b, taps, c1, c2):
        a_np, b_np = a.detach().contiguous().numpy(), b.detach().contiguous().numpy()
        height, width, channels = a_np.shape
        planes = np.empty((5 * channels, height, width), a_np.dtype)
        _ssim_moments(a_np, b_np, planes)
        taps_np = taps.numpy().astype(a_np.dtype)
        blurred = blur_planes(planes, taps_np)
        rows = np.empty(height)
        _ssim_map(blurred, channels, a_np.dtype.type(c1), a_np.dtype.type(c2), rows,
                  np.empty((0, 0, 0), a_np.dtype))  # fmt: skip
        ctx.saved = (a_np, b_np, blurred, taps_np, c1, c2)
        return torch.tensor(rows.sum() / a_np.size, dtype=a.dtype)

    @staticmethod
    def backward(ctx, grad):
        a_np, b_np, blurred, taps_np, c1, c2 = ctx.saved
        height, width, channels = a_np.shape
        grads = np.empty((3 * channels, height, width), a_np.dtype)
        _ssim_map(blurred, channels, a_np.dtype.type(c1), a_np.dtype.type(c2),
                  np.empty(height), grads)  # fmt: skip
        out = np.empty_like(a_np)
        scale = a_np.dtype.type(float(grad) / a_np.size)
        _ssim_chain(a_np, b_np, blur_planes(grads, taps_np), scale, out)
        return torch.from_numpy(out), None, None, None, None


def fused_ssim(a: torch.Tensor, b: torch.Tensor, taps: torch.Tensor, c1: float, c2: float
               ) -> torch.Tensor:  # fmt: skip
    """Mean SSIM of [H,W,C] images with the separable window ``taps``; differentiable with
    respect to ``a`` only (``b`` is the measured image)."""
    if b.requires_grad:
        raise ValueError("fused_ssim differentiates the rendered image only: detach the target")
    return _Ssim.apply(a, b, taps, c1, c2)
