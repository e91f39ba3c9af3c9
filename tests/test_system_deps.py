"""scripts/system-deps.sh: the shared libraries `make demo`/`make test` install before Open3D loads.

The script runs with shims for `ldconfig`, `id` and `apt-get` first on PATH, so every branch is
exercised without touching the machine's packages.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "system-deps.sh"
LIBUSB = "\tlibusb-1.0.so.0 (libc6,x86-64) => /lib/x86_64-linux-gnu/libusb-1.0.so.0"
LIBGOMP = "\tlibgomp.so.1 (libc6,x86-64) => /lib/x86_64-linux-gnu/libgomp.so.1"


def shim(folder: Path, name: str, body: str) -> None:
    path = folder / name
    path.write_text(f"#!/bin/sh\n{body}\n")
    path.chmod(0o755)


def run_script(tmp_path: Path, libraries: list[str], uid: int = 0, apt_fails: bool = False
               ) -> tuple[subprocess.CompletedProcess, list[str]]:  # fmt: skip
    """Run the script against a made-up machine; its result and the apt-get calls made."""
    bin_dir, log = tmp_path / "bin", tmp_path / "apt.log"
    bin_dir.mkdir()
    listing = "\n".join([f"{len(libraries)} libs found in cache `/etc/ld.so.cache'", *libraries])
    shim(bin_dir, "ldconfig", f"cat <<'END'\n{listing}\nEND")
    shim(bin_dir, "id", f"echo {uid}")
    shim(bin_dir, "apt-get", f'echo "$*" >> {log}' + ("\nexit 100" if apt_fails else ""))
    env = dict(os.environ, PATH=f"{bin_dir}:{os.environ['PATH']}")
    done = subprocess.run(["bash", str(SCRIPT)], env=env, capture_output=True, text=True)
    return done, log.read_text().splitlines() if log.exists() else []


def test_nothing_happens_when_every_library_is_there(tmp_path):
    done, apt = run_script(tmp_path, [LIBUSB, LIBGOMP])
    assert done.returncode == 0 and done.stdout == done.stderr == "" and apt == []


def test_a_missing_library_as_root_is_installed_with_apt(tmp_path):
    done, apt = run_script(tmp_path, [LIBGOMP])
    assert done.returncode == 0, done.stderr
    assert apt == ["update -qq", "install -y -qq libusb-1.0-0"]
    assert done.stdout.strip() == "system-deps: installed libusb-1.0-0 (for libusb-1.0.so.0)"


def test_a_missing_library_without_root_names_the_command_and_fails(tmp_path):
    done, apt = run_script(tmp_path, [LIBGOMP], uid=1000)
    assert done.returncode == 1 and apt == []
    assert done.stderr.splitlines() == [
        "system-deps: missing libusb-1.0.so.0; run: sudo apt-get install -y libusb-1.0-0"
    ]


def test_both_missing_name_both_packages(tmp_path):
    done, _ = run_script(tmp_path, [], uid=1000)
    assert "libusb-1.0-0 libgomp1" in done.stderr and done.returncode == 1


def test_a_failing_apt_get_fails_with_one_line_of_its_own(tmp_path):
    done, apt = run_script(tmp_path, [LIBGOMP], apt_fails=True)
    assert done.returncode == 1 and apt == ["update -qq"]
    assert done.stderr.splitlines()[-1].startswith("system-deps: could not install libusb-1.0-0")


@pytest.mark.parametrize("target", ["demo", "test"])
def test_the_two_commands_check_the_libraries_first(target):
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MFLAGS", "MAKELEVEL")}
    command = ["make", "--no-print-directory", "-n", "-B", target]  # also when run by make test
    done = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0] == "bash scripts/system-deps.sh"
