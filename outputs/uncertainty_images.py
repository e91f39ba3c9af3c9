"""PNG images of a `FrameUncertainty`: colour-mapped variances and residuals, renders, panels.

Files (``{frame}`` is the zero-padded frame index)::

    uncertainty/<quantity>/{frame}.png   one colour-mapped image with its colour bar per quantity
    renders/rgb/{frame}.png              rendered colour, 8-bit RGB
    renders/depth/{frame}.png            rendered depth, 16-bit, RENDER_DEPTH_SCALE units per m

Colour variances (Σ_C and its two terms) share one log10 scale, depth variances another: whole
decades around the 1st-99th percentile of the observed pixels (alpha at or above the
"unobserved" threshold) of the first frame exported, then fixed for the whole export, so the
images of one export compare directly; values beyond the ends are clipped (the bar says so; the
"unobserved" pixels, whose variance is the large fill value, show at the top). Residuals use
fixed linear scales (`COLOR_ERROR_RANGE`, `DEPTH_ERROR_RANGE_M`). Invalid depth is grey.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from bgs_batch.config import UncertaintyConfig
from outputs.colormap import (
    DEPTH_MAP,
    ERROR_MAP,
    VARIANCE_MAP,
    Scale,
    colorize,
    grid,
    rgb_to_bgr8,
    tile,
    write_png,
)
from outputs.uncertainty import FrameUncertainty

COLOR_ERROR_RANGE = 0.25  # |ΔC| (intensity in [0,1]) at the top of the colour-error bar
DEPTH_ERROR_RANGE_M = 0.10  # |ΔD| at the top of the depth-error bar
DEPTH_DISPLAY_PERCENTILE = 99.0  # depth tiles of a panel span 0 .. this percentile of the frame
DEPTH_DISPLAY_STEP_M = 0.5  # ... rounded up to a multiple of this
RENDER_DEPTH_SCALE = 5000.0  # 16-bit depth PNG units per metre (the TUM RGB-D convention)
UINT16_MAX = np.iinfo(np.uint16).max
FRAME_DIGITS = 6

# quantity: (FrameUncertainty attribute, title, kind of scale)
QUANTITIES: dict[str, tuple[str, str, str]] = {
    "var_color": ("var_color", "Sigma_C predictive colour var", "variance"),
    "var_color_map": ("var_color_map", "Sigma_C map term", "variance"),
    "var_color_sensor": ("var_color_sensor", "Sigma_C sensor term", "variance"),
    "var_depth": ("var_depth", "Sigma_D predictive depth var", "variance_depth"),
    "var_depth_map": ("var_depth_map", "Sigma_D map term", "variance_depth"),
    "var_depth_sensor": ("var_depth_sensor", "Sigma_D sensor term", "variance_depth"),
    "error_color": ("error_color", "|C_render - C| mean RGB", "error_color"),
    "error_depth": ("error_depth", "|D_render - D|", "error_depth"),
}


def frame_name(frame: int) -> str:
    return f"{frame:0{FRAME_DIGITS}d}.png"


VARIANCE_PERCENTILES = (1.0, 99.0)
# kind of variance scale: (units, the FrameUncertainty attributes it is fitted on)
VARIANCE_KINDS = {
    "variance": ("var", ("var_color", "var_color_map", "var_color_sensor")),
    "variance_depth": ("m^2", ("var_depth", "var_depth_map", "var_depth_sensor")),
}


class ImageScales:
    """The scales of one export's images; variance scales are fitted on the first frame seen."""

    def __init__(self, cfg: UncertaintyConfig) -> None:
        self.cfg = cfg
        self.scales = {
            "error_color": Scale(0.0, COLOR_ERROR_RANGE, False, "", ERROR_MAP),
            "error_depth": Scale(0.0, DEPTH_ERROR_RANGE_M, False, "m", ERROR_MAP),
        }

    def _fallback(self, units: str) -> Scale:
        """From the config: the smaller floor to the unobserved fill value."""
        low = 10.0 ** math.floor(math.log10(min(self.cfg.sensor_min, self.cfg.map_floor)))
        high = 10.0 ** math.ceil(math.log10(self.cfg.unobserved_variance))
        return Scale(low, high, True, units, VARIANCE_MAP)

    def __call__(self, kind: str, item: FrameUncertainty) -> Scale:
        if kind not in self.scales:
            units, attributes = VARIANCE_KINDS[kind]
            observed = item.alpha >= self.cfg.unobserved_alpha
            values = np.concatenate([getattr(item, a)[observed] for a in attributes])
            fitted = Scale.fitted_log(values, units, VARIANCE_MAP, VARIANCE_PERCENTILES)
            self.scales[kind] = fitted or self._fallback(units)
        return self.scales[kind]


def quantity_tile(item: FrameUncertainty, quantity: str, scales: ImageScales) -> np.ndarray:
    attribute, title, kind = QUANTITIES[quantity]
    scale = scales(kind, item)
    return tile(colorize(getattr(item, attribute), scale), title, scale)


def write_quantities(item: FrameUncertainty, out_dir: Path, scales: ImageScales) -> list[Path]:
    """One PNG per quantity into ``out_dir/<quantity>/``; returns the files written."""
    written = []
    for quantity in QUANTITIES:
        folder = out_dir / quantity
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / frame_name(item.frame)
        write_png(path, quantity_tile(item, quantity, scales))
        written.append(path)
    return written


def write_renders(item: FrameUncertainty, out_dir: Path) -> list[Path]:
    """Rendered colour (8-bit) and depth (16-bit, `RENDER_DEPTH_SCALE` per m) into out_dir."""
    name = frame_name(item.frame)
    rgb, depth = out_dir / "rgb" / name, out_dir / "depth" / name
    for path in (rgb, depth):
        path.parent.mkdir(parents=True, exist_ok=True)
    write_png(rgb, rgb_to_bgr8(item.rendered_rgb))
    units = np.clip(np.round(item.rendered_depth * RENDER_DEPTH_SCALE), 0, UINT16_MAX)
    write_png(depth, units.astype(np.uint16))
    return [rgb, depth]


def depth_scale_of(item: FrameUncertainty) -> Scale:
    """Display range of the depth tiles of one frame's panel."""
    valid = item.measured_depth[item.valid]
    top = float(np.percentile(valid, DEPTH_DISPLAY_PERCENTILE)) if valid.size else 1.0
    top = max(DEPTH_DISPLAY_STEP_M, math.ceil(top / DEPTH_DISPLAY_STEP_M) * DEPTH_DISPLAY_STEP_M)
    return Scale(0.0, top, False, "m", DEPTH_MAP)


def panel(item: FrameUncertainty, scales: ImageScales) -> np.ndarray:
    """A 2-row overview of one frame: colour (top) and depth (bottom), measured → variances."""
    depth_scale = depth_scale_of(item)
    measured_depth = np.where(item.valid, item.measured_depth, np.nan)
    colour_row = [
        tile(rgb_to_bgr8(item.measured_rgb), "measured colour"),
        tile(rgb_to_bgr8(item.rendered_rgb), "rendered colour"),
        *(quantity_tile(item, q, scales)
          for q in ("error_color", "var_color", "var_color_map", "var_color_sensor")),
    ]  # fmt: skip
    depth_row = [
        tile(colorize(measured_depth, depth_scale), "measured depth", depth_scale),
        tile(colorize(item.rendered_depth, depth_scale), "rendered depth", depth_scale),
        *(quantity_tile(item, q, scales)
          for q in ("error_depth", "var_depth", "var_depth_map", "var_depth_sensor")),
    ]  # fmt: skip
    return grid([colour_row, depth_row])
