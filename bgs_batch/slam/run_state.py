"""What a checkpoint of a SLAM run holds, and how a run is restored from it.

`state_of` gathers the run's state into tensors and plain Python values only
(``torch.load(weights_only=True)`` reads them): the poses and their stamps, the motions each frame
was prepared with, the frozen submaps' records, the active submap and its keyframes' indices, the
sensor network and its optimiser, the keyframe selector, the tracker, the loop closer and both
random generators. Keyframe images are not stored: `restore` re-reads them from the frame store,
prepared as they were mapped. A state an older version wrote (a key missing) is refused by name:
such a job starts over.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict
from typing import Any, Protocol

import numpy as np
import torch

from bgs_batch.errors import InputError
from bgs_batch.slam.adam import Adam
from bgs_batch.slam.camera_motion import CameraMotion
from bgs_batch.slam.gaussian_map import GaussianMap
from bgs_batch.slam.keyframes import KeyframeSelector
from bgs_batch.slam.loop_closure import LoopCloser
from bgs_batch.slam.mapping import Keyframe
from bgs_batch.slam.run_record import Timings
from bgs_batch.slam.sensor_noise import SensorNoiseNet
from bgs_batch.slam.submaps import SubmapRecord
from bgs_batch.slam.tracking import Tracker
from bgs_batch.store import Frame


class RunParts(Protocol):
    """The parts of a run (`pipeline.Slam`) that a checkpoint holds."""

    poses: list[np.ndarray]
    timestamps: list[float]
    motion: CameraMotion
    submaps: list[SubmapRecord]
    keyframe_frames: list[int]
    mapping_calls: int
    timings: Timings
    gmap: GaussianMap
    active_keyframes: list[Keyframe]
    submap_first_frame: int
    sensor: SensorNoiseNet
    sensor_opt: Adam
    selector: KeyframeSelector
    tracker: Tracker
    rng: np.random.Generator
    loop_closer: LoopCloser
    unrectified_first: Frame | None

    def reread_keyframe(self, index: int, read_frame: Callable[[int], Frame]) -> Keyframe: ...


def state_of(run: RunParts) -> dict[str, Any]:
    """Everything needed to continue `run` bit for bit (module docstring)."""
    poses = np.stack(run.poses) if run.poses else np.zeros((0, 4, 4))
    return {
        "poses": torch.from_numpy(poses),
        "timestamps": list(run.timestamps),
        **run.motion.state_dict(),
        "submaps": [asdict(s) for s in run.submaps],
        "keyframe_frames": list(run.keyframe_frames),
        "mapping_calls": run.mapping_calls,
        "timings": asdict(run.timings),
        "gmap": run.gmap.state_dict(),
        "active_keyframes": [k.frame for k in run.active_keyframes],
        "submap_first_frame": run.submap_first_frame,
        "sensor": run.sensor.state_dict(),
        "sensor_opt": run.sensor_opt.state_dict(),
        "selector": run.selector.state_dict(),
        "tracker": run.tracker.state_dict(),
        "rng": run.rng.bit_generator.state,
        "torch_rng": torch.get_rng_state(),
        "loop_closure": run.loop_closer.state_dict(),
    }


def restore(run: RunParts, state: dict[str, Any], read_frame: Callable[[int], Frame]) -> None:
    """Put `state` (`state_of`) back into `run`; `read_frame(i)` re-reads keyframe i of the
    active submap. A state that lacks a key of `state_of` is refused by name."""
    if missing := sorted(set(state_of(run)) - set(state)):
        raise InputError(f"this job's checkpoint was made by an older version of bgs-batch "
                         f"(it has no {', '.join(missing)}); start the job over with "
                         "`bgs run --force`")  # fmt: skip
    run.poses = [np.ascontiguousarray(p) for p in state["poses"].numpy()]
    run.timestamps = [float(t) for t in state["timestamps"]]
    run.motion.load_state_dict(state)
    run.submaps = [SubmapRecord(**s) for s in state["submaps"]]
    run.keyframe_frames = list(state["keyframe_frames"])
    run.mapping_calls = int(state["mapping_calls"])
    run.timings = Timings(**state["timings"])
    run.gmap = GaussianMap.from_state_dict(state["gmap"])
    run.active_keyframes = [run.reread_keyframe(i, read_frame) for i in state["active_keyframes"]]
    run.submap_first_frame = int(state["submap_first_frame"])
    run.sensor.load_state_dict(state["sensor"])
    run.sensor_opt.load_state_dict(state["sensor_opt"])
    run.selector.load_state_dict(state["selector"])
    run.tracker.load_state_dict(state["tracker"])
    run.rng.bit_generator.state = state["rng"]
    torch.set_rng_state(state["torch_rng"])
    run.loop_closer.load_state_dict(state["loop_closure"])
    if len(run.poses) == 1 and run.motion.readout_active():  # stopped before frame 1
        run.unrectified_first = read_frame(0)
