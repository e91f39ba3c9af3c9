"""The report's plots (matplotlib, Agg, no global pyplot state): each function writes one PNG.

PNG metadata carries no software version or date, so the same inputs give the same bytes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from outputs.ause import FRACTIONS, Sparsification
from outputs.jobfiles import FrameEvent

DPI = 110
WIDE = (9.0, 3.6)  # inches
SQUARE = (6.0, 5.2)
TALL = (9.0, 6.4)
AXES = "xyz"
REASON_COLOURS = {
    "first-of-submap": "tab:purple",
    "surprise-color": "tab:red",
    "surprise-depth": "tab:blue",
    "fallback": "tab:gray",
    "every": "tab:green",
}
SYMLOG_LINEAR_WIDTH = 1.0  # surprise scores are sums over pixels: symlog shows both signs
CM_PER_M = 100.0


MARGINS = {"left": 0.11, "right": 0.97, "bottom": 0.13, "top": 0.91, "wspace": 0.3, "hspace": 0.3}
LEGEND = {"loc": "upper right", "fontsize": 7}  # fixed places: "best" costs a search per plot


def _save(fig: Figure, path: Path) -> Path:
    fig.subplots_adjust(**MARGINS)  # fixed margins: tight_layout would double the drawing time
    fig.savefig(path, dpi=DPI, metadata={"Software": None})
    return path


def top_view_axes(positions: np.ndarray) -> tuple[int, int]:
    """The two coordinate axes along which `positions` (N,3) spread most (finite rows)."""
    finite = positions[np.all(np.isfinite(positions), axis=1)]
    extent = np.ptp(finite, axis=0) if len(finite) else np.zeros(3)
    first, second = sorted(np.argsort(-extent, kind="stable")[:2])
    return int(first), int(second)


def trajectory_top(path: Path, estimate: np.ndarray, gt: np.ndarray | None) -> Path:
    """Top view: positions (N,3) of the (aligned) estimate and the GT on their widest plane."""
    fig = Figure(figsize=SQUARE)
    ax = fig.add_subplot()
    a, b = top_view_axes(gt if gt is not None else estimate)
    if gt is not None:
        ax.plot(gt[:, a], gt[:, b], color="k", lw=1.5, label="ground truth")
    ax.plot(estimate[:, a], estimate[:, b], color="tab:orange", lw=1.2,
            label="estimate (aligned)" if gt is not None else "estimate")  # fmt: skip
    ax.plot(*estimate[0, [a, b]], "o", color="tab:orange", ms=5, label="start")
    ax.set_xlabel(f"{AXES[a]} [m]")
    ax.set_ylabel(f"{AXES[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(**LEGEND)
    ax.set_title("trajectory, top view" + (" (GT frame)" if gt is not None else ""))
    return _save(fig, path)


def trajectory_axes(path: Path, times: np.ndarray, estimate: np.ndarray, gt: np.ndarray | None
                    ) -> Path:  # fmt: skip
    """x, y, z of the (aligned) estimate and the GT over time."""
    fig = Figure(figsize=TALL)
    t = times - times[0]
    for k in range(3):
        ax = fig.add_subplot(3, 1, k + 1)
        if gt is not None:
            ax.plot(t, gt[:, k], color="k", lw=1.2, label="ground truth")
        label = "estimate (aligned)" if gt is not None else "estimate"
        ax.plot(t, estimate[:, k], color="tab:orange", lw=1.0, label=label)
        ax.set_ylabel(f"{AXES[k]} [m]")
        ax.grid(alpha=0.3)
        if k == 0:
            ax.legend(**LEGEND)
    ax.set_xlabel("time [s]")
    return _save(fig, path)


def ate_over_time(path: Path, times: np.ndarray, errors_m: np.ndarray, rmse_m: float) -> Path:
    """Per-frame position error after rigid alignment, with the RMSE."""
    fig = Figure(figsize=WIDE)
    ax = fig.add_subplot()
    t = times - times[0]
    ax.plot(t, errors_m * CM_PER_M, color="tab:red", lw=1.0, label="error")
    ax.axhline(rmse_m * CM_PER_M, color="k", ls="--", lw=1.0,
               label=f"RMSE {rmse_m * CM_PER_M:.2f} cm")  # fmt: skip
    ax.set_xlabel("time [s]")
    ax.set_ylabel("position error [cm]")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(**LEGEND)
    ax.set_title("ATE over time (rigid alignment)")
    return _save(fig, path)


def sparsification(path: Path, title: str, units: str, curves: dict[str, Sparsification]
                   ) -> Path:  # fmt: skip
    """Mean sparsification curves: the oracle (of the first entry) and one curve per entry."""
    fig = Figure(figsize=SQUARE)
    ax = fig.add_subplot()
    first = next(iter(curves.values()))
    ax.plot(FRACTIONS, first.oracle, color="k", lw=1.5, ls="--", label="oracle")
    for name, result in curves.items():
        ax.plot(
            FRACTIONS,
            result.by_uncertainty,
            lw=1.2,
            label=f"{name} (AUSE {result.ause_raw:.4g}, norm. {result.ause_normalised:.3f})",
        )
    ax.set_xlabel("fraction of pixels removed (highest uncertainty first)")
    ax.set_ylabel(f"MAE of remaining pixels [{units}]")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(**LEGEND)
    ax.set_title(title)
    return _save(fig, path)


def keyframe_timeline(path: Path, events: list[FrameEvent], threshold: float) -> Path:
    """Surprise scores S_C, S_D per frame, the threshold K and the keyframes by reason."""
    fig = Figure(figsize=WIDE)
    ax = fig.add_subplot()
    frames = np.array([e.frame for e in events])
    for attribute, label, colour in (("score_color", "S_C", "tab:red"),
                                     ("score_depth", "S_D", "tab:blue")):  # fmt: skip
        values = np.array([np.nan if getattr(e, attribute) is None else getattr(e, attribute)
                           for e in events], dtype=float)  # fmt: skip
        ax.plot(frames, values, color=colour, lw=1.0, label=label)
    ax.axhline(threshold, color="k", ls="--", lw=1.0, label=f"threshold K = {threshold:g}")
    ax.set_yscale("symlog", linthresh=SYMLOG_LINEAR_WIDTH)
    for reason, colour in REASON_COLOURS.items():
        marked = [e.frame for e in events if e.keyframe and e.reason == reason]
        if marked:
            ax.plot(marked, np.full(len(marked), threshold), "|", color=colour, ms=14, mew=2,
                    label=f"keyframe: {reason} ({len(marked)})")  # fmt: skip
    ax.set_xlabel("frame")
    ax.set_ylabel("predictive surprise (symlog)")
    ax.grid(alpha=0.3)
    ax.legend(ncol=2, **LEGEND)
    ax.set_title("keyframe selection (paper Eq. 9)")
    return _save(fig, path)


def timing(path: Path, stages: dict[str, float], events: list[FrameEvent]) -> Path:
    """Seconds per stage (bar) and wall time per frame (from log.jsonl's elapsed times)."""
    fig = Figure(figsize=WIDE)
    bars, line = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    names = list(stages)
    bars.barh(names, [stages[n] for n in names], color="tab:blue")
    bars.invert_yaxis()
    bars.set_xlabel("seconds")
    bars.set_title("time per stage (whole run)")
    elapsed = np.array([np.nan if e.elapsed_s is None else e.elapsed_s for e in events])
    per_frame = np.diff(np.concatenate([[0.0], elapsed]))
    frames = np.array([e.frame for e in events])
    line.plot(frames, per_frame, color="k", lw=0.8, label="all frames")
    key = np.array([e.keyframe for e in events])
    line.plot(frames[key], per_frame[key], "o", color="tab:red", ms=3, label="keyframes")
    line.set_xlabel("frame")
    line.set_ylabel("seconds")
    line.set_ylim(bottom=0)
    line.grid(alpha=0.3)
    line.legend(**LEGEND)
    line.set_title("wall time per frame")
    return _save(fig, path)
