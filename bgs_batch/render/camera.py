"""Pinhole camera and the se(3) pose parametrisation used for tracking gradients."""

from dataclasses import dataclass

import torch

SMALL_ANGLE_SQ = 1e-8
"""Below this squared rotation angle, :func:`se3_exp` uses Taylor series (exact to rounding)."""


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics of an image of ``width`` × ``height`` pixels (OpenCV convention)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def scaled(self, factor: float) -> "Camera":
        """The same camera at ``factor`` times the resolution (pixel centres kept consistent)."""
        return Camera(
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
            width=round(self.width * factor),
            height=round(self.height * factor),
        )


def _hat(phi: torch.Tensor) -> torch.Tensor:
    """The skew-symmetric matrix ``[φ]×`` of a 3-vector."""
    zero = phi.new_zeros(())
    x, y, z = phi.unbind()
    return torch.stack(
        [
            torch.stack([zero, -z, y]),
            torch.stack([z, zero, -x]),
            torch.stack([-y, x, zero]),
        ]
    )


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """The 4×4 rigid transform ``exp(ξ^)`` of a twist ``ξ = (ρ, φ)`` (translation first).

    Differentiable, smooth at ``ξ = 0``. Tracking perturbs the world-to-camera pose on the
    **left**: ``viewmat = se3_exp(ξ) @ viewmat₀``, so ``ξ`` is expressed in the camera frame
    and ``∂L/∂ξ`` at ``ξ = 0`` is the left-Jacobian pose gradient.
    """
    rho, phi = xi[:3], xi[3:]
    theta_sq = (phi * phi).sum()
    small = theta_sq < SMALL_ANGLE_SQ
    safe_sq = torch.where(small, torch.ones_like(theta_sq), theta_sq)
    theta = safe_sq.sqrt()
    # a = sinθ/θ, b = (1−cosθ)/θ², c = (θ−sinθ)/θ³, with their Taylor series near 0.
    a = torch.where(small, 1 - theta_sq / 6, theta.sin() / theta)
    b = torch.where(small, 0.5 - theta_sq / 24, (1 - theta.cos()) / safe_sq)
    c = torch.where(small, 1 / 6 - theta_sq / 120, (theta - theta.sin()) / (safe_sq * theta))
    k = _hat(phi)
    k2 = k @ k
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    rot = eye + a * k + b * k2
    trans = (eye + b * k + c * k2) @ rho
    bottom = xi.new_tensor([0.0, 0.0, 0.0, 1.0]).unsqueeze(0)
    return torch.cat([torch.cat([rot, trans.unsqueeze(1)], 1), bottom], 0)
