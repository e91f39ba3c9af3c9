"""Read a finished job directory (written by `bgs run`, see `jobs.run`) for the exports.

Each accessor loads its file on first use and fails with an `InputError` that names the file and
the fix, so an export that needs only the submaps works on a job that lacks, say, its log.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from functools import cache, cached_property
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bgs_batch.config import Config, config_from_dict
from bgs_batch.errors import InputError
from bgs_batch.slam.gaussian_map import PARAMS
from bgs_batch.slam.loop_closure.correction import CORRECTION_KEY
from bgs_batch.store import FrameStore
from bgs_batch.trajectory_files import read_tum
from jobs.jobdir import JOB_FILE, JobError, lock_owner_alive, store_entry
from jobs.run import (
    GLOBAL_MAP_FILE,
    LOG_FILE,
    SENSOR_FILE,
    SUBMAP_DIR,
    SUMMARY_FILE,
    read_colour_offset,
)
from outputs.trajectory import match_timestamps

TRAJECTORY_FILE = "trajectory.txt"
CONFIG_FILE = "config.json"
OUTPUT_DIR = "outputs"
POSE_ROWS = 3  # log.jsonl stores the top 3×4 of each camera-to-world pose, row-major


def incomplete(job_dir: Path, what: str) -> InputError:
    """The error for a job directory that lacks (a valid) `what`."""
    return InputError(f"{job_dir} is not a finished job directory: {what}; "
                      "run `bgs run STORE --job-dir JOB` to completion first")  # fmt: skip


@dataclass(frozen=True)
class GlobalMap:
    """``global_map.pt``: the map of the run's global stage and what it trained on."""

    params: dict[str, torch.Tensor]  # `GaussianMap` layout
    training_frames: list[int]
    held_out_frames: list[int]  # never in any of the stage's optimisations
    visits_per_frame: list[int]  # steps the stage took on each frame


