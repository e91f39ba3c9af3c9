"""TUM and KITTI trajectory files: round trips, unknown poses left out, malformed files refused."""

import numpy as np
import pytest

from bgs_batch.geometry import pose_matrix
from bgs_batch.trajectory_files import read_kitti, read_tum, write_kitti, write_tum


def unit(q):
    q = np.asarray(q, float)
    return q / np.linalg.norm(q)


def random_poses(n, seed=0):
    rng = np.random.default_rng(seed)
    quats = rng.normal(size=(n, 4))
    return pose_matrix(rng.normal(size=(n, 3)), quats / np.linalg.norm(quats, axis=1)[:, None])


def test_tum_trajectory_round_trip(tmp_path):
    poses = np.stack([pose_matrix([i, 2.0, -1], unit([0.1 * i, 0.2, 0.3, 0.9])) for i in range(4)])
    poses[2] = np.nan
    write_tum(tmp_path / "t.txt", np.arange(4) + 0.5, poses)
    times, back = read_tum(tmp_path / "t.txt")
    assert times.tolist() == [0.5, 1.5, 3.5]
    assert np.allclose(back, poses[[0, 1, 3]], atol=1e-8)


def test_a_file_with_other_columns_is_not_read_as_tum(tmp_path):
    (tmp_path / "t.txt").write_text("0.0 1 2 3\n")
    with pytest.raises(ValueError, match="4 columns, TUM has 8"):
        read_tum(tmp_path / "t.txt")


def test_kitti_round_trip_is_row_major(tmp_path):
    poses = random_poses(5)
    write_kitti(tmp_path / "t.kitti", poses)
    first = np.loadtxt(tmp_path / "t.kitti")[0]
    np.testing.assert_allclose(first, poses[0, :3, :].ravel(), atol=1e-9)
    np.testing.assert_allclose(read_kitti(tmp_path / "t.kitti"), poses, atol=1e-8)
    with pytest.raises(ValueError):
        write_kitti(tmp_path / "bad.kitti", np.full((1, 4, 4), np.nan))


def test_a_tum_file_written_again_from_its_own_poses_is_the_same(tmp_path):
    """Exports write trajectory.txt again from the poses read back: a component that rounds to
    zero is written as 0, never −0, whichever side of zero its last bits fall."""
    c2w = pose_matrix(np.array([[1e-12, -1e-12, 0.5]]), np.array([[-1e-12, 1e-12, 0.0, 1.0]]))
    first, second = tmp_path / "a.tum", tmp_path / "b.tum"
    write_tum(first, np.array([0.0]), c2w)
    write_tum(second, *read_tum(first))
    assert "-0.000000000" not in first.read_text()
    assert second.read_bytes() == first.read_bytes()
