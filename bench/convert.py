"""Conversion and read-back speed of the frame store, side by side with plain PNG decoding.

Usage: .venv/bin/python bench/convert.py [--tum DIR] [--repeats 3]

Runs on the real TUM fr1/rpy excerpt in ../shared/data (or any TUM folder); all numbers come
from one run, so the ratios hold even on a noisy machine. Prints a table and one summary line.
Targets (issue P1): conversion >= 80 % of the single-thread OpenCV decode rate of the same
PNGs, peak RSS growth 60 -> 240 frames < 50 MB, read-back >= 150 frames/s.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import h5py

from bgs_batch.store import FrameStore
from converters.tum import TumOptions, plan_tum

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
DEFAULT_TUM = SHARED_DATA / "tum_rgbd" / "rgbd_dataset_freiburg1_rpy"
TARGET_CONVERT_RATIO = 0.8
TARGET_RSS_GROWTH_MB = 50
TARGET_READ_FPS = 150

# Runs one conversion in a fresh interpreter and reports its own peak RSS.
_CHILD = """
import json, resource, sys, time
from pathlib import Path
from converters.pipeline import write_store
from converters.tum import TumOptions, plan_tum
folder, out, frames = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
plan = plan_tum(folder, TumOptions(max_frames=frames))
start = time.perf_counter()
report = write_store(plan.frames, out, plan.meta, overwrite=True)
print(json.dumps({"seconds": time.perf_counter() - start, "frames": report.frames,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def decode_rate(pairs: list[tuple[Path, Path]], threads: int) -> float:
    """Frames/s of decoding both PNGs of every pair with OpenCV, nothing else."""

    def decode(pair: tuple[Path, Path]) -> None:
        cv2.imread(str(pair[0]), cv2.IMREAD_UNCHANGED)
        cv2.imread(str(pair[1]), cv2.IMREAD_UNCHANGED)

    start = time.perf_counter()
    if threads == 1:
        for pair in pairs:
            decode(pair)
    else:
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(decode, pairs))
    return len(pairs) / (time.perf_counter() - start)


def convert_in_child(folder: Path, out: Path, frames: int) -> dict:
    result = subprocess.run([sys.executable, "-c", _CHILD, folder, out, str(frames)],
                            check=True, capture_output=True, text=True)  # fmt: skip
    return json.loads(result.stdout)


def read_rates(path: Path) -> tuple[float, float]:
    """Frames/s of FrameStore iteration (prefetching) and of plain single-thread h5py reads."""
    with FrameStore(path) as store:
        start = time.perf_counter()
        n = sum(1 for _ in store)
        ours = n / (time.perf_counter() - start)
    with h5py.File(path) as f:
        start = time.perf_counter()
        for i in range(n):
            f["rgb"][i], f["depth"][i]
        plain = n / (time.perf_counter() - start)
    return ours, plain


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tum", type=Path, default=DEFAULT_TUM, help="TUM sequence folder")
    parser.add_argument("--repeats", type=int, default=3, help="best of N for each timing")
    args = parser.parse_args()
    if not (args.tum / "rgb.txt").is_file():
        sys.exit(f"no TUM folder at {args.tum}; pass --tum DIR")

    plan = plan_tum(args.tum, TumOptions())
    n = len(plan.frames)
    pairs = [(args.tum / f.name.split(" + ")[0], args.tum / f.name.split(" + ")[1])
             for f in plan.frames]  # fmt: skip
    png_mb = sum(p.stat().st_size for pair in pairs for p in pair) / 2**20
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "seq.h5"
        decode_1 = max(decode_rate(pairs, 1) for _ in range(args.repeats))
        decode_2 = max(decode_rate(pairs, 2) for _ in range(args.repeats))
        runs = [convert_in_child(args.tum, out, n) for _ in range(args.repeats)]
        convert = max(r["frames"] / r["seconds"] for r in runs)
        store_mb = out.stat().st_size / 2**20
        reads = [read_rates(out) for _ in range(args.repeats)]
        read_ours, read_plain = (max(r[k] for r in reads) for k in range(2))
        short = convert_in_child(args.tum, Path(tmp) / "short.h5", min(60, n))
        long = convert_in_child(args.tum, Path(tmp) / "long.h5", n)
    growth = long["peak_rss_mb"] - short["peak_rss_mb"]
    ratio = convert / decode_1

    rows = [
        ("decode PNGs only, OpenCV, 1 thread", f"{decode_1:.1f} frames/s", "reference"),
        ("decode PNGs only, OpenCV, 2 threads", f"{decode_2:.1f} frames/s", "context"),
        ("convert (decode+deflate+write), 2 workers", f"{convert:.1f} frames/s",
         f"{ratio:.2f}x decode-1t (target >= {TARGET_CONVERT_RATIO}); "
         f"{convert / decode_2:.2f}x decode-2t"),
        (f"peak RSS converting {min(60, n)} frames", f"{short['peak_rss_mb']:.0f} MB", ""),
        (f"peak RSS converting {n} frames", f"{long['peak_rss_mb']:.0f} MB",
         f"growth {growth:+.1f} MB (target < {TARGET_RSS_GROWTH_MB})"),
        ("store size / source PNG size", f"{store_mb:.1f} / {png_mb:.1f} MB",
         f"ratio {store_mb / png_mb:.2f}"),
        ("read back, FrameStore iteration", f"{read_ours:.1f} frames/s",
         f"target >= {TARGET_READ_FPS}"),
        ("read back, plain h5py single thread", f"{read_plain:.1f} frames/s", "context"),
    ]  # fmt: skip
    print(f"bench/convert.py: {args.tum.name}, {n} frames, best of {args.repeats}")
    width = max(len(r[0]) for r in rows)
    for name, value, note in rows:
        print(f"  {name:<{width}}  {value:>20}  {note}")
    ok = (ratio >= TARGET_CONVERT_RATIO and growth < TARGET_RSS_GROWTH_MB
          and read_ours >= TARGET_READ_FPS)  # fmt: skip
    print(f"SUMMARY convert {convert:.0f} fps = {ratio:.2f}x decode; RSS growth {growth:+.0f} MB; "
          f"read {read_ours:.0f} fps; size ratio {store_mb / png_mb:.2f}; "
          f"{'all targets met' if ok else 'TARGET MISSED'}")


if __name__ == "__main__":
    main()
