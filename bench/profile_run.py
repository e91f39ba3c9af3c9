"""Where a real run's seconds go: per stage, then per function (the kernels' callers).

Usage: .venv/bin/python bench/profile_run.py [--frames 60] [--tum [DIR]] [--set KEY=VALUE ...]

Converts the first --frames of a TUM folder (default: the fr1/rpy excerpt in ../shared/data),
runs the `cpu` preset (kernels compiled beforehand on the same frames, so no JIT is counted) and
prints:

- the stages from ``log.jsonl`` (``stage_s``, summed over the frames), the estimates made from
  the first frames, the end-of-run refinement and global stage, and the default export that
  `bgs run` ends with, in seconds per frame and as shares of the run and export, from a run
  without the profiler, with its CPU seconds per frame beside those of Open3D's dense SLAM on
  the same frames (`baseline.py`);
- the functions with the most own time from a second, profiled run of the same job (cProfile;
  a numba kernel's time counts to the Python function that calls it, which names it). Python
  calls are slowed by the profiler, so read those shares as an upper bound for Python work.

The next lever is the top row of both tables. Ends with one SUMMARY line.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import resource
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

from baseline import open3d_dense_slam

from bgs_batch.config import load_config
from converters.tum import TumOptions, convert_tum
from jobs.run import LOG_FILE, run_job
from outputs.export import RUN_DEFAULTS, export_job

from status_page import recorded

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_TUM = ROOT.parent / "shared" / "data" / "tum_rgbd" / "rgbd_dataset_freiburg1_rpy"
WARM_FRAMES = 4  # a short run first compiles (or loads) every kernel
TOP_FUNCTIONS = 15
END_OF_RUN_STAGES = {"estimates": "estimates (first frames)", "refinement": "end-of-run refinement",
                     "global_map": "global stage"}  # fmt: skip
"""The stages of summary.json that are not per frame, and their names in the table."""


def stage_seconds(job: Path, export_seconds: float) -> dict[str, float]:
    """Seconds per stage over the run's frames (log.jsonl), the estimates before them, the
    end-of-run work and the default export."""
    totals: dict[str, float] = defaultdict(float)
    for line in (job / LOG_FILE).read_text().splitlines():
        for stage, seconds in json.loads(line).get("stage_s", {}).items():
            totals[stage] += seconds
    summary = json.loads((job / "summary.json").read_text())
    for stage, label in END_OF_RUN_STAGES.items():
        totals[label] = summary["stage_seconds"][stage]
    totals["other (reading, calibration)"] = max(
        0.0, summary["seconds"] - sum(totals.values()))  # fmt: skip
    totals["export (bgs run's default)"] = export_seconds
    return dict(sorted(totals.items(), key=lambda kv: -kv[1]))


def process_cpu_seconds() -> float:
    """User and system CPU seconds of this process so far, all threads."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def top_functions(profile: cProfile.Profile, count: int) -> list[tuple[str, float, int]]:
    """(function, own seconds, calls) with the most own time."""
    stats = pstats.Stats(profile).stats  # (file, line, name) -> (cc, nc, tt, ct, callers)
    rows = []
    for (path, line, name), (_, calls, own, _, _) in stats.items():
        where = Path(path)
        label = f"{where.relative_to(ROOT)}:{name}" if where.is_relative_to(ROOT) else (
            f"{where.name}:{name}" if line else name)  # fmt: skip
        rows.append((label, own, calls))
    return sorted(rows, key=lambda r: -r[1])[:count]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--tum", type=Path, default=DEFAULT_TUM, help="TUM folder to run")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE", help="settings to profile (repeatable)")  # fmt: skip
    args = parser.parse_args()
    if not (args.tum / "rgb.txt").is_file():
        sys.exit(f"no TUM folder at {args.tum}; pass --tum DIR")
    cfg = load_config("cpu", args.overrides)

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        store = convert_tum(args.tum, root / "seq.h5", TumOptions(max_frames=args.frames))
        run_job(store, root / "warm", cfg, max_frames=WARM_FRAMES)
        cpu_before = process_cpu_seconds()
        summary = run_job(store, root / "plain", cfg)
        start = time.perf_counter()
        export_job(root / "plain", RUN_DEFAULTS)
        stages = stage_seconds(root / "plain", time.perf_counter() - start)
        cpu = process_cpu_seconds() - cpu_before
        _, o3d_wall, o3d_cpu = open3d_dense_slam(store, summary.frames)
        profile = cProfile.Profile()
        start = time.perf_counter()
        profile.enable()
        run_job(store, root / "profiled", cfg)
        profile.disable()
        profiled_seconds = time.perf_counter() - start

    n, total = summary.frames, sum(stages.values())
    print(f"bench/profile_run.py: {args.tum.name}, first {n} frames, cpu preset"
          f"{' ' + ' '.join(args.overrides) if args.overrides else ''}; run and export "
          f"{total:.1f} s ({n / total:.2f} fps end to end), {summary.keyframes} keyframes")
    # fmt: skip
    print(f"  CPU s/frame (all threads, run and export): bgs {cpu / n:.2f}, Open3D's dense SLAM "
          f"{o3d_cpu / n:.2f} ({n / o3d_wall:.2f} fps) on the same frames")
    print(f"\n  {'stage':<28} {'s/frame':>8} {'share':>7}")
    for stage, seconds in stages.items():
        print(f"  {stage:<28} {seconds / n:>8.3f} {100 * seconds / total:>6.1f}%")
    print(f"\n  profiled run {profiled_seconds:.1f} s ({profiled_seconds / summary.seconds:.2f}x "
          "the plain run); functions by own time (kernels count to their caller):")  # fmt: skip
    print(f"  {'function':<64} {'s/frame':>8} {'share':>7} {'calls/frame':>12}")
    functions = top_functions(profile, TOP_FUNCTIONS)
    for label, own, calls in functions:
        print(f"  {label[:64]:<64} {own / n:>8.3f} {100 * own / profiled_seconds:>6.1f}% "
              f"{calls / n:>12.1f}")  # fmt: skip
    stage, seconds = next(iter(stages.items()))
    print(f"SUMMARY {n / total:.2f} fps end to end, {cpu / n:.2f} CPU s/frame (Open3D "
          f"{o3d_cpu / n:.2f}); largest stage {stage} "
          f"{100 * seconds / total:.0f}% ({seconds / n:.2f} s/frame); "
          f"top function {functions[0][0]} "
          f"{100 * functions[0][1] / profiled_seconds:.0f}% of the profiled run")  # fmt: skip


if __name__ == "__main__":
    with recorded("profile_run"):
        main()
