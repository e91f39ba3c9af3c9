"""A job directory's identity and ownership: ``job.json`` and the lock file (docs/usage.md).

``job.json`` records what the job computes (input store with its checksum, resolved config,
package version); running again on the same directory with other inputs or settings is refused
and ``--force`` moves the old run aside whole before starting over, so a job can never mix two
runs. The lock file holds the owner's host and PID and the owner's flock: a second ``bgs run``
on the same job refuses with a clear message naming them, and a lock no process holds (its
owner died, whatever PID it names) is taken over.
"""

from __future__ import annotations

import fcntl
import hashlib
import itertools
import json
import os
import socket
import stat
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from bgs_batch import __version__, atomic
from bgs_batch.errors import BgsError

JOB_FILE = "job.json"
LOCK_FILE = "lock"
CHECKSUM_BLOCK = 1 << 20


class JobError(BgsError):
    """The job directory cannot be used as asked (locked, or made for other inputs)."""

    exit_code = 5


def file_sha256(path: Path) -> str:
    """SHA-256 of a file, read in blocks (stores can be many GB)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(CHECKSUM_BLOCK):
            digest.update(block)
    return digest.hexdigest()


IDENTITY = ("store", "config", "max_frames")  # what must not change between runs of a job
STORE_IDENTITY = ("path", "sha256")  # of the store entry; size and mtime only skip re-hashing


def read_record(job_dir: Path) -> dict[str, Any] | None:
    """The job's ``job.json``, or None when there is none (or it is unreadable)."""
    try:
        return json.loads((job_dir / JOB_FILE).read_text())
    except (OSError, ValueError):
        return None


def store_entry(store: Path, known: dict[str, Any] | None = None) -> dict[str, Any]:
    """Path, SHA-256, size and modification time of a store.

    Hashing a multi-GB store takes seconds, which every resumed job would pay before its first
    frame; when `known` (the entry recorded in ``job.json``) names the same path, size and
    modification time, its checksum is reused (rsync's quick check), else the file is hashed.
    """
    path, stat = Path(store).resolve(), os.stat(store)
    entry = {"path": str(path), "size": stat.st_size, "mtime_ns": stat.st_mtime_ns}
    same_file = known is not None and all(known.get(k) == v for k, v in entry.items())
    entry["sha256"] = known["sha256"] if same_file else file_sha256(path)
    return entry


def job_record(store: Path, config: dict[str, Any], max_frames: int | None,
               previous: dict[str, Any] | None = None) -> dict[str, Any]:  # fmt: skip
    """What identifies a job: its input (path and checksum), settings and package version;
    `previous` is the job's earlier record, whose checksum is reused for an unchanged store."""
    return {
        "store": store_entry(store, (previous or {}).get("store")),
        "config": config,
        "max_frames": max_frames,
        "package_version": __version__,
    }


def _identity(record: dict[str, Any], name: str) -> Any:
    value = record.get(name)
    if name == "store" and isinstance(value, dict):
        return {k: value.get(k) for k in STORE_IDENTITY}
    return value


def check_or_write_record(job_dir: Path, record: dict[str, Any]) -> None:
    """Write ``job.json`` for a new job; for an existing one, refuse changed inputs or settings
    (a store with the same checksum but a new modification time is the same input).

    A folder with other files but no readable ``job.json`` is refused too: resuming whatever
    checkpoints it holds could splice another run into this one.
    """
    path = job_dir / JOB_FILE
    old = read_record(job_dir)
    if old is None and path.exists():
        raise JobError(f"{path} is unreadable, so {job_dir} cannot be resumed safely; pass "
                       "--force to start the job over (the old files are moved aside)")  # fmt: skip
    if old is None and any(p.name != LOCK_FILE for p in job_dir.iterdir()):
        raise JobError(f"{job_dir} is not empty and has no {JOB_FILE}, so it is not a bgs job "
                       "directory; choose a new or empty --job-dir")  # fmt: skip
    if old is not None:
        changes = [name for name in IDENTITY if _identity(old, name) != _identity(record, name)]
        if changes:
            what = " and ".join(changes)
            raise JobError(
                f"{job_dir} belongs to a job with a different {what} (see {path}); use another "
                "--job-dir, or pass --force to start this one over with the new settings"
            )
        if old == record:
            return
    atomic.write_text(path, json.dumps(record, indent=2, sort_keys=True))


