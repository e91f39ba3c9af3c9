"""The validation suite: the `cpu` preset beside Open3D's dense SLAM on recordings nobody tunes on.

Usage: .venv/bin/python bench/validate.py [--seeds N] [--first-seed K] [--only NAME ...]
       [--set KEY=VALUE ...] [--max-frames N] [--keep DIR]

A change to tracking, mapping or a preset counts only when it holds here, on every sequence and
over seeds, not only on the dev excerpt it was tried on. The sequences:

- ``dev``: the 240-frame TUM fr1/rpy excerpt in ``../shared/data`` that the presets were tuned
  on, shown for reference (its numbers flatter the method);
- ``val-240``, ``val-420``: the real validation pieces of the same recording (frames 240-299 and
  420-479, ``../shared/data/tum_rgbd/validation/``), which no setting is ever tuned on;
- ``walk``, ``shake``, ``loop``, ``hard``: synthetic rooms from ``bgs synth`` with seeds no test
  or preset uses: a brisk walk, fr1/rpy-like roll/pitch/yaw shaking, a loop, and shaking with
  motion blur, a rolling shutter and large depth holes;
- ``rs-both``, ``rs-mixed``: one shaking room seen by a camera reading both images out over
  0.9 of a frame, and by one whose depth is taken at once beside its rolling colour (a
  RealSense D435), readouts known; ``reg``, ``misreg``: one handheld room seen by registered
  cameras, and by a colour camera 6 mm and 1.6° off the depth camera with a 3 % longer focal
  length (``bgs synth --misregister``); each pair's ATE ratio is printed, with the rigid and
  scale-aligned ATE;
- ``v240-auto``, ``v420-auto``, ``hard-auto``: those converted with ``--readout auto``, as a
  camera the converter does not know, so that the run estimates the readout from the frames;
  ``mix-auto``: ``rs-mixed`` with ``--readout auto --depth-readout 0``; ``v240-gs``,
  ``v420-gs``: converted as global shutters. A fifth table shows the estimates beside the
  known 30 ms and the ATE of the three runs of each recording, and the mixed room's ATE over
  the room read out alike.

Every sequence is converted with the defaults (what a user gets) and run with the `cpu` preset at
seeds K..K+N-1 (``--first-seed K``, ``--seeds N``; 0..2 by default) plus the ``--set`` overrides,
and once with Open3D's frame-to-model TSDF SLAM in a child process (`baseline.py`). Per sequence it
prints: the ATE of each seed and their mean, the ratio of the mean to Open3D's ATE, the
frame-to-frame error (RPE over one frame, translation, mean over seeds), the estimated path length
of the first seed beside the true one and Open3D's, CPU seconds per frame of bgs (all threads) and
of Open3D, bgs's frames per second end to end (the estimates from the first frames, SLAM, the
end-of-run stages and the default export `bgs run` ends with), its tracking seconds per frame,
median tracking iterations, and the share of frames whose start the warm start moved (registration
trusted), and the peak resident memory of a run's process (the largest over seeds). Each run has a
process of its own, as a user's `bgs run` does, so its ATE is the CLI's to the last digit (a job's
float rounding depends on what ran before it in a process). A second table ranks the uncertainty:
per sequence the depth AUSE-MAE (raw, m; `bgs eval`'s metrics on the keyframes, mean over seeds) of
the full predictive variance Σ_D and of its map and sensor parts and a VarSplat-style variance, the
colour AUSE, and at how many seeds the full variance ranks the depth errors best of the four, and,
on the synthetic sequences, whose true per-pixel noise σ `bgs synth` writes, the Spearman
correlation of the predicted sensor depth σ with it (`sigma_rank`). A third table scores the map a
user takes away: ``global.ply`` rendered at ``trajectory.txt``'s poses at input resolution on the
frames the global stage held out and on the keyframes, beside the submaps' keyframe PSNR, with the
stage's seconds and its share of the run. A fourth table breaks a run's time down by stage, end to
end. The SUMMARY line gives the mean ratio to Open3D over the real validation pieces and over the
synthetic sequences, the dev ratio, the slowest fps, the highest peak memory, the sequences where
the full variance was not the best at every seed, the smallest margin of the global map's held-out
PSNR over the submaps' keyframe PSNR, the largest share of a run the global stage took, and the
lowest Spearman correlation. ATEs are deterministic for a given seed; times depend on the machine's
load.
The numba kernels are compiled into their cache by `bgs_batch.warmup` before anything is timed; a
run's process loads them from there, as `bgs run` does.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import resource
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from baseline import open3d_dense_slam
from peak_memory import peak_rss_mb
from scipy.stats import spearmanr

from bgs_batch.config import ConfigError, load_config
from bgs_batch.metrics import ate, path_length, rpe
from bgs_batch.slam.frames import Level, downsample
from bgs_batch.store import READOUT_UNKNOWN, FrameStore
from bgs_batch.trajectory_files import read_tum
from bgs_batch.warmup import warm_up
from converters.synthetic import motion_config, read_depth_sigma, synthesize
from converters.tum import TumOptions, convert_tum
from jobs.run import LOG_FILE, RunSummary, run_job
from outputs.export import METRICS_FILE, RUN_DEFAULTS, ExportOptions, export_job
from outputs.jobfiles import FinishedJob
from outputs.uncertainty import DEPTH_VARIANCES, UncertaintyRenderer, select_frames

from status_page import recorded

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
TUM = SHARED_DATA / "tum_rgbd"
REAL = {  # name: TUM folder
    "dev": TUM / "rgbd_dataset_freiburg1_rpy",
    "val-240": TUM / "validation" / "rgbd_dataset_freiburg1_rpy_240_299",
    "val-420": TUM / "validation" / "rgbd_dataset_freiburg1_rpy_420_479",
}
VALIDATION_PIECES = ("val-240", "val-420")
SYNTHETIC_FRAMES = 90
SYNTHETIC_SIZE = (320, 240)
SYNTHETIC = {  # name: (motion, effects, loop, seed); seeds that no test, preset or demo uses
    "walk": ("walk", (), False, 7101),
    "shake": ("shake", (), False, 7202),
    "loop": ("handheld", (), True, 7303),
    "hard": ("shake", ("blur", "rolling_shutter", "holes"), False, 7404),
}
# Pairs of cameras in one room: a shaking room read out alike by both images, and by a camera
# whose depth is taken at once beside its rolling colour (a RealSense D435), readouts known; a
# handheld room seen by registered cameras, and by a colour camera 6 mm and 1.6° off the depth
# camera with a 3 % longer focal length, published with the depth camera's intrinsics
PAIRED_ROOMS = {
    "rs-both": ("shake", ("rolling_shutter",), False, 7505),
    "rs-mixed": ("shake", ("rolling_shutter", "global_shutter_depth"), False, 7505),
    "reg": ("handheld", (), False, 7606),
    "misreg": ("handheld", ("misregister",), False, 7606),
}
ROOMS = {**SYNTHETIC, **PAIRED_ROOMS}
# Sequences above converted as for a camera the converter does not know: the readout left to the
# run to estimate ("auto"; the D435-like room told only that its depth is a global shutter), or
# a global shutter ("gs", what `bgs convert` assumed before)
READOUT_VARIANTS = {  # name: (sequence, readout, depth readout (None: the same))
    "v240-auto": ("val-240", READOUT_UNKNOWN, None),
    "v420-auto": ("val-420", READOUT_UNKNOWN, None),
    "hard-auto": ("hard", READOUT_UNKNOWN, None),
    "mix-auto": ("rs-mixed", READOUT_UNKNOWN, 0.0),
    "v240-gs": ("val-240", 0.0, None),
    "v420-gs": ("val-420", 0.0, None),
}


@dataclass
class SequenceResult:
    """One sequence: Open3D's run and one bgs run per seed."""

    name: str
    frames: int
    true_length: float
    o3d_ate: float
    o3d_rpe: float
    o3d_length: float
    o3d_cpu_per_frame: float
    ates: list[float] = field(default_factory=list)
    scaled_ates: list[float] = field(default_factory=list)  # after a similarity alignment
    rpes: list[float] = field(default_factory=list)
    lengths: list[float] = field(default_factory=list)
    cpu_per_frame: list[float] = field(default_factory=list)
    fps: list[float] = field(default_factory=list)
    tracking_per_frame: list[float] = field(default_factory=list)
    median_iterations: list[float] = field(default_factory=list)
    registered: list[float] = field(default_factory=list)  # share of frames the warm start moved
    peak_rss_mb: list[float] = field(default_factory=list)  # of the run's own process
    ause_depth: list[dict[str, float]] = field(default_factory=list)  # per seed, per variance
    ause_color: list[float] = field(default_factory=list)
    sigma_rho: list[float] = field(default_factory=list)  # synthetic: per seed, see sigma_rank
    rendering: list[dict[str, float]] = field(default_factory=list)  # per seed, `rendering_scores`
    readouts: list[float | None] = field(default_factory=list)  # s, per seed, when estimated
    stages: list[dict[str, float]] = field(default_factory=list)  # per seed, `stage_times`

    @property
    def ratio(self) -> float:
        return statistics.mean(self.ates) / self.o3d_ate

    @property
    def full_variance_best(self) -> int:
        """Seeds at which the full predictive Σ_D has the lowest depth AUSE of the four."""
        return sum(min(seed, key=seed.get) == "predictive" for seed in self.ause_depth)


