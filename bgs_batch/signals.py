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


class Interruption:
    """The signal that arrived inside `interruptible`, if any."""

    def __init__(self) -> None:
        self.signum: int | None = None

    def check(self) -> None:
        """Raise `Interrupted` if a signal arrived: Python runs a signal handler wherever the
        main thread is, also inside a weakref callback or a destructor, which swallow what it
        raises ("Exception ignored in ..."), so long loops call this once per item and before
        they commit their output."""
        if self.signum is not None:
            raise Interrupted(self.signum)


@contextmanager
def interruptible(signums: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)
                  ) -> Iterator[Interruption]:  # fmt: skip
    """Within the block, SIGINT/SIGTERM raise `Interrupted` in the main thread, and the yielded
    `Interruption` remembers them (`Interruption.check`)."""
    interruption = Interruption()

    def _raise(signum: int, _frame: object) -> None:
        interruption.signum = signum
        raise Interrupted(signum)

    with signal_handlers(signums, _raise):
        yield interruption
