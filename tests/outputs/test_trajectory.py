"""The trajectory a user takes away: timestamp matching, the aligned estimate and its ATE."""

import numpy as np
import pytest

from bgs_batch.geometry import pose_matrix
from bgs_batch.trajectory_files import read_kitti, read_tum
from outputs.trajectory import match_timestamps, write_trajectories


def random_poses(n, seed=0):
    rng = np.random.default_rng(seed)
    quats = rng.normal(size=(n, 4))
    return pose_matrix(rng.normal(size=(n, 3)), quats / np.linalg.norm(quats, axis=1)[:, None])


def world_transform(angle=0.4, translation=(1.0, -2.0, 0.5)):
    out = np.eye(4)
    out[:3, :3] = [[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]]
    out[:3, 3] = translation
    return out


def test_match_timestamps():
    reference = np.array([3.0, 1.0, 2.0])
    np.testing.assert_array_equal(
        match_timestamps(np.array([1.00000001, 2.0, 2.5, 3.0, 9.0]), reference), [1, 2, -1, 0, -1]
    )


def test_rigidly_moved_estimate_aligns_to_zero_error(tmp_path):
    n = 12
    times = 100 + np.arange(n) / 30
    gt = random_poses(n, seed=1)
    gt[4] = np.nan  # a frame without GT
    estimate = np.linalg.inv(world_transform()) @ random_poses(n, seed=1)
    stats = write_trajectories(tmp_path, times, estimate, gt)
    assert stats["rigid"]["rmse"] < 1e-9 and stats["rigid"]["frames"] == n - 1
    assert stats["with_scale"]["rmse"] < 1e-9

    t_tum, aligned = read_tum(tmp_path / "estimate_aligned.tum")
    assert len(t_tum) == n  # TUM: every frame with an estimate
    np.testing.assert_allclose(aligned, random_poses(n, seed=1), atol=1e-7)
    t_est, est_back = read_tum(tmp_path / "estimate.tum")
    np.testing.assert_allclose(est_back, estimate, atol=1e-7)
    np.testing.assert_allclose(t_est, times, atol=1e-6)
    assert len(read_tum(tmp_path / "gt.tum")[0]) == n - 1
    kitti = {name: read_kitti(tmp_path / f"{name}.kitti")
             for name in ("estimate", "estimate_aligned", "gt")}  # fmt: skip
    assert {len(p) for p in kitti.values()} == {n - 1}  # KITTI: frames where all are finite
    np.testing.assert_allclose(kitti["estimate_aligned"], kitti["gt"], atol=1e-7)
    np.testing.assert_allclose(np.loadtxt(tmp_path / "times.txt"), np.delete(times, 4), atol=1e-6)


def test_known_noise_gives_known_rmse(tmp_path):
    gt = np.tile(np.eye(4), (4, 1, 1))
    gt[:, :3, 3] = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]
    estimate = gt.copy()
    estimate[:, 2, 3] = [0.01, -0.01, -0.01, 0.01]  # zero-mean, no rotation can absorb it
    stats = write_trajectories(tmp_path, np.arange(4.0), estimate, gt)
    assert stats["rigid"]["rmse"] == pytest.approx(0.01, rel=1e-6)


def test_without_ground_truth_only_the_estimate(tmp_path):
    assert write_trajectories(tmp_path, np.arange(3.0), random_poses(3)) == {}
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "estimate.kitti",
        "estimate.tum",
        "times.txt",
    ]