def make_stores(root: Path, only: list[str], max_frames: int | None) -> dict[str, Path]:
    """Convert every selected sequence (synthesising the synthetic ones first) with defaults,
    or only its first `max_frames` frames."""
    stores = {}
    for name, folder in REAL.items():
        if only and name not in only:
            continue
        if not (folder / "rgb.txt").is_file():
            sys.exit(f"bench/validate.py: no TUM folder at {folder} (../shared/data is needed)")
        stores[name] = convert_tum(folder, root / f"{name}.h5", TumOptions(max_frames=max_frames))
    for name in ROOMS:
        if only and name not in only:
            continue
        sequence = synthesize_room(root, name)
        stores[name] = convert_tum(sequence, root / f"{name}.h5", TumOptions(max_frames=max_frames))
    for name, (base, readout, depth_readout) in READOUT_VARIANTS.items():
        if only and name not in only:
            continue
        folder = REAL.get(base) or root / base
        if not (folder / "rgb.txt").is_file():  # a synthetic sequence not selected itself
            folder = synthesize_room(root, base)
        options = TumOptions(readout=readout, depth_readout=depth_readout, max_frames=max_frames)
        stores[name] = convert_tum(folder, root / f"{name}.h5", options)
    return stores


def synthesize_room(root: Path, name: str) -> Path:
    """The synthetic sequence `name` of `ROOMS`, rendered into ``root / name``."""
    motion, effects, loop, seed = ROOMS[name]
    width, height = SYNTHETIC_SIZE
    return synthesize(root / name, motion_config(motion, effects, frames=SYNTHETIC_FRAMES,
                                                 width=width, height=height, seed=seed,
                                                 loop=loop))  # fmt: skip


