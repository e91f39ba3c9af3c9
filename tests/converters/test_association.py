import numpy as np
import pytest

from converters.association import associate, association_summary


def best_matching(first: np.ndarray, second: np.ndarray, tolerance: float) -> tuple[int, float]:
    """Oracle: (most pairs, least summed |Δt| among those) of any order-preserving one-to-one
    matching, by the full O(N·M) dynamic programme."""
    n, m = len(first), len(second)
    best = [[(0, 0.0)] * (m + 1) for _ in range(n + 1)]
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            options = [best[i - 1][j], best[i][j - 1]]
            gap = abs(first[i - 1] - second[j - 1])
            if gap <= tolerance:
                count, negative_cost = best[i - 1][j - 1]
                options.append((count + 1, negative_cost - gap))
            best[i][j] = max(options)
    count, negative_cost = best[n][m]
    return count, -negative_cost


def test_streams_half_a_period_apart_keep_every_frame():
    # colour at 30 Hz, each depth frame ~16.7 ms after its colour frame (a jitter of 2 ms decides
    # which neighbour is nearer): nearest-first matching (TUM's associate.py) lets neighbours take
    # each other's partners and keeps 52 of 60 pairs; the order-preserving matching keeps all
    rgb = np.arange(60) / 30
    depth = rgb + 1 / 60 + np.random.default_rng(0).uniform(-0.002, 0.002, 60)
    pairs = associate(rgb, depth, 0.02)
    assert pairs.tolist() == [[i, i] for i in range(60)]


def test_pairs_are_one_to_one_order_preserving_and_within_tolerance():
    rng = np.random.default_rng(3)
    first = np.sort(rng.uniform(0, 10, 300))
    second = np.sort(rng.uniform(0, 10, 280))
    pairs = associate(first, second, 0.02)
    assert np.all(np.diff(pairs[:, 0]) > 0) and np.all(np.diff(pairs[:, 1]) > 0)
    assert np.abs(first[pairs[:, 0]] - second[pairs[:, 1]]).max() <= 0.02


@pytest.mark.parametrize("seed", range(6))
def test_most_pairs_then_least_time_difference_as_the_full_dynamic_programme(seed):
    rng = np.random.default_rng(seed)
    first = np.sort(rng.uniform(0, 3, 60))
    second = np.sort(rng.uniform(0, 3, 55))
    pairs = associate(first, second, 0.03)
    count, cost = best_matching(first, second, 0.03)
    assert len(pairs) == count
    assert np.abs(first[pairs[:, 0]] - second[pairs[:, 1]]).sum() == pytest.approx(cost, abs=1e-9)


def test_tolerance_is_inclusive_and_nothing_matches_far_streams():
    assert associate(np.array([1.0, 1.01]), np.array([1.005]), 0.005).tolist() == [[0, 0]]
    assert associate(np.array([1.0]), np.array([1.5]), 0.1).shape == (0, 2)
    assert associate(np.array([1.0]), np.array([]), 0.1).shape == (0, 2)


def test_the_summary_names_what_was_dropped_and_what_a_wider_tolerance_keeps():
    rgb = np.arange(10) / 30
    depth = np.delete(rgb, [3, 7]) + np.where(np.arange(8) < 5, 0.001, 0.03)
    matched = len(associate(rgb, depth, 0.02))
    line = association_summary(rgb, depth, 0.02, matched)
    wider = len(associate(rgb, depth, 0.04))
    assert wider > matched
    assert line == (f"10 RGB images, {matched} associated ({10 - matched} without a depth image "
                    f"within 0.02 s; --tolerance 0.04 keeps {wider})")  # fmt: skip
    everything = association_summary(rgb, rgb, 0.02, 10)
    assert everything == "10 RGB images, 10 associated (each with a depth image within 0.02 s)"
