"""Differentiable rasterization of projected Gaussians with opacity-induced variances.

One operator, :func:`rasterize`, with two backends: ``"numba"`` (default; tile based,
deterministic, float32 or float64) and ``"torch"`` (the dense float64 oracle of
:mod:`.reference`). Both implement docs/method.md §1-2 (paper Eq. 3, 12, 13).
"""

import threading
from typing import NamedTuple

import numba
import numpy as np
import torch

from . import _numba_raster as nr
from .constants import TILE_SIZE
from .reference import rasterize_ref

BACKENDS = ("numba", "torch")
DEFAULT_BACKEND = "numba"
DEPTH_NORM_EPS = 1e-8
"""Alpha floor of :meth:`RasterOutput.normalized_depth` (keeps empty pixels at depth 0)."""


class RasterOutput(NamedTuple):
    """Per-pixel renders, channels last: [H,W,3] colour, [H,W,1] for the rest."""

    color: torch.Tensor
    """``C = Σ c_i α_i T_i``."""
    depth: torch.Tensor
    """Unnormalised ``D = Σ d_i α_i T_i`` (camera z, ``d_i`` at the pixel: :func:`rasterize`)."""
    alpha: torch.Tensor
    """``A = Σ α_i T_i = 1 − T_final``."""
    var_color: torch.Tensor
    """``V_C = Σ (c_i − C)² T_i² v_i`` per channel (paper Eq. 3, 12), no floors."""
    var_depth: torch.Tensor
    """``V_D = Σ (d_i − D)² T_i² v_i`` (paper Eq. 13), no floors."""

    def normalized_depth(self) -> torch.Tensor:
        """Alpha-normalised depth ``D / A`` (0 where nothing was rendered)."""
        return self.depth / self.alpha.clamp_min(DEPTH_NORM_EPS)


def check_float_inputs(*tensors: torch.Tensor) -> torch.dtype:
    """The common dtype of CPU float32/float64 tensors; raises ``ValueError`` otherwise."""
    dtype = tensors[0].dtype
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"expected float32 or float64 tensors, got {dtype}")
    for t in tensors:
        if t.dtype != dtype:
            raise ValueError(f"mixed dtypes {dtype} and {t.dtype}: cast all inputs to one dtype")
        if t.device.type != "cpu":
            raise ValueError(f"the numba backend runs on CPU tensors, got device {t.device}")
    return dtype


def rasterize(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    depths: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    variances: torch.Tensor,
    width: int,
    height: int,
    *,
    full_grad: bool = True,
    depth_slopes: torch.Tensor | None = None,
    backend: str = DEFAULT_BACKEND,
) -> RasterOutput:
    """Composite M projected Gaussians front to back into a ``height`` × ``width`` image.

    Args:
        means2d: [M,2] pixel positions (OpenCV convention, see :mod:`.constants`).
        conics: [M,3] inverse screen covariances ``(a, b, c)``, positive definite.
        depths: [M] camera-space depths ``d_i`` (sort key and depth feature).
        opacities: [M] activated opacities ``o_i``.
        colors: [M,3] RGB colours ``c_i``.
        variances: [M] opacity variances ``v_i = softplus(r_i)`` (docs/method.md §1).
        full_grad: differentiate ``T_i²`` in the variances too; ``False`` is the authors'
            gradient (``T_i²`` constant, ``C`` and ``D`` still differentiated).
        depth_slopes: optional [M,2] screen gradients ``s_i`` of each Gaussian's depth: at pixel
            ``p`` its depth feature is ``d_i + s_i·(p − μ_i)``, the depth of its plane
            (:attr:`.project.Projected.depth_slopes`); None: ``d_i`` everywhere.
        backend: ``"numba"`` or ``"torch"``.
    """
    if depth_slopes is None:
        depth_slopes = means2d.new_zeros(means2d.shape)
    if depth_slopes.shape != means2d.shape:
        raise ValueError(f"depth_slopes must be {list(means2d.shape)}, got "
                         f"{list(depth_slopes.shape)}")  # fmt: skip
    args = (means2d, conics, depths, opacities, colors, variances, depth_slopes)
    if backend == "torch":
        return RasterOutput(*rasterize_ref(*args, width, height, full_grad))
    if backend != "numba":
        raise ValueError(f"unknown backend {backend!r}; choose one of {BACKENDS}")
    check_float_inputs(*args)
    return RasterOutput(*_RasterizeNumba.apply(*args, width, height, full_grad))


_scratch = threading.local()


