"""Errors users can act on: each carries a message naming the file and the fix, and an exit code.

Exit codes (documented in README):

- 0 success
- 1 unexpected internal error (a bug: please report it)
- 2 usage error (bad command line; Click's convention)
- 3 invalid input data (missing, unreadable or inconsistent files)
- 4 output already exists (pass ``--overwrite`` to replace it)
- 5 job directory in use by another process, or made for another store or settings; an output
  another bgs process is writing
- 6 the file system refused: disk full, read-only, permission denied, a name too long, a
  symlink loop, a folder where a file belongs (the path is named;
  nothing half-written is kept, and the same command continues once it is fixed)
- 75 a job stopped by SIGTERM/SIGUSR1/SIGINT after checkpointing (run it again to continue)
- 128 + N interrupted by signal N (130 for Ctrl-C, 143 for SIGTERM); nothing half-written is left
"""

import errno
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


class BgsError(Exception):
    """Base class of errors that are reported to the user without a traceback."""

    exit_code = 1


class InputError(BgsError):
    """The input data is missing, unreadable or inconsistent."""

    exit_code = 3


class OutputExistsError(BgsError):
    """The output path exists and the user did not ask to overwrite it."""

    exit_code = 4


class InUseError(BgsError):
    """Another process is writing the same output."""

    exit_code = 5


class FileSystemError(BgsError):
    """A file could not be written or read because of the file system, not the data."""

    exit_code = 6


FILE_SYSTEM_ERRNOS = {  # errno: (what failed, what to do)
    errno.ENOSPC: ("write", "the disk is full: free space (or choose another folder) and run the "
                            "same command again"),
    errno.EDQUOT: ("write", "the disk quota is exhausted: free space (or choose another folder) "
                            "and run the same command again"),
    errno.EROFS: ("write", "the file system is read-only: choose a writable folder"),
    errno.EACCES: ("access", "permission denied: check the permissions, or choose another folder"),
    errno.EPERM: ("access", "operation not permitted: check the permissions, or choose another "
                            "folder"),
    errno.EIO: ("access", "the disk reported an I/O error: check it, then run the same command "
                          "again"),
    errno.ENAMETOOLONG: ("create", "the name is longer than the file system allows: choose a "
                                   "shorter one"),
    errno.ELOOP: ("resolve", "symbolic links there form a loop: remove the loop"),
    errno.EISDIR: ("write", "a folder stands where a file belongs: remove or rename it"),
    errno.ENOTDIR: ("access", "a part of the path is a file, not a folder: fix the path"),
}  # fmt: skip


@contextmanager
def naming(path: Path | str) -> Iterator[None]:
    """Give an `OSError` raised in the block the path it concerns, when it names none (a
    ``write`` that fills the disk reports only ENOSPC)."""
    try:
        yield
    except OSError as err:
        if err.filename is None and err.errno is not None:
            raise OSError(err.errno, err.strerror, str(path)) from err
        raise


def file_system_error(err: OSError) -> FileSystemError | None:
    """The user-facing error for an `OSError` the file system caused (disk full, read-only,
    permission denied), naming the path; None for any other `OSError`."""
    if err.errno not in FILE_SYSTEM_ERRNOS:
        return None
    verb, hint = FILE_SYSTEM_ERRNOS[err.errno]
    path = err.filename or next((w.strip("',") for w in str(err).split() if "/" in w), None)
    return FileSystemError(f"cannot {verb} {path}: {hint}" if path else hint)


class Interrupted(BgsError):
    """Work was stopped by a signal; partial output has been removed."""

    def __init__(self, signum: int) -> None:
        import signal

        super().__init__(f"interrupted by {signal.Signals(signum).name}; partial output removed")
        self.signum = signum
        self.exit_code = 128 + signum
