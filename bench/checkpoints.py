"""Cost of checkpointed, resumable jobs: checkpoint time and size, cadence overhead,
resume latency.

Usage: .venv/bin/python bench/checkpoints.py [--tum DIR] [--frames 30]

On the real TUM fr1/rpy excerpt in ../shared/data (a synthetic room when it is absent), `cpu`
preset, all numbers from one run:

1. one run with the default cadence (``checkpoint_every`` = 10): every checkpoint's size, the
   time to snapshot the state (``Slam.state_dict``) and to write it (serialise, checksum, fsync,
   rename), by frames done;
2. the same run with checkpointing disabled, side by side: wall and CPU time of both. The
   overhead verdict uses the checkpoints' own measured time over the run's time, which other
   processes on the machine do not distort; the wall difference of the two runs is printed too.
   Target: <= 5 %. When missed, the cadence that meets it is printed;
3. resume latency: ``bgs run`` (a fresh process, as Slurm starts it) on a copy of run 1 cut back
   to its newest checkpoint before the end, until its first newly tracked frame appears in
   ``log.jsonl``. Target: <= 5 s. That line comes after the frame's mapping when it is a
   keyframe; the time its pose was tracked is reported too (the line's time less the stages
   run after tracking, from its ``stage_s``). The resumed run then finishes and must equal
   run 1 bitwise.

Prints a table and one SUMMARY line.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jobs.run as job_run
from bgs_batch.config import Config, load_config
from converters.pipeline import write_store
from converters.synthetic import SynthConfig, synthesize
from converters.tum import TumOptions, plan_tum
from jobs.checkpoint import CHECKPOINT_DIR
from jobs.run import LOG_FILE, RunSummary, run_job

from status_page import recorded

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
DEFAULT_TUM = SHARED_DATA / "tum_rgbd" / "rgbd_dataset_freiburg1_rpy"
DEFAULT_FRAMES = 30  # three runs fit in ~10 minutes; --frames 60 shows a larger map
PRESET = "cpu"
DEFAULT_CADENCE = Config().checkpoint_every
NEVER = 10**9  # checkpoint_every that no run reaches: checkpointing disabled
TARGET_OVERHEAD = 0.05
TARGET_RESUME_S = 5.0
POLL_S = 0.005
RESUME_TIMEOUT_S = 600
MB = 1e6
BGS = Path(sys.executable).with_name("bgs")
AFTER_TRACKING = ("submaps", "loop_closure", "mapping")  # stages `Slam.process` runs after it


@dataclass(frozen=True)
class CheckpointCost:
    frames_done: int
    gaussians: int  # in the active submap (frozen submaps are on disk, not in checkpoints)
    snapshot_s: float
    write_s: float
    bytes: int

    @property
    def total_s(self) -> float:
        return self.snapshot_s + self.write_s


def timed_run(store: Path, job: Path, cfg: Config) -> tuple[RunSummary, float, float,
                                                             list[CheckpointCost]]:  # fmt: skip
    """Run the job in this process; (summary, wall s, CPU s, every checkpoint's cost)."""
    costs: list[CheckpointCost] = []
    pending: dict[str, Any] = {}
    original_state, original_write = job_run._job_state, job_run.write_checkpoint

    def job_state(slam: Any, seconds: float, stage: Any = None) -> dict[str, Any]:
        start = time.perf_counter()
        state = original_state(slam, seconds, stage)
        gaussians = len(slam.gmap) if stage is None else len(stage.gmap)
        pending.update(snapshot_s=time.perf_counter() - start, gaussians=gaussians)
        return state

    def write(job_dir: Path, frames_done: int, state: dict[str, Any], end_steps: int = 0
              ) -> Path:  # fmt: skip
        start = time.perf_counter()
        path = original_write(job_dir, frames_done, state, end_steps)
        kept = job_dir.parent / f"{job_dir.name}{ALL_CHECKPOINTS}"  # the job keeps two only
        kept.mkdir(exist_ok=True)
        shutil.copy2(path, kept / path.name)
        costs.append(CheckpointCost(frames_done, pending["gaussians"], pending["snapshot_s"],
                                    time.perf_counter() - start, path.stat().st_size))  # fmt: skip
        return path

    job_run._job_state, job_run.write_checkpoint = job_state, write
    try:
        wall, cpu = time.perf_counter(), time.process_time()
        summary = run_job(store, job, cfg)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    finally:
        job_run._job_state, job_run.write_checkpoint = original_state, original_write
    return summary, wall, cpu, costs


ALL_CHECKPOINTS = ".all-checkpoints"  # beside a timed job: a copy of every checkpoint written


def cut_back_to_checkpoint(source: Path, target: Path, frames: int) -> int:
    """Copy a finished job and undo everything after its newest checkpoint before `frames`,
    as if it had been stopped there; returns that checkpoint's frame count."""
    shutil.copytree(source, target)
    for name in ("summary.json", "trajectory.txt", "sensor_net.pt", "global_map.pt"):
        (target / name).unlink()
    shutil.rmtree(target / CHECKPOINT_DIR)
    (target / CHECKPOINT_DIR).mkdir()
    written = sorted(source.parent.joinpath(f"{source.name}{ALL_CHECKPOINTS}").glob("*.pt"))
    before = [path for path in written if int(path.name.split("-")[0]) < frames]
    if not before:
        raise SystemExit(f"no checkpoint before frame {frames}: use --frames >= "
                         f"{2 * DEFAULT_CADENCE}")  # fmt: skip
    shutil.copy2(before[-1], target / CHECKPOINT_DIR / before[-1].name)
    kept = [int(before[-1].name.split("-")[0])]
    lines = (target / LOG_FILE).read_text().splitlines(keepends=True)
    (target / LOG_FILE).write_text("".join(lines[: kept[-1]]))
    return kept[-1]


@dataclass(frozen=True)
class ResumeLatency:
    """Seconds from starting `bgs run` on a stopped job to ..."""

    logged: float  # ... its first new frame's line in log.jsonl
    tracked: float  # ... that frame's tracked pose (the line less the stages after tracking)
    started: float  # ... the start of that frame's first stage (the line less all its stages)
    ended: float  # ... the end of the process


def resume_latency(store: Path, job: Path, done: int) -> ResumeLatency:
    """How long `bgs run` resuming `job` (a fresh process) takes to its first new frame."""
    log = job / LOG_FILE

    def logged() -> int:
        return log.read_text().count("\n") if log.exists() else 0

    start = time.perf_counter()
    proc = subprocess.Popen([str(BGS), "-q", "run", str(store), "--job-dir", str(job),
                             "--preset", PRESET], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip
    first = None
    while proc.poll() is None and time.perf_counter() - start < RESUME_TIMEOUT_S:
        if first is None and logged() > done:
            first = time.perf_counter() - start
        time.sleep(POLL_S)
    _, err = proc.communicate()
    ended = time.perf_counter() - start
    if proc.returncode != 0 or first is None:
        raise SystemExit(f"resumed `bgs run` failed (exit {proc.returncode}): {err}")
    stages = json.loads(log.read_text().splitlines()[done])["stage_s"]
    after = sum(stages.get(s, 0.0) for s in AFTER_TRACKING)
    return ResumeLatency(first, first - after, first - sum(stages.values()), ended)


def frame_seconds(job: Path, index: int, costs: list[CheckpointCost]) -> float:
    """Seconds frame `index` took in a finished run (from its log; checkpoint time removed)."""
    lines = (job / LOG_FILE).read_text().splitlines()
    elapsed = [json.loads(lines[i])["elapsed_s"] for i in (index - 1, index)]
    checkpoint = sum(c.total_s for c in costs if c.frames_done == index)
    return elapsed[1] - elapsed[0] - checkpoint


def same_result(job: Path, reference: Path) -> bool:
    """Trajectory, sensor network and every submap file bitwise equal."""
    names = sorted(p.name for p in (reference / "submaps").iterdir())
    files = ["trajectory.txt", "sensor_net.pt", *(f"submaps/{n}" for n in names)]
    return sorted(p.name for p in (job / "submaps").iterdir()) == names and all(
        (job / f).read_bytes() == (reference / f).read_bytes() for f in files
    )


def make_store(tum: Path, frames: int, tmp: Path) -> tuple[Path, str]:
    """The store to run on and its description: the TUM excerpt, else a synthetic room."""
    if (tum / "rgb.txt").is_file():
        plan = plan_tum(tum, TumOptions(max_frames=frames))
        name = tum.name
    else:
        folder = synthesize(tmp / "synthetic_room", SynthConfig(frames=frames))
        plan = plan_tum(folder, TumOptions())
        name = f"synthetic room (no TUM excerpt at {tum})"
    return write_store(plan.frames, tmp / "seq.h5", plan.meta).path, name


def row(cells: list[str], widths: list[int]) -> str:
    return "  " + "".join(f"{c:>{w}}" if i else f"{c:<{w}}" for i, (c, w) in
                          enumerate(zip(cells, widths, strict=True)))  # fmt: skip


def print_table(title: str, header: list[str], rows: list[list[str]],
                widths: list[int]) -> None:  # fmt: skip
    print(title)
    print(row(header, widths))
    for cells in rows:
        print(row(cells, widths))


def pct(x: float) -> str:
    return f"{x * 100:+.1f} %"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tum", type=Path, default=DEFAULT_TUM)
    parser.add_argument("--frames", type=int, default=DEFAULT_FRAMES,
                        help=f"frames per run (>= {2 * DEFAULT_CADENCE})")  # fmt: skip
    args = parser.parse_args()
    if args.frames < 2 * DEFAULT_CADENCE:
        parser.error(f"--frames must be >= {2 * DEFAULT_CADENCE} (two checkpoints)")
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())

    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        store, name = make_store(args.tum, args.frames, tmp)
        # warm-up: numba's JIT cache and the page cache must not land on either timed run
        run_job(store, tmp / "warmup", load_config(PRESET, [f"checkpoint_every={NEVER}"]),
                max_frames=2)  # fmt: skip
        # disabled first, default second: a drift in machine load favours neither consistently
        never, never_wall, never_cpu, _ = timed_run(
            store, tmp / "never", load_config(PRESET, [f"checkpoint_every={NEVER}"])
        )
        default, wall, cpu, costs = timed_run(store, tmp / "default", load_config(PRESET))
        done = cut_back_to_checkpoint(tmp / "default", tmp / "resumed", default.frames)
        resume = resume_latency(store, tmp / "resumed", done)
        first_s = resume.logged
        frame_cost = frame_seconds(tmp / "default", done, costs)
        resumed_equal = same_result(tmp / "resumed", tmp / "default")
        uninterrupted_equal = same_result(tmp / "never", tmp / "default")

    frames = default.frames
    print(
        f"bench/checkpoints.py: {name}, {frames} frames, {PRESET} preset, "
        f"load average before: {load}"
    )
    widths = [14, 11, 12, 13, 11, 11]
    print_table(
        f"\ncheckpoints of one run (checkpoint_every = {DEFAULT_CADENCE}):",
        ["frames done", "Gaussians", "size MB", "snapshot ms", "write ms", "total ms"],
        [[str(c.frames_done), str(c.gaussians), f"{c.bytes / MB:.2f}", f"{c.snapshot_s * 1e3:.0f}",
          f"{c.write_s * 1e3:.0f}", f"{c.total_s * 1e3:.0f}"] for c in costs],
        widths,
    )  # fmt: skip
    spent = sum(c.total_s for c in costs)
    overhead = spent / (wall - spent)
    frame_s = (wall - spent) / frames
    mean_cost = spent / len(costs)
    needed = max(1, int(-(-mean_cost // (TARGET_OVERHEAD * frame_s))))  # ceil
    every_frame = mean_cost / frame_s
    print_table(
        "\nside by side:",
        ["run", "wall s", "CPU s", "s/frame", "checkpoints", "vs disabled"],
        [["disabled", f"{never_wall:.1f}", f"{never_cpu:.1f}", f"{never_wall / frames:.2f}", "0",
          "-"],
         [f"every {DEFAULT_CADENCE}", f"{wall:.1f}", f"{cpu:.1f}", f"{wall / frames:.2f}",
          str(len(costs)), f"wall {pct(wall / never_wall - 1)}, CPU {pct(cpu / never_cpu - 1)}"]],
        [14, 11, 12, 13, 13, 26],
    )  # fmt: skip
    print(
        f"  measured checkpoint time {spent:.2f} s of {wall:.1f} s: overhead {overhead:.2%} "
        f"(target <= {TARGET_OVERHEAD:.0%}); {mean_cost * 1e3:.0f} ms per checkpoint, "
        f"{frame_s:.2f} s per frame: "
        + (
            f"every {needed} frames keeps it <= {TARGET_OVERHEAD:.0%}"
            if needed > 1
            else f"even checkpointing every frame would cost only {every_frame:.1%}"
        )
    )
    print(f"  default and disabled runs bitwise equal: {'yes' if uninterrupted_equal else 'NO'}")
    print(f"\nresume from the checkpoint at frame {done} (fresh `bgs run` process):")
    print(
        f"  first new frame logged after {first_s:.2f} s (target <= {TARGET_RESUME_S:.0f} s): "
        f"start-up and restore {first_s - frame_cost:.2f} s + that frame's own SLAM "
        f"{frame_cost:.2f} s (as in the uninterrupted run); process ended after "
        f"{resume.ended:.1f} s"
    )
    print(
        f"  its pose was tracked after {resume.tracked:.2f} s (target <= {TARGET_RESUME_S:.0f} s:"
        f" {'met' if resume.tracked <= TARGET_RESUME_S else 'MISSED'}): start-up and restore "
        f"{resume.started:.2f} s + sensor and tracking {resume.tracked - resume.started:.2f} s, "
        f"measured in that process; then {first_s - resume.tracked:.2f} s of stages after "
        f"tracking (mapping when a keyframe)"
    )
    print(f"  result bitwise equal to the uninterrupted run: {'yes' if resumed_equal else 'NO'}")
    if not (resumed_equal and uninterrupted_equal):
        print("  (a difference also appears when the package's code changed during this run)")

    ok_overhead = overhead <= TARGET_OVERHEAD
    ok_resume = first_s <= TARGET_RESUME_S
    ok = ok_overhead and ok_resume and resumed_equal and uninterrupted_equal
    largest = max(costs, key=lambda c: c.bytes)
    verdict = "all targets met" if ok else "TARGET MISSED"
    if not ok_overhead:
        verdict += f" (overhead: use checkpoint_every >= {needed})"
    print(
        f"SUMMARY: checkpoint every {DEFAULT_CADENCE} frames costs {overhead:.1%} of run time "
        f"({mean_cost * 1e3:.0f} ms each, up to {largest.bytes / MB:.1f} MB); resume to first "
        f"new frame {first_s:.1f} s ({first_s - frame_cost:.1f} s start-up and restore + "
        f"{frame_cost:.1f} s that frame), to its tracked pose {resume.tracked:.1f} s; "
        f"resumed == uninterrupted: "
        f"{'yes' if resumed_equal else 'NO'}"
        f"; {verdict}"
    )


if __name__ == "__main__":
    with recorded("checkpoints"):
        main()
