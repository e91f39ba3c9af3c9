"""The conductor of a SLAM run: the stages in order, each one an object or function of its own.

`Slam.process` takes one frame through the per-frame stages and returns its log event:

1. prepare (`frames.prepare_frame`, moved by the motions `camera_motion` predicts);
2. track (`tracking.Tracker`);
3. switch submap? (`submaps.exceeds_motion`, `submaps.freeze_submap`), then close loops
   (`loop_closure.LoopCloser`);
4. keyframe? (`keyframes.KeyframeSelector`);
5. map (`mapping.Mapper`).

At the end `Slam.finish`, `Slam.trajectory` and `Slam.global_stage` call the end-of-run stages
(`end_of_run`, `global_map`). The state lives in this object and its stages' objects, each with
its own ``state_dict``, so a job can checkpoint and resume bit for bit; finished submaps are
frozen to disk, so memory stays bounded. Ground truth is never read.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bgs_batch.config import Config
from bgs_batch.slam.adam import Adam
from bgs_batch.slam.camera_motion import CameraMotion, ReadoutMotions
from bgs_batch.slam.end_of_run import (
    ReadKeyframe,
    calibrate_depth_gains,
    refine_uncertainties,
    reported_trajectory,
)
from bgs_batch.slam.frames import Level, prepare_frame
from bgs_batch.slam.gaussian_map import GaussianMap
from bgs_batch.slam.global_map import GlobalMapStage, merge_submaps, split_frames
from bgs_batch.slam.keyframes import KeyframeSelector
from bgs_batch.slam.loop_closure import LoopCloser, inject_drift
from bgs_batch.slam.mapping import Keyframe, Mapper
from bgs_batch.slam.run_record import Timings, log_motions, logged_rows
from bgs_batch.slam.run_state import restore, state_of
from bgs_batch.slam.sensor_noise import SensorNoiseNet
from bgs_batch.slam.smoothing import SmoothingReport
from bgs_batch.slam.submaps import SubmapRecord, exceeds_motion, freeze_submap
from bgs_batch.slam.tracking import Tracker
from bgs_batch.store import Frame


@dataclass
class Slam:
    """An uncertainty-aware Gaussian-splatting SLAM run over one sequence."""

    cfg: Config
    intrinsics: np.ndarray
    submap_dir: Path
    poses: list[np.ndarray] = field(default_factory=list)
    timestamps: list[float] = field(default_factory=list)  # of the frames tracked so far
    submaps: list[SubmapRecord] = field(default_factory=list)
    keyframe_frames: list[int] = field(default_factory=list)
    mapping_calls: int = 0
    timings: Timings = field(default_factory=Timings)

    def __post_init__(self) -> None:
        torch.manual_seed(self.cfg.seed)
        self.rng = np.random.default_rng(self.cfg.seed)
        u = self.cfg.uncertainty
        self.sensor = SensorNoiseNet.from_config(u)
        self.sensor_opt = Adam(self.sensor.parameters(), lr=u.sensor_lr)
        self.tracker = Tracker(self.cfg)
        self.mapper = Mapper(self.cfg, self.sensor, self.sensor_opt)
        self.selector = KeyframeSelector(self.cfg.keyframes)
        self.gmap = GaussianMap()
        self.active_keyframes: list[Keyframe] = []
        self.submap_first_frame = 0
        self.loop_closer = LoopCloser(self.cfg)
        # the constant-velocity motion, and the motions each frame was prepared with: frames
        # are re-read on resume, at the end of the run and by the exports, prepared as tracked
        self.motion = CameraMotion(self.cfg)
        # the first frame while its rows wait for a velocity to be rectified with (the second
        # frame's), `_rectify_first_keyframe`
        self.unrectified_first: Frame | None = None

    def prepare(self, frame: Frame, depth_motion: np.ndarray | None = None,
                readouts: ReadoutMotions = (None, None)) -> tuple[Level, Level]:  # fmt: skip
        """The frame at input resolution and at mapping resolution (`frames.prepare_frame`)."""
        return prepare_frame(frame, self.intrinsics, self.cfg, depth_motion, *readouts)

    def process(self, frame: Frame) -> dict[str, Any]:
        """Track, select and map one frame; return its log event (steps 1-5 of `bgs_batch.slam`)."""
        totals_before = asdict(self.timings)
        motion = self.motion.next_depth_motion(frame, self.poses, self.timestamps)
        readouts = self.motion.next_readout_motions(self.poses, self.timestamps)
        full, level = self.prepare(frame, motion, readouts)
        event: dict[str, Any] = {"frame": frame.index, "timestamp": frame.timestamp}
        # the exports prepare the frame the same way from the log
        log_motions(event, "", {"depth_motion": motion}, readouts)
        with self.timings.measure("sensor"), torch.no_grad():
            scale = self.cfg.uncertainty.sensor_downscale
            sensor_c, sensor_d = self.sensor(level, scale)
        c2w, score_c, score_d = self._track(full, sensor_c, sensor_d, event)
        self.poses.append(c2w)
        self.timestamps.append(frame.timestamp)
        if self._rectifies_again(readouts):
            again = self.motion.next_readout_motions(self.poses, self.timestamps)
            readouts, (full, level) = again, self.prepare(frame, motion, again)
            log_motions(event, "", {"depth_motion": motion}, readouts)
            c2w, score_c, score_d = self._track(full, sensor_c, sensor_d, event, start=c2w)
            self.poses[-1] = c2w
        if self.unrectified_first is not None and len(self.poses) == 2:
            readouts = self._rectify_first_keyframe(event)
            full, level = self.prepare(frame, motion, readouts)
            log_motions(event, "", {}, readouts)
        elif not self.poses[:-1] and self.motion.readout_active():
            self.unrectified_first = frame
        first_of_submap = not self.active_keyframes
        if not first_of_submap and self._should_switch(frame.index, c2w):
            c2w = self._switch_submap(frame.index, event)
            first_of_submap = True
        decision = self.selector.decide(frame.index, score_c, score_d, first_of_submap)
        event.update(decision.as_dict())
        self.motion.keep(frame.index, motion, readouts)
        if decision.keyframe:
            self._add_keyframe(frame.index, full, level, c2w, first_of_submap, event)
        event.update(submap=len(self.submaps), gaussians=len(self.gmap),
                     pose=logged_rows(c2w),
                     stage_s=self._stages_since(totals_before))  # fmt: skip
        return event

    def _rectify_first_keyframe(self, event: dict[str, Any]) -> np.ndarray:
        """Once the second frame gives the first velocity, map the first keyframe again from its
        rectified rows (no velocity was known when it was mapped): a map of raw rows would bias
        every rectified frame tracked against it. Returns the readout motion of that velocity,
        which the second frame shares (constant velocity)."""
        first, self.unrectified_first = self.unrectified_first, None
        readouts = self.motion.next_readout_motions(self.poses, self.timestamps)
        self.motion.keep(first.index, readouts=readouts)
        log_motions(event, "first_", {}, readouts)
        level = self.prepare(first, self.motion.of_frame(first.index)[0], readouts)[1]
        with self.timings.measure("mapping"):
            self.gmap = GaussianMap()
            self.active_keyframes = [Keyframe(first.index, level, self.poses[0])]
            self.mapper.map(self.gmap, self.active_keyframes, True, self.rng)
        return readouts

    def _rectifies_again(self, readouts: ReadoutMotions) -> bool:
        """Whether the frame just tracked is rectified again with the interval ending at it
        (`rectify_again`): a rolling-shutter frame with a velocity, other than the second
        frame, whose velocity the first keyframe's rectification takes."""
        return (self.cfg.rectify_again and readouts[0] is not None and len(self.poses) >= 3
                and self.unrectified_first is None)  # fmt: skip

    def _track(self, full: Level, sensor_c: torch.Tensor, sensor_d: torch.Tensor,
               event: dict[str, Any], start: np.ndarray | None = None
               ) -> tuple[np.ndarray, float | None, float | None]:  # fmt: skip
        """The frame's camera-to-world pose and its two surprise scores (none for frame 0),
        tracked from `start` (default: the constant-velocity prediction)."""
        if not self.poses:
            return np.eye(4), None, None  # the first camera defines the world frame
        with self.timings.measure("tracking"):
            init = (self.motion.initial_pose(self.poses) if start is None
                    else torch.from_numpy(start))  # fmt: skip
            result = self.tracker.track(self.gmap, full, sensor_c, sensor_d,
                                        torch.linalg.inv(init))  # fmt: skip
            # C order always: LAPACK returns column-major, and a checkpoint restores row-major;
            # the layout changes BLAS's summation order, so resuming would drift by an ulp
            c2w = np.ascontiguousarray(torch.linalg.inv(result.w2c).numpy())
            # a second tracking (`rectify_again`) keeps the first's record beside its own
            key = "track_" if start is None else "retrack_"
            event.update({key + "loss": result.loss, key + "iterations": result.iterations,
                          key + "doubled": result.doubled})  # fmt: skip
            if result.start is not None:
                event[key + "start"] = result.start
        return c2w, result.score_color, result.score_depth

    def _switch_submap(self, index: int, event: dict[str, Any]) -> np.ndarray:
        """Freeze the active submap, start a new one at frame `index` and close loops; returns
        the (possibly corrected) current pose."""
        finished = self.active_keyframes
        with self.timings.measure("submaps"):
            self._finish_submap(last_frame=index - 1)
        return self._close_loops(finished, event)  # may correct every pose

    def _add_keyframe(self, index: int, full: Level, level: Level, c2w: np.ndarray,
                      first_of_submap: bool, event: dict[str, Any]) -> None:  # fmt: skip
        """Register the keyframe for loop closure and map the active submap with it."""
        with self.timings.measure("loop_closure"):
            self.loop_closer.add_keyframe(index, len(self.submaps), full, c2w)
        with self.timings.measure("mapping"):
            self.active_keyframes.append(Keyframe(index, level, c2w))
            if first_of_submap:
                self.submap_first_frame = index
            stats = self.mapper.map(self.gmap, self.active_keyframes, first_of_submap, self.rng)
            self.keyframe_frames.append(index)
            self.mapping_calls += 1
            event.update(map_added=stats.added, map_pruned=stats.pruned, map_loss=stats.loss)

    def _stages_since(self, totals_before: dict[str, float]) -> dict[str, float]:
        """Seconds per stage since the run's totals were `totals_before` (the stages that ran)."""
        return {stage: total - totals_before[stage]
                for stage, total in asdict(self.timings).items()
                if total != totals_before[stage]}  # fmt: skip

    def _should_switch(self, index: int, c2w: np.ndarray) -> bool:
        s = self.cfg.submaps
        if s.mode == "interval":
            return index - self.submap_first_frame >= s.every
        return exceeds_motion(self.poses[self.submap_first_frame], c2w, s)

    # --- loop closure hook --------------------------------------------------------------
    def _close_loops(self, finished: list[Keyframe], event: dict[str, Any] | None) -> np.ndarray:
        """Loop closure after a submap was frozen (it may correct all poses so far), then the
        optional injected drift of the new submap's first pose; returns the current pose."""
        with self.timings.measure("loop_closure"):
            report = self.loop_closer.on_submap_finished(self.submaps, finished, self.poses,
                                                         self.sensor)  # fmt: skip
            if report is not None and event is not None:
                event["loop_closure"] = report
            lc = self.cfg.loop_closure
            if event is not None:  # a switch (not the end of the run): the drift lever
                before = self.poses[-1]
                self.poses[-1] = inject_drift(before, lc.inject_drift_deg, lc.inject_drift_m)
                if self.poses[-1] is not before and len(self.poses) > 1:
                    self.motion.drifted(before, self.poses[-1], self.poses[-2])
        return self.poses[-1]

    # --- end loop closure hook ----------------------------------------------------------------

    def _finish_submap(self, last_frame: int) -> None:
        """Freeze the active submap to disk and start an empty one."""
        index = len(self.submaps)
        self.submaps.append(freeze_submap(
            self.submap_dir / f"{index:06d}.pt", index, self.gmap.state_dict(),
            [k.frame for k in self.active_keyframes], self.submap_first_frame, last_frame))
        self.gmap = GaussianMap()
        self.active_keyframes = []

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue bit for bit (`run_state.state_of`)."""
        return state_of(self)

    def load_state_dict(self, state: dict[str, Any], read_frame: Callable[[int], Frame]) -> None:
        """Restore `state_dict` (`run_state.restore`); `read_frame(i)` re-reads keyframe i of
        the active submap."""
        restore(self, state, read_frame)

    def prepare_index(self, index: int, read_frame: Callable[[int], Frame]) -> tuple[Level, Level]:
        """Frame `index` from the store, prepared as when it was tracked."""
        return self.prepare(read_frame(index), *self.motion.of_frame(index))

    def global_stage(self, poses: np.ndarray, read_frame: Callable[[int], Frame]
                     ) -> GlobalMapStage:  # fmt: skip
        """The end-of-run global stage (`global_map`), to be fitted at `poses` (the reported
        trajectory), from the frozen submaps as corrected and refined, merged."""
        split = split_frames(len(self.poses), set(self.keyframe_frames),
                             self.cfg.global_map.hold_out_every)  # fmt: skip
        with self.timings.measure("global_map"):
            merged, kept = merge_submaps(self.submaps, self._keyframe_reader(read_frame),
                                         self.cfg.global_map)  # fmt: skip
        return GlobalMapStage(self.cfg, merged, poses, split, self.sensor, kept)

    def _keyframe_reader(self, read_frame: Callable[[int], Frame]) -> ReadKeyframe:
        return lambda index: self.reread_keyframe(index, read_frame)

    def reread_keyframe(self, index: int, read_frame: Callable[[int], Frame]) -> Keyframe:
        """Keyframe `index` from the store, prepared as when it was mapped."""
        return Keyframe(index, self.prepare_index(index, read_frame)[1], self.poses[index])

    def finish(self, read_frame: Callable[[int], Frame]) -> None:
        """Write the last submap too (LoopSplat drops it; its frames deserve a map), then the
        end-of-run stages (`end_of_run`): refine every submap's uncertainties and calibrate
        Σ_D's gains (`read_frame(i)` reads keyframe i). Repeatable: after an interruption it
        gives the same files again."""
        if self.active_keyframes:
            finished = self.active_keyframes
            self._finish_submap(last_frame=len(self.poses) - 1)
            if self.cfg.loop_closure.final:  # LoopSplat's lc.final
                self._close_loops(finished, event=None)
        u = self.cfg.uncertainty
        keyframe = self._keyframe_reader(read_frame)
        if u.refine_passes or u.calibrate:
            with self.timings.measure("refinement"):
                if u.refine_passes:
                    refine_uncertainties(self.mapper, self.submaps, keyframe)
                if u.calibrate:
                    calibrate_depth_gains(self.sensor, self.submaps, keyframe,
                                          len(self.keyframe_frames), u)  # fmt: skip

    def trajectory(self) -> tuple[np.ndarray, SmoothingReport | None]:
        """The camera-to-world poses (N, 4, 4) to report (`end_of_run.reported_trajectory`)."""
        return reported_trajectory(self.cfg, np.stack(self.poses), np.array(self.timestamps),
                                   self.submaps, self.loop_closer)  # fmt: skip
