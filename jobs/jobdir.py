"""A job directory's identity and ownership: ``job.json`` and the lock file (docs/usage.md).

``job.json`` records what the job computes (input store with its checksum, resolved config,
package version); running again on the same directory with other inputs or settings is refused
unless forced, so a resumed job can never silently mix two configurations. The lock file holds
the owner's host and PID: a second ``bgs run`` on the same job refuses with a clear message,
and a lock left by a dead process (same host, PID gone) is taken over.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import socket
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


def check_or_write_record(job_dir: Path, record: dict[str, Any], force: bool) -> None:
    """Write ``job.json`` for a new job; for an existing one, refuse changed inputs or settings
    (a store with the same checksum but a new modification time is the same input)."""
    path = job_dir / JOB_FILE
    old = read_record(job_dir) if path.exists() else None
    if old is not None and not force:
        changes = [name for name in IDENTITY if _identity(old, name) != _identity(record, name)]
        if changes:
            what = " and ".join(changes)
            raise JobError(
                f"{job_dir} belongs to a job with a different {what} (see {path}); use another "
                "--job-dir, or pass --force to restart this one with the new settings"
            )
        if old == record:
            return
    atomic.write_text(path, json.dumps(record, indent=2, sort_keys=True))


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except OSError as err:
        return err.errno == errno.EPERM  # exists, owned by someone else
    return True


def _read_owner(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _is_stale(owner: dict[str, Any]) -> bool:
    """A lock is stale when it names a process on this host that no longer exists."""
    pid = owner.get("pid")
    if owner.get("host") != socket.gethostname() or not isinstance(pid, int):
        return False
    return not _pid_alive(pid)


def lock_owner_alive(job_dir: Path) -> bool:
    """True while the process holding the job's lock may still be running."""
    path = job_dir / LOCK_FILE
    return path.exists() and not _is_stale(_read_owner(path))


@contextmanager
def job_lock(job_dir: Path) -> Iterator[None]:
    """Hold the job's lock for the duration of the block (atomic create; stale locks reclaimed)."""
    path = job_dir / LOCK_FILE
    me = {"host": socket.gethostname(), "pid": os.getpid()}
    while True:
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            owner = _read_owner(path)
            if _is_stale(owner):
                path.unlink(missing_ok=True)  # its process is gone
                continue
            raise JobError(
                f"{job_dir} is in use by process {owner.get('pid', '?')} on "
                f"{owner.get('host', '?')}; wait for it to finish (bgs status {job_dir}), or "
                f"delete {path} if that process is really gone"
            ) from None
        with os.fdopen(fd, "w") as fh:
            json.dump(me, fh)
        break
    try:
        yield
    finally:
        path.unlink(missing_ok=True)
