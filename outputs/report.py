"""``outputs/report.html``: one self-contained page (images base64-embedded) from metrics.json
and the report's PNGs, readable offline and sendable as a single file."""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path
from typing import Any


def _fmt(value: Any, digits: int = 4) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return html.escape(str(value))


def _table(rows: list[tuple[str, Any]], header: tuple[str, str] | None = None) -> str:
    head = f"<tr><th>{header[0]}</th><th>{header[1]}</th></tr>" if header else ""
    body = "".join(f"<tr><td>{html.escape(k)}</td><td>{_fmt(v)}</td></tr>" for k, v in rows)
    return f"<table>{head}{body}</table>"


def _image(path: Path, caption: str) -> str:
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return (f'<figure><img alt="{html.escape(caption)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")  # fmt: skip


def _ate_rows(ate: dict[str, Any]) -> list[tuple[str, Any]]:
    if not ate.get("available"):
        return [("ATE", f"not available: {ate.get('reason')}")]
    rows: list[tuple[str, Any]] = [("frames with ground truth", ate["frames"])]
    for alignment in ("rigid", "with_scale"):
        for key, value in ate[alignment].items():
            rows.append((f"ATE {key.replace('_cm', '')} ({alignment.replace('_', ' ')}) [cm]",
                         value))  # fmt: skip
    return rows


def _uncertainty_rows(unc: dict[str, Any] | None) -> list[tuple[str, Any]]:
    if unc is None:
        return [("AUSE", "not available: no evaluated frame has valid depth")]
    rows = [("frames", unc["frames"]),
            ("AUSE-MAE colour, raw", unc["ause_mae_color"]["ause_raw"]),
            ("AUSE-MAE colour, normalised", unc["ause_mae_color"]["ause_normalised"])]  # fmt: skip
    for name, result in unc["ause_mae_depth_by_variance"].items():
        rows.append((f"AUSE-MAE depth [m], {name}, raw", result["ause_raw"]))
        rows.append((f"AUSE-MAE depth, {name}, normalised", result["ause_normalised"]))
    return rows


def _run_rows(run: dict[str, Any]) -> list[tuple[str, Any]]:
    rows = [
        (key.replace("_", " "), run[key])
        for key in (
            "frames",
            "keyframes",
            "keyframe_share",
            "mapping_calls",
            "submaps",
            "seconds",
            "fps",
        )
    ]
    rows += [(f"keyframes: {reason}", count) for reason, count in run["keyframe_reasons"].items()]
    for stage, info in run["stages"].items():
        rows.append((f"{stage}: seconds (share)",
                     f"{info['seconds']:.2f} ({_fmt(info['share'], 3)})"))  # fmt: skip
        if info["ms_per_call"] is not None:
            rows.append((f"{stage}: ms per call", info["ms_per_call"]))
    return rows


RENDERING_LABELS = {
    "frames": "frames",
    "psnr_db": "PSNR [dB]",
    "ssim": "SSIM",
    "ms_ssim": "MS-SSIM",
    "depth_l1_cm": "depth L1 [cm]",
    "lpips": "LPIPS",
}

STYLE = """
body { font-family: sans-serif; margin: 2em auto; max-width: 1200px; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; }
td, th { border: 1px solid #ccc; padding: 3px 8px; text-align: left; font-size: 0.9em; }
figure { display: inline-block; margin: 0.5em; vertical-align: top; }
img { max-width: 100%; }
figcaption { font-size: 0.85em; color: #555; }
dt { font-weight: bold; margin-top: 0.5em; }
dd { margin-left: 1.5em; font-size: 0.9em; }
"""


def _rendering_rows(rendering: dict[str, Any]) -> list[tuple[str, Any]]:
    rows = [(label, rendering[key]) for key, label in RENDERING_LABELS.items()]
    if rendering.get("ms_ssim_note"):
        rows.append(("MS-SSIM note", rendering["ms_ssim_note"]))
    return rows


def _global_map_part(global_map: dict[str, Any], held_out: list[tuple[Path, str]]) -> list[str]:
    """The global map's section: its numbers on held-out frames and keyframes, side by side,
    and the held-out views."""
    res = global_map["resolution"]
    held, keys = global_map["held_out"]["rendering"], global_map["keyframes"]["rendering"]
    rows = "".join(f"<tr><td>{html.escape(label)}</td><td>{_fmt(held[key])}</td>"
                   f"<td>{_fmt(keys[key])}</td></tr>"
                   for key, label in RENDERING_LABELS.items())  # fmt: skip
    return [
        "<h2>Global map (global.ply)</h2>",
        f"<p>{global_map['gaussians']} Gaussians, rendered at the poses of trajectory.txt at "
        f"{res['width']}x{res['height']} (input resolution); held-out frames were never "
        f"trained on ({global_map['training_frames']} frames were).</p>",
        f"<table><tr><th></th><th>held-out frames</th><th>keyframes</th></tr>{rows}</table>",
        *(_image(p, caption) for p, caption in held_out),
    ]


def write_report(path: Path, metrics: dict[str, Any], plots: list[tuple[Path, str]],
                 gallery: list[tuple[Path, str]],
                 held_out: list[tuple[Path, str]] = ()) -> None:  # fmt: skip
    """Write the page: summary tables, the global map on held-out views, plots, gallery,
    conventions and the raw metrics."""
    render_rows = _rendering_rows(metrics["rendering"])
    res = metrics["resolution"]
    title = f"bgs-batch report: {Path(metrics['job']).name}"
    parts = [
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
        f"<style>{STYLE}</style></head><body><h1>{html.escape(title)}</h1>",
        _table([("job", metrics["job"]), ("store", metrics["store"]),
                ("created by", metrics["created_by"]),
                ("evaluated resolution", f"{res['width']}x{res['height']} (input / "
                                         f"{res['downscale']})")]),  # fmt: skip
        "<h2>Trajectory</h2>", _table(_ate_rows(metrics["ate"])),
        *_global_map_part(metrics["global_map"], list(held_out)),
        "<h2>Rendering (keyframes, each from its own submap)</h2>", _table(render_rows),
        "<h2>Uncertainty</h2>", _table(_uncertainty_rows(metrics["uncertainty"])),
        "<h2>Run</h2>", _table(_run_rows(metrics["run"])),
        "<h2>Plots</h2>", *(_image(p, caption) for p, caption in plots),
        "<h2>Uncertainty images</h2>", *(_image(p, caption) for p, caption in gallery),
        "<h2>Conventions</h2><dl>",
        *(f"<dt>{html.escape(k)}</dt><dd>{html.escape(v)}</dd>"
          for k, v in metrics["conventions"].items()),
        "</dl><h2>metrics.json</h2><pre>", html.escape(json.dumps(metrics, indent=1)),
        "</pre></body></html>\n",
    ]  # fmt: skip
    path.write_text("".join(parts), encoding="utf-8")
