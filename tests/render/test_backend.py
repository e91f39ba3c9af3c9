"""The numba backend against the dense float64 oracle: forward, every gradient, edge cases,
determinism and dtype discipline (docs/method.md §1-2, §10)."""

import re

import numba
import numpy as np
import pytest
import torch

from bgs_batch.render import (
    Camera,
    Gaussians,
    project,
    rasterize,
    render,
    se3_exp,
    shape_matrices,
)
from bgs_batch.render import _numba_project as npj
from bgs_batch.render import _numba_raster as nr
from bgs_batch.render.constants import T_MIN
from bgs_batch.render.rasterize import depth_order
from bgs_batch.render.reference import quat_wxyz_to_matrix
from bgs_batch.render.testing import (
    max_rel_error,
    random_gaussians,
    random_screen_gaussians,
    random_vjp,
    room_gaussians,
)

TOL = {torch.float64: 1e-9, torch.float32: 1e-4}
"""Maximum relative error (max-norm) against the float64 reference, per dtype."""
WIDTH, HEIGHT = 61, 45
"""Image size of the random scenes (deliberately not multiples of the tile size)."""
DOUBLE_ARITHMETIC = re.compile(r"\bfpext\b|\b(fadd|fsub|fmul|fdiv|fcmp \w+) double")
CAMERA = Camera(fx=50.0, fy=48.0, cx=30.2, cy=21.7, width=WIDTH, height=HEIGHT)


def _requires_grad(tensors):
    return [t.detach().clone().requires_grad_() for t in tensors]


def _random_slopes(n, seed, dtype=torch.float64):
    """Depth slopes of up to 5 cm per pixel either way (a surface at a steep slant)."""
    gen = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 2, generator=gen, dtype=torch.float64) * 0.1 - 0.05).to(dtype)


def _compare_rasterize(inputs, dtype, *, full_grad=True, seed=0, width=WIDTH, height=HEIGHT):
    """Assert numba(dtype) == reference(float64 copy of the same inputs), outputs and VJPs.

    ``inputs``: rasterize's six tensors, or seven with the depth slopes last."""
    fast_in = _requires_grad(t.to(dtype) for t in inputs)
    ref_in = _requires_grad(t.to(dtype).double() for t in inputs)
    fast = rasterize(*fast_in[:6], width, height, full_grad=full_grad,
                     depth_slopes=fast_in[6] if len(inputs) > 6 else None)  # fmt: skip
    ref = rasterize(*ref_in[:6], width, height, full_grad=full_grad, backend="torch",
                    depth_slopes=ref_in[6] if len(inputs) > 6 else None)  # fmt: skip
    for name, a, b in zip(fast._fields, fast, ref, strict=True):
        assert a.dtype == dtype, name
        assert max_rel_error(a, b) <= TOL[dtype], name
    grads_fast = random_vjp(fast, fast_in, seed=seed)
    grads_ref = random_vjp(ref, ref_in, seed=seed)
    for i, (a, b) in enumerate(zip(grads_fast, grads_ref, strict=True)):
        assert a.dtype == dtype, i
        assert max_rel_error(a, b) <= TOL[dtype], i
    return fast, grads_fast


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("full_grad", [True, False])
def test_rasterize_matches_reference(dtype, full_grad):
    for seed in range(3):
        inputs = random_screen_gaussians(250, WIDTH, HEIGHT, seed=seed)
        _compare_rasterize(inputs, dtype, full_grad=full_grad, seed=seed)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("full_grad", [True, False])
def test_rasterize_with_depth_slopes_matches_reference(dtype, full_grad):
    """Each Gaussian's depth a plane across the screen: the depth, its variance and every
    gradient (the slopes' own, and the means' through ``p − μ``) as the oracle's."""
    for seed in range(2):
        inputs = (*random_screen_gaussians(250, WIDTH, HEIGHT, seed=seed),
                  _random_slopes(250, seed))  # fmt: skip
        out, grads = _compare_rasterize(inputs, dtype, full_grad=full_grad, seed=seed)
        assert grads[6].abs().max() > 0
        flat = rasterize(*(t.to(dtype) for t in inputs[:6]), WIDTH, HEIGHT)
        assert max_rel_error(out.depth, flat.depth) > 1e-3  # the planes change the depth …
        assert torch.equal(out.color, flat.color)  # … and nothing else


