"""Our PLY read by a real downstream tool: PlayCanvas's `splat-transform` (SuperSplat's converter).

The npm package is installed once into ``.venv/.cache/splat-transform`` (or a temporary folder
when there is no venv) with ``npm install --prefix``; the tests skip with the reason when npm is
missing or the install fails (no registry). PLY → CSV must give back every property exactly, and
PLY → SPZ (Niantic's compressed format) → CSV the same Gaussians within SPZ's quantisation.
"""

import csv
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest

from outputs.ply import PROPERTIES, SH_C0, Splats, write_ply

PACKAGE = "@playcanvas/splat-transform@2.7.1"
INSTALL_TIMEOUT_S = 600
RUN_TIMEOUT_S = 120
VENV = Path(__file__).resolve().parents[2] / ".venv"
# SPZ v4 quantisation: positions 12 fractional bits, colour and alpha 8 bits
SPZ_POSITION_TOL_M = 2.0**-12
SPZ_UNIT_TOL = 1.5 / 255
SPZ_LOG_SCALE_TOL = 1 / 16 + 1e-6  # log scales are stored with 4 fractional bits


@pytest.fixture(scope="module")
def splat_transform() -> Path:
    npm = shutil.which("npm")
    if npm is None:
        pytest.skip("npm is not installed (needed for @playcanvas/splat-transform)")
    root = VENV / ".cache" / "splat-transform" if VENV.is_dir() else \
        Path(tempfile.gettempdir()) / "bgs-splat-transform"  # fmt: skip
    cli = root / "node_modules" / ".bin" / "splat-transform"
    if not cli.exists():
        root.mkdir(parents=True, exist_ok=True)
        try:
            done = subprocess.run(
                [npm, "install", "--prefix", str(root), "--no-audit", "--no-fund", PACKAGE],
                capture_output=True, text=True, timeout=INSTALL_TIMEOUT_S,
                env={**os.environ, "npm_config_update_notifier": "false"},
            )  # fmt: skip
        except subprocess.TimeoutExpired:
            pytest.skip(f"npm install {PACKAGE} timed out")
        if done.returncode != 0 or not cli.exists():
            pytest.skip(f"npm install {PACKAGE} failed: {done.stderr.strip()[-300:]}")
    return cli


def convert(cli: Path, source: Path, target: Path) -> None:
    done = subprocess.run([str(cli), "-q", "-w", str(source), str(target)], capture_output=True,
                          text=True, timeout=RUN_TIMEOUT_S)  # fmt: skip
    assert done.returncode == 0, done.stderr + done.stdout


def read_csv(path: Path) -> dict[str, np.ndarray]:
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    values = np.array(rows[1:], dtype=np.float64)
    return {name: values[:, i] for i, name in enumerate(rows[0])}


def splats(n: int = 200, seed: int = 0) -> Splats:
    rng = np.random.default_rng(seed)
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    quats *= np.sign(quats[:, :1])  # w ≥ 0: SPZ stores the hemisphere with w ≥ 0
    return Splats(
        means=rng.uniform(-2, 2, (n, 3)).astype(np.float32),
        log_scales=rng.uniform(-5, -1, (n, 3)).astype(np.float32),
        quats=quats.astype(np.float32),
        opacity_logits=rng.uniform(-3, 3, n).astype(np.float32),
        colors=rng.uniform(0.05, 0.95, (n, 3)).astype(np.float32),
        uncertainty=rng.uniform(1e-4, 1e-2, n).astype(np.float32),
    )


def test_ply_converts_to_csv_with_every_property(splat_transform, tmp_path):
    ours = splats()
    write_ply(tmp_path / "map.ply", ours)
    convert(splat_transform, tmp_path / "map.ply", tmp_path / "map.csv")
    table = read_csv(tmp_path / "map.csv")
    assert list(table) == list(PROPERTIES)  # the uncertainty column survives too
    expected = {
        "x": ours.means[:, 0], "y": ours.means[:, 1], "z": ours.means[:, 2],
        "f_dc_0": (ours.colors[:, 0] - 0.5) / SH_C0, "opacity": ours.opacity_logits,
        "scale_2": ours.log_scales[:, 2], "rot_0": ours.quats[:, 0], "rot_3": ours.quats[:, 3],
        "uncertainty": ours.uncertainty,
    }  # fmt: skip
    for name, values in expected.items():
        np.testing.assert_array_equal(table[name], values.astype(np.float32), err_msg=name)


def test_ply_survives_a_round_trip_through_spz(splat_transform, tmp_path):
    ours = splats(seed=1)
    write_ply(tmp_path / "map.ply", ours)
    convert(splat_transform, tmp_path / "map.ply", tmp_path / "map.spz")
    convert(splat_transform, tmp_path / "map.spz", tmp_path / "back.csv")
    table = read_csv(tmp_path / "back.csv")
    assert len(table["x"]) == len(ours)
    means = np.stack([table[k] for k in "xyz"], 1)
    np.testing.assert_allclose(means, ours.means, atol=SPZ_POSITION_TOL_M)
    colours = np.stack([table[f"f_dc_{c}"] for c in range(3)], 1) * SH_C0 + 0.5
    np.testing.assert_allclose(colours, ours.colors, atol=SPZ_UNIT_TOL)
    alpha = 1 / (1 + np.exp(-table["opacity"]))
    np.testing.assert_allclose(alpha, 1 / (1 + np.exp(-ours.opacity_logits)), atol=SPZ_UNIT_TOL)
    scales = np.stack([table[f"scale_{c}"] for c in range(3)], 1)
    np.testing.assert_allclose(scales, ours.log_scales, atol=SPZ_LOG_SCALE_TOL)
    quats = np.stack([table[f"rot_{c}"] for c in range(4)], 1)
    agree = np.abs(np.sum(quats / np.linalg.norm(quats, axis=1, keepdims=True) * ours.quats, 1))
    assert agree.min() > 0.99  # same rotation (sign-free), within 10-bit quantisation
