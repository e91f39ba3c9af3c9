"""``outputs/uncertainty.h5``: the per-frame renders, variances and residuals of one run.

Layout (every image dataset float32 ``[N,H,W]`` or ``[N,H,W,3]``, one gzip+shuffle chunk per
frame, with ``units`` and ``description`` attributes)::

    /frame              int64   [N]  frame index in the job's frame store
    /timestamp          float64 [N]  seconds, of the RGB frame
    /keyframe           bool    [N]  whether the SLAM mapped the frame
    /submap             int64   [N]  the submap the frame was rendered from
    /render/color       [N,H,W,3]    rendered colour Ĉ, RGB in [0,1] (clamped)
    /render/depth       [N,H,W]      rendered depth D̂, m
    /render/alpha       [N,H,W]      accumulated opacity A
    /variance/color     [N,H,W]      Σ_C, channel mean (sensor + map term)
    /variance/color_map, /variance/color_sensor     its two terms
    /variance/depth     [N,H,W]      Σ_D, m² (sensor + map term)
    /variance/depth_map, /variance/depth_sensor     its two terms
    /error/color        [N,H,W]      |Ĉ − C|, channel mean
    /error/depth        [N,H,W]      |D̂ − D|, m; NaN where the measured depth is invalid

Root attributes: ``created_by``, ``job``, ``store``, ``width``, ``height``, ``downscale``,
``intrinsics`` (of the rendered images), ``conventions`` (text) and the run's ``uncertainty``
config (JSON). Frames are deflated with ISA-L and written as raw chunks (as the frame store), so
any HDF5 reader sees plain gzip data. The file is built under a temporary name and renamed when
complete.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from isal import isal_zlib

from bgs_batch import __version__
from outputs.uncertainty import FrameUncertainty

COMPRESSION_LEVEL = 1  # ISA-L deflate levels 0-3; written as HDF5 gzip
CONVENTIONS = (
    "Re-rendered from the job's frozen submaps at the estimated poses with the saved sensor "
    "network. Sigma = sensor variance + map term; map term = rendered opacity-induced variance "
    "V + floor, or the 'unobserved' variance where alpha < threshold (paper Eq. 3, 10, 11). "
    "Colour variances and errors are channel means. Rendered colour clamped to [0,1]."
)

# dataset name: (FrameUncertainty attribute, units, description)
IMAGES: dict[str, tuple[str, str, str]] = {
    "render/color": ("rendered_rgb", "1", "rendered colour, RGB in [0,1] (clamped)"),
    "render/depth": ("rendered_depth", "m", "rendered depth (alpha-weighted, not normalised)"),
    "render/alpha": ("alpha", "1", "accumulated opacity"),
    "variance/color": ("var_color", "1", "predictive colour variance Sigma_C, channel mean"),
    "variance/color_map": ("var_color_map", "1", "map term of Sigma_C, channel mean"),
    "variance/color_sensor": ("var_color_sensor", "1", "sensor term of Sigma_C"),
    "variance/depth": ("var_depth", "m^2", "predictive depth variance Sigma_D"),
    "variance/depth_map": ("var_depth_map", "m^2", "map term of Sigma_D"),
    "variance/depth_sensor": ("var_depth_sensor", "m^2", "sensor term of Sigma_D"),
    "error/color": ("error_color", "1", "|rendered - measured| colour, channel mean"),
    "error/depth": ("error_depth", "m", "|rendered - measured| depth; NaN: no valid depth"),
}
SCALARS: dict[str, tuple[str, type]] = {
    "frame": ("frame", np.int64),
    "timestamp": ("timestamp", np.float64),
    "keyframe": ("keyframe", np.bool_),
    "submap": ("submap", np.int64),
}


def _shuffled(image: np.ndarray) -> bytes:
    """HDF5's shuffle filter applied to a contiguous array (byte k of every element together)."""
    raw = np.ascontiguousarray(image)
    return raw.reshape(-1).view(np.uint8).reshape(-1, raw.dtype.itemsize).T.tobytes()


class UncertaintyWriter:
    """Writes frames one by one into the layout above; a context manager (`path` should be a
    temporary name: see `outputs.atomic`)."""

    def __init__(self, path: Path, frames: int, height: int, width: int,
                 attrs: dict[str, Any]) -> None:  # fmt: skip
        self.file = h5py.File(path, "w")
        self.count, self.frames = 0, frames
        for name, value in {"created_by": f"bgs-batch {__version__}", "conventions": CONVENTIONS,
                            **attrs}.items():  # fmt: skip
            self.file.attrs[name] = json.dumps(value) if isinstance(value, dict) else value
        for name, (_, units, description) in IMAGES.items():
            shape = (frames, height, width) + ((3,) if name == "render/color" else ())
            ds = self.file.create_dataset(name, shape, np.float32, chunks=(1, *shape[1:]),
                                          compression="gzip", shuffle=True)  # fmt: skip
            ds.attrs.update(units=units, description=description)
        for name, (_, dtype) in SCALARS.items():
            self.file.create_dataset(name, (frames,), dtype)

    def add(self, item: FrameUncertainty) -> None:
        """Append one frame (at most `frames` in total)."""
        if self.count >= self.frames:
            raise ValueError(f"the file was made for {self.frames} frames")
        k = self.count
        for name, (attribute, _, _) in IMAGES.items():
            image = np.asarray(getattr(item, attribute), np.float32)
            chunk = isal_zlib.compress(_shuffled(image), COMPRESSION_LEVEL)
            self.file[name].id.write_direct_chunk((k,) + (0,) * image.ndim, chunk)
        for name, (attribute, _) in SCALARS.items():
            self.file[name][k] = getattr(item, attribute)
        self.count += 1

    def __enter__(self) -> UncertaintyWriter:
        return self

    def __exit__(self, exc_type: type | None, *_: object) -> None:
        self.file.close()
        if exc_type is None and self.count != self.frames:
            raise ValueError(f"{self.count} of {self.frames} frames written")


def read_frame(path: Path, position: int) -> dict[str, Any]:
    """One stored frame as a dict of arrays (dataset names as keys), for tests and users."""
    with h5py.File(path, "r") as f:
        out = {name: f[name][position] for name in IMAGES}
        out |= {name: f[name][position].item() for name in SCALARS}
    return out
