"""Turn termination signals into exceptions, so that `with` blocks clean up partial output."""

from __future__ import annotations

import signal
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from bgs_batch.errors import Interrupted


@contextmanager
def signal_handlers(signums: tuple[int, ...], handler: Callable[[int, object], None]
                    ) -> Iterator[None]:  # fmt: skip
    """Within the block, `handler` receives `signums`; the previous handlers are restored on exit.

    Outside the main thread this is a no-op (Python only delivers signals there).
    """
    try:
        previous = {s: signal.signal(s, handler) for s in signums}
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        for s, old in previous.items():
            signal.signal(s, old)


@contextmanager
def interruptible(signums: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[None]:
    """Within the block, SIGINT/SIGTERM raise `Interrupted` in the main thread."""

    def _raise(signum: int, _frame: object) -> None:
        raise Interrupted(signum)

    with signal_handlers(signums, _raise):
        yield
