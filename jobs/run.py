"""`bgs run`: one SLAM job over one frame store, written into a job directory.

Job directory::

    job.json         input store (path, SHA-256), resolved configuration, package version
    lock             present while a process runs the job (host and PID)
    config.json      the resolved configuration (preset + overrides + the store's recommended
                     crop) as ``settings``, and where store-derived values came from (``sources``)
    log.jsonl        one event per frame: pose, keyframe decision and scores, losses, timings
                     (``TIMING_FIELDS``: seconds since the job started, and per stage)
    trajectory.txt   estimated camera-to-world poses, TUM format
    submaps/         frozen submaps (Gaussian parameters + keyframe ids), one file each
    readout.json     the rolling-shutter readout estimated from the frames, when the store did
                     not know it (`bgs_batch.slam.readout`)
    global_map.pt    the global map (`bgs_batch.slam.global_map`): Gaussian parameters, the
                     training and held-out frames, the visits each frame had
    sensor_net.pt    the trained sensor-noise network (state dict)
    summary.json     frames, keyframes, mapping calls, fps, time per stage, ATE when GT exists
    error.json       the exception that stopped the last run, if any
    outputs/         written afterwards by `bgs export` / `bgs eval` (`outputs.export`); `bgs run`
                     runs the default export itself when the run is complete
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from contextlib import suppress
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, TypeVar

import numba
import torch

from bgs_batch.atomic import atomic_file, remove_temporaries, save_torch, write_text
from bgs_batch.config import Config, check_crop, for_store, needs_colour_offset, needs_readout
from bgs_batch.metrics import ate
from bgs_batch.slam import Slam
from bgs_batch.slam.colour_offset import ColourOffsetEstimate, estimate_colour_offset
from bgs_batch.slam.global_map import GlobalMapStage
from bgs_batch.slam.readout import ReadoutEstimate, estimate_readout
from bgs_batch.store import FrameStore
from bgs_batch.trajectory_files import write_tum
from jobs.checkpoint import CHECKPOINT_DIR, load_latest, write_checkpoint
from jobs.jobdir import check_or_write_record, job_lock, job_record, read_record, set_aside
from jobs.preemption import Preempted, StopRequest, stop_requests


@dataclass(frozen=True)
class RunSummary:
    frames: int
    keyframes: int
    mapping_calls: int
    submaps: int
    seconds: float
    fps: float
    stage_seconds: dict[str, float]
    ate_rmse_m: float | None
    # the smoother's maximum-likelihood noise of the tracked trajectory (`smoothing.enabled`)
    trajectory_smoothing: dict[str, float] | None = None
    global_map: dict[str, int] | None = None  # `GlobalMapStage.summary`
    readout: dict[str, Any] | None = None  # `ReadoutEstimate.as_dict`, when it was estimated
    colour_offset: dict[str, Any] | None = None  # `ColourOffsetEstimate.as_dict`, likewise

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


Estimate = TypeVar("Estimate", ReadoutEstimate, ColourOffsetEstimate)
ERROR_FILE = "error.json"
SENSOR_FILE = "sensor_net.pt"
GLOBAL_MAP_FILE = "global_map.pt"
READOUT_FILE = "readout.json"
COLOUR_OFFSET_FILE = "colour_offset.json"
READOUT_SETTINGS = ("rolling_shutter_readout", "depth_rolling_shutter_readout")
SUMMARY_FILE = "summary.json"
LOG_FILE = "log.jsonl"
SUBMAP_DIR = "submaps"
TIMING_FIELDS = ("elapsed_s", "stage_s")
"""Event fields that measure time: the only ones that differ between runs of the same job."""
log = logging.getLogger(__name__)
TORCH_THREADS = 1
"""Torch's threads, whatever `threads` says: torch splits its sums by thread count, so only a
constant keeps every machine's and every setting's results equal. One, because torch's work
here is small tensors (320×240 images, the sensor network at 80×60, Adam on the submap): a
sleeping pool (``OMP_WAIT_POLICY=PASSIVE``, which keeps it from slowing numba's kernels) takes
longer to wake than such an operation takes on one core (docs/experiments.md)."""


def set_threads(threads: int) -> None:
    """Fix thread counts: the numba kernels get `threads` (their sums have a fixed order, so
    results do not depend on it), torch ``TORCH_THREADS``."""
    torch.set_num_threads(TORCH_THREADS)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))


def run_job(
    store_path: Path,
    job_dir: Path,
    cfg: Config,
    *,
    max_frames: int | None = None,
    force: bool = False,
    on_start: Callable[[int], None] | None = None,
    on_frame: Callable[[dict[str, Any]], None] | None = None,
    on_visit: Callable[[int, int], None] | None = None,
) -> RunSummary:
    """Run SLAM over the store (or its first `max_frames`) and write the job directory;
    `on_start(frames)` once the store is open and valid, with the number of frames to run,
    `on_frame(event)` after each frame, `on_visit(done, total)` after each visit of the global
    stage.

    Settings the config leaves to the store (``crop_edge``, ``rolling_shutter_readout``: None)
    take the store's value. Refuses
    a job directory locked by a live process, or made for another store or settings. `force`
    starts the job over: the previous run's directory is moved aside whole (`set_aside`) and
    the run begins at frame 0, so its record, settings and outputs never mix with the new run's.
    """
    set_threads(cfg.threads)
    with FrameStore(store_path) as store:  # validated before the job directory is taken
        cfg, sources = for_store(cfg, store)
        check_crop(cfg, store.width, store.height)
        if on_start is not None:
            on_start(_frames_to_run(store, max_frames))
        job_dir.mkdir(parents=True, exist_ok=True)
        if force and (moved := set_aside(job_dir)) is not None:
            log.warning("--force: moved the previous run of %s to %s", job_dir, moved)
        with job_lock(job_dir):
            record = job_record(store_path, cfg.to_dict(), max_frames, read_record(job_dir))
            check_or_write_record(job_dir, record)
            for folder in (CHECKPOINT_DIR, SUBMAP_DIR):  # what a `kill -9` left half-written
                remove_temporaries(job_dir / folder)
            (job_dir / ERROR_FILE).unlink(missing_ok=True)
            try:
                return _run(store, job_dir, cfg, sources, max_frames, on_frame, on_visit)
            except BaseException as err:  # recorded for `bgs status`, then re-raised
                error = {"type": type(err).__name__, "message": str(err)}
                with suppress(OSError):  # a full disk may refuse this too: keep the cause
                    write_text(job_dir / ERROR_FILE, json.dumps(error))
                raise


def _run(
    store: FrameStore,
    job_dir: Path,
    cfg: Config,
    sources: dict[str, str],
    max_frames: int | None,
    on_frame: Callable[[dict[str, Any]], None] | None,
    on_visit: Callable[[int, int], None] | None,
) -> RunSummary:
    if (job_dir / SUMMARY_FILE).exists():  # finished before: nothing to do (array reruns)
        return RunSummary(**json.loads((job_dir / SUMMARY_FILE).read_text()))
    document = {"settings": cfg.to_dict(), "sources": sources}
    write_text(job_dir / "config.json", json.dumps(document, indent=2, sort_keys=True))
    with stop_requests() as stop:
        clock = time.perf_counter()  # the run's time counts from here, the estimates included
        n = _frames_to_run(store, max_frames)
        readout = _readout(store, job_dir, cfg, n) if needs_readout(cfg) else None
        if readout is not None:  # in place of the readouts the store left open
            found = readout.seconds or 0.0
            cfg = replace(cfg, **{key: found if getattr(cfg, key) is None else getattr(cfg, key)
                                  for key in READOUT_SETTINGS})  # fmt: skip
            if stop.requested:  # during the estimate: kept in readout.json, no frame to save
                raise Preempted(stop.requested, "after the readout estimate", job_dir)
        colour = _colour_offset(store, job_dir, cfg, n) if needs_colour_offset(cfg) else None
        if colour is not None:  # needs the readout: the estimate rectifies the frames with it
            cfg = colour.applied_to(cfg)
            if stop.requested:
                raise Preempted(stop.requested, "after the colour offset estimate", job_dir)
        estimates = time.perf_counter() - clock
        slam = Slam(cfg, store.intrinsics, job_dir / SUBMAP_DIR)
        done, previous_seconds, stage_state = _resume(slam, store, job_dir)
        slam.timings.add("estimates", estimates)  # a resumed run reads them back: milliseconds
        start = clock - previous_seconds

        def checkpoint(frames: int, stage: GlobalMapStage | None = None) -> None:
            state = _job_state(slam, time.perf_counter() - start, stage)
            write_checkpoint(job_dir, frames, state, 0 if stage is None else 1 + stage.visits)

        with open(job_dir / LOG_FILE, "a", buffering=1) as log:  # line-buffered: status reads it
            for frame in store.frames(range(done, n)):
                event = slam.process(frame)
                event["elapsed_s"] = time.perf_counter() - start
                log.write(json.dumps(event) + "\n")
                if on_frame is not None:
                    on_frame(event)
                done = frame.index + 1
                if done % cfg.checkpoint_every == 0 or stop.requested:
                    log.flush()
                    checkpoint(done)
                if stop.requested and done < n:
                    raise Preempted(stop.requested, f"after {done} frames", job_dir)
        if stage_state is None:  # the end of the run: refinement, then the global stage's merge
            slam.finish(store.__getitem__)
        poses, smoothing = slam.trajectory()
        if stage_state is None:
            stage = slam.global_stage(poses, store.__getitem__)
            checkpoint(n, stage)  # a resumed job starts here, not with `finish` again
        else:
            stage = GlobalMapStage.from_state_dict(cfg, stage_state, slam.sensor)
        _optimise_global_map(slam, stage, store, stop, lambda: checkpoint(n, stage), job_dir,
                             on_visit)  # fmt: skip
        save_sensor_and_map(job_dir, slam, stage)
        timestamps = store.timestamps[:n]
        gt = store.poses_gt[:n] if store.has_gt else None
    with atomic_file(job_dir / "trajectory.txt") as tmp:
        write_tum(tmp, timestamps, poses)
    seconds = time.perf_counter() - start
    ate_rmse = ate(poses[:, :3, 3], gt[:, :3, 3])["rmse"] if gt is not None else None
    summary = RunSummary(
        frames=n,
        keyframes=len(slam.keyframe_frames),
        mapping_calls=slam.mapping_calls,
        submaps=len(slam.submaps),
        seconds=seconds,
        fps=n / seconds,
        stage_seconds=asdict(slam.timings),
        ate_rmse_m=ate_rmse,
        trajectory_smoothing=smoothing.as_dict() if smoothing else None,
        global_map=stage.summary(),
        readout=None if readout is None else readout.as_dict(),
        colour_offset=None if colour is None else colour.as_dict(),
    )
    write_text(job_dir / SUMMARY_FILE, json.dumps(summary.as_dict(), indent=2))
    return summary


def _frames_to_run(store: FrameStore, max_frames: int | None) -> int:
    return len(store) if max_frames is None else min(max_frames, len(store))


def _readout(store: FrameStore, job_dir: Path, cfg: Config, n: int) -> ReadoutEstimate:
    """The readout estimated from the store's first frames (`estimate_readout`), made once per
    job and kept in ``readout.json``, so that a resumed run uses the same value."""
    log.info("estimating the rolling-shutter readout from the first %d frames",
             min(n, cfg.readout_estimation.frames))  # fmt: skip
    return _estimate_once(job_dir / READOUT_FILE, ReadoutEstimate.from_dict, lambda: (
        estimate_readout(store.__getitem__, store.timestamps[:n], store.intrinsics, cfg)))


def _colour_offset(store: FrameStore, job_dir: Path, cfg: Config, n: int
                   ) -> ColourOffsetEstimate:  # fmt: skip
    """The colour camera's offset estimated from the store's first frames
    (`estimate_colour_offset`), made once per job and kept in ``colour_offset.json``."""
    log.info("estimating the colour camera's offset from the first %d frames",
             min(n, cfg.colour_offset.frames))  # fmt: skip
    return _estimate_once(job_dir / COLOUR_OFFSET_FILE, ColourOffsetEstimate.from_dict, lambda: (
        estimate_colour_offset(store.__getitem__, store.timestamps[:n], store.intrinsics, cfg)))


def _estimate_once(path: Path, parse: Callable[[dict], Estimate],
                   estimate: Callable[[], Estimate]) -> Estimate:  # fmt: skip
    """A sensor property estimated from the frames once per job: read back from `path` when a
    run before made it (a resumed run uses the same value), else estimated, logged and kept;
    a damaged file is estimated again (the same frames give the same value)."""
    if (recorded := read_estimate(path, parse)) is not None:
        return recorded
    if path.exists():
        log.warning("%s does not hold an estimate; estimating it again", path)
    found = estimate()
    log.warning("%s", found.reason)
    write_text(path, json.dumps(found.as_dict(), indent=2))
    return found


def read_estimate(path: Path, parse: Callable[[dict], Estimate]) -> Estimate | None:
    """The estimate kept in `path`; None when there is none, or one that does not parse."""
    try:
        return parse(json.loads(path.read_text()))
    except (OSError, ValueError, TypeError, KeyError):
        return None


def read_readout(job_dir: Path) -> ReadoutEstimate | None:
    """The job's ``readout.json`` (`read_estimate`)."""
    return read_estimate(job_dir / READOUT_FILE, ReadoutEstimate.from_dict)


def read_colour_offset(job_dir: Path) -> ColourOffsetEstimate | None:
    """The job's ``colour_offset.json`` (`read_estimate`)."""
    return read_estimate(job_dir / COLOUR_OFFSET_FILE, ColourOffsetEstimate.from_dict)


def _optimise_global_map(slam: Slam, stage: GlobalMapStage, store: FrameStore,
                         stop: StopRequest, checkpoint: Callable[[], None], job_dir: Path,
                         on_visit: Callable[[int, int], None] | None) -> None:  # fmt: skip
    """The global stage's visits, checkpointed every ``global_map.checkpoint_every`` and on a
    stop signal (then `Preempted`); `on_visit(done, total)` after each."""
    every, total = slam.cfg.global_map.checkpoint_every, len(stage.order)
    with slam.timings.measure("global_map"):
        for visits in stage.run(lambda i: slam.prepare_index(i, store.__getitem__)):
            if on_visit is not None:
                on_visit(visits, total)
            if visits % every == 0 or stop.requested:
                checkpoint()
            if stop.requested and visits < total:
                raise Preempted(stop.requested, f"in the global stage after {visits} of "
                                f"{total} visits", job_dir)  # fmt: skip


def save_sensor_and_map(job_dir: Path, slam: Slam, stage: GlobalMapStage) -> None:
    """The trained sensor network and the global map with the stage's record."""
    save_torch(slam.sensor.state_dict(), job_dir / SENSOR_FILE)
    save_torch({"params": stage.params(), **stage.record()}, job_dir / GLOBAL_MAP_FILE)


def _job_state(slam: Slam, seconds: float, stage: GlobalMapStage | None = None
               ) -> dict[str, Any]:  # fmt: skip
    state = {"slam": slam.state_dict(), "seconds": seconds}
    if stage is not None:  # every frame done and the run's end reached
        state["global_map"] = stage.state_dict()
    return state


def _resume(slam: Slam, store: FrameStore, job_dir: Path
            ) -> tuple[int, float, dict[str, Any] | None]:  # fmt: skip
    """Restore the newest valid checkpoint (if any) and cut the log back to it.

    Returns (frames done, seconds already spent, the global stage's state when the checkpoint
    was taken in it). Without a checkpoint the log starts empty.
    """
    latest = load_latest(job_dir)
    done, seconds, stage = 0, 0.0, None
    if latest is not None:
        done, state = latest
        slam.load_state_dict(state["slam"], store.__getitem__)
        seconds = float(state["seconds"])
        stage = state.get("global_map")
    log_path = job_dir / LOG_FILE
    lines = log_path.read_text().splitlines(keepends=True)[:done] if log_path.exists() else []
    write_text(log_path, "".join(lines))
    return done, seconds, stage
