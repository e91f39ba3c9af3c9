"""`bgs eval`: the metrics of a finished job, with every convention stated (docs/outputs.md).

`FrameEvaluator` collects per-frame rendering and uncertainty metrics from `FrameUncertainty`
items (the same renders as the uncertainty images, so nothing is rendered twice);
`evaluate_trajectory` aligns the estimate to the ground truth; `run_statistics` reads the run's
own counts and timings; `build_metrics` assembles ``metrics.json``.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from bgs_batch import __version__
from outputs.ause import (
    FRACTIONS,
    Sparsification,
    colour_sparsification,
    depth_sparsifications,
    mean_over_frames,
)
from outputs.image_metrics import MS_SSIM_MIN_SIDE, depth_l1, ms_ssim, psnr, ssim_index
from outputs.jobfiles import FinishedJob
from outputs.lpips import Lpips, lpips_distance
from outputs.trajectory import MIN_ALIGNED_FRAMES, align_to_ground_truth
from outputs.uncertainty import DEPTH_VARIANCES, FrameUncertainty

METRICS_SCHEMA = 1
CM_PER_M = 100.0

CONVENTIONS = {
    "ate": "Absolute trajectory error of camera positions over every frame with both an "
    "estimate and ground truth (matched by timestamp). 'rigid': Horn/Umeyama alignment of the "
    "estimate to GT with rotation and translation, no scale (as `evo_ape tum gt.tum "
    "estimate.tum -a`); 'with_scale': Sim(3) alignment (`-as`). RMSE, mean, median, max in cm.",
    "frames": "'rendering' and 'uncertainty' use the keyframes (frames the SLAM mapped), each "
    "rendered from its own submap (as saved at the end of the run) at the pose that submap was "
    "fitted at: the frame's tracked pose moved by its submap's loop-closure correction (the "
    "trajectory.txt pose may differ: it spreads the corrections along the frames and is "
    "smoothed).",
    "resolution": "'rendering' and 'uncertainty': images are rendered and compared at input "
    "resolution / downscale after the run's border crop; the measured frame is block-averaged "
    "to that resolution as the SLAM does (colour mean, depth mean of valid readings).",
    "global_map": "The global map (outputs/ply/global.ply, from global_map.pt) rendered at the "
    "poses of trajectory.txt at input resolution after the run's border crop, against the "
    "measured frames prepared as the run prepared them (rolling-shutter rows and depth moved "
    "to the frame's instant where the run did): 'held_out' are the frames the global stage "
    "held back from every optimisation (every global_map.hold_out_every-th frame that is not a "
    "keyframe; no keyframe is ever held out), 'keyframes' the frames the SLAM mapped (the "
    "stage trained on them). Metrics as for 'rendering' but MS-SSIM; AUSE on the held-out "
    "frames only, with Σ from the global map's refitted opacity variances and the run's "
    "sensor network.",
    "psnr": "10 log10(1/MSE) over all pixels and channels, colour in [0,1], rendered colour "
    "clamped to [0,1]; mean over frames (dB).",
    "ssim": "3DGS Gaussian-window SSIM (11x11, sigma 1.5); mean over frames.",
    "ms_ssim": "MS-SSIM (5 scales, pytorch-msssim weights); null when an image side is "
    f"<= {MS_SSIM_MIN_SIDE} px.",
    "depth_l1": "Mean |rendered - measured depth| over pixels with valid measured depth, per "
    "frame, then mean over frames (cm).",
    "lpips": "LPIPS v0.1 (alex or vgg, user-supplied weights), images in [0,1] mapped to "
    "[-1,1]; null unless --lpips-weights is given.",
    "ause": "AUSE-MAE per frame, then mean over frames. Elements: pixels with valid measured "
    "depth. Colour: error |C_render - C| averaged over channels vs the channel mean of Sigma_C; "
    "depth: |D_render - D| (m) vs Sigma_D. 100 fractions r = 0, 0.01, ..., 0.99: keep the "
    "floor((1 - r) N) elements of lowest uncertainty (stable sort) and, for the oracle, of "
    "lowest error; curve = MAE of the kept elements; AUSE = trapezoid of (curve - oracle) over "
    "r. 'raw': in the error's units (colour intensity in [0,1], depth m), no normalisation, as "
    "BayesianGS-SLAM reports; 'normalised': both curves divided by their largest value (Bayes' "
    "Rays). Rank-based: variance and std give the same AUSE.",
    "ause_depth_variances": "Depth AUSE of four uncertainties: predictive (Sigma_D = sensor + "
    "map term), map (map term only), sensor (sensor term only), varsplat (the map term of the "
    "colour variance, channel mean, reused for depth as VarSplat's depth NLL does).",
    "variance": "Sigma = sensor variance + map term; map term = rendered opacity-induced "
    "variance V (paper Eq. 3) + floor, or the unobserved variance where alpha < threshold "
    "(Eq. 10, 11); values from the run's config (see 'uncertainty_config').",
    "timing": "From summary.json: wall time of the whole run and seconds per stage. "
    "frames_per_second of a stage = frames / that stage's seconds; 'other' = total - stages "
    "(frame reading, logging, checkpoints).",
}


def json_safe(value: Any) -> Any:
    """`value` with every NaN/inf float (also in nested dicts and lists) replaced by None."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _finite(value: float) -> float | None:
    """JSON-safe: None for NaN/inf."""
    return float(value) if value is not None and math.isfinite(value) else None


