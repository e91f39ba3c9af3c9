"""`bgs export` / `bgs eval`: turn a finished job directory into files other tools open.

Written into ``JOB/outputs/``::

    ply/submap_XXXXXX.ply   one PLY per submap (INRIA 3DGS layout, see `outputs.ply`)
    ply/global.ply          the global map: the submaps merged and optimised on the run's
                            frames at the reported poses (`bgs_batch.slam.global_map`)
    trajectory/             estimate.{tum,kitti}, times.txt; with the frame store's ground truth
                            also estimate_aligned.{tum,kitti} and gt.{tum,kitti}
    colmap/                 the frames, depths, a COLMAP model and nerfstudio's transforms.json
                            for the splat trainers (`outputs.colmap`; not in `bgs run`'s export)
    uncertainty.h5          per-frame renders, variances, residuals (`outputs.uncertainty_h5`)
    uncertainty/<quantity>/ colour-mapped PNGs with colour bars (`outputs.uncertainty_images`)
    renders/{rgb,depth}/    rendered colour (8-bit) and depth (16-bit PNG, 5000 per m)
    metrics.json            ATE, rendering and uncertainty metrics, run statistics, conventions
    report.html             self-contained report (images embedded)
    report/                 the report's PNGs

Every file and folder is built under a temporary name and renamed when complete
(`outputs.atomic`), so an interrupted or failed export leaves the previous outputs intact and
no half-written file; a folder is replaced as a whole, so no file of an earlier export lingers.
Everything an export needs is checked before anything is written. Frames are rendered once and
shared by the uncertainty images, the renders and the metrics.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bgs_batch.atomic import atomic_dir, atomic_file, remove_temporaries
from bgs_batch.errors import InputError, Interrupted
from bgs_batch.signals import interruptible
from bgs_batch.store import FrameStore
from jobs.jobdir import job_lock
from jobs.preemption import STOP_SIGNALS, pending_stop
from outputs import plots
from outputs.colmap import COLMAP_DIR, Handoff, check_folder, export_handoff
from outputs.colormap import write_png
from outputs.evaluate import (
    MIN_ALIGNED_FRAMES,
    FrameEvaluator,
    GlobalMapEvaluation,
    TrajectoryEvaluation,
    build_metrics,
    evaluate_trajectory,
    run_statistics,
)
from outputs.jobfiles import FinishedJob, incomplete
from outputs.lpips import Lpips, load_lpips
from outputs.ply import Splats, write_ply
from outputs.report import write_report
from outputs.trajectory import write_trajectories
from outputs.uncertainty import FrameUncertainty, UncertaintyRenderer, select_frames
from outputs.uncertainty_h5 import UncertaintyWriter
from outputs.uncertainty_images import ImageScales, panel, write_quantities, write_renders

UNCERTAINTY_FILE = "uncertainty.h5"
METRICS_FILE = "metrics.json"
REPORT_FILE = "report.html"
REPORT_DIR = "report"
GALLERY_FRAMES = 4  # keyframes (and held-out frames) shown in the report, evenly spaced
GLOBAL_PLY = "global.ply"


@dataclass(frozen=True)
class ExportOptions:
    """What to write; `frames`/`stride` choose the frames of the uncertainty images, renders and
    the COLMAP/nerfstudio hand-off ("keyframes" or "all", then every stride-th); metrics always
    use the keyframes."""

    ply: bool = True
    trajectory: bool = True
    uncertainty: bool = True
    renders: bool = True
    metrics: bool = True  # metrics.json
    report: bool = True  # report.html and report/ (implies metrics)
    colmap: bool = False  # outputs/colmap: images, depths and a COLMAP model (`outputs.colmap`)
    nerfstudio: bool = False  # ... and nerfstudio's transforms.json beside them
    text: bool = False  # the COLMAP model also as .txt
    frames: str = "keyframes"
    stride: int = 1
    downscale: int | None = None  # None: the run's mapping resolution
    lpips_weights: tuple[Path, ...] = ()
    store: Path | None = None

    def __post_init__(self) -> None:
        if self.report and not self.metrics:
            raise ValueError("a report needs the metrics")
        if (self.nerfstudio or self.text) and not self.colmap:
            raise ValueError("--nerfstudio and --text write into the COLMAP hand-off")
        if self.frames not in ("keyframes", "all") or self.stride < 1:
            raise ValueError(f"frames {self.frames!r}, stride {self.stride}: invalid")


# what `bgs run` exports when it ends (no PNG renders: the HDF5 file holds them; the hand-off
# to the trainers on request)
RUN_DEFAULTS = ExportOptions(renders=False)
EVERYTHING = ExportOptions(colmap=True, nerfstudio=True)  # `bgs export` without a flag


def export_is_current(job_dir: Path) -> bool:
    """True when the outputs of a default export are complete and newer than the run."""
    summary = Path(job_dir) / "summary.json"
    outputs = Path(job_dir) / "outputs"
    needed = [outputs / name for name in ("ply", "trajectory", METRICS_FILE, REPORT_FILE)]
    if not summary.is_file() or not all(p.exists() for p in needed):
        return False
    return min(p.stat().st_mtime for p in needed) >= summary.stat().st_mtime


@dataclass
class ExportReport:
    """What `export_job` wrote: paths, Gaussian counts, ATE statistics and the metrics."""

    files: list[Path] = field(default_factory=list)
    gaussians: dict[str, int] = field(default_factory=dict)
    handoff: Handoff | None = None
    ate: dict[str, dict[str, float]] = field(default_factory=dict)
    metrics: dict[str, Any] | None = None


def export_ply(job: FinishedJob, report: ExportReport) -> None:
    """One PLY per submap and the global map of the run's global stage, into ``outputs/ply``."""
    submaps = [Splats.from_params(job.submap_params(p)) for p in job.submap_paths()]
    named = [(f"submap_{i:06d}.ply", s) for i, s in enumerate(submaps)]
    global_map = Splats.from_params(job.global_map.params)
    with atomic_dir(job.outputs / "ply") as tmp:
        for name, splats in [*named, (GLOBAL_PLY, global_map)]:
            report.gaussians[name] = write_ply(tmp / name, splats)
    report.files.extend(job.outputs / "ply" / name for name, _ in named)
    report.files.append(job.outputs / "ply" / GLOBAL_PLY)


