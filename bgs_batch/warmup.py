"""Compile the numba kernels once at install time, so a user's first `bgs run` starts tracking
within seconds instead of waiting half a minute for the JIT.

The kernels are compiled with ``cache=True`` into the package's ``__pycache__`` (or
``NUMBA_CACHE_DIR``), keyed by their source files and this CPU. Compiling them needs the exact
argument types a run passes, so the warm-up does what a run does, on a sequence small enough to
take a few seconds once compiled: synthesise, convert, run the default preset, export. `make
install` (and so `make demo` and `make test`) calls ``python -m bgs_batch.warmup``.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

from bgs_batch.config import load_config

FRAMES = 6  # enough for tracking's warm start, a keyframe and a mapping call
# large enough that the registration is trusted, so Gauss-Newton's kernel compiles too (at
# 96×72 the cropped, downscaled frames are too small to register)
WIDTH, HEIGHT = 128, 96


def warm_up(workdir: Path) -> float:
    """Run every compiled stage once inside `workdir`; returns the seconds it took."""
    from converters.synthetic import EFFECTS, SynthConfig, synthesize
    from converters.tum import TumOptions, convert_tum
    from jobs.run import run_job
    from outputs.export import RUN_DEFAULTS, export_job

    start = time.perf_counter()
    # a rolling shutter (the Kinect's), so that the rectification's kernels compile too
    config = SynthConfig(frames=FRAMES, width=WIDTH, height=HEIGHT,
                         readout=EFFECTS["rolling_shutter"]["readout"])  # fmt: skip
    sequence = synthesize(workdir / "sequence", config)
    store = convert_tum(sequence, workdir / "sequence.h5", TumOptions())
    run_job(store, workdir / "job", load_config())
    export_job(workdir / "job", RUN_DEFAULTS)
    return time.perf_counter() - start


def main() -> None:
    with tempfile.TemporaryDirectory(prefix="bgs-warmup-") as tmp:
        seconds = warm_up(Path(tmp))
    print(f"bgs: compiled the kernels for this CPU in {seconds:.0f} s", file=sys.stderr)


if __name__ == "__main__":
    main()
