"""The end of a run, once every frame is tracked and mapped, as named stages (the global stage,
which comes last, is `global_map`).

1. `refine_uncertainties`: each frozen submap's r_i and the sensor network fitted by the NLL
   (Eq. 13, 14) on the submap's keyframes, the geometry fixed (``uncertainty.refine_passes``;
   docs/method.md §4);
2. `calibrate_depth_gains`: the gains of Σ_D's map and sensor parts fitted on every submap's
   keyframes (``uncertainty.calibrate``; `calibration`);
3. `reported_trajectory`: the poses a user gets, the loop corrections spread along the frames
   and smoothed (`loop_closure.correction.continuous_poses`, `smoothing`).

Each stage reads the frozen submaps' files and keyframes re-read from the store (`ReadKeyframe`),
so that a stage repeated after an interruption gives the same files again.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from bgs_batch.config import Config, UncertaintyConfig
from bgs_batch.slam.calibration import depth_samples, fit_depth_gains
from bgs_batch.slam.gaussian_map import UNCERTAINTY_KEY, GaussianMap
from bgs_batch.slam.loop_closure import LoopCloser
from bgs_batch.slam.loop_closure.correction import (
    continuous_poses,
    load_mapped,
    write_uncertainty,
)
from bgs_batch.slam.mapping import Keyframe, Mapper
from bgs_batch.slam.sensor_noise import DepthGains, SensorNoiseNet
from bgs_batch.slam.smoothing import SmoothingReport, smooth_trajectory
from bgs_batch.slam.submaps import SubmapRecord, submap_params

ReadKeyframe = Callable[[int], Keyframe]  # frame index → the keyframe as it was mapped


def refine_uncertainties(mapper: Mapper, submaps: list[SubmapRecord], keyframe: ReadKeyframe
                         ) -> None:  # fmt: skip
    """`Mapper.refine_uncertainty` on each frozen submap at its final pose, from the r_i as
    mapped (so that a repeated call gives the same result); the refined r_i are written back."""
    for record in submaps:
        gmap = GaussianMap.from_state_dict(load_mapped(record.path))
        mapper.refine_uncertainty(gmap, [keyframe(i) for i in record.keyframes])
        write_uncertainty(record.path, gmap.params[UNCERTAINTY_KEY].detach())


def calibrate_depth_gains(sensor: SensorNoiseNet, submaps: list[SubmapRecord],
                          keyframe: ReadKeyframe, keyframes: int, cfg: UncertaintyConfig
                          ) -> None:  # fmt: skip
    """Set the sensor's Σ_D gains fitted on every submap's keyframes at their final state
    (`calibration.fit_depth_gains`, at most ``calibration_pixels`` residuals spread over the
    run's `keyframes`), from gains 1 so that a repeated call agrees."""
    sensor.set_gains(DepthGains())
    limit = cfg.calibration_pixels // max(1, keyframes)
    samples = []
    for record in submaps:
        gmap = GaussianMap.from_state_dict(submap_params(record))
        if not len(gmap):
            continue
        gaussians = gmap.gaussians()
        for index in record.keyframes:
            samples.append(depth_samples(gaussians, keyframe(index), sensor, cfg, limit))
    if samples:
        sensor.set_gains(fit_depth_gains(*map(np.concatenate, zip(*samples, strict=True))))


def reported_trajectory(cfg: Config, poses: np.ndarray, timestamps: np.ndarray,
                        submaps: list[SubmapRecord], loop_closer: LoopCloser
                        ) -> tuple[np.ndarray, SmoothingReport | None]:  # fmt: skip
    """The camera-to-world poses (N, 4, 4) to report: as tracked and corrected, with the loop
    corrections spread along the frames when ``loop_closure.trajectory_correction`` is
    "continuous" (the submaps themselves stay rigidly corrected), then smoothed over the frames
    when ``smoothing.enabled`` (with the noise the smoother estimated)."""
    lc = cfg.loop_closure
    if lc.enabled and lc.trajectory_correction == "continuous" and submaps:
        spans = [(r.first_frame, r.last_frame) for r in submaps]
        poses = continuous_poses(poses, spans, loop_closer.chain_corrections(len(spans)))
    if not cfg.smoothing.enabled:
        return poses, None
    return smooth_trajectory(poses, timestamps, cfg.smoothing)
