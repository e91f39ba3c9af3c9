"""The hostile user's probes (issues P13 and P16): each one a clear one-line error with its
documented exit code, or a correct recovery; never a spliced run, a traceback or damaged input
stored as data. (P16's first probe, a cold against a warm kernel cache, is
`tests/test_kernel_cache.py`.)

The probes of truncated JPEGs and of nonsense settings are replayed where their code is tested:
`tests/converters/test_tum.py::test_a_truncated_jpeg_is_refused_not_stored_grey` (also the bag
and ScanNet readers' tests) and `tests/test_config.py`.
"""

from __future__ import annotations

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
from click.testing import CliRunner
from conftest import make_tum_folder

from bgs_batch.cli import main
from bgs_batch.config import load_config
from bgs_batch.errors import Interrupted
from converters.tum import convert_tum
from jobs.jobdir import JOB_FILE, LOCK_FILE, JobError, job_lock
from jobs.run import run_job
from outputs.export import ExportOptions, export_job

TINY = ["mapping.iterations=2", "mapping.new_submap_iterations=2", "tracking.iterations=2",
        "checkpoint_every=2"]  # fmt: skip
SETS = sum((["--set", s] for s in TINY), [])
TRAJECTORY_ONLY = ExportOptions(ply=False, uncertainty=False, renders=False, metrics=False,
                                report=False)  # fmt: skip


def store(root, seed=0, frames=6):
    folder = make_tum_folder(root / f"src{seed}", frames=frames, seed=seed)
    return convert_tum(folder, root / f"s{seed}.h5")


def bgs(*args):
    return CliRunner().invoke(main, ["-q", *map(str, args)])


def one_line_error(result, code, *needles):
    """The command failed with `code` and one `Error:` line holding every needle."""
    assert result.exit_code == code, result.output
    assert "Traceback" not in result.output
    errors = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1, result.output
    for needle in needles:
        assert needle in errors[0], errors[0]


def stop_at(frame):
    """An `on_frame` that stops the run after `frame` with a real KeyboardInterrupt."""

    def hook(event):
        if event["frame"] == frame:
            raise KeyboardInterrupt

    return hook


# 1. --force never splices two runs -------------------------------------------------------------


def test_force_after_a_killed_run_with_another_store_runs_the_new_store_from_frame_0(tmp_path):
    first, other = store(tmp_path, 0), store(tmp_path, 1)
    job, fresh = tmp_path / "job", tmp_path / "fresh"
    cfg = load_config("cpu", TINY)
    with pytest.raises(KeyboardInterrupt):
        run_job(first, job, cfg, on_frame=stop_at(4))  # checkpoint after 4 frames
    run_job(other, job, cfg, force=True)
    run_job(other, fresh, cfg)
    assert (job / "trajectory.txt").read_bytes() == (fresh / "trajectory.txt").read_bytes()
    [moved] = tmp_path.glob("job.replaced-*")
    assert json.loads((moved / JOB_FILE).read_text())["store"]["path"] == str(first.resolve())
    assert not (moved / LOCK_FILE).exists() and not (moved / "summary.json").exists()


def test_force_with_new_settings_runs_every_frame_with_them(tmp_path):
    source = store(tmp_path)
    job, fresh = tmp_path / "job", tmp_path / "fresh"
    with pytest.raises(KeyboardInterrupt):
        run_job(source, job, load_config("cpu", TINY), on_frame=stop_at(4))
    new = load_config("cpu", [*TINY, "tracking.iterations=3"])
    run_job(source, job, new, force=True)
    run_job(source, fresh, new)
    assert (job / "trajectory.txt").read_bytes() == (fresh / "trajectory.txt").read_bytes()
    assert (job / "log.jsonl").read_text().count("\n") == 6
    settings = json.loads((job / "config.json").read_text())["settings"]
    assert settings["tracking"]["iterations"] == 3


