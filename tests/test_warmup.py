"""`python -m bgs_batch.warmup` (run by `make install`) compiles every kernel a run calls."""

import subprocess
import sys

import pytest

# in a fresh process: warm up, then list the kernels that still have no compiled signature
# (helpers that other kernels call are compiled, or loaded from the cache, as part of them)
PROBE = """
import sys, tempfile
from pathlib import Path
from numba.core.dispatcher import Dispatcher
from bgs_batch.warmup import warm_up
with tempfile.TemporaryDirectory() as tmp:
    warm_up(Path(tmp))
kernels = {f"{name}.{attr}": obj for name, module in list(sys.modules.items())
           if name.split(".")[0] in ("bgs_batch", "converters", "jobs", "outputs")
           for attr, obj in vars(module).items() if isinstance(obj, Dispatcher)}
called = {name for d in kernels.values() for name in d.py_func.__code__.co_names}
entry = {k: d for k, d in kernels.items() if k.rsplit(".", 1)[1] not in called}
print(len(entry))
print(" ".join(sorted(k for k, d in entry.items() if not d.signatures)))
"""


@pytest.mark.slow
def test_the_warm_up_compiles_every_kernel_of_a_run():
    done = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True,
                          check=False, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr
    count, missing = (done.stdout.splitlines() + [""])[:2]
    assert int(count) >= 10  # the renderer's, the losses' and the blur's kernels were found
    assert missing == "", f"not compiled by the warm-up: {missing}"