def run_sequence(name: str, store: Path, root: Path, seeds: range, overrides: list[str]
                 ) -> SequenceResult:  # fmt: skip
    """Open3D once and the cpu preset per seed on one store."""
    with FrameStore(store) as frames:
        n, gt = len(frames), frames.poses_gt
    o3d_poses, _, o3d_cpu = open3d_dense_slam(store, n)
    result = SequenceResult(
        name, n, path_length(gt[:, :3, 3]), ate(o3d_poses[:, :3, 3], gt[:, :3, 3])["rmse"],
        rpe(o3d_poses, gt)["translation_rmse"], path_length(o3d_poses[:, :3, 3]), o3d_cpu / n,
    )  # fmt: skip
    for seed in seeds:
        job = root / f"{name}_seed{seed}"
        run = run_in_child(store, job, [*overrides, f"seed={seed}"])
        summary = run.summary
        result.peak_rss_mb.append(run.peak_rss_mb)
        _, poses = read_tum(job / "trajectory.txt")
        events = [json.loads(line) for line in (job / LOG_FILE).read_text().splitlines()]
        result.ates.append(summary.ate_rmse_m)
        result.scaled_ates.append(ate(poses[:, :3, 3], gt[:, :3, 3], with_scale=True)["rmse"])
        result.rpes.append(rpe(poses, gt)["translation_rmse"])
        result.lengths.append(path_length(poses[:, :3, 3]))
        result.cpu_per_frame.append(run.cpu_seconds / n)
        result.fps.append(n / (summary.seconds + run.export_seconds))
        result.stages.append(stage_times(summary, run.export_seconds))
        result.tracking_per_frame.append(summary.stage_seconds["tracking"] / n)
        result.median_iterations.append(
            float(np.median([e["track_iterations"] for e in events if "track_iterations" in e]))
        )
        starts = [e["track_start"]["start"] for e in events if "track_start" in e]
        result.registered.append(starts.count("registration") / max(1, n - 1))
        metrics = evaluate(job, store)
        depth, colour = uncertainty_ranking(metrics)
        result.ause_depth.append(depth)
        result.ause_color.append(colour)
        result.rendering.append(rendering_scores(metrics, summary))
        if summary.readout is not None:
            result.readouts.append(summary.readout["seconds"])
        if name in ROOMS:
            result.sigma_rho.append(sigma_rank(job, store, root / name))
        print(f"  {name} seed {seed}: ATE {summary.ate_rmse_m * 100:.2f} cm, "
              f"{result.fps[-1]:.2f} fps end to end", flush=True)  # fmt: skip
    return result


