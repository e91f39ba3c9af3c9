"""Graceful stops for jobs: SIGTERM, SIGUSR1 (Slurm's warning) and SIGINT finish the current
frame, write a checkpoint and exit with `PREEMPTED_EXIT` so the job can be resumed or requeued.
"""

from __future__ import annotations

import signal
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from bgs_batch.errors import BgsError
from bgs_batch.signals import signal_handlers

STOP_SIGNALS = (signal.SIGTERM, signal.SIGUSR1, signal.SIGINT)
PREEMPTED_EXIT = 75  # EX_TEMPFAIL: "try again later"; the job resumes from its checkpoint


class Preempted(BgsError):
    """The job stopped on request after checkpointing; run it again to continue."""

    exit_code = PREEMPTED_EXIT

    def __init__(self, signum: int, progress: str, job_dir: Path) -> None:
        """`progress` says where it stopped: "after 12 frames", "in the global stage …"."""
        super().__init__(
            f"stopped by {signal.Signals(signum).name} {progress}; checkpoint "
            f"written: `bgs run … --job-dir {job_dir}` continues where it stopped"
        )


class ExportStopped(BgsError):
    """A complete run's end-of-run export stopped on a signal (its partial files removed);
    running the job again finishes the export, so this too is a resumable stop."""

    exit_code = PREEMPTED_EXIT

    def __init__(self, signum: int, job_dir: Path) -> None:
        super().__init__(
            f"the run is complete, but its export was stopped by {signal.Signals(signum).name} "
            f"(partial output removed); `bgs run … --job-dir {job_dir}` finishes it"
        )


class StopRequest:
    """Set by a stop signal; the run loop checks it between frames."""

    requested: int = 0  # the signal number, 0 while none arrived


_active: list[StopRequest] = []  # the request of the outermost `stop_requests` block


@contextmanager
def stop_requests() -> Iterator[StopRequest]:
    """Within the block, stop signals only set ``requested`` (restored afterwards). Blocks nest:
    an inner block shares the outer one's request, so `bgs run` notes a signal that arrives
    between its run and its export, and the run acts on one that came before its first frame."""
    if _active:
        yield _active[0]
        return
    request = StopRequest()

    def note(signum: int, _frame: object) -> None:
        request.requested = signum

    with signal_handlers(STOP_SIGNALS, note):
        _active.append(request)
        try:
            yield request
        finally:
            _active.remove(request)


def pending_stop() -> int:
    """The stop signal an enclosing `stop_requests` block noted (0: none): work that installs
    its own handlers inside such a block (an export) starts by acting on it."""
    return _active[0].requested if _active else 0
