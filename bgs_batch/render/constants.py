"""Named constants of the rendering model (3DGS conventions, docs/method.md §1).

Pixel convention: pixel ``(x, y)`` is sampled at image coordinates ``(x, y)``, the OpenCV
convention for the intrinsics ``u = fx·X/Z + cx``, ``v = fy·Y/Z + cy``.
"""

ALPHA_MAX = 0.99
"""Per-Gaussian alpha clamp: ``α_i = min(ALPHA_MAX, o_i·G_i)``."""

ALPHA_MIN = 1.0 / 255.0
"""A Gaussian with ``α_i < ALPHA_MIN`` at a pixel is skipped there."""

T_MIN = 1e-4
"""Compositing stops *before* a Gaussian that would bring the transmittance below ``T_MIN``."""

LOWPASS = 0.3
"""EWA low-pass filter: added to the diagonal of every screen-space covariance (pixels²)."""

SLOPE_RIDGE = 1e-3
"""Depth slopes use the screen covariance without the low-pass (which would flatten the planes
of Gaussians a pixel or so wide) plus this share of its trace on the diagonal, which bounds its
condition number for a disc seen edge on."""

NEAR_PLANE = 0.01
"""Gaussians whose centre is closer than this camera-space depth (metres) are culled."""

FRUSTUM_MARGIN = 1.3
"""Gaussians whose projected centre lies further than ``FRUSTUM_MARGIN`` half-widths
(half-heights) from the image centre are culled (the 3DGS guard band)."""

TILE_SIZE = 16
"""Side of the square screen tiles used for binning (pixels)."""
