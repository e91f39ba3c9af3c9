"""Timestamp association of two sensor streams (RGB ↔ depth)."""

from __future__ import annotations

import numpy as np

_Chain = tuple[tuple[int, float], int]
"""((pairs in the chain, −sum of |Δt|), index of its last pair): chains compare by the first."""


def associate(first: np.ndarray, second: np.ndarray, tolerance: float) -> np.ndarray:
    """The order-preserving one-to-one matching with the most pairs within `tolerance`, and among
    those the smallest summed time difference.

    Two free-running 30 Hz streams (a Kinect's colour and depth) can sit half a period apart, so
    every depth frame is nearly as close to the colour frame before it as to the one after. The
    greedy nearest-first matching of TUM's ``associate.py`` then lets neighbours take each
    other's partners and leaves frames unmatched that an order-preserving shift keeps (fr1/rpy
    RGB frames 420–479: 53 of 60 greedily at 0.02 s, 57 at 0.08 s with pairs 49 ms apart; all 60
    here, at most 20 ms apart). Both inputs must be sorted ascending; ``|Δt| <= tolerance`` is
    inclusive. Returns an int array of shape (M, 2) with rows ``(i, j)``, both strictly
    increasing.

    A maximum-weight chain over the candidate pairs, with a Fenwick tree of the best chain ending
    at each `second` index: O(K log N) for K candidate pairs.
    """
    first = np.asarray(first, np.float64)
    second = np.asarray(second, np.float64)
    lo = np.searchsorted(second, first - tolerance, side="left")
    hi = np.searchsorted(second, first + tolerance, side="right")
    tree: list[_Chain] = [((0, 0.0), -1)] * (len(second) + 1)
    pairs: list[tuple[int, int]] = []
    previous: list[int] = []
    for i in range(len(first)):
        # this row's candidates from the latest back: a chain may not use two pairs of one row
        for j in range(int(hi[i]) - 1, int(lo[i]) - 1, -1):
            (count, negative_cost), last = _best_before(tree, j)
            pairs.append((i, j))
            previous.append(last)
            gap = abs(first[i] - second[j])
            _offer(tree, j + 1, ((count + 1, negative_cost - gap), len(pairs) - 1))
    _, last = _best_before(tree, len(second))
    chain = []
    while last >= 0:
        chain.append(pairs[last])
        last = previous[last]
    return np.asarray(chain[::-1], np.int64).reshape(-1, 2)


def _best_before(tree: list[_Chain], position: int) -> _Chain:
    """The best chain whose last `second` index is below `position` (Fenwick prefix maximum)."""
    best: _Chain = ((0, 0.0), -1)
    while position > 0:
        if tree[position][0] > best[0]:
            best = tree[position]
        position -= position & -position
    return best


def _offer(tree: list[_Chain], position: int, chain: _Chain) -> None:
    """Record a chain ending at 1-based `position` where it beats the stored ones."""
    while position < len(tree):
        if chain[0] > tree[position][0]:
            tree[position] = chain
        position += position & -position


def association_summary(
    first: np.ndarray, second: np.ndarray, tolerance: float, matched: int,
    first_name: str = "RGB images", second_name: str = "depth image",
) -> str:  # fmt: skip
    """One line naming what an association kept and dropped, e.g. ``120 RGB images, 107
    associated (13 without a depth image within 0.02 s; --tolerance 0.04 keeps 118)``."""
    line = f"{len(first)} {first_name}, {matched} associated"
    dropped = len(first) - matched
    if dropped == 0:
        return f"{line} (each with a {second_name} within {tolerance:g} s)"
    wider = 2 * tolerance
    kept = len(associate(first, second, wider))
    hint = f"--tolerance {wider:g} keeps {kept}" if kept > matched else "no more at twice that"
    return f"{line} ({dropped} without a {second_name} within {tolerance:g} s; {hint})"
