"""The in-house Adam must match ``torch.optim.Adam`` bit for bit and checkpoint like it."""

from __future__ import annotations

import io
from collections.abc import Callable

import numpy as np
import pytest
import torch

from bgs_batch.config import MappingConfig
from bgs_batch.slam.adam import Adam
from bgs_batch.slam.gaussian_map import ADAM_EPS, PARAMS, GaussianMap

STEPS = 7
SHAPES = ((5, 3), (4,), ())
LRS = (1e-2, 3e-3, 0.5)
STEPS_PER_SEED = 1000


def make_params(dtype: torch.dtype) -> list[torch.Tensor]:
    gen = torch.Generator().manual_seed(0)
    return [torch.randn(s, generator=gen, dtype=dtype).requires_grad_(True) for s in SHAPES]


def groups(params: list[torch.Tensor]) -> list[dict]:
    return [{"params": [p], "lr": lr, "name": f"g{i}"}
            for i, (p, lr) in enumerate(zip(params, LRS, strict=True))]  # fmt: skip


def run(opt: object, params: list[torch.Tensor], steps: int, seed: int, first: int = 0) -> None:
    """Steps `first`..`first + steps - 1` on a loss whose gradients vary in sign and magnitude
    (every third step one parameter has none); step k's gradients depend on (seed, k) only."""
    for k in range(first, first + steps):
        gen = torch.Generator().manual_seed(seed * STEPS_PER_SEED + k)
        opt.zero_grad(set_to_none=True)
        used = params if k % 3 else params[:-1]
        weights = [torch.randn(p.shape, generator=gen, dtype=p.dtype) * 10.0 ** (k % 4 - 2)
                   for p in used]  # fmt: skip
        loss = sum(
            (p * w).sum() + (p**2 * w.abs()).sum() for p, w in zip(used, weights, strict=True)
        )
        loss.backward()
        opt.step()


def assert_bitwise(a: list[torch.Tensor], b: list[torch.Tensor]) -> None:
    for x, y in zip(a, b, strict=True):
        assert torch.equal(x, y), (x - y).abs().max()


OPTIONS = [
    pytest.param(dtype, kwargs, id=f"{str(dtype)[6:]}-{'-'.join(map(str, kwargs.values()))}")
    for dtype in (torch.float32, torch.float64)
    for kwargs in (
        {"amsgrad": False},
        {"amsgrad": True},
        {"amsgrad": True, "eps": 1e-15, "betas": (0.8, 0.99)},
    )
]


@pytest.mark.parametrize(("dtype", "kwargs"), OPTIONS)
def test_matches_torch_adam_bitwise(dtype: torch.dtype, kwargs: dict) -> None:
    ours, theirs = make_params(dtype), make_params(dtype)
    run(Adam(groups(ours), **kwargs), ours, STEPS, seed=1)
    run(torch.optim.Adam(groups(theirs), **kwargs), theirs, STEPS, seed=1)
    assert_bitwise(ours, theirs)


@pytest.mark.parametrize("amsgrad", [False, True])
def test_plain_parameter_list_and_default_lr(amsgrad: bool) -> None:
    ours, theirs = make_params(torch.float32), make_params(torch.float32)
    run(Adam(ours, amsgrad=amsgrad), ours, STEPS, seed=2)
    run(torch.optim.Adam(theirs, amsgrad=amsgrad), theirs, STEPS, seed=2)
    assert_bitwise(ours, theirs)


