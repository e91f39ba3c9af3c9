"""End-to-end differentiable render of a Gaussian map: projection, then rasterization."""

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .camera import Camera
from .project import project
from .rasterize import DEFAULT_BACKEND, RasterOutput, rasterize


@dataclass
class Gaussians:
    """Raw (unactivated) parameters of N Gaussians (docs/method.md §1).

    Colours are stored as plain RGB (SH degree 0 without the SH-DC constant); opacity and the
    opacity uncertainty are activated as ``o_i = sigmoid(opacity_logits)`` and
    ``v_i = softplus(uncertainty_logits)``.
    """

    means: torch.Tensor
    """[N,3] world positions."""
    log_scales: torch.Tensor
    """[N,3] log standard deviations."""
    quats: torch.Tensor
    """[N,4] (w, x, y, z) rotations, any norm."""
    opacity_logits: torch.Tensor
    """[N] opacity logits."""
    colors: torch.Tensor
    """[N,3] RGB."""
    uncertainty_logits: torch.Tensor
    """[N] raw opacity-uncertainty parameters ``r_i`` (initially −7)."""

    def __len__(self) -> int:
        return self.means.shape[0]


def render(
    gaussians: Gaussians,
    viewmat: torch.Tensor,
    camera: Camera,
    *,
    full_grad: bool = True,
    shapes: torch.Tensor | None = None,
    backend: str = DEFAULT_BACKEND,
) -> RasterOutput:
    """Render colour, depth, alpha and the variances ``V_C``, ``V_D`` (paper Eq. 3, 12, 13).

    Gradients reach every Gaussian parameter and ``viewmat`` (world-to-camera); for tracking,
    pass ``viewmat = se3_exp(ξ) @ viewmat₀`` and differentiate with respect to ``ξ``, and
    ``shapes`` = :func:`.project.shape_matrices` of the fixed map to skip recomputing them.
    See :func:`.rasterize.rasterize` for ``full_grad`` and ``backend``.
    """
    g = gaussians
    proj = project(g.means, g.log_scales, g.quats, g.opacity_logits, viewmat, camera,
                   shapes=shapes, backend=backend)  # fmt: skip
    ids = proj.ids
    return rasterize(
        proj.means2d,
        proj.conics,
        proj.depths,
        torch.sigmoid(g.opacity_logits[ids]),
        g.colors[ids],
        F.softplus(g.uncertainty_logits[ids]),
        camera.width,
        camera.height,
        full_grad=full_grad,
        depth_slopes=proj.depth_slopes,
        backend=backend,
    )