def evaluate(job: Path, store: Path) -> dict:
    """``metrics.json`` of a finished job as `bgs eval --no-report` writes it."""
    only_metrics = ExportOptions(ply=False, trajectory=False, uncertainty=False, renders=False,
                                 report=False, store=store)  # fmt: skip
    export_job(job, only_metrics)
    return json.loads((job / "outputs" / METRICS_FILE).read_text())


def uncertainty_ranking(metrics: dict) -> tuple[dict[str, float], float]:
    """Depth AUSE-MAE per variance and colour AUSE-MAE (raw), at the run's mapping resolution."""
    ranking = metrics["uncertainty"]
    depth = {name: ranking["ause_mae_depth_by_variance"][name]["ause_raw"]
             for name in DEPTH_VARIANCES}  # fmt: skip
    return depth, ranking["ause_mae_color"]["ause_raw"]


def rendering_scores(metrics: dict, summary: RunSummary) -> dict[str, float]:
    """The global map's PSNR and SSIM on its held-out frames and PSNR on the keyframes (input
    resolution, at trajectory.txt's poses), the submaps' keyframe PSNR (`bgs eval`'s
    per-submap block, mapping resolution), and the global stage's seconds and share of the run."""
    held, keys = (metrics["global_map"][part]["rendering"] for part in ("held_out", "keyframes"))
    stage = summary.stage_seconds["global_map"]
    return {"held_out_frames": held["frames"], "held_out_psnr": held["psnr_db"],
            "held_out_ssim": held["ssim"], "global_keyframe_psnr": keys["psnr_db"],
            "submap_keyframe_psnr": metrics["rendering"]["psnr_db"], "stage_s": stage,
            "stage_share": stage / summary.seconds}  # fmt: skip


