"""Adam (Kingma & Ba 2015) with optional AMSGrad, for the tracker, the mapper and the sensor net.

Why not ``torch.optim.Adam``: constructing the first one imports ``torch._dynamo`` (1.5-2.6 s
on the 2-core machine), which lands on every resumed job's latency. This class does
the same arithmetic as torch's single-tensor CPU Adam (no weight decay, not maximising), op for
op, so runs are bitwise identical to the ones made with it (tests/slam/test_adam.py checks this).

Interface as far as the package uses it: ``param_groups`` (dicts with ``params`` and per-group
``lr``, ``betas``, ``eps``, ``amsgrad``, plus any extra keys such as a name), ``state`` (keyed
by parameter tensor), ``zero_grad``, ``step``, and ``state_dict``/``load_state_dict`` in
torch's layout (tensors and plain values only, so ``torch.load(weights_only=True)`` reads it;
checkpoints written with ``torch.optim.Adam`` load too).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import torch

DEFAULT_LR = 1e-3
DEFAULT_BETAS = (0.9, 0.999)
DEFAULT_EPS = 1e-8
HYPERPARAMETERS = ("lr", "betas", "eps", "amsgrad")
"""The per-group settings a state dict carries over (torch's other ones are ignored on load)."""
STEP_DTYPE = torch.float32  # torch keeps the step count as a float32 scalar tensor

ParamGroup = dict[str, Any]


class Adam:
    """Adam over parameter groups; each group may set its own ``lr``, ``betas``, ``eps``,
    ``amsgrad``. Parameters without a gradient are skipped by `step`, as in torch."""

    def __init__(
        self,
        params: Iterable[torch.Tensor] | Iterable[ParamGroup],
        lr: float = DEFAULT_LR,
        betas: tuple[float, float] = DEFAULT_BETAS,
        eps: float = DEFAULT_EPS,
        amsgrad: bool = False,
    ) -> None:
        self.defaults: ParamGroup = {"lr": lr, "betas": tuple(betas), "eps": eps,
                                     "amsgrad": amsgrad}  # fmt: skip
        items = list(params)
        if not items:
            raise ValueError("Adam got an empty parameter list")
        groups = items if isinstance(items[0], dict) else [{"params": items}]
        self.param_groups: list[ParamGroup] = [self._group(g) for g in groups]
        self.state: dict[torch.Tensor, dict[str, Any]] = {}

    def _group(self, group: ParamGroup) -> ParamGroup:
        """`group` with the defaults filled in and its settings checked."""
        full = {**self.defaults, **group, "params": list(group["params"])}
        beta1, beta2 = full["betas"]
        if full["lr"] < 0 or full["eps"] < 0 or not (0 <= beta1 < 1 and 0 <= beta2 < 1):
            raise ValueError(f"invalid Adam settings lr={full['lr']}, betas={full['betas']}, "
                             f"eps={full['eps']}")  # fmt: skip
        full["betas"] = (float(beta1), float(beta2))
        return full

    def zero_grad(self, set_to_none: bool = True) -> None:
        """Clear every parameter's gradient (drop it, or zero it in place)."""
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                if set_to_none:
                    p.grad = None
                else:
                    p.grad.detach_().zero_()

    @torch.no_grad()
    def step(self) -> None:
        """One Adam step for every parameter that has a gradient."""
        for group in self.param_groups:
            lr, (beta1, beta2), eps, amsgrad = (group[k] for k in HYPERPARAMETERS)
            for param in group["params"]:
                if param.grad is not None:
                    self._update(param, param.grad, lr, beta1, beta2, eps, amsgrad)

    def _update(self, param: torch.Tensor, grad: torch.Tensor, lr: float, beta1: float,
                beta2: float, eps: float, amsgrad: bool) -> None:  # fmt: skip
        """torch's ``_single_tensor_adam`` for one tensor, in its order of operations."""
        state = self.state.get(param)
        if not state:
            state = self.state[param] = {"step": 0, "exp_avg": torch.zeros_like(param),
                                         "exp_avg_sq": torch.zeros_like(param)}  # fmt: skip
            if amsgrad:
                state["max_exp_avg_sq"] = torch.zeros_like(param)
        state["step"] += 1
        exp_avg, exp_avg_sq = state["exp_avg"], state["exp_avg_sq"]
        exp_avg.lerp_(grad, 1 - beta1)
        exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
        step = float(state["step"])
        bias_correction1 = 1 - beta1**step
        bias_correction2_sqrt = (1 - beta2**step) ** 0.5
        second = exp_avg_sq
        if amsgrad:
            second = state["max_exp_avg_sq"]
            torch.maximum(second, exp_avg_sq, out=second)
        denom = (second.sqrt() / bias_correction2_sqrt).add_(eps)
        param.addcdiv_(exp_avg, denom, value=-(lr / bias_correction1))

    def state_dict(self) -> dict[str, Any]:
        """torch's layout: parameters numbered in group order; copies, not views."""
        index = {id(p): i for i, p in enumerate(self._params())}
        state = {
            index[id(p)]: {k: _saved(v) for k, v in s.items()}
            for p, s in self.state.items()
            if id(p) in index
        }
        groups = [{**{k: v for k, v in g.items() if k != "params"},
                   "params": [index[id(p)] for p in g["params"]]}
                  for g in self.param_groups]  # fmt: skip
        return {"state": state, "param_groups": groups}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Restore `state_dict` (this class's or ``torch.optim.Adam``'s) onto the same
        parameter layout: the groups' settings and every parameter's moments and step."""
        saved_groups = state_dict["param_groups"]
        sizes = [len(g["params"]) for g in self.param_groups]
        saved_sizes = [len(g["params"]) for g in saved_groups]
        if sizes != saved_sizes:
            raise ValueError(f"optimizer state has groups of {saved_sizes} parameters, "
                             f"this optimizer {sizes}")  # fmt: skip
        ids = [i for g in saved_groups for i in g["params"]]
        for group, saved in zip(self.param_groups, saved_groups, strict=True):
            group.update({k: saved[k] for k in HYPERPARAMETERS if k in saved})
            group["betas"] = tuple(group["betas"])
        self.state = {}
        for i, param in zip(ids, self._params(), strict=True):
            if i in state_dict["state"]:
                self.state[param] = {k: _restored(k, v, param)
                                     for k, v in state_dict["state"][i].items()}  # fmt: skip

    def _params(self) -> list[torch.Tensor]:
        return [p for g in self.param_groups for p in g["params"]]


def _saved(value: Any) -> Any:
    """A state entry as torch stores it: the step as a float32 scalar tensor, tensors copied."""
    if isinstance(value, int):
        return torch.tensor(float(value), dtype=STEP_DTYPE)
    return value.detach().clone()


def _restored(key: str, value: Any, param: torch.Tensor) -> Any:
    """A loaded state entry: the step as an int, moments as own copies in `param`'s dtype."""
    if key == "step":
        return int(float(value))
    return value.detach().to(dtype=param.dtype, copy=True)
