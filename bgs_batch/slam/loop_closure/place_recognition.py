"""Loop candidates for a query submap: LoopSplat's self-similarity rule on bag-of-words vectors.

For each keyframe i of the query submap the threshold τ_i is the k-th best similarity to the
n other keyframes of its own submap, k = max(int(n·share), 1) (about the median; the keyframe
itself, similarity 1, is left out). An older submap is a candidate when one of its keyframes
is more similar to some i than τ_i, and it is more than `min_interval` submaps older than the
query. A query submap with a single keyframe has no self-similarity and proposes nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Candidate:
    """An older submap that looks like the query, with its most similar keyframe pairs."""

    submap: int
    margin: float  # best similarity minus the query keyframe's threshold
    similarity: float
    pairs: list[tuple[int, int]]  # (query row, candidate row) into the keyframe table, best first


def self_thresholds(sim: np.ndarray, share: float) -> np.ndarray:
    """τ_i of every row of a query submap's (n, n) similarity matrix (NaN when n < 2)."""
    n = len(sim)
    if n < 2:
        return np.full(n, np.nan)
    others = np.sort(sim[~np.eye(n, dtype=bool)].reshape(n, n - 1), axis=1)[:, ::-1]
    k = max(int((n - 1) * share), 1)
    return others[:, k - 1]


def candidates(
    vectors: np.ndarray,
    submap_of: np.ndarray,
    query: int,
    share: float,
    min_interval: int,
    max_pairs: int,
) -> list[Candidate]:
    """Candidates of submap `query` among older submaps, best margin first.

    `vectors` (m, words) are the keyframes' bag-of-words vectors, `submap_of` (m,) their submaps.
    """
    rows_q = np.flatnonzero(submap_of == query)
    thresholds = self_thresholds(vectors[rows_q] @ vectors[rows_q].T, share)
    if np.all(np.isnan(thresholds)):
        return []
    out = []
    for submap in np.unique(submap_of[submap_of < query - min_interval]):
        rows_c = np.flatnonzero(submap_of == submap)
        sim = vectors[rows_q] @ vectors[rows_c].T  # (n_q, n_c)
        margin = sim - thresholds[:, None]
        if not np.any(margin > 0):
            continue
        order = np.argsort(-sim, axis=None, kind="stable")[:max_pairs]
        qi, ci = np.unravel_index(order, sim.shape)
        pairs = [(int(rows_q[a]), int(rows_c[b])) for a, b in zip(qi, ci, strict=True)]
        out.append(Candidate(int(submap), float(margin.max()), float(sim.max()), pairs))
    return sorted(out, key=lambda c: (-c.margin, c.submap))
