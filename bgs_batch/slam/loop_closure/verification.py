"""Geometric verification of a keyframe pair: rigid RANSAC on matched 3-D keypoints.

Both keyframes have depth, so matched keypoints are 3-D/3-D correspondences and the relative
camera pose follows from three of them (Umeyama/Horn). Hypotheses are drawn all at once from
a seeded generator and scored in one batch, so the result is reproducible; the best one is
refined on its inliers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bgs_batch.config import LoopClosureConfig
from bgs_batch.metrics import align_rigid
from bgs_batch.slam.loop_closure.features import KeyframeFeatures, match

SAMPLE = 3  # points per rigid hypothesis
MIN_SPREAD = 1e-3  # m²: hypotheses from (nearly) collinear samples are skipped
REFINE_ROUNDS = 2  # refits on the inliers of the previous fit


@dataclass(frozen=True)
class Verification:
    """The relative pose of a verified pair: points of camera a → camera b."""

    a_to_b: np.ndarray  # (4, 4)
    inliers: int
    matches: int

    @property
    def ratio(self) -> float:
        return self.inliers / max(self.matches, 1)


def rigid(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The 4×4 rigid transform mapping `src` (n, 3) onto `dst` in the least-squares sense."""
    rot, trans, _ = align_rigid(src, dst)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, trans
    return out


def batched_rigid(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(h, 4, 4) rigid fits of h point triples (h, 3, 3) onto theirs (Kabsch, no scale)."""
    mu_s, mu_d = src.mean(1, keepdims=True), dst.mean(1, keepdims=True)
    cov = np.einsum("hni,hnj->hij", dst - mu_d, src - mu_s)
    u, _, vt = np.linalg.svd(cov)
    sign = np.ones((len(src), 3))
    sign[:, 2] = np.sign(np.linalg.det(u) * np.linalg.det(vt))
    rot = np.einsum("hij,hj,hjk->hik", u, sign, vt)
    out = np.tile(np.eye(4), (len(src), 1, 1))
    out[:, :3, :3] = rot
    out[:, :3, 3] = mu_d[:, 0] - np.einsum("hij,hj->hi", rot, mu_s[:, 0])
    return out


def ransac(src: np.ndarray, dst: np.ndarray, cfg: LoopClosureConfig, rng: np.random.Generator
           ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Best rigid transform src → dst and its inlier mask (all False when none is found)."""
    n = len(src)
    if n < SAMPLE:
        return np.eye(4), np.zeros(n, bool)
    picks = np.stack([rng.choice(n, SAMPLE, replace=False)
                      for _ in range(cfg.ransac_iterations)])  # fmt: skip
    tri = src[picks]
    spread = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    picks = picks[spread > MIN_SPREAD]
    if len(picks) == 0:
        return np.eye(4), np.zeros(n, bool)
    hyp = batched_rigid(src[picks], dst[picks])
    moved = np.einsum("hij,nj->hni", hyp[:, :3, :3], src) + hyp[:, None, :3, 3]
    inliers = np.linalg.norm(moved - dst[None], axis=2) < cfg.ransac_threshold
    best = inliers[int(np.argmax(inliers.sum(1)))]
    transform = hyp[int(np.argmax(inliers.sum(1)))]
    for _ in range(REFINE_ROUNDS):
        if best.sum() < SAMPLE:
            break
        transform = rigid(src[best], dst[best])
        moved = src @ transform[:3, :3].T + transform[:3, 3]
        best = np.linalg.norm(moved - dst, axis=1) < cfg.ransac_threshold
    return transform, best


def verify(a: KeyframeFeatures, b: KeyframeFeatures, cfg: LoopClosureConfig,
           rng: np.random.Generator) -> Verification | None:  # fmt: skip
    """The pose of camera a in camera b when enough matches agree on one, else None."""
    pairs = match(a.descriptors, b.descriptors, cfg.match_ratio)
    if len(pairs) < cfg.min_inliers:
        return None
    src = a.points[pairs[:, 0]].astype(np.float64)
    dst = b.points[pairs[:, 1]].astype(np.float64)
    transform, inliers = ransac(src, dst, cfg, rng)
    result = Verification(transform, int(inliers.sum()), len(pairs))
    if result.inliers < cfg.min_inliers or result.ratio < cfg.min_inlier_ratio:
        return None
    return result