def set_aside(job_dir: Path) -> Path | None:
    """`--force`: move a previous run's job directory aside as a whole, under the job's lock,
    and leave an empty one; returns where it went (None when there was no previous run).

    One rename moves every file of the old run at once, so no crash can leave a mix of its
    checkpoints, log or outputs behind for the new run to resume; the moved folder stays a
    complete job directory (`bgs status`, `bgs export` still read it).
    """
    with job_lock(job_dir):
        if not (job_dir / JOB_FILE).exists():
            return None  # a new, empty or foreign folder: check_or_write_record decides
        suffix = f".replaced-{time.strftime('%Y%m%dT%H%M%S')}"
        names = (job_dir.with_name(atomic.fitted_name(job_dir.name, end))
                 for end in _numbered(suffix))  # fmt: skip
        target = next(name for name in names if not name.exists())
        os.rename(job_dir, target)
        job_dir.mkdir()
    (target / LOCK_FILE).unlink(missing_ok=True)
    return target


def _numbered(stem: str) -> Iterator[str]:
    """`stem`, then `stem-1`, `stem-2`, ...: names for folders made in the same second."""
    yield stem
    for n in itertools.count(1):
        yield f"{stem}-{n}"


def _parse_owner(data: bytes) -> dict[str, Any]:
    """The host and PID a lock file names ({} when it names none readably)."""
    try:
        owner = json.loads(data)
    except ValueError:
        return {}
    return owner if isinstance(owner, dict) else {}


def _is_held(fd: int) -> bool:
    """True when a process holds the lock file's flock (the owner does for its whole run; the
    kernel drops it when that process dies). A shared lock works on read-only files and NFS."""
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    fcntl.flock(fd, fcntl.LOCK_UN)
    return False


def _live_owner(fd: int) -> dict[str, Any] | None:
    """The owner named by an open lock file (possibly {}), or None when the lock is stale.

    The flock decides, never the PID the file names: a PID outlives its process in the file and
    is reused after a crash or a requeue, while the kernel drops a flock with its process. A
    lock no process holds is stale whatever it contains."""
    return _parse_owner(os.pread(fd, 4096, 0)) if _is_held(fd) else None


def _open_lock(path: Path) -> int | None:
    """A read-only descriptor of the lock file at `path` (None: there is none), or a
    `JobError` when something else stands there: a directory, a symlink, a loop of them."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return None
    if not stat.S_ISREG(mode):
        kind = "a directory" if stat.S_ISDIR(mode) else (
            "a symbolic link" if stat.S_ISLNK(mode) else "not a regular file")  # fmt: skip
        raise JobError(f"{path} is {kind}, not a bgs lock file; remove it (rm -r {path}) and "
                       "run the command again")  # fmt: skip
    try:
        return os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    except FileNotFoundError:
        return None  # released meanwhile


def lock_owner_alive(job_dir: Path) -> bool:
    """True while a process holds the job's lock."""
    fd = _open_lock(job_dir / LOCK_FILE)
    if fd is None:
        return False
    try:
        return _live_owner(fd) is not None
    finally:
        os.close(fd)


def _reclaim_or_owner(path: Path) -> dict[str, Any] | None:
    """Remove a stale lock and return None, or return the live owner of the lock at `path`."""
    fd = _open_lock(path)
    if fd is None:
        return None
    try:
        owner = _live_owner(fd)
        if owner is not None:
            return owner
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)  # another reclaimer may be here too
        except BlockingIOError:
            return {}
        if os.stat(path).st_ino == os.fstat(fd).st_ino:  # not replaced since it was read
            path.unlink(missing_ok=True)
        return None
    finally:
        os.close(fd)


@contextmanager
def job_lock(job_dir: Path) -> Iterator[None]:
    """Hold the job's lock for the duration of the block.

    The lock file is written whole (host and PID) under a temporary name and hard-linked into
    place, which fails if a lock exists: readers never see an empty lock. Its flock is held
    until the block ends, so a stale lock (dead PID on this host, or unreadable and not held)
    is told apart from a live one and reclaimed.
    """
    path = job_dir / LOCK_FILE
    tmp = atomic.temp_name(path)
    fd = os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        os.write(fd, json.dumps({"host": socket.gethostname(), "pid": os.getpid()}).encode())
        os.fsync(fd)
        while True:
            try:
                os.link(tmp, path)
                break
            except FileExistsError:
                owner = _reclaim_or_owner(path)
                if owner is not None:
                    raise JobError(
                        f"{job_dir} is in use by process {owner.get('pid', '?')} on "
                        f"{owner.get('host', '?')}; wait for it to finish (bgs status "
                        f"{job_dir}), or delete {path} if that process is really gone"
                    ) from None
    except BaseException:
        os.close(fd)
        raise
    finally:
        tmp.unlink(missing_ok=True)
    try:
        yield
    finally:
        path.unlink(missing_ok=True)
        os.close(fd)
