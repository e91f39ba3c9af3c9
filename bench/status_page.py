"""``docs/status.md``: the latest output of every bench, written by the bench itself.

Each bench runs its ``main`` inside `recorded`. When it finishes, what it printed (its table and
``SUMMARY`` line) replaces that bench's section of ``docs/status.md``, headed by the command, the
commit (and whether the tree had local changes), the date, the machine and its load. The page is
never edited by hand: to update a number, run its bench again. ``BGS_BENCH_NO_STATUS=1`` leaves
the page alone (for trial runs).
"""

from __future__ import annotations

import io
import os
import platform
import re
import shlex
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager, redirect_stdout
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STATUS_PAGE = ROOT / "docs" / "status.md"
SKIP_ENV = "BGS_BENCH_NO_STATUS"
TITLE = "# Status: the latest bench results"
INTRO = (
    "Written by the benches in `bench/` (`bench/status_page.py`); do not edit. Each section is\n"
    "the complete output of that bench's latest run, with the command, commit and machine it ran\n"
    "on. All numbers of a section come from one run; compare ratios, not absolute times, across\n"
    "machines.\n"
)
_SECTION = re.compile(r"<!-- bench:(?P<name>[\w-]+) -->\n.*?<!-- /bench:(?P=name) -->\n", re.S)


class _Tee(io.TextIOBase):
    """Writes to the terminal and keeps a copy."""

    def __init__(self, terminal: io.TextIOBase) -> None:
        self.terminal, self.copy = terminal, io.StringIO()

    def write(self, text: str) -> int:
        self.copy.write(text)
        return self.terminal.write(text)

    def flush(self) -> None:
        self.terminal.flush()


@contextmanager
def recorded(name: str, page: Path = STATUS_PAGE) -> Iterator[None]:
    """Run the ``with`` body and, if it succeeds, publish what it printed as section `name`."""
    tee = _Tee(sys.stdout)
    with redirect_stdout(tee):
        yield
    if os.environ.get(SKIP_ENV) != "1":
        publish(page, name, section(name, tee.copy.getvalue()))
        print(f"(written to {page.relative_to(ROOT) if page.is_relative_to(ROOT) else page})")


def section(name: str, output: str) -> str:
    """One bench's section: a heading, where and when it ran, and its output verbatim."""
    command = shlex.join(["python", *[_relative(arg) for arg in sys.argv]])
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    when = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    return (
        f"<!-- bench:{name} -->\n## {name}\n\n"
        f"`{command}` at {_commit()}, {when}; {_machine()}; load average at the end {load}.\n\n"
        f"```text\n{output.rstrip()}\n```\n<!-- /bench:{name} -->\n"
    )


def publish(page: Path, name: str, text: str) -> None:
    """Replace section `name` of `page` with `text` (or add it), keeping sections in name order."""
    old = page.read_text() if page.exists() else ""
    sections = {match["name"]: match[0] for match in _SECTION.finditer(old)}
    sections[name] = text
    body = "\n".join(sections[key] for key in sorted(sections))
    page.parent.mkdir(parents=True, exist_ok=True)
    page.write_text(f"{TITLE}\n\n{INTRO}\n{body}")


def _relative(arg: str) -> str:
    """A path inside the repository as the user would type it from its root."""
    path = Path(arg)
    inside = path.is_absolute() and path.is_relative_to(ROOT)
    return str(path.relative_to(ROOT)) if inside else arg


def _commit() -> str:
    """The short commit hash, marked when the working tree differs from it."""
    git = ["git", "-C", str(ROOT)]
    def output(*args: str) -> str:
        return subprocess.run([*git, *args], capture_output=True, text=True, check=True).stdout

    try:
        head = output("rev-parse", "--short", "HEAD").strip()
        dirty = output("status", "--porcelain", "--untracked-files=no").strip()
    except (OSError, subprocess.CalledProcessError):
        return "an unknown commit"
    return f"commit {head}" + (" with local changes" if dirty else "")


def _machine() -> str:
    """CPU model and core count, e.g. ``Intel(R) Xeon(R) ..., 2 cores``."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} cores"
