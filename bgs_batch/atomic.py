"""All-or-nothing files and folders: built under a temporary name beside the target, then renamed.

Every writer in the project (frame stores, checkpoints, job records, submap files, exports) gives
the same guarantee through this module: a reader, a crash or a power cut sees either the previous
complete file or the new complete one, never half of one. The data is fsynced before the rename
and the folder after it, so the rename is durable; on any error, also Ctrl-C, the temporary is
removed and the target is kept. Temporary names start with ``.tmp-`` on the same file system, so
`os.replace` is atomic; they get the usual permissions (umask), not the private ones of `tempfile`.
"""

from __future__ import annotations

import fcntl
import io
import os
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from bgs_batch.errors import InUseError, naming

TEMP_PREFIX = ".tmp-"
NAME_MAX = 255  # bytes of one name on Linux's file systems (ext4, xfs, btrfs, tmpfs, NFS)


def fitted_name(name: str, suffix: str, prefix: str = "") -> str:
    """``prefix + name + suffix``, with `name` shortened (from its end) so that the whole fits
    in `NAME_MAX` bytes: a legal output name must not fail because of a temporary name."""
    room = NAME_MAX - len((prefix + suffix).encode())
    encoded = name.encode()
    if len(encoded) > room:
        name = encoded[:room].decode(errors="ignore")
    return prefix + name + suffix


def temp_name(path: Path, tag: str = "") -> Path:
    """A unique, hidden name beside `path`."""
    suffix = f".{tag}{os.getpid()}.{uuid.uuid4().hex[:8]}"
    return path.with_name(fitted_name(path.name, suffix, TEMP_PREFIX))


@contextmanager
def writer_lock(path: Path, what: str) -> Iterator[None]:
    """Be the only process writing `path` for the duration of the block: an flock on a hidden
    lock file beside it (``.lock-NAME``, removed at the end; one left by a killed process is
    held by nobody and taken over). Another writer gets an `InUseError` naming the process
    (`what` says which command, for the message)."""
    lock = path.with_name(fitted_name(path.name, "", ".lock-"))
    while True:
        fd = os.open(lock, os.O_CREAT | os.O_RDWR, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            owner = os.pread(fd, 64, 0).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise InUseError(f"{path} is being written by another {what} (process {owner}); "
                             "wait for it to finish, or choose another output") from None
        try:
            if os.fstat(fd).st_ino == os.stat(lock).st_ino:  # not unlinked by its last owner
                break
        except FileNotFoundError:
            pass
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        yield
    finally:
        lock.unlink(missing_ok=True)
        os.close(fd)


def remove_temporaries(folder: Path) -> list[Path]:
    """Delete the temporaries a killed writer (``kill -9``, power cut) left in `folder`; only call
    it while no other writer uses the folder (e.g. under the job's lock). Returns what went."""
    found = sorted(Path(folder).glob(f"{TEMP_PREFIX}*")) if Path(folder).is_dir() else []
    for path in found:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
    return found


def fsync_path(path: Path) -> None:
    """Flush a file's data, or a folder's entries, to the disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def commit(tmp: Path, path: Path) -> None:
    """Make the finished file `tmp` durable and move it to `path` in one step."""
    fsync_path(tmp)
    os.replace(tmp, path)
    fsync_path(path.parent)


@contextmanager
def atomic_file(path: Path) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces `path`, on error it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_name(path)
    tmp.touch(exist_ok=False)
    try:
        with naming(path):
            yield tmp
            commit(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_bytes(path: Path, data: bytes) -> None:
    """Write `data` to `path` atomically."""
    with atomic_file(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: Path, text: str) -> None:
    """Write `text` (UTF-8) to `path` atomically."""
    write_bytes(path, text.encode())


def save_torch(obj: Any, path: Path) -> None:
    """`torch.save(obj)` to `path` atomically. Saved through a buffer, because torch names the
    archive's root folder after the file it writes: a temporary name would make the same object
    give different bytes each time."""
    import torch  # here: writers of frame stores and exports do not need it

    buffer = io.BytesIO()
    torch.save(obj, buffer)
    write_bytes(path, buffer.getvalue())


@contextmanager
def atomic_dir(path: Path) -> Iterator[Path]:
    """Yield an empty temporary folder; on success it replaces the folder `path` as a whole.

    The old folder (or a symlink in its place) is moved aside first and deleted after the new one
    is in place, so no file of an earlier output lingers; on error the temporary folder is
    removed and `path` is kept.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_name(path)
    tmp.mkdir()
    try:
        with naming(path):
            yield tmp
        for folder, _, files in os.walk(tmp):
            for name in files:
                fsync_path(Path(folder, name))
            fsync_path(Path(folder))
        old = None
        if path.exists() or path.is_symlink():
            old = temp_name(path, "old.")
            os.replace(path, old)
        os.replace(tmp, path)
        fsync_path(path.parent)
        if old is not None and old.is_symlink():
            old.unlink()
        elif old is not None:
            shutil.rmtree(old)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