def test_force_on_a_finished_job_reruns_it_and_every_file_describes_the_new_run(tmp_path):
    source = store(tmp_path)
    job = tmp_path / "job"
    assert bgs("run", source, "--job-dir", job, *SETS).exit_code == 0
    old_metrics = (job / "outputs/metrics.json").read_text()
    old_trajectory = (job / "trajectory.txt").read_bytes()
    new = ["--set", "tracking.iterations=3"]
    rerun = bgs("run", source, "--job-dir", job, *SETS, *new, "--force")
    assert rerun.exit_code == 0, rerun.output
    assert json.loads((job / JOB_FILE).read_text())["config"]["tracking"]["iterations"] == 3
    settings = json.loads((job / "config.json").read_text())["settings"]
    assert settings["tracking"]["iterations"] == 3
    trajectory = (job / "trajectory.txt").read_bytes()
    assert trajectory != old_trajectory
    assert (job / "outputs/trajectory/estimate.tum").read_bytes() == trajectory
    [moved] = tmp_path.glob("job.replaced-*")
    assert (moved / "outputs/metrics.json").read_text() == old_metrics  # kept, not lost
    assert (moved / "trajectory.txt").read_bytes() == old_trajectory
    one_line_error(bgs("run", source, "--job-dir", job, *SETS), 5, "different config")


def test_a_folder_with_run_files_but_no_readable_job_json_is_not_resumed(tmp_path):
    source = store(tmp_path)
    job = tmp_path / "job"
    with pytest.raises(KeyboardInterrupt):
        run_job(source, job, load_config("cpu", TINY), on_frame=stop_at(4))
    (job / JOB_FILE).write_text("{garbage")
    one_line_error(bgs("run", source, "--job-dir", job, *SETS), 5, "unreadable", "--force")
    (job / JOB_FILE).unlink()
    one_line_error(bgs("run", source, "--job-dir", job, *SETS), 5, "not empty")
    assert bgs("run", source, "--job-dir", job, *SETS, "--force").exit_code == 5  # not a job
    (job / JOB_FILE).write_text("{garbage")
    assert bgs("run", source, "--job-dir", job, *SETS, "--force").exit_code == 0
    assert (job / "log.jsonl").read_text().count("\n") == 6


# 4. a damaged store chunk ----------------------------------------------------------------------


def flip_bytes(path, frame, dataset="rgb"):
    with h5py.File(path, "r") as fh:
        chunk = fh[dataset].id.get_chunk_info(frame)
    with open(path, "r+b") as fh:
        fh.seek(chunk.byte_offset + chunk.size // 2)
        data = fh.read(8)
        fh.seek(chunk.byte_offset + chunk.size // 2)
        fh.write(bytes(b ^ 0xFF for b in data))


def test_a_damaged_chunk_names_the_store_and_frame_everywhere(tmp_path):
    source = store(tmp_path)
    flip_bytes(source, 3)
    flip_bytes(source, 5, "depth")
    one_line_error(bgs("inspect", source), 3, str(source), "frame 3 is damaged", "--verify")
    verify = bgs("inspect", "--verify", source)
    assert verify.exit_code == 3
    assert [line.split(":")[0] for line in verify.output.splitlines()[:2]] == ["frame 3",
                                                                               "frame 5"]
    assert "2 of 6 frames are damaged" in verify.output
    job = tmp_path / "job"
    one_line_error(bgs("run", source, "--job-dir", job, *SETS), 3, "frame 3 is damaged")
    assert "frame 3 is damaged" in json.loads((job / "error.json").read_text())["message"]
    assert bgs("inspect", "--verify", store(tmp_path, 1)).exit_code == 0


# 5. the file system says no --------------------------------------------------------------------


@pytest.fixture
def tmpfs(tmp_path):
    """Mount a small tmpfs (`tmpfs(name, size)`); `tmpfs.read_only(path)` remounts it read-only.
    Needs root (mount); skipped otherwise, and the mapping is tested without it below."""
    mounts = []

    def mount(name, size="2m"):
        path = tmp_path / name
        path.mkdir()
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                              capture_output=True, text=True, check=False)  # fmt: skip
        if done.returncode:
            pytest.skip(f"cannot mount a tmpfs here (needs root): {done.stderr.strip()}")
        mounts.append(path)
        return path

    def read_only(path):
        subprocess.run(["mount", "-o", "remount,ro", str(path)], check=True)

    mount.read_only = read_only
    yield mount
    for path in reversed(mounts):
        subprocess.run(["umount", "-l", str(path)], check=False)


def test_convert_onto_a_full_or_read_only_disk_is_one_line_and_leaves_nothing(tmp_path, tmpfs):
    folder = make_tum_folder(tmp_path / "src", frames=30, size=(320, 240))
    full = tmpfs("full", "300k")
    one_line_error(bgs("convert", "tum", folder, "-o", full / "s.h5"), 6, str(full),
                   "disk is full")  # fmt: skip
    assert list(full.iterdir()) == []
    read_only = tmpfs("ro")
    tmpfs.read_only(read_only)
    one_line_error(bgs("convert", "tum", folder, "-o", read_only / "s.h5"), 6, "read-only")
    one_line_error(bgs("synth", full / "seq", "--frames", 3), 6, "disk is full")
    assert list(full.iterdir()) == []


def test_run_on_a_full_disk_says_so_and_resumes_once_space_is_freed(tmp_path, tmpfs):
    source = store(tmp_path, frames=8)
    settings = [*TINY, "checkpoint_every=1"]
    args = ["run", source, *sum((["--set", s] for s in settings), []), "--no-export"]
    disk = tmpfs("disk", "3m")
    job = disk / "job"
    ballast = disk / "ballast"
    free = os.statvfs(disk).f_bavail * os.statvfs(disk).f_frsize
    ballast.write_bytes(b"\0" * (free - 600_000))  # room for one checkpoint (~430 kB), not two
    one_line_error(bgs(*args, "--job-dir", job), 6, str(job), "disk is full")
    assert not list((job / "checkpoints").glob(".tmp-*"))
    ballast.unlink()
    resumed = bgs(*args, "--job-dir", job)
    assert resumed.exit_code == 0, resumed.output
    run_job(source, tmp_path / "reference", load_config("cpu", settings))
    reference = (tmp_path / "reference/trajectory.txt").read_bytes()
    assert (job / "trajectory.txt").read_bytes() == reference


def test_export_into_a_read_only_job_is_one_line(tmp_path, tmpfs):
    source = store(tmp_path)
    disk = tmpfs("disk", "20m")
    job = disk / "job"
    assert bgs("run", source, "--job-dir", job, *SETS, "--no-export").exit_code == 0
    tmpfs.read_only(disk)
    one_line_error(bgs("export", job), 6, str(job), "read-only")
    one_line_error(bgs("eval", job), 6, "read-only")


def test_any_file_system_refusal_is_exit_6_without_a_traceback(tmp_path, monkeypatch):
    """Where no tmpfs can be mounted: the same path, entered by the error the kernel gives."""
    import jobs.run

    source = store(tmp_path)
    job = tmp_path / "job"

    def refuse(job_dir, *_args):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(job_dir / "checkpoints"))

    monkeypatch.setattr(jobs.run, "write_checkpoint", refuse)
    one_line_error(bgs("run", source, "--job-dir", job, *SETS), 6, "checkpoints", "disk is full")
    verbose = CliRunner().invoke(main, ["-q", "-v", "run", str(source), "--job-dir", str(job),
                                        *SETS])  # fmt: skip
    assert verbose.exit_code == 6  # -v adds the details (logged to stderr)