def scratch(name: str, shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
    """A reusable uninitialised array for transient kernel data (per thread, grow only).

    Fresh multi-megabyte arrays cost page faults on every call (several ms at 640×480); never
    hand a scratch array (or a view of it) to the caller.
    """
    size = int(np.prod(shape))
    key = (name, np.dtype(dtype))
    buf = getattr(_scratch, "buffers", None)
    if buf is None:
        buf = _scratch.buffers = {}
    if key not in buf or buf[key].size < size:
        buf[key] = np.empty(size, dtype)
    return buf[key][:size].reshape(shape)


def depth_order(depths: np.ndarray) -> np.ndarray:
    """Indices that sort `depths` ascending, ties by index: exactly
    ``np.argsort(depths, kind="stable")``, for float32 several times faster.

    Each float32 depth's bits, made order preserving as an unsigned integer (the sign bit set
    for non-negative values, all bits flipped for negative ones), are the key of a stable radix
    sort (:func:`._numba_raster.radix_order`), which leaves no order to chance. ±0 and NaN do
    not occur: projection keeps only depths beyond the near plane. Float64 (the tests' oracle
    precision) keeps the stable argsort.
    """
    if depths.dtype != np.float32:
        return np.argsort(depths, kind="stable")
    bits = depths.view(np.uint32)
    keys = np.where(bits >> 31, ~bits, bits | np.uint32(0x80000000))
    return nr.radix_order(keys)


def to_numpy(t: torch.Tensor) -> np.ndarray:
    """A contiguous numpy view (no copy when already contiguous) of a detached CPU tensor."""
    return t.detach().contiguous().numpy()


class _RasterizeNumba(torch.autograd.Function):
    """Autograd wrapper of the numba tile kernels (:mod:`._numba_raster`)."""

    @staticmethod
    def forward(
        ctx, means2d, conics, depths, opacities, colors, variances, slopes, width, height, full
    ):
        dtype = means2d.dtype
        mean_np, conic_np, opac_np, var_np, slope_np = map(
            to_numpy, (means2d, conics, opacities, variances, slopes)
        )
        a, b, c = conic_np.T
        if not (np.all(a > 0) and np.all(a * c > b * b)):
            raise ValueError("conics must be positive definite (a > 0, a·c > b²)")
        feats = to_numpy(torch.cat([colors.detach(), depths.detach().unsqueeze(-1)], -1))
        tiles_x, n_tiles = nr.tile_grid(height, width)
        rects = nr.compute_rects(mean_np, conic_np, opac_np, width, height)
        order = depth_order(to_numpy(depths))
        tile_start, isect_gauss, isect_slot, gauss_start = nr.bin_tiles(
            rects, order, tiles_x, n_tiles
        )
        # Pixel coordinates padded to whole tiles (the kernels' lanes).
        xs, ys = (
            np.arange(-(-n // TILE_SIZE) * TILE_SIZE, dtype=feats.dtype) for n in (width, height)
        )
        consts = nr.raster_consts(feats.dtype)
        out_feat = torch.empty(height, width, nr.N_FEAT, dtype=dtype)
        out_var = torch.empty(height, width, nr.N_FEAT, dtype=dtype)
        out_dvdf = torch.empty(height, width, nr.N_FEAT, dtype=dtype)
        out_trans = torch.empty(height, width, dtype=dtype)
        out_last = torch.empty(height, width, dtype=torch.int64)
        nr.raster_fwd(
            mean_np, conic_np, opac_np, feats, slope_np, var_np, rects, tile_start, isect_gauss,
            xs, ys, consts, numba.get_num_threads(),
            *(t.numpy() for t in (out_feat, out_trans, out_var, out_dvdf, out_last)),
        )  # fmt: skip
        ctx.full_grad = full
        ctx.kernel_args = (
            mean_np, conic_np, opac_np, feats, slope_np, var_np, rects, tile_start, isect_gauss,
            xs, ys, consts, numba.get_num_threads(),
        )  # fmt: skip
        ctx.reduce_args = (isect_slot, gauss_start)
        ctx.saved = (out_feat.numpy(), out_trans.numpy(), out_dvdf.numpy(), out_last.numpy())
        alpha = (1 - out_trans).unsqueeze(-1)
        return out_feat[..., :3], out_feat[..., 3:], alpha, out_var[..., :3], out_var[..., 3:]

    @staticmethod
    def backward(ctx, g_color, g_depth, g_alpha, g_var_color, g_var_depth):
        feats = ctx.kernel_args[3]
        grads_in = []
        for name, g_rgb, g_d in (("feat", g_color, g_depth), ("var", g_var_color, g_var_depth)):
            buf = scratch("grad_" + name, (*g_rgb.shape[:2], nr.N_FEAT), feats.dtype)
            buf[..., :3] = to_numpy(g_rgb)
            buf[..., 3:] = to_numpy(g_d)
            grads_in.append(buf)
        slots = scratch("slots", (ctx.kernel_args[8].shape[0], nr.N_SLOT), feats.dtype)
        want_appearance = any(ctx.needs_input_grad[3:6])  # else pose-only tracking
        variance_only = not any(ctx.needs_input_grad[:5])  # the uncertainty refinement
        nr.raster_bwd(
            *ctx.kernel_args, ctx.full_grad, want_appearance, variance_only, *ctx.saved,
            grads_in[0],
            to_numpy(g_alpha[..., 0]), grads_in[1], slots,
        )  # fmt: skip
        grads = np.empty((feats.shape[0], nr.N_SLOT), feats.dtype)
        nr.reduce_slots(slots, *ctx.reduce_args, grads)
        g = torch.from_numpy(grads)
        return (
            g[:, nr.S_MEAN : nr.S_MEAN + 2],
            g[:, nr.S_CONIC : nr.S_CONIC + 3],
            g[:, nr.S_FEAT + 3],
            g[:, nr.S_OPACITY],
            g[:, nr.S_FEAT : nr.S_FEAT + 3],
            g[:, nr.S_VAR],
            g[:, nr.S_SLOPE : nr.S_SLOPE + 2],
            None,
            None,
            None,
        )
