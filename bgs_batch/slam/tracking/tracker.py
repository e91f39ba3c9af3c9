"""Camera tracking against the active submap (paper §III-B, Eq. 15-17; docs/method.md §6).

The pose is a left perturbation of the initial world-to-camera matrix, ``w2c = exp(ξ) · w2c₀``
with ξ = (ρ, φ), or ``P exp(ξ) P⁻¹ · w2c₀`` with P the shift to a point on the optical axis at
``tracking.pivot_depth_ratio`` × the median depth (the rotation turns the camera about that
point), optimised on the uncertainty-normalised L1 loss by Adam (amsgrad, LoopSplat's rates;
the paper's tracker) or, from a trusted warm start, by Gauss-Newton steps
(``tracking.optimizer``; `_gauss_newton`): their first-order model holds within a few pixels,
so a start far off keeps Adam's coarse-to-fine walk. The map, and the sensor network's
variance (computed once per frame), are fixed. CPU levers: a coarse-to-fine image pyramid and
early stopping once the loss stops improving. The lowest-loss pose of the finest level is
kept, with its predictive-surprise scores (Eq. 9). Like LoopSplat, a frame that starts far
worse than the frames before it (fast motion) gets twice the iterations
(``tracking.init_err_ratio``).

With ``tracking.warm_start`` the optimisation starts instead from the constant-velocity pose
corrected by dense RGB-D registration of the measured frame to the map rendered there
(`registration.register`); an untrusted registration (too little overlap, or a correction
beyond ``registration.max_shift`` / ``max_turn_deg``) falls back to constant velocity, and a
trusted one is used only where the paper's loss is lower there than at constant velocity.
Either way the paper's loss has the final word: the start only decides where refinement begins.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass, field
from typing import Any

import torch

from bgs_batch.config import Config
from bgs_batch.render import Gaussians, RasterOutput, render, se3_exp, shape_matrices
from bgs_batch.slam.adam import Adam
from bgs_batch.slam.frames import Level, block_mean, downsample
from bgs_batch.slam.gaussian_map import GaussianMap
from bgs_batch.slam.losses import (
    predictive_variances,
    surprise_scores,
    tracking_loss,
    tracking_weights,
)
from bgs_batch.slam.tracking.pose_jacobian import (
    ALPHA_MIN,
    image_motion_normal_matrix,
    irls_weights,
)
from bgs_batch.slam.tracking.registration import View, register

Variances = tuple[torch.Tensor, torch.Tensor]  # sensor colour [H,W,1], sensor depth [H,W,1]
Images = tuple[torch.Tensor, ...]  # colour, depth, Σ_C, Σ_D of one render
# Gauss-Newton's trust scale: ×2 when a step's decrease exceeds this share of the predicted
# one, ÷2 below the poor share, ÷4 when the loss rose (the usual trust-region thresholds)
TRUST_GROW, TRUST_GOOD, TRUST_POOR = 2.0, 0.75, 0.25
NORMAL_FLOOR = 1e-9  # of the normal matrix's trace: keeps a degenerate system solvable


@dataclass(frozen=True)
class Evaluation:
    """The loss at ``exp(ξ)·w2c`` for ``ξ = twist = 0``, differentiable in `twist` (Gauss-Newton's
    iterate), with the render and Σ_C, Σ_D there."""

    twist: torch.Tensor  # (6,) float64 zeros, requires grad
    loss: torch.Tensor
    out: RasterOutput
    var_c: torch.Tensor
    var_d: torch.Tensor


@dataclass(frozen=True)
class Objective:
    """The tracking loss (Eq. 15-17) of one pyramid level against the fixed map: what both
    optimisers and the warm start's choice evaluate at a pose."""

    gaussians: Gaussians
    shapes: torch.Tensor  # the fixed map's shape matrices (`shape_matrices`)
    level: Level
    variances: Variances  # the frozen network's, at this level
    cfg: Config
    # evaluations handed to `keep`, by pose, until `at` is asked for them
    kept: dict[bytes, Evaluation] = field(default_factory=dict)

    def render(self, w2c: torch.Tensor) -> tuple[RasterOutput, torch.Tensor, torch.Tensor]:
        """The render at `w2c` and its total predictive variances Σ_C, Σ_D (Eq. 10, 11)."""
        u = self.cfg.uncertainty
        out = render(self.gaussians, w2c.float(), self.level.camera, full_grad=u.full_grad,
                     shapes=self.shapes)  # fmt: skip
        return out, *predictive_variances(out, *self.variances, u)

    def evaluate(self, w2c: torch.Tensor
                 ) -> tuple[torch.Tensor, RasterOutput, torch.Tensor, torch.Tensor]:  # fmt: skip
        """The loss at `w2c` (differentiable where `w2c` is) with the render and Σ_C, Σ_D."""
        out, var_c, var_d = self.render(w2c)
        loss = tracking_loss(out.color, out.depth, out.alpha, self.level.rgb, self.level.depth,
                             var_c, var_d, self.cfg.tracking)  # fmt: skip
        return loss, out, var_c, var_d

    def at(self, w2c: torch.Tensor) -> Evaluation:
        """The `Evaluation` at `w2c`: the one kept for this pose (`keep`), else a new render."""
        kept = self.kept.pop(_pose_key(w2c), None)
        if kept is not None:
            return kept
        twist = torch.zeros(6, dtype=torch.float64, requires_grad=True)
        return Evaluation(twist, *self.evaluate(se3_exp(twist) @ w2c))

    def keep(self, w2c: torch.Tensor, evaluation: Evaluation) -> None:
        """Hand `evaluation` to the next `at(w2c)`: the warm start renders the start it
        chooses, and Gauss-Newton's first iteration takes that render instead of another."""
        self.kept[_pose_key(w2c)] = evaluation


