"""All-or-nothing output: files and folders are built under a temporary name, then renamed.

A reader (or a crash) therefore sees either the previous complete output or the new complete
output, never a half-written one. Temporary names start with ``.tmp-`` beside the target, on the
same file system, so the final `os.replace` is atomic; they are made with the usual permissions
(umask), not the private ones of `tempfile`.
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

TEMP_PREFIX = ".tmp-"


def temp_name(path: Path, tag: str = "") -> Path:
    """A unique, hidden name beside `path`."""
    return path.with_name(f"{TEMP_PREFIX}{path.name}.{tag}{os.getpid()}.{uuid.uuid4().hex[:8]}")


@contextmanager
def atomic_file(path: Path) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces `path`, on error it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_name(path)
    tmp.touch(exist_ok=False)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


@contextmanager
def atomic_dir(path: Path) -> Iterator[Path]:
    """Yield an empty temporary folder; on success it replaces the folder `path` as a whole.

    The old folder is moved aside first and deleted after the new one is in place, so no file
    of an earlier export lingers; on error the temporary folder is removed and `path` is kept.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_name(path)
    tmp.mkdir()
    try:
        yield tmp
        old = None
        if path.exists():
            old = temp_name(path, "old.")
            os.replace(path, old)
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