@dataclass(frozen=True)
class FrameEvent:
    """One line of ``log.jsonl``: what the SLAM did with a frame."""

    frame: int
    timestamp: float
    keyframe: bool
    reason: str
    score_color: float | None
    score_depth: float | None
    submap: int
    c2w: np.ndarray  # (4, 4) float64, as estimated when the frame was processed (loop closure
    # may correct it later: the final poses are in trajectory.txt, see `FinishedJob.final_poses`)
    elapsed_s: float | None
    # the warp that moved the frame's depth image to its colour image's time (None: not moved)
    depth_motion: np.ndarray | None = None
    # the camera's motion over the frame's rolling-shutter readout (None: not rectified), and on
    # the second frame the first one's, known only then (`Slam._rectify_first_keyframe`)
    readout_motion: np.ndarray | None = None
    first_readout_motion: np.ndarray | None = None
    # the same for the depth image, when it is read out apart from the colour image
    depth_readout_motion: np.ndarray | None = None
    first_depth_readout_motion: np.ndarray | None = None

    @classmethod
    def from_json(cls, event: dict[str, Any]) -> FrameEvent:
        return cls(int(event["frame"]), float(event["timestamp"]), bool(event["keyframe"]),
                   str(event["reason"]), event.get("score_color"), event.get("score_depth"),
                   int(event["submap"]), _rigid(event["pose"]), event.get("elapsed_s"),
                   _rigid(event.get("depth_motion")), _rigid(event.get("readout_motion")),
                   _rigid(event.get("first_readout_motion")),
                   _rigid(event.get("depth_readout_motion")),
                   _rigid(event.get("first_depth_readout_motion")))  # fmt: skip

    @property
    def readouts(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The colour and depth readout motions, as `frames.prepare_frame` takes them."""
        return self.readout_motion, self.depth_readout_motion


def _rigid(rows: list[float] | None) -> np.ndarray | None:
    """A 4×4 rigid transform from its top three rows as logged (None stays None)."""
    if rows is None:
        return None
    matrix = np.eye(4)
    matrix[:POSE_ROWS] = np.asarray(rows, np.float64).reshape(POSE_ROWS, 4)
    return matrix


class FinishedJob:
    """A job directory whose run has ended; `store` overrides the store recorded in job.json."""

    def __init__(self, job_dir: Path, store: Path | None = None) -> None:
        job_dir = Path(job_dir)
        if not job_dir.is_dir():
            raise InputError(f"{job_dir} is not a directory; pass the --job-dir of a `bgs run`")
        if lock_owner_alive(job_dir):
            raise InputError(f"{job_dir} is still being written by `bgs run`; export when it ends")
        self.job_dir = job_dir
        self.explicit_store = None if store is None else Path(store)

    @property
    def outputs(self) -> Path:
        return self.job_dir / OUTPUT_DIR

    def _json(self, name: str) -> Any:
        path = self.job_dir / name
        if not path.is_file():
            raise incomplete(self.job_dir, f"{name} is missing")
        try:
            return json.loads(path.read_text())
        except ValueError as err:
            raise incomplete(self.job_dir, f"{name} is not valid JSON ({err})") from err

    @cached_property
    def record(self) -> dict[str, Any] | None:
        """``job.json`` (None for jobs made before it existed)."""
        return self._json(JOB_FILE) if (self.job_dir / JOB_FILE).is_file() else None

    @cached_property
    def config(self) -> Config:
        """The run's resolved settings (job.json, else config.json; flat in older jobs), with
        the colour offset the run estimated (``colour_offset.json``), so that the exports
        prepare each frame as the run did."""
        data = self.record["config"] if self.record else self._json(CONFIG_FILE)
        config = config_from_dict(data.get("settings", data))
        offset = read_colour_offset(self.job_dir)
        return config if offset is None else offset.applied_to(config)

    @cached_property
    def summary(self) -> dict[str, Any]:
        """``summary.json``: written last by `bgs run`, so its presence means the run finished."""
        return self._json(SUMMARY_FILE)

    @cached_property
    def events(self) -> list[FrameEvent]:
        """The per-frame log, in frame order."""
        path = self.job_dir / LOG_FILE
        if not path.is_file():
            raise incomplete(self.job_dir, f"{LOG_FILE} is missing")
        events = []
        for number, line in enumerate(path.read_text().splitlines(), 1):
            try:
                events.append(FrameEvent.from_json(json.loads(line)))
            except (ValueError, KeyError, TypeError) as err:
                raise incomplete(self.job_dir, f"{LOG_FILE} line {number} is damaged ({err})"
                                 ) from err  # fmt: skip
        if not events or [e.frame for e in events] != list(range(len(events))):
            raise incomplete(self.job_dir, f"{LOG_FILE} does not list frames 0, 1, 2, … in order")
        second = events[1] if len(events) > 1 else None
        if second is not None and (second.first_readout_motion is not None
                                   or second.first_depth_readout_motion is not None):
            # the SLAM re-mapped the first keyframe from its rows rectified at the second's
            events[0] = replace(events[0], readout_motion=second.first_readout_motion,
                                depth_readout_motion=second.first_depth_readout_motion)
        return events

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Timestamps (N,) and camera-to-world poses (N, 4, 4) of ``trajectory.txt``."""
        path = self.job_dir / TRAJECTORY_FILE
        if not path.is_file():
            raise incomplete(self.job_dir, f"{TRAJECTORY_FILE} is missing")
        try:
            timestamps, poses = read_tum(path)
        except ValueError as err:
            raise incomplete(self.job_dir, f"{TRAJECTORY_FILE} is not a TUM trajectory ({err})"
                             ) from err  # fmt: skip
        if len(timestamps) == 0:
            raise incomplete(self.job_dir, f"{TRAJECTORY_FILE} holds no poses")
        return timestamps, poses

    def mapped_poses(self) -> np.ndarray:
        """Camera-to-world pose of every frame of the log (N, 4, 4) in the map as saved: the
        pose it was tracked at, moved by its submap's loop-closure correction. Each submap was
        fitted to its keyframes at these poses, so the map is rendered from them;
        ``trajectory.txt`` reports the trajectory, which may spread the corrections along the
        frames and be smoothed (`loop_closure.trajectory_correction`, `smoothing`)."""
        paths = self.submap_paths()
        corrections = [self._submap_file(path).get(CORRECTION_KEY) for path in paths]
        poses = []
        for event in self.events:
            if event.submap >= len(paths):
                raise InputError(f"{self.job_dir}: {LOG_FILE} names submap {event.submap}, "
                                 f"but {SUBMAP_DIR}/ holds {len(paths)} files; the job is "
                                 "damaged")  # fmt: skip
            correction = corrections[event.submap]
            poses.append(event.c2w if correction is None else correction.numpy() @ event.c2w)
        return np.stack(poses)

    def submap_paths(self) -> list[Path]:
        paths = sorted((self.job_dir / SUBMAP_DIR).glob("*.pt"))
        if not paths:
            raise incomplete(self.job_dir, f"no {SUBMAP_DIR}/*.pt files")
        return paths

    def submap_params(self, path: Path) -> dict[str, torch.Tensor]:
        """The Gaussian parameters (`GaussianMap` layout) of one submap file."""
        params = self._submap_file(path)["params"]
        try:
            return {name: params[name] for name in PARAMS}
        except (KeyError, TypeError) as err:
            raise incomplete(self.job_dir, f"{path.name} lacks a parameter ({err})") from err

    def _submap_file(self, path: Path) -> dict[str, Any]:
        try:
            data = torch.load(path, weights_only=True)
        except Exception as err:  # torch.load raises many types (IndexError too) on damaged files
            raise incomplete(self.job_dir, f"{path.name} is unreadable ({err})") from err
        if not isinstance(data, dict) or not isinstance(data.get("params"), dict):
            raise incomplete(self.job_dir, f"{path.name} lacks the Gaussian parameters")
        return data

    @cached_property
    def global_map(self) -> GlobalMap:
        """The global stage's map and record (``global_map.pt``)."""
        path = self.job_dir / GLOBAL_MAP_FILE
        if not path.is_file():
            raise incomplete(self.job_dir, f"{GLOBAL_MAP_FILE} is missing (jobs made before the "
                             "global stage need `bgs run --force`)")  # fmt: skip
        try:
            data = torch.load(path, weights_only=True)
            return GlobalMap({name: data["params"][name] for name in PARAMS},
                             [int(i) for i in data["training_frames"]],
                             [int(i) for i in data["held_out_frames"]],
                             [int(i) for i in data["visits_per_frame"]])  # fmt: skip
        except Exception as err:  # torch.load raises many types on damaged files
            raise incomplete(self.job_dir, f"{GLOBAL_MAP_FILE} is unreadable ({err})") from err

    def sensor_state(self) -> dict[str, torch.Tensor]:
        """The trained sensor-noise network's state dict."""
        path = self.job_dir / SENSOR_FILE
        if not path.is_file():
            raise incomplete(self.job_dir, f"{SENSOR_FILE} is missing")
        try:
            return torch.load(path, weights_only=True)
        except Exception as err:
            raise incomplete(self.job_dir, f"{SENSOR_FILE} is unreadable ({err})") from err

    def recorded_store(self) -> Path | None:
        """The store named in ``job.json`` if that file still exists (and is the job's store,
        `check_store`)."""
        if self.record is None:
            return None
        store = Path(self.record["store"]["path"])
        return self.check_store(store) if store.is_file() else None

    @cache  # noqa: B019 - one per job and store path: hashing a moved store takes seconds
    def check_store(self, store: Path) -> Path:
        """`store` if its content is the store the job ran on (the SHA-256 in ``job.json``; a
        store at its recorded path, size and time is not hashed again), else a `JobError`
        naming both: outputs rendered against another recording's frames would be wrong
        without a sign of it. Jobs made before ``job.json`` existed are not checked."""
        known = None if self.record is None else self.record.get("store")
        if not isinstance(known, dict) or "sha256" not in known:
            return store
        try:
            entry = store_entry(store, known)
        except OSError as err:
            raise InputError(f"cannot read the frame store {store} ({err.strerror})") from err
        if entry["sha256"] != known["sha256"]:
            raise JobError(
                f"{store} is not the frame store {self.job_dir} ran on: its SHA-256 "
                f"{entry['sha256'][:12]}… differs from {known['sha256'][:12]}… recorded in "
                f"{JOB_FILE} (from {known.get('path')}); pass the job's own store with --store"
            )
        return store

    def store_path(self) -> Path:
        """The frame store to read images from: ``--store``, else the one in job.json; either
        must be the store the job ran on (`check_store`)."""
        if self.explicit_store is not None:
            return self.check_store(self.explicit_store)
        store = self.recorded_store()
        if store is None:
            named = self.record["store"]["path"] if self.record else f"no {JOB_FILE}"
            raise InputError(f"the frame store of {self.job_dir} is not available ({named}); "
                             "pass it with --store")  # fmt: skip
        return store

    def open_store(self) -> FrameStore:
        """The job's frame store, checked to hold the job's frames (by timestamp)."""
        path = self.store_path()
        store = FrameStore(path)
        stamps = np.array([e.timestamp for e in self.events])
        index = match_timestamps(stamps, store.timestamps)
        if len(store) < len(stamps) or np.any(index != np.arange(len(stamps))):
            store.close()
            raise InputError(
                f"{path} does not hold the frames of {self.job_dir} (timestamps "
                "differ): is it the job's store? Pass the right one with --store"
            )
        return store

    def ground_truth(self, timestamps: np.ndarray) -> np.ndarray | None:
        """GT camera-to-world poses at `timestamps` (NaN where unknown), matched by timestamp.

        From ``--store`` (an error if it has no GT), else from the recorded store when it is
        still there; None without GT."""
        store = (self.recorded_store() if self.explicit_store is None
                 else self.check_store(self.explicit_store))  # fmt: skip
        if store is None:
            return None
        with FrameStore(store) as opened:
            if not opened.has_gt:
                if self.explicit_store is not None:
                    raise InputError(f"{store} has no ground-truth poses; leave out --store")
                return None
            index = match_timestamps(timestamps, opened.timestamps)
            poses = opened.poses_gt
        if not np.any(index >= 0):
            raise InputError(f"no frame of the job is in {store}: is it the job's store?")
        return np.where((index >= 0)[:, None, None], poses[index], np.nan)