def sigma_rank(job: Path, store: Path, sequence: Path) -> float:
    """Spearman correlation of the predicted sensor depth σ with the σ of the noise `bgs synth`
    drew, per keyframe at the run's mapping resolution (the simulated σ cropped and block-
    averaged over valid readings as the depth is), mean over keyframes."""
    finished = FinishedJob(job, store)
    cfg = finished.config
    crop, factor = cfg.crop_edge or 0, cfg.mapping.downscale
    rhos = []
    with FrameStore(store) as frames:
        renderer = UncertaintyRenderer(finished, frames)
        for index in select_frames(finished):
            item = renderer.frame(index)
            simulated = read_depth_sigma(sequence, index)
            simulated = simulated[crop:-crop, crop:-crop] if crop else simulated
            blocks = Level(torch.zeros(*simulated.shape, 3), torch.from_numpy(simulated)[..., None],
                           item.camera)  # fmt: skip
            simulated = downsample(blocks, factor).depth[..., 0].numpy()
            valid = item.valid & (simulated > 0)
            predicted = np.sqrt(item.var_depth_sensor[valid])
            rhos.append(spearmanr(predicted, simulated[valid]).statistic)
    return float(np.mean(rhos))


@dataclass(frozen=True)
class ChildRun:
    """What a run measured in its own process."""

    summary: RunSummary
    export_seconds: float  # the default export that `bgs run` ends with
    cpu_seconds: float  # of the run and its export, all threads
    peak_rss_mb: float  # the process's peak resident set, its imports included


def run_in_child(store: Path, job: Path, overrides: list[str]) -> ChildRun:
    """One `cpu`-preset run in a fresh process, as `bgs run` does it: a job's last float bits
    depend on what ran before it in a process (docs/development.md), so each run starts from
    nothing and the bench reports the numbers a user's `bgs run` gets."""
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        return pool.apply(_run, (store, job, overrides))


def _run(store: Path, job: Path, overrides: list[str]) -> ChildRun:
    before = resource.getrusage(resource.RUSAGE_SELF)
    summary = run_job(store, job, load_config("cpu", overrides))
    start = time.perf_counter()
    export_job(job, RUN_DEFAULTS)
    export_seconds = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_SELF)
    cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    return ChildRun(summary, export_seconds, cpu, peak_rss_mb())


def print_header(header: str) -> None:
    """A table's column header and the rule under it."""
    print(header)
    print("-" * len(header))


def print_table(results: list[SequenceResult], seeds: range) -> None:
    seed_columns = "".join(f"{f'seed {s}':>8}" for s in seeds)
    header = (f"{'sequence':<9}{'frames':>7}{'Open3D':>8}{seed_columns}{'mean':>8}{'ratio':>7}"
              f"{'RPE bgs':>9}{'RPE O3D':>9}{'path bgs/true/O3D m':>21}{'cpu s/f':>9}"
              f"{'O3D':>6}{'fps':>6}{'track s/f':>10}{'iters':>6}{'warm':>6}"
              f"{'peak MB':>9}")  # fmt: skip
    print("ATE and RPE (1 frame, translation) in cm; ratio = mean ATE / Open3D's ATE")
    print_header(header)
    for r in results:
        ates = "".join(f"{a * 100:>8.2f}" for a in r.ates)
        lengths = f"{r.lengths[0]:.2f}/{r.true_length:.2f}/{r.o3d_length:.2f}"
        print(f"{r.name:<9}{r.frames:>7}{r.o3d_ate * 100:>8.2f}{ates}"
              f"{statistics.mean(r.ates) * 100:>8.2f}{r.ratio:>7.2f}"
              f"{statistics.mean(r.rpes) * 100:>9.2f}{r.o3d_rpe * 100:>9.2f}{lengths:>21}"
              f"{statistics.mean(r.cpu_per_frame):>9.2f}{r.o3d_cpu_per_frame:>6.2f}"
              f"{statistics.mean(r.fps):>6.2f}{statistics.mean(r.tracking_per_frame):>10.2f}"
              f"{statistics.median(r.median_iterations):>6.0f}"
              f"{statistics.mean(r.registered):>6.0%}{max(r.peak_rss_mb):>9.0f}")  # fmt: skip
    print()
    print("Depth AUSE-MAE (raw, m, mean over seeds) of each variance; colour AUSE of Σ_C; "
          "best = seeds at which the full Σ_D ranks depth errors best of the four; ρ σ_D = "
          "Spearman correlation of the predicted sensor depth σ with the simulated one "
          "(synthetic only)")  # fmt: skip
    header = (f"{'sequence':<9}" + "".join(f"{name:>12}" for name in DEPTH_VARIANCES)
              + f"{'colour':>10}{'best':>7}{'ρ σ_D':>8}")  # fmt: skip
    print_header(header)
    for r in results:
        means = "".join(f"{statistics.mean(seed[name] for seed in r.ause_depth):>12.4f}"
                        for name in DEPTH_VARIANCES)  # fmt: skip
        rho = f"{statistics.mean(r.sigma_rho):.2f}" if r.sigma_rho else "-"
        print(f"{r.name:<9}{means}{statistics.mean(r.ause_color):>10.4f}"
              f"{f'{r.full_variance_best}/{len(r.ause_depth)}':>7}{rho:>8}")  # fmt: skip


