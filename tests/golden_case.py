"""One golden case, run in a child process whose numerical libraries are pinned to one target.

Usage: python tests/golden_case.py CASE WORKDIR RECORD.json   (tests/test_golden.py runs it)

A case converts a fixed input, runs `bgs run` (with its default export) and condenses the
results: the trajectory file (text, compared line by line), every keyframe decision with both
surprise scores, the metrics of `metrics.json`, and summary statistics (count, mean, std,
quantiles) of the global map PLY's properties and of each uncertainty image dataset.

Runs are deterministic on one machine; across CPUs, every library that picks its kernels by the
CPU it finds would change the order of vectorised sums, which a SLAM run then amplifies. The
child therefore compiles numba for the x86-64-v3 target (AVX2 + FMA, the x86-64 psABI level)
and keeps PyTorch, oneDNN, OpenBLAS, NumPy and OpenCV on their AVX2 kernels and MKL on its
vendor-independent branch (`pinned_environment`), so one record holds on every x86-64 CPU with
AVX2 of the recording's vendor (PyTorch's float32 sqrt and atan still differ between vendors).
"""

from __future__ import annotations

import json
import os
import sys
import traceback
from pathlib import Path
from typing import Any

TARGET = "x86-64-v3"
# LLVM's x86-64-v3 feature set, spelled out for numba (which otherwise takes the host's)
TARGET_FEATURES = (
    "64bit", "avx", "avx2", "bmi", "bmi2", "cmov", "crc32", "cx16", "cx8", "f16c", "fma", "fxsr",
    "lzcnt", "mmx", "movbe", "popcnt", "sahf", "sse", "sse2", "sse3", "sse4.1", "sse4.2",
    "ssse3", "xsave",
)  # fmt: skip
REQUIRED_HOST_FEATURES = ("avx2", "fma", "bmi2", "f16c", "movbe", "lzcnt")
"""What the host must have to run x86-64-v3 code (llvmlite's names)."""
FIXED_ENVIRONMENT = {
    "NUMBA_CPU_NAME": TARGET,
    "NUMBA_CPU_FEATURES": ",".join(f"+{feature}" for feature in TARGET_FEATURES),
    "NUMBA_DISABLE_INTEL_SVML": "1",  # SVML's vector maths differ per ISA
    "ATEN_CPU_CAPABILITY": "avx2",  # PyTorch's CPU kernels
    "ONEDNN_MAX_CPU_ISA": "AVX2",  # the sensor network's convolutions
    # MKL (PyTorch's BLAS and LAPACK; Open3D's): its one code path that is the same on Intel
    # and AMD CPUs (SSE2 without approximate reciprocals). An AMD CPU ignores every other
    # branch (MKL_VERBOSE reports CNR:AUTO there) and runs its own kernels.
    "MKL_CBWR": "COMPATIBLE",
    "OPENBLAS_CORETYPE": "Haswell",  # NumPy's BLAS: its AVX2 kernels
    "OMP_NUM_THREADS": "2",
}
# the dispatch targets of NumPy and OpenCV that the target includes; higher ones are disabled
NUMPY_TARGET_LEVELS = ("X86_V2", "X86_V3", "SSE", "SSE2", "SSE3", "SSSE3", "SSE41", "SSE42",
                       "POPCNT", "AVX", "F16C", "FMA3", "AVX2")  # fmt: skip
OPENCV_TARGET_LEVELS = ("SSE", "SSE2", "SSE3", "SSE4.1", "SSE4.2", "AVX", "FP16", "AVX2")

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
    "global_held_out_psnr_db": ("global_map", "held_out", "rendering", "psnr_db"),
    "global_keyframes_psnr_db": ("global_map", "keyframes", "rendering", "psnr_db"),
}