def test_full_and_authors_gradients_differ_only_through_transmittance():
    inputs = _requires_grad(random_screen_gaussians(150, WIDTH, HEIGHT, seed=7))
    full = random_vjp(rasterize(*inputs, WIDTH, HEIGHT, full_grad=True), inputs, seed=1)
    authors = random_vjp(rasterize(*inputs, WIDTH, HEIGHT, full_grad=False), inputs, seed=1)
    # T_i² depends on the alphas in front (opacity, mean, conic), not on colours, depths or v_i.
    for i in (0, 1, 3):
        assert max_rel_error(authors[i], full[i]) > 1e-3
    for i in (2, 4, 5):
        assert max_rel_error(authors[i], full[i]) == 0.0


def _project_both(gaussians: Gaussians, dtype, camera=CAMERA):
    """Project with both backends from a left-perturbed pose; returns outputs and VJPs."""
    results = []
    for backend, cast in (("numba", dtype), ("torch", torch.float64)):
        params = _requires_grad(t.to(dtype).to(cast) for t in vars(gaussians).values())
        xi = torch.zeros(6, dtype=cast, requires_grad=True)
        base = torch.eye(4, dtype=cast)
        base[:3, 3] = torch.tensor([0.1, -0.05, 0.2], dtype=cast)
        proj = project(*params[:4], se3_exp(xi) @ base, camera, backend=backend)
        grads = random_vjp(proj[:4], [*params[:3], xi], seed=3)
        results.append((proj, grads))
    return results


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_project_matches_reference(dtype):
    (fast, g_fast), (ref, g_ref) = _project_both(random_gaussians(300, seed=1), dtype)
    assert torch.equal(fast.ids, ref.ids) and len(ref.ids) > 200
    for a, b in zip(fast[:4], ref[:4], strict=True):
        assert a.dtype == dtype and max_rel_error(a, b) <= TOL[dtype]
    for a, b in zip(g_fast, g_ref, strict=True):
        assert a.dtype == dtype and max_rel_error(a, b) <= TOL[dtype]


def _render_vjp(gaussians, backend, full_grad, camera=CAMERA):
    params = _requires_grad(vars(gaussians).values())
    xi = torch.zeros(6, dtype=params[0].dtype, requires_grad=True)
    out = render(Gaussians(*params), se3_exp(xi), camera, full_grad=full_grad, backend=backend)
    return out, random_vjp(out, [*params, xi], seed=5)


@pytest.mark.parametrize("full_grad", [True, False])
def test_render_matches_reference_including_pose(full_grad):
    gaussians = random_gaussians(200, seed=2)
    fast, g_fast = _render_vjp(gaussians, "numba", full_grad)
    ref, g_ref = _render_vjp(gaussians, "torch", full_grad)
    for a, b in zip(fast, ref, strict=True):
        assert max_rel_error(a, b) <= TOL[torch.float64]
    for a, b in zip(g_fast, g_ref, strict=True):
        assert max_rel_error(a, b) <= TOL[torch.float64]
    assert g_fast[-1].abs().min() > 0  # every pose component gets a gradient


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("full_grad", [True, False])
def test_pose_only_gradient_equals_full_path(dtype, full_grad):
    """Tracking (no Gaussian tensor requires grad) skips the appearance gradients; the pose
    gradient must be bitwise the one of the full path."""
    g = Gaussians(*(t.to(dtype) for t in vars(random_gaussians(200, seed=8)).values()))
    pose, images = [], []
    for gaussians_grad, precomputed in ((True, False), (False, False), (False, True)):
        params = [t.clone().requires_grad_(gaussians_grad) for t in vars(g).values()]
        shapes = shape_matrices(g.log_scales, g.quats) if precomputed else None
        xi = torch.zeros(6, dtype=dtype, requires_grad=True)
        out = render(Gaussians(*params), se3_exp(xi), CAMERA, full_grad=full_grad,
                     shapes=shapes)  # fmt: skip
        pose.append(random_vjp(out, [xi], seed=2)[0])
        images.append(out)
    assert pose[0].abs().min() > 0
    assert torch.equal(pose[0], pose[1]) and torch.equal(pose[0], pose[2])
    for a, b in zip(images[0], images[2], strict=True):  # precomputed shapes: the same render
        assert torch.equal(a, b)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("full_grad", [True, False])
