"""docs/status.md is written by the benches: each run replaces its own section, nothing else."""

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def status_page():
    spec = importlib.util.spec_from_file_location("status_page", ROOT / "bench/status_page.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_run_replaces_its_own_section_and_keeps_the_others(
    status_page, tmp_path, monkeypatch, capsys
):
    page = tmp_path / "status.md"
    monkeypatch.delenv(status_page.SKIP_ENV, raising=False)
    monkeypatch.setattr(sys, "argv", [str(ROOT / "bench/raster.py"), "--quick"])
    with status_page.recorded("raster", page):
        print("table 1\nSUMMARY: first")
    with status_page.recorded("convert", page):
        print("SUMMARY convert")
    with status_page.recorded("raster", page):
        print("table 2\nSUMMARY: second")
    text = page.read_text()
    assert text.startswith(status_page.TITLE)
    assert text.count("## raster") == 1 and "SUMMARY: second" in text and "first" not in text
    assert text.index("## convert") < text.index("## raster")  # sections in name order
    assert "`python bench/raster.py --quick` at commit " in text
    assert "table 2" in capsys.readouterr().out  # the terminal still sees everything


def test_a_failed_or_trial_run_leaves_the_page_alone(status_page, tmp_path, monkeypatch):
    page = tmp_path / "status.md"
    with pytest.raises(RuntimeError), status_page.recorded("raster", page):
        print("half a table")
        raise RuntimeError("bench crashed")
    assert not page.exists()
    monkeypatch.setenv(status_page.SKIP_ENV, "1")
    with status_page.recorded("raster", page):
        print("SUMMARY: trial")
    assert not page.exists()
