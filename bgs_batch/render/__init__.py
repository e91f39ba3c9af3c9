"""Differentiable CPU Gaussian rasterizer with opacity-induced colour and depth variance.

Public API: :func:`render` (map → images), built from :func:`project` (3D → screen Gaussians)
and :func:`rasterize` (screen Gaussians → colour, depth, alpha, ``V_C``, ``V_D``), plus
:func:`se3_exp` for pose gradients. Kernels are compiled by numba with ``cache=True``; set
``NUMBA_CACHE_DIR`` to a writable directory when the package directory is read-only.
"""

from .camera import Camera, se3_exp
from .project import Projected, project, shape_matrices
from .rasterize import RasterOutput, rasterize
from .render import Gaussians, render

__all__ = [
    "Camera",
    "Gaussians",
    "Projected",
    "RasterOutput",
    "project",
    "rasterize",
    "render",
    "se3_exp",
    "shape_matrices",
]
