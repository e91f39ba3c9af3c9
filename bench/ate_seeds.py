"""ATE of the cpu preset over several seeds, with and without a change of settings (A/B).

Usage: .venv/bin/python bench/ate_seeds.py [--seeds N] [--frames N] [--tum DIR]
       [--set KEY=VALUE ...]

On fr1/rpy one run's ATE is one draw: the seed (random seeding pixels and keyframe sampling in
mapping) moves it by up to a centimetre (seeds 0/1/2: 2.6/3.3/2.5 cm on an Intel Rocket Lake,
2.6/3.8/2.6 cm on an AMD Zen 4 machine), and so does any change of a setting, through the same
chaos. A change is an improvement when it lowers the ATE over seeds, not in one run. This bench
runs the `cpu` preset (with `bench/slam_tum.py`'s fr1 settings) for seeds 0..N-1, then the same
with the `--set` overrides when there are any, one run at a time, and prints per seed the ATE
and keyframes of both, their means, and the ratio of the means.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

from slam_tum import DEFAULT_TUM

from bgs_batch.config import ConfigError, load_config
from converters.tum import TumOptions, convert_tum
from jobs.run import RunSummary, run_job

from status_page import recorded


def run_seeds(store: Path, root: Path, name: str, overrides: list[str], seeds: int,
              frames: int) -> list[RunSummary]:  # fmt: skip
    """One cpu-preset run per seed with `overrides`, in job folders below `root`."""
    runs = []
    for seed in range(seeds):
        cfg = load_config("cpu", [*overrides, f"seed={seed}"])
        runs.append(run_job(store, root / f"{name}_seed{seed}", cfg, max_frames=frames))
    return runs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tum", type=Path, default=DEFAULT_TUM)
    parser.add_argument("--frames", type=int, default=240)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE", help="the change to compare (repeatable)")  # fmt: skip
    args = parser.parse_args()
    if not (args.tum / "rgb.txt").is_file():
        sys.exit(f"no TUM folder at {args.tum}; pass --tum DIR")
    try:  # a bad override fails now, not after the first runs
        load_config("cpu", args.overrides)
    except ConfigError as err:
        sys.exit(f"bench/ate_seeds.py: {err}")

    with tempfile.TemporaryDirectory() as tmp:
        store = convert_tum(args.tum, Path(tmp) / "seq.h5", TumOptions(max_frames=args.frames))
        configs = {"cpu": []}
        if args.overrides:
            configs["cpu + " + " ".join(args.overrides)] = args.overrides
        results = {name: run_seeds(store, Path(tmp), f"job{i}", sets, args.seeds, args.frames)
                   for i, (name, sets) in enumerate(configs.items())}  # fmt: skip

    print(f"bench/ate_seeds.py: {args.tum.name}, {args.frames} frames, seeds 0-{args.seeds - 1}")
    print(f"  {'settings':<40} " + " ".join(f"{'seed ' + str(s):>14}" for s in range(args.seeds))
          + f" {'mean ATE':>9}")  # fmt: skip
    means = {}
    for name, runs in results.items():
        means[name] = statistics.mean(r.ate_rmse_m for r in runs)
        cells = " ".join(f"{r.ate_rmse_m * 100:>6.2f} cm {r.keyframes:>3}kf" for r in runs)
        print(f"  {name:<40} {cells} {means[name] * 100:>6.2f} cm")
    base = means["cpu"]
    if len(means) == 1:
        print(f"SUMMARY cpu preset mean ATE {base * 100:.2f} cm over {args.seeds} seeds")
        return
    name, changed = list(means.items())[1]
    print(f"SUMMARY {name}: mean ATE {changed * 100:.2f} cm vs {base * 100:.2f} cm "
          f"= {changed / base:.2f}x over {args.seeds} seeds")  # fmt: skip


if __name__ == "__main__":
    with recorded("ate_seeds"):
        main()
