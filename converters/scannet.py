"""ScanNet scenes → frame store, from an exported folder or straight from the raw ``.sens`` file.

Exported layout (ScanNet's SensReader): ``color/<i>.jpg`` (1296x968), ``depth/<i>.png`` (640x480,
16-bit millimetres), ``pose/<i>.txt`` (4x4 camera-to-world, ``-inf`` where tracking failed) and
``intrinsic/intrinsic_depth.txt`` (4x4). Both sources go through the same per-frame steps, so a
folder and the ``.sens`` it was exported from give identical stores: colour is resized to the
depth resolution (area averaging) and the depth intrinsics describe the pair, as the reference
SLAM systems do; invalid poses are stored as NaN and their frames kept.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from bgs_batch.errors import InputError
from bgs_batch.geometry import matrix_to_quat_xyzw, pose_matrix
from bgs_batch.store import StoreMeta
from converters import image_codec
from converters.image_codec import ImageDecodeError
from converters.pipeline import SourceFrame
from converters.readout import readout_source, stored_readout
from converters.sens import SensFrame, SensHeader, read_frame, read_sens_index

SCANNET_FPS = 30.0  # exports carry no timestamps (so .sens ones are not used either): 30 Hz
SCANNET_DEPTH_SCALE = 1000.0  # depth PNGs in millimetres ("depth shift")
COLOR_RESIZE = cv2.INTER_AREA  # downscaling 1296x968 -> 640x480 without aliasing
SENS_SUFFIX = ".sens"
# LoopSplat's and the BayesianGS authors' ScanNet camera block crops 12 px per side of the
# 640x480 depth-resolution frames
SCANNET_CROP_EDGE = 12
SCANNET_SIZE = (640, 480)
DEPTH_INTRINSICS = Path("intrinsic") / "intrinsic_depth.txt"


@dataclass(frozen=True)
class ScanNetOptions:
    """Choices of a ScanNet conversion; every one is recorded in the store's provenance."""

    stride: int = 1
    max_frames: int | None = None
    # s over which the colour (and the depth) image's rows are read out; ScanNet names no
    # readout, so the default leaves it to `bgs run` to estimate (READOUT_UNKNOWN)
    readout: float | None = None
    depth_readout: float | None = None  # the depth image's, when it differs (None: the same)


@dataclass(frozen=True)
class ScanNetPlan:
    """The frames to convert (read lazily, one by one) and the store metadata."""

    frames: list[SourceFrame]
    count: int
    meta: StoreMeta


@dataclass(frozen=True)
class _Source:
    """What the layout-specific planners find."""

    frames: list[SourceFrame]
    intrinsics: np.ndarray
    depth_scale: float
    provenance: dict[str, object]
    size: tuple[int, int] | None  # (width, height) of the stored frames; None: unknown


def plan_scannet(path: Path, options: ScanNetOptions) -> ScanNetPlan:
    """Index a ScanNet export folder or ``.sens`` file; decode nothing yet."""
    path = Path(path)
    if options.stride < 1 or (options.max_frames is not None and options.max_frames < 1):
        raise InputError("--stride and --max-frames must be at least 1")
    if path.suffix == SENS_SUFFIX and path.is_file():
        source = _plan_sens(path, options)
    elif path.is_dir():
        source = _plan_folder(path, options)
    else:
        raise InputError(
            f"{path} is neither a ScanNet .sens file nor an exported scene folder "
            "(color/, depth/, pose/, intrinsic/)"
        )
    frames = source.frames
    if source.size == SCANNET_SIZE:
        crop_edge, crop_source = SCANNET_CROP_EDGE, "LoopSplat's and BayesianGS's ScanNet camera"
    else:
        crop_edge, crop_source = 0, "none: the reference crop is for 640x480 frames"
    provenance = {
        **source.provenance,
        "colour_resize": "to the depth resolution, cv2.INTER_AREA",
        "intrinsics_source": "depth camera (colour is resized onto it)",
        "timestamps": f"frame index / {SCANNET_FPS:g} Hz (exports carry no times)",
        "invalid_poses": "stored as NaN, frames kept",
        "gt_frames": sum(frame.pose_gt is not None for frame in frames),
        "stride": options.stride,
        "max_frames": options.max_frames,
        "crop_edge_source": crop_source,
        "rolling_shutter_readout_source": readout_source(options.readout,
                                                         "ScanNet names no readout"),
    }
    meta = StoreMeta(
        source_format="scannet",
        source_path=str(path.resolve()),
        sequence=path.resolve().stem if path.is_file() else path.resolve().name,
        intrinsics=source.intrinsics,
        depth_scale=source.depth_scale,
        has_gt=True,
        crop_edge=crop_edge,
        rolling_shutter_readout=stored_readout(options.readout),
        depth_rolling_shutter_readout=options.depth_readout,
        provenance=provenance,
    )
    return ScanNetPlan(frames, len(frames), meta)


