"""ScanNet's raw ``.sens`` recordings (SensorData version 4), indexed once and read per frame.

Layout, all little-endian::

    uint32 version (4) | uint64 n + n bytes sensor name
    float32[16] colour intrinsics, colour extrinsics, depth intrinsics, depth extrinsics (4x4 each)
    int32 colour compression (0 raw, 1 png, 2 jpeg) | int32 depth compression (0 raw, 1 zlib)
    uint32 colour width, height, depth width, height | float32 depth shift (units per metre)
    uint64 frame count, then per frame:
        float32[16] camera-to-world | uint64 colour and depth timestamps
        uint64 colour bytes, depth bytes | the colour image | the depth image (uint16)

`write_sens` writes the same layout (JPEG colour, zlib depth) for tests and benchmarks.
Indexing walks the frame records (seeking over the images), so a truncated file is refused
before anything is written and each frame can then be read on its own by a worker thread.
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np

from bgs_batch.errors import InputError
from converters import image_codec
from converters.image_codec import ImageDecodeError

SENS_VERSION = 4
COLOR_CODECS = {0: "raw", 1: "png", 2: "jpeg"}
DEPTH_CODECS = {0: "raw_ushort", 1: "zlib_ushort"}  # 2 (occi_ushort) is not supported
JPEG_CODEC, ZLIB_CODEC = 2, 1  # what write_sens writes
UINT32 = struct.Struct("<I")
UINT64 = struct.Struct("<Q")
MATRIX = struct.Struct("<16f")
CODECS_AND_SIZES = struct.Struct("<ii4If")
FRAME_RECORD = struct.Struct("<16f4Q")  # pose, colour/depth timestamps, colour/depth sizes
DEPTH_PIXEL = np.dtype("<u2")


@dataclass(frozen=True)
class SensHeader:
    """Calibration and stream formats of a ``.sens`` file."""

    sensor_name: str
    depth_intrinsics: np.ndarray  # 4x4 (colour is resized onto the depth camera, see scannet)
    color_codec: str
    depth_codec: str
    color_size: tuple[int, int]  # (width, height)
    depth_size: tuple[int, int]
    depth_shift: float  # units per metre
    frame_count: int


@dataclass(frozen=True)
class SensFrame:
    """Where one frame's images are in the file, and its camera-to-world pose."""

    index: int
    camera_to_world: np.ndarray  # 4x4 float64 (from float32), may hold -inf
    color_offset: int
    color_bytes: int
    depth_bytes: int


def read_sens_index(path: Path) -> tuple[SensHeader, list[SensFrame]]:
    """Parse the header and every frame record of a ``.sens`` file (images are skipped)."""
    size = path.stat().st_size
    try:
        with open(path, "rb") as fh:
            header = _read_header(fh, path)
            frames = [_read_frame_record(fh, i, size) for i in range(header.frame_count)]
    except _Truncated as err:
        raise InputError(
            f"{path} is truncated or damaged ({err}): download it again"
        ) from None
    return header, frames


class _Truncated(Exception):
    """The file ends inside a record."""


def _read(fh: BinaryIO, size: int) -> bytes:
    """`size` bytes, or `_Truncated` when fewer are left (also for a garbage length)."""
    left = os.fstat(fh.fileno()).st_size - fh.tell()
    if size > left:
        raise _Truncated(f"{size} bytes wanted at offset {fh.tell()}, {left} left")
    return fh.read(size)


def _read_header(fh: BinaryIO, path: Path) -> SensHeader:
    (version,) = UINT32.unpack(_read(fh, UINT32.size))
    if version != SENS_VERSION:
        raise InputError(
            f"{path} is SensorData version {version}, but only version {SENS_VERSION} (ScanNet "
            "v2) is supported; re-download the scene or export it with ScanNet's SensReader"
        )
    (name_length,) = UINT64.unpack(_read(fh, UINT64.size))
    name = _read(fh, name_length).decode("utf-8", "replace")
    _, _, depth_k, _ = (  # colour intrinsics and extrinsics, depth intrinsics and extrinsics
        np.asarray(MATRIX.unpack(_read(fh, MATRIX.size)), np.float64).reshape(4, 4)
        for _ in range(4)
    )
    color_codec, depth_codec, cw, ch, dw, dh, shift = CODECS_AND_SIZES.unpack(
        _read(fh, CODECS_AND_SIZES.size)
    )
    (frames,) = UINT64.unpack(_read(fh, UINT64.size))
    if color_codec not in COLOR_CODECS or depth_codec not in DEPTH_CODECS:
        raise InputError(
            f"{path}: colour compression {color_codec} / depth compression {depth_codec} is not "
            f"supported (colour: {COLOR_CODECS}, depth: {DEPTH_CODECS})"
        )
    return SensHeader(
        name,
        depth_k,
        COLOR_CODECS[color_codec],
        DEPTH_CODECS[depth_codec],
        (cw, ch),
        (dw, dh),
        shift,
        frames,
    )


