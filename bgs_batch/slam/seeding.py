"""Where new Gaussians come from: pixels chosen on a keyframe, back-projected with its depth.

LoopSplat's rules (docs/method.md §5): a submap's first frame is seeded at uniformly
random pixels, at pixels drawn in proportion to the colour gradient and at all Canny edge pixels;
later keyframes only where the map is thin (alpha below a threshold) or lies in front of the
measured surface by far more than usual. Candidates near an existing Gaussian are dropped.
"""

from __future__ import annotations

import cv2
import numpy as np

from bgs_batch.config import SeedingConfig
from bgs_batch.geometry import kd_tree

CANNY_THRESHOLDS = (100, 200)
CANNY_APERTURE = 3
EDGE_DILATION = np.ones((2, 2), np.uint8)


def _grey(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def submap_seed_pixels(
    rgb: np.ndarray, depth: np.ndarray, cfg: SeedingConfig, rng: np.random.Generator
) -> np.ndarray:
    """Flat pixel indices to seed a new submap from its first frame (valid depth only)."""
    grey = _grey(rgb)
    n_pixels = grey.size
    uniform = rng.choice(n_pixels, min(cfg.new_submap_points, n_pixels), replace=False)
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1)
    magnitude = np.sqrt(gx * gx + gy * gy).ravel().astype(np.float64)
    by_gradient = np.empty(0, np.int64)
    if magnitude.sum() > 0 and cfg.new_submap_gradient_points > 0:
        by_gradient = rng.choice(n_pixels, cfg.new_submap_gradient_points, replace=True,
                                 p=magnitude / magnitude.sum())  # fmt: skip
    edges = cv2.Canny(grey, *CANNY_THRESHOLDS, apertureSize=CANNY_APERTURE, L2gradient=True)
    edges = np.flatnonzero(cv2.dilate(edges, EDGE_DILATION))
    pixels = np.unique(np.concatenate([uniform, by_gradient, edges]))
    return pixels[depth.ravel()[pixels] > 0]


def keyframe_seed_pixels(
    alpha: np.ndarray,
    rendered_depth: np.ndarray,
    depth: np.ndarray,
    cfg: SeedingConfig,
    rng: np.random.Generator,
) -> np.ndarray:
    """Flat pixel indices where a later keyframe adds Gaussians: thin map or map in front."""
    valid = depth > 0
    error = np.abs(rendered_depth - depth)
    median = np.median(error[valid]) if valid.any() else 0.0
    in_front = (rendered_depth > depth) & (error > cfg.depth_error_factor * median)
    pixels = np.flatnonzero(((alpha < cfg.alpha_threshold) | in_front) & valid)
    if len(pixels) > cfg.new_frame_points:
        pixels = np.sort(rng.choice(pixels, cfg.new_frame_points, replace=False))
    return pixels


def backproject(
    depth: np.ndarray, pixels: np.ndarray, intrinsics: np.ndarray, c2w: np.ndarray, push: float
) -> np.ndarray:
    """World points (M, 3) of flat pixel indices, depth scaled by `push` (seeds sit behind)."""
    h, w = depth.shape
    v, u = np.divmod(pixels, w)
    z = depth.ravel()[pixels].astype(np.float64) * push
    fx, fy, cx, cy = intrinsics[0, 0], intrinsics[1, 1], intrinsics[0, 2], intrinsics[1, 2]
    cam = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=1)
    return cam @ c2w[:3, :3].T + c2w[:3, 3]


def far_from(existing: np.ndarray, candidates: np.ndarray, min_distance: float) -> np.ndarray:
    """Boolean mask of candidates with no existing point within `min_distance` (KD-tree)."""
    if len(existing) == 0 or len(candidates) == 0:
        return np.ones(len(candidates), bool)
    dist, _ = kd_tree(existing).query(candidates, k=1, distance_upper_bound=min_distance)
    return ~np.isfinite(dist)


def surface_normals(depth: np.ndarray, pixels: np.ndarray, intrinsics: np.ndarray,
                    c2w: np.ndarray) -> np.ndarray:  # fmt: skip
    """World unit normals (M, 3) of the measured surface at flat pixel indices, from the depth
    image's central differences; NaN where a neighbour has no depth or the image border cuts."""
    h, w = depth.shape
    v, u = np.divmod(pixels, w)
    inside = (u > 0) & (u < w - 1) & (v > 0) & (v < h - 1)
    u, v = np.clip(u, 1, w - 2), np.clip(v, 1, h - 2)
    measured = np.where(depth > 0, depth, np.nan)

    def point(du: int, dv: int) -> np.ndarray:  # camera-frame points of the neighbours
        return backproject(measured, (v + dv) * w + u + du, intrinsics, np.eye(4), 1.0)

    normal = np.cross(point(1, 0) - point(-1, 0), point(0, 1) - point(0, -1))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    normal[~inside] = np.nan
    return normal @ c2w[:3, :3].T
