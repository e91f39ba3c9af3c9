"""Rendering metrics and AUSE against closed-form and hand-computed values."""

import math

import numpy as np
import pytest
import torch

from outputs.ause import (
    colour_sparsification,
    depth_sparsification,
    mean_over_frames,
    sparsification,
)
from outputs.image_metrics import depth_l1, ms_ssim, psnr, ssim_index

PYTORCH_MSSSIM_VALUE = 0.9650129296774024  # pytorch-msssim 1.0.0 ms_ssim(data_range=1) on `pair`


def pair(h=170, w=180):
    y = torch.arange(h, dtype=torch.float64)[:, None, None]
    x = torch.arange(w, dtype=torch.float64)[None, :, None]
    c = torch.arange(3, dtype=torch.float64)
    a = 0.5 + 0.4 * torch.sin(x / 7 + c) * torch.cos(y / 11)
    return a, (a + 0.08 * torch.sin(x * y / 13 + 2 * c)).clamp(0, 1)


def test_identical_images():
    a, _ = pair()
    assert psnr(a, a) == math.inf
    assert ssim_index(a, a) == pytest.approx(1.0, abs=1e-12)
    assert ms_ssim(a, a) == pytest.approx(1.0, abs=1e-12)


def test_constant_offset_gives_closed_form_psnr():
    a, _ = pair(20, 30)
    assert psnr(a * 0.5 + 0.1, a * 0.5) == pytest.approx(20.0)  # MSE 0.01 → 20 dB


def test_ms_ssim_matches_reference_and_orders_quality():
    a, b = pair()
    assert ms_ssim(a, b) == pytest.approx(PYTORCH_MSSSIM_VALUE, abs=1e-6)
    assert ssim_index(a, (a + 0.2 * (b - a))) > ssim_index(a, b)
    with pytest.raises(ValueError, match="160"):
        ms_ssim(a[:160], b[:160])


def test_depth_l1_on_valid_pixels_only():
    measured = torch.tensor([[1.0, 0.0], [2.0, math.nan]])
    rendered = torch.tensor([[1.5, 5.0], [2.5, 7.0]])
    assert depth_l1(rendered, measured) == pytest.approx(0.5)
    assert math.isnan(depth_l1(rendered, torch.zeros(2, 2)))


def test_oracle_uncertainty_has_zero_ause():
    error = np.random.default_rng(0).exponential(size=1000)
    result = sparsification(error, error)
    assert result.ause_raw == 0 and result.ause_normalised == 0
    np.testing.assert_array_equal(result.oracle, result.by_uncertainty)


def test_hand_computed_small_case():
    # Errors 4, 3, 2, 1 with uncertainty ranking them backwards. Kept counts over k = 0..99:
    # 4 (k=0), 3 (1..25), 2 (26..50), 1 (51..99). Oracle MAE 2.5, 2, 1.5, 1; by uncertainty
    # 2.5, 3, 3.5, 4; differences 0, 1 (25×), 2 (25×), 3 (49×). Trapezoid with step 0.01:
    # 0.01·(25 + 50 + 147 − (0 + 3)/2) = 2.205; normalised by the peak 4.
    result = sparsification(np.array([1.0, 2.0, 3.0, 4.0]), np.array([4.0, 3.0, 2.0, 1.0]))
    expected = 0.01 * (25 + 50 + 147 - 1.5)
    assert result.ause_raw == pytest.approx(expected)
    assert result.ause_normalised == pytest.approx(expected / 4)
    assert result.oracle[[0, 1, 26, 51, 99]] == pytest.approx([2.5, 2, 1.5, 1, 1])
    assert result.by_uncertainty[[0, 25, 50, 75]] == pytest.approx([2.5, 3, 3.5, 4])


def test_invariant_to_monotone_transforms_of_uncertainty():
    rng = np.random.default_rng(1)
    sigma = rng.uniform(0.1, 2.0, 500)
    error = np.abs(rng.normal(0, sigma))
    sigma[::7] = sigma[0]  # ties must be broken the same way too
    base = sparsification(sigma**2, error)
    for transformed in (sigma, np.log(sigma), 3 * np.exp(sigma) + 1):
        other = sparsification(transformed, error)
        assert (other.ause_raw, other.ause_normalised) == (base.ause_raw, base.ause_normalised)
    assert 0 < base.ause_raw < sparsification(-sigma, error).ause_raw  # informative beats inverse


def test_frame_helpers_use_valid_depth_and_channel_means():
    rng = np.random.default_rng(2)
    rendered, target = rng.uniform(size=(2, 6, 8, 3))
    variance = rng.uniform(size=(6, 8, 3))
    depth = rng.uniform(1, 2, (6, 8))
    depth[0] = 0.0  # invalid row: excluded from both metrics
    valid = depth > 0
    colour = colour_sparsification(rendered, target, variance, depth[..., None])
    expected = sparsification(variance.mean(-1)[valid], np.abs(rendered - target).mean(-1)[valid])
    assert colour.ause_raw == expected.ause_raw
    rendered_depth = depth + rng.normal(0, 0.01, depth.shape)
    result = depth_sparsification(rendered_depth, depth, variance[..., 0])
    expected = sparsification(variance[..., 0][valid], np.abs(rendered_depth - depth)[valid])
    assert result.ause_raw == expected.ause_raw
    mean = mean_over_frames([colour, result])
    assert mean.ause_raw == pytest.approx((colour.ause_raw + result.ause_raw) / 2)
    np.testing.assert_allclose(mean.oracle, (colour.oracle + result.oracle) / 2)
