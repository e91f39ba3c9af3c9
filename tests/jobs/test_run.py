"""Job directories: identity (job.json), refusal of changed inputs, and the lock."""

import errno
import fcntl
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import pytest
import torch
from click.testing import CliRunner
from conftest import make_tum_folder

from bgs_batch.cli import main
from bgs_batch.config import load_config
from bgs_batch.slam import Slam
from converters.tum import convert_tum
from jobs.checkpoint import CHECKPOINT_DIR, load_latest, write_checkpoint
from jobs.jobdir import LOCK_FILE, JobError, job_lock
from jobs.run import GLOBAL_MAP_FILE, TIMING_FIELDS, run_job

TINY = ["mapping.iterations=2", "mapping.new_submap_iterations=2", "tracking.iterations=2"]


def tiny_store(root, seed=0):
    folder = make_tum_folder(root / f"src{seed}", frames=3, seed=seed)
    return convert_tum(folder, root / f"s{seed}.h5")


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


def test_bgs_run_opens_its_store_once_and_learns_the_frame_count_from_the_run(
        tmp_path, monkeypatch):  # fmt: skip
    import bgs_batch.store as store_module

    store = tiny_store(tmp_path)
    opened, started = [], []
    real_open = store_module.FrameStore.__init__

    def counting_open(self, *args, **kwargs):
        opened.append(args)
        real_open(self, *args, **kwargs)

    monkeypatch.setattr(store_module.FrameStore, "__init__", counting_open)
    result = CliRunner().invoke(main, ["run", str(store), "--job-dir", str(tmp_path / "job"),
                                       "--max-frames", "2", "--no-export",
                                       *(f"--set={s}" for s in TINY)])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert len(opened) == 1
    run_job(store, tmp_path / "other", load_config("cpu", TINY), max_frames=2,
            on_start=started.append)  # fmt: skip
    run_job(store, tmp_path / "all", load_config("cpu", TINY), on_start=started.append)
    assert started == [2, len(store_module.FrameStore(store))]


def test_unchanged_store_is_not_hashed_again(tmp_path, monkeypatch):
    import jobs.jobdir as jobdir

    store = tiny_store(tmp_path)
    job = tmp_path / "job"
    cfg = load_config("cpu", TINY)
    run_job(store, job, cfg, max_frames=1)
    hashed = []
    real_hash = jobdir.file_sha256
    monkeypatch.setattr(jobdir, "file_sha256", lambda p: hashed.append(p) or real_hash(p))
    run_job(store, job, cfg, max_frames=1)  # same size and mtime: the recorded checksum
    assert hashed == []
    os.utime(store, ns=(store.stat().st_atime_ns, store.stat().st_mtime_ns + 10**9))
    run_job(store, job, cfg, max_frames=1)  # touched, same content: hashed, accepted, recorded
    assert len(hashed) == 1
    recorded = json.loads((job / "job.json").read_text())["store"]
    assert recorded["mtime_ns"] == store.stat().st_mtime_ns
    with h5py.File(store, "r+") as fh:  # other content: hashed and refused
        fh["rgb"][0, 0, 0] = 255 - fh["rgb"][0, 0, 0]
    with pytest.raises(JobError, match="different store"):
        run_job(store, job, cfg, max_frames=1)


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
    # another host's lock is decided by its flock too (NFS carries flocks between hosts)
    (tmp_path / LOCK_FILE).write_text(json.dumps({"host": "elsewhere", "pid": dead.pid}))
    with job_lock(tmp_path):
        pass
    (tmp_path / LOCK_FILE).write_text(json.dumps({"host": "elsewhere", "pid": 4242}))
    with open(tmp_path / LOCK_FILE) as held:  # held there: in use, named as the file says
        fcntl.flock(held, fcntl.LOCK_EX)
        with pytest.raises(JobError, match="process 4242 on elsewhere"), job_lock(tmp_path):
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


# ---------------------------------------------------------------- checkpoints and resume

RESUME = ["mapping.iterations=6", "mapping.new_submap_iterations=6", "tracking.iterations=8",
          "checkpoint_every=2",
          # the store's depth is stamped 3 ms after colour: resumed runs must move the
          # keyframes' depth they re-read exactly as the uninterrupted run did
          "align_depth_time=true",
          # the global stage checkpoints often enough to be stopped in its middle
          "global_map.hold_out_every=4", "global_map.checkpoint_every=3"]  # fmt: skip


