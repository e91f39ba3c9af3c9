"""`bgs submit`: one Slurm array job over many frame stores, pre-emption safe.

Each array task runs ``bgs run STORE --job-dir JOB_ROOT/<store name>``. Slurm sends SIGUSR1 to
the batch shell 120 s before the time limit (``--signal=B:USR1@120``); the shell forwards it to
``bgs run``, which finishes its frame, checkpoints and exits with 75, and the shell then
requeues its own task (``--requeue``); the requeued task resumes from the checkpoint.

SIGTERM (pre-emption, ``scontrol requeue``, ``scancel``) also makes ``bgs run`` checkpoint and
exit with 75, but the shell does not requeue then: Slurm already requeues a pre-empted or
requeued job itself, and a cancelled job must stay cancelled (a later ``bgs submit`` of the same
stores resumes it). Real Slurm (22.05) showed why the task is named ``<array id>_<task id>``:
``scontrol requeue $SLURM_JOB_ID`` in the task whose job id equals the array's id requeues the
whole array, killing its running siblings. A task that finished returns at once when requeued.
"""

from __future__ import annotations

import shlex
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from bgs_batch.errors import BgsError, InputError
from jobs.preemption import PREEMPTED_EXIT

WARNING_SECONDS = 120
# this task alone: one task's $SLURM_JOB_ID (22.05: the last task's) is the array id, and
# `scontrol requeue <array id>` requeues every task of the array
TASK_ID = "${SLURM_ARRAY_JOB_ID}_${SLURM_ARRAY_TASK_ID}"


@dataclass(frozen=True)
class SubmitOptions:
    """What Slurm is asked for, and how each task runs."""

    partition: str | None = None
    time: str | None = None  # Slurm time limit, e.g. 24:00:00
    cpus: int = 2
    preset: str = "cpu"
    overrides: tuple[str, ...] = ()
    extra: tuple[str, ...] = field(default_factory=tuple)  # further raw #SBATCH options


def job_dirs(stores: list[Path], job_root: Path) -> list[Path]:
    """One job directory per store, named after it; refuses two stores with the same name."""
    dirs = [job_root / Path(s).stem for s in stores]
    if len(set(dirs)) != len(dirs):
        raise InputError("two stores share a file name, so their job directories would collide; "
                         "rename one of them")  # fmt: skip
    return dirs


def sbatch_script(stores: list[Path], job_root: Path, options: SubmitOptions) -> str:
    """The sbatch array script for `stores` (absolute paths, quoted)."""
    for store in stores:
        if not Path(store).is_file():
            raise InputError(f"{store} does not exist; convert it first with `bgs convert …`")
    stores = [Path(s).resolve() for s in stores]
    dirs = [d.resolve() for d in job_dirs(stores, job_root)]
    directives = [
        "--job-name=bgs-batch",
        f"--array=0-{len(stores) - 1}",
        f"--cpus-per-task={options.cpus}",
        f"--signal=B:USR1@{WARNING_SECONDS}",
        "--requeue",
        "--open-mode=append",
        f"--output={job_root.resolve()}/slurm-%A_%a.out",
        f"--chdir={job_root.resolve()}",  # the submit directory may not exist on the node
    ]
    if options.partition:
        directives.append(f"--partition={options.partition}")
    if options.time:
        directives.append(f"--time={options.time}")
    directives += list(options.extra)
    bgs = shlex.quote(str(Path(sys.executable).with_name("bgs")))
    run_args = [f"--preset {shlex.quote(options.preset)}", f"--set threads={options.cpus}"]
    run_args += [f"--set {shlex.quote(o)}" for o in options.overrides]
    return "\n".join([
        "#!/bin/bash",
        *(f"#SBATCH {d}" for d in directives),
        "",
        "# written by `bgs submit`: one task per frame store, pre-emption safe (see jobs/slurm.py)",
        f"STORES=({' '.join(shlex.quote(str(s)) for s in stores)})",
        f"JOBS=({' '.join(shlex.quote(str(d)) for d in dirs)})",
        'store="${STORES[$SLURM_ARRAY_TASK_ID]}"',
        'job="${JOBS[$SLURM_ARRAY_TASK_ID]}"',
        "",
        f'{bgs} -q run "$store" --job-dir "$job" {" ".join(run_args)} &',
        "child=$!",
        "# forward Slurm's time-limit warning (USR1) and TERM (pre-emption, requeue, scancel):",
        "# bgs checkpoints and exits 75; only after the warning does this task requeue itself",
        "signal=",
        "trap 'signal=USR1; kill -USR1 \"$child\" 2>/dev/null' USR1",
        "trap 'signal=TERM; kill -TERM \"$child\" 2>/dev/null' TERM",
        'while true; do wait "$child"; rc=$?; kill -0 "$child" 2>/dev/null || break; done',
        f'if [ "$rc" -eq {PREEMPTED_EXIT} ] && [ "$signal" = USR1 ]; then',
        f'    scontrol requeue "{TASK_ID}" || echo "bgs: requeue of {TASK_ID} failed; run'
        ' the same bgs submit again to resume" >&2',
        "fi",
        'exit "$rc"',
        "",
    ])  # fmt: skip


def submit(script: str) -> str:
    """Submit with ``sbatch --parsable``; returns the job id."""
    try:
        done = subprocess.run(["sbatch", "--parsable"], input=script, text=True,
                              capture_output=True, check=False)  # fmt: skip
    except FileNotFoundError:
        raise BgsError("sbatch not found: run `bgs submit` on a Slurm login node, or use "
                       "--dry-run to print the script") from None  # fmt: skip
    if done.returncode != 0:
        raise BgsError(f"sbatch refused the job: {done.stderr.strip()}")
    return done.stdout.strip().split(";")[0]