RENDERING_COLUMNS = (  # key, header, format
    ("held_out_frames", "held", ">6.0f"), ("held_out_psnr", "PSNR", ">8.2f"),
    ("held_out_ssim", "SSIM", ">7.3f"), ("global_keyframe_psnr", "kf PSNR", ">9.2f"),
    ("submap_keyframe_psnr", "submap kf", ">11.2f"), ("stage_s", "stage s", ">9.1f"),
    ("stage_share", "share", ">7.0%"),
)  # fmt: skip


def print_rendering_table(results: list[SequenceResult]) -> None:
    print()
    print("Global map (outputs/ply/global.ply) rendered at trajectory.txt's poses at input "
          "resolution, mean over seeds: on its held-out frames (never trained on) and on the "
          "keyframes; submap kf = each keyframe from its own submap at mapping resolution (the "
          "per-submap block of `bgs eval`); the global stage's seconds and share of the run. "
          "The stage does not move the poses: the ATE above is the ATE before and after it.")
    header = f"{'sequence':<9}" + "".join(f"{h:>{f[1:].split('.')[0]}}"
                                        for _, h, f in RENDERING_COLUMNS)  # fmt: skip
    print_header(header)
    for r in results:
        cells = "".join(format(_mean_of(r.rendering, key), fmt)
                        for key, _, fmt in RENDERING_COLUMNS)  # fmt: skip
        print(f"{r.name:<9}{cells}")


STAGES = ("estimates", "tracking", "mapping", "loop_closure", "refinement", "global_map")
"""The stages of `summary.json` that the breakdown shows, in the order a run meets them."""


def stage_times(summary: RunSummary, export_seconds: float) -> dict[str, float]:
    """Seconds of a run end to end by stage: the run's own stages (`STAGES`; the sensor
    network, submap switches and the rest under ``other``) and the default export."""
    times = {stage: summary.stage_seconds.get(stage, 0.0) for stage in STAGES}
    times["other"] = max(0.0, summary.seconds - sum(times.values()))
    times["export"] = export_seconds
    return times


def print_stage_table(results: list[SequenceResult]) -> None:
    print()
    print("Where a run's time goes end to end, s/frame (mean over seeds): the readout and colour "
          "offset estimated from the first frames, tracking, mapping, loop closure, the "
          "end-of-run refinement, the global stage, the rest of the run (sensor network, submap "
          "switches, reading frames) and the default export; fps = frames / their sum")
    names = [*STAGES, "other", "export"]
    labels = {"loop_closure": "loops", "global_map": "global"}
    header = (f"{'sequence':<9}" + "".join(f"{labels.get(name, name):>11}" for name in names)
              + f"{'fps':>7}")  # fmt: skip
    print_header(header)
    for r in results:
        cells = "".join(f"{_mean_of(r.stages, name) / r.frames:>11.3f}" for name in names)
        print(f"{r.name:<9}{cells}{statistics.mean(r.fps):>7.2f}")