@pytest.fixture(scope="module")
def resume_case(tmp_path_factory):
    """A 12-frame store and the uninterrupted run every resumed run must equal."""
    root = tmp_path_factory.mktemp("resume")
    folder = make_tum_folder(root, frames=12, size=(64, 48), seed=5)
    store = convert_tum(folder, root / "s.h5")
    run_job(store, root / "reference", load_config("cpu", RESUME))
    return store, root / "reference"


def assert_same_result(job, reference):
    assert (job / "trajectory.txt").read_bytes() == (reference / "trajectory.txt").read_bytes()
    names = sorted(p.name for p in (reference / "submaps").iterdir())
    assert sorted(p.name for p in (job / "submaps").iterdir()) == names
    for name in names:
        a = torch.load(job / "submaps" / name, weights_only=True)["params"]
        b = torch.load(reference / "submaps" / name, weights_only=True)["params"]
        assert all(torch.equal(a[k], b[k]) for k in b)
    ours, theirs = (torch.load(j / GLOBAL_MAP_FILE, weights_only=True) for j in (job, reference))
    assert all(torch.equal(ours["params"][k], theirs["params"][k]) for k in theirs["params"])
    assert ours["visits_per_frame"] == theirs["visits_per_frame"]
    ours = [json.loads(x) for x in (job / "log.jsonl").read_text().splitlines()]
    theirs = [json.loads(x) for x in (reference / "log.jsonl").read_text().splitlines()]
    strip = TIMING_FIELDS
    assert [{k: v for k, v in e.items() if k not in strip} for e in ours] == [
        {k: v for k, v in e.items() if k not in strip} for e in theirs]


def bgs_run(store, job):
    args = [str(Path(sys.executable).with_name("bgs")), "-q", "run", str(store), "--job-dir",
            str(job), *sum((["--set", s] for s in RESUME), [])]  # fmt: skip
    return subprocess.Popen(args, stderr=subprocess.PIPE, text=True)


def wait_for_frames(job, count, proc):
    log = job / "log.jsonl"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if log.exists() and log.read_text().count("\n") >= count:
            return
        time.sleep(0.01)
    raise AssertionError(f"the run ended or stalled before frame {count}")


@pytest.mark.slow
@pytest.mark.parametrize("kill_at", [3, 6, 9])
def test_kill_9_then_resume_equals_uninterrupted(resume_case, tmp_path, kill_at):
    store, reference = resume_case
    job = tmp_path / "job"
    proc = bgs_run(store, job)
    wait_for_frames(job, kill_at, proc)
    proc.kill()
    proc.wait()
    assert not (job / "summary.json").exists()
    run_job(store, job, load_config("cpu", RESUME))
    assert_same_result(job, reference)


def wait_for_global_stage(job, proc, end_steps=2):
    """Until a checkpoint of the global stage with `end_steps` − 1 visits done exists."""
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline and proc.poll() is None:
        names = [p.name for p in (job / CHECKPOINT_DIR).glob("*.pt")]
        if any(int(name.split("-")[1]) >= end_steps for name in names):
            return
        time.sleep(0.01)
    raise AssertionError("the run ended or stalled before its global stage checkpointed")


@pytest.mark.slow
def test_kill_9_in_the_global_stage_then_resume_equals_uninterrupted(resume_case, tmp_path):
    store, reference = resume_case
    job = tmp_path / "job"
    proc = bgs_run(store, job)
    wait_for_global_stage(job, proc)
    proc.kill()
    proc.wait()
    assert not (job / "summary.json").exists()
    assert load_latest(job)[1]["global_map"]["visits"] >= 3  # resumes inside the stage
    run_job(store, job, load_config("cpu", RESUME))
    assert_same_result(job, reference)


@pytest.mark.slow
def test_sigterm_in_the_global_stage_checkpoints_exits_75_and_resumes(resume_case, tmp_path):
    store, reference = resume_case
    job = tmp_path / "job"
    proc = bgs_run(store, job)
    wait_for_global_stage(job, proc, end_steps=1)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 75, err
    assert "in the global stage after" in err and "continues where it stopped" in err
    run_job(store, job, load_config("cpu", RESUME))
    assert_same_result(job, reference)