def _mean(values: list[float | None]) -> float | None:
    kept = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(kept)) if kept else None


def _curves(result: Sparsification) -> dict[str, Any]:
    return {"ause_raw": result.ause_raw, "ause_normalised": result.ause_normalised,
            "oracle": [float(v) for v in result.oracle],
            "by_uncertainty": [float(v) for v in result.by_uncertainty]}  # fmt: skip


@dataclass
class FrameEvaluator:
    """Accumulates per-frame metrics of the evaluated frames (see `CONVENTIONS`)."""

    lpips: Lpips | None = None
    # the global map's blocks leave out MS-SSIM (its five blurs of a frame at input resolution
    # took a third of an export's time), and its keyframes the AUSE (held-out frames keep it)
    with_ms_ssim: bool = True
    with_uncertainty: bool = True
    rows: list[dict[str, Any]] = field(default_factory=list)
    colour: list[Sparsification] = field(default_factory=list)
    depth: dict[str, list[Sparsification]] = field(
        default_factory=lambda: {name: [] for name in DEPTH_VARIANCES}
    )

    def add(self, item: FrameUncertainty) -> None:
        rendered, target = torch.from_numpy(item.rendered_rgb), torch.from_numpy(item.measured_rgb)
        row: dict[str, Any] = {"frame": item.frame, "timestamp": item.timestamp}
        row["psnr_db"] = _finite(psnr(rendered, target))
        row["ssim"] = ssim_index(rendered, target)
        small = min(rendered.shape[:2]) <= MS_SSIM_MIN_SIDE
        row["ms_ssim"] = None if small or not self.with_ms_ssim else ms_ssim(rendered, target)
        l1 = depth_l1(torch.from_numpy(item.rendered_depth), torch.from_numpy(item.measured_depth))
        row["depth_l1_cm"] = _finite(l1 * CM_PER_M)
        row["lpips"] = None if self.lpips is None else lpips_distance(self.lpips, rendered, target)
        if self.with_uncertainty and item.valid.any():
            colour = colour_sparsification(
                item.rendered_rgb, item.measured_rgb, item.var_color[..., None], item.measured_depth
            )
            depth = depth_sparsifications(
                item.rendered_depth, item.measured_depth, item.depth_variances()
            )
            self.colour.append(colour)
            for name, result in depth.items():
                self.depth[name].append(result)
            row["ause_color_raw"] = colour.ause_raw
            row["ause_depth_raw"] = depth["predictive"].ause_raw
        self.rows.append(row)

    def rendering(self) -> dict[str, Any]:
        """Means over frames and the per-frame rows."""

        def mean(key: str) -> float | None:
            return _mean([row[key] for row in self.rows])

        return {
            "frames": len(self.rows),
            "psnr_db": mean("psnr_db"),
            "ssim": mean("ssim"),
            "ms_ssim": mean("ms_ssim"),
            "ms_ssim_note": None if mean("ms_ssim") is not None else
            f"images not larger than {MS_SSIM_MIN_SIDE} px on each side" if self.with_ms_ssim
            else "not computed for the global map",
            "depth_l1_cm": mean("depth_l1_cm"),
            "lpips": mean("lpips"),
            "lpips_net": None if self.lpips is None else self.lpips.net,
            "per_frame": self.rows,
        }  # fmt: skip

    def uncertainty(self) -> dict[str, Any] | None:
        """AUSE (raw and normalised) and mean sparsification curves; None without frames."""
        if not self.colour:
            return None
        depth = {name: _curves(mean_over_frames(results)) for name, results in self.depth.items()}
        return {
            "frames": len(self.colour),
            "fractions": [float(f) for f in FRACTIONS],
            "ause_mae_color": _curves(mean_over_frames(self.colour)),
            "ause_mae_depth": depth["predictive"],
            "ause_mae_depth_by_variance": depth,
        }

    def sparsification_means(self) -> tuple[Sparsification, dict[str, Sparsification]] | None:
        """Mean colour and per-variance depth results (for the plots)."""
        if not self.colour:
            return None
        return mean_over_frames(self.colour), {
            name: mean_over_frames(results) for name, results in self.depth.items()
        }


