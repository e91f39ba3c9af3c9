"""The `bgs` command line end to end: help that teaches, clean errors, the demo."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from bgs_batch import __version__
from bgs_batch.cli import main

BGS = Path(sys.executable).with_name("bgs")


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_version_and_help_teach():
    assert run("--version").output.strip() == f"bgs, version {__version__}"
    top = run("--help")
    assert top.exit_code == 0 and "bgs convert tum" in top.output and "bgs demo" in top.output
    for command in (["convert", "tum"], ["convert", "scannet"], ["convert", "bag"], ["inspect"],
                    ["synth"], ["demo"], ["convert"], ["run"], ["status"],
                    ["settings"]):  # fmt: skip
        result = run(*command, "--help")
        assert result.exit_code == 0 and "Example" in result.output, command


def test_settings_lists_every_key_with_its_value_range_and_doc():
    from bgs_batch.config import SETTINGS

    listed = run("settings")
    assert listed.exit_code == 0
    keys = [line.split(" = ")[0] for line in listed.output.splitlines() if " = " in line
            and not line.startswith(" ")]  # fmt: skip
    assert keys == list(SETTINGS)
    tracking = run("settings", "tracking.iterations").output.splitlines()
    assert tracking[0] == "tracking.iterations = 60 (paper: 200)  [an integer >= 1]"
    assert tracking[1].startswith("    Adam iterations per frame")
    assert "note: tracking.iterations=60 applies only to frames whose warm start" in tracking[2]
    paper = run("settings", "rolling_shutter_readout", "--preset", "paper").output
    assert paper.startswith("rolling_shutter_readout = 0.0 (cpu: none)  [a number >= 0 and <= 1,"
                            " or none]")  # fmt: skip
    unknown = run("settings", "trackin.")
    assert unknown.exit_code == 2 and "tracking" in unknown.output


def test_usage_errors_exit_2():
    assert run("synth", "x", "--size", "640by480").exit_code == 2
    assert run("synth", "x", "--motion", "sprint").exit_code == 2
    alone = run("synth", "x", "--global-shutter-depth")
    assert alone.exit_code == 2 and "--rolling-shutter" in alone.output
    assert run("convert", "tum").exit_code == 2
    assert run("nope").exit_code == 2


def test_synth_motions_and_sensor_effects(tmp_path):
    out = tmp_path / "shaky"
    result = run("-q", "synth", out, "--frames", "3", "--size", "64x48", "--motion", "shake",
                 "--blur", "--rolling-shutter", "--global-shutter-depth", "--holes")  # fmt: skip
    assert result.exit_code == 0, result.output
    assert len(list((out / "rgb").glob("*.png"))) == 3
    assert len((out / "readout.txt").read_text().split()) == 2  # the colour's, the depth's


def test_inspect_rejects_non_stores(tmp_path):
    fake = tmp_path / "seq.h5"
    fake.write_text("not hdf5")
    result = run("inspect", fake)
    assert result.exit_code == 3 and str(fake) in result.output and "bgs convert" in result.output
    assert "Traceback" not in result.output


def test_synth_convert_inspect_through_the_installed_script(tmp_path):
    """The real console script, as a user types it (subprocess, not CliRunner)."""
    seq, store = tmp_path / "room", tmp_path / "room.h5"
    steps = [
        [BGS, "-q", "synth", seq, "--frames", "8", "--size", "64x48", "--seed", "4"],
        [BGS, "-q", "convert", "tum", seq, "-o", store],
        [BGS, "inspect", store, "--json"],
    ]
    for step in steps:
        done = subprocess.run(step, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["frames"] == 8 and (summary["width"], summary["height"]) == (64, 48)
    assert summary["gt_coverage_percent"] == 100.0
    assert summary["provenance"]["intrinsics_source"] == "calibration.txt"
    again = subprocess.run(steps[0], capture_output=True, text=True, timeout=120)
    assert again.returncode == 4 and "--overwrite" in again.stderr


@pytest.mark.slow
def test_demo_end_to_end(tmp_path):
    result = run("-q", "demo", "--dir", tmp_path / "demo", "--frames", "6", "--size", "64x48")
    assert result.exit_code == 0, result.output
    assert (tmp_path / "demo" / "synthetic_room.h5").is_file()
    assert "valid (schema v1)" in result.output and "ATE RMSE" in result.output
    assert (tmp_path / "demo" / "job" / "trajectory.txt").is_file()
    outputs = tmp_path / "demo" / "job" / "outputs"
    for name in ("report.html", "metrics.json", "ply/global.ply", "uncertainty.h5"):
        assert (outputs / name).is_file(), name
    # a second demo replaces its own outputs instead of refusing
    assert run("-q", "demo", "--dir", tmp_path / "demo", "--frames", "6", "--size", "64x48"
               ).exit_code == 0  # fmt: skip