def print_readout_table(results: list[SequenceResult]) -> None:
    by_name = {r.name: r for r in results}
    global_shutter = {base: by_name.get(name) for name, (base, readout, _) in
                      READOUT_VARIANTS.items() if readout == 0}  # fmt: skip
    rows = [(r, by_name.get(READOUT_VARIANTS[r.name][0]),
             global_shutter.get(READOUT_VARIANTS[r.name][0]))
            for r in results if r.name in READOUT_VARIANTS and r.readouts]  # fmt: skip
    for pair in PAIRS:
        if all(name in by_name for name in pair):
            print()
            print(pair_line(by_name, *pair))
    if not rows:
        return
    print()
    print("Readout estimated by the run from the frames (store converted with --readout auto) "
          "beside the recording's known readout (30 ms); ATE mean over seeds (cm) of the run "
          "that estimated it, of the run that knew it, and of a global-shutter run")
    header = (f"{'sequence':<10}{'estimate ms':>12}{'error':>8}{'ATE auto':>10}{'known':>8}"
              f"{'auto/known':>11}{'global':>8}")  # fmt: skip
    print_header(header)
    for r, known, global_run in rows:
        estimate = readout_ms(r)
        error = f"{estimate / 30 - 1:+.0%}" if estimate == estimate else "-"
        known_ate = statistics.mean(known.ates) * 100 if known else float("nan")
        gs = statistics.mean(global_run.ates) * 100 if global_run else float("nan")
        auto = statistics.mean(r.ates) * 100
        print(f"{r.name:<10}{estimate:>12.1f}{error:>8}{auto:>10.2f}{known_ate:>8.2f}"
              f"{auto / known_ate:>11.2f}{gs:>8.2f}")  # fmt: skip


PAIRS = (("rs-mixed", "rs-both"), ("misreg", "reg"))


def pair_ratio(by_name: dict[str, SequenceResult], name: str, reference: str) -> float:
    """Mean ATE of `name` over the mean ATE of the same room's `reference` camera."""
    return statistics.mean(by_name[name].ates) / statistics.mean(by_name[reference].ates)


def pair_line(by_name: dict[str, SequenceResult], name: str, reference: str) -> str:
    r = by_name[name]
    return (f"{name}: ATE {pair_ratio(by_name, name, reference):.2f}x {reference}'s (same room); "
            f"rigid {statistics.mean(r.ates) * 100:.2f} cm, scale-aligned "
            f"{statistics.mean(r.scaled_ates) * 100:.2f} cm")


def readout_ms(result: SequenceResult) -> float:
    """The mean estimate over seeds in ms (NaN when no seed could estimate it)."""
    found = [x for x in result.readouts if x is not None]
    return 1000 * statistics.mean(found) if found else float("nan")


def _mean_of(rows: list[dict[str, float]], key: str) -> float:
    values = [row[key] for row in rows if row[key] is not None]
    return statistics.mean(values) if values else float("nan")