def export_trajectories(job: FinishedJob, report: ExportReport) -> None:
    """Estimate (and with ground truth the aligned estimate and GT) into ``outputs/trajectory``.

    GT comes from ``--store`` (an error if it has none or too little), else from the job's
    recorded store when it is still there and has GT for at least three frames; GT poses are
    matched to the estimate by timestamp."""
    timestamps, estimate = job.trajectory()
    ground_truth = job.ground_truth(timestamps)
    known = np.all(np.isfinite(estimate), axis=(1, 2))
    if ground_truth is not None and job.explicit_store is None:
        known &= np.all(np.isfinite(ground_truth), axis=(1, 2))
        if known.sum() < MIN_ALIGNED_FRAMES:  # too little GT in the recorded store: no alignment
            ground_truth = None
    with atomic_dir(job.outputs / "trajectory") as tmp:
        try:
            report.ate = write_trajectories(tmp, timestamps, estimate, ground_truth)
        except ValueError as err:
            raise InputError(f"cannot compare {job.job_dir}/trajectory.txt with the ground truth "
                             f"of {job.store_path()}: {err}") from err  # fmt: skip
        names = sorted(p.name for p in tmp.iterdir())
    report.files.extend(job.outputs / "trajectory" / name for name in names)


def _gallery_frames(keyframes: list[int]) -> set[int]:
    if not keyframes:
        return set()
    picks = np.linspace(0, len(keyframes) - 1, min(GALLERY_FRAMES, len(keyframes)))
    return {keyframes[int(round(k))] for k in picks}


