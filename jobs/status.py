"""`bgs status`: what a job directory says about its run, for people and for scripts."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from bgs_batch.errors import InputError
from jobs.jobdir import JOB_FILE, lock_owner_alive
from jobs.preemption import Preempted
from jobs.run import ERROR_FILE, LOG_FILE, SUMMARY_FILE, read_colour_offset, read_readout


@dataclass(frozen=True)
class JobStatus:
    job: str
    state: str  # running | done | stopped (resumable) | failed | new
    frames_done: int
    fps: float | None
    keyframes: int
    last_error: str | None
    readout: str | None = None  # the readout estimated from the frames (`readout.json`)
    colour_offset: str | None = None  # the colour camera's, likewise (`colour_offset.json`)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def _last_event(log: Path) -> tuple[int, int, dict[str, Any] | None]:
    """(events, keyframes, last event) of a per-frame log; a torn last line is ignored."""
    count = keyframes = 0
    last = None
    if log.exists():
        for line in log.read_text().splitlines():
            try:
                event = json.loads(line)
            except ValueError:
                break
            count, last = count + 1, event
            keyframes += bool(event.get("keyframe"))
    return count, keyframes, last


def job_status(job_dir: Path) -> JobStatus:
    """Read a job directory's state without touching it (safe while it runs)."""
    if not (job_dir / JOB_FILE).exists():
        raise InputError(f"{job_dir} is not a bgs job directory (no {JOB_FILE}); "
                         "start one with `bgs run STORE --job-dir DIR`")  # fmt: skip
    frames, keyframes, last = _last_event(job_dir / LOG_FILE)
    fps = frames / last["elapsed_s"] if last and last.get("elapsed_s") else None
    error = info = None
    if (job_dir / ERROR_FILE).exists():
        info = json.loads((job_dir / ERROR_FILE).read_text())
        error = f"{info['type']}: {info['message']}"
    if lock_owner_alive(job_dir):
        state = "running"
    elif (job_dir / SUMMARY_FILE).exists() and error is None:
        state = "done"
        fps = json.loads((job_dir / SUMMARY_FILE).read_text())["fps"]
    elif info is not None and info["type"] == Preempted.__name__:
        state = "stopped"  # checkpointed on a signal (exit 75): running it again resumes
    elif error is not None:
        state = "failed"
    elif frames:  # ended without recording an error: killed (SIGKILL, power, OOM killer)
        state = "stopped"
        error = "ended without an error (killed?); running it again resumes"
    else:
        state = "new"
    readout, colour = read_readout(job_dir), read_colour_offset(job_dir)
    return JobStatus(str(job_dir), state, frames, fps, keyframes, error,
                     readout.reason if readout else None,
                     colour.reason if colour else None)  # fmt: skip
