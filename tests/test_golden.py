"""Golden outputs: short deterministic runs must reproduce `tests/golden/*.json` exactly.

Each case runs `bgs run` (with its default export) on a fixed input and condenses the results:
the trajectory file (text, compared line by line), every keyframe decision with both surprise
scores, the metrics of `metrics.json`, and summary statistics (count, mean, std, quantiles) of
the merged PLY's properties and of each uncertainty image dataset.

Comparison is exact: runs are deterministic, so bitwise equality is the normal case. The one
real platform difference is the CPU: numba compiles for the host CPU, and a different
instruction set changes the order of vectorised sums, which a SLAM run then amplifies. Goldens
are therefore kept per CPU (`tests/golden/<case>.<cpu>.json`); on a CPU without its own the test
skips, saying so.

Record or regenerate this CPU's, only with a reason in the commit message:  make goldens
A golden may hold only some parts (the comparison is per part present): the Zen 4 ones keep the
trajectory and the keyframe decisions, the parts the end-of-run uncertainty refinement left
unchanged, until they are recorded again on such a machine.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import h5py
import llvmlite.binding as llvm
import numpy as np
import pytest
from click.testing import CliRunner
from conftest import TUM_EXCERPT

from bgs_batch.cli import main
from converters.pipeline import write_store
from converters.synthetic import SynthConfig, synthesize
from converters.tum import TumOptions, plan_tum
from outputs.ply import read_ply

GOLDEN_DIR = Path(__file__).parent / "golden"
UPDATE_ENV = "BGS_UPDATE_GOLDENS"
QUANTILES = (0.05, 0.25, 0.5, 0.75, 0.95)
FAST = ["tracking.iterations=20", "mapping.iterations=10", "mapping.new_submap_iterations=15"]
"""The cpu preset with fewer iterations: the goldens guard numbers, not accuracy."""
METRICS = {
    "ate_rmse_cm": ("ate", "rigid", "rmse_cm"),
    "ate_rmse_with_scale_cm": ("ate", "with_scale", "rmse_cm"),
    "psnr_db": ("rendering", "psnr_db"),
    "ssim": ("rendering", "ssim"),
    "depth_l1_cm": ("rendering", "depth_l1_cm"),
    "ause_color": ("uncertainty", "ause_mae_color", "ause_raw"),
    "ause_depth": ("uncertainty", "ause_mae_depth", "ause_raw"),
}


def host_cpu() -> str:
    """The CPU numba compiles for (e.g. ``znver4``)."""
    return llvm.get_host_cpu_name()


def statistics(values: np.ndarray) -> dict[str, Any]:
    """Count, mean, std and quantiles of the finite values (float64 sums, fixed order)."""
    flat = np.asarray(values, np.float64).reshape(-1)
    flat = flat[np.isfinite(flat)]
    if flat.size == 0:
        return {"count": 0}
    return {
        "count": int(flat.size),
        "mean": float(flat.mean()),
        "std": float(flat.std()),
        "quantiles": [float(q) for q in np.quantile(flat, QUANTILES)],
    }


def _lookup(data: dict, path: tuple[str, ...]) -> Any:
    for key in path:
        data = data[key]
    return data


def condense(job: Path) -> dict[str, Any]:
    """The golden record of a finished, exported job."""
    events = [json.loads(line) for line in (job / "log.jsonl").read_text().splitlines()]
    metrics = json.loads((job / "outputs" / "metrics.json").read_text())
    splats = read_ply(job / "outputs" / "ply" / "global.ply")
    images = {}
    with h5py.File(job / "outputs" / "uncertainty.h5", "r") as h5:
        h5.visititems(lambda name, d: images.update({name: statistics(d[()])})
                      if isinstance(d, h5py.Dataset) and d.dtype.kind == "f" else None)  # fmt: skip
    return {
        "cpu": host_cpu(),
        "trajectory": (job / "trajectory.txt").read_text().splitlines(),
        "keyframes": [[e["frame"], e["keyframe"], e["reason"], e["score_color"], e["score_depth"]]
                      for e in events],  # fmt: skip
        "metrics": {name: _lookup(metrics, path) for name, path in METRICS.items()},
        "ply": {name: statistics(value) for name, value in vars(splats).items()},
        "uncertainty_images": images,
    }


def run_case(store: Path, job: Path) -> dict[str, Any]:
    args = ["-q", "run", str(store), "--job-dir", str(job), *sum((["--set", s] for s in FAST), [])]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    return condense(job)


def check_golden(name: str, record: dict[str, Any]) -> None:
    """Compare with (or, with BGS_UPDATE_GOLDENS=1, write) this CPU's golden of case `name`."""
    path = GOLDEN_DIR / f"{name}.{record['cpu']}.json"
    if os.environ.get(UPDATE_ENV) == "1":
        path.parent.mkdir(exist_ok=True)
        path.write_text(json.dumps(record, indent=1) + "\n")
        return
    if not path.is_file():
        recorded = sorted(p.name for p in GOLDEN_DIR.glob(f"{name}.*.json")) or ["none"]
        pytest.skip(f"no golden for this {record['cpu']} CPU (recorded: {', '.join(recorded)}): "
                    f"vectorised sums differ by CPU; record one with `make goldens` here")
    golden = json.loads(path.read_text())
    for key in golden:  # one assertion per part, so a failure says what moved
        assert record[key] == golden[key], f"{name}: {key} moved from {path}"


@pytest.mark.slow
def test_golden_synthetic(tmp_path):
    folder = synthesize(tmp_path / "seq", SynthConfig(frames=16, width=160, height=120, seed=3))
    plan = plan_tum(folder, TumOptions())
    store = write_store(plan.frames, tmp_path / "seq.h5", plan.meta).path
    check_golden("synthetic", run_case(store, tmp_path / "job"))


@pytest.mark.slow
@pytest.mark.skipif(not TUM_EXCERPT.is_dir(), reason=f"real TUM excerpt not at {TUM_EXCERPT}")
def test_golden_real_tum_first_30_frames(tmp_path):
    plan = plan_tum(TUM_EXCERPT, TumOptions(max_frames=30))
    store = write_store(plan.frames, tmp_path / "fr1.h5", plan.meta).path
    check_golden("tum_fr1_rpy_30", run_case(store, tmp_path / "job"))


def test_a_cpu_without_goldens_skips_and_names_the_recorded_ones(monkeypatch):
    monkeypatch.delenv(UPDATE_ENV, raising=False)  # `make goldens` must not record "made-up"
    with pytest.raises(pytest.skip.Exception, match=r"made-up CPU \(recorded: synthetic\.\w+"):
        check_golden("synthetic", {"cpu": "made-up"})
