"""The fused loss kernels against float64 autograd of the plain PyTorch formulas."""

import pytest
import torch
import torch.nn.functional as F

from bgs_batch.slam.blur import gaussian_window
from bgs_batch.slam.loss_kernels import fused_ssim, l1_nll_terms, weighted_normalised_l1
from bgs_batch.slam.losses import SSIM_C1, SSIM_C2, SSIM_SIGMA, SSIM_WINDOW


def scene(dtype, h=13, w=17, seed=0):
    """Render-like inputs (requiring grad) and targets with invalid-depth pixels."""
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=torch.float64)

    render = {
        "color": rand(h, w, 3),
        "depth": rand(h, w, 1) + 0.5,
        "alpha": rand(h, w, 1) * 0.9 + 0.05,
        "var_c": rand(h, w, 3) * 0.1 + 1e-3,
        "var_d": rand(h, w, 1) * 0.1 + 1e-3,
    }
    target_c, target_d = rand(h, w, 3), rand(h, w, 1) + 0.5
    target_d[rand(h, w, 1) < 0.3] = 0
    render = {k: v.to(dtype).requires_grad_() for k, v in render.items()}
    return render, target_c.to(dtype), target_d.to(dtype)


def l1_nll_oracle(color, depth, target_c, target_d, var_c, var_d):
    mask = target_d > 0
    mask_c = mask.expand_as(color)
    r_c, r_d = color - target_c, depth - target_d
    return torch.stack([
        r_c.abs()[mask_c].mean(),
        r_d.abs()[mask].mean(),
        (0.5 * (r_c**2 / var_c + var_c.log()))[mask_c].mean(),
        (0.5 * (r_d**2 / var_d + var_d.log()))[mask].mean(),
    ])  # fmt: skip


def tracking_oracle(color, depth, alpha, target_c, target_d, var_c, var_d, weights):
    weight = (target_d > 0) * alpha**3
    err_c = ((color - target_c).abs() / var_c.sqrt() * weight).sum()
    err_d = ((depth - target_d).abs() / var_d.sqrt() * weight).sum()
    return weights[0] * err_c + weights[1] * err_d


def ssim_oracle(a, b):
    """conv2d SSIM with the 2-D window, channels-last inputs."""
    taps = gaussian_window(SSIM_WINDOW, SSIM_SIGMA, a.dtype)
    channels = a.shape[-1]
    window = torch.outer(taps, taps).expand(channels, 1, -1, -1)

    def blur(x):
        return F.conv2d(x, window, padding=SSIM_WINDOW // 2, groups=channels)

    a, b = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2
    cov = blur(a * b) - mu_a * mu_b
    num = (2 * mu_a * mu_b + SSIM_C1) * (2 * cov + SSIM_C2)
    return (num / ((mu_a**2 + mu_b**2 + SSIM_C1) * (var_a + var_b + SSIM_C2))).mean()


def gradients(value, inputs):
    return torch.autograd.grad(value, inputs, retain_graph=True)


@pytest.mark.parametrize(("dtype", "tol"), [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_l1_nll_terms_values_and_gradients(dtype, tol):
    r, target_c, target_d = scene(dtype)
    args = (r["color"], r["depth"], target_c, target_d, r["var_c"], r["var_d"])
    upstream = torch.tensor([0.8, 1.0, 1e-3, 2e-3], dtype=dtype)
    fused = l1_nll_terms(*args)
    oracle = l1_nll_oracle(*(a.double() for a in args))
    torch.testing.assert_close(fused.double(), oracle, rtol=tol, atol=tol)
    inputs = [r[k] for k in ("color", "depth", "var_c", "var_d")]
    got_all = gradients((fused * upstream).sum(), inputs)
    want_all = gradients((oracle * upstream.double()).sum(), inputs)
    for got, want in zip(got_all, want_all, strict=True):
        torch.testing.assert_close(got.double(), want.double(), rtol=tol, atol=tol)


def test_l1_nll_terms_gradcheck():
    r, target_c, target_d = scene(torch.float64, 5, 4, seed=1)
    assert torch.autograd.gradcheck(
        lambda c, d, vc, vd: l1_nll_terms(c, d, target_c, target_d, vc, vd),
        (r["color"], r["depth"], r["var_c"], r["var_d"]),
    )


@pytest.mark.parametrize(("dtype", "tol"), [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_weighted_normalised_l1_values_and_gradients(dtype, tol):
    r, target_c, target_d = scene(dtype)
    weights = (900.0, 0.4 / 30)
    args = (r["color"], r["depth"], r["alpha"], target_c, target_d, r["var_c"], r["var_d"])
    fused = weighted_normalised_l1(*args, weights)
    oracle = tracking_oracle(*(a.double() for a in args), weights)
    torch.testing.assert_close(fused.double(), oracle, rtol=tol, atol=0)
    inputs = [r[k] for k in ("color", "depth", "alpha", "var_c", "var_d")]
    for got, want in zip(gradients(fused, inputs), gradients(oracle, inputs), strict=True):
        torch.testing.assert_close(got.double(), want.double(), rtol=tol, atol=tol * 900)


def test_weighted_normalised_l1_gradcheck():
    r, target_c, target_d = scene(torch.float64, 5, 4, seed=2)
    assert torch.autograd.gradcheck(
        lambda c, d, a, vc, vd: weighted_normalised_l1(c, d, a, target_c, target_d, vc, vd,
                                                       (0.6, 0.4)),  # fmt: skip
        (r["color"], r["depth"], r["alpha"], r["var_c"], r["var_d"]),
    )


@pytest.mark.parametrize(("dtype", "tol"), [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_fused_ssim_value_and_gradient(dtype, tol):
    r, target_c, _ = scene(dtype, 21, 26)
    a = r["color"]
    taps = gaussian_window(SSIM_WINDOW, SSIM_SIGMA, torch.float64)
    fused = fused_ssim(a, target_c, taps, SSIM_C1, SSIM_C2)
    a64 = a.detach().double().requires_grad_()
    oracle = ssim_oracle(a64, target_c.double())
    torch.testing.assert_close(fused.double(), oracle.detach(), rtol=tol, atol=tol)
    (got,) = gradients(fused * 3.0, [a])
    (want,) = gradients(oracle * 3.0, [a64])
    torch.testing.assert_close(got.double(), want, rtol=tol, atol=tol * 1e-2)


def test_fused_ssim_gradcheck_and_identity():
    r, target_c, _ = scene(torch.float64, 7, 9, seed=3)
    taps = gaussian_window(SSIM_WINDOW, SSIM_SIGMA, torch.float64)
    assert torch.autograd.gradcheck(
        lambda a: fused_ssim(a, target_c, taps, SSIM_C1, SSIM_C2), (r["color"],)
    )
    same = fused_ssim(target_c, target_c, taps, SSIM_C1, SSIM_C2)
    assert float(same) == pytest.approx(1.0, abs=1e-12)
    with pytest.raises(ValueError, match="detach the target"):
        fused_ssim(target_c, r["color"], taps, SSIM_C1, SSIM_C2)


def test_kernels_do_not_depend_on_thread_count():
    import numba

    r, target_c, target_d = scene(torch.float32, 64, 48, seed=4)
    args = (r["color"], r["depth"], target_c, target_d, r["var_c"], r["var_d"])
    results = []
    for threads in (1, min(2, numba.config.NUMBA_NUM_THREADS)):
        numba.set_num_threads(threads)
        terms = l1_nll_terms(*args)
        results.append((terms, *gradients(terms.sum(), [r["color"], r["var_d"]])))
    for a, b in zip(*results, strict=True):
        assert torch.equal(a, b)
