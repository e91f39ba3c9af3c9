"""Colour-mapped images with a labelled colour bar, drawn with OpenCV (fast, no plotting stack).

A `Scale` maps values to colours: linear or log10, clipped to its range (the end labels then read
``<=``/``>=``), NaN drawn grey. Images smaller than `MIN_HEIGHT` are enlarged by an integer
factor (nearest neighbour, so pixels stay visible) to keep the labels legible. Output arrays are
BGR uint8, as OpenCV expects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from converters import image_codec

MIN_HEIGHT = 240  # px; smaller images are enlarged by an integer factor
BAR_WIDTH = 14  # px, the colour strip
LABEL_WIDTH = 58  # px, room for tick labels right of the strip
TITLE_HEIGHT = 20  # px, strip above the image
MARGIN = 6  # px
TICKS = 5  # labelled values on a bar
FONT = cv2.FONT_HERSHEY_SIMPLEX
FONT_SCALE = 0.36
TITLE_SCALE = 0.42
TEXT_COLOUR = (20, 20, 20)
BACKGROUND = 255
NAN_COLOUR = (128, 128, 128)
FRAME_COLOUR = (160, 160, 160)  # 1-px outline, so white image borders stay visible
PNG_COMPRESSION = 1  # zlib level: speed over size for many images
VARIANCE_MAP = cv2.COLORMAP_VIRIDIS
ERROR_MAP = cv2.COLORMAP_INFERNO
DEPTH_MAP = cv2.COLORMAP_TURBO


@dataclass(frozen=True)
class Scale:
    """Value range, spacing and colour map of one kind of image; `units` labels the bar."""

    low: float
    high: float
    log: bool
    units: str
    colormap: int

    def normalised(self, values: np.ndarray) -> np.ndarray:
        """Values mapped to [0, 1] (NaN stays NaN)."""
        v = np.asarray(values, np.float64)
        lo, hi = self.low, self.high
        if self.log:
            with np.errstate(divide="ignore", invalid="ignore"):
                v = np.log10(np.maximum(v, np.finfo(np.float64).tiny))
            lo, hi = math.log10(lo), math.log10(hi)
        return np.clip((v - lo) / (hi - lo), 0.0, 1.0)

    def tick_values(self) -> np.ndarray:
        """Linear: `TICKS` even steps; log: the decades (every k-th when there are many)."""
        if not self.log:
            return np.linspace(self.low, self.high, TICKS)
        first, last = math.ceil(math.log10(self.low)), math.floor(math.log10(self.high))
        step = max(1, math.ceil((last - first + 1) / TICKS))
        return 10.0 ** np.arange(first, last + 1, step)

    @classmethod
    def fitted_log(cls, values: np.ndarray, units: str, colormap: int,
                   percentiles: tuple[float, float]) -> Scale | None:  # fmt: skip
        """A log scale over the given percentiles of the positive finite `values`, widened to
        whole decades; None when there are no such values."""
        v = np.asarray(values, np.float64)
        v = v[np.isfinite(v) & (v > 0)]
        if v.size == 0:
            return None
        lo, hi = np.log10(np.percentile(v, percentiles))
        low, high = math.floor(lo), max(math.ceil(hi), math.floor(lo) + 1)
        return cls(10.0**low, 10.0**high, True, units, colormap)


def colorize(values: np.ndarray, scale: Scale) -> np.ndarray:
    """[H,W] values → [H,W,3] BGR uint8 through the scale's colour map; NaN grey."""
    unit = scale.normalised(values)
    nan = np.isnan(unit)
    levels = np.round(np.nan_to_num(unit) * 255).astype(np.uint8)
    bgr = cv2.applyColorMap(levels, scale.colormap)
    bgr[nan] = NAN_COLOUR
    return bgr


def rgb_to_bgr8(rgb: np.ndarray) -> np.ndarray:
    """[H,W,3] RGB floats in [0,1] → BGR uint8."""
    return np.ascontiguousarray((np.clip(rgb, 0, 1) * 255).round().astype(np.uint8)[..., ::-1])