def _pose_key(w2c: torch.Tensor) -> bytes:
    return w2c.detach().numpy().tobytes()


@dataclass(frozen=True)
class TrackResult:
    """The tracked pose and what was measured at it."""

    w2c: torch.Tensor  # (4, 4) float64
    loss: float  # at the best pose, finest level
    iterations: int  # over all levels
    score_color: float
    score_depth: float
    doubled: bool  # the initial loss exceeded `init_err_ratio` × the median: twice the budget
    start: dict[str, Any] | None = None  # the warm start's report (`Tracker.warm_start`)


def constant_velocity(c2w_prev: torch.Tensor, c2w_prev2: torch.Tensor | None) -> torch.Tensor:
    """Initial camera-to-world pose: the last relative motion applied once more."""
    if c2w_prev2 is None:
        return c2w_prev.clone()
    return c2w_prev @ torch.linalg.inv(c2w_prev2) @ c2w_prev


class Tracker:
    """Optimises one frame's pose against a Gaussian map."""

    def __init__(self, cfg: Config) -> None:
        self.cfg = cfg
        # best coarsest-level loss of every frame tracked so far (init_err_ratio's median)
        self.coarse_losses: list[float] = []

    def state_dict(self) -> dict[str, list[float]]:
        return {"coarse_losses": list(self.coarse_losses)}

    def load_state_dict(self, state: dict[str, list[float]]) -> None:
        self.coarse_losses = [float(x) for x in state["coarse_losses"]]

    def _doubling_threshold(self) -> float:
        """The initial loss above which a frame's budget doubles (inf: never)."""
        ratio = self.cfg.tracking.init_err_ratio
        if not ratio or not self.coarse_losses:
            return float("inf")
        return ratio * statistics.median(self.coarse_losses)

    def pyramid(self, frame: Level) -> list[tuple[int, Level]]:
        """(factor, level) from the coarsest level to the tracking resolution.

        Factors are relative to the input frame; each is a multiple of the mapping downscale, so
        the sensor variances (evaluated at mapping resolution) block-average onto every level.
        """
        t, m = self.cfg.tracking, self.cfg.mapping.downscale
        if t.downscale % m:
            raise ValueError(f"tracking.downscale ({t.downscale}) must be a multiple of "
                             f"mapping.downscale ({m})")  # fmt: skip
        factors = [t.downscale * 2**k for k in range(t.coarse_levels, -1, -1)]
        return [(f, downsample(frame, f)) for f in factors]

    def iteration_budget(self) -> list[int]:
        """Iterations per pyramid level (coarsest first)."""
        t = self.cfg.tracking
        coarse = round(t.iterations * t.coarse_fraction) if t.coarse_levels else 0
        per_coarse = [coarse // t.coarse_levels] * t.coarse_levels if t.coarse_levels else []
        return per_coarse + [t.iterations - sum(per_coarse)]

    def track(
        self,
        gmap: GaussianMap,
        frame: Level,
        sensor_color: torch.Tensor,
        sensor_depth: torch.Tensor,
        w2c_init: torch.Tensor,
    ) -> TrackResult:
        """Track `frame` (input resolution) from `w2c_init`.

        `sensor_color`, `sensor_depth` are the frozen network's variances at mapping resolution.
        """
        gaussians = gmap.gaussians()
        for p in gmap.params.values():
            p.requires_grad_(False)
        shapes = shape_matrices(gaussians.log_scales, gaussians.quats)  # the map stays fixed
        try:
            w2c, loss, iterations = w2c_init.to(torch.float64), float("inf"), 0
            t, sensor = self.cfg.tracking, (sensor_color, sensor_depth)
            schedule = list(zip(self.pyramid(frame), self.iteration_budget(), strict=True))
            start = None
            # the tracking resolution's objective, which keeps the warm start's renders
            finest = schedule[-1][0]
            final_objective = self._objective(gaussians, shapes, finest, sensor)
            if t.warm_start:
                w2c, start = self.warm_start(gaussians, shapes, frame, w2c, final_objective)
            pivot = self.pivot(frame)
            threshold, doubled = self._doubling_threshold(), False
            if start is not None and start["trusted"] and t.warm_iterations:
                # the registration agreed with constant velocity within bounds, so whichever
                # start the loss chose is close: refine at tracking resolution only
                schedule = [(schedule[-1][0], t.warm_iterations)]
            for depth, (scaled, budget) in enumerate(schedule):
                level = scaled[1]
                objective = (final_objective if scaled is finest
                             else self._objective(gaussians, shapes, scaled, sensor))  # fmt: skip
                lr_scale = t.level_lr_factor**depth
                # the coarsest level tests its initial loss; finer levels inherit the doubling
                double_above = threshold if depth == 0 else math.inf
                if t.optimizer == "gauss_newton" and start is not None and start["trusted"]:
                    w2c, loss, used, best, hard = self._gauss_newton(
                        objective, w2c, budget * (1 + doubled), double_above)  # fmt: skip
                else:
                    w2c, loss, used, best, hard = self._optimise(
                        objective, w2c, pivot, budget * (1 + doubled), lr_scale,
                        double_above)  # fmt: skip
                doubled = doubled or hard
                if depth == 0 and self.cfg.tracking.init_err_ratio and math.isfinite(loss):
                    self.coarse_losses.append(loss)
                iterations += used
            if best is None:  # no finite loss at this level (or no iterations): render the pose
                with torch.no_grad():
                    out, var_c, var_d = objective.render(w2c)
                best = (out.color, out.depth, var_c, var_d)
            color, depth_image, var_c, var_d = best  # the finest level's render at its best pose
            scores = surprise_scores(color, depth_image, level.rgb, level.depth, var_c, var_d)
        finally:
            for p in gmap.params.values():
                p.requires_grad_(True)
        return TrackResult(w2c, loss, iterations, *scores, doubled, start)

    def warm_start(self, gaussians: Gaussians, shapes: torch.Tensor, frame: Level,
                   w2c: torch.Tensor, objective: Objective | None = None
                   ) -> tuple[torch.Tensor, dict[str, Any]]:  # fmt: skip
        """The registered start near `w2c` (constant velocity) and a report of it: which start
        was used, the registration's fitness and RMS, and how far it moved the pose.

        A registration is trusted when it found enough of the map and moved the pose within
        bounds; given the tracking level's `objective`, a trusted start must also lower the
        paper's loss below the constant-velocity pose's (one render each), since a sparse map
        can offer the registration a wrong basin that the loss sees through."""
        r = self.cfg.registration
        coarse = downsample(frame, self.cfg.tracking.downscale * r.downscale)
        with torch.no_grad():
            out = render(gaussians, w2c.float(), coarse.camera, shapes=shapes)
        alpha = out.alpha.to(torch.float64)
        covered = alpha >= r.min_alpha
        depth = torch.where(covered, out.depth / alpha.clamp_min(r.min_alpha), 0.0)
        color = out.color / alpha.clamp_min(r.min_alpha)
        target = View.of(color, depth, coarse.camera)
        result = register(View.of(coarse.rgb, coarse.depth, coarse.camera), target, r)
        moved_m = float(result.transform[:3, 3].norm())
        cos = (torch.trace(result.transform[:3, :3]) - 1) / 2
        moved_deg = math.degrees(math.acos(float(cos.clamp(-1.0, 1.0))))
        trusted = (result.fitness >= r.min_fitness and moved_m <= r.max_shift
                   and moved_deg <= r.max_turn_deg)  # fmt: skip
        # x_target = T x_source and x_target = w2c x_world: the source's w2c is T⁻¹ w2c
        registered = torch.linalg.inv(result.transform) @ w2c
        report = {"start": "registration" if trusted else "constant_velocity",
                  "fitness": result.fitness, "rmse": result.rmse,
                  "iterations": result.iterations, "moved_m": moved_m,
                  "moved_deg": moved_deg, "trusted": trusted}  # fmt: skip
        use = trusted
        if trusted and objective is not None:
            evaluations = [objective.at(pose) for pose in (w2c, registered)]
            losses = [float(e.loss.detach()) for e in evaluations]
            report["loss_ratio"] = losses[1] / losses[0] if losses[0] > 0 else 1.0
            use = losses[1] < losses[0]
            objective.keep(registered if use else w2c, evaluations[1 if use else 0])
            report["start"] = "registration" if use else "constant_velocity"
        return (registered if use else w2c), report

    def pivot(self, frame: Level) -> torch.Tensor:
        """The (4, 4) shift P of ``w2c = P exp(ξ) P⁻¹ w2c₀``: to the point on the optical axis
        at ``pivot_depth_ratio`` × the median valid measured depth of `frame` (the identity
        for ratio 0: rotations about the camera centre)."""
        pivot = torch.eye(4, dtype=torch.float64)
        ratio = self.cfg.tracking.pivot_depth_ratio
        if ratio:  # the median only when it is used: this runs on every frame
            valid = frame.depth[frame.depth > 0]
            if valid.numel():
                pivot[2, 3] = ratio * float(valid.median())
        return pivot

    def _objective(self, gaussians: Gaussians, shapes: torch.Tensor, scaled: tuple[int, Level],
                   sensor: Variances) -> Objective:  # fmt: skip
        """The loss of the pyramid level `scaled` (factor, level), with the `sensor` variances
        (at mapping resolution) block-averaged onto it."""
        factor, level = scaled
        return Objective(gaussians, shapes, level, self._sensor_at(*sensor, factor), self.cfg)

    def _sensor_at(self, color: torch.Tensor, depth: torch.Tensor, factor: int) -> Variances:
        rel = factor // self.cfg.mapping.downscale
        return block_mean(color, rel).detach(), block_mean(depth, rel).detach()

    def _optimise(
        self,
        objective: Objective,
        w2c_start: torch.Tensor,
        pivot: torch.Tensor,
        budget: int,
        lr_scale: float = 1.0,
        double_above: float = float("inf"),
    ) -> tuple[torch.Tensor, float, int, Images | None, bool]:
        """Adam on ξ of ``w2c = pivot · exp(ξ) · pivot⁻¹ · w2c_start`` on one pyramid level's
        `objective` (rates × `lr_scale`); returns the lowest-loss pose, its loss, the
        iterations used, the render there (colour, depth, Σ_C, Σ_D; None when no iteration
        gave a finite loss), which the surprise scores reuse, and whether the budget was
        doubled because the initial loss exceeded `double_above`."""
        t = self.cfg.tracking
        rho = torch.zeros(3, dtype=torch.float64, requires_grad=True)
        phi = torch.zeros(3, dtype=torch.float64, requires_grad=True)
        optimizer = Adam(
            [{"params": [rho], "lr": t.trans_lr * lr_scale},
             {"params": [phi], "lr": t.rot_lr * lr_scale}], amsgrad=True
        )  # fmt: skip
        best_w2c, best, stale, used, doubled = w2c_start, float("inf"), 0, 0, False
        best_images: Images | None = None
        start = torch.linalg.inv(pivot) @ w2c_start
        while used < budget:
            used += 1
            w2c = pivot @ se3_exp(torch.cat([rho, phi])) @ start
            loss, out, var_c, var_d = objective.evaluate(w2c)
            value = float(loss.detach())
            if used == 1 and value > double_above:
                budget, doubled = 2 * budget, True
            if value < best:
                stale = 0 if best - value > t.early_stop_rel * abs(value) else stale + 1
                best, best_w2c = value, w2c.detach()
                best_images = tuple(x.detach() for x in (out.color, out.depth, var_c, var_d))
            else:
                stale += 1
            if t.early_stop_patience and stale >= t.early_stop_patience:
                break
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        return best_w2c, best, used, best_images, doubled

    def _gauss_newton(
        self,
        objective: Objective,
        w2c_start: torch.Tensor,
        budget: int,
        double_above: float = float("inf"),
    ) -> tuple[torch.Tensor, float, int, Images | None, bool]:
        """Gauss-Newton on the left twist from `w2c_start` on one pyramid level's `objective`, with
        `_optimise`'s returns. Each iteration renders once. A pose with a lower loss is kept and
        gives the next step: the renderer's exact gradient against the image-motion normal
        matrix (`pose_jacobian`) divided by a trust scale, which doubles when the loss fell as
        the model predicted and halves when it fell much less; a pose with a higher loss is
        dropped and the step from the best pose retried at a quarter of the scale. Stops once a
        step is shorter than ``tracking.gn_converged`` or the model predicts it lowers the loss
        by less than ``tracking.early_stop_rel`` of it (Adam's test of a stale iteration)."""
        t = self.cfg.tracking
        best_w2c, best, used, doubled = w2c_start, float("inf"), 0, False
        best_images: Images | None = None
        w2c, scale, predicted = w2c_start, 1.0, 0.0
        gradient = normal = None
        while used < budget:
            used += 1
            evaluation = objective.at(w2c)
            loss, out, var_c, var_d = (evaluation.loss, evaluation.out, evaluation.var_c,
                                       evaluation.var_d)  # fmt: skip
            value = float(loss.detach())
            if used == 1 and value > double_above:
                budget, doubled = 2 * budget, True
            if value < best:
                if predicted > 0:  # how well the model predicted the decrease
                    ratio = (best - value) / predicted
                    if ratio > TRUST_GOOD:
                        scale *= TRUST_GROW
                    elif ratio < TRUST_POOR:
                        scale /= TRUST_GROW
                loss.backward()
                gradient = evaluation.twist.grad
                normal = self._normal_matrix(out, objective.level, var_c, var_d)
                best, best_w2c = value, w2c
                best_images = tuple(x.detach() for x in (out.color, out.depth, var_c, var_d))
            else:
                scale /= TRUST_GROW**2
            if gradient is None or not float(torch.trace(normal)) > 0:
                break  # no finite loss yet, or nothing in view to move
            model = normal / scale
            model = model + NORMAL_FLOOR * torch.trace(model) * torch.eye(6, dtype=torch.float64)
            step = -torch.linalg.solve(model, gradient)
            predicted = -float(gradient @ step + 0.5 * step @ model @ step)
            if float(step.norm()) < t.gn_converged or predicted < t.early_stop_rel * best:
                break
            w2c = se3_exp(step) @ best_w2c
        return best_w2c, best, used, best_images, doubled

    def _normal_matrix(self, out: RasterOutput, level: Level, var_c: torch.Tensor,
                       var_d: torch.Tensor) -> torch.Tensor:  # fmt: skip
        """The reweighted least-squares normal matrix (6, 6) of `tracking_loss` at a render."""
        w_color, w_depth = tracking_weights(self.cfg.tracking)
        alpha = out.alpha.detach().to(torch.float64)
        mask = ((level.depth > 0) & (alpha >= ALPHA_MIN)) * alpha**3  # pixels with a surface
        irls_color = irls_weights(out.color - level.rgb, w_color * mask / var_c.sqrt())
        irls_depth = irls_weights(out.depth - level.depth, w_depth * mask / var_d.sqrt())
        return image_motion_normal_matrix(out, level.camera, irls_color, irls_depth)
