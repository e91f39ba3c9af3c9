"""The trajectory smoother: its posterior mean against a dense float64 solve, its
maximum-likelihood noise against the noise drawn, and what it does to noisy and clean poses."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bgs_batch.config import SmoothingConfig
from bgs_batch.slam.smoothing import DIFFUSE, smooth_coordinates, smooth_trajectory


def _fixed(log_ratio: float) -> SmoothingConfig:
    return SmoothingConfig(enabled=True, log_ratio_min=log_ratio, log_ratio_max=log_ratio)


def _dense_posterior_mean(z: np.ndarray, t: np.ndarray, ratio: float) -> np.ndarray:
    """The posterior mean of the constant-velocity model in one linear solve: states
    (position, velocity) per time, measurements of unit variance, process noise ratio · Q(dt),
    the first position known to unit variance and its velocity to DIFFUSE."""
    n = len(z)
    information = np.zeros((2 * n, 2 * n))
    vector = np.zeros((2 * n, z.shape[1]))
    for k in range(n):  # measurements
        information[2 * k, 2 * k] += 1.0
        vector[2 * k] += z[k]
    information[1, 1] += 1.0 / DIFFUSE
    for k in range(1, n):
        dt = t[k] - t[k - 1]
        f = np.array([[1.0, dt], [0.0, 1.0]])
        q = ratio * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        a = np.zeros((2, 2 * n))  # w = x_k - F x_{k-1}
        a[:, 2 * k : 2 * k + 2] = np.eye(2)
        a[:, 2 * k - 2 : 2 * k] = -f
        information += a.T @ np.linalg.inv(q) @ a
    return np.linalg.solve(information, vector)[0::2]


def test_the_smoother_is_the_dense_posterior_mean():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.02, 0.05, 40))  # uneven frame times
    z = np.cumsum(rng.normal(size=(40, 3)), axis=0) * 0.01
    for log_ratio in (0.0, 3.0, 6.0):
        smoothed, fit = smooth_coordinates(z, t, _fixed(log_ratio))
        assert fit.log10_ratio == log_ratio
        np.testing.assert_allclose(smoothed, _dense_posterior_mean(z, t, 10.0**log_ratio),
                                   rtol=0, atol=1e-9)  # fmt: skip


def _simulate(rng, n, dt, q, r, c=3):
    """A constant-velocity process driven by white acceleration of density q, measured with
    variance r."""
    f = np.array([[1.0, dt], [0.0, 1.0]])
    cov = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    x = np.zeros((c, 2))
    truth = []
    for _ in range(n):
        x = x @ f.T + rng.multivariate_normal(np.zeros(2), cov, size=c)
        truth.append(x[:, 0].copy())
    truth = np.array(truth)
    return truth, truth + rng.normal(scale=np.sqrt(r), size=truth.shape)


@pytest.mark.parametrize("log_ratio", [3.0, 5.0])
def test_the_noise_is_the_maximum_likelihood_one(log_ratio):
    rng = np.random.default_rng(1)
    r = 0.002**2
    truth, z = _simulate(rng, 1500, 1 / 30, r * 10.0**log_ratio, r)
    t = np.arange(len(z)) / 30
    smoothed, fit = smooth_coordinates(z, t, SmoothingConfig(enabled=True))
    assert abs(fit.log10_ratio - log_ratio) <= 0.5
    assert fit.noise == pytest.approx(0.002, rel=0.1)
    raw_error = np.sqrt(np.mean((z - truth) ** 2))
    assert np.sqrt(np.mean((smoothed - truth) ** 2)) < 0.8 * raw_error


def _spinning_trajectory(n: int, dt: float) -> np.ndarray:
    """Camera-to-world poses turning twice about a tilted axis while moving on a circle."""
    times = np.arange(n) * dt
    poses = np.tile(np.eye(4), (n, 1, 1))
    angle = 4 * np.pi * times / times[-1]
    axis = np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0])
    poses[:, :3, :3] = Rotation.from_rotvec(angle[:, None] * axis).as_matrix()
    poses[:, :3, 3] = np.stack([np.cos(angle / 2), np.sin(angle / 2), 0.1 * angle], axis=1)
    return poses


def _errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """RMS position error (m) and rotation error (rad)."""
    position = np.sqrt(np.mean(np.sum((estimate[:, :3, 3] - truth[:, :3, 3]) ** 2, axis=1)))
    relative = Rotation.from_matrix(np.swapaxes(truth[:, :3, :3], 1, 2) @ estimate[:, :3, :3])
    return float(position), float(np.sqrt(np.mean(relative.magnitude() ** 2)))


def test_jittery_poses_come_closer_to_the_truth_through_full_turns():
    rng = np.random.default_rng(2)
    truth = _spinning_trajectory(300, 1 / 30)
    noisy = truth.copy()
    noisy[:, :3, 3] += rng.normal(scale=0.003, size=(300, 3))
    jitter = Rotation.from_rotvec(rng.normal(scale=np.radians(0.2), size=(300, 3)))
    noisy[:, :3, :3] = (Rotation.from_matrix(truth[:, :3, :3]) * jitter).as_matrix()
    smoothed, report = smooth_trajectory(noisy, np.arange(300) / 30, SmoothingConfig(True))
    before, after = _errors(noisy, truth), _errors(smoothed, truth)
    assert after[0] < 0.5 * before[0] and after[1] < 0.5 * before[1]
    assert report.position.noise == pytest.approx(0.003, rel=0.25)
    assert report.as_dict()["rotation_noise_deg"] == pytest.approx(0.2, rel=0.25)
    np.testing.assert_allclose(smoothed[:, 3], truth[:, 3])  # still rigid transforms
    np.testing.assert_allclose(np.linalg.det(smoothed[:, :3, :3]), 1.0, atol=1e-12)


def test_a_clean_trajectory_is_left_as_it_is():
    truth = _spinning_trajectory(120, 1 / 30)
    smoothed, _ = smooth_trajectory(truth, np.arange(120) / 30, SmoothingConfig(True))
    position, rotation = _errors(smoothed, truth)
    assert position < 1e-4 and rotation < 1e-4


@pytest.mark.parametrize("n", [1, 2])
def test_too_short_a_trajectory_is_returned_unchanged(n):
    poses = _spinning_trajectory(5, 0.1)[:n]
    smoothed, _ = smooth_trajectory(poses, np.arange(n) * 0.1, SmoothingConfig(True))
    np.testing.assert_array_equal(smoothed, poses)
