"""Dense RGB-D registration of a measured frame to a view of the map: tracking's warm start.

`register` finds the rigid motion T (source camera → target camera) that aligns a measured
RGB-D frame (the source) with a target view, in tracking the active submap rendered at the
constant-velocity pose (docs/method.md §6). It minimises, by Gauss-Newton coarse to fine, two
residuals per source pixel with valid depth, each divided by its own robust scale and weighted
by Huber's function (iteratively reweighted least squares):

- geometric: the point-to-plane distance n·(T x − v) to the target surface at the pixel the
  point projects to (projective association, as KinectFusion's ICP); pairs further apart than
  ``max_distance`` are not associated;
- photometric: the intensity difference I_t(π(T x)) − I_s(x) (as dense visual odometry, DVO),
  sampled bilinearly, with its gradient through the projection.

Each term's scale is 1.4826 × its median absolute residual at the level's first iteration
(floored), so neither term needs a weight tuned per sensor or scene. The pose update is the
left perturbation T ← exp(ξ) T of `render.se3_exp`. The residuals and normal equations are
numba kernels (`registration_kernels`) with fixed-order float64 sums: the same input gives the
same transform.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from bgs_batch.config import RegistrationConfig
from bgs_batch.render import Camera, se3_exp
from bgs_batch.slam.tracking import registration_kernels as kernels

MAD_TO_SIGMA = 1.4826  # the median absolute deviation of a Gaussian is 0.6745 σ
GEOMETRIC_SCALE_FLOOR_M = 1e-3
PHOTOMETRIC_SCALE_FLOOR = 2e-3  # intensity in [0, 1]
HUBER_K = 1.345  # 95 % efficiency on Gaussian residuals
DAMPING = 1e-9  # of the normal matrix's trace: keeps a degenerate (e.g. planar) system solvable
JACOBIAN_COLUMNS = 6  # a step needs at least as many residuals
GRAY_WEIGHTS = (0.299, 0.587, 0.114)  # ITU-R BT.601 luma


@dataclass(frozen=True)
class View:
    """One RGB-D image for registration: intensity [H, W] in [0, 1] and depth [H, W] in metres
    (0: invalid), float64, with its pinhole camera."""

    gray: torch.Tensor
    depth: torch.Tensor
    camera: Camera

    @staticmethod
    def of(rgb: torch.Tensor, depth: torch.Tensor, camera: Camera) -> View:
        """From colour [H, W, 3] in [0, 1] and depth [H, W] or [H, W, 1]."""
        weights = torch.tensor(GRAY_WEIGHTS, dtype=torch.float64)
        gray = rgb.to(torch.float64) @ weights
        return View(gray, depth.to(torch.float64).reshape(gray.shape), camera)

    def halved(self) -> View:
        """Half the resolution: 2×2 block means (depth over its valid readings)."""
        h, w = self.gray.shape[0] // 2 * 2, self.gray.shape[1] // 2 * 2

        def blocks(image: torch.Tensor) -> torch.Tensor:
            return image[:h, :w].reshape(h // 2, 2, w // 2, 2)

        valid = (blocks(self.depth) > 0).to(torch.float64)
        count = valid.sum((1, 3))
        depth = torch.where(count > 0, blocks(self.depth).sum((1, 3)) / count.clamp_min(1), 0.0)
        camera = self.camera.scaled(0.5)
        camera = Camera(camera.fx, camera.fy, camera.cx, camera.cy, w // 2, h // 2)
        return View(blocks(self.gray).mean((1, 3)), depth, camera)

    def points(self) -> torch.Tensor:
        """Camera-frame points [H, W, 3] of every pixel (z = depth; 0 where invalid)."""
        c, (h, w) = self.camera, self.depth.shape
        v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64),
                              torch.arange(w, dtype=torch.float64), indexing="ij")  # fmt: skip
        z = self.depth
        return torch.stack([(u - c.cx) / c.fx * z, (v - c.cy) / c.fy * z, z], -1)


@dataclass(frozen=True)
class Registration:
    """The result of `register`."""

    transform: torch.Tensor  # (4, 4) float64: source camera → target camera
    fitness: float  # share of the source's valid pixels associated with the target surface
    rmse: float  # point-to-plane RMS (m) of the associated pixels
    iterations: int  # Gauss-Newton steps over all levels


def register(source: View, target: View, cfg: RegistrationConfig,
             initial: torch.Tensor | None = None, photometric: bool = True
             ) -> Registration:  # fmt: skip
    """Align `source` to `target` (same camera and size), coarse to fine from a level at most
    ``cfg.coarsest_width`` pixels wide, from `initial` (the identity when None); by the
    point-to-plane term alone when not `photometric` (a colour image that may not sit on its
    depth image cannot move the result)."""
    pyramid = [(source, target)]
    while pyramid[-1][0].camera.width > cfg.coarsest_width:
        pyramid.append((pyramid[-1][0].halved(), pyramid[-1][1].halved()))
    transform = torch.eye(4, dtype=torch.float64) if initial is None else initial.clone()
    steps = 0
    for level_source, level_target in reversed(pyramid):  # the finest last: `fit` reuses it
        problem = _Problem(level_source, level_target, cfg, photometric)
        scales = None
        for _ in range(cfg.iterations):
            step, scales = problem.step(transform, scales)
            if step is None:
                break
            transform = se3_exp(step) @ transform
            steps += 1
            if float(step.norm()) < cfg.converged:
                break
    fitness, rmse = problem.fit(transform)
    return Registration(transform, fitness, rmse, steps)


def residuals(source: View, target: View, cfg: RegistrationConfig, transform: torch.Tensor
              ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The geometric (m) and photometric residuals of the source pixels associated with the
    target at `transform`, at full resolution: what `register` minimises."""
    return _Problem(source, target, cfg).residuals(transform)


