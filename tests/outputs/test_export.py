"""`bgs export` on a fabricated job directory: files exist and parse; clean input errors."""

import fcntl
import json
import os
import socket

import numpy as np
import torch
from click.testing import CliRunner
from conftest import make_tum_folder
from plyfile import PlyData

from bgs_batch.cli import main
from bgs_batch.store import FrameStore
from bgs_batch.trajectory_files import read_kitti, read_tum, write_tum
from jobs.jobdir import LOCK_FILE
from outputs.ply import PROPERTIES, read_ply


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def make_job(job, timestamps, poses, gaussians=(3, 4)):
    """A job directory as `bgs run` writes it: submaps/*.pt, global_map.pt (the submaps
    concatenated, trained on every frame) and trajectory.txt."""
    (job / "submaps").mkdir(parents=True)
    parts = []
    for index, n in enumerate(gaussians):
        params = {"means": torch.randn(n, 3) + 10 * index, "log_scales": torch.full((n, 3), -4.0),
                  "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                  "opacity_logits": torch.zeros(n), "colors": torch.rand(n, 3),
                  "uncertainty_logits": torch.full((n,), -7.0)}  # fmt: skip
        torch.save({"params": params, "keyframes": torch.tensor([index]), "first_frame": index},
                   job / "submaps" / f"{index:06d}.pt")  # fmt: skip
        parts.append(params)
    merged = {name: torch.cat([p[name] for p in parts]) for name in parts[0]}
    frames = list(range(len(timestamps)))
    torch.save({"params": merged, "merged_from": list(gaussians), "training_frames": frames,
                "held_out_frames": [], "visits": 0, "visits_per_frame": [0] * len(frames)},
               job / "global_map.pt")  # fmt: skip
    write_tum(job / "trajectory.txt", timestamps, poses)


def test_export_writes_plys_and_trajectories_with_ground_truth(tmp_path):
    folder = make_tum_folder(tmp_path, frames=6)
    store = tmp_path / "seq.h5"
    assert run("convert", "tum", folder, "-o", store).exit_code == 0
    with FrameStore(store) as opened:
        timestamps, gt = opened.timestamps, opened.poses_gt
    moved = np.eye(4)
    moved[:3, 3] = [0.3, -0.2, 1.0]
    job = tmp_path / "job"
    make_job(job, timestamps, moved @ gt)

    result = run("export", job, "--store", store, "--ply", "--trajectory")
    assert result.exit_code == 0, result.output
    assert "ATE RMSE (rigid): 0.00 cm" in result.output
    ply_dir = job / "outputs" / "ply"
    assert sorted(p.name for p in ply_dir.iterdir()) == [
        "global.ply",
        "submap_000000.ply",
        "submap_000001.ply",
    ]
    assert [p.name for p in PlyData.read(str(ply_dir / "global.ply"))["vertex"].properties] == list(
        PROPERTIES
    )
    assert len(read_ply(ply_dir / "global.ply")) == 7
    traj = job / "outputs" / "trajectory"
    times, aligned = read_tum(traj / "estimate_aligned.tum")
    np.testing.assert_allclose(aligned[:, :3, 3], gt[:, :3, 3], atol=1e-6)
    np.testing.assert_allclose(times, timestamps, atol=1e-6)
    assert len(read_kitti(traj / "gt.kitti")) == len(read_kitti(traj / "estimate.kitti")) == 6

    assert run("export", job, "--ply").exit_code == 0  # re-export replaces only its own folder
    assert (traj / "gt.tum").is_file()
    assert run("export", job, "--trajectory").exit_code == 0  # no store: no stale GT files
    assert sorted(p.name for p in traj.iterdir()) == ["estimate.kitti", "estimate.tum", "times.txt"]


def test_missing_or_incomplete_job_exits_3(tmp_path):
    result = run("export", tmp_path / "nope")
    assert result.exit_code == 3 and "bgs run" in result.output
    job = tmp_path / "job"
    make_job(job, np.arange(3.0), np.tile(np.eye(4), (3, 1, 1)))
    (job / "submaps" / "000001.pt").write_bytes(b"truncated")
    result = run("export", job, "--ply")
    assert result.exit_code == 3 and "000001.pt" in result.output
    (job / "trajectory.txt").unlink()
    result = run("export", job, "--trajectory")
    assert result.exit_code == 3 and "trajectory.txt" in result.output
    assert run("export", job, "--trajectory", "--store", tmp_path / "none.h5").exit_code == 3


def test_ground_truth_from_the_recorded_store_and_running_jobs_refused(tmp_path):
    folder = make_tum_folder(tmp_path, frames=4)
    store = tmp_path / "seq.h5"
    assert run("convert", "tum", folder, "-o", store).exit_code == 0
    with FrameStore(store) as opened:
        timestamps, gt = opened.timestamps, opened.poses_gt
    job = tmp_path / "job"
    make_job(job, timestamps, gt, gaussians=(2,))
    (job / "job.json").write_text(json.dumps({"store": {"path": str(store)}}))
    result = run("export", job, "--trajectory")
    assert result.exit_code == 0 and "ATE RMSE (rigid)" in result.output
    assert (job / "outputs" / "trajectory" / "gt.tum").is_file()

    (job / LOCK_FILE).write_text(json.dumps({"host": socket.gethostname(), "pid": os.getpid()}))
    with open(job / LOCK_FILE) as held:  # a running `bgs run` holds its lock's flock
        fcntl.flock(held, fcntl.LOCK_EX)
        result = run("export", job)
    assert result.exit_code == 3 and "still being written" in result.output
    (job / LOCK_FILE).unlink()
