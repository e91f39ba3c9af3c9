"""Decode ROS image messages (``sensor_msgs/Image`` and ``CompressedImage``) into numpy arrays.

Colour comes out as (H, W, 3) uint8 in RGB order. Depth follows REP 118: ``16UC1``/``mono16`` as
uint16 millimetres and ``32FC1`` as float32 metres, with 0 marking invalid pixels (NaN, inf and
non-positive floats become 0). ``compressedDepth`` messages (compressed_depth_image_transport)
start with a 12-byte header ``int32 format, float32 depthQuantA, float32 depthQuantB`` followed by
a PNG: raw millimetres for 16UC1, quantised inverse depth for 32FC1.
"""

from __future__ import annotations

import struct
from typing import Any

import cv2
import numpy as np

from converters.image_codec import ImageDecodeError, decode

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)

COLOR, DEPTH, MONO = "colour", "depth", "mono"

# encoding -> (dtype, channels, cv2 conversion to RGB or None when already RGB)
COLOR_ENCODINGS: dict[str, tuple[np.dtype, int, int | None]] = {
    "rgb8": (np.dtype(np.uint8), 3, None),
    "bgr8": (np.dtype(np.uint8), 3, cv2.COLOR_BGR2RGB),
    "rgba8": (np.dtype(np.uint8), 4, cv2.COLOR_RGBA2RGB),
    "bgra8": (np.dtype(np.uint8), 4, cv2.COLOR_BGRA2RGB),
    "mono8": (np.dtype(np.uint8), 1, cv2.COLOR_GRAY2RGB),
}
DEPTH_ENCODINGS: dict[str, np.dtype] = {
    "16UC1": np.dtype(np.uint16),
    "mono16": np.dtype(np.uint16),
    "32FC1": np.dtype(np.float32),
}
DEPTH_UNITS_PER_METRE = {"16UC1": 1000.0, "mono16": 1000.0, "32FC1": 1.0}  # REP 118

# OpenCV builds that have IMREAD_COLOR_RGB decode JPEG/PNG straight into RGB order: the
# same pixels as IMREAD_COLOR + COLOR_BGR2RGB without the extra pass and image buffer
IMREAD_COLOR_RGB: int | None = getattr(cv2, "IMREAD_COLOR_RGB", None)

COMPRESSED_DEPTH = "compressedDepth"
COMPRESSED_DEPTH_HEADER = struct.Struct("<iff")  # format, depthQuantA, depthQuantB
INVERSE_DEPTH_FORMAT = 0


def original_encoding(msgtype: str, msg: Any) -> str:
    """Raw encoding of an image message; for compressed images the part before ``;`` if any."""
    if msgtype == IMAGE:
        return msg.encoding
    head, sep, _ = msg.format.partition(";")
    return head.strip() if sep else ""


def image_role(msgtype: str, msg: Any) -> str | None:
    """Whether an image topic carries colour, depth or monochrome (e.g. infrared) images."""
    encoding = original_encoding(msgtype, msg)
    if encoding in DEPTH_ENCODINGS or (
        msgtype == COMPRESSED_IMAGE and COMPRESSED_DEPTH in msg.format
    ):
        return DEPTH
    if encoding == "mono8":
        return MONO
    if encoding in COLOR_ENCODINGS or msgtype == COMPRESSED_IMAGE:
        return COLOR
    return None


def depth_encoding(msgtype: str, msg: Any) -> str:
    """The REP 118 encoding of a depth message (compressedDepth without one means 16UC1)."""
    return original_encoding(msgtype, msg) or "16UC1"


def decode_color(msgtype: str, msg: Any) -> np.ndarray:
    """(H, W, 3) uint8 RGB from an Image (rgb8, bgr8, rgba8, bgra8, mono8) or a JPEG/PNG."""
    if msgtype == COMPRESSED_IMAGE:
        if IMREAD_COLOR_RGB is not None:
            return _imdecode(msg.data, IMREAD_COLOR_RGB, msg.format)
        image = _imdecode(msg.data, cv2.IMREAD_COLOR, msg.format)
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if msg.encoding not in COLOR_ENCODINGS:
        raise ImageDecodeError(
            f"colour encoding {msg.encoding!r} is not supported "
            f"(supported: {', '.join(COLOR_ENCODINGS)})"
        )
    dtype, channels, conversion = COLOR_ENCODINGS[msg.encoding]
    pixels = _raw_pixels(msg, dtype, channels)
    return pixels.copy() if conversion is None else cv2.cvtColor(pixels, conversion)