@dataclass
class GlobalMapEvaluation:
    """The global map's metrics on its held-out frames and on the keyframes (`CONVENTIONS`)."""

    held_out: FrameEvaluator
    keyframes: FrameEvaluator
    size: tuple[int, int] | None = None  # width, height of the images

    def as_dict(self, job: FinishedJob) -> dict[str, Any]:
        record = job.global_map
        return {
            "map": "outputs/ply/global.ply",
            "poses": "trajectory.txt",
            "resolution": {"downscale": 1, "width": None if self.size is None else self.size[0],
                           "height": None if self.size is None else self.size[1]},
            "gaussians": int(record.params["means"].shape[0]),
            "training_frames": len(record.training_frames),
            "held_out_frames": record.held_out_frames,
            "held_out": {"rendering": self.held_out.rendering(),
                         "uncertainty": self.held_out.uncertainty()},
            "keyframes": {"rendering": self.keyframes.rendering(),
                          "uncertainty": self.keyframes.uncertainty()},
        }  # fmt: skip


@dataclass(frozen=True)
class TrajectoryEvaluation:
    """The estimate and, with ground truth, its alignment and per-frame errors."""

    timestamps: np.ndarray  # (N,)
    estimate: np.ndarray  # (N, 4, 4)
    ground_truth: np.ndarray | None  # (N, 4, 4), NaN rows where unknown
    aligned: np.ndarray | None  # estimate after the rigid alignment
    errors_m: np.ndarray | None  # (N,) position error after rigid alignment, NaN without GT
    stats: dict[str, dict[str, float]]  # "rigid", "with_scale": ate() statistics (m)


def evaluate_trajectory(job: FinishedJob) -> TrajectoryEvaluation:
    """Align ``trajectory.txt`` to the store's ground truth (when there is one)."""
    timestamps, estimate = job.trajectory()
    gt = job.ground_truth(timestamps)
    if gt is None:
        return TrajectoryEvaluation(timestamps, estimate, None, None, None, {})
    alignment = align_to_ground_truth(estimate, gt)
    if alignment is None:
        return TrajectoryEvaluation(timestamps, estimate, gt, None, None, {})
    errors = np.linalg.norm(alignment.aligned[:, :3, 3] - gt[:, :3, 3], axis=1)
    errors[~alignment.rows] = np.nan
    return TrajectoryEvaluation(timestamps, estimate, gt, alignment.aligned, errors,
                                alignment.stats)  # fmt: skip


