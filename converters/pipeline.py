"""The conversion pipeline shared by every converter: decode and compress on a thread pool,
write chunks in order, drop or refuse bad frames, and leave nothing behind on failure.

Every frame allocates and frees buffers of about a megabyte (decoded images, the shuffled depth,
ISA-L's deflate output, which grows by doubling from 16 KiB). glibc's malloc hands blocks above
its mmap threshold straight back to the kernel and trims an arena's free top above its trim
threshold; both start at 128 KiB and rise only to the largest mmapped block freed so far (and
twice that). So unless something bigger was freed first, every frame's buffers are page-faulted
and zeroed afresh: ROS1 and MCAP readers free multi-megabyte chunk buffers early and are spared,
ROS2 sqlite3 rows are smaller, and a 240-frame VGA ``.db3`` conversion spent 0.15-0.2 s more CPU
in the kernel (60k page faults against 15k). `write_store` therefore sets the two thresholds to
the values glibc's own adjustment tops out at (once per process, glibc only).
"""

from __future__ import annotations

import ctypes
import os
import platform
import time
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from bgs_batch.atomic import writer_lock
from bgs_batch.errors import InputError
from bgs_batch.signals import interruptible
from bgs_batch.store import (
    DEFAULT_COMPRESSION_LEVEL,
    EncodedFrame,
    FrameStoreWriter,
    StoreMeta,
    check_output_path,
    encode_frame,
    temp_path,
)

DEFAULT_WORKERS = 2
IN_FLIGHT_PER_WORKER = 2  # frames decoded ahead per worker: bounds memory, keeps cores busy
FLUSH_EVERY_FRAMES = 16  # frames between background flushes of the store being written
_sync_data = getattr(os, "fdatasync", os.fsync)
# glibc mallopt(3): the ceiling of the dynamic mmap threshold on 64-bit, and the trim threshold
# glibc pairs with it (twice the mmap threshold)
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
HEAP_MMAP_THRESHOLD = 32 << 20
HEAP_TRIM_THRESHOLD = 2 * HEAP_MMAP_THRESHOLD
_heap_tuned = False


@dataclass(frozen=True)
class SourceFrame:
    """One frame of a recording, not yet decoded.

    `load` returns (rgb (H, W, 3) uint8 in RGB order, depth (H, W) uint16 units or float32
    metres) and raises `InputError` naming the offending file when the data is bad.
    """

    name: str
    timestamp: float
    pose_gt: np.ndarray | None
    load: Callable[[], tuple[np.ndarray, np.ndarray]]
    depth_timestamp: float | None = None  # when the depth image was taken, if not with colour


@dataclass
class ConversionReport:
    """What a conversion wrote and what it had to drop."""

    path: Path
    frames: int
    seconds: float
    skipped: list[dict[str, str]] = field(default_factory=list)


def write_store(
    frames: Iterable[SourceFrame],
    out: Path,
    meta: StoreMeta,
    *,
    overwrite: bool = False,
    skip_bad_frames: bool = False,
    workers: int = DEFAULT_WORKERS,
    level: int = DEFAULT_COMPRESSION_LEVEL,
    progress: Callable[[int], None] | None = None,
) -> ConversionReport:
    """Decode, compress and write `frames` into a new store at `out` (atomically).

    Frames are decoded and compressed `workers` at a time with a bounded look-ahead, and written
    in input order. A bad frame aborts the conversion with its error, or is dropped and listed in
    the store's provenance when `skip_bad_frames` is set. Ctrl-C / SIGTERM abort cleanly.
    """
    keep_frame_buffers_in_heap()
    check_output_path(Path(out), overwrite)  # before the lock file is made beside it
    with interruptible() as interruption, writer_lock(Path(out), "bgs convert"):
        try:
            return _write(frames, out, meta, overwrite, skip_bad_frames, workers, level, progress,
                          interruption)  # fmt: skip
        finally:  # a signal can land between the temp file's creation and the writer's `with`
            temp_path(out).unlink(missing_ok=True)


def _write(frames, out, meta, overwrite, skip_bad_frames, workers, level, progress, interruption):
    start = time.perf_counter()
    skipped: list[dict[str, str]] = []

    def encode(frame: SourceFrame) -> EncodedFrame:
        rgb, depth = frame.load()
        return encode_frame(rgb, depth, frame.timestamp, frame.pose_gt, level,
                            frame.depth_timestamp)  # fmt: skip

    with (
        FrameStoreWriter(out, meta, overwrite=overwrite, level=level) as writer,
        ThreadPoolExecutor(max(1, workers)) as pool,
        _BackgroundFlush(temp_path(out)) as flush,
    ):
        pending: deque[tuple[SourceFrame, Future[EncodedFrame]]] = deque()

        def drain_one() -> None:
            interruption.check()
            frame, future = pending.popleft()
            try:
                writer.append(future.result(), frame.name)
                flush.frame_written(len(writer))
            except InputError as err:
                if not skip_bad_frames:
                    pool.shutdown(cancel_futures=True)
                    raise
                skipped.append({"frame": frame.name, "reason": str(err)})
            if progress is not None:
                progress(1)

        try:
            for frame in frames:
                pending.append((frame, pool.submit(encode, frame)))
                if len(pending) >= workers * IN_FLIGHT_PER_WORKER:
                    drain_one()
            while pending:
                drain_one()
        except BaseException:
            pool.shutdown(cancel_futures=True)
            raise
        if len(writer) == 0:
            raise InputError(f"every frame was bad; nothing written to {out}")
        if skipped:
            writer.meta = replace(meta, provenance={**meta.provenance, "skipped_frames": skipped})
        interruption.check()  # the last chance before the store is committed
        path = writer.finish()
    return ConversionReport(path, frames=len(writer), seconds=time.perf_counter() - start,
                            skipped=skipped)  # fmt: skip


def keep_frame_buffers_in_heap() -> bool:
    """Let glibc reuse freed megabyte-sized buffers instead of returning them to the kernel
    (see the module doc); True if the thresholds are set. Process-wide and idempotent; a no-op
    (False) off glibc."""
    global _heap_tuned
    if not _heap_tuned and platform.libc_ver()[0] == "glibc":
        mallopt = ctypes.CDLL(None).mallopt
        mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
        trim = mallopt(M_TRIM_THRESHOLD, HEAP_TRIM_THRESHOLD)  # each returns 1 on success
        mmap = mallopt(M_MMAP_THRESHOLD, HEAP_MMAP_THRESHOLD)
        _heap_tuned = trim == 1 and mmap == 1
    return _heap_tuned


class _BackgroundFlush:
    """Writes the store being built to disk on a helper thread as it grows, so the fsync that
    makes the finished store durable has little left to write instead of the whole store.

    A failed flush is not reported here: the writer's own fsync fails the same way.
    """

    def __init__(self, path: Path) -> None:
        self._fd = os.open(path, os.O_RDONLY)
        self._helper = ThreadPoolExecutor(1)
        self._running: Future[None] | None = None

    def __enter__(self) -> _BackgroundFlush:
        return self

    def __exit__(self, *_: object) -> None:
        self._helper.shutdown(wait=True)
        os.close(self._fd)

    def frame_written(self, count: int) -> None:
        """Start a flush every `FLUSH_EVERY_FRAMES` frames, unless the last one still runs."""
        if count % FLUSH_EVERY_FRAMES == 0 and (self._running is None or self._running.done()):
            self._running = self._helper.submit(_sync_data, self._fd)
