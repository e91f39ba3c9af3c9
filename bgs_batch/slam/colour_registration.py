"""A colour image resampled onto the depth camera's pixels, for a colour camera that does not sit
on its depth camera (`colour_offset` estimates how it sits; docs/method.md §6)."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from bgs_batch.config import ColourOffsetConfig


def colour_homography(intrinsics: np.ndarray, offset: ColourOffsetConfig) -> np.ndarray:
    """The 3×3 map from a depth-camera pixel to the colour-camera pixel that sees the same ray:
    K_c R K⁻¹, with K_c the depth camera's intrinsics at the colour camera's focal length."""
    rotation = Rotation.from_rotvec(np.radians(
        [offset.rotation_x_deg, offset.rotation_y_deg, offset.rotation_z_deg])).as_matrix()
    k = np.asarray(intrinsics, np.float64)
    k_colour = k.copy()
    k_colour[:2, :2] *= offset.focal_ratio
    return k_colour @ rotation @ np.linalg.inv(k)


def register_colour(rgb: np.ndarray, intrinsics: np.ndarray, offset: ColourOffsetConfig
                    ) -> np.ndarray:  # fmt: skip
    """The colour image (H, W, 3) resampled onto the depth camera's pixels (bilinear; a pixel
    whose ray leaves the colour image takes the nearest border pixel's colour)."""
    height, width = rgb.shape[:2]
    return cv2.warpPerspective(rgb, colour_homography(intrinsics, offset), (width, height),
                               flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_REPLICATE)  # fmt: skip
