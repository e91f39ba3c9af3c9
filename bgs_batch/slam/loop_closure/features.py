"""ORB features of a keyframe with their 3-D points, and Hamming-distance matching.

Only keypoints with a valid depth reading are kept: verification is 3-D/3-D, so a keypoint
without depth could never support a loop. Keypoints are put in a canonical order (strongest
first, then by position), so the same image always gives the same arrays.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from bgs_batch.config import LoopClosureConfig
from bgs_batch.slam.frames import Level

DESCRIPTOR_BYTES = 32  # ORB: 256 bits
DESCRIPTOR_BITS = 8 * DESCRIPTOR_BYTES
MAX_8BIT = 255


@dataclass(frozen=True)
class KeyframeFeatures:
    """A keyframe's ORB descriptors and the camera-frame 3-D points of their keypoints."""

    frame: int
    submap: int
    c2w: np.ndarray  # (4, 4) pose in its submap's frame at the time it was mapped
    descriptors: np.ndarray  # (n, 32) uint8
    points: np.ndarray  # (n, 3) float32, camera frame, metres


def orb_detector(cfg: LoopClosureConfig) -> cv2.ORB:
    return cv2.ORB_create(
        nfeatures=cfg.orb_features,
        scaleFactor=cfg.orb_scale,
        nlevels=cfg.orb_levels,
        edgeThreshold=cfg.orb_patch,
        patchSize=cfg.orb_patch,
        fastThreshold=cfg.orb_fast_threshold,
    )


def extract(frame: int, submap: int, level: Level, c2w: np.ndarray, cfg: LoopClosureConfig
            ) -> KeyframeFeatures:  # fmt: skip
    """ORB on the grey image of `level`, back-projected with its depth."""
    rgb = (level.rgb.numpy() * MAX_8BIT).round().astype(np.uint8)
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    keypoints, descriptors = orb_detector(cfg).detectAndCompute(grey, None)
    if descriptors is None or not keypoints:
        return KeyframeFeatures(frame, submap, c2w.copy(), np.zeros((0, DESCRIPTOR_BYTES),
                                np.uint8), np.zeros((0, 3), np.float32))  # fmt: skip
    uv = np.array([k.pt for k in keypoints], np.float64)
    response = np.array([k.response for k in keypoints], np.float64)
    order = np.lexsort((uv[:, 0], uv[:, 1], -response))
    uv, descriptors = uv[order], descriptors[order]
    depth = level.depth[..., 0].numpy()
    h, w = depth.shape
    col = np.clip(np.rint(uv[:, 0]).astype(int), 0, w - 1)
    row = np.clip(np.rint(uv[:, 1]).astype(int), 0, h - 1)
    z = depth[row, col].astype(np.float64)
    ok = z > 0
    cam = level.camera
    points = np.stack([(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z], 1)
    return KeyframeFeatures(frame, submap, c2w.copy(), np.ascontiguousarray(descriptors[ok]),
                            points[ok].astype(np.float32))  # fmt: skip


def bits(descriptors: np.ndarray) -> np.ndarray:
    """(n, 256) float32 0/1 bits of (n, 32) uint8 descriptors (for distances by matmul)."""
    return np.unpackbits(descriptors, axis=1).astype(np.float32)


def hamming(a_bits: np.ndarray, b_bits: np.ndarray) -> np.ndarray:
    """(n, m) Hamming distances of bit rows: |a| + |b| − 2 a·b.

    All terms are small integers, exact in float32 whatever the BLAS summation order, so the
    result does not depend on the thread count.
    """
    return a_bits.sum(1)[:, None] + b_bits.sum(1)[None, :] - 2.0 * (a_bits @ b_bits.T)


def match(a: np.ndarray, b: np.ndarray, ratio: float) -> np.ndarray:
    """(k, 2) index pairs of mutual nearest descriptors passing Lowe's ratio test."""
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), int)
    dist = hamming(bits(a), bits(b))
    best_b = np.argmin(dist, 1)
    two = np.partition(dist, 1, axis=1)[:, :2]
    best_a = np.argmin(dist, 0)
    rows = np.arange(len(a))
    keep = (best_a[best_b] == rows) & (two[:, 0] < ratio * two[:, 1])
    return np.stack([rows[keep], best_b[keep]], 1)
