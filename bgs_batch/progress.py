"""Progress bars for long work (rich), silent under ``--quiet`` or when stderr is not a terminal.

rich is imported only when a bar is shown: ``bgs -q run`` (as Slurm runs it) skips its ~0.1 s
import, which every resumed job would pay before its first frame.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager


@contextmanager
def progress_bar(
    description: str, total: int | None, enabled: bool = True
) -> Iterator[Callable[..., None]]:
    """Yield ``advance(n, status="", total=None)``: moves a bar showing count, rate, time left
    and status (`total`, when given, replaces the bar's total: known only once work starts)."""
    if not enabled:
        yield lambda _n, status="", total=None: None
        return
    from bgs_batch._rich_progress import rich_progress

    with rich_progress(description, total) as advance:
        yield advance