def decode_depth(msgtype: str, msg: Any) -> np.ndarray:
    """(H, W) uint16 mm or float32 m from an Image (16UC1, mono16, 32FC1) or compressed depth."""
    if msgtype == COMPRESSED_IMAGE:
        if COMPRESSED_DEPTH in msg.format:
            return _decode_compressed_depth(msg)
        depth = _imdecode(msg.data, cv2.IMREAD_UNCHANGED, msg.format)
        return _require_uint16(depth, msg.format)
    encoding = msg.encoding
    if encoding not in DEPTH_ENCODINGS:
        raise ImageDecodeError(
            f"depth encoding {encoding!r} is not supported "
            f"(supported: {', '.join(DEPTH_ENCODINGS)})"
        )
    depth = _raw_pixels(msg, DEPTH_ENCODINGS[encoding], 1)
    return _clean_float(depth) if depth.dtype == np.float32 else depth.copy()


def _raw_pixels(msg: Any, dtype: np.dtype, channels: int) -> np.ndarray:
    """View the pixel rows of an Image, honouring ``step`` padding and ``is_bigendian``."""
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = width * channels * dtype.itemsize
    data = np.asarray(msg.data, np.uint8)
    if step < row_bytes or data.size < height * step:
        raise ImageDecodeError(
            f"{width}x{height} {msg.encoding} image needs {height} rows of {row_bytes} bytes, "
            f"but has step {step} and {data.size} bytes (truncated or corrupt message)"
        )
    rows = data[: height * step].reshape(height, step)[:, :row_bytes]
    order = ">" if msg.is_bigendian else "<"
    pixels = np.ascontiguousarray(rows).view(dtype.newbyteorder(order))
    pixels = pixels.reshape(height, width, channels) if channels > 1 else pixels
    return pixels.astype(dtype, copy=False)


def _decode_compressed_depth(msg: Any) -> np.ndarray:
    data = np.frombuffer(msg.data, np.uint8)  # a view: no copy of the payload
    if "rvl" in msg.format.lower():
        raise ImageDecodeError(
            f"compressedDepth format {msg.format!r} (RVL) is not supported; "
            "record with the png codec"
        )
    if len(data) <= COMPRESSED_DEPTH_HEADER.size:
        raise ImageDecodeError(f"compressedDepth message of {len(data)} bytes has no payload")
    kind, quant_a, quant_b = COMPRESSED_DEPTH_HEADER.unpack_from(data)
    payload = data[COMPRESSED_DEPTH_HEADER.size :]
    values = _require_uint16(_imdecode(payload, cv2.IMREAD_UNCHANGED, msg.format), msg.format)
    if depth_encoding(COMPRESSED_IMAGE, msg) != "32FC1":
        return values
    if kind != INVERSE_DEPTH_FORMAT:
        raise ImageDecodeError(f"compressedDepth 32FC1 header format {kind} is not inverse depth")
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.float32(quant_a) / (values.astype(np.float32) - np.float32(quant_b))
    depth[values == 0] = 0.0
    return _clean_float(depth)


def _imdecode(data: Any, flags: int, fmt: str) -> np.ndarray:
    """Decode a whole JPEG/PNG held in any bytes-like object or uint8 array, without copying."""
    return decode(data, flags, f"image ({fmt})" if fmt else "image")


def _require_uint16(image: np.ndarray, fmt: str) -> np.ndarray:
    if image.dtype != np.uint16 or image.ndim != 2:
        raise ImageDecodeError(
            f"{fmt} depth must be a 16-bit single-channel PNG, got {image.dtype} {image.shape}"
        )
    return image


def _clean_float(depth: np.ndarray) -> np.ndarray:
    """float32 metres with NaN, inf and non-positive readings set to 0 (the store's 'invalid')."""
    depth = depth.astype(np.float32, copy=True)
    depth[~(np.isfinite(depth) & (depth > 0))] = 0.0
    return depth