def roundtrip(state: dict) -> dict:
    """Through torch.save and the safe loader, as a checkpoint goes."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    buffer.seek(0)
    return torch.load(buffer, weights_only=True)


@pytest.mark.parametrize("source", [Adam, torch.optim.Adam], ids=["ours", "torch"])
@pytest.mark.parametrize("amsgrad", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_state_dict_resume_is_bitwise(source: Callable, amsgrad: bool, dtype: torch.dtype) -> None:
    """Stop after some steps, reload the state (ours, or one torch.optim.Adam wrote) into a
    fresh optimiser, continue: equal to the uninterrupted run."""
    straight = make_params(dtype)
    run(Adam(groups(straight), amsgrad=amsgrad), straight, 2 * STEPS, seed=3)

    first = make_params(dtype)
    opt = source(groups(first), amsgrad=amsgrad)
    run(opt, first, STEPS, seed=3)
    state = roundtrip(opt.state_dict())
    resumed = [p.detach().clone().requires_grad_(True) for p in first]
    fresh = Adam([{"params": [p], "name": "?"} for p in resumed], lr=1.0, amsgrad=amsgrad)
    fresh.load_state_dict(state)
    assert [g["lr"] for g in fresh.param_groups] == list(LRS)  # settings come from the state
    run(fresh, resumed, STEPS, seed=3, first=STEPS)
    assert_bitwise(resumed, straight)


def test_state_dict_layout_is_torchs() -> None:
    params = make_params(torch.float32)
    ours = Adam(groups(params), amsgrad=True)
    run(ours, params, 2, seed=4)
    ref = make_params(torch.float32)
    theirs = torch.optim.Adam(groups(ref), amsgrad=True)
    run(theirs, ref, 2, seed=4)
    a, b = ours.state_dict(), theirs.state_dict()
    assert a["state"].keys() == b["state"].keys()
    for i in a["state"]:
        assert a["state"][i].keys() == b["state"][i].keys()
        for key, value in a["state"][i].items():
            assert torch.equal(value, b["state"][i][key])
            assert value.dtype == b["state"][i][key].dtype
    assert [g["params"] for g in a["param_groups"]] == [g["params"] for g in b["param_groups"]]


def test_state_dict_is_a_copy() -> None:
    params = make_params(torch.float32)
    opt = Adam(params)
    run(opt, params, 2, seed=5)
    saved = opt.state_dict()
    before = saved["state"][0]["exp_avg"].clone()
    run(opt, params, 2, seed=6)
    assert torch.equal(saved["state"][0]["exp_avg"], before)


def test_rejects_bad_settings_and_layouts() -> None:
    params = make_params(torch.float32)
    with pytest.raises(ValueError):
        Adam(params, lr=-1.0)
    with pytest.raises(ValueError):
        Adam(params, betas=(1.0, 0.999))
    with pytest.raises(ValueError):
        Adam([])
    with pytest.raises(ValueError):
        Adam(params[:1]).load_state_dict(Adam(params).state_dict())


def test_pruning_edits_the_moments_as_with_torch() -> None:
    """`GaussianMap.keep` drops pruned Gaussians' moments from the optimiser's state; steps
    after it match torch.optim.Adam's."""
    rng = np.random.default_rng(0)
    means, colors = rng.normal(size=(9, 3)), rng.uniform(size=(9, 3))
    weights = {n: torch.from_numpy(rng.normal(size=(9, *GaussianMap().params[n].shape[1:])))
               for n in PARAMS}  # fmt: skip
    mask = torch.from_numpy(rng.uniform(size=9) > 0.4)
    results = []
    for torch_adam in (False, True):
        gmap = GaussianMap()
        gmap.add(means, colors, 0.5, -7.0)
        opt = gmap.optimizer(MappingConfig())
        if torch_adam:
            opt = torch.optim.Adam([{"params": g["params"], "lr": g["lr"], "name": g["name"]}
                                    for g in opt.param_groups], eps=ADAM_EPS)  # fmt: skip
        for k in range(4):
            if k == 2:
                gmap.keep(mask, opt)
            opt.zero_grad(set_to_none=True)
            live = mask if k >= 2 else torch.ones(9, dtype=torch.bool)
            sum((p * weights[n][live].float()).sum() for n, p in gmap.params.items()).backward()
            opt.step()
        results.append([gmap.params[n].detach() for n in PARAMS])
    assert_bitwise(*results)