def test_random_bytes_are_not_a_bag_or_a_sens_file(tmp_path):
    rng = __import__("numpy").random.default_rng(0)
    bag = tmp_path / "random.bag"
    bag.write_bytes(rng.bytes(20_000))
    one_line_error(bgs("convert", "bag", bag, "-o", tmp_path / "b.h5"), 3, str(bag))
    sens = tmp_path / "garbage.sens"
    sens.write_bytes((4).to_bytes(4, "little") + rng.bytes(5_000))  # valid version, then junk
    one_line_error(bgs("convert", "scannet", sens, "-o", tmp_path / "s.h5"), 3, str(sens))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["garbage.sens", "random.bag"]


# 6. a signal or kill -9 during the export ------------------------------------------------------


def test_an_export_removes_what_a_killed_one_left_and_a_signal_leaves_nothing(tmp_path):
    source = store(tmp_path)
    job = tmp_path / "job"
    assert bgs("run", source, "--job-dir", job, *SETS).exit_code == 0
    outputs = job / "outputs"
    before = {p.relative_to(job): p.read_bytes() for p in outputs.rglob("*") if p.is_file()}
    (outputs / ".tmp-report.html.999.deadbeef").write_text("<html")  # as kill -9 leaves them
    (outputs / ".tmp-uncertainty.999.cafe").mkdir()
    export_job(job, TRAJECTORY_ONLY)
    assert not list(outputs.glob(".tmp-*"))

    def sigterm(_frames):
        os.kill(os.getpid(), signal.SIGTERM)

    with pytest.raises(Interrupted) as stopped:
        export_job(job, ExportOptions(), progress=sigterm)
    assert stopped.value.exit_code == 128 + signal.SIGTERM
    assert not list(outputs.glob(".tmp-*"))
    after = {p.relative_to(job): p.read_bytes() for p in outputs.rglob("*") if p.is_file()}
    assert after == before  # the previous complete outputs are untouched


