"""Closed-form and oracle checks of the method's losses, scores and small networks."""

import math

import numpy as np
import pytest
import torch

from bgs_batch.config import KeyframeConfig, TrackingConfig, UncertaintyConfig
from bgs_batch.slam.keyframes import KeyframeSelector
from bgs_batch.slam.loss_kernels import l1_nll_terms
from bgs_batch.slam.losses import (
    isotropy_loss,
    mapping_loss,
    predictive_variance,
    ssim,
    surprise_scores,
    tracking_loss,
)


def test_predictive_variance_floors_and_unobserved_fill():
    cfg = UncertaintyConfig()
    rendered = torch.tensor([[[0.5], [0.5]]], requires_grad=True)
    alpha = torch.tensor([[[0.9], [0.3]]])
    sensor = torch.tensor([[[0.2], [0.2]]])
    total = predictive_variance(rendered, sensor, alpha, cfg)
    assert torch.allclose(total, torch.tensor([[[0.2 + 0.5 + 1e-3], [0.2 + 100.0]]]))
    total.sum().backward()
    assert rendered.grad.flatten().tolist() == [1.0, 0.0]  # no gradient where unobserved


def ssim_oracle(a, b):
    """Direct per-pixel SSIM (11x11 Gaussian, sigma 1.5, zero padding), float64 loops."""
    h, w, c = a.shape
    x = np.arange(11) - 5
    g = np.exp(-(x**2) / 4.5)
    win = np.outer(g, g) / g.sum() ** 2
    pa, pb = np.pad(a, ((5, 5), (5, 5), (0, 0))), np.pad(b, ((5, 5), (5, 5), (0, 0)))
    total = 0.0
    for i in range(h):
        for j in range(w):
            for k in range(c):
                wa, wb = pa[i:i + 11, j:j + 11, k], pb[i:i + 11, j:j + 11, k]
                ma, mb = (win * wa).sum(), (win * wb).sum()
                va, vb = (win * wa * wa).sum() - ma**2, (win * wb * wb).sum() - mb**2
                cov = (win * wa * wb).sum() - ma * mb
                total += ((2 * ma * mb + 1e-4) * (2 * cov + 9e-4)
                          / ((ma**2 + mb**2 + 1e-4) * (va + vb + 9e-4)))  # fmt: skip
    return total / (h * w * c)


def test_ssim_against_direct_oracle():
    rng = np.random.default_rng(0)
    a = rng.uniform(size=(9, 13, 3))
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
    assert float(ssim(torch.tensor(a), torch.tensor(b))) == pytest.approx(ssim_oracle(a, b), 1e-12)
    assert float(ssim(torch.tensor(a), torch.tensor(a))) == pytest.approx(1.0, abs=1e-12)


def test_nll_terms_closed_form_and_mask():
    depth = torch.tensor([[[2.0], [7.0]]], dtype=torch.float64)
    target_d = torch.tensor([[[1.0], [0.0]]], dtype=torch.float64)  # second pixel: invalid
    var_d = torch.tensor([[[math.e], [1.0]]], dtype=torch.float64)
    color = torch.zeros(1, 2, 3, dtype=torch.float64)
    terms = l1_nll_terms(color, depth, color, target_d, torch.ones_like(color), var_d)
    assert terms.tolist() == pytest.approx([0.0, 1.0, 0.0, 0.5 / math.e + 0.5])
    none_valid = l1_nll_terms(color, depth, color, target_d * 0, torch.ones_like(color), var_d)
    assert none_valid.tolist() == [0.0, 0.0, 0.0, 0.0]


def test_isotropy_zero_for_spheres():
    assert float(isotropy_loss(torch.log(torch.full((4, 3), 0.2)))) == pytest.approx(0, abs=1e-12)
    assert float(isotropy_loss(torch.log(torch.tensor([[1.0, 2.0, 3.0]])))) == pytest.approx(2 / 3)


def images(h=6, w=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=torch.float64)

    return rand(h, w, 3), rand(h, w, 1) + 0.5, rand(h, w, 1)


def test_tracking_loss_forms_closed_form():
    color, depth, _ = images()
    target_c, target_d = color + 0.1, depth - 0.2
    target_d[0, 0] = 0  # invalid depth pixel: excluded
    alpha = torch.full_like(depth, 0.5)
    var_c, var_d = torch.full_like(color, 4.0), torch.full_like(depth, 0.25)
    valid = 29
    err_c = valid * 3 * 0.1 / 2 * 0.125  # |r| / sqrt(var) * alpha^3
    err_d = valid * 0.2 / 0.5 * 0.125
    paper = tracking_loss(color, depth, alpha, target_c, target_d, var_c, var_d, TrackingConfig())
    assert float(paper) == pytest.approx(900 * err_c + 900 * err_d)
    authors = tracking_loss(color, depth, alpha, target_c, target_d, var_c, var_d,
                            TrackingConfig(loss_form="authors"))  # fmt: skip
    assert float(authors) == pytest.approx(0.6 * err_c / 30 + 0.4 * err_d / 30)


def test_surprise_scores_closed_form():
    color, depth, _ = images()
    var_c, var_d = torch.full_like(color, 2.0), torch.full_like(depth, 0.5)
    s_c, s_d = surprise_scores(color, depth, color + 1, depth, var_c, var_d)
    n = 30
    assert s_c == pytest.approx(n * 3 * 0.5 * (1 / 2 + math.log(2)))
    assert s_d == pytest.approx(n * 0.5 * math.log(0.5))  # perfect depth: only the log term
    assert s_d < 0  # well explained by a confident prediction: not surprising


def test_mapping_loss_parts_and_gradients():
    color, depth, _ = images()
    color.requires_grad_(True)
    log_scales = torch.zeros(3, 3, dtype=torch.float64)
    target_c, target_d = color.detach() * 0.5, depth + 0.1
    var_c, var_d = torch.ones_like(color), torch.ones_like(depth)
    terms = mapping_loss(color, depth, target_c, target_d, var_c, var_d, log_scales, 1e-3, 0.2)
    l1 = float((color.detach() - target_c).abs().mean())
    expected_color = 0.8 * l1 + 0.2 * (1 - float(ssim(color.detach(), target_c)))
    assert float(terms.color.detach()) == pytest.approx(expected_color)
    assert float(terms.depth.detach()) == pytest.approx(0.1) and float(terms.isotropy) == 0
    assert float(terms.nll_depth.detach()) == pytest.approx(0.5 * 0.01)
    assert float(terms.total.detach()) == pytest.approx(
        float(terms.color + terms.depth + 1e-3 * (terms.nll_color + terms.nll_depth)))
    terms.total.backward()
    assert color.grad.abs().sum() > 0


def test_keyframe_rule():
    sel = KeyframeSelector(KeyframeConfig())
    decisions = [sel.decide(0, None, None, True)]
    decisions += [sel.decide(i, -5.0, -5.0, False) for i in range(1, 7)]
    decisions += [sel.decide(7, 3.0, -1.0, False), sel.decide(8, -1.0, 0.5, False),
                  sel.decide(9, 0.0, 0.0, False)]  # fmt: skip
    reasons = [d.reason for d in decisions]
    assert reasons == ["first-of-submap", "skip", "skip", "skip", "skip", "fallback", "skip",
                       "surprise-color", "surprise-depth", "skip"]  # fmt: skip
    every = KeyframeSelector(KeyframeConfig(mode="every"))
    assert all(every.decide(i, -1.0, -1.0, False).keyframe for i in range(4))
    restored = KeyframeSelector(KeyframeConfig())
    restored.load_state_dict(sel.state_dict())
    assert restored.since_last == sel.since_last == 1
