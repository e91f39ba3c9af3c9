"""Turn termination signals into exceptions, so that `with` blocks clean up partial output."""

from __future__ import annotations

import signal
from collections.abc import Iterator
from contextlib import contextmanager

from bgs_batch.errors import Interrupted


@contextmanager
def interruptible(signums: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[None]:
    """Within the block, SIGINT/SIGTERM raise `Interrupted` in the main thread.

    The previous handlers are restored on exit. Outside the main thread this is a no-op (Python
    only delivers signals there).
    """

    def _raise(signum: int, _frame: object) -> None:
        raise Interrupted(signum)

    try:
        previous = {s: signal.signal(s, _raise) for s in signums}
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
