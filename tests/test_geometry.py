import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from bgs_batch.geometry import (
    euler_zyx_deg,
    interpolate_poses,
    matrix_to_quat_xyzw,
    pose_matrix,
    quat_xyzw_to_matrix,
    rotation_angle_deg,
    slerp,
)

unit_quats = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 0.1
).map(lambda q: np.asarray(q) / np.linalg.norm(q))


def axis_angle(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([axis * np.sin(angle / 2), [np.cos(angle / 2)]])


@given(unit_quats)
@settings(max_examples=200, deadline=None)
def test_quaternion_round_trip(q):
    rot = quat_xyzw_to_matrix(q)
    assert np.allclose(rot @ rot.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(rot), 1.0)
    back = matrix_to_quat_xyzw(rot)
    assert back[3] >= 0
    assert np.allclose(back, q, atol=1e-9) or np.allclose(back, -q, atol=1e-9)


def test_quat_xyzw_to_matrix_closed_form():
    # 90 degrees about z maps x to y
    rot = quat_xyzw_to_matrix(axis_angle([0, 0, 1], np.pi / 2))
    assert np.allclose(rot @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(matrix_to_quat_xyzw(np.eye(3)), [0, 0, 0, 1])
    # 180 degrees: the numerically delicate case
    half_turn = quat_xyzw_to_matrix([1.0, 0, 0, 0])
    assert np.allclose(np.abs(matrix_to_quat_xyzw(half_turn)), [1, 0, 0, 0])


def test_slerp_constant_rate_and_short_way():
    q0, q1 = axis_angle([0, 1, 0], 0.2), axis_angle([0, 1, 0], 1.0)
    assert np.allclose(slerp(q0, q1, 0.25), axis_angle([0, 1, 0], 0.4))
    # -q1 is the same rotation; slerp must still take the short way
    assert np.allclose(slerp(q0, -q1, 0.25), axis_angle([0, 1, 0], 0.4))
    assert np.allclose(slerp(q0, q0, 0.7), q0)


def test_interpolate_poses_linear_slerp_and_gaps():
    times = np.array([0.0, 0.1, 0.5])
    trans = np.array([[0, 0, 0], [1.0, 2, 3], [5, 5, 5]])
    quats = np.stack([axis_angle([0, 0, 1], a) for a in (0.0, 0.4, 0.5)])
    out = interpolate_poses(times, trans, quats, np.array([0.025, 0.1, 0.3, -1.0, 0.6]), 0.1)
    assert np.allclose(out[0], pose_matrix([0.25, 0.5, 0.75], axis_angle([0, 0, 1], 0.1)))
    assert np.allclose(out[1], pose_matrix(trans[1], quats[1]))  # exactly on a sample
    assert np.isnan(out[2]).all()  # bracket 0.1..0.5 is wider than 0.1 s
    assert np.isnan(out[3]).all() and np.isnan(out[4]).all()  # outside the samples


@pytest.mark.parametrize("n", [0, 1])
def test_interpolate_poses_few_samples(n):
    out = interpolate_poses(np.zeros(n), np.zeros((n, 3)), np.tile([0, 0, 0, 1.0], (n, 1)),
                            np.array([0.0, 1.0]), 0.1)  # fmt: skip
    assert np.isnan(out[1]).all()
    assert np.isnan(out[0]).all() == (n == 0)


@given(unit_quats)
@settings(max_examples=200, deadline=None)
def test_rotation_angle_and_euler_against_scipy(q):
    rot = quat_xyzw_to_matrix(q)
    reference = Rotation.from_quat(q)
    assert rotation_angle_deg(rot) == pytest.approx(np.degrees(reference.magnitude()), abs=1e-5)
    yaw, pitch, roll = reference.as_euler("ZYX", degrees=True)  # intrinsic: R = Rz Ry Rx
    if abs(pitch) < 89:  # away from gimbal lock the decomposition is unique (up to ±180°)
        wrapped = (euler_zyx_deg(rot) - [roll, pitch, yaw] + 180) % 360 - 180
        assert np.allclose(wrapped, 0, atol=1e-6)


def test_euler_at_gimbal_lock_rebuilds_the_rotation():
    rot = Rotation.from_euler("ZYX", [30, 90, 20], degrees=True).as_matrix()
    roll, pitch, yaw = euler_zyx_deg(rot)
    assert pitch == pytest.approx(90) and yaw == 0
    rebuilt = Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True).as_matrix()
    assert np.allclose(rebuilt, rot, atol=1e-9)