def test_a_signal_during_the_run_s_export_exits_75_and_the_rerun_finishes_it(tmp_path,
                                                                            monkeypatch):
    import outputs.export

    source = store(tmp_path)
    job = tmp_path / "job"
    real = outputs.export.export_trajectories
    monkeypatch.setattr(outputs.export, "export_trajectories",
                        lambda *a: os.kill(os.getpid(), signal.SIGUSR1) or real(*a))  # fmt: skip
    stopped = bgs("run", source, "--job-dir", job, *SETS)
    one_line_error(stopped, 75, "export was stopped by SIGUSR1", "finishes it")
    assert not list((job / "outputs").glob(".tmp-*"))
    monkeypatch.undo()
    finished = bgs("run", source, "--job-dir", job, *SETS)
    assert finished.exit_code == 0 and (job / "outputs/report.html").is_file()


# 7. the smaller items --------------------------------------------------------------------------


def test_a_nan_translation_in_the_ground_truth_is_named_as_such(tmp_path):
    folder = make_tum_folder(tmp_path)
    gt = folder / "groundtruth.txt"
    lines = gt.read_text().splitlines()
    fields = lines[5].split()
    lines[5] = " ".join([fields[0], "nan", *fields[2:]])
    gt.write_text("\n".join(lines) + "\n")
    one_line_error(bgs("convert", "tum", folder, "-o", tmp_path / "s.h5"), 3,
                   f"{gt}:6", "not a finite number")  # fmt: skip


def test_status_of_a_job_and_a_missing_folder_shows_the_job_then_the_error(tmp_path):
    source = store(tmp_path)
    job = tmp_path / "job"
    run_job(source, job, load_config("cpu", TINY))
    result = bgs("status", job, tmp_path / "missing")
    assert result.exit_code == 3 and "done" in result.output
    assert "missing is not a bgs job directory" in result.output


def test_an_empty_or_garbage_lock_is_stale_unless_a_process_holds_it(tmp_path):
    source = store(tmp_path)
    job = tmp_path / "job"
    run_job(source, job, load_config("cpu", TINY))
    for garbage in ("", "{not json"):
        (job / LOCK_FILE).write_text(garbage)
        assert json.loads(bgs("status", job, "--json").output)[0]["state"] == "done"
        assert bgs("run", source, "--job-dir", job, *SETS, "--no-export").exit_code == 0
        assert not (job / LOCK_FILE).exists()
    (job / LOCK_FILE).write_text("")
    with open(job / LOCK_FILE) as held:  # another process's lock, its PID not yet readable
        fcntl.flock(held, fcntl.LOCK_EX)
        assert json.loads(bgs("status", job, "--json").output)[0]["state"] == "running"
        with pytest.raises(JobError, match="in use"), job_lock(job):
            pass


def test_the_lock_appears_whole(tmp_path):
    with job_lock(tmp_path):
        assert json.loads((tmp_path / LOCK_FILE).read_text())["pid"] == os.getpid()
        assert sorted(p.name for p in tmp_path.iterdir()) == [LOCK_FILE]  # no temporary left
    assert list(tmp_path.iterdir()) == []


def test_a_job_stopped_by_a_signal_shows_as_stopped_resumable(tmp_path):
    source = store(tmp_path)
    job = tmp_path / "job"

    def sigterm_at_2(event):
        if event["frame"] == 2:
            os.kill(os.getpid(), signal.SIGTERM)

    with pytest.raises(Exception, match="stopped by SIGTERM") as stopped:
        run_job(source, job, load_config("cpu", TINY), on_frame=sigterm_at_2)
    assert stopped.value.exit_code == 75
    assert json.loads(bgs("status", job, "--json").output)[0]["state"] == "stopped"
    assert "stopped (resumable)" in bgs("status", job).output


# ================================================================ round two (issue P16) =========
# 1. outputs cannot mix stores ------------------------------------------------------------------


def test_export_or_eval_with_another_recording_s_store_is_refused_naming_both(tmp_path):
    source, other = store(tmp_path, 0), store(tmp_path, 1)
    job = tmp_path / "job"
    run_job(source, job, load_config("cpu", TINY))
    for command in (("export", job, "--trajectory"), ("eval", job, "--no-report")):
        result = bgs(*command, "--store", other)
        one_line_error(result, 5, str(other), "is not the frame store", "job.json")
    assert not (job / "outputs").exists()
    moved = tmp_path / "moved" / "s0.h5"  # the job's own store, moved: still its store
    moved.parent.mkdir()
    source.rename(moved)
    assert bgs("export", job, "--trajectory", "--store", moved).exit_code == 0