class _Problem:
    """One pyramid level: the source points and the target images the residuals read, as the
    float64 arrays of `registration_kernels`."""

    def __init__(self, source: View, target: View, cfg: RegistrationConfig,
                 photometric: bool = True) -> None:  # fmt: skip
        self.cfg = cfg
        self.photometric = photometric
        valid = source.depth > 0
        self.points = source.points()[valid].numpy()  # [N, 3]
        self.intensities = source.gray[valid].numpy()
        points = target.points()
        gy, gx = torch.gradient(target.gray)
        c = target.camera
        height, width = target.depth.shape
        # flattened [H·W, ...] target images, gathered by pixel index
        self.target = (
            points.reshape(-1, 3).numpy(),
            _normals(points, target.depth > 0).reshape(-1, 3).numpy(),
            (target.depth > 0).reshape(-1).numpy(),
            target.gray.reshape(-1).numpy(),
            torch.stack([gx, gy], -1).reshape(-1, 2).numpy(),  # ∂I/∂u, ∂I/∂v
            np.array([c.fx, c.fy, c.cx, c.cy]),
            height,
            width,
            cfg.max_distance,
        )

    def step(self, transform: torch.Tensor, scales: tuple[float, float] | None
             ) -> tuple[torch.Tensor | None, tuple[float, float]]:  # fmt: skip
        """The Gauss-Newton step ξ from `transform`, and the terms' scales (fixed per level)."""
        if scales is None:
            geometric, photometric = self.residuals(transform)
            scales = (_robust_scale(geometric, GEOMETRIC_SCALE_FLOOR_M),
                      _robust_scale(photometric, PHOTOMETRIC_SCALE_FLOOR) if self.photometric
                      else math.inf)  # an infinite scale: the term weighs nothing  # fmt: skip
        normal, rhs, used = kernels.normal_equations(
            self.points, self.intensities, transform.numpy(), *self.target, *scales, HUBER_K
        )
        normal = torch.from_numpy(normal)
        if used < JACOBIAN_COLUMNS or not float(torch.trace(normal)) > 0:  # nothing constrains it
            return None, scales
        normal = normal + DAMPING * torch.trace(normal) * torch.eye(6, dtype=torch.float64)
        return -torch.linalg.solve(normal, torch.from_numpy(rhs)), scales

    def fit(self, transform: torch.Tensor) -> tuple[float, float]:
        """(fitness, point-to-plane RMS) of `transform` at this level."""
        geometric, _ = self.residuals(transform)
        if geometric.size == 0:
            return 0.0, float("inf")
        return geometric.size / self.points.shape[0], float(np.sqrt(np.mean(geometric**2)))

    def residuals(self, transform: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        return kernels.residuals(self.points, self.intensities, transform.numpy(), *self.target)


def _normals(points: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Unit normals [H, W, 3] of a vertex map by central differences, facing the camera; zero
    where a neighbour is missing or the surface breaks (depth jumps by more than 5 %)."""
    normals = torch.zeros_like(points)
    right, left = points[1:-1, 2:], points[1:-1, :-2]
    down, up = points[2:, 1:-1], points[:-2, 1:-1]
    n = torch.linalg.cross(right - left, down - up)
    centre = points[1:-1, 1:-1]
    z = centre[..., 2:]
    neighbours = torch.stack([right, left, down, up])[..., 2:]
    ok = (valid[1:-1, 1:-1] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1]
          & valid[:-2, 1:-1] & ((neighbours - z).abs() < 0.05 * z).all(0)[..., 0])  # fmt: skip
    length = n.norm(dim=-1, keepdim=True)
    ok = ok & (length[..., 0] > 0)
    n = n / length.clamp_min(1e-30)
    n = torch.where((n * centre).sum(-1, keepdim=True) > 0, -n, n)  # towards the camera
    normals[1:-1, 1:-1] = torch.where(ok[..., None], n, 0.0)
    return normals


def _robust_scale(residuals: np.ndarray, floor: float) -> float:
    """MAD_TO_SIGMA × the lower median of |r| (as `torch.median`), at least `floor`."""
    if residuals.size == 0:
        return floor
    middle = (residuals.size - 1) // 2
    return max(MAD_TO_SIGMA * float(np.partition(np.abs(residuals), middle)[middle]), floor)
