"""`bgs demo`: the newcomer's path, from nothing to a tracked and mapped sequence.

Each step calls the same library code as the matching command, so the demo is also a smoke
test of the whole data flow: synthesise, convert, inspect, run SLAM, export and evaluate.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from bgs_batch.config import load_config
from bgs_batch.progress import progress_bar
from bgs_batch.store import FrameStore
from bgs_batch.store_summary import StoreSummary, print_summary, summarize
from converters.pipeline import write_store
from converters.synthetic import SynthConfig, synthesize
from converters.tum import TumOptions, plan_tum
from jobs.run import RunSummary, run_job
from outputs.export import RUN_DEFAULTS, export_job, frames_to_render
from outputs.jobfiles import OUTPUT_DIR, FinishedJob


@dataclass(frozen=True)
class DemoConfig:
    """Where the demo writes and how large its sequence is (small enough for minutes on 2 cores)."""

    workdir: Path = Path("demo")
    frames: int = 30  # the CLI's DEMO_FRAMES
    width: int = 320
    height: int = 240
    seed: int = 0


@dataclass(frozen=True)
class DemoResult:
    sequence_dir: Path
    store: Path
    summary: StoreSummary
    job_dir: Path
    run: RunSummary


def result_table(run: RunSummary, metrics: dict[str, Any] | None, outputs: Path) -> Table:
    """The demo's closing summary: the numbers, then where to look."""
    table = Table(title="demo result", show_header=False, title_justify="left")
    uncertainty = (metrics or {}).get("uncertainty") or {}
    ause = {k: uncertainty[f"ause_mae_{k}"]["ause_raw"] for k in ("color", "depth")
            if f"ause_mae_{k}" in uncertainty}  # fmt: skip
    rows = [
        ("frames", str(run.frames)),
        ("keyframes", f"{run.keyframes} ({run.keyframes / run.frames:.0%})"),
        ("ATE RMSE", f"{run.ate_rmse_m * 100:.2f} cm (rigid alignment, all frames)"),
        ("speed", f"{run.fps:.2f} frames/s"),
        ("AUSE-MAE", ", ".join(f"{k} {v:.4f}" for k, v in ause.items()) + " (raw units)"),
        ("report", str(outputs / "report.html")),
        ("Gaussian map (PLY)", str(outputs / "ply" / "global.ply")),
        ("trajectory (TUM)", str(outputs / "trajectory" / "estimate.tum")),
        ("uncertainty images", str(outputs / "uncertainty.h5")),
    ]
    for key, value in rows:
        table.add_row(key, value)
    return table


def run_demo(config: DemoConfig, *, show_progress: bool = True, console: Console | None = None
             ) -> DemoResult:  # fmt: skip
    """Synthesise a sequence, convert it into a frame store and inspect it; replaces old output."""
    console = console or Console()
    config.workdir.mkdir(parents=True, exist_ok=True)
    sequence_dir = config.workdir / "synthetic_room"
    store_path = config.workdir / "synthetic_room.h5"

    console.rule("[bold]1/5 synthesise a sequence")
    synth = SynthConfig(frames=config.frames, width=config.width, height=config.height,
                        seed=config.seed)  # fmt: skip
    with progress_bar("rendering", config.frames, show_progress) as advance:
        synthesize(sequence_dir, synth, overwrite=True, progress=lambda _done, _total: advance(1))
    console.print(f"TUM-layout sequence with exact ground truth in [cyan]{sequence_dir}[/]")

    console.rule("[bold]2/5 convert it into a frame store")
    plan = plan_tum(sequence_dir, TumOptions())
    with progress_bar("converting", len(plan.frames), show_progress) as advance:
        report = write_store(plan.frames, store_path, plan.meta, overwrite=True, progress=advance)
    console.print(f"frame store [cyan]{report.path}[/] ({report.frames} frames)")

    console.rule("[bold]3/5 inspect the store")
    with FrameStore(store_path) as store:
        summary = summarize(store)
    print_summary(summary, console)

    console.rule("[bold]4/5 run uncertainty-aware SLAM (cpu preset)")
    job_dir = config.workdir / "job"
    shutil.rmtree(job_dir, ignore_errors=True)
    with progress_bar("SLAM", report.frames, show_progress) as advance:
        run = run_job(store_path, job_dir, load_config("cpu"), on_frame=lambda _e: advance(1))

    console.rule("[bold]5/5 export maps, uncertainty images, metrics and the report")
    options = RUN_DEFAULTS
    count = frames_to_render(FinishedJob(job_dir), options).count
    with progress_bar("rendering", count, show_progress) as advance:
        exported = export_job(job_dir, options, progress=advance)
    console.print(result_table(run, exported.metrics, job_dir / OUTPUT_DIR))
    console.print(
        "Next, your own data:\n"
        "  bgs convert tum PATH/TO/rgbd_dataset_freiburg1_xyz -o fr1_xyz.h5\n"
        "  bgs run fr1_xyz.h5 --job-dir jobs/fr1_xyz"
    )
    return DemoResult(sequence_dir, store_path, summary, job_dir, run)