def _report_plots(folder: Path, trajectory: TrajectoryEvaluation, evaluator: FrameEvaluator,
                  job: FinishedJob) -> list[tuple[Path, str]]:  # fmt: skip
    """The report's plots into `folder`, with captions."""
    has_gt = trajectory.aligned is not None
    estimate = (trajectory.aligned if has_gt else trajectory.estimate)[:, :3, 3]
    gt = trajectory.ground_truth[:, :3, 3] if has_gt else None
    out = [
        (plots.trajectory_top(folder / "trajectory_top.png", estimate, gt),
         "Trajectory, top view (the two axes of largest extent)"),
        (plots.trajectory_axes(folder / "trajectory_axes.png", trajectory.timestamps, estimate,
                               gt), "Position per axis over time"),
    ]  # fmt: skip
    if has_gt:
        rmse = trajectory.stats["rigid"]["rmse"]
        out.append((plots.ate_over_time(folder / "ate_over_time.png", trajectory.timestamps,
                                        trajectory.errors_m, rmse),
                    "ATE over time (rigid alignment)"))  # fmt: skip
    means = evaluator.sparsification_means()
    if means is not None:
        colour, depth = means
        out.append((plots.sparsification(folder / "ause_color.png", "colour sparsification",
                                         "intensity", {"Sigma_C": colour}),
                    "Colour sparsification curves (mean over keyframes)"))  # fmt: skip
        out.append((plots.sparsification(folder / "ause_depth.png", "depth sparsification",
                                         "m", depth),
                    "Depth sparsification curves of four variances"))  # fmt: skip
    out.append((plots.keyframe_timeline(folder / "keyframes.png", job.events,
                                        job.config.keyframes.threshold),
                "Keyframe timeline: surprise scores and threshold"))  # fmt: skip
    stages = {k: v["seconds"] for k, v in run_statistics(job)["stages"].items()}
    out.append((plots.timing(folder / "timing.png", stages, job.events), "Timing breakdown"))
    return out


def _check_inputs(job: FinishedJob, options: ExportOptions) -> None:
    """Load (and so validate) the job's files the requested outputs need, before writing."""
    if options.ply:
        job.submap_paths()
    if options.ply or options.metrics:
        _ = job.global_map
    if options.trajectory or options.metrics:
        job.trajectory()
    if options.uncertainty or options.renders or options.metrics:
        events, submaps = job.events, job.submap_paths()
        if max(e.submap for e in events) >= len(submaps):
            raise incomplete(job.job_dir, f"log.jsonl names submap {max(e.submap for e in events)}"
                             f" but submaps/ holds {len(submaps)} files")  # fmt: skip
    if options.metrics or options.colmap:
        _ = job.summary
    if options.colmap:
        check_folder(job.outputs / COLMAP_DIR)
        if not select_frames(job, options.frames, options.stride):
            raise InputError(f"{job.job_dir} has no {options.frames} to export; choose "
                             "--frames all")  # fmt: skip


def export_job(job_dir: Path, options: ExportOptions = ExportOptions(),
               progress: Callable[[int], None] | None = None) -> ExportReport:  # fmt: skip
    """Write the requested outputs of a finished job into ``job_dir/outputs``; `progress(1)` is
    called after each rendered frame.

    Holds the job's lock, so no run or other export writes there meanwhile, and first removes
    what a killed export left; SIGTERM, SIGUSR1 or Ctrl-C raise `Interrupted` and every
    temporary file is removed on the way out.
    """
    job = FinishedJob(job_dir, options.store)
    _check_inputs(job, options)
    lpips = None
    if options.metrics and options.lpips_weights:
        lpips = load_lpips(list(options.lpips_weights))
    report = ExportReport()
    with job_lock(job.job_dir), interruptible(STOP_SIGNALS) as interruption, ExitStack() as stack:
        if signum := pending_stop():  # came before these handlers (e.g. as `bgs run` ended)
            raise Interrupted(signum)
        remove_temporaries(job.outputs)  # of an export killed before it could clean up

        def step(frames: int) -> None:  # a signal swallowed by a destructor still stops here
            interruption.check()
            if progress is not None:
                progress(frames)

        renderer = store = None
        if options.uncertainty or options.renders or options.metrics or options.colmap:
            store = stack.enter_context(job.open_store())  # checks store, network
        if options.uncertainty or options.renders or options.metrics:
            renderer = UncertaintyRenderer(job, store, options.downscale)
        if options.ply:
            export_ply(job, report)
        if options.trajectory:
            export_trajectories(job, report)
        if options.colmap:
            frames = frames_to_render(job, options).handoff
            handoff = export_handoff(job, store, frames, options.text, options.nerfstudio, step)
            report.files.append(handoff.folder)
            report.handoff = handoff
        if renderer is not None:
            _export_frames(job, renderer, options, report, lpips, step)
    return report


