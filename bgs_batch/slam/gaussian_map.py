"""The Gaussians of one submap: parameters, growth, pruning, optimiser and (de)serialisation.

Parameters are raw (unactivated) float32 leaf tensors, as `bgs_batch.render.Gaussians` expects:
means, log-scales, w-first quaternions, opacity logits, RGB colours and the opacity-uncertainty
logits r_i (v_i = softplus(r_i); docs/method.md §1).
"""

from __future__ import annotations

import numpy as np
import torch

from bgs_batch.config import MappingConfig
from bgs_batch.geometry import kd_tree
from bgs_batch.render import Gaussians
from bgs_batch.slam.adam import Adam

PARAMS = ("means", "log_scales", "quats", "opacity_logits", "colors", "uncertainty_logits")
UNCERTAINTY_KEY = PARAMS[-1]  # r_i, the only parameter the end-of-run refinement changes
SCALE_NEIGHBOURS = 3  # initial scale: RMS distance to this many nearest Gaussians
ADAM_EPS = 1e-15  # LoopSplat's mapping Adam
MIN_INITIAL_SCALE = 1e-4  # m; guards log(0) for duplicate points


def _logit(p: float) -> float:
    return float(np.log(p / (1 - p)))


class GaussianMap:
    """The Gaussians of one submap, with the optimiser state that goes with them."""

    def __init__(self, params: dict[str, torch.Tensor] | None = None) -> None:
        empty = {"means": (0, 3), "log_scales": (0, 3), "quats": (0, 4), "opacity_logits": (0,),
                 "colors": (0, 3), "uncertainty_logits": (0,)}  # fmt: skip
        params = params or {name: torch.zeros(shape) for name, shape in empty.items()}
        self.params = {n: params[n].detach().clone().float().requires_grad_(True) for n in PARAMS}

    def __len__(self) -> int:
        return int(self.params["means"].shape[0])

    @property
    def means(self) -> torch.Tensor:
        return self.params["means"]

    def gaussians(self) -> Gaussians:
        """The parameters as the renderer takes them (gradients flow to this map)."""
        return Gaussians(**self.params)

    def add(
        self,
        means: np.ndarray,
        colors: np.ndarray,
        opacity: float,
        uncertainty_logit: float,
        normals: np.ndarray | None = None,
        flatness: float = 1.0,
    ) -> int:
        """Append Gaussians at `means` with `colors`; returns how many were added.

        Scale: RMS distance to the 3 nearest Gaussians among old and new (3DGS's distCUDA2);
        where a finite normal is given, the Gaussian is a disc across it (its scale along the
        normal times `flatness`), else isotropic with identity rotation; opacity and
        uncertainty as given (docs/method.md §1, §5).
        """
        if len(means) == 0:
            return 0
        old = self.params["means"].detach().numpy()
        everything = np.concatenate([old, means]).astype(np.float64)
        k = min(SCALE_NEIGHBOURS + 1, len(everything))
        dist, _ = kd_tree(everything).query(means, k=k)
        dist = np.atleast_2d(dist)[:, 1:] if k > 1 else np.full((len(means), 1), 0.01)
        scale = np.sqrt(np.maximum(np.mean(dist**2, axis=1), MIN_INITIAL_SCALE**2))
        n = len(means)
        log_scales = np.repeat(np.log(scale)[:, None], 3, axis=1)
        quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        if normals is not None:
            disc = np.isfinite(normals).all(axis=1)
            nz = np.where(normals[:, 2:] < 0, -normals, normals)[disc]  # a disc has no side
            # the rotation that takes the local z axis to the normal: axis e_z × n, w = 1 + n_z
            q = np.stack([1 + nz[:, 2], -nz[:, 1], nz[:, 0], np.zeros(len(nz))], axis=1)
            quats[disc] = q / np.linalg.norm(q, axis=1, keepdims=True)
            log_scales[disc, 2] += np.log(flatness)
        new = {
            "means": torch.from_numpy(np.asarray(means, np.float32)),
            "log_scales": torch.from_numpy(log_scales.astype(np.float32)),
            "quats": torch.from_numpy(quats.astype(np.float32)),
            "opacity_logits": torch.full((n,), _logit(opacity)),
            "colors": torch.from_numpy(np.asarray(colors, np.float32)),
            "uncertainty_logits": torch.full((n,), float(uncertainty_logit)),
        }
        self.params = {
            name: torch.cat([self.params[name].detach(), new[name]]).requires_grad_(True)
            for name in PARAMS
        }
        return n

    def keep(self, mask: torch.Tensor, optimizer: Adam | None = None) -> int:
        """Keep the Gaussians where `mask` holds (and their Adam moments); return how many went."""
        removed = int((~mask).sum())
        if removed == 0:
            return 0
        old = self.params
        self.params = {n: old[n].detach()[mask].clone().requires_grad_(True) for n in PARAMS}
        if optimizer is not None:
            for group in optimizer.param_groups:
                name = group["name"]
                state = optimizer.state.pop(old[name], None)
                group["params"] = [self.params[name]]
                if state:
                    optimizer.state[self.params[name]] = {
                        k: (v[mask] if torch.is_tensor(v) and v.dim() > 0 else v)
                        for k, v in state.items()
                    }
        return removed

    def optimizer(self, cfg: MappingConfig) -> Adam:
        """A fresh Adam with LoopSplat's per-parameter learning rates (one per mapping call)."""
        lrs = {"means": cfg.lr_means, "log_scales": cfg.lr_scales, "quats": cfg.lr_rotations,
               "opacity_logits": cfg.lr_opacity, "colors": cfg.lr_colors,
               "uncertainty_logits": cfg.lr_uncertainty}  # fmt: skip
        groups = [{"params": [self.params[n]], "lr": lrs[n], "name": n} for n in PARAMS]
        return Adam(groups, eps=ADAM_EPS)

    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.params["opacity_logits"].detach())

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {n: self.params[n].detach().clone() for n in PARAMS}

    @classmethod
    def from_state_dict(cls, state: dict[str, torch.Tensor]) -> GaussianMap:
        return cls(state)
