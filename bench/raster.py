"""Benchmark of the CPU rasterizer on the room scene of docs/method.md §10.

Run ``.venv/bin/python bench/raster.py`` (float32; a run's threads: numba on 2, torch on
``jobs.run.TORCH_THREADS``). Every case renders colour, depth, alpha and both variances and
back-propagates random upstream gradients; the tracking case differentiates the pose only.
Each backward starts from cleared gradients (``grad = None``), as every mapping and tracking
iteration does, so no run adds into the previous run's gradients.
Times are the minimum of ``REPEATS`` runs after ``WARMUP``.

JIT rows start fresh processes: *cold* with an empty temporary ``NUMBA_CACHE_DIR``, *warm* with
the same directory again. Numba caches compiled kernels in ``__pycache__`` next to the sources,
or in ``NUMBA_CACHE_DIR`` when set (set it when the package directory is read-only).
``bgs_batch.render`` is imported before torch so that ``OMP_WAIT_POLICY=PASSIVE`` reaches both
OpenMP pools (see ``bgs_batch/__init__.py``). The load average is printed: other processes on
the 2 cores inflate every number.

``cpu ms`` is the process CPU time of forward + backward summed over threads: less sensitive
to other processes than wall time (ideal 2-thread wall time ≈ cpu / 2). The floor column
divides by the compute-bound floor of docs/method.md §10: necessary
(pixel, Gaussian) evaluations × 220 flop at 141 GFLOP/s.
"""

import os
import subprocess
import sys
import tempfile
import time

# isort: off
import bgs_batch.render  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its pool)

# isort: on
import torch

from bgs_batch.render import _numba_raster as nr
from bgs_batch.render import project, rasterize, render, se3_exp
from bgs_batch.render.render import Gaussians
from bgs_batch.render.testing import VGA, room_gaussians, room_viewmat
from jobs.run import TORCH_THREADS, set_threads

from status_page import recorded

THREADS = 2
REPEATS = 5
WARMUP = 2
FLOP_PER_EVAL = 220
PEAK_FLOPS = 141e9
SEED = 0
# (name, Gaussians, resolution scale of the 640×480 camera, target ms, pose-only tracking)
CASES = [
    ("100k @ 640x480", 100_000, 1.0, 45.0, False),
    ("300k @ 640x480", 300_000, 1.0, 120.0, False),
    ("100k @ 160x120", 100_000, 0.25, 12.0, False),
    ("tracking 100k @ 160x120", 100_000, 0.25, 20.0, True),
]
REFERENCE_CASE = ("10k @ 80x60", 10_000, 0.125)
"""The one case small enough for the dense PyTorch reference (float32, one run)."""
JIT_TARGETS_S = {"cold": 30.0, "warm": 1.0}
JIT_SNIPPET = """
import time
import bgs_batch.render
import torch
from bgs_batch.render import Camera, render, se3_exp
from bgs_batch.render.testing import random_gaussians
x = torch.ones(1, requires_grad=True)
torch.autograd.backward([x * 1], [x.detach()])  # torch's own lazy imports, not JIT
for dtype in (torch.float32, torch.float64):
    start = time.perf_counter()
    g = random_gaussians(50, seed=0, dtype=dtype)
    for t in vars(g).values():
        t.requires_grad_()
    xi = torch.zeros(6, dtype=dtype, requires_grad=True)
    out = render(g, se3_exp(xi), Camera(40.0, 40.0, 19.5, 14.5, 40, 30))
    torch.autograd.backward(list(out), [torch.ones_like(o) for o in out])
    print(time.perf_counter() - start)
"""


def _timed(fn) -> tuple[float, float]:
    """Minimum wall time and minimum process CPU time (all threads) of ``fn``, in ms."""
    best, best_cpu = float("inf"), float("inf")
    for i in range(WARMUP + REPEATS):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        if i >= WARMUP:
            best = min(best, (time.perf_counter() - start) * 1e3)
            best_cpu = min(best_cpu, (time.process_time() - start_cpu) * 1e3)
    return best, best_cpu


def _evaluations(gaussians: Gaussians, camera) -> tuple[int, int]:
    """Visible Gaussians and necessary (pixel, Gaussian) evaluations of a view."""
    with torch.no_grad():
        p = project(*list(vars(gaussians).values())[:4], room_viewmat(), camera)
        opac = torch.sigmoid(gaussians.opacity_logits[p.ids])
        rects = nr.compute_rects(
            p.means2d.numpy(), p.conics.numpy(), opac.numpy(), camera.width, camera.height
        )
    area = ((rects[:, 1] - rects[:, 0] + 1).clip(0) * (rects[:, 3] - rects[:, 2] + 1).clip(0)).sum()
    return len(p.ids), int(area)


