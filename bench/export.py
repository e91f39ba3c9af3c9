"""Export time of a finished run against the run's own time.

Usage: .venv/bin/python bench/export.py [--frames 40] [--size 320x240] [--tum [DIR]]

Makes a synthetic sequence (or takes the first --frames of the real TUM fr1/rpy excerpt with
--tum), runs SLAM on it (cpu preset) and then times, in the same process (kernels compiled, as
at the end of `bgs run`), each part of the export alone and the default end-of-run export as a
whole: PLY maps, trajectories, uncertainty images of all keyframes (HDF5 + PNGs), metrics and
report, in one rendering pass. A row at input resolution (--downscale 1) is for information.
Target: the default export takes at most 10 % of the run's time (summary.json's `seconds`).
Then the hand-off to the splat trainers (`--colmap --nerfstudio`) of the keyframes and of every
frame. Target: every frame of a 240-frame run in at most 30 s (`--tum --frames 240`).
Prints a table and one SUMMARY line.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

from bgs_batch.config import load_config
from converters.pipeline import write_store
from converters.synthetic import SynthConfig, synthesize
from converters.tum import TumOptions, plan_tum
from jobs.run import run_job
from outputs.export import RUN_DEFAULTS, ExportOptions, export_job

from status_page import recorded

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
DEFAULT_TUM = SHARED_DATA / "tum_rgbd" / "rgbd_dataset_freiburg1_rpy"
TARGET_SHARE = 0.10
SYNTH_SEED = 3
MB = 2**20
NOTHING = ExportOptions(ply=False, trajectory=False, uncertainty=False, renders=False,
                        metrics=False, report=False)  # fmt: skip
PARTS = {
    "PLY (submaps + global map)": dataclasses.replace(NOTHING, ply=True),
    "trajectories (TUM, KITTI, aligned)": dataclasses.replace(NOTHING, trajectory=True),
    "uncertainty images (HDF5 + PNGs)": dataclasses.replace(NOTHING, uncertainty=True),
    "metrics + report": dataclasses.replace(NOTHING, metrics=True, report=True),
    "renders (PNG)": dataclasses.replace(NOTHING, renders=True),
}
HANDOFF = dataclasses.replace(NOTHING, colmap=True, nerfstudio=True)
HANDOFF_TARGET_S = 30.0  # every frame of a 240-frame run


def make_store(root: Path, args: argparse.Namespace) -> Path:
    if args.tum is not None:
        if not (args.tum / "rgb.txt").is_file():
            sys.exit(f"no TUM folder at {args.tum}; pass --tum DIR")
        plan = plan_tum(args.tum, TumOptions(max_frames=args.frames))
    else:
        width, height = (int(v) for v in args.size.split("x"))
        config = SynthConfig(frames=args.frames, width=width, height=height, seed=SYNTH_SEED)
        plan = plan_tum(synthesize(root / "seq", config), TumOptions())
    return write_store(plan.frames, root / "seq.h5", plan.meta).path


def timed_export(job: Path, options: ExportOptions) -> float:
    start = time.perf_counter()
    export_job(job, options)
    return time.perf_counter() - start


def size_mb(path: Path) -> float:
    files = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]
    return sum(p.stat().st_size for p in files) / MB


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--size", default="320x240", help="synthetic image size WxH")
    parser.add_argument("--tum", type=Path, nargs="?", const=DEFAULT_TUM,
                        help="use this TUM folder instead of a synthetic sequence")  # fmt: skip
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        store = make_store(root, args)
        job = root / "job"
        summary = run_job(store, job, load_config("cpu"))
        run_seconds = json.loads((job / "summary.json").read_text())["seconds"]
        timed_export(job, RUN_DEFAULTS)  # warm-up: first plots, first file-system writes
        rows = [(name, timed_export(job, options)) for name, options in PARTS.items()]
        total = timed_export(job, RUN_DEFAULTS)
        sizes = {name: size_mb(job / "outputs" / name)
                 for name in ("ply", "uncertainty.h5", "uncertainty", "report.html")}  # fmt: skip
        metrics = json.loads((job / "outputs" / "metrics.json").read_text())
        full_res = timed_export(job, dataclasses.replace(RUN_DEFAULTS, downscale=1))
        full_h5 = size_mb(job / "outputs" / "uncertainty.h5")
        handoff_keyframes = timed_export(job, HANDOFF)
        handoff_all = timed_export(job, dataclasses.replace(HANDOFF, frames="all"))
        handoff_mb = size_mb(job / "outputs" / "colmap")

    source = f"TUM {args.tum.name}" if args.tum is not None else f"synthetic {args.size}"
    res = metrics["resolution"]
    print(f"bench/export.py: {source}, {summary.frames} frames, {summary.keyframes} keyframes, "
          f"run {run_seconds:.1f} s ({summary.fps:.2f} fps)")  # fmt: skip
    print(f"  {'export part':<44} {'seconds':>8} {'% of run':>9}")
    for name, seconds in rows:
        print(f"  {name:<44} {seconds:>8.2f} {100 * seconds / run_seconds:>8.1f}%")
    share = total / run_seconds
    print(f"  {'default export (all but renders, one pass)':<44} {total:>8.2f} "
          f"{100 * share:>8.1f}%   <- target <= {100 * TARGET_SHARE:.0f}%")  # fmt: skip
    print(f"  {'  same at input resolution (--downscale 1)':<44} {full_res:>8.2f} "
          f"{100 * full_res / run_seconds:>8.1f}%   (information)")  # fmt: skip
    print(
        f"  sizes: ply {sizes['ply']:.1f} MB, uncertainty.h5 {sizes['uncertainty.h5']:.1f} MB "
        f"({res['width']}x{res['height']}; {full_h5:.1f} MB at input resolution), PNGs "
        f"{sizes['uncertainty']:.1f} MB, report.html {sizes['report.html']:.1f} MB"
    )
    handoff_limit = HANDOFF_TARGET_S * summary.frames / 240
    print(f"  {'colmap/ + transforms.json, keyframes':<44} {handoff_keyframes:>8.2f} "
          f"{100 * handoff_keyframes / run_seconds:>8.1f}%")  # fmt: skip
    print(f"  {'colmap/ + transforms.json, every frame':<44} {handoff_all:>8.2f} "
          f"{100 * handoff_all / run_seconds:>8.1f}%   <- target <= {handoff_limit:.1f} s "
          f"({HANDOFF_TARGET_S:.0f} s per 240 frames); {handoff_mb:.0f} MB")  # fmt: skip
    ok = share <= TARGET_SHARE and handoff_all <= handoff_limit
    print(
        f"SUMMARY export {total:.1f} s = {100 * share:.1f}% of the run's {run_seconds:.0f} s "
        f"({summary.keyframes} keyframes, {res['width']}x{res['height']}); hand-off of all "
        f"{summary.frames} frames {handoff_all:.1f} s; {'targets met' if ok else 'TARGET MISSED'}"
    )


if __name__ == "__main__":
    with recorded("export"):
        main()