# 2. a JPEG corrupted in its middle is damage ---------------------------------------------------


def test_a_jpeg_corrupted_in_its_middle_is_refused_or_skipped_never_stored(tmp_path):
    import cv2

    folder = make_tum_folder(tmp_path / "src", frames=6)
    victims = sorted((folder / "rgb").iterdir())
    for victim in victims:  # JPEG colour images (the content decides, not the name)
        victim.write_bytes(cv2.imencode(".jpg", cv2.imread(str(victim)))[1].tobytes())
    data = victims[3].read_bytes()
    middle = len(data) // 2  # marker-like bytes in the entropy-coded data, end marker intact
    victims[3].write_bytes(data[:middle] + b"\xff\xd0" * 8 + data[middle + 16:])
    result = bgs("convert", "tum", folder, "-o", tmp_path / "s.h5")
    one_line_error(result, 3, victims[3].name, "corrupt JPEG", "Corrupt JPEG data")
    assert list(tmp_path.glob("s.h5*")) == []
    assert bgs("convert", "tum", folder, "-o", tmp_path / "s.h5", "--skip-bad-frames"
               ).exit_code == 0  # fmt: skip
    with h5py.File(tmp_path / "s.h5") as f:
        assert f["rgb"].shape[0] == 5 and "corrupt JPEG" in f.attrs["provenance"]


# 3. and 4. locks decided by flock; a lock that is not a file ------------------------------------


def test_a_lock_naming_a_live_pid_that_holds_nothing_is_stale(tmp_path):
    source = store(tmp_path)
    job = tmp_path / "job"
    run_job(source, job, load_config("cpu", TINY))
    (job / LOCK_FILE).write_text(json.dumps({"host": os.uname().nodename, "pid": 1}))
    assert json.loads(bgs("status", job, "--json").output)[0]["state"] == "done"
    assert bgs("run", source, "--job-dir", job, *SETS, "--no-export").exit_code == 0
    assert bgs("export", job, "--trajectory").exit_code == 0
    assert not (job / LOCK_FILE).exists()


@pytest.mark.parametrize("kind", ["directory", "symlink loop"])
def test_a_lock_that_is_not_a_file_is_one_line_naming_what_to_remove(tmp_path, kind):
    source = store(tmp_path)
    job = tmp_path / "job"
    run_job(source, job, load_config("cpu", TINY))
    lock = job / LOCK_FILE
    if kind == "directory":
        lock.mkdir()
    else:
        (job / "other").symlink_to(lock)
        lock.symlink_to(job / "other")
    for command in (("run", source, "--job-dir", job, *SETS), ("status", job),
                    ("export", job, "--trajectory")):  # fmt: skip
        one_line_error(bgs(*command), 5, str(lock), "not a bgs lock file", "rm -r")


# 5. two converts to one output -----------------------------------------------------------------


def test_a_second_convert_to_the_same_output_exits_5_and_the_first_finishes(tmp_path):
    # long enough that the second convert finds it still writing, even on a loaded machine
    folder = make_tum_folder(tmp_path / "src", frames=400, distinct=False)
    out = tmp_path / "s.h5"
    bgs_bin = str(Path(sys.executable).with_name("bgs"))
    first = subprocess.Popen([bgs_bin, "-q", "convert", "tum", str(folder), "-o", str(out)],
                             stderr=subprocess.PIPE, text=True)  # fmt: skip
    lock = tmp_path / ".lock-s.h5"
    deadline = time.monotonic() + 60
    while not lock.exists() and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
    second = bgs("convert", "tum", folder, "-o", out)
    assert first.wait(timeout=120) == 0, first.stderr.read()
    one_line_error(second, 5, str(out), "being written by another bgs convert",
                   f"process {first.pid}")  # fmt: skip
    with h5py.File(out) as f:
        assert f["rgb"].shape[0] == 400
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.h5", "src"]


# 6. names the file system cannot hold ------------------------------------------------------------


def test_long_names_convert_or_fail_with_exit_6_naming_the_path(tmp_path):
    folder = make_tum_folder(tmp_path / "src", frames=4)
    legal = tmp_path / ("n" * 247 + ".h5")  # 250 bytes: legal, its ".tmp" name would not be
    assert bgs("convert", "tum", folder, "-o", legal).exit_code == 0 and legal.is_file()
    job = tmp_path / ("j" * 300)
    one_line_error(bgs("run", legal, "--job-dir", job, *SETS), 6, "jjj", "longer than the file")
    job = tmp_path / ("j" * 250)
    assert bgs("run", legal, "--job-dir", job, *SETS, "--no-export").exit_code == 0
    assert bgs("run", legal, "--job-dir", job, *SETS, "--no-export", "--force").exit_code == 0
    [moved] = tmp_path.glob("jjj*.replaced-*")
    assert len(moved.name) <= 255 and (moved / JOB_FILE).is_file()


