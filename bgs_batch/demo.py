"""`bgs demo`: the newcomer's path, from nothing to a converted, inspected sequence.

Each step calls the same library code as the matching command, so the demo is also a smoke
test of the whole data flow. It grows as the pipeline does (SLAM, export and evaluation next).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from rich.console import Console

from bgs_batch.progress import progress_bar
from bgs_batch.store import FrameStore
from bgs_batch.summary import StoreSummary, print_summary, summarize
from converters.pipeline import write_store
from converters.synthetic import SynthConfig, synthesize
from converters.tum import TumOptions, plan_tum


@dataclass(frozen=True)
class DemoConfig:
    """Where the demo writes and how large its sequence is (small enough for minutes on 2 cores)."""

    workdir: Path = Path("demo")
    frames: int = 60
    width: int = 320
    height: int = 240
    seed: int = 0


@dataclass(frozen=True)
class DemoResult:
    sequence_dir: Path
    store: Path
    summary: StoreSummary


def run_demo(config: DemoConfig, *, show_progress: bool = True, console: Console | None = None
             ) -> DemoResult:  # fmt: skip
    """Synthesise a sequence, convert it into a frame store and inspect it; replaces old output."""
    console = console or Console()
    config.workdir.mkdir(parents=True, exist_ok=True)
    sequence_dir = config.workdir / "synthetic_room"
    store_path = config.workdir / "synthetic_room.h5"

    console.rule("[bold]1/3 synthesise a sequence")
    synth = SynthConfig(frames=config.frames, width=config.width, height=config.height,
                        seed=config.seed)  # fmt: skip
    with progress_bar("rendering", config.frames, show_progress) as advance:
        synthesize(sequence_dir, synth, overwrite=True, progress=lambda _done, _total: advance(1))
    console.print(f"TUM-layout sequence with exact ground truth in [cyan]{sequence_dir}[/]")

    console.rule("[bold]2/3 convert it into a frame store")
    plan = plan_tum(sequence_dir, TumOptions())
    with progress_bar("converting", len(plan.frames), show_progress) as advance:
        report = write_store(plan.frames, store_path, plan.meta, overwrite=True, progress=advance)
    console.print(f"frame store [cyan]{report.path}[/] ({report.frames} frames)")

    console.rule("[bold]3/3 inspect the store")
    with FrameStore(store_path) as store:
        summary = summarize(store)
    print_summary(summary, console)

    console.rule("[bold]next")
    console.print(
        "The SLAM stage (`bgs run`) lands next: it will track and map this store into an\n"
        "uncertainty-aware Gaussian map. Meanwhile, convert your own data:\n"
        f"  bgs convert tum PATH/TO/rgbd_dataset_freiburg1_xyz -o fr1_xyz.h5\n"
        f"  bgs inspect fr1_xyz.h5\n"
        f"Outputs of this demo: {sequence_dir}/ and {store_path}"
    )
    return DemoResult(sequence_dir, store_path, summary)
