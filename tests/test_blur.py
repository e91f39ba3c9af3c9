"""The numba Gaussian blur equals PyTorch's zero-padded conv2d, and its backward is exact."""

import pytest
import torch
import torch.nn.functional as F

from bgs_batch.blur import gaussian_blur, gaussian_window


def conv2d_blur(images: torch.Tensor, taps: torch.Tensor) -> torch.Tensor:
    """The reference: one 2-D depthwise convolution with the outer-product window."""
    n, size = images.shape[0], taps.shape[0]
    window = (taps[:, None] * taps[None, :]).expand(n, 1, size, size)
    return F.conv2d(images[None], window, padding=size // 2, groups=n)[0]


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-14), (torch.float32, 1e-6)])
@pytest.mark.parametrize("shape", [(3, 23, 37), (5, 4, 9), (1, 11, 1)])
def test_blur_equals_conv2d(dtype, tol, shape):
    gen = torch.Generator().manual_seed(0)
    images = torch.rand(shape, generator=gen, dtype=torch.float64)
    taps = gaussian_window(11, 1.5, torch.float64)
    expected = conv2d_blur(images, taps)
    actual = gaussian_blur(images.to(dtype), taps.to(dtype))
    assert actual.dtype == dtype
    assert (actual.double() - expected).abs().max() < tol


def test_blur_gradcheck():
    gen = torch.Generator().manual_seed(1)
    images = torch.rand(2, 9, 14, generator=gen, dtype=torch.float64, requires_grad=True)
    taps = gaussian_window(5, 1.0, torch.float64)
    assert torch.autograd.gradcheck(lambda x: gaussian_blur(x, taps), (images,))


def test_blur_rejects_bad_shapes():
    with pytest.raises(ValueError, match="odd-length"):
        gaussian_blur(torch.zeros(2, 3, 3), torch.ones(4))
    with pytest.raises(ValueError, match=r"\[N,H,W\]"):
        gaussian_blur(torch.zeros(3, 3), torch.ones(3))
