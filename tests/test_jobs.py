"""Job directories: identity (job.json), refusal of changed inputs, and the lock."""

import json
import os
import subprocess

import pytest
from click.testing import CliRunner
from conftest import make_tum_folder

from bgs_batch.cli import main
from bgs_batch.config import load_config
from converters.pipeline import write_store
from converters.tum import TumOptions, plan_tum
from jobs.jobdir import LOCK_FILE, JobError, job_lock
from jobs.run import run_job

TINY = ["mapping.iterations=2", "mapping.new_submap_iterations=2", "tracking.iterations=2"]


def tiny_store(root, seed=0):
    folder = make_tum_folder(root / f"src{seed}", frames=3, seed=seed)
    plan = plan_tum(folder, TumOptions())
    return write_store(plan.frames, root / f"s{seed}.h5", plan.meta).path


def test_job_json_records_inputs_and_refuses_changes(tmp_path):
    store, other = tiny_store(tmp_path, 0), tiny_store(tmp_path, 1)
    job = tmp_path / "job"
    cfg = load_config("cpu", TINY)
    run_job(store, job, cfg, max_frames=2)
    record = json.loads((job / "job.json").read_text())
    assert record["store"]["path"] == str(store.resolve()) and len(record["store"]["sha256"]) == 64
    assert record["config"]["tracking"]["iterations"] == 2 and record["max_frames"] == 2
    run_job(store, job, cfg, max_frames=2)  # same job again: fine
    with pytest.raises(JobError, match="different store"):
        run_job(other, job, cfg, max_frames=2)
    with pytest.raises(JobError, match="different config"):
        run_job(store, job, load_config("cpu", [*TINY, "seed=1"]), max_frames=2)
    run_job(other, job, cfg, max_frames=2, force=True)
    assert json.loads((job / "job.json").read_text())["store"]["path"] == str(other.resolve())
    assert not (job / LOCK_FILE).exists()


def test_second_run_on_a_locked_job_is_refused(tmp_path):
    store = tiny_store(tmp_path)
    job = tmp_path / "job"
    job.mkdir()
    with job_lock(job):
        result = CliRunner().invoke(main, ["-q", "run", str(store), "--job-dir", str(job),
                                           *sum((["--set", s] for s in TINY), [])])  # fmt: skip
        assert result.exit_code == 5, result.output
        assert f"in use by process {os.getpid()}" in result.output
    assert not (job / LOCK_FILE).exists()


def test_stale_lock_of_a_dead_process_is_taken_over(tmp_path):
    dead = subprocess.Popen(["true"])
    dead.wait()
    (tmp_path / LOCK_FILE).write_text(json.dumps({"host": os.uname().nodename,
                                                  "pid": dead.pid}))  # fmt: skip
    with job_lock(tmp_path):
        assert json.loads((tmp_path / LOCK_FILE).read_text())["pid"] == os.getpid()
    foreign = {"host": "elsewhere", "pid": dead.pid}  # another host's lock is never stale here
    (tmp_path / LOCK_FILE).write_text(json.dumps(foreign))
    with pytest.raises(JobError, match="elsewhere"), job_lock(tmp_path):
        pass


def test_status_reports_done_failed_running_and_bad_dirs(tmp_path):
    store = tiny_store(tmp_path)
    done = tmp_path / "done"
    run_job(store, done, load_config("cpu", TINY), max_frames=2)
    broken = tmp_path / "broken"
    with pytest.raises(KeyboardInterrupt):
        run_job(store, broken, load_config("cpu", TINY), max_frames=2,
                on_frame=lambda _e: (_ for _ in ()).throw(KeyboardInterrupt()))  # fmt: skip
    result = CliRunner().invoke(main, ["status", str(done), str(broken), "--json"])
    assert result.exit_code == 0, result.output
    by_state = {s["state"]: s for s in json.loads(result.output)}
    assert by_state["done"]["frames_done"] == 2 and by_state["done"]["fps"] > 0
    assert by_state["failed"]["frames_done"] == 1
    assert by_state["failed"]["last_error"].startswith("KeyboardInterrupt")
    with job_lock(done):
        assert json.loads(CliRunner().invoke(main, ["status", str(done), "--json"]).output
                          )[0]["state"] == "running"  # fmt: skip
    table = CliRunner().invoke(main, ["status", str(done)])
    assert "done" in table.output
    missing = CliRunner().invoke(main, ["status", str(tmp_path / "nope")])
    assert missing.exit_code == 3 and "not a bgs job directory" in missing.output
