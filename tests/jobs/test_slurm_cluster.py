"""`bgs submit` against a real Slurm cluster (e.g. the single node of `.ci/slurm/start.sh`).

Two tiny stores go in as one array job. While both tasks run, task 0 gets Slurm's time-limit
warning (SIGUSR1 to the batch shell only, as ``--signal=B:USR1@…`` sends it) and requeues
itself; task 1 is requeued from outside with ``scontrol requeue``, which Slurm 22.05 carries out
by sending SIGTERM to every process of the job (then SIGKILL after ``KillWait``). Both resume
from their checkpoints and must end bitwise equal to uninterrupted local ``bgs run``s.

Skips, with the reason, when the Slurm tools are missing or no controller answers.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import make_tum_folder

from converters.tum import convert_tum
from jobs.run import TIMING_FIELDS

pytestmark = pytest.mark.slow

TOOLS = ("sbatch", "squeue", "scontrol", "scancel", "sinfo")
START_HINT = "start one with `.ci/slurm/start.sh` (installs: slurmctld slurmd slurm-client munge)"
QUERY_TIMEOUT_S = 15  # one scontrol/sinfo/squeue call
START_TIMEOUT_S = 180  # until both tasks have tracked a few frames
FINISH_TIMEOUT_S = 420  # until both tasks are done, a default 120 s requeue hold included
POLL_S = 0.2
FRAMES = 24  # per store; at 80x60 with SETTINGS one frame takes ~0.4 s per core
SIZE = (80, 60)
SIGNAL_AFTER_FRAMES = 3  # interrupt both tasks once they tracked this many frames
CPUS = 1  # per task: both tasks of the array run at once on a 2-core node
SETTINGS = [
    "checkpoint_every=2",
    "tracking.iterations=10",
    "mapping.iterations=6",
    "mapping.new_submap_iterations=6",
    "seeding.new_submap_points=3000",
    "seeding.new_submap_gradient_points=1000",
    "seeding.new_frame_points=1000",
]
BGS = Path(sys.executable).with_name("bgs")


def query(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, capture_output=True, text=True, timeout=QUERY_TIMEOUT_S,
                          check=False)  # fmt: skip


def cluster_skip_reason() -> str | None:
    """Why no test cluster can be used here, or None when one answers with a usable node."""
    missing = [tool for tool in TOOLS if shutil.which(tool) is None]
    if missing:
        return f"Slurm tools not installed ({', '.join(missing)} missing); {START_HINT}"
    try:
        ping = query("scontrol", "ping")
        nodes = query("sinfo", "-h", "-o", "%T")
    except subprocess.TimeoutExpired:
        return f"the Slurm controller does not answer within {QUERY_TIMEOUT_S} s; {START_HINT}"
    if ping.returncode != 0 or "UP" not in ping.stdout:
        answer = ((ping.stdout + ping.stderr).strip().splitlines() or ["no output"])[0]
        return f"no Slurm controller answers `scontrol ping` ({answer}); {START_HINT}"
    if not {"idle", "mixed"} & set(nodes.stdout.split()):
        return f"no idle Slurm node (sinfo states: {nodes.stdout.split()}); {START_HINT}"
    return None


@pytest.fixture(scope="module")
def slurm_cluster() -> None:
    reason = cluster_skip_reason()
    if reason:
        pytest.skip(reason)


def make_store(root: Path, name: str, seed: int) -> Path:
    folder = make_tum_folder(root / f"src_{name}", frames=FRAMES, size=SIZE, seed=seed)
    return convert_tum(folder, root / f"{name}.h5")


def frames_logged(job: Path) -> int:
    log = job / "log.jsonl"
    return log.read_text().count("\n") if log.exists() else 0


def tasks(array_id: str) -> dict[str, tuple[str, str]]:
    """Array tasks Slurm still lists (pending, running, completing): id → (state, reason)."""
    out = query("squeue", "-h", "-r", "-j", array_id, "-o", "%i %T %r").stdout
    return {task: (state, reason) for task, state, reason in (ln.split() for ln in
                                                              out.splitlines())}  # fmt: skip


def slurm_outputs(root: Path) -> str:
    return "\n".join(f"--- {p.name}\n{p.read_text()}" for p in sorted(root.glob("slurm-*.out")))


def job_states(jobs: list[Path]) -> list[str]:
    done = subprocess.run([str(BGS), "status", "--json", *map(str, jobs)], capture_output=True,
                          text=True, check=True)  # fmt: skip
    return [s["state"] for s in json.loads(done.stdout)]


def without_venv_on_path() -> dict[str, str]:
    """The environment minus the venv's bin directory: the batch script must not rely on it."""
    venv_bin = BGS.parent.resolve()
    path = [p for p in os.environ["PATH"].split(os.pathsep) if p and Path(p).resolve() != venv_bin]
    return {**os.environ, "PATH": os.pathsep.join(path)}