def _read_frame_record(fh: BinaryIO, index: int, file_size: int) -> SensFrame:
    *pose, _, _, color_bytes, depth_bytes = FRAME_RECORD.unpack(_read(fh, FRAME_RECORD.size))
    offset = fh.tell()
    end = offset + color_bytes + depth_bytes
    if end > file_size:
        raise _Truncated(f"frame {index} needs bytes up to {end}, the file has {file_size}")
    fh.seek(end)
    return SensFrame(
        index, np.asarray(pose, np.float64).reshape(4, 4), offset, color_bytes, depth_bytes
    )


def read_frame(path: Path, header: SensHeader, frame: SensFrame) -> tuple[np.ndarray, np.ndarray]:
    """One frame's colour (H, W, 3) BGR at colour size and depth (uint16) at depth size."""
    with open(path, "rb") as fh:
        fh.seek(frame.color_offset)
        color = fh.read(frame.color_bytes)
        depth = fh.read(frame.depth_bytes)
    where = f"{path} frame {frame.index}"
    if header.color_codec == "raw":  # 8-bit RGB
        width, height = header.color_size
        bgr = cv2.cvtColor(
            np.frombuffer(color, np.uint8).reshape(height, width, 3), cv2.COLOR_RGB2BGR
        )
    else:
        try:
            bgr = image_codec.decode(color, cv2.IMREAD_COLOR, f"{header.color_codec} colour image")
        except ImageDecodeError as err:
            raise InputError(f"{where}: {err}; pass --skip-bad-frames to drop such frames"
                             ) from None  # fmt: skip
    try:
        raw = zlib.decompress(depth) if header.depth_codec == "zlib_ushort" else depth
    except zlib.error as err:
        raise InputError(
            f"{where}: corrupt depth ({err}); pass --skip-bad-frames to drop such frames"
        ) from None
    width, height = header.depth_size
    if len(raw) != width * height * DEPTH_PIXEL.itemsize:
        raise InputError(f"{where}: depth has {len(raw)} bytes, not {width}x{height} uint16")
    return bgr, np.frombuffer(raw, DEPTH_PIXEL).reshape(height, width).astype(np.uint16)


def write_sens(
    path: Path,
    frames: Sequence[tuple[bytes, np.ndarray, np.ndarray]],
    color_intrinsics: np.ndarray,
    depth_intrinsics: np.ndarray,
    color_size: tuple[int, int],
    depth_shift: float = 1000.0,
    sensor_name: str = "bgs-batch",
) -> Path:
    """Write (JPEG colour bytes, uint16 depth, 4x4 camera-to-world) frames as a ``.sens``."""
    depth_size = frames[0][1].shape[::-1]
    name = sensor_name.encode()
    eye = np.eye(4)
    with open(path, "wb") as fh:
        fh.write(UINT32.pack(SENS_VERSION) + UINT64.pack(len(name)) + name)
        for matrix in (color_intrinsics, eye, depth_intrinsics, eye):
            fh.write(MATRIX.pack(*np.ravel(matrix)))
        fh.write(
            CODECS_AND_SIZES.pack(JPEG_CODEC, ZLIB_CODEC, *color_size, *depth_size, depth_shift)
        )
        fh.write(UINT64.pack(len(frames)))
        for index, (color, depth, pose) in enumerate(frames):
            packed = zlib.compress(depth.astype(DEPTH_PIXEL).tobytes())
            fh.write(FRAME_RECORD.pack(*np.ravel(pose), index, index, len(color), len(packed)))
            fh.write(color + packed)
    return path
