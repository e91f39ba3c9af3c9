"""Strict decoding of compressed images (a file that is not whole is an error, not data), and
PNG writing whose failures say why.

OpenCV's ``imdecode`` fills the missing rows of a truncated JPEG with grey and returns it
without complaint, so every converter decodes through `decode`, which first checks that the
bytes end where their format says an image ends: a JPEG with its end-of-image marker (FF D9;
inside the entropy-coded data an FF byte is always stuffed or a restart marker, so the marker
can only end the image), a PNG with its IEND chunk. A JPEG damaged in its middle keeps its end
marker, and libjpeg decodes it with a warning ("Corrupt JPEG data: …") that OpenCV only prints:
such an image is first decoded by libjpeg-turbo through simplejpeg in strict mode, where every
warning is an error. The pixels still come from OpenCV, so a whole image decodes as before.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import simplejpeg

from bgs_batch.errors import naming

JPEG_START, JPEG_END = b"\xff\xd8", b"\xff\xd9"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_END = b"IEND\xaeB`\x82"  # the IEND chunk's type and CRC
TRAILING_PADDING = b"\x00\r\n\t "  # bytes some writers append after the image
# OpenCV's own warnings ("[ WARN:0@…] …") would reach the terminal before the one-line error
# that names the file; errors still come through
cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


class ImageDecodeError(ValueError):
    """Image bytes that do not decode to a whole image."""


def decode(data: Any, flags: int, what: str = "image") -> np.ndarray:
    """Decode JPEG or PNG bytes (any bytes-like object or uint8 array, not copied) with OpenCV
    `flags`; raises `ImageDecodeError` naming `what` when they are truncated or corrupt."""
    buffer = np.frombuffer(data, np.uint8)
    head = buffer[:8].tobytes()
    tail = buffer[-64:].tobytes().rstrip(TRAILING_PADDING)
    if head.startswith(JPEG_START) and not tail.endswith(JPEG_END):
        raise ImageDecodeError(f"truncated JPEG {what}: it does not end with the end-of-image "
                               "marker")  # fmt: skip
    if head == PNG_SIGNATURE and not tail.endswith(PNG_END):
        raise ImageDecodeError(f"truncated PNG {what}: it has no IEND chunk at its end")
    if head.startswith(JPEG_START):
        try:
            simplejpeg.decode_jpeg(buffer, strict=True)
        except ValueError as err:
            raise ImageDecodeError(f"corrupt JPEG {what}: {err}") from None
    image = cv2.imdecode(buffer, flags)
    if image is None:
        raise ImageDecodeError(f"corrupt or truncated {what} data")
    return image


def read(path: Any, flags: int, what: str = "image") -> np.ndarray:
    """`decode` the file at `path`; raises `ImageDecodeError` naming the file when it cannot be
    read or decoded."""
    try:
        return decode(np.fromfile(str(path), np.uint8), flags, what)
    except OSError as err:
        raise ImageDecodeError(f"{path}: cannot be read ({err.strerror or err})") from None
    except ImageDecodeError as err:
        raise ImageDecodeError(f"{path}: {err}") from None


def write_png(path: Path, image: np.ndarray, compression: int | None = None) -> None:
    """Write an image (BGR, grey or 16-bit) as PNG, with zlib level `compression` (default:
    OpenCV's). Encoded in memory and written by Python, so a full or read-only disk raises an
    `OSError` carrying its errno and path (``cv2.imwrite`` only returns False)."""
    params = [] if compression is None else [cv2.IMWRITE_PNG_COMPRESSION, compression]
    ok, data = cv2.imencode(".png", image, params)
    if not ok:
        raise ValueError(f"OpenCV cannot encode a {image.dtype} {image.shape} image as PNG")
    with naming(path):
        Path(path).write_bytes(data.tobytes())
