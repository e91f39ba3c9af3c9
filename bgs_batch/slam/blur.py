"""Separable Gaussian blur with zero padding: SSIM's filter, as a numba kernel.

PyTorch's CPU depthwise ``conv2d`` took ~180 ms per SSIM forward+backward at 320×240 (two
thirds of a mapping iteration); these loops over contiguous rows vectorise and take a few ms.
With a symmetric window and zero padding the blur is a symmetric linear operator, so its
backward is the same blur applied to the upstream gradient (`bgs_batch.slam.loss_kernels`' SSIM).
"""

from __future__ import annotations

import numba
import numpy as np
import torch


def gaussian_window(size: int, sigma: float, dtype: torch.dtype) -> torch.Tensor:
    """Normalised 1-D Gaussian taps of odd length ``size``."""
    x = torch.arange(size, dtype=dtype) - size // 2
    taps = torch.exp(-(x**2) / (2 * sigma**2))
    return taps / taps.sum()


@numba.njit(parallel=True, cache=True, fastmath={"contract"})
def _blur_kernel(src, taps, tmp, out):
    """``out = blur_y(blur_x(src))`` for ``src`` [N,H,W]; ``tmp`` holds the x-blurred images."""
    n, height, width = src.shape
    pad = taps.shape[0] // 2
    for r in numba.prange(n * height):
        i, y = r // height, r % height
        row, acc = src[i, y], tmp[i, y]
        acc[:] = 0
        for k in range(taps.shape[0]):
            shift = k - pad
            lo = max(0, -shift)
            hi = max(lo, min(width, width - shift))
            t, dst, seg = taps[k], acc[lo:hi], row[lo + shift : hi + shift]
            for x in range(hi - lo):  # slice views: offset indexing would not vectorise
                dst[x] += t * seg[x]
    for r in numba.prange(n * height):
        i, y = r // height, r % height
        acc = out[i, y]
        acc[:] = 0
        for k in range(taps.shape[0]):
            src_y = y + k - pad
            if 0 <= src_y < height:
                t, row = taps[k], tmp[i, src_y]
                for x in range(width):
                    acc[x] += t * row[x]


def blur_planes(src: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """Blur each of the contiguous [N,H,W] planes with the separable window ``taps`` (odd
    length, symmetric, same dtype), zero padding, same size: equal to ``conv2d`` with
    ``taps ⊗ taps``. A new array. Being its own adjoint, it also blurs gradients back."""
    if src.ndim != 3 or taps.ndim != 1 or taps.shape[0] % 2 != 1:
        raise ValueError("expected images [N,H,W] and an odd-length 1-D window")
    tmp, out = np.empty_like(src), np.empty_like(src)
    _blur_kernel(np.ascontiguousarray(src), taps.astype(src.dtype), tmp, out)
    return out
