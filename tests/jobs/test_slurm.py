"""`bgs submit`: the sbatch array script, run here under a stand-in Slurm environment."""

import os
import signal
import subprocess
import time

import pytest
from click.testing import CliRunner
from conftest import make_tum_folder

from bgs_batch.cli import main
from converters.pipeline import write_store
from converters.tum import TumOptions, plan_tum
from jobs.checkpoint import load_latest
from jobs.preemption import PREEMPTED_EXIT


def stores(root, names):
    out = []
    for seed, name in enumerate(names):
        folder = make_tum_folder(root / f"src_{name}", frames=10, size=(64, 48), seed=seed)
        plan = plan_tum(folder, TumOptions())
        out.append(write_store(plan.frames, root / f"{name}.h5", plan.meta).path)
    return out


def test_dry_run_prints_a_preemption_safe_array(tmp_path):
    a, b = stores(tmp_path, ["a", "b"])
    result = CliRunner().invoke(main, ["submit", str(a), str(b), "--job-root", str(tmp_path / "r"),
                                       "--partition", "cpu", "--time", "1:00:00", "--cpus", "4",
                                       "--set", "tracking.iterations=9", "--dry-run"])  # fmt: skip
    assert result.exit_code == 0, result.output
    script = result.output
    for line in ("#SBATCH --array=0-1", "#SBATCH --signal=B:USR1@120", "#SBATCH --requeue",
                 "#SBATCH --partition=cpu", "#SBATCH --time=1:00:00",
                 "#SBATCH --cpus-per-task=4", "--set tracking.iterations=9",
                 "--set threads=4", "#SBATCH --chdir=",
                 'scontrol requeue "${SLURM_ARRAY_JOB_ID}_${SLURM_ARRAY_TASK_ID}"'):  # fmt: skip
        assert line in script, line
    assert str(tmp_path / "r" / "a") in script and str(tmp_path / "r" / "b") in script
    assert subprocess.run(["bash", "-n"], input=script, text=True).returncode == 0
    assert not (tmp_path / "r").exists()  # a dry run writes nothing


def test_bad_submissions_are_refused(tmp_path):
    (a,) = stores(tmp_path, ["a"])
    missing = CliRunner().invoke(main, ["submit", str(tmp_path / "x.h5"), "--job-root", "r",
                                        "--dry-run"])  # fmt: skip
    assert missing.exit_code == 3 and "bgs convert" in missing.output
    bad = CliRunner().invoke(main, ["submit", str(a), "--job-root", "r", "--set", "nope=1",
                                    "--dry-run"])  # fmt: skip
    assert bad.exit_code == 2
    (tmp_path / "other").mkdir()
    twin = tmp_path / "other" / "a.h5"
    twin.write_bytes(a.read_bytes())
    clash = CliRunner().invoke(main, ["submit", str(a), str(twin), "--job-root", "r",
                                      "--dry-run"])  # fmt: skip
    assert clash.exit_code == 3 and "collide" in clash.output


@pytest.mark.parametrize("signum", [signal.SIGUSR1, signal.SIGTERM], ids=["USR1", "TERM"])
def test_task_forwards_signals_checkpoints_and_requeues_after_usr1(tmp_path, signum):
    """The array task under a stand-in Slurm: USR1 (time-limit warning) to the batch shell →
    checkpoint → the task requeues itself, by its array task id (one task's job id is the
    array's, and requeueing that would requeue every task). TERM (pre-emption,
    `scontrol requeue`, `scancel`) → checkpoint, but no requeue: Slurm requeues those itself,
    and a cancelled job must stay cancelled."""
    (store,) = stores(tmp_path, ["a"])
    root = tmp_path / "runs"
    args = ["submit", str(store), "--job-root", str(root), "--set", "checkpoint_every=100",
            "--dry-run"]  # fmt: skip
    script = CliRunner().invoke(main, args).output
    fake_bin = tmp_path / "bin"
    fake_bin.mkdir()
    (fake_bin / "scontrol").write_text(f'#!/bin/sh\necho "$@" > {tmp_path}/requeued\n')
    (fake_bin / "scontrol").chmod(0o755)
    env = {**os.environ, "SLURM_ARRAY_TASK_ID": "0", "SLURM_ARRAY_JOB_ID": "4242",
           "SLURM_JOB_ID": "4243",
           "PATH": f"{fake_bin}:{os.environ['PATH']}"}  # fmt: skip
    (tmp_path / "task.sh").write_text(script)
    proc = subprocess.Popen(["bash", tmp_path / "task.sh"], env=env, stderr=subprocess.PIPE,
                            text=True)  # fmt: skip
    log = root / "a" / "log.jsonl"
    deadline = time.monotonic() + 120
    while not (log.exists() and log.read_text().count("\n") >= 2):
        assert time.monotonic() < deadline and proc.poll() is None, "task ended too early"
        time.sleep(0.01)
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == PREEMPTED_EXIT, err
    assert signal.Signals(signum).name in err
    frames, _ = load_latest(root / "a")
    assert frames >= 2  # checkpointed on the signal, not on the (never reached) cadence
    if signum == signal.SIGTERM:
        assert not (tmp_path / "requeued").exists()
        return
    assert (tmp_path / "requeued").read_text().split() == ["requeue", "4242_0"]
    # the requeued task resumes and finishes
    assert subprocess.run(["bash", tmp_path / "task.sh"], env=env).returncode == 0
    assert (root / "a" / "summary.json").exists()
