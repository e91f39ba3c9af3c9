"""The HDF5 frame store (schema version 1, docs/store-format.md): one file per RGB-D sequence.

Layout::

    /rgb         uint8   [N,H,W,3]  RGB order, one gzip chunk per frame
    /depth       uint16  [N,H,W]    depth_scale units per metre (or float32 metres), 0 = invalid
    /timestamp   float64 [N]        seconds, of the RGB frame
    /pose_gt     float64 [N,4,4]    camera-to-world ground truth, NaN rows where unknown (optional)
    /depth_timestamp  float64 [N]   seconds, of the depth image (optional; absent: of the RGB)
    /intrinsics  float64 [3,3]      pinhole matrix of the stored, registered RGB-D pair
    attributes   schema_version, source_format, source_path, sequence, depth_scale, distortion,
                 distortion_applied, width, height, created_by, provenance (JSON of every choice);
                 optional: crop_edge (pixels per border the reference systems crop for this
                 camera; `bgs run` applies it by default; absent = 0),
                 rolling_shutter_readout (seconds over which the camera reads its rows out;
                 the `cpu` preset moves them to one instant; absent = 0, a global shutter;
                 NaN = unknown: `bgs run` estimates it from the frames),
                 depth_rolling_shutter_readout (the depth image's, when it differs: absent =
                 rolling_shutter_readout),
                 depth_registered (true: the recording or the converter registered depth to
                 colour with the cameras' calibration; absent = false: `bgs run` checks the
                 colour camera's offset from the frames)

Frames are deflated in worker threads with ISA-L (5x faster than zlib at level 1, and it
releases the GIL) and written as raw chunks, so conversion uses every core; the files stay plain
gzip(+shuffle) HDF5 that any HDF5 tool reads.
The writer builds ``NAME.h5.tmp`` and commits it (`atomic.commit`) only once complete and valid.
The reader streams frames (never the whole sequence) and prefetches/decompresses on a small
thread pool.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from isal import isal_zlib

from bgs_batch import __version__
from bgs_batch.atomic import commit, fitted_name
from bgs_batch.errors import InputError, OutputExistsError

SCHEMA_VERSION = 1
DEFAULT_COMPRESSION_LEVEL = 1  # ISA-L deflate levels are 0-3; 1 is the speed/size sweet spot
READ_WORKERS = 2
MAX_READOUT_S = 1.0  # a row readout of a second or more is no video camera's
READOUT_UNKNOWN = math.nan  # a camera whose readout nobody gave: `bgs run` estimates it


def same_readout(a: float, b: float) -> bool:
    """Equal readouts, unknown (NaN) ones included."""
    return a == b or (math.isnan(a) and math.isnan(b))
READ_PREFETCH = 4
REQUIRED_ATTRS = (
    "schema_version",
    "source_format",
    "source_path",
    "sequence",
    "depth_scale",
    "distortion",
    "distortion_applied",
    "width",
    "height",
    "created_by",
    "provenance",
)
TMP_SUFFIX = ".tmp"
DECODE_ERRORS = (OSError, ValueError, isal_zlib.error)  # what a damaged chunk raises


@dataclass(frozen=True)
class Frame:
    """One RGB-D frame as the SLAM code consumes it."""

    index: int
    rgb: np.ndarray  # (H, W, 3) uint8, RGB order
    depth: np.ndarray  # (H, W) float32 metres, 0 where invalid
    timestamp: float
    pose_gt: np.ndarray | None  # (4, 4) float64 camera-to-world, None where unknown
    # seconds, when the depth image was taken; None: with the colour image (`timestamp`)
    depth_timestamp: float | None = None

    @property
    def depth_time_offset(self) -> float:
        """Seconds from the colour image to the depth image (0 when taken together)."""
        return 0.0 if self.depth_timestamp is None else self.depth_timestamp - self.timestamp


@dataclass(frozen=True)
class StoreMeta:
    """Sequence-level facts a converter knows before writing frames."""

    source_format: str
    source_path: str
    sequence: str
    intrinsics: np.ndarray  # (3, 3)
    depth_scale: float  # units per metre of uint16 depth; 1.0 for float32 metres
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    distortion_applied: bool = False  # True: images were undistorted with `distortion`
    has_gt: bool = False
    crop_edge: int = 0  # recommended border crop (pixels per side); 0: none
    # s over which the rows are read out; 0: a global shutter; READOUT_UNKNOWN: not known
    rolling_shutter_readout: float = 0.0
    depth_rolling_shutter_readout: float | None = None  # the depth image's; None: the same
    # True: depth was registered to colour with the cameras' calibration (by the recording's
    # driver or by the converter); False: nobody says, `bgs run` estimates the colour offset
    depth_registered: bool = False
    provenance: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class EncodedFrame:
    """A frame compressed into the exact bytes of its HDF5 chunks (see `encode_frame`)."""

    rgb_chunk: bytes
    depth_chunk: bytes
    shape: tuple[int, int]
    depth_dtype: np.dtype
    timestamp: float
    pose_gt: np.ndarray | None
    depth_timestamp: float | None = None


def _shuffle(raw: np.ndarray) -> np.ndarray:
    """HDF5's shuffle filter: byte k of every element grouped together (better deflate ratio).

    `raw` must be C-contiguous. Plane k is cut out of the elements read as little-endian words
    (byte k of memory is then bits 8k..8k+7, on any host) by a shift and a narrowing copy: numpy
    runs both vectorised and without the GIL, where the transposed byte view of the same planes
    is a byte-by-byte strided copy that holds the GIL (0.17 against 0.06 ms for a VGA uint16
    depth image).
    """
    size = raw.dtype.itemsize
    words = raw.reshape(-1).view(np.dtype(f"<u{size}"))
    planes = np.empty((size, words.size), np.uint8)
    np.copyto(planes[0], words, casting="unsafe")  # narrowing keeps the low byte
    for k in range(1, size):
        np.right_shift(words, 8 * k, out=planes[k], casting="unsafe")
    return planes


def _unshuffle(data: bytes, dtype: np.dtype, shape: tuple[int, ...]) -> np.ndarray:
    size = dtype.itemsize
    planes = np.frombuffer(data, np.uint8).reshape(size, -1)
    return np.ascontiguousarray(planes.T).view(dtype).reshape(shape)


def encode_frame(
    rgb: np.ndarray,
    depth: np.ndarray,
    timestamp: float,
    pose_gt: np.ndarray | None = None,
    level: int = DEFAULT_COMPRESSION_LEVEL,
    depth_timestamp: float | None = None,
) -> EncodedFrame:
    """Compress one frame into HDF5 chunk bytes; thread-safe and GIL-free in its heavy parts.

    `rgb` is (H, W, 3) uint8 in RGB order; `depth` is (H, W) uint16 in depth-scale units or
    float32 metres, 0 where invalid; `depth_timestamp` is when the depth image was taken, when
    the recording says and it differs from the colour image's `timestamp`.
    """
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if depth.dtype not in (np.uint16, np.float32) or depth.shape != rgb.shape[:2]:
        raise ValueError(f"depth must be (H, W) uint16/float32, got {depth.shape} {depth.dtype}")
    return EncodedFrame(
        rgb_chunk=isal_zlib.compress(np.ascontiguousarray(rgb).data, level),
        depth_chunk=isal_zlib.compress(_shuffle(np.ascontiguousarray(depth)).data, level),
        shape=(int(rgb.shape[0]), int(rgb.shape[1])),
        depth_dtype=depth.dtype,
        timestamp=float(timestamp),
        pose_gt=None if pose_gt is None else np.asarray(pose_gt, np.float64),
        depth_timestamp=None if depth_timestamp is None else float(depth_timestamp),
    )


def temp_path(path: Path) -> Path:
    """Where a store is built before the final rename (docs/store-format.md: ``NAME.h5.tmp``;
    a name too long for ``.tmp`` loses its last characters first)."""
    return path.with_name(fitted_name(path.name, TMP_SUFFIX))


def check_output_path(path: Path, overwrite: bool) -> None:
    """Refuse to replace an existing store unless asked, before any work is done."""
    if path.exists() and not overwrite:
        raise OutputExistsError(f"{path} already exists; pass --overwrite to replace it")
    if not path.parent.is_dir():
        raise InputError(f"output folder {path.parent} does not exist; create it first")


class FrameStoreWriter:
    """Builds a frame store at ``path + '.tmp'``; `finish` validates it and renames it into place.

    Use as a context manager: leaving the block by an exception (including Ctrl-C) deletes the
    temporary file, so no half-written store ever appears under the final name.
    """

    def __init__(
        self,
        path: Path,
        meta: StoreMeta,
        *,
        overwrite: bool = False,
        level: int = DEFAULT_COMPRESSION_LEVEL,
    ) -> None:
        self.path = Path(path)
        self.meta = meta
        self.level = level
        check_output_path(self.path, overwrite)
        self.tmp = temp_path(self.path)
        self._file = h5py.File(self.tmp, "w", libver="latest")
        self._timestamps: list[float] = []
        self._depth_timestamps: list[float | None] = []
        self._poses: list[np.ndarray] = []
        self._shape: tuple[int, int] | None = None
        self._depth_dtype: np.dtype | None = None
        # (rgb, depth) dataset handles and frame shapes: looking them up per frame costs more
        # than writing the frame's chunks
        self._datasets: tuple[tuple[h5py.h5d.DatasetID, tuple[int, ...]], ...] = ()

    def __enter__(self) -> FrameStoreWriter:
        return self

    def __exit__(self, exc_type: type | None, *_: object) -> None:
        if exc_type is not None or self._file:
            self.abort()

    def __len__(self) -> int:
        return len(self._timestamps)

    def _create_datasets(self, frame: EncodedFrame) -> None:
        h, w = frame.shape
        self._shape, self._depth_dtype = frame.shape, frame.depth_dtype
        rgb = self._file.create_dataset(
            "rgb", (0, h, w, 3), np.uint8, maxshape=(None, h, w, 3), chunks=(1, h, w, 3),
            compression="gzip", compression_opts=self.level,
        )  # fmt: skip
        depth = self._file.create_dataset(
            "depth", (0, h, w), frame.depth_dtype, maxshape=(None, h, w), chunks=(1, h, w),
            compression="gzip", compression_opts=self.level, shuffle=True,
        )  # fmt: skip
        self._datasets = ((rgb.id, (h, w, 3)), (depth.id, (h, w)))

    def append(self, frame: EncodedFrame, source: str = "") -> None:
        """Append an encoded frame; `source` names its file(s) in error messages."""
        if self._shape is None:
            self._create_datasets(frame)
        elif frame.shape != self._shape or frame.depth_dtype != self._depth_dtype:
            raise InputError(
                f"{source or f'frame {len(self)}'}: size {frame.shape[1]}x{frame.shape[0]} "
                f"({frame.depth_dtype} depth) differs from the first frame's "
                f"{self._shape[1]}x{self._shape[0]} ({self._depth_dtype}); a store holds one "
                "camera: convert the parts separately or drop the odd frames"
            )
        n = len(self)
        for (dataset, frame_shape), chunk in zip(
            self._datasets, (frame.rgb_chunk, frame.depth_chunk), strict=True
        ):
            dataset.set_extent((n + 1, *frame_shape))
            dataset.write_direct_chunk((n,) + (0,) * len(frame_shape), chunk)
        self._timestamps.append(frame.timestamp)
        self._depth_timestamps.append(frame.depth_timestamp)
        self._poses.append(np.full((4, 4), np.nan) if frame.pose_gt is None else frame.pose_gt)

    def finish(self) -> Path:
        """Write the per-sequence arrays and attributes, validate, fsync and rename into place."""
        if not self._timestamps:
            raise InputError(f"no frames to write to {self.path}")
        f, meta = self._file, self.meta
        f["timestamp"] = np.asarray(self._timestamps, np.float64)
        if any(t is not None for t in self._depth_timestamps):
            f["depth_timestamp"] = np.array(
                [t if d is None else d for t, d in zip(self._timestamps, self._depth_timestamps,
                                                       strict=True)], np.float64)  # fmt: skip
        if meta.has_gt:
            f["pose_gt"] = np.stack(self._poses).astype(np.float64)
        f["intrinsics"] = np.asarray(meta.intrinsics, np.float64)
        h, w = self._shape
        f.attrs.update(
            schema_version=SCHEMA_VERSION,
            source_format=meta.source_format,
            source_path=meta.source_path,
            sequence=meta.sequence,
            depth_scale=float(meta.depth_scale),
            distortion=np.asarray(meta.distortion, np.float64),
            distortion_applied=bool(meta.distortion_applied),
            width=w,
            height=h,
            created_by=f"bgs-batch {__version__}",
            crop_edge=int(meta.crop_edge),
            provenance=json.dumps(meta.provenance, sort_keys=True),
        )
        if meta.rolling_shutter_readout:
            f.attrs["rolling_shutter_readout"] = float(meta.rolling_shutter_readout)
        depth = meta.depth_rolling_shutter_readout
        if depth is not None and not same_readout(depth, meta.rolling_shutter_readout):
            f.attrs["depth_rolling_shutter_readout"] = float(depth)
        if meta.depth_registered:
            f.attrs["depth_registered"] = True
        validate(f, self.tmp)
        f.close()
        commit(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        """Close and delete the temporary file (idempotent)."""
        if self._file:
            self._file.close()
        self.tmp.unlink(missing_ok=True)


def validate(f: h5py.File, path: Path | str) -> None:
    """Check an open store against schema v1; raise `InputError` listing every problem found."""
    problems: list[str] = []
    missing = [a for a in REQUIRED_ATTRS if a not in f.attrs]
    if missing:
        problems.append(f"missing attributes: {', '.join(missing)}")
    version = f.attrs.get("schema_version")
    if version is not None and int(version) > SCHEMA_VERSION:  # made by a newer bgs-batch
        raise InputError(f"{path} is a frame store of schema v{int(version)}, written by "
                         f"{f.attrs.get('created_by', 'a newer bgs-batch')}; this bgs-batch "
                         f"({__version__}) reads schema v{SCHEMA_VERSION}: open it with the "
                         "version that wrote it, or newer")  # fmt: skip
    if version is not None and int(version) != SCHEMA_VERSION:
        problems.append(f"schema_version is {version}, this bgs-batch reads {SCHEMA_VERSION}")
    for name in ("rgb", "depth", "timestamp", "intrinsics"):
        if name not in f:
            problems.append(f"missing dataset /{name}")
    if problems:
        raise InputError(_invalid(path, problems))

    rgb, depth, ts = f["rgb"], f["depth"], f["timestamp"]
    n = rgb.shape[0]
    if rgb.dtype != np.uint8 or rgb.ndim != 4 or rgb.shape[3] != 3:
        problems.append(f"/rgb must be uint8 [N,H,W,3], is {rgb.dtype} {rgb.shape}")
    if depth.dtype not in (np.uint16, np.float32) or depth.shape != rgb.shape[:3]:
        problems.append(f"/depth must be uint16/float32 {rgb.shape[:3]}, is {depth.dtype} "
                        f"{depth.shape}")  # fmt: skip
    if ts.shape != (n,) or ts.dtype != np.float64:
        problems.append(f"/timestamp must be float64 [{n}], is {ts.dtype} {ts.shape}")
    elif n > 1 and not np.all(np.diff(ts[()]) > 0):
        problems.append("/timestamp is not strictly increasing")
    if "depth_timestamp" in f:
        depth_ts = f["depth_timestamp"]
        if depth_ts.shape != (n,) or depth_ts.dtype != np.float64:
            problems.append(f"/depth_timestamp must be float64 [{n}], is {depth_ts.dtype} "
                            f"{depth_ts.shape}")  # fmt: skip
        elif not np.all(np.isfinite(depth_ts[()])):
            problems.append("/depth_timestamp holds values that are not finite")
    if n == 0:
        problems.append("the store holds no frames")
    if rgb.ndim == 4 and (f.attrs["width"], f.attrs["height"]) != (rgb.shape[2], rgb.shape[1]):
        problems.append("width/height attributes disagree with /rgb")
    k = f["intrinsics"][()]
    if k.shape != (3, 3) or not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0:
        problems.append(f"/intrinsics must be a finite 3x3 pinhole matrix, is {k.tolist()}")
    if float(f.attrs["depth_scale"]) <= 0:
        problems.append("depth_scale must be positive")
    crop = int(f.attrs.get("crop_edge", 0))
    if rgb.ndim == 4 and not 0 <= 2 * crop < min(rgb.shape[1:3]):
        problems.append(f"crop_edge {crop} must be >= 0 and leave part of the "
                        f"{rgb.shape[2]}x{rgb.shape[1]} image")  # fmt: skip
    for key in ("rolling_shutter_readout", "depth_rolling_shutter_readout"):
        readout = float(f.attrs.get(key, 0.0))
        if not (math.isnan(readout) or 0 <= readout < MAX_READOUT_S):
            problems.append(f"{key} {readout} must be >= 0 and below {MAX_READOUT_S} s, or NaN "
                            "(unknown)")  # fmt: skip
    if not isinstance(f.attrs.get("depth_registered", False), bool | np.bool_):
        problems.append(f"depth_registered {f.attrs['depth_registered']!r} must be true or false")
    if len(np.atleast_1d(f.attrs["distortion"])) != 5:
        problems.append("distortion must hold 5 coefficients (k1 k2 p1 p2 k3)")
    if "pose_gt" in f:
        poses = f["pose_gt"][()]
        if poses.shape != (n, 4, 4):
            problems.append(f"/pose_gt must be [{n},4,4], is {poses.shape}")
        else:
            known = poses[np.all(np.isfinite(poses), axis=(1, 2))]
            if not _are_rigid(known):
                problems.append("/pose_gt holds matrices that are not rigid transforms")
    try:
        json.loads(f.attrs["provenance"])
    except (TypeError, ValueError):
        problems.append("provenance attribute is not JSON")
    if problems:
        raise InputError(_invalid(path, problems))


def _are_rigid(poses: np.ndarray, tol: float = 1e-6) -> bool:
    if len(poses) == 0:
        return True
    rot = poses[:, :3, :3]
    orthonormal = np.abs(rot @ rot.transpose(0, 2, 1) - np.eye(3)).max() < tol
    bottom = np.abs(poses[:, 3] - np.array([0, 0, 0, 1.0])).max() < tol
    return bool(orthonormal and bottom and np.all(np.linalg.det(rot) > 0))


def _invalid(path: Path | str, problems: list[str]) -> str:
    """One line: the store, every problem found, the fix."""
    return (f"{path} is not a valid bgs-batch frame store (schema v{SCHEMA_VERSION}): "
            f"{'; '.join(problems)}; re-create it with `bgs convert …` from the original "
            "recording")  # fmt: skip


class FrameStore:
    """Streaming reader of a frame store: ``len``, indexing and iteration yield `Frame` objects.

    Frames are read one at a time (plus a few prefetched); nothing holds the whole sequence.
    """

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(f"{self.path} does not exist; create it with `bgs convert …`")
        try:
            self._file = h5py.File(self.path, "r")
        except OSError as err:
            raise InputError(
                f"{self.path} is not a readable HDF5 file ({err}); it may be truncated or still "
                "being written: re-create it with `bgs convert …`"
            ) from err
        validate(self._file, self.path)
        self._rgb, self._depth = self._file["rgb"], self._file["depth"]
        self.attrs: dict[str, Any] = dict(self._file.attrs)
        self.intrinsics: np.ndarray = self._file["intrinsics"][()]
        self.timestamps: np.ndarray = self._file["timestamp"][()]
        # when each depth image was taken; None: with its colour image
        self.depth_timestamps: np.ndarray | None = (
            self._file["depth_timestamp"][()] if "depth_timestamp" in self._file else None)
        self.depth_scale = float(self.attrs["depth_scale"])
        self.width, self.height = int(self.attrs["width"]), int(self.attrs["height"])
        self.crop_edge = int(self.attrs.get("crop_edge", 0))  # recommended; stores before it: 0
        self.rolling_shutter_readout = float(self.attrs.get("rolling_shutter_readout", 0.0))
        # the depth image's readout; stores before it and cameras reading both alike: the same
        self.depth_rolling_shutter_readout = float(self.attrs.get(
            "depth_rolling_shutter_readout", self.rolling_shutter_readout))  # fmt: skip
        self.depth_registered = bool(self.attrs.get("depth_registered", False))
        self.provenance: dict[str, Any] = json.loads(self.attrs["provenance"])
        self._poses = self._file["pose_gt"][()] if "pose_gt" in self._file else None
        self._fast = _is_our_pipeline(self._rgb) and _is_our_pipeline(self._depth)

    @property
    def has_gt(self) -> bool:
        return self._poses is not None

    @property
    def poses_gt(self) -> np.ndarray | None:
        """All ground-truth poses (N, 4, 4), NaN where unknown; None when the store has no GT."""
        return None if self._poses is None else self._poses.copy()

    def __len__(self) -> int:
        return int(self._rgb.shape[0])

    def __enter__(self) -> FrameStore:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def close(self) -> None:
        if self._file:
            self._file.close()

    def __getitem__(self, index: int) -> Frame:
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"frame {index} out of range for {n} frames in {self.path}")
        index %= n
        return self._frame(index, self.read_rgb(index), self.read_depth(index))

    def __iter__(self) -> Iterator[Frame]:
        return self.frames()

    def frames(self, indices: Iterable[int] | None = None) -> Iterator[Frame]:
        """Iterate frames in the given order (default: all), decoding ahead on a thread pool."""
        order = range(len(self)) if indices is None else list(indices)
        with ThreadPoolExecutor(READ_WORKERS) as pool:
            pending = []
            for i in order:
                pending.append(pool.submit(self.__getitem__, i))
                if len(pending) > READ_PREFETCH:
                    yield pending.pop(0).result()
            for future in pending:
                yield future.result()

    def read_rgb(self, index: int) -> np.ndarray:
        """RGB of one frame, (H, W, 3) uint8."""
        return self._read(self._rgb, index)

    def read_depth_raw(self, index: int) -> np.ndarray:
        """Depth of one frame as stored (uint16 units or float32 metres)."""
        return self._read(self._depth, index)

    def read_depth(self, index: int) -> np.ndarray:
        """Depth of one frame in metres, float32, 0 where invalid."""
        raw = self.read_depth_raw(index)
        if raw.dtype == np.float32:
            return np.nan_to_num(raw, nan=0.0, posinf=0.0, neginf=0.0)
        return raw.astype(np.float32) / np.float32(self.depth_scale)

    def _read(self, ds: h5py.Dataset, index: int) -> np.ndarray:
        """One frame of `ds`; a chunk that does not decode (flipped bytes, a truncated copy) is
        an `InputError` naming the store and the frame, never data."""
        try:
            return self._decode(ds, index)
        except DECODE_ERRORS as err:
            raise InputError(
                f"{self.path}: frame {index} is damaged ({ds.name.lstrip('/')} chunk: {err}); "
                f"re-create the store with `bgs convert …` (`bgs inspect --verify {self.path}` "
                "lists every damaged frame)"
            ) from err

    def _decode(self, ds: h5py.Dataset, index: int) -> np.ndarray:
        if self._fast:
            mask, chunk = ds.id.read_direct_chunk((index,) + (0,) * (ds.ndim - 1))
            if mask == 0:  # every filter was applied: decode here, off h5py's global lock
                raw = isal_zlib.decompress(chunk)
                if ds.shuffle:
                    return _unshuffle(raw, ds.dtype, ds.shape[1:])
                return np.frombuffer(raw, ds.dtype).reshape(ds.shape[1:]).copy()
        return ds[index]

    def damaged_frames(self, workers: int = READ_WORKERS) -> list[tuple[int, str]]:
        """Decode every chunk of every frame (threaded: decompression releases the GIL) and
        return (frame, problem) for each frame whose colour or depth does not decode."""

        def check(index: int) -> tuple[int, str] | None:
            for ds in (self._rgb, self._depth):
                try:
                    self._decode(ds, index)
                except DECODE_ERRORS as err:
                    return index, f"{ds.name.lstrip('/')} chunk: {err}"
            return None

        with ThreadPoolExecutor(workers) as pool:
            return [found for found in pool.map(check, range(len(self))) if found is not None]

    def _frame(self, index: int, rgb: np.ndarray, depth: np.ndarray) -> Frame:
        pose = None
        if self._poses is not None and np.all(np.isfinite(self._poses[index])):
            pose = self._poses[index].copy()
        depth_time = None
        if self.depth_timestamps is not None:
            depth_time = float(self.depth_timestamps[index])
        return Frame(index, rgb, depth, float(self.timestamps[index]), pose, depth_time)


def _is_our_pipeline(ds: h5py.Dataset) -> bool:
    """True when chunks are exactly one frame of deflate(+shuffle), so we may decode them here."""
    one_frame = ds.chunks == (1,) + ds.shape[1:]
    return bool(
        one_frame and ds.compression == "gzip" and not ds.fletcher32 and ds.scaleoffset is None
    )