def cpu_vendor() -> str:
    """The CPU's vendor string (``GenuineIntel``, ``AuthenticAMD``, ...; "unknown" without
    /proc/cpuinfo): some libraries' results still differ between vendors (docs/goldens.md)."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return "unknown"
    return next((line.split(":", 1)[1].strip() for line in lines
                 if line.startswith("vendor_id")), "unknown")  # fmt: skip


def host_supports_target() -> bool:
    """True on an x86-64 CPU that runs x86-64-v3 code."""
    import llvmlite.binding as llvm

    if llvm.get_process_triple().split("-")[0] != "x86_64":
        return False
    features = llvm.get_host_cpu_features()
    return all(features.get(name, False) for name in REQUIRED_HOST_FEATURES)


def pinned_environment(cache_dir: Path) -> dict[str, str]:
    """This process's environment with every CPU-dispatching library held to the target, and
    numba's cache in `cache_dir` (so no kernel compiled for the host is reused)."""
    env = dict(os.environ, **FIXED_ENVIRONMENT, NUMBA_CACHE_DIR=str(cache_dir))
    env["NPY_DISABLE_CPU_FEATURES"] = " ".join(_numpy_targets_above())
    env["OPENCV_CPU_DISABLE"] = ",".join(_opencv_targets_above())
    return env


def _numpy_targets_above() -> list[str]:
    """NumPy's dispatch targets above x86-64-v3 that this CPU has (NumPy refuses to disable
    one the CPU lacks)."""
    from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

    return [t for t in __cpu_dispatch__ if t not in NUMPY_TARGET_LEVELS and __cpu_features__[t]]


def _opencv_targets_above() -> list[str]:
    """OpenCV's dispatched code paths above AVX2 that this CPU has (its feature line marks
    dispatched ones with ``*`` and those the CPU lacks with ``?``; OpenCV warns about those)."""
    import cv2

    names = [name.lstrip("*") for name in cv2.getCPUFeaturesLine().split()]
    return [n for n in names if n not in OPENCV_TARGET_LEVELS and not n.endswith("?")]


def statistics(values: Any) -> dict[str, Any]:
    """Count, mean, std and quantiles of the finite values (float64 sums, fixed order)."""
    import numpy as np

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
    import h5py

    from outputs.ply import read_ply

    events = [json.loads(line) for line in (job / "log.jsonl").read_text().splitlines()]
    metrics = json.loads((job / "outputs" / "metrics.json").read_text())
    splats = read_ply(job / "outputs" / "ply" / "global.ply")
    images = {}
    with h5py.File(job / "outputs" / "uncertainty.h5", "r") as h5:
        h5.visititems(lambda name, d: images.update({name: statistics(d[()])})
                      if isinstance(d, h5py.Dataset) and d.dtype.kind == "f" else None)  # fmt: skip
    return {
        "target": TARGET,
        "vendor": cpu_vendor(),
        "trajectory": (job / "trajectory.txt").read_text().splitlines(),
        "keyframes": [[e["frame"], e["keyframe"], e["reason"], e["score_color"], e["score_depth"]]
                      for e in events],  # fmt: skip
        "metrics": {name: _lookup(metrics, path) for name, path in METRICS.items()},
        "ply": {name: statistics(value) for name, value in vars(splats).items()},
        "uncertainty_images": images,
    }


def make_store(case: str, workdir: Path) -> Path:
    """The case's frame store, converted with the defaults a user gets."""
    from conftest import TUM_EXCERPT

    from converters.synthetic import SynthConfig, synthesize
    from converters.tum import TumOptions, convert_tum

    if case == "synthetic":
        config = SynthConfig(frames=16, width=160, height=120, seed=3)
        folder, options = synthesize(workdir / "seq", config), TumOptions()
    elif case == "tum_fr1_rpy_30":
        folder, options = TUM_EXCERPT, TumOptions(max_frames=30)
    else:
        raise SystemExit(f"unknown golden case {case!r}")
    return convert_tum(folder, workdir / f"{case}.h5", options)


def run_case(case: str, workdir: Path, overrides: list[str]) -> dict[str, Any]:
    """Convert, run (with the default export) and condense one case."""
    from click.testing import CliRunner

    from bgs_batch.cli import main

    store, job = make_store(case, workdir), workdir / "job"
    sets = sum((["--set", s] for s in [*FAST, *overrides]), [])
    result = CliRunner().invoke(main, ["-q", "run", str(store), "--job-dir", str(job), *sets])
    if result.exit_code != 0:
        trace = "".join(traceback.format_exception(result.exception)) if result.exception else ""
        raise SystemExit(f"bgs run failed ({result.exit_code}): {result.output}{trace}")
    return condense(job)


if __name__ == "__main__":
    name, folder, out, *extra = sys.argv[1:]
    record = run_case(name, Path(folder), extra)
    Path(out).write_text(json.dumps(record, indent=1) + "\n")
