"""What `bgs inspect` reports about a frame store: size, timing, depth validity, GT, camera."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from bgs_batch.store import FrameStore, same_readout

_PINHOLE = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}


@dataclass(frozen=True)
class StoreSummary:
    path: str
    frames: int
    width: int
    height: int
    duration_s: float
    fps: float
    depth_valid_percent: float
    depth_min_m: float
    depth_median_m: float
    depth_max_m: float
    gt_coverage_percent: float | None  # None: the store has no ground truth
    intrinsics: dict[str, float]
    depth_scale: float
    distortion: list[float]
    distortion_applied: bool
    crop_edge: int  # recommended border crop, pixels per side (`bgs run` applies it)
    rolling_shutter_readout: float  # s over which the rows are read out (0: global shutter)
    depth_rolling_shutter_readout: float  # the depth image's (the same unless its sensor differs)
    depth_registered: bool  # registered to colour with the cameras' calibration
    source_format: str
    source_path: str
    sequence: str
    created_by: str
    provenance: dict[str, Any]

    def as_dict(self) -> dict[str, Any]:
        """For JSON: an unknown readout (NaN in the store) is null."""
        data = asdict(self)
        for key in ("rolling_shutter_readout", "depth_rolling_shutter_readout"):
            if math.isnan(data[key]):
                data[key] = None
        return data


def summarize(store: FrameStore) -> StoreSummary:
    """Scan every frame's depth (streamed) and collect the store's facts."""
    n = len(store)
    valid = 0
    lo, hi = np.inf, 0.0
    medians = []
    for frame in store.frames():
        depth = frame.depth[frame.depth > 0]
        valid += depth.size
        if depth.size:
            lo, hi = min(lo, float(depth.min())), max(hi, float(depth.max()))
            medians.append(float(np.median(depth)))
    duration = float(store.timestamps[-1] - store.timestamps[0])
    k = store.intrinsics
    gt = None
    if store.has_gt:
        gt = 100.0 * float(np.all(np.isfinite(store.poses_gt), axis=(1, 2)).mean())
    a = store.attrs
    return StoreSummary(
        path=str(store.path),
        frames=n,
        width=store.width,
        height=store.height,
        duration_s=duration,
        fps=(n - 1) / duration if duration > 0 else 0.0,
        depth_valid_percent=100.0 * valid / (n * store.width * store.height),
        depth_min_m=lo if valid else 0.0,
        depth_median_m=float(np.median(medians)) if medians else 0.0,
        depth_max_m=hi,
        gt_coverage_percent=gt,
        intrinsics={name: float(k[i, j]) for name, (i, j) in _PINHOLE.items()},
        depth_scale=store.depth_scale,
        distortion=[float(x) for x in np.atleast_1d(a["distortion"])],
        distortion_applied=bool(a["distortion_applied"]),
        crop_edge=store.crop_edge,
        rolling_shutter_readout=store.rolling_shutter_readout,
        depth_rolling_shutter_readout=store.depth_rolling_shutter_readout,
        depth_registered=store.depth_registered,
        source_format=str(a["source_format"]),
        source_path=str(a["source_path"]),
        sequence=str(a["sequence"]),
        created_by=str(a["created_by"]),
        provenance=store.provenance,
    )


def print_summary(summary: StoreSummary, console: Console | None = None) -> None:
    """Render a summary as a two-column table, provenance last."""
    s = summary
    table = Table(title=f"frame store {s.path}", show_header=False, title_justify="left")
    table.add_column(style="bold")
    table.add_column()
    gt = "none" if s.gt_coverage_percent is None else f"{s.gt_coverage_percent:.1f} % of frames"
    k = s.intrinsics
    rows = {
        "sequence": f"{s.sequence} ({s.source_format}, from {s.source_path})",
        "frames": f"{s.frames} at {s.width}x{s.height}",
        "duration": f"{s.duration_s:.2f} s ({s.fps:.1f} fps)",
        "depth": f"{s.depth_valid_percent:.1f} % valid, {s.depth_min_m:.2f} / "
        f"{s.depth_median_m:.2f} / {s.depth_max_m:.2f} m (min / median / max), "
        f"scale {s.depth_scale:g} per m",
        "ground truth": gt,
        "intrinsics": f"fx {k['fx']:.2f}  fy {k['fy']:.2f}  cx {k['cx']:.2f}  cy {k['cy']:.2f}",
        "distortion": " ".join(f"{x:g}" for x in s.distortion)
        + (" (applied: images undistorted)" if s.distortion_applied else " (not applied)"),
        "crop": (f"{s.crop_edge} px per border, applied by `bgs run` (--set crop_edge=N "
                 "overrides)" if s.crop_edge else "none recommended"),
        "shutter": _shutter(s.rolling_shutter_readout),
        **({"depth shutter": _shutter(s.depth_rolling_shutter_readout).replace(
            "rolling_shutter_readout", "depth_rolling_shutter_readout")}
           if not same_readout(s.depth_rolling_shutter_readout, s.rolling_shutter_readout)
           else {}),  # fmt: skip
        "depth registered": ("to colour, with the cameras' calibration" if s.depth_registered
                             else "not known: the `cpu` preset estimates the colour camera's "
                             "offset from the frames"),  # fmt: skip
        "created by": s.created_by,
    }
    rows |= {f"  {key}": str(value) for key, value in sorted(s.provenance.items())}
    for key, value in rows.items():
        table.add_row(key, value)
    (console or Console()).print(table)
    (console or Console()).print("[green]valid[/green] (schema v1)")


def _shutter(readout: float) -> str:
    if math.isnan(readout):
        return ("unknown: `bgs run` estimates the readout from the frames (--set "
                "rolling_shutter_readout=S sets it)")
    if readout:
        return (f"rolling, rows read out over {1000 * readout:.1f} ms; the `cpu` preset moves "
                "them to one instant (--set rolling_shutter_readout=S overrides)")
    return "global"
