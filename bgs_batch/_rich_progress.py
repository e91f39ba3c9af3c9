"""The rich progress bar behind `bgs_batch.progress.progress_bar` (imported when one is shown)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    ProgressColumn,
    Task,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.text import Text

stderr = Console(stderr=True)


class _RateColumn(ProgressColumn):
    """Items per second, as frames per second."""

    def render(self, task: Task) -> Text:
        speed = task.finished_speed or task.speed
        return Text(f"{speed:5.1f} fps" if speed else "    – fps", style="cyan")


@contextmanager
def rich_progress(description: str, total: int | None) -> Iterator[Callable[..., None]]:
    """A bar showing count, rate, time elapsed and left, and a status text."""
    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        _RateColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        TextColumn("{task.fields[status]}"),
    )
    with Progress(*columns, console=stderr, transient=False) as progress:
        task = progress.add_task(description, total=total, status="")

        def advance(n: int, status: str = "", total: int | None = None) -> None:
            progress.update(task, advance=n, status=status, total=total)  # None: kept

        yield advance