@pytest.mark.slow
def test_a_run_stopped_after_its_frames_repeats_the_end_to_the_same_files(
        resume_case, tmp_path, monkeypatch):  # fmt: skip
    """Stopped after `Slam.finish` (the end-of-run uncertainty refinement has rewritten submap
    files) but before the global stage's first checkpoint: the resumed run refines from the
    mapped r_i again, not twice."""
    store, reference = resume_case
    first = torch.load(reference / "submaps/000000.pt", weights_only=True)
    logits = [first[key]["uncertainty_logits"] for key in ("params", "raw_params")]
    assert not torch.equal(*logits)  # the cpu preset refines; the raw ones stay as mapped
    job = tmp_path / "job"

    def killed(*_args):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(Slam, "global_stage", killed)
        with pytest.raises(KeyboardInterrupt):
            run_job(store, job, load_config("cpu", RESUME))
    assert load_latest(job)[0] == 12 and "global_map" not in load_latest(job)[1]
    run_job(store, job, load_config("cpu", RESUME))  # every frame done: `finish` runs again
    assert_same_result(job, reference)


@pytest.mark.slow
def test_sigterm_checkpoints_and_exits_75(resume_case, tmp_path):
    store, reference = resume_case
    job = tmp_path / "job"
    proc = bgs_run(store, job)
    wait_for_frames(job, 3, proc)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 75, err
    assert "SIGTERM" in err and "continues where it stopped" in err
    frames = load_latest(job)[0]
    assert frames == (job / "log.jsonl").read_text().count("\n") >= 3
    run_job(store, job, load_config("cpu", RESUME))
    assert_same_result(job, reference)


def test_damaged_newest_checkpoint_falls_back(resume_case, tmp_path, caplog):
    store, reference = resume_case
    job = tmp_path / "job"

    def stop_at_frame_5(event):
        if event["frame"] == 5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_job(store, job, load_config("cpu", RESUME), on_frame=stop_at_frame_5)
    newest = sorted((job / CHECKPOINT_DIR).glob("*.pt"))[-1]
    assert newest.name.startswith("00000004")
    newest.write_bytes(newest.read_bytes()[:100])  # truncated
    run_job(store, job, load_config("cpu", RESUME))
    assert "damaged" in caplog.text
    assert_same_result(job, reference)


def test_failed_checkpoint_write_keeps_the_previous_one(tmp_path, monkeypatch):
    first = write_checkpoint(tmp_path, 2, {"x": torch.ones(3)})

    def disk_full(*_args):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", disk_full)
    with pytest.raises(OSError, match="No space"):
        write_checkpoint(tmp_path, 4, {"x": torch.zeros(3)})
    monkeypatch.undo()
    assert sorted((tmp_path / CHECKPOINT_DIR).iterdir()) == [first]  # no temp file left
    frames, state = load_latest(tmp_path)
    assert frames == 2 and torch.equal(state["x"], torch.ones(3))


def test_the_store_s_recommended_crop_is_applied_unless_set(tmp_path):
    folder = make_tum_folder(tmp_path / "src", frames=2, size=(640, 480))  # freiburg1: 50 px
    store = convert_tum(folder, tmp_path / "fr1.h5")

    def run(job: str, *sets: str):
        args = ["-q", "run", str(store), "--job-dir", str(tmp_path / job), "--max-frames", "1",
                "--no-export", *sum((["--set", s] for s in [*TINY, *sets]), [])]  # fmt: skip
        return CliRunner().invoke(main, args)

    assert run("default").exit_code == 0
    config = json.loads((tmp_path / "default" / "config.json").read_text())
    assert config["settings"]["crop_edge"] == 50
    assert config["sources"]["crop_edge"].startswith("the store's value (fr1.h5")
    record = json.loads((tmp_path / "default" / "job.json").read_text())
    assert record["config"]["crop_edge"] == 50  # exports and resumes use the resolved value
    # the Kinect's rolling shutter comes from the store too, and the frames say how they moved
    assert config["settings"]["rolling_shutter_readout"] == pytest.approx(0.03)
    assert config["sources"]["rolling_shutter_readout"].startswith("the store's value")
    assert run("set", "crop_edge=0").exit_code == 0
    config = json.loads((tmp_path / "set" / "config.json").read_text())
    assert config["settings"]["crop_edge"] == 0 and config["sources"]["crop_edge"].startswith("set")
    assert run("global", "rolling_shutter_readout=0").exit_code == 0
    config = json.loads((tmp_path / "global" / "config.json").read_text())
    assert config["settings"]["rolling_shutter_readout"] == 0
    too_big = run("big", "crop_edge=240")
    assert too_big.exit_code == 2 and "leaves nothing of the 640x480 images" in too_big.output
    assert not (tmp_path / "big").exists()
