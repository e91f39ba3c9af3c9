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
left perturbation T ← exp(ξ) T of `render.se3_exp`. All sums are fixed-order float64 torch
reductions on the CPU: the same input gives the same transform.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from bgs_batch.config import RegistrationConfig
from bgs_batch.render import Camera, se3_exp

MAD_TO_SIGMA = 1.4826  # the median absolute deviation of a Gaussian is 0.6745 σ
GEOMETRIC_SCALE_FLOOR_M = 1e-3
PHOTOMETRIC_SCALE_FLOOR = 2e-3  # intensity in [0, 1]
HUBER_K = 1.345  # 95 % efficiency on Gaussian residuals
DAMPING = 1e-9  # of the normal matrix's trace: keeps a degenerate (e.g. planar) system solvable
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
             initial: torch.Tensor | None = None) -> Registration:  # fmt: skip
    """Align `source` to `target` (same camera and size), coarse to fine from a level at most
    ``cfg.coarsest_width`` pixels wide, from `initial` (the identity when None)."""
    pyramid = [(source, target)]
    while pyramid[-1][0].camera.width > cfg.coarsest_width:
        pyramid.append((pyramid[-1][0].halved(), pyramid[-1][1].halved()))
    transform = torch.eye(4, dtype=torch.float64) if initial is None else initial.clone()
    steps = 0
    for level_source, level_target in reversed(pyramid):  # the finest last: `fit` reuses it
        problem = _Problem(level_source, level_target, cfg)
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


class _Problem:
    """The residuals of one pyramid level, with what does not depend on the transform."""

    def __init__(self, source: View, target: View, cfg: RegistrationConfig) -> None:
        self.cfg, self.camera = cfg, target.camera
        valid = source.depth > 0
        self.points = source.points()[valid]  # [N, 3]
        self.intensity = source.gray[valid]
        self.size = target.depth.shape
        points = target.points()
        gy, gx = torch.gradient(target.gray)
        # flattened [H·W, ...] target images, gathered by pixel index
        self.has_depth = (target.depth > 0).reshape(-1)
        self.surface = points.reshape(-1, 3)
        self.normals = _normals(points, target.depth > 0).reshape(-1, 3)
        self.gray = target.gray.reshape(-1)
        self.gradient = torch.stack([gx, gy], -1).reshape(-1, 2)  # ∂I/∂u, ∂I/∂v

    def step(self, transform: torch.Tensor, scales: tuple[float, float] | None
             ) -> tuple[torch.Tensor | None, tuple[float, float]]:  # fmt: skip
        """The Gauss-Newton step ξ from `transform`, and the terms' scales (fixed per level)."""
        x = self.points @ transform[:3, :3].T + transform[:3, 3]
        geometric, j_geometric = self._geometric(x)
        photometric, j_photometric = self._photometric(x)
        if scales is None:
            scales = (_robust_scale(geometric, GEOMETRIC_SCALE_FLOOR_M),
                      _robust_scale(photometric, PHOTOMETRIC_SCALE_FLOOR))  # fmt: skip
        residuals = torch.cat([geometric / scales[0], photometric / scales[1]])
        jacobian = torch.cat([j_geometric / scales[0], j_photometric / scales[1]])
        if residuals.numel() < 6:
            return None, scales
        weights = _huber_weights(residuals)
        normal = jacobian.T @ (weights[:, None] * jacobian)
        normal = normal + DAMPING * torch.trace(normal) * torch.eye(6, dtype=torch.float64)
        rhs = jacobian.T @ (weights * residuals)
        return -torch.linalg.solve(normal, rhs), scales

    def fit(self, transform: torch.Tensor) -> tuple[float, float]:
        """(fitness, point-to-plane RMS) of `transform` at this level."""
        if self.points.shape[0] == 0:
            return 0.0, float("inf")
        x = self.points @ transform[:3, :3].T + transform[:3, 3]
        geometric, _ = self._geometric(x)
        if geometric.numel() == 0:
            return 0.0, float("inf")
        fitness = geometric.numel() / self.points.shape[0]
        return fitness, float(geometric.square().mean().sqrt())

    def _project(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Pixel coordinates (u, v) of points x and whether they lie in front of the camera."""
        c = self.camera
        z = x[:, 2]
        front = z > 1e-6
        z = torch.where(front, z, 1.0)
        return c.fx * x[:, 0] / z + c.cx, c.fy * x[:, 1] / z + c.cy, front

    def _geometric(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Point-to-plane residuals [M] and their Jacobians [M, 6] of the associated points."""
        h, w = self.size
        u, v, front = self._project(x)
        col, row = torch.round(u).long(), torch.round(v).long()
        inside = front & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        pixel = row.clamp(0, h - 1) * w + col.clamp(0, w - 1)
        normal = self.normals[pixel]
        offset = x - self.surface[pixel]
        ok = (inside & self.has_depth[pixel] & normal.any(-1)
              & (offset.norm(dim=-1) < self.cfg.max_distance))  # fmt: skip
        x, normal, offset = x[ok], normal[ok], offset[ok]
        residual = (normal * offset).sum(-1)
        return residual, torch.cat([normal, torch.linalg.cross(x, normal)], -1)

    def _photometric(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Intensity residuals [M] and their Jacobians [M, 6] where the bilinear sample's four
        target pixels all have depth (the map is there)."""
        c, (h, w) = self.camera, self.size
        u, v, front = self._project(x)
        u0, v0 = torch.floor(u), torch.floor(v)
        inside = front & (u0 >= 0) & (u0 < w - 1) & (v0 >= 0) & (v0 < h - 1)
        top_left = v0.long().clamp(0, h - 2) * w + u0.long().clamp(0, w - 2)
        corners = [top_left, top_left + 1, top_left + w, top_left + w + 1]
        ok = inside & torch.stack([self.has_depth[k] for k in corners]).all(0)
        fu, fv = (u - u0)[ok], (v - v0)[ok]
        bilinear = [(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv]
        corners = [k[ok] for k in corners]

        def sample(image: torch.Tensor) -> torch.Tensor:
            return sum(wt.reshape(-1, *(1,) * (image.dim() - 1)) * image[k]
                       for wt, k in zip(bilinear, corners, strict=True))  # fmt: skip

        residual = sample(self.gray) - self.intensity[ok]
        grad = sample(self.gradient)  # [M, 2]
        x = x[ok]
        inv_z = 1.0 / x[:, 2]
        # ∂I/∂x through the pinhole: (g_u fx / z, g_v fy / z, −(g_u fx X + g_v fy Y) / z²)
        g_u, g_v = grad[:, 0] * c.fx * inv_z, grad[:, 1] * c.fy * inv_z
        d_point = torch.stack([g_u, g_v, -(g_u * x[:, 0] + g_v * x[:, 1]) * inv_z], -1)
        return residual, torch.cat([d_point, torch.linalg.cross(x, d_point)], -1)


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


def _robust_scale(residuals: torch.Tensor, floor: float) -> float:
    if residuals.numel() == 0:
        return floor
    return max(MAD_TO_SIGMA * float(residuals.abs().median()), floor)


def _huber_weights(scaled: torch.Tensor) -> torch.Tensor:
    magnitude = scaled.abs()
    return torch.where(magnitude <= HUBER_K, 1.0, HUBER_K / magnitude.clamp_min(1e-30))