def _enlarge(image: np.ndarray) -> np.ndarray:
    factor = max(1, math.ceil(MIN_HEIGHT / image.shape[0]))
    if factor == 1:
        return image
    return cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_NEAREST)


def _tick_label(value: float, scale: Scale, end: str) -> str:
    text = f"1e{round(math.log10(value))}" if scale.log else f"{value:.3g}"
    return f"{end}{text}"


def tile(image: np.ndarray, title: str, scale: Scale | None = None) -> np.ndarray:
    """A titled tile: the (enlarged) BGR image and, with a `scale`, its colour bar and ticks.

    Without a scale the bar area stays blank, so tiles of one panel line up.
    """
    body = _enlarge(image)
    h, w = body.shape[:2]
    width = w + MARGIN + BAR_WIDTH + LABEL_WIDTH
    canvas = np.full((TITLE_HEIGHT + h, width, 3), BACKGROUND, np.uint8)
    canvas[TITLE_HEIGHT:, :w] = body
    cv2.rectangle(canvas, (0, TITLE_HEIGHT), (w - 1, TITLE_HEIGHT + h - 1), FRAME_COLOUR, 1)
    cv2.putText(canvas, title, (2, TITLE_HEIGHT - 6), FONT, TITLE_SCALE, TEXT_COLOUR, 1,
                cv2.LINE_AA)  # fmt: skip
    if scale is not None:
        gradient = np.linspace(1.0, 0.0, h)[:, None].repeat(BAR_WIDTH, 1)
        levels = np.round(gradient * 255).astype(np.uint8)
        x0 = w + MARGIN
        canvas[TITLE_HEIGHT:, x0 : x0 + BAR_WIDTH] = cv2.applyColorMap(levels, scale.colormap)
        ticks = scale.tick_values()
        for k, value in enumerate(ticks):
            # values beyond the ends are clipped: say so (a linear scale starts at its minimum)
            at_low = scale.log and value == scale.low
            end = ">=" if k == len(ticks) - 1 and value == scale.high else "<=" if at_low else ""
            y = TITLE_HEIGHT + round((1 - scale.normalised(np.array(value))) * (h - 1))
            y_text = min(max(y + 4, TITLE_HEIGHT + 9), TITLE_HEIGHT + h - 2)
            cv2.line(canvas, (x0 + BAR_WIDTH, y), (x0 + BAR_WIDTH + 3, y), TEXT_COLOUR, 1)
            cv2.putText(canvas, _tick_label(float(value), scale, end),
                        (x0 + BAR_WIDTH + 5, y_text), FONT, FONT_SCALE, TEXT_COLOUR, 1,
                        cv2.LINE_AA)  # fmt: skip
        cv2.putText(canvas, scale.units, (x0, TITLE_HEIGHT - 6), FONT, FONT_SCALE, TEXT_COLOUR,
                    1, cv2.LINE_AA)  # fmt: skip
    return canvas


def grid(tiles: list[list[np.ndarray]]) -> np.ndarray:
    """Rows of tiles into one image (short rows padded with background)."""
    height = max(t.shape[0] for row in tiles for t in row)
    rows = []
    for row in tiles:
        padded = [np.pad(t, ((0, height - t.shape[0]), (0, MARGIN), (0, 0)),
                         constant_values=BACKGROUND) for t in row]  # fmt: skip
        rows.append(np.concatenate(padded, axis=1))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, MARGIN), (0, width - r.shape[1]), (0, 0)), constant_values=BACKGROUND)
            for r in rows]  # fmt: skip
    return np.concatenate(rows, axis=0)


def write_png(path: Path, bgr: np.ndarray) -> None:
    """Write a BGR (or grey, or 16-bit) image as PNG at the exports' compression level."""
    image_codec.write_png(path, bgr, PNG_COMPRESSION)