# 7. and 8. every setting checked before the job directory exists ---------------------------------


@pytest.mark.parametrize("setting, needle", [
    ("loop_closure.descriptor=netvlad", "not supported yet"),
    ("crop_edge=58", "less than the 8 px a side"),
    ("max_depth=1e-300", "out of range"),
])  # fmt: skip
def test_a_setting_refused_leaves_no_job_directory(tmp_path, setting, needle):
    folder = make_tum_folder(tmp_path / "src", frames=3, size=(160, 120))
    source = convert_tum(folder, tmp_path / "s.h5")
    job = tmp_path / "job"
    one_line_error(bgs("run", source, "--job-dir", job, "--set", setting), 2, needle)
    assert not job.exists()
    assert bgs("run", source, "--job-dir", job, *SETS, "--no-export").exit_code == 0


# 9. a signal between the run and its export ------------------------------------------------------


def test_a_signal_between_the_run_and_its_export_exits_75_and_the_rerun_exports(tmp_path,
                                                                               monkeypatch):
    import outputs.export

    source = store(tmp_path)
    job = tmp_path / "job"
    real = outputs.export.export_is_current

    def signal_first(job_dir):  # the first thing the export step does
        os.kill(os.getpid(), signal.SIGTERM)
        return real(job_dir)

    monkeypatch.setattr(outputs.export, "export_is_current", signal_first)
    one_line_error(bgs("run", source, "--job-dir", job, *SETS), 75, "SIGTERM", "finishes it")
    monkeypatch.undo()
    assert (job / "summary.json").is_file() and not (job / "outputs").exists()
    finished = bgs("run", source, "--job-dir", job, *SETS)
    assert finished.exit_code == 0 and (job / "outputs/report.html").is_file()


# 10. the smaller items ----------------------------------------------------------------------------


def test_a_job_killed_by_sigkill_shows_as_stopped_not_failed(tmp_path):
    source = store(tmp_path)
    job = tmp_path / "job"
    with pytest.raises(KeyboardInterrupt):
        run_job(source, job, load_config("cpu", TINY), on_frame=stop_at(3))
    (job / "error.json").unlink()  # as SIGKILL leaves it: no error recorded
    status = json.loads(bgs("status", job, "--json").output)[0]
    assert status["state"] == "stopped" and "resumes" in status["last_error"]


def test_a_bom_before_the_first_line_of_a_tum_list_is_not_data(tmp_path):
    folder = make_tum_folder(tmp_path / "src", frames=3)
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        text = (folder / name).read_text()
        (folder / name).write_text("\ufeff" + text.split("\n", 3)[3])  # no header, a BOM first
    assert bgs("convert", "tum", folder, "-o", tmp_path / "s.h5").exit_code == 0
    with h5py.File(tmp_path / "s.h5") as f:
        assert f["rgb"].shape[0] == 3


def test_a_store_of_a_newer_schema_names_the_version_that_reads_it(tmp_path):
    source = store(tmp_path)
    with h5py.File(source, "r+") as f:
        f.attrs["schema_version"] = 7
        f.attrs["created_by"] = "bgs-batch 9.0.0"
    one_line_error(bgs("inspect", source), 3, "schema v7", "bgs-batch 9.0.0", "reads schema v1")


def test_a_damaged_store_is_one_line_listing_every_problem(tmp_path):
    source = store(tmp_path)
    with h5py.File(source, "r+") as f:
        del f["intrinsics"]
        del f.attrs["depth_scale"]
    one_line_error(bgs("inspect", source), 3, "missing attributes: depth_scale",
                   "missing dataset /intrinsics", "re-create it")  # fmt: skip


def test_setting_tracking_iterations_under_the_warm_start_says_what_it_does(tmp_path):
    source = store(tmp_path)
    result = CliRunner().invoke(main, ["-q", "run", str(source), "--job-dir", str(tmp_path / "j"),
                                       "--max-frames", "2", "--no-export", "--set",
                                       "tracking.iterations=5"])  # fmt: skip
    assert result.exit_code == 0
    assert "Note: tracking.iterations=5 applies only to frames whose warm start" in result.output