def _ate_section(evaluation: TrajectoryEvaluation) -> dict[str, Any]:
    if not evaluation.stats:
        reason = ("the frame store has no ground truth" if evaluation.ground_truth is None
                  else f"fewer than {MIN_ALIGNED_FRAMES} frames have ground truth")  # fmt: skip
        return {"available": False, "reason": reason}
    out: dict[str, Any] = {"available": True, "frames": evaluation.stats["rigid"]["frames"]}
    for alignment, stats in evaluation.stats.items():
        out[alignment] = {f"{k}_cm": stats[k] * CM_PER_M for k in ("rmse", "mean", "median", "max")}
    return out


def run_statistics(job: FinishedJob) -> dict[str, Any]:
    """Counts and timings of the run (summary.json and log.jsonl)."""
    summary, events = job.summary, job.events
    frames, seconds = int(summary["frames"]), float(summary["seconds"])
    stages = {k: float(v) for k, v in summary["stage_seconds"].items()}
    stages["other"] = max(seconds - sum(stages.values()), 0.0)
    calls = {"tracking": max(frames - 1, 0), "mapping": int(summary["mapping_calls"])}
    breakdown = {}
    for name, spent in stages.items():
        breakdown[name] = {
            "seconds": spent,
            "share": spent / seconds if seconds > 0 else None,
            "frames_per_second": frames / spent if spent > 0 else None,
            "ms_per_call": 1000 * spent / calls[name] if calls.get(name) else None,
        }
    reasons = Counter(e.reason for e in events if e.keyframe)
    return {
        "frames": frames,
        "keyframes": int(summary["keyframes"]),
        "keyframe_share": int(summary["keyframes"]) / frames if frames else None,
        "keyframe_reasons": dict(sorted(reasons.items())),
        "mapping_calls": int(summary["mapping_calls"]),
        "submaps": int(summary["submaps"]),
        "seconds": seconds,
        "fps": float(summary["fps"]),
        "stages": breakdown,
    }


def build_metrics(
    job: FinishedJob,
    trajectory: TrajectoryEvaluation,
    frames: FrameEvaluator,
    downscale: int,
    image_size: tuple[int, int] | None,
    global_map: GlobalMapEvaluation,
) -> dict[str, Any]:
    """The content of ``metrics.json`` (non-finite numbers, e.g. the scale of a degenerate
    trajectory, become null)."""
    cfg = job.config
    return json_safe(
        {
            "schema_version": METRICS_SCHEMA,
            "created_by": f"bgs-batch {__version__}",
            "job": str(job.job_dir.resolve()),
            "store": str(job.store_path()),
            "resolution": {
                "downscale": downscale,
                "mapping_downscale": cfg.mapping.downscale,
                "width": None if image_size is None else image_size[0],
                "height": None if image_size is None else image_size[1],
            },
            "ate": _ate_section(trajectory),
            "rendering": frames.rendering(),
            "uncertainty": frames.uncertainty(),
            "global_map": global_map.as_dict(job),
            "run": run_statistics(job),
            "uncertainty_config": {
                "map_floor": cfg.uncertainty.map_floor,
                "unobserved_alpha": cfg.uncertainty.unobserved_alpha,
                "unobserved_variance": cfg.uncertainty.unobserved_variance,
                "sensor_min": cfg.uncertainty.sensor_min,
                "full_grad": cfg.uncertainty.full_grad,
            },
            "keyframe_threshold": cfg.keyframes.threshold,
            "conventions": CONVENTIONS,
        }
    )