def test_variance_only_gradient_equals_full_path(dtype, full_grad):
    """The uncertainty refinement (only the r_i require grad) skips every other gradient; the
    r_i's gradient must be bitwise the one of the full path."""
    g = Gaussians(*(t.to(dtype) for t in vars(random_gaussians(200, seed=9)).values()))
    grads = []
    for others_grad in (True, False):
        params = {n: t.clone().requires_grad_(others_grad) for n, t in vars(g).items()}
        params["uncertainty_logits"].requires_grad_(True)
        out = render(Gaussians(**params), se3_exp(torch.zeros(6, dtype=dtype)), CAMERA,
                     full_grad=full_grad)  # fmt: skip
        grads.append(random_vjp(out, [params["uncertainty_logits"]], seed=3)[0])
    assert grads[0].abs().max() > 0
    assert torch.equal(grads[0], grads[1])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_shape_matrices_closed_form(dtype):
    g = random_gaussians(300, seed=4)
    shapes = shape_matrices(g.log_scales.to(dtype), g.quats.to(dtype))
    oracle = quat_wxyz_to_matrix(g.quats) * torch.exp(g.log_scales)[:, None, :]  # R·diag(e^s)
    assert shapes.dtype == dtype and max_rel_error(shapes, oracle) <= TOL[dtype]
    with pytest.raises(ValueError, match="shapes must be"):
        project(g.means, g.log_scales, g.quats, g.opacity_logits, torch.eye(4, dtype=g.means.dtype),
                CAMERA, shapes=shapes[:-1])  # fmt: skip


def test_gradcheck_rasterize():
    """Only the full gradient is the true derivative (the authors' one drops ∂T_i²/∂α_j).

    Fast mode checks random projections ``uᵀJv`` instead of all 2 520 output rows.
    """
    inputs = _requires_grad((*random_screen_gaussians(12, 20, 14, seed=4), _random_slopes(12, 4)))

    def fn(*args):
        return tuple(rasterize(*args[:6], 20, 14, depth_slopes=args[6]))

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_gradcheck_render_pose_and_gaussians():
    """Fast-mode gradcheck (random directions): the full Jacobian has 76 × 1 680 entries."""
    camera = Camera(fx=20.0, fy=20.0, cx=9.5, cy=6.5, width=20, height=14)
    g = random_gaussians(10, seed=6, half_width=0.8, scale=(0.08, 0.2))
    means, quats = g.means.clone().requires_grad_(), g.quats.clone().requires_grad_()
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)

    def fn(xi, means, quats):
        scene = Gaussians(
            means, g.log_scales, quats, g.opacity_logits, g.colors, g.uncertainty_logits
        )
        return tuple(render(scene, se3_exp(xi), camera))

    assert torch.autograd.gradcheck(
        fn, (xi, means, quats), eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True
    )


def _edge_scene(name: str) -> tuple[torch.Tensor, ...]:
    """Screen-space scenes that exercise one edge of the compositing rules each."""
    means2d, conics, depths, opac, colors, var = random_screen_gaussians(80, WIDTH, HEIGHT, seed=9)
    if name == "border":  # centres on and just outside the image border
        means2d[:40, 0] = torch.linspace(-3, WIDTH + 2, 40)
        means2d[40:, 1] = torch.linspace(-3, HEIGHT + 2, 40)
    elif name == "huge":  # σ of 40 px: every splat covers most of the image
        conics = conics * 0 + torch.tensor([1 / 1600, 0.0, 1 / 1600], dtype=conics.dtype)
        opac = opac * 0.3
    elif name == "subpixel":  # the low-pass floor: σ² = 0.3 px²
        conics = conics * 0 + torch.tensor([1 / 0.3, 0.0, 1 / 0.3], dtype=conics.dtype)
    elif name == "opaque":  # o > 0.99: clamped alphas, early termination everywhere
        opac = opac * 0 + 0.995
    elif name == "termination":  # stacks of wide, dense Gaussians drive T below 1e-4
        conics = conics / 9
        opac = opac * 0.2 + 0.75
    return means2d, conics, depths, opac, colors, var


