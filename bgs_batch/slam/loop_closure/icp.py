"""Point-to-plane ICP on Gaussian centres: the geometric fallback of submap registration.

Written with numpy and scipy rather than Open3D's `registration_icp`: Open3D merges the
correspondences of its OpenMP threads in whatever order they finish, so its sums (and our
checkpoint/resume equality) would depend on timing. Here every sum has a fixed order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bgs_batch.geometry import kd_tree
from bgs_batch.render import se3_exp

CONVERGED = 1e-7  # stop when the update twist is this small (rad / m)
MIN_CORRESPONDENCES = 6  # a 6-DoF step needs at least this many


@dataclass(frozen=True)
class IcpResult:
    transform: np.ndarray  # (4, 4) source → target
    fitness: float  # share of source points with a target neighbour within the distance
    rmse: float  # of their point-to-plane residuals, m


def normals(points: np.ndarray, neighbours: int) -> np.ndarray:
    """Unit normals from the smallest principal axis of each point's neighbourhood."""
    k = min(neighbours, len(points))
    _, idx = kd_tree(points).query(points, k=k)
    local = points[np.atleast_2d(idx)]
    centred = local - local.mean(1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
    return vectors[:, :, 0]


def subsample(points: np.ndarray, count: int) -> np.ndarray:
    """At most `count` evenly spaced points (deterministic)."""
    if len(points) <= count:
        return points
    return points[np.linspace(0, len(points) - 1, count).astype(int)]


def point_to_plane(
    source: np.ndarray,
    target: np.ndarray,
    init: np.ndarray,
    max_distance: float,
    iterations: int,
    neighbours: int,
) -> IcpResult:
    """Align `source` (n, 3) to `target` (m, 3) from `init` by Gauss-Newton point-to-plane."""
    tree = kd_tree(target)
    target_normals = normals(target, neighbours)
    transform = init.copy()
    for _ in range(iterations):
        moved = source @ transform[:3, :3].T + transform[:3, 3]
        dist, idx = tree.query(moved, distance_upper_bound=max_distance)
        ok = np.isfinite(dist)
        if ok.sum() < MIN_CORRESPONDENCES:
            break
        p, q, n = moved[ok], target[idx[ok]], target_normals[idx[ok]]
        residual = np.einsum("ij,ij->i", p - q, n)
        jac = np.concatenate([n, np.cross(p, n)], 1)  # d r / d (ρ, φ) of a left twist
        step = np.linalg.lstsq(jac.T @ jac, -jac.T @ residual, rcond=None)[0]
        delta = se3_exp(torch.from_numpy(step)).numpy()
        transform = delta @ transform
        if np.linalg.norm(step) < CONVERGED:
            break
    moved = source @ transform[:3, :3].T + transform[:3, 3]
    dist, idx = tree.query(moved, distance_upper_bound=max_distance)
    ok = np.isfinite(dist)
    if not ok.any():
        return IcpResult(transform, 0.0, float("inf"))
    residual = np.einsum("ij,ij->i", moved[ok] - target[idx[ok]], target_normals[idx[ok]])
    return IcpResult(transform, float(ok.mean()), float(np.sqrt(np.mean(residual**2))))