def summary_line(results: list[SequenceResult]) -> str:
    by_name = {r.name: r for r in results}
    parts = []
    pieces = [by_name[n].ratio for n in VALIDATION_PIECES if n in by_name]
    if pieces:
        parts.append(f"real validation ATE/Open3D mean {statistics.mean(pieces):.2f}x "
                     f"(worst {max(pieces):.2f}x)")  # fmt: skip
    synthetic = [by_name[n].ratio for n in SYNTHETIC if n in by_name]
    if synthetic:
        parts.append(f"synthetic mean {statistics.mean(synthetic):.2f}x "
                     f"(worst {max(synthetic):.2f}x)")  # fmt: skip
    if "dev" in by_name:
        parts.append(f"dev {by_name['dev'].ratio:.2f}x")
    slowest = min(results, key=lambda r: statistics.mean(r.fps))
    parts.append(f"slowest {statistics.mean(slowest.fps):.2f} fps ({slowest.name})")
    parts.append(f"peak RSS {max(max(r.peak_rss_mb) for r in results):.0f} MB")
    behind = [r.name for r in results if r.full_variance_best < len(r.ause_depth)]
    parts.append("full Σ_D ranks depth best at every seed " + (
        "on every sequence" if not behind else f"except on {', '.join(behind)}"))  # fmt: skip
    margins = {r.name: _mean_of(r.rendering, "held_out_psnr")
               - _mean_of(r.rendering, "submap_keyframe_psnr") for r in results}  # fmt: skip
    worst = min(margins, key=margins.get)
    parts.append(f"global map held-out PSNR − submap keyframe PSNR ≥ {margins[worst]:+.2f} dB "
                 f"({worst})")  # fmt: skip
    costliest = max(results, key=lambda r: _mean_of(r.rendering, "stage_share"))
    parts.append(f"global stage ≤ {_mean_of(costliest.rendering, 'stage_share'):.0%} of a run "
                 f"({costliest.name})")  # fmt: skip
    estimates = {r.name: readout_ms(r) for r in results if r.name in READOUT_VARIANTS
                 and r.readouts}  # fmt: skip
    missing = [name for name, ms in estimates.items() if math.isnan(ms)]
    found = {name: ms for name, ms in estimates.items() if not math.isnan(ms)}
    if found:
        worst = max(found, key=lambda n: abs(found[n] / 30 - 1))
        parts.append(f"readout estimated within {abs(found[worst] / 30 - 1):.0%} of 30 ms "
                     f"({worst})")  # fmt: skip
    if missing:
        parts.append(f"readout not estimated on {', '.join(missing)}")
    parts += [f"{name} {pair_ratio(by_name, name, reference):.2f}x {reference}"
              for name, reference in PAIRS if name in by_name and reference in by_name]
    rhos = {r.name: min(r.sigma_rho) for r in results if r.sigma_rho}
    if rhos:
        worst = min(rhos, key=rhos.get)
        parts.append(f"sensor σ_D vs simulated: Spearman ≥ {rhos[worst]:.2f} ({worst})")
    return "SUMMARY cpu preset: " + "; ".join(parts)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3, help="cpu-preset seeds: this many")
    parser.add_argument("--first-seed", type=int, default=0, metavar="K",
                        help="start at seed K (more seeds for a paired comparison)")  # fmt: skip
    parser.add_argument("--only", nargs="+", default=[],
                        choices=[*REAL, *ROOMS, *READOUT_VARIANTS],
                        metavar="NAME", help="run only these sequences")  # fmt: skip
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE", help="settings to validate (repeatable)")  # fmt: skip
    parser.add_argument("--max-frames", type=int, help="only the first N frames (quick trials)")
    parser.add_argument("--keep", type=Path, metavar="DIR",
                        help="keep the stores and jobs in DIR, a new folder")  # fmt: skip
    args = parser.parse_args()
    if args.seeds < 1 or args.first_seed < 0:
        sys.exit("bench/validate.py: --seeds must be at least 1 and --first-seed at least 0")
    if args.keep and args.keep.exists() and any(args.keep.iterdir()):
        sys.exit(f"bench/validate.py: {args.keep} is not empty (--keep needs a new folder)")
    try:  # a bad override fails now, not after the first runs
        load_config("cpu", args.overrides)
    except ConfigError as err:
        sys.exit(f"bench/validate.py: {err}")
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    settings = " ".join(f"--set {o}" for o in args.overrides) or "no overrides"
    print(f"bench/validate.py: cpu preset ({settings}), seeds {seeds[0]}-{seeds[-1]}, beside "
          "Open3D's dense SLAM (TSDF 1 cm)", flush=True)  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        # a cold numba cache (a fresh worktree) would charge the JIT to the first run's speed
        print(f"  kernels compiled or loaded in {warm_up(root / 'warmup'):.0f} s (not timed)",
              flush=True)  # fmt: skip
        stores = make_stores(root, args.only, args.max_frames)
        results = [run_sequence(name, store, root, seeds, args.overrides)
                   for name, store in stores.items()]  # fmt: skip
    print()
    print_table(results, seeds)
    print_rendering_table(results)
    print_stage_table(results)
    print_readout_table(results)
    print(summary_line(results))


if __name__ == "__main__":
    with recorded("validate"):
        main()