def _run_case(gaussians: Gaussians, camera, tracking: bool) -> tuple[float, float, float, dict]:
    """(forward ms, backward ms, CPU ms of both, profile ms per operator) of a render."""
    for t in vars(gaussians).values():
        t.requires_grad_(not tracking)
    xi = torch.zeros(6, requires_grad=True)
    state = {}

    def forward():
        state["out"] = render(gaussians, se3_exp(xi) @ room_viewmat(), camera)

    def backward():
        for t in [*vars(gaussians).values(), xi]:  # as mapping and tracking do each iteration
            t.grad = None
        forward()
        out = list(state["out"])
        torch.autograd.backward(out, [torch.ones_like(o) for o in out])

    fwd, _ = _timed(forward)
    total, cpu = _timed(backward)
    with torch.profiler.profile() as prof:
        backward()
    names = ("_ProjectNumba", "_RasterizeNumba", "_RasterizeNumbaBackward", "_ProjectNumbaBackward")
    profile = {e.key: e.cpu_time_total / 1e3 for e in prof.key_averages() if e.key in names}
    return fwd, total - fwd, cpu, profile


def _reference_ratio() -> tuple[float, float]:
    """(numba fwd+bwd ms, dense reference fwd+bwd ms) on :data:`REFERENCE_CASE`."""
    _, n, scale = REFERENCE_CASE
    camera = VGA.scaled(scale)
    g = room_gaussians(n, seed=SEED)
    fwd, bwd, _, _ = _run_case(g, camera, tracking=False)
    start = time.perf_counter()
    p = project(*list(vars(g).values())[:4], room_viewmat(), camera)
    out = rasterize(
        p.means2d, p.conics, p.depths, torch.sigmoid(g.opacity_logits[p.ids]), g.colors[p.ids],
        torch.nn.functional.softplus(g.uncertainty_logits[p.ids]), camera.width, camera.height,
        backend="torch",
    )  # fmt: skip
    torch.autograd.backward(list(out), [torch.ones_like(o) for o in out])
    return fwd + bwd, (time.perf_counter() - start) * 1e3


def _jit_seconds(cache_dir: str) -> tuple[float, float]:
    """Seconds of the first float32 and then float64 render + backward in a fresh process."""
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    done = subprocess.run(
        [sys.executable, "-c", JIT_SNIPPET], env=env, capture_output=True, text=True, check=True
    )
    f32, f64 = (float(x) for x in done.stdout.split()[-2:])
    return f32, f64


def main() -> None:
    set_threads(THREADS)  # as a run: numba's kernels on THREADS, torch on TORCH_THREADS
    header = (
        f"{'case':<26}{'visible':>8}{'fwd ms':>9}{'bwd ms':>9}{'total':>9}{'target':>9}"
        f"{'vs ref':>9}{'vs floor':>10}{'cpu ms':>9}  status"
    )
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"float32, numba {THREADS} threads, torch {TORCH_THREADS}, min of {REPEATS} runs; "
          f"load average before: {load}")
    print(header)
    print("-" * len(header))
    met, gaps, profiles = 0, [], []
    for name, n, scale, target, tracking in CASES:
        camera = VGA.scaled(scale)
        g = room_gaussians(n, seed=SEED)
        visible, evals = _evaluations(g, camera)
        fwd, bwd, cpu, profile = _run_case(g, camera, tracking)
        total = fwd + bwd
        floor = evals * FLOP_PER_EVAL / PEAK_FLOPS * 1e3
        ok = total <= target
        met += ok
        if not ok:
            gaps.append(f"{name} {total:.1f}/{target:.0f} ms")
        status = "ok" if ok else f"MISSED by {total - target:.1f} ms"
        print(
            f"{name:<26}{visible:>8}{fwd:>9.1f}{bwd:>9.1f}{total:>9.1f}{target:>9.0f}"
            f"{'-':>9}{total / floor:>9.0f}x{cpu:>9.1f}  {status}"
        )
        profiles.append((name, profile))
    fast, dense = _reference_ratio()
    ref_name = f"{REFERENCE_CASE[0]} (dense ref)"
    print(
        f"{ref_name:<26}{'':>8}{'':>9}{'':>9}{fast:>9.1f}{'-':>9}{dense / fast:>8.0f}x"
        f"{'-':>10}  dense reference {dense / 1e3:.1f} s"
    )
    with tempfile.TemporaryDirectory() as cache_dir:
        for kind in ("cold", "warm"):
            seconds, seconds_f64 = _jit_seconds(cache_dir)
            target = JIT_TARGETS_S[kind]
            ok = seconds <= target
            met += ok
            if not ok:
                gaps.append(f"JIT {kind} {seconds:.1f}/{target:.0f} s")
            name = f"JIT {kind} (float32, s)"
            status = "ok" if ok else f"MISSED by {seconds - target:.1f} s"
            status += f"; float64 variants (tests only) +{seconds_f64:.2f} s"
            print(f"{name:<26}{'':>8}{'':>9}{'':>9}{seconds:>9.2f}{target:>9.0f}{'':>19}  {status}")
    print("\nprofile (ms, one run; projection and rasterizer forward / backward kernels + glue):")
    for name, profile in profiles:
        parts = ", ".join(f"{k.lstrip('_')} {v:.1f}" for k, v in profile.items())
        print(f"  {name:<26}{parts}")
    n_targets = len(CASES) + len(JIT_TARGETS_S)
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    summary = f"SUMMARY: {met}/{n_targets} targets met (load average after: {load})"
    print("\n" + summary + (f"; gaps: {'; '.join(gaps)}" if gaps else ""))


if __name__ == "__main__":
    with recorded("raster"):
        main()
