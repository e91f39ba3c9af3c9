"""Fixed-interval smoothing of the reported trajectory.

Frame-to-model tracking gives every frame a pose with its own small error, independent of its
neighbours', while a hand-held camera moves smoothly at 30 frames per second: the jitter makes
the estimated path far longer than the true one and dominates the frame-to-frame error. A batch
run has every frame's pose before it reports any, so it can estimate each pose from the frames
after it too, as an offline smoother does.

Each coordinate of the trajectory (the camera centre in the world; the rotation as the running
sum of the frame-to-frame rotation vectors) is modelled as a constant-velocity process driven
by white acceleration noise of spectral density q and measured with white noise of variance r.
The ratio q / r is not a setting: it is the maximum-likelihood value of the tracked trajectory
itself (the Kalman filter's innovations), searched on a logarithmic grid and shared by the
three coordinates of a group, so a steady tracker is left alone and a jittery one smoothed as
much as its own data supports. The Rauch-Tung-Striebel pass then gives each pose the posterior
mean given all frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from bgs_batch.config import SmoothingConfig

DIFFUSE = 1e6  # prior variance of the first velocity, in units of r: nothing is known of it


@dataclass(frozen=True)
class GroupFit:
    """The maximum-likelihood noise of one group of coordinates."""

    log10_ratio: float  # log10(q / r), q in units²/s³
    noise: float  # √r: the measured coordinates' noise (RMS over the group's coordinates)


@dataclass(frozen=True)
class SmoothingReport:
    position: GroupFit  # m
    rotation: GroupFit  # rad

    def as_dict(self) -> dict[str, float]:
        return {
            "position_log10_ratio": self.position.log10_ratio,
            "position_noise_m": self.position.noise,
            "rotation_log10_ratio": self.rotation.log10_ratio,
            "rotation_noise_deg": float(np.degrees(self.rotation.noise)),
        }


def _transition(dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Constant-velocity transition F and its process covariance Q per unit q over `dt` s."""
    f = np.array([[1.0, dt], [0.0, 1.0]])
    q = np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    return f, q


def _filter(z: np.ndarray, t: np.ndarray, ratios: np.ndarray, keep: bool = False):
    """Kalman filter of measurements `z` (n, c) at times `t` (n,) for each ratio q/r (g,), in
    units of r. Returns the innovations' sums (g, c) of e²/S and of log S from the third
    measurement on (the first two fix position and velocity), and with `keep` the filtered and
    predicted means and covariances for the backward pass."""
    n, c = z.shape
    x = np.zeros((len(ratios), c, 2))
    x[..., 0] = z[0]
    p = np.broadcast_to(np.diag([1.0, DIFFUSE]), (*x.shape, 2)).copy()
    weighted = np.zeros(x.shape[:2])
    log_s = np.zeros(x.shape[:2])
    history = [(x, p, None, None)] if keep else None
    q_scale = ratios[:, None, None, None]
    for k in range(1, n):
        f, q = _transition(float(t[k] - t[k - 1]))
        x_pred = x @ f.T
        p_pred = f @ p @ f.T + q_scale * q
        s = p_pred[..., 0, 0] + 1.0
        innovation = z[k] - x_pred[..., 0]
        gain = p_pred[..., :, 0] / s[..., None]
        x = x_pred + gain * innovation[..., None]
        p = p_pred - gain[..., :, None] * p_pred[..., 0, None, :]
        if k >= 2:
            weighted += innovation**2 / s
            log_s += np.log(s)
        if keep:
            history.append((x, p, x_pred, p_pred))
    return weighted, log_s, history


def smooth_coordinates(z: np.ndarray, t: np.ndarray, cfg: SmoothingConfig
                       ) -> tuple[np.ndarray, GroupFit]:  # fmt: skip
    """Posterior means (n, c) of the coordinates `z` (n ≥ 3, c) measured at times `t` (s), with
    the maximum-likelihood ratio q/r shared by the c coordinates (each with its own scale)."""
    n = len(z)
    grid = np.arange(cfg.log_ratio_min, cfg.log_ratio_max + cfg.log_ratio_step / 2,
                     cfg.log_ratio_step)  # fmt: skip
    weighted, log_s, _ = _filter(z, t, 10.0**grid)
    m = n - 2  # innovations in the likelihood
    scale = np.maximum(weighted / m, np.finfo(float).tiny)  # ML r per ratio and coordinate
    log_likelihood = -0.5 * (log_s + m * np.log(scale)).sum(axis=1)
    best = int(np.argmax(log_likelihood))
    _, _, history = _filter(z, t, 10.0 ** grid[best : best + 1], keep=True)
    x, p = history[-1][:2]
    out = np.empty_like(z)
    out[-1] = x[0, :, 0]
    for k in range(n - 2, -1, -1):  # Rauch-Tung-Striebel
        x_filt, p_filt = history[k][:2]
        x_pred, p_pred = history[k + 1][2:]
        f, _ = _transition(float(t[k + 1] - t[k]))
        gain = p_filt @ f.T @ np.linalg.inv(p_pred)
        x = x_filt + (gain @ (x - x_pred)[..., None])[..., 0]
        out[k] = x[0, :, 0]
    noise = float(np.sqrt(scale[best].mean()))
    return out, GroupFit(float(grid[best]), noise)


def smooth_trajectory(c2w: np.ndarray, timestamps: np.ndarray, cfg: SmoothingConfig
                      ) -> tuple[np.ndarray, SmoothingReport | None]:  # fmt: skip
    """The camera-to-world poses (N, 4, 4) smoothed: camera centres directly; rotations through
    the running sum θ of the body-frame rotation vectors between consecutive frames, each pose
    turned by its own correction exp(θ̃ − θ) (small, so the sum's path dependence cancels).
    The report is None for fewer than three poses, which are returned as they are."""
    out = c2w.copy()
    if len(c2w) < 3:  # nothing to estimate a noise from
        return out, None
    t = np.asarray(timestamps, dtype=np.float64) - float(timestamps[0])
    out[:, :3, 3], position = smooth_coordinates(c2w[:, :3, 3], t, cfg)
    rotations = Rotation.from_matrix(c2w[:, :3, :3])
    steps = (rotations[:-1].inv() * rotations[1:]).as_rotvec()
    theta = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])
    smoothed, rotation = smooth_coordinates(theta, t, cfg)
    out[:, :3, :3] = (rotations * Rotation.from_rotvec(smoothed - theta)).as_matrix()
    return out, SmoothingReport(position, rotation)