def local_run(store: Path, job: Path) -> subprocess.Popen[str]:
    """The uninterrupted reference: same CLI, preset and settings as the array task."""
    args = [str(BGS), "-q", "run", str(store), "--job-dir", str(job), "--preset", "cpu",
            "--set", f"threads={CPUS}", *sum((["--set", s] for s in SETTINGS), [])]  # fmt: skip
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def assert_bitwise_equal(job: Path, reference: Path) -> None:
    for name in ("trajectory.txt", "sensor_net.pt"):
        assert (job / name).read_bytes() == (reference / name).read_bytes(), f"{job}/{name}"
    submaps = sorted(p.name for p in (reference / "submaps").iterdir())
    assert submaps and sorted(p.name for p in (job / "submaps").iterdir()) == submaps
    for name in submaps:
        ours, theirs = job / "submaps" / name, reference / "submaps" / name
        assert ours.read_bytes() == theirs.read_bytes(), f"{ours} differs from {theirs}"

    def events(path: Path) -> list[dict]:
        lines = (path / "log.jsonl").read_text().splitlines()
        return [{k: v for k, v in json.loads(x).items() if k not in TIMING_FIELDS} for x in lines]

    assert events(job) == events(reference)
    assert len(events(job)) == FRAMES


def test_array_resumes_bitwise_after_usr1_and_scontrol_requeue(slurm_cluster, tmp_path):
    stores = [make_store(tmp_path, "a", 0), make_store(tmp_path, "b", 1)]
    root = tmp_path / "runs"
    jobs = [root / "a", root / "b"]
    submitted = subprocess.run(
        [str(BGS), "submit", *map(str, stores), "--job-root", str(root), "--cpus", str(CPUS),
         *sum((["--set", s] for s in SETTINGS), [])],
        capture_output=True, text=True, env=without_venv_on_path(), cwd=tmp_path,
    )  # fmt: skip
    assert submitted.returncode == 0, submitted.stderr
    array_id = re.search(r"submitted array job (\d+)", submitted.stdout).group(1)
    references: list[subprocess.Popen[str]] = []
    try:
        # task 0 gets the time-limit warning, as --signal=B:USR1 delivers it (to the batch shell
        # only); task 1 is requeued. Each as soon as it has tracked a few frames: on a loaded
        # machine one task may start long after the other
        interrupts = [("scancel", "--batch", "--signal=USR1", f"{array_id}_0"),
                      ("scontrol", "requeue", f"{array_id}_1")]  # fmt: skip
        pending = dict(enumerate(jobs))
        deadline = time.monotonic() + START_TIMEOUT_S
        while pending:
            for i, job in list(pending.items()):
                if frames_logged(job) >= SIGNAL_AFTER_FRAMES:
                    sent = query(*interrupts[i])
                    assert sent.returncode == 0, sent.stderr
                    assert frames_logged(job) < FRAMES, f"task {i} ended before its signal"
                    del pending[i]
            assert time.monotonic() < deadline, (
                f"tasks did not start tracking within {START_TIMEOUT_S} s: squeue says "
                f"{tasks(array_id)}\n{slurm_outputs(root)}"
            )
            time.sleep(POLL_S)
        references = [local_run(s, tmp_path / f"local_{s.stem}") for s in stores]

        deadline = time.monotonic() + FINISH_TIMEOUT_S
        while (listed := tasks(array_id)) or job_states(jobs) != ["done", "done"]:
            assert time.monotonic() < deadline, (
                f"array {array_id} not done within {FINISH_TIMEOUT_S} s: squeue says {listed}, "
                f"bgs status says {job_states(jobs)}\n{slurm_outputs(root)}"
            )
            assert listed or job_states(jobs) == ["done", "done"], (
                f"array {array_id} left the queue unfinished: {job_states(jobs)}\n"
                f"{slurm_outputs(root)}"
            )
            # A requeued task is held (PENDING, Reason=BeginTime) for AuthInfo's cred_expire
            # (Slurm's default 120 s, .ci/slurm sets 10 s) and must not be released early:
            # `scontrol update StartTime=now` let a task start within the second of its requeue,
            # and slurmd killed it ("Job credential revoked", exit 1). So the test waits.
            time.sleep(POLL_S)
    finally:
        query("scancel", array_id)  # no-op once finished; frees the node when the test fails
    for proc in references:
        output, _ = proc.communicate()
        assert proc.returncode == 0, output

    outputs = {job.name: (root / f"slurm-{array_id}_{i}.out").read_text()
               for i, job in enumerate(jobs)}  # fmt: skip
    assert "stopped by SIGUSR1" in outputs["a"], outputs["a"]  # checkpointed, requeued itself
    assert "stopped by SIGTERM" in outputs["b"], outputs["b"]  # checkpointed on Slurm's TERM
    assert "DUE TO JOB REQUEUE" in outputs["b"] and "requeue of" not in outputs["a"]
    for job in jobs:
        # interrupted exactly once (a task must not requeue its siblings), then finished
        assert outputs[job.name].count("stopped by") == 1, outputs[job.name]
        assert f"{FRAMES} frames" in outputs[job.name], outputs[job.name]
        assert_bitwise_equal(job, tmp_path / f"local_{job.name}")
