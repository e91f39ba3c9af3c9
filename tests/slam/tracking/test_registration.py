"""The warm start's dense RGB-D registration (bgs_batch/slam/tracking/registration.py)."""

import math

import numpy as np
import pytest
import torch

from bgs_batch.config import RegistrationConfig
from bgs_batch.render import Camera
from bgs_batch.slam.tracking import registration_kernels as kernels
from bgs_batch.slam.tracking.registration import View, _Problem, register
from converters.synthetic import RoomRenderer, SynthConfig, camera_poses

CONFIG = SynthConfig(width=160, height=120, seed=5, frames=30)


def _offset(degrees: float, metres: float) -> np.ndarray:
    """A rigid motion turning `degrees` about a skew axis and moving `metres` sideways-forward."""
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = math.radians(degrees)
    motion = np.eye(4)
    motion[:3, :3] = np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k
    motion[:3, 3] = metres * np.array([1.0, -0.5, 0.3]) / np.linalg.norm([1.0, -0.5, 0.3])
    return motion


def _view(renderer: RoomRenderer, c2w: np.ndarray, seed: int) -> View:
    rgb, depth, _ = renderer.render([c2w], c2w, np.random.default_rng(seed))
    fx, fy, cx, cy = CONFIG.intrinsics
    camera = Camera(fx, fy, cx, cy, CONFIG.width, CONFIG.height)
    metres = torch.from_numpy(depth.astype(np.float64) / CONFIG.depth_scale)
    return View.of(torch.from_numpy(rgb) / 255.0, metres, camera)


def _errors(estimate: torch.Tensor, truth: np.ndarray) -> tuple[float, float]:
    """(degrees, metres) between two rigid motions."""
    error = np.linalg.inv(truth) @ estimate.numpy()
    angle = math.degrees(math.acos(np.clip((np.trace(error[:3, :3]) - 1) / 2, -1, 1)))
    return angle, float(np.linalg.norm(error[:3, 3]))


@pytest.fixture(scope="module")
def renderer() -> RoomRenderer:
    return RoomRenderer(CONFIG)


@pytest.mark.parametrize("frame", [3, 17])
def test_a_known_3_degree_3_cm_offset_is_recovered(renderer, frame):
    target_c2w = camera_poses(CONFIG)[frame]
    offset = _offset(3.0, 0.03)  # source camera → target camera
    source = _view(renderer, target_c2w @ offset, seed=1)
    target = _view(renderer, target_c2w, seed=2)  # other sensor noise, holes
    result = register(source, target, RegistrationConfig())
    degrees, metres = _errors(result.transform, offset)
    assert degrees < 0.1 and metres < 1e-3, (degrees, metres)
    assert result.fitness > 0.8 and result.rmse < 0.02
    start = _errors(torch.eye(4, dtype=torch.float64), offset)
    assert start[0] > 2.9 and start[1] > 0.029  # the test starts where it says


def test_without_the_photometric_term_the_colour_cannot_move_the_result(renderer):
    c2w = camera_poses(CONFIG)[8]
    offset = _offset(2.0, 0.02)
    source, target = _view(renderer, c2w @ offset, 1), _view(renderer, c2w, 2)
    noise = torch.from_numpy(np.random.default_rng(0).random(source.gray.shape))
    scrambled = View(noise, source.depth, source.camera)
    geometric = register(source, target, RegistrationConfig(), photometric=False)
    assert torch.equal(register(scrambled, target, RegistrationConfig(),
                                photometric=False).transform, geometric.transform)  # fmt: skip
    assert not torch.equal(register(scrambled, target, RegistrationConfig()).transform,
                           register(source, target, RegistrationConfig()).transform)  # fmt: skip
    degrees, metres = _errors(geometric.transform, offset)
    assert degrees < 0.2 and metres < 2e-3, (degrees, metres)


def test_the_same_input_gives_the_same_transform(renderer):
    c2w = camera_poses(CONFIG)[8]
    source, target = _view(renderer, c2w @ _offset(2.0, 0.02), 1), _view(renderer, c2w, 2)
    first = register(source, target, RegistrationConfig())
    again = register(source, target, RegistrationConfig())
    assert torch.equal(first.transform, again.transform) and first.fitness == again.fitness


def test_no_overlap_gives_no_fitness(renderer):
    c2w = camera_poses(CONFIG)[8]
    source = _view(renderer, c2w, 1)
    empty = View(source.gray, torch.zeros_like(source.depth), source.camera)
    result = register(source, empty, RegistrationConfig())
    assert result.fitness == 0.0
    assert torch.equal(result.transform, torch.eye(4, dtype=torch.float64))


