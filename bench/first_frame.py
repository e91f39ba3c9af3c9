"""How long a user waits, from typing ``bgs run`` to the first tracked frame.

Usage: .venv/bin/python bench/first_frame.py [--tum DIR] [--frames 8]

Converts the first ``--frames`` of a TUM folder (default: the fr1/rpy excerpt in ../shared/data)
and starts ``bgs run`` (the ``cpu`` preset, a fresh job) as a user does, in a new process, then
watches the job's ``log.jsonl`` for frame 1, the first tracked frame: the seconds include
Python's start, the imports, loading the store, mapping frame 0 and tracking frame 1. Two kernel
caches:

- *installed*: the kernels as ``make install`` leaves them (its warm-up compiles them into the
  package's ``__pycache__``): what a user of a fresh clone gets on the first run;
- *empty*: ``NUMBA_CACHE_DIR`` set to an empty folder, so every kernel compiles first (a package
  installed without the warm-up; for comparison, no target).

Ends with one SUMMARY line; the target is 10 s for the installed cache (issue P14).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from converters.tum import TumOptions, convert_tum
from jobs.run import LOG_FILE

from status_page import recorded

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_TUM = ROOT.parent / "shared" / "data" / "tum_rgbd" / "rgbd_dataset_freiburg1_rpy"
BGS = Path(sys.executable).with_name("bgs")
TARGET_S = 10.0
POLL_S = 0.05
TIMEOUT_S = 600.0


def first_tracked(log: Path) -> bool:
    """Whether ``log.jsonl`` already holds a tracked frame (frame ≥ 1)."""
    if not log.is_file():
        return False
    for line in log.read_text().splitlines():
        try:
            if json.loads(line).get("frame", 0) >= 1:
                return True
        except json.JSONDecodeError:  # a line still being written
            return False
    return False


def seconds_to_first_frame(store: Path, job: Path, env: dict[str, str]) -> tuple[float, float]:
    """(seconds from starting ``bgs run`` to its first tracked frame, seconds of the whole run)."""
    command = [str(BGS), "run", str(store), "--job-dir", str(job), "--no-export"]
    start = time.perf_counter()
    process = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, text=True)  # fmt: skip
    first = None
    while process.poll() is None and time.perf_counter() - start < TIMEOUT_S:
        if first is None and first_tracked(job / LOG_FILE):
            first = time.perf_counter() - start
        time.sleep(POLL_S)
    if process.poll() is None:
        process.kill()
        sys.exit(f"bgs run took more than {TIMEOUT_S:.0f} s; nothing measured")
    _, err = process.communicate()
    if process.returncode != 0:
        sys.exit(f"bgs run failed ({process.returncode}): {err.strip()[-500:]}")
    total = time.perf_counter() - start
    return (first if first is not None else total), total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tum", type=Path, default=DEFAULT_TUM, help="TUM folder to run")
    parser.add_argument("--frames", type=int, default=8, help="frames to convert and run")
    args = parser.parse_args()
    if not (args.tum / "rgb.txt").is_file():
        sys.exit(f"no TUM folder at {args.tum}; pass --tum DIR")
    if not BGS.is_file():
        sys.exit(f"no `bgs` next to {sys.executable}; run `make install` first")

    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"bench/first_frame.py: `bgs run` on the first {args.frames} frames of {args.tum.name}, "
          f"cpu preset; load average before: {load}")  # fmt: skip
    print(f"  {'kernel cache':<34} {'first tracked frame':>20} {'whole run':>10}  status")
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        store = convert_tum(args.tum, root / "seq.h5", TumOptions(max_frames=args.frames))
        caches = {
            "installed (after make install)": {},
            "empty (every kernel compiles)": {"NUMBA_CACHE_DIR": str(root / "cache")},
        }
        for name, extra in caches.items():
            env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"} | extra
            first, total = seconds_to_first_frame(store, root / f"job-{len(rows)}", env)
            rows[name] = first
            status = "" if extra else ("ok" if first <= TARGET_S else
                                       f"MISSED by {first - TARGET_S:.1f} s")  # fmt: skip
            print(f"  {name:<34} {first:>18.1f} s {total:>8.1f} s  {status}")
    installed, empty = rows.values()
    verdict = "met" if installed <= TARGET_S else "MISSED"
    print(
        f"SUMMARY first tracked frame {installed:.1f} s after `bgs run` starts with the "
        f"installed kernels (target {TARGET_S:.0f} s: {verdict}); {empty:.1f} s with an empty "
        "cache"
    )


if __name__ == "__main__":
    with recorded("first_frame"):
        main()
