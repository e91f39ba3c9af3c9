"""Relative pose error and path length (bgs_batch/metrics.py) against closed forms."""

import numpy as np
import pytest

from bgs_batch.metrics import path_length, rpe


def _yaw(degrees: float) -> np.ndarray:
    a = np.radians(degrees)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def _walk(steps: int, step: np.ndarray, turn_deg: float = 0.0) -> np.ndarray:
    """Camera-to-world poses moving `step` (camera frame) and turning `turn_deg` per frame."""
    poses = [np.eye(4)]
    motion = np.eye(4)
    motion[:3, :3], motion[:3, 3] = _yaw(turn_deg), step
    for _ in range(steps - 1):
        poses.append(poses[-1] @ motion)
    return np.stack(poses)


def test_rpe_measures_the_error_of_each_step_in_any_world_frame():
    truth = _walk(20, np.array([0.01, 0.0, 0.0]), turn_deg=2.0)
    assert rpe(truth, truth)["translation_rmse"] == pytest.approx(0.0, abs=1e-12)
    longer = _walk(20, np.array([0.013, 0.004, 0.0]), turn_deg=3.0)  # 5 mm and 1 degree off
    moved = np.eye(4)
    moved[:3, :3], moved[:3, 3] = _yaw(40.0), [1.0, -2.0, 0.5]
    for estimate in (longer, moved @ longer):  # the world frame does not matter
        error = rpe(estimate, truth)
        assert error["translation_rmse"] == pytest.approx(0.005, rel=1e-9)
        assert error["rotation_mean_deg"] == pytest.approx(1.0, rel=1e-9)
        assert error["pairs"] == 19


def test_rpe_skips_unknown_poses_and_refuses_when_nothing_is_left():
    truth = _walk(5, np.array([0.01, 0.0, 0.0]))
    estimate = truth.copy()
    estimate[2] = np.nan
    assert rpe(estimate, truth)["pairs"] == 2  # 0-1 and 3-4
    with pytest.raises(ValueError, match="no pair"):
        rpe(estimate[:3], truth[:3], delta=2)


def test_path_length_of_a_square_with_a_gap():
    square = np.array([[0, 0, 0], [1, 0, 0], [np.nan, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 0.0]])
    assert path_length(square) == pytest.approx(4.0)