@pytest.mark.parametrize("term", ["geometric", "photometric"])
def test_kernel_jacobians_match_finite_differences(renderer, term):
    """Each residual's Jacobian row (ρ, φ) equals central differences of the residual under
    x → x + ε e_k (ρ) and x → x + ε e_k × x (φ), for points whose association does not change."""
    c2w = camera_poses(CONFIG)[5]
    source = _view(renderer, c2w, seed=1)
    target = _view(renderer, c2w @ _offset(1.0, 0.01), seed=2)
    problem = _Problem(source, target, RegistrationConfig())
    surface, normals, has_depth, gray, gradient, camera, height, width, max_distance = (
        problem.target
    )
    points, intensities = problem.points, problem.intensities

    def residual(x: np.ndarray, i: int, jac: np.ndarray) -> tuple[bool, float]:
        if term == "geometric":
            return kernels.geometric_term(*x, surface, normals, has_depth, camera, height, width,
                                          max_distance, jac)  # fmt: skip
        return kernels.photometric_term(*x, intensities[i], gray, gradient, has_depth, camera,
                                        height, width, jac)  # fmt: skip

    eps, checked = 1e-7, 0
    jac, scratch = np.empty(6), np.empty(6)
    for i in range(0, len(points), 97):
        x = points[i]
        ok, _ = residual(x, i, jac)
        if not ok:
            continue
        moves = [np.eye(3)[k] for k in range(3)] + [np.cross(np.eye(3)[k], x) for k in range(3)]
        numeric = []
        for move in moves:
            (ok_plus, plus), (ok_minus, minus) = (residual(x + s * eps * move, i, scratch)
                                                  for s in (1, -1))  # fmt: skip
            numeric.append((plus - minus) / (2 * eps) if ok_plus and ok_minus else np.nan)
        if np.isnan(numeric).any() or np.abs(np.array(numeric) - jac).max() > 1e-3 * (
            1 + np.abs(jac).max()
        ):
            continue  # the association changed within ε (a pixel or cell boundary)
        checked += 1
    assert checked > 0.9 * sum(residual(points[i], i, jac)[0] for i in range(0, len(points), 97))



def _oracle_normal_equations(problem: _Problem, transform: np.ndarray, scales: tuple[float, float],
                             huber_k: float) -> tuple[np.ndarray, np.ndarray, int]:  # fmt: skip
    """``Jᵀ W J``, ``Jᵀ W r`` and the residual count from the kernels' per-point terms, summed
    by numpy: the oracle of `normal_equations`' chunked sums."""
    surface, normals, has_depth, gray, gradient, camera, height, width, max_distance = (
        problem.target
    )
    rows, residuals = [], []
    for p, intensity in zip(problem.points, problem.intensities, strict=True):
        x = transform[:3, :3] @ p + transform[:3, 3]
        geometric, photometric = np.empty(6), np.empty(6)
        terms = (
            (kernels.geometric_term(*x, surface, normals, has_depth, camera, height, width,
                                    max_distance, geometric), geometric, scales[0]),
            (kernels.photometric_term(*x, intensity, gray, gradient, has_depth, camera, height,
                                      width, photometric), photometric, scales[1]),
        )  # fmt: skip
        for (ok, r), jac, scale in terms:
            if ok:
                rows.append(jac / scale)
                residuals.append(r / scale)
    j, r = np.array(rows), np.array(residuals)
    weights = np.where(np.abs(r) <= huber_k, 1.0, huber_k / np.maximum(np.abs(r), 1e-30))
    return (j * weights[:, None]).T @ j, j.T @ (weights * r), len(r)


def test_normal_equations_match_a_numpy_oracle_on_any_thread_count(renderer):
    """The kernel's chunked sums equal numpy's over the same terms (float64), and give the same
    bits on one thread as on two."""
    import numba

    c2w = camera_poses(CONFIG)[8]
    source, target = _view(renderer, c2w @ _offset(2.0, 0.02), 1), _view(renderer, c2w, 2)
    problem = _Problem(source, target, RegistrationConfig())
    transform = _offset(1.0, 0.01)
    scales, huber_k = (0.004, 0.02), 1.345  # small scales: many residuals beyond Huber's knee
    arguments = (problem.points, problem.intensities, transform, *problem.target, *scales, huber_k)
    normal, rhs, used = kernels.normal_equations(*arguments)
    expected_normal, expected_rhs, expected_used = _oracle_normal_equations(
        problem, transform, scales, huber_k)  # fmt: skip
    assert used == expected_used > 1000
    np.testing.assert_allclose(normal, expected_normal, rtol=1e-10, atol=1e-10 * abs(normal).max())
    np.testing.assert_allclose(rhs, expected_rhs, rtol=1e-10, atol=1e-10 * abs(rhs).max())
    assert np.array_equal(normal, normal.T)
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        single = kernels.normal_equations(*arguments)
    finally:
        numba.set_num_threads(threads)
    assert np.array_equal(single[0], normal) and np.array_equal(single[1], rhs)
