"""`bgs export`: turn a job directory into files other tools open (``JOB/outputs/``).

Written::

    outputs/ply/submap_XXXXXX.ply   one PLY per submap (INRIA 3DGS layout, see `outputs.ply`)
    outputs/ply/global.ply          all submaps merged, near-duplicates thinned
    outputs/trajectory/             estimate.{tum,kitti}, times.txt; with the frame store's
                                    ground truth also estimate_aligned.* and gt.*

Each of the two folders is replaced as a whole, so no file of an earlier export lingers. Ground
truth comes from the store given, else from the store recorded in ``job.json`` when it is still
there and has GT.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from bgs_batch.errors import InputError
from bgs_batch.gaussian_map import PARAMS
from bgs_batch.store import FrameStore
from jobs.jobdir import JOB_FILE, lock_owner_alive
from outputs.ply import Splats, merge_submaps, write_ply
from outputs.trajectory import match_timestamps, read_tum, write_trajectories

TRAJECTORY_FILE = "trajectory.txt"
SUBMAP_DIR = "submaps"
OUTPUT_DIR = "outputs"


@dataclass
class ExportReport:
    """What `export_job` wrote: paths, Gaussian counts and ATE statistics (when GT exists)."""

    files: list[Path] = field(default_factory=list)
    gaussians: dict[str, int] = field(default_factory=dict)
    ate: dict[str, dict[str, float]] = field(default_factory=dict)


def _incomplete(job_dir: Path, what: str) -> InputError:
    return InputError(f"{job_dir} is not a finished job directory: {what}; "
                      "run `bgs run STORE --job-dir JOB` to completion first")  # fmt: skip


def load_submaps(job_dir: Path) -> list[Splats]:
    """The job's frozen submaps in order, as `Splats` (world coordinates, no correction)."""
    paths = sorted((job_dir / SUBMAP_DIR).glob("*.pt"))
    if not paths:
        raise _incomplete(job_dir, f"no {SUBMAP_DIR}/*.pt files")
    submaps = []
    for path in paths:
        try:
            params = torch.load(path, weights_only=True)["params"]
            submaps.append(Splats.from_params({name: params[name] for name in PARAMS}))
        except Exception as err:  # torch.load raises many types (IndexError too) on damaged files
            raise _incomplete(job_dir, f"{path.name} is unreadable or lacks a parameter ({err})"
                              ) from err  # fmt: skip
    return submaps


def _fresh_dir(path: Path) -> Path:
    if path.exists():
        shutil.rmtree(path)
    path.mkdir(parents=True)
    return path


def export_ply(job_dir: Path, report: ExportReport) -> None:
    """One PLY per submap and the merged global map, into ``outputs/ply``."""
    submaps = load_submaps(job_dir)
    out = _fresh_dir(job_dir / OUTPUT_DIR / "ply")
    named = [(f"submap_{i:06d}.ply", s) for i, s in enumerate(submaps)]
    for name, splats in [*named, ("global.ply", merge_submaps(submaps))]:
        report.gaussians[name] = write_ply(out / name, splats)
        report.files.append(out / name)


def _ground_truth(store: Path, timestamps: np.ndarray) -> np.ndarray | None:
    """The store's GT poses at `timestamps` (NaN where unknown); None if it has no GT."""
    with FrameStore(store) as opened:
        if not opened.has_gt:
            return None
        index = match_timestamps(timestamps, opened.timestamps)
        poses = opened.poses_gt
    if not np.any(index >= 0):
        raise InputError(f"no frame of the job is in {store}: is it the job's store?")
    return np.where((index >= 0)[:, None, None], poses[index], np.nan)


def _recorded_store(job_dir: Path) -> Path | None:
    """The store named in ``job.json`` if that file still exists (older jobs have no record)."""
    record = job_dir / JOB_FILE
    if not record.is_file():
        return None
    store = Path(json.loads(record.read_text())["store"]["path"])
    return store if store.is_file() else None


def export_trajectories(job_dir: Path, report: ExportReport, store: Path | None = None) -> None:
    """Estimate (and with ground truth the aligned estimate and GT) into ``outputs/trajectory``.

    GT comes from `store` (an error if it has none), else from the job's recorded store when it
    is still there and has GT; GT poses are matched to the estimate by timestamp."""
    path = job_dir / TRAJECTORY_FILE
    if not path.is_file():
        raise _incomplete(job_dir, f"{TRAJECTORY_FILE} is missing")
    try:
        timestamps, estimate = read_tum(path)
    except ValueError as err:
        raise _incomplete(job_dir, f"{TRAJECTORY_FILE} is not a TUM trajectory ({err})") from err
    if len(timestamps) == 0:
        raise _incomplete(job_dir, f"{TRAJECTORY_FILE} holds no poses")
    explicit = store is not None
    store = store if explicit else _recorded_store(job_dir)
    ground_truth = None if store is None else _ground_truth(store, timestamps)
    if explicit and ground_truth is None:
        raise InputError(f"{store} has no ground-truth poses; leave out --store")
    out = _fresh_dir(job_dir / OUTPUT_DIR / "trajectory")
    try:
        report.ate = write_trajectories(out, timestamps, estimate, ground_truth)
    except ValueError as err:
        raise InputError(f"cannot compare {path} with the ground truth of {store}: {err}"
                         ) from err  # fmt: skip
    report.files.extend(sorted(out.iterdir()))


def export_job(job_dir: Path, *, ply: bool = True, trajectory: bool = True,
               store: Path | None = None) -> ExportReport:  # fmt: skip
    """Write the requested outputs of a finished job into ``job_dir/outputs``."""
    if not job_dir.is_dir():
        raise InputError(f"{job_dir} is not a directory; pass the --job-dir of a `bgs run`")
    if lock_owner_alive(job_dir):
        raise InputError(f"{job_dir} is still being written by `bgs run`; export when it ends")
    report = ExportReport()
    if ply:
        export_ply(job_dir, report)
    if trajectory:
        export_trajectories(job_dir, report, store)
    return report
