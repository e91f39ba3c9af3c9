"""Every reference resolves inside the repository: README and docs links, and the code's
citations of ``docs/<page>.md §N``."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
CODE = sorted(p for folder in ("bgs_batch", "converters", "jobs", "outputs", "bench", "tests")
              for p in (ROOT / folder).rglob("*.py"))  # fmt: skip
LINK = re.compile(r"\]\(([^)\s]+)\)")
CITATION = re.compile(r"docs/([\w-]+\.md)(?: §(\d+)(?:-(\d+))?)?")
README_MAX_LINES = 200


def _sections(page: Path) -> set[str]:
    return set(re.findall(r"^## (\d+)\.", page.read_text(), re.M))


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_relative_link_of_a_page_exists(page):
    missing = [
        target for target in LINK.findall(page.read_text())
        if not re.match(r"[a-z]+:", target) and not target.startswith("#")
        and not (page.parent / target.split("#")[0]).exists()
    ]  # fmt: skip
    assert missing == [], f"{page.relative_to(ROOT)} links to missing files: {missing}"


def test_every_citation_in_the_code_names_a_page_and_section_that_exist():
    broken = []
    for path in CODE:
        for page, first, last in CITATION.findall(path.read_text()):
            target = ROOT / "docs" / page
            wanted = {str(n) for n in range(int(first), int(last or first) + 1)} if first else set()
            if not target.exists() or not wanted <= _sections(target):
                broken.append(f"{path.relative_to(ROOT)}: docs/{page} §{first}")
    assert broken == []


def test_the_code_cites_nothing_outside_the_repository():
    pattern = re.compile(r"DESIGN\.md|research/\w+\.md")
    outside = [f"{path.relative_to(ROOT)}: {match}"
               for path in CODE if path.name != "test_docs.py"
               for match in pattern.findall(path.read_text())]  # fmt: skip
    assert outside == []


def test_the_readme_stays_short():
    assert len((ROOT / "README.md").read_text().splitlines()) <= README_MAX_LINES


def test_every_test_or_bench_file_that_code_and_pages_name_exists():
    named = re.compile(r"\b((?:tests|bench)/[\w/]+\.py)\b")
    missing = sorted({f"{path.relative_to(ROOT)}: {name}"
                      for path in [*CODE, *PAGES] for name in named.findall(path.read_text())
                      if not (ROOT / name).exists()})  # fmt: skip
    assert missing == []


@pytest.mark.parametrize("package", ["bgs_batch/slam", "bgs_batch/slam/tracking",
                                     "bgs_batch/slam/loop_closure"])  # fmt: skip
def test_a_package_s_step_map_names_every_module_in_it(package):
    """The docstring of the method's packages is their map: a newcomer finds every module there."""
    import ast

    folder = ROOT / package
    doc = ast.get_docstring(ast.parse((folder / "__init__.py").read_text())) or ""
    named = set(re.findall(r"`([A-Za-z_.]+)`", doc))
    modules = {p.stem for p in folder.glob("*.py") if p.stem != "__init__"}
    modules |= {p.parent.name for p in folder.glob("*/__init__.py")}
    missing = {m for m in modules if not any(n == m or n.startswith(m + ".") for n in named)}
    assert missing == set(), f"{package}/__init__.py does not name {sorted(missing)}"
