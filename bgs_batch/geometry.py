"""Rigid-body helpers: quaternions (x, y, z, w as in TUM files), rotations, pose interpolation.

Vectorised over leading dimensions; float64 throughout.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from scipy.spatial import cKDTree


def kd_tree(points: np.ndarray) -> cKDTree:
    """scipy's KD-tree over `points` (n, d). scipy.spatial is imported here, on first use: it
    takes ~0.3 s and tracking a frame never needs it, so a resumed job starts sooner."""
    from scipy.spatial import cKDTree

    return cKDTree(points)


def quat_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from unit quaternions (..., 4) in (x, y, z, w) order."""
    x, y, z, w = np.moveaxis(np.asarray(q, np.float64), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quat_xyzw(rot: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4), (x, y, z, w) order, w ≥ 0, from rotation matrices (..., 3, 3).

    Bar-Itzhack's method: the quaternion is the dominant eigenvector of a symmetric 4x4 matrix
    built from the rotation; robust for every rotation and for slightly non-orthogonal input.
    """
    m = np.asarray(rot, np.float64)
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    k = np.stack(
        [
            np.stack([m00 - m11 - m22, m01 + m10, m02 + m20, m21 - m12], -1),
            np.stack([m01 + m10, m11 - m00 - m22, m12 + m21, m02 - m20], -1),
            np.stack([m02 + m20, m12 + m21, m22 - m00 - m11, m10 - m01], -1),
            np.stack([m21 - m12, m02 - m20, m10 - m01, m00 + m11 + m22], -1),
        ],
        -2,
    ) / 3.0
    q = np.linalg.eigh(k)[1][..., -1]  # eigenvector of the largest eigenvalue
    return q * np.where(q[..., 3:4] < 0, -1.0, 1.0)


GIMBAL_LOCK = 1e-6  # cos(pitch) below this: roll and yaw turn about the same axis


def rotation_angle_deg(rotation: np.ndarray) -> float:
    """Angle (degrees) of a 3×3 rotation matrix."""
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1.0, 1.0))))


def euler_zyx_deg(rotation: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) in degrees with ``R = R_z(yaw) R_y(pitch) R_x(roll)``; at gimbal lock
    (pitch ±90°) the shared angle goes to roll and yaw is 0."""
    r = rotation
    cos_pitch = np.hypot(r[0, 0], r[1, 0])
    pitch = np.arctan2(-r[2, 0], cos_pitch)
    if cos_pitch < GIMBAL_LOCK:
        return np.degrees([np.arctan2(-r[1, 2], r[1, 1]), pitch, 0.0])
    return np.degrees([np.arctan2(r[2, 1], r[2, 2]), pitch, np.arctan2(r[1, 0], r[0, 0])])


def pose_matrix(translation: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """Homogeneous transforms (..., 4, 4) from translations (..., 3) and quaternions (..., 4)."""
    translation = np.asarray(translation, np.float64)
    out = np.zeros(translation.shape[:-1] + (4, 4))
    out[..., :3, :3] = quat_xyzw_to_matrix(quat_xyzw)
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions (..., 4) at fractions t (...).

    Takes the short way round (flips q1 when the dot product is negative); falls back to
    normalised linear interpolation for nearly identical rotations.
    """
    q0, q1 = np.asarray(q0, np.float64), np.asarray(q1, np.float64)
    t = np.asarray(t, np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.clip(np.abs(dot), -1.0, 1.0)
    theta = np.arccos(dot)
    sin_theta = np.sin(theta)
    near = sin_theta < 1e-9
    safe = np.where(near, 1.0, sin_theta)
    w0 = np.where(near, 1 - t, np.sin((1 - t) * theta) / safe)
    w1 = np.where(near, t, np.sin(t * theta) / safe)
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def interpolate_poses(
    sample_times: np.ndarray,
    translations: np.ndarray,
    quats_xyzw: np.ndarray,
    query_times: np.ndarray,
    max_gap: float,
) -> np.ndarray:
    """Poses (M, 4, 4) at `query_times`: linear in position, slerp in rotation.

    A query gets a pose only when it lies between two samples at most `max_gap` seconds apart
    (or exactly on a sample); otherwise its matrix is all NaN. `sample_times` must increase.
    """
    sample_times = np.asarray(sample_times, np.float64)
    query_times = np.asarray(query_times, np.float64)
    out = np.full((len(query_times), 4, 4), np.nan)
    if len(sample_times) == 0:
        return out
    hi = np.searchsorted(sample_times, query_times, side="left")
    exact = (hi < len(sample_times)) & (sample_times[np.minimum(hi, len(sample_times) - 1)]
                                         == query_times)  # fmt: skip
    lo = hi - 1
    inside = (lo >= 0) & (hi < len(sample_times))
    lo_c, hi_c = np.clip(lo, 0, None), np.minimum(hi, len(sample_times) - 1)
    gap = sample_times[hi_c] - sample_times[lo_c]
    ok = inside & (gap <= max_gap)
    frac = np.where(ok, (query_times - sample_times[lo_c]) / np.where(gap > 0, gap, 1.0), 0.0)
    trans = translations[lo_c] + frac[:, None] * (translations[hi_c] - translations[lo_c])
    quat = slerp(quats_xyzw[lo_c], quats_xyzw[hi_c], frac)
    trans = np.where(exact[:, None], translations[hi_c], trans)
    quat = np.where(exact[:, None], quats_xyzw[hi_c], quat)
    valid = ok | exact
    out[valid] = pose_matrix(trans[valid], quat[valid])
    return out
