"""A rolling-shutter frame moved to one instant: what a global shutter would have seen.

Kinect-class RGB-D cameras read their rows top to bottom over most of a frame interval, so a
camera turning at 60°/s sees its bottom rows about 1.5° later than its top ones: vertical edges
lean and pitch stretches the image. The renderer, the tracker and the map explain a frame by one
pose; fed the raw rows they settle on a pose biased along the motion (a synthetic shake with a
0.9-frame readout tracks 3.4× worse than the same shake with a global shutter,
docs/experiments.md). Each row is instead moved to the frame's time stamp (the middle of the
readout) by the camera's constant-velocity motion over the row's offset, as Kerl et al. (ICCV
2015) model rolling-shutter RGB-D cameras with a continuous trajectory.

Rotation dominates hand-held motion within a frame, and a rotation's image motion does not depend
on depth, so the rectified image samples the raw one at the pixel minus the motion computed at
the rectified pixel itself (one fixed-point step); depth readings also take the motion's change
of their distance.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from bgs_batch.slam.rolling_shutter_kernels import moved_depth, source_maps

# four neighbouring readings further apart than this share of the nearest are not one surface
SURFACE_SPREAD = 0.05


def row_motions(readout_motion: np.ndarray, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Per image row, the rotation (H, 3, 3) and translation (H, 3) taking a point of the
    camera when the row was read to the camera at the middle of the readout.

    `readout_motion` is the camera's motion over the whole readout (`depth_timing.
    interval_motion` scaled to it): the first row is read half of it before the middle, the
    last half after, and each row's share of it follows the rotation vector and translation
    linearly (constant velocity).
    """
    share = np.linspace(-0.5, 0.5, height)[:, None]
    rotvec = Rotation.from_matrix(readout_motion[:3, :3]).as_rotvec()
    rotations = Rotation.from_rotvec(share * rotvec).as_matrix()
    return rotations, share * readout_motion[:3, 3]


def rectify(rgb: np.ndarray, depth: np.ndarray, intrinsics: np.ndarray,
            readout_motion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Colour (H, W, 3) uint8 and depth (H, W) float32 m (0 invalid) of a rolling-shutter frame
    whose two images are read out alike, as seen at the middle of the readout (module
    docstring); pixels whose source falls outside the image are black and invalid."""
    sources = _Sources(depth, intrinsics, readout_motion)
    return sources.colour(rgb), sources.depth(depth)


def rectify_colour(rgb: np.ndarray, depth: np.ndarray, intrinsics: np.ndarray,
                   readout_motion: np.ndarray) -> np.ndarray:  # fmt: skip
    """The colour image alone moved to the middle of its readout (a camera whose colour and
    depth sensors read out differently, e.g. a RealSense D435's rolling colour and global depth);
    `depth` only guesses each pixel's distance, which the motion's translation needs."""
    return _Sources(depth, intrinsics, readout_motion).colour(rgb)


def rectify_depth(depth: np.ndarray, intrinsics: np.ndarray, readout_motion: np.ndarray
                  ) -> np.ndarray:  # fmt: skip
    """The depth image alone moved to the middle of its readout (see `rectify_colour`)."""
    return _Sources(depth, intrinsics, readout_motion).depth(depth)


class _Sources:
    """Where each rectified pixel's reading came from in the raw image, and each raw row's
    motion to the middle of the readout (`rolling_shutter_kernels`)."""

    def __init__(self, depth: np.ndarray, intrinsics: np.ndarray, readout_motion: np.ndarray
                 ) -> None:  # fmt: skip
        height, width = depth.shape
        fx, fy, cx, cy = (float(intrinsics[0, 0]), float(intrinsics[1, 1]),
                          float(intrinsics[0, 2]), float(intrinsics[1, 2]))  # fmt: skip
        rotations, shifts = row_motions(readout_motion, height)
        valid = depth > 0
        z_guess = np.where(valid, depth, np.median(depth[valid]) if valid.any() else 1.0)
        self.map_u, self.map_v = np.empty((height, width)), np.empty((height, width))
        source_maps(np.ascontiguousarray(z_guess), np.ascontiguousarray(rotations),
                    np.ascontiguousarray(shifts), fx, fy, cx, cy,
                    self.map_u, self.map_v)  # fmt: skip
        self.rotations, self.shifts, self.intrinsics = rotations, shifts, (fx, fy, cx, cy)

    def colour(self, rgb: np.ndarray) -> np.ndarray:
        return cv2.remap(rgb, self.map_u.astype(np.float32), self.map_v.astype(np.float32),
                         cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)  # fmt: skip

    def depth(self, depth: np.ndarray) -> np.ndarray:
        out = np.empty(depth.shape, np.float32)
        moved_depth(np.ascontiguousarray(depth), self.map_u, self.map_v,
                    np.ascontiguousarray(self.rotations), np.ascontiguousarray(self.shifts),
                    *self.intrinsics, SURFACE_SPREAD, out)  # fmt: skip
        return out
