"""A run gives the same bits whether its numba kernels were just compiled or loaded from the
cache (docs/development.md, "Kernels and their cache").

Numba links a kernel's callees into it as ``linkonce_odr`` copies and resolves a call to
whichever copy the process loaded first, assuming every copy computes the same. A callee
compiled with value-changing fast-math flags (FMA contraction, reciprocal rewrites) breaks
that: each copy is optimised where it was inlined, so a process that compiled the rasterizer
ran other code than the cache it wrote, and a first run gave other numbers than later ones.
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from numba.core.dispatcher import Dispatcher

import bgs_batch.render._numba_project
import bgs_batch.render._numba_raster
import bgs_batch.slam.blur
import bgs_batch.slam.loss_kernels
import bgs_batch.slam.rolling_shutter_kernels
import bgs_batch.slam.tracking.pose_jacobian
import bgs_batch.slam.tracking.registration_kernels

KERNEL_MODULES = (bgs_batch.render._numba_raster, bgs_batch.render._numba_project,
                  bgs_batch.slam.blur, bgs_batch.slam.loss_kernels,
                  bgs_batch.slam.rolling_shutter_kernels, bgs_batch.slam.tracking.pose_jacobian,
                  bgs_batch.slam.tracking.registration_kernels)  # fmt: skip
VALUE_CHANGING = {"fast", "contract", "arcp", "reassoc", "afn"}


def fast_math(dispatcher: Dispatcher) -> set[str] | None:
    """The flags a kernel declares (None: none declared, so it takes its caller's)."""
    flags = dispatcher.targetoptions.get("fastmath")
    if flags is None:
        return None
    return {"fast"} if flags is True else set(flags or ())


def test_no_kernel_that_others_call_may_change_values_by_fast_math():
    kernels = {name: obj for module in KERNEL_MODULES for name, obj in vars(module).items()
               if isinstance(obj, Dispatcher)}  # fmt: skip
    callers = {name: {c for c, d in kernels.items() if name in d.py_func.__code__.co_names}
               for name in kernels}  # fmt: skip
    offences = []
    for name, dispatcher in kernels.items():
        if not callers[name] or dispatcher.targetoptions.get("inline") == "always":
            continue  # an entry point (one copy), or inlined into its callers' own code
        flags = fast_math(dispatcher)
        inherited = flags is None and any(
            (fast_math(kernels[c]) or set()) & VALUE_CHANGING for c in callers[name])
        if inherited or (flags or set()) & VALUE_CHANGING:
            offences.append(f"{name} (called by {', '.join(sorted(callers[name]))}): {flags}")
    assert offences == [], "\n".join(offences)


def run_in_child(store: Path, job: Path, cache: Path) -> None:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    args = [str(Path(sys.executable).with_name("bgs")), "-q", "run", str(store), "--job-dir",
            str(job), "--no-export", "--set", "global_map.passes=1"]  # fmt: skip
    done = subprocess.run(args, env=env, capture_output=True, text=True, timeout=900,
                          check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr


@pytest.mark.slow
def test_an_empty_and_a_warm_kernel_cache_give_the_same_bits(tum_excerpt, tmp_path):
    from converters.tum import TumOptions, convert_tum

    store = convert_tum(tum_excerpt, tmp_path / "fr1.h5", TumOptions(max_frames=8))
    cache = tmp_path / "numba-cache"  # empty: the first run compiles every kernel into it
    for job in ("cold", "warm"):
        run_in_child(store, tmp_path / job, cache)
    cold, warm = tmp_path / "cold", tmp_path / "warm"
    assert (cold / "trajectory.txt").read_bytes() == (warm / "trajectory.txt").read_bytes()
    for name in ("global_map.pt", *(f"submaps/{p.name}" for p in (cold / "submaps").iterdir())):
        a, b = (torch.load(job / name, weights_only=True)["params"] for job in (cold, warm))
        assert all(torch.equal(a[k], b[k]) for k in a), name