@dataclass(frozen=True)
class RenderPlan:
    """The frames an export renders: of the images, of the metrics (both from the submaps, at
    the export's resolution) and of the global map's metrics (at input resolution)."""

    images: list[int]
    metrics: list[int]
    global_map: list[int]  # the held-out frames and the keyframes
    handoff: list[int]  # the frames of outputs/colmap

    @property
    def count(self) -> int:
        """Frames in all (a frame of both the images and the metrics is rendered once)."""
        return (len(set(self.images) | set(self.metrics)) + len(self.global_map)
                + len(self.handoff))  # fmt: skip


def frames_to_render(job: FinishedJob, options: ExportOptions) -> RenderPlan:
    """Which frames the export renders (`RenderPlan`)."""
    chosen = select_frames(job, options.frames, options.stride)
    images = chosen if options.uncertainty or options.renders else []
    handoff = chosen if options.colmap else []
    if not options.metrics:
        return RenderPlan(images, [], [], handoff)
    keyframes = select_frames(job, "keyframes")
    return RenderPlan(images, keyframes, sorted({*job.global_map.held_out_frames, *keyframes}),
                      handoff)  # fmt: skip


class _FrameSinks:
    """Where one rendered frame goes: HDF5 + PNGs, renders, metrics, report gallery; each
    folder or file under a temporary name entered on `stack`."""

    def __init__(self, job: FinishedJob, options: ExportOptions, stack: ExitStack,
                 image_frames: list[int], metric_frames: list[int], lpips: Lpips | None
                 ) -> None:  # fmt: skip
        out = job.outputs
        self.job, self.stack, self.count = job, stack, len(image_frames)
        self.images, self.metric_frames = set(image_frames), set(metric_frames)
        self.gallery = _gallery_frames(metric_frames) if options.report else set()
        self.scales = ImageScales(job.config.uncertainty)
        unc = options.uncertainty and bool(image_frames)
        self.h5 = stack.enter_context(atomic_file(out / UNCERTAINTY_FILE)) if unc else None
        self.pngs = stack.enter_context(atomic_dir(out / "uncertainty")) if unc else None
        renders = options.renders and bool(image_frames)
        self.renders = stack.enter_context(atomic_dir(out / "renders")) if renders else None
        self.report = stack.enter_context(atomic_dir(out / REPORT_DIR)) if options.report else None
        self.writer: UncertaintyWriter | None = None
        self.evaluator = FrameEvaluator(lpips)
        self.gallery_files: list[tuple[Path, str]] = []
        self.held_out_files: list[tuple[Path, str]] = []  # the global map's, for the report
        self.size: tuple[int, int] | None = None  # width, height of the images

    def add(self, item: FrameUncertainty) -> None:
        self.size = self.size or (item.alpha.shape[1], item.alpha.shape[0])
        if item.frame in self.images and self.h5 is not None:
            if self.writer is None:
                attrs = _h5_attributes(self.job, item)
                writer = UncertaintyWriter(self.h5, self.count, *item.alpha.shape, attrs)
                self.writer = self.stack.enter_context(writer)
            self.writer.add(item)
            write_quantities(item, self.pngs, self.scales)
        if item.frame in self.images and self.renders is not None:
            write_renders(item, self.renders)
        if item.frame in self.metric_frames:
            self.evaluator.add(item)
        if item.frame in self.gallery:
            path = self.report / f"frame_{item.frame:06d}.png"
            write_png(path, panel(item, self.scales))
            caption = (
                f"frame {item.frame} (keyframe, t = {item.timestamp:.3f} s): colour (top) and "
                "depth (bottom): measured, rendered, error, variances"
            )
            self.gallery_files.append((path, caption))


