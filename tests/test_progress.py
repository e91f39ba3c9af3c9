"""Progress bars: counts, a total learnt once the work has started, silence when disabled."""

import io

from rich.console import Console

import bgs_batch._rich_progress as rich_progress
from bgs_batch.progress import progress_bar


def test_a_total_given_after_the_start_is_what_the_bar_counts_to(monkeypatch):
    out = io.StringIO()
    monkeypatch.setattr(rich_progress, "stderr", Console(file=out, width=120))
    with progress_bar("SLAM", None) as advance:
        advance(0, total=7)  # the run has opened its store
        advance(3, "2 keyframes")
        advance(4)
    assert "7/7" in out.getvalue()


def test_a_disabled_bar_takes_the_same_calls_and_prints_nothing(capsys):
    with progress_bar("SLAM", None, enabled=False) as advance:
        advance(0, total=7)
        advance(1, "status")
    assert capsys.readouterr() == ("", "")
