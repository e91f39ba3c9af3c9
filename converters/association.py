"""Timestamp association of two sensor streams (RGB ↔ depth, frames ↔ poses)."""

from __future__ import annotations

import numpy as np


def associate(first: np.ndarray, second: np.ndarray, tolerance: float) -> np.ndarray:
    """Greedy one-to-one matching of two timestamp lists, as TUM's ``associate.py`` does.

    All pairs with ``|first[i] - second[j]| <= tolerance`` are taken in order of increasing time
    difference (ties by index); each timestamp is used at most once. Returns an int array of
    shape (M, 2) with rows ``(i, j)`` sorted by ``i``. Both inputs must be sorted ascending.
    """
    first = np.asarray(first, np.float64)
    second = np.asarray(second, np.float64)
    lo = np.searchsorted(second, first - tolerance, side="left")
    hi = np.searchsorted(second, first + tolerance, side="right")
    counts = hi - lo
    i = np.repeat(np.arange(len(first)), counts)
    starts = np.repeat(lo - np.cumsum(counts) + counts, counts)
    j = starts + np.arange(counts.sum())
    diff = np.abs(first[i] - second[j])
    order = np.lexsort((j, i, diff))
    used_first = np.zeros(len(first), bool)
    used_second = np.zeros(len(second), bool)
    pairs = []
    for a, b in zip(i[order].tolist(), j[order].tolist(), strict=True):
        if not (used_first[a] or used_second[b]):
            used_first[a] = used_second[b] = True
            pairs.append((a, b))
    pairs.sort()
    return np.asarray(pairs, np.int64).reshape(-1, 2)