def _export_frames(
    job: FinishedJob,
    renderer: UncertaintyRenderer,
    options: ExportOptions,
    report: ExportReport,
    lpips: Lpips | None,
    progress: Callable[[int], None],
) -> None:
    """One pass over the frames feeding every per-frame output, then metrics and report."""
    plan = frames_to_render(job, options)
    out = job.outputs
    with ExitStack() as stack:
        sinks = _FrameSinks(job, options, stack, plan.images, plan.metrics, lpips)
        for index in sorted(set(plan.images) | set(plan.metrics)):
            sinks.add(renderer.frame(index))
            progress(1)
        if options.metrics:
            global_map = _evaluate_global_map(job, renderer.store, plan.global_map, sinks, lpips,
                                              progress)  # fmt: skip
            trajectory = evaluate_trajectory(job)
            metrics = build_metrics(job, trajectory, sinks.evaluator, renderer.downscale,
                                    sinks.size, global_map)  # fmt: skip
            with atomic_file(out / METRICS_FILE) as tmp:
                tmp.write_text(json.dumps(metrics, indent=2, allow_nan=False) + "\n")
            report.metrics = metrics
            report.files.append(out / METRICS_FILE)
        if options.report:
            figures = _report_plots(sinks.report, trajectory, sinks.evaluator, job)
            with atomic_file(out / REPORT_FILE) as tmp:
                write_report(tmp, metrics, figures, sinks.gallery_files, sinks.held_out_files)
            report.files += [out / REPORT_FILE, out / REPORT_DIR]
    # leaving the block renamed the temporary files and folders into place
    if sinks.h5 is not None:
        report.files += [out / UNCERTAINTY_FILE, out / "uncertainty"]
    if sinks.renders is not None:
        report.files.append(out / "renders")


def _evaluate_global_map(job: FinishedJob, store: FrameStore, frames: list[int],
                         sinks: _FrameSinks, lpips: Lpips | None,
                         progress: Callable[[int], None]) -> GlobalMapEvaluation:  # fmt: skip
    """The global map rendered at ``trajectory.txt``'s poses at input resolution on its
    held-out frames and on the keyframes; a gallery of held-out views for the report."""
    renderer = UncertaintyRenderer(job, store, 1, global_map=True)
    held_out = set(job.global_map.held_out_frames)
    evaluation = GlobalMapEvaluation(
        FrameEvaluator(lpips, with_ms_ssim=False),
        FrameEvaluator(lpips, with_ms_ssim=False, with_uncertainty=False))
    gallery = _gallery_frames(sorted(held_out)) if sinks.report is not None else set()
    for index in frames:
        item = renderer.frame(index)
        evaluation.size = (item.alpha.shape[1], item.alpha.shape[0])
        (evaluation.held_out if index in held_out else evaluation.keyframes).add(item)
        if index in gallery:
            path = sinks.report / f"held_out_{index:06d}.png"
            write_png(path, panel(item, sinks.scales))
            sinks.held_out_files.append((path, (
                f"held-out frame {index} (t = {item.timestamp:.3f} s), never trained on: the "
                "global map at trajectory.txt's pose, input resolution; colour (top) and depth "
                "(bottom): measured, rendered, error, variances")))  # fmt: skip
        progress(1)
    return evaluation


def _h5_attributes(job: FinishedJob, item: FrameUncertainty) -> dict[str, Any]:
    c = item.camera
    u = job.config.uncertainty
    return {
        "job": str(job.job_dir.resolve()),
        "store": str(job.store_path()),
        "width": item.alpha.shape[1],
        "height": item.alpha.shape[0],
        "downscale": item.downscale,
        "intrinsics": np.array([c.fx, c.fy, c.cx, c.cy]),
        "uncertainty": {
            "map_floor": u.map_floor,
            "unobserved_alpha": u.unobserved_alpha,
            "unobserved_variance": u.unobserved_variance,
            "sensor_min": u.sensor_min,
            "full_grad": u.full_grad,
        },
    }