@pytest.mark.parametrize("name", ["border", "huge", "subpixel", "opaque", "termination"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_edge_cases_match_reference(name, dtype):
    out, _ = _compare_rasterize(_edge_scene(name), dtype)
    assert (out.alpha >= 0).all() and (out.alpha <= 1).all()
    if name in ("opaque", "termination"):
        assert out.alpha.max() > 0.999  # the stop rule was reached …
        # … and T never fell below T_MIN (up to the rounding of 1 − T).
        assert out.alpha.max() <= 1 - T_MIN + torch.finfo(dtype).eps


@pytest.mark.parametrize("n", [0, 50])
def test_nothing_visible_gives_empty_images_and_zero_gradients(n):
    g = random_gaussians(n, seed=3)
    g.means[:, 2] *= -1  # all behind the camera
    params = _requires_grad(vars(g).values())
    out = render(Gaussians(*params), torch.eye(4, dtype=torch.float64), CAMERA)
    assert all((o == 0).all() for o in out)
    for grad in random_vjp(out, params, seed=0):
        assert grad is not None and (grad == 0).all()


def test_gaussians_behind_camera_are_culled():
    g = random_gaussians(120, seed=4)
    g.means[::2, 2] *= -1
    (fast, g_fast), (ref, g_ref) = _project_both(g, torch.float64)
    assert torch.equal(fast.ids, ref.ids)
    assert (fast.ids % 2 == 1).all() and len(fast.ids) > 50
    for a, b in zip(g_fast, g_ref, strict=True):
        assert max_rel_error(a, b) <= TOL[torch.float64]


def test_float32_variance_is_accurate_and_never_negative():
    """Depths ≈ 8 m with mm spread: the unshifted one-pass moments cancel here in float32."""
    means2d, conics, depths, opac, colors, var = random_screen_gaussians(
        600, WIDTH, HEIGHT, seed=11, opacity=(0.05, 0.3), variance=(0.5, 1.0)
    )
    depths = 8.0 + depths * 1e-3
    out, _ = _compare_rasterize((means2d, conics, depths, opac, colors, var), torch.float32)
    assert (out.var_depth >= 0).all() and (out.var_color >= 0).all()
    assert out.var_depth.max() > 0


def _room_step(seed: int):
    g = room_gaussians(20_000, seed=seed)
    camera = Camera(fx=131.25, fy=131.25, cx=79.5, cy=59.5, width=160, height=120)
    params = _requires_grad(vars(g).values())
    xi = torch.zeros(6, requires_grad=True)
    out = render(Gaussians(*params), se3_exp(xi), camera)
    return out, random_vjp(out, [*params, xi], seed=seed)


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs 2 numba threads")
def test_results_are_bitwise_identical_across_thread_counts():
    previous = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = _room_step(0)
        numba.set_num_threads(2)
        two = _room_step(0)
    finally:
        numba.set_num_threads(previous)
    assert one[0].alpha.max() > 0.5
    for a, b in zip((*one[0], *one[1]), (*two[0], *two[1]), strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_depth_order_is_the_stable_argsort(dtype):
    rng = np.random.default_rng(3)
    depths = rng.normal(2.0, 1.5, 5000).astype(dtype)  # both signs
    depths[::7] = depths[0]  # ties keep their index order
    depths[1::11] = np.finfo(dtype).tiny  # the smallest normal number
    depths[2::13] = np.float32(1e30)
    order = depth_order(depths)
    assert np.array_equal(order, np.argsort(depths, kind="stable"))
    for few in (depths[:0], depths[:1], depths[:2]):  # a view with nothing or little in it
        assert np.array_equal(depth_order(few), np.argsort(few, kind="stable"))


def test_rejects_bad_inputs():
    inputs = list(random_screen_gaussians(5, 8, 8, seed=0))
    with pytest.raises(ValueError, match="mixed dtypes"):
        rasterize(*inputs[:-1], inputs[-1].float(), 8, 8)
    with pytest.raises(ValueError, match="float32 or float64"):
        rasterize(*(t.half() for t in inputs), 8, 8)
    with pytest.raises(ValueError, match="positive definite"):
        rasterize(inputs[0], -inputs[1], *inputs[2:], 8, 8)
    with pytest.raises(ValueError, match="unknown backend"):
        rasterize(*inputs, 8, 8, backend="cuda")
    with pytest.raises(ValueError, match="depth_slopes must be"):
        rasterize(*inputs, 8, 8, depth_slopes=inputs[0][:-1])


@pytest.mark.slow
@pytest.mark.parametrize("kernel", [nr.raster_fwd, nr.raster_bwd, npj.project_bwd])
def test_float32_kernels_do_not_compute_in_double(kernel):
    """No float64 arithmetic in the float32 LLVM IR (numba promotes silently). Integer-to-text
    formatting in error paths uses doubles and is not arithmetic on data.

    Cached code cannot be inspected, so the serial twin of the kernel is compiled afresh.
    """
    _room_step(1)  # records the float32 signatures
    sig = next(s for s in kernel.signatures if s[0].dtype == numba.float32)
    twin = numba.njit(kernel.py_func)
    twin.compile(sig)
    ir = twin.inspect_llvm(sig)
    assert "fmul float" in ir and not DOUBLE_ARITHMETIC.search(ir)
