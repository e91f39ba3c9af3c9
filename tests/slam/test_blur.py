"""The numba Gaussian blur equals PyTorch's zero-padded conv2d and is its own adjoint."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from bgs_batch.slam.blur import blur_planes, gaussian_window


def conv2d_blur(images: torch.Tensor, taps: torch.Tensor) -> torch.Tensor:
    """The reference: one 2-D depthwise convolution with the outer-product window."""
    n, size = images.shape[0], taps.shape[0]
    window = (taps[:, None] * taps[None, :]).expand(n, 1, size, size)
    return F.conv2d(images[None], window, padding=size // 2, groups=n)[0]


@pytest.mark.parametrize("dtype, tol", [(np.float64, 1e-14), (np.float32, 1e-6)])
@pytest.mark.parametrize("shape", [(3, 23, 37), (5, 4, 9), (1, 11, 1)])
def test_blur_equals_conv2d(dtype, tol, shape):
    gen = torch.Generator().manual_seed(0)
    images = torch.rand(shape, generator=gen, dtype=torch.float64)
    taps = gaussian_window(11, 1.5, torch.float64)
    expected = conv2d_blur(images, taps).numpy()
    actual = blur_planes(images.numpy().astype(dtype), taps.numpy())
    assert actual.dtype == dtype
    assert np.abs(actual.astype(np.float64) - expected).max() < tol


def test_blur_is_its_own_adjoint():
    """<B x, y> = <x, B y>: what lets the SSIM backward blur gradients with the same kernel."""
    rng = np.random.default_rng(1)
    x, y = rng.uniform(size=(2, 2, 9, 14))
    taps = gaussian_window(5, 1.0, torch.float64).numpy()
    assert np.vdot(blur_planes(x, taps), y) == pytest.approx(np.vdot(x, blur_planes(y, taps)),
                                                             rel=1e-13)  # fmt: skip


def test_blur_rejects_bad_shapes():
    with pytest.raises(ValueError, match="odd-length"):
        blur_planes(np.zeros((2, 3, 3)), np.ones(4))
    with pytest.raises(ValueError, match=r"\[N,H,W\]"):
        blur_planes(np.zeros((3, 3)), np.ones(3))
