"""Differentiable EWA projection of 3D Gaussians through a pinhole camera.

Backends: ``"numba"`` (fused analytic forward/backward, the pose gradient reduced in the
kernel: no autograd graph over the Gaussians) and ``"torch"`` (autograd oracle in
:mod:`.reference`). The pose enters as a world-to-camera 4×4 ``viewmat``; compose it with
:func:`.camera.se3_exp` for se(3) tangent gradients.
"""

from typing import NamedTuple

import numba
import numpy as np
import torch

from . import _numba_project as npj
from .camera import Camera
from .rasterize import BACKENDS, DEFAULT_BACKEND, check_float_inputs, scratch, to_numpy
from .reference import project_ref


class Projected(NamedTuple):
    """The M visible Gaussians in screen space (inputs of :func:`.rasterize.rasterize`)."""

    means2d: torch.Tensor
    """[M,2] pixel positions ``(fx·x/z + cx, fy·y/z + cy)``."""
    conics: torch.Tensor
    """[M,3] inverse low-passed screen covariance ``(a, b, c)``."""
    depths: torch.Tensor
    """[M] camera-space depths ``z``."""
    depth_slopes: torch.Tensor
    """[M,2] screen gradients of each Gaussian's depth: the depth of its plane at pixel ``p`` is
    ``z + s·(p − means2d)``, where the pixel's ray meets it (unlike ``z``, unbiased for a
    surface seen at a slant)."""
    ids: torch.Tensor
    """[M] int64 indices of the visible Gaussians in the input arrays (ascending)."""


def shape_matrices(log_scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """[N,3,3] M_i = R(q̂_i)·diag(e^{s_i}), the view-independent factor of each covariance.

    For a map that stays fixed over many renders (tracking): compute it once and pass it as
    ``shapes`` to :func:`project` / :func:`.render.render`. No gradient reaches the inputs.
    """
    check_float_inputs(log_scales, quats)
    arrays = [to_numpy(t) for t in (log_scales, quats)]
    out = np.empty((arrays[0].shape[0], 3, 3), arrays[0].dtype)
    params = npj.project_params(None, out.dtype)
    npj.shape_matrices(*arrays, params, numba.get_num_threads(), out)
    return torch.from_numpy(out)


def project(
    means: torch.Tensor,
    log_scales: torch.Tensor,
    quats: torch.Tensor,
    opacity_logits: torch.Tensor,
    viewmat: torch.Tensor,
    camera: Camera,
    *,
    shapes: torch.Tensor | None = None,
    backend: str = DEFAULT_BACKEND,
) -> Projected:
    """Project N Gaussians and keep the visible ones (near plane, guard band, screen bounds).

    Args:
        means: [N,3] world positions μ_i.
        log_scales: [N,3] log standard deviations along the local axes.
        quats: [N,4] rotations as (w, x, y, z) quaternions (any norm).
        opacity_logits: [N] opacity logits; only used for the opacity-aware bounds.
        viewmat: [4,4] world-to-camera transform; gradients flow to its top 3×4 block.
        camera: intrinsics and image size.
        shapes: optional :func:`shape_matrices` of ``log_scales`` and ``quats`` (numba backend):
            the same result without recomputing them, and no gradient for those two.
    """
    if backend == "torch":
        *out, visible = project_ref(means, log_scales, quats, opacity_logits, viewmat, camera)
        ids = visible.nonzero().squeeze(-1)
        return Projected(*(t[ids] for t in out), ids)
    if backend != "numba":
        raise ValueError(f"unknown backend {backend!r}; choose one of {BACKENDS}")
    check_float_inputs(means, log_scales, quats, opacity_logits, viewmat)
    if shapes is not None and shapes.shape != (means.shape[0], 3, 3):
        raise ValueError(f"shapes must be [{means.shape[0]},3,3], got {list(shapes.shape)}")
    return Projected(
        *_ProjectNumba.apply(means, log_scales, quats, opacity_logits, viewmat, camera, shapes)
    )


class _ProjectNumba(torch.autograd.Function):
    """Autograd wrapper of :mod:`._numba_project`."""

    @staticmethod
    def forward(ctx, means, log_scales, quats, opacity_logits, viewmat, camera, shapes):
        n = means.shape[0]
        arrays = tuple(to_numpy(t) for t in (means, log_scales, quats, viewmat))
        params = npj.project_params(camera, arrays[0].dtype)
        dtype = arrays[0].dtype
        given = shapes is not None
        shape_np = to_numpy(shapes) if given else np.empty((0, 3, 3), dtype)
        means2d, conics = scratch("means2d", (n, 2), dtype), scratch("conics", (n, 3), dtype)
        depths, visible = scratch("depths", (n,), dtype), scratch("visible", (n,), np.bool_)
        slopes = scratch("slopes", (n, 2), dtype)
        npj.project_fwd(
            arrays[0], arrays[1], arrays[2], to_numpy(opacity_logits), arrays[3], params,
            camera.width, camera.height, shape_np, given, numba.get_num_threads(),
            means2d, conics, depths, slopes, visible,
        )  # fmt: skip
        ids = np.flatnonzero(visible)
        # np.take: the same rows as a[ids], several times faster for row arrays
        out = [
            torch.from_numpy(np.take(a, ids, axis=0)) for a in (means2d, conics, depths, slopes)
        ]
        ctx.arrays, ctx.params, ctx.ids, ctx.conics = arrays, params, ids, out[1].numpy()
        ctx.shapes = shape_np
        ids = torch.from_numpy(ids)
        ctx.mark_non_differentiable(ids)
        return *out, ids

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, g_slopes, _g_ids):
        means, log_scales, quats, viewmat = ctx.arrays
        given = ctx.shapes.shape[0] > 0
        want = ctx.needs_input_grad[0] or (not given and any(ctx.needs_input_grad[1:3]))
        rows = means.shape[0] if want else 0
        out = [np.zeros((rows, a.shape[1]), a.dtype) for a in (means, log_scales, quats)]
        pose = np.empty(npj.N_POSE, means.dtype)
        npj.project_bwd(
            means, log_scales, quats, viewmat, ctx.params, ctx.ids, ctx.conics,
            *map(to_numpy, (g_means2d, g_conics, g_depths, g_slopes)), want, ctx.shapes,
            given and not want, numba.get_num_threads(), *out, pose,
        )  # fmt: skip
        g_view = torch.zeros(4, 4, dtype=g_means2d.dtype)
        g_view[:3, :3] = torch.from_numpy(pose[:9].reshape(3, 3))
        g_view[:3, 3] = torch.from_numpy(pose[9:])
        g_means = torch.from_numpy(out[0]) if want else None
        g_scales, g_quats = (torch.from_numpy(a) if want and not given else None for a in out[1:])
        return g_means, g_scales, g_quats, None, g_view, None, None