def natural_key(name: str) -> list[int | str]:
    """Sort key putting ``2.jpg`` before ``10.jpg``."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def clean_pose(camera_to_world: np.ndarray) -> np.ndarray | None:
    """A rigid 4x4 pose (rotation re-orthonormalised: files keep ~7 digits), None if invalid."""
    if not np.all(np.isfinite(camera_to_world)):
        return None
    return pose_matrix(camera_to_world[:3, 3], matrix_to_quat_xyzw(camera_to_world[:3, :3]))


def to_store_pair(bgr: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Colour resized onto the depth grid and turned into RGB; depth unchanged."""
    height, width = depth.shape
    if bgr.shape[:2] != (height, width):
        bgr = cv2.resize(bgr, (width, height), interpolation=COLOR_RESIZE)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth


def _selected(count: int, options: ScanNetOptions) -> range:
    return range(0, count, options.stride)[: options.max_frames]


def _plan_sens(path: Path, options: ScanNetOptions) -> _Source:
    header, records = read_sens_index(path)
    frames = [
        SourceFrame(
            name=f"{path.name} frame {record.index}",
            timestamp=record.index / SCANNET_FPS,
            pose_gt=clean_pose(record.camera_to_world),
            load=partial(_load_sens_frame, path, header, record),
        )
        for record in (records[i] for i in _selected(len(records), options))
    ]
    if not frames:
        raise InputError(f"{path} holds no frames")
    provenance = {
        "layout": f".sens (SensorData v4, sensor {header.sensor_name!r})",
        "colour_codec": header.color_codec,
        "depth_codec": header.depth_codec,
        "frames_in_source": len(records),
        "depth_scale_source": ".sens header depth shift",
    }
    return _Source(frames, header.depth_intrinsics[:3, :3], header.depth_shift, provenance,
                   tuple(header.depth_size))  # fmt: skip


def _load_sens_frame(
    path: Path, header: SensHeader, record: SensFrame
) -> tuple[np.ndarray, np.ndarray]:
    return to_store_pair(*read_frame(path, header, record))


def _plan_folder(folder: Path, options: ScanNetOptions) -> _Source:
    intrinsics_file = folder / DEPTH_INTRINSICS
    if not intrinsics_file.is_file():
        raise InputError(
            f"{intrinsics_file} is missing; a ScanNet export folder needs color/, "
            "depth/, pose/ and intrinsic/ (as ScanNet's SensReader exports them)"
        )
    intrinsics = _read_matrix(intrinsics_file)[:3, :3]
    colors = sorted((folder / "color").glob("*.jpg"), key=lambda p: natural_key(p.name))
    if not colors:
        raise InputError(f"{folder / 'color'} holds no .jpg frames; is {folder} a ScanNet export?")
    frames = []
    for i in _selected(len(colors), options):
        color = colors[i]
        depth, pose = folder / "depth" / f"{color.stem}.png", folder / "pose" / f"{color.stem}.txt"
        for needed in (depth, pose):
            if not needed.is_file():
                raise InputError(
                    f"{needed} is missing (frame {color.name}); restore it from the export"
                )
        frames.append(
            SourceFrame(
                name=f"color/{color.name} + depth/{depth.name}",
                timestamp=i / SCANNET_FPS,
                pose_gt=clean_pose(_read_matrix(pose)),
                load=partial(_load_folder_frame, color, depth),
            )
        )
    provenance = {
        "layout": "exported folder (color/, depth/, pose/, intrinsic/)",
        "frames_in_source": len(colors),
        "depth_scale_source": "ScanNet convention (depth PNGs in millimetres)",
    }
    first_depth = cv2.imread(str(folder / "depth" / f"{colors[0].stem}.png"), cv2.IMREAD_UNCHANGED)
    size = None if first_depth is None else (first_depth.shape[1], first_depth.shape[0])
    return _Source(frames, intrinsics, SCANNET_DEPTH_SCALE, provenance, size)


def _read_matrix(path: Path) -> np.ndarray:
    try:
        return np.array(path.read_text().split(), np.float64).reshape(4, 4)
    except ValueError:
        raise InputError(f"{path}: expected a 4x4 matrix of numbers") from None


def _load_folder_frame(color: Path, depth: Path) -> tuple[np.ndarray, np.ndarray]:
    try:
        bgr = image_codec.read(color, cv2.IMREAD_COLOR, "colour image")
        values = image_codec.read(depth, cv2.IMREAD_UNCHANGED, "depth image")
    except ImageDecodeError as err:
        raise InputError(f"{err}; restore it or pass --skip-bad-frames to drop the frame"
                         ) from None  # fmt: skip
    if values.dtype != np.uint16 or values.ndim != 2:
        raise InputError(
            f"{depth}: not a 16-bit single-channel PNG ({values.dtype} {values.shape}); restore "
            "it or pass "
            "--skip-bad-frames to drop the frame"
        )
    return to_store_pair(bgr, values)
