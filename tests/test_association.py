import numpy as np

from converters.association import associate


def test_greedy_one_to_one_nearest_first():
    first = np.array([0.0, 0.033, 0.066, 0.1])
    second = np.array([0.001, 0.030, 0.034, 0.2])
    pairs = associate(first, second, 0.02)
    # 0.033 takes 0.034 (diff 0.001) before 0.030 (diff 0.003); 0.066 has nothing within 0.02
    # after 0.030 is left for... 0.066-0.030 = 0.036 > 0.02, so no pair
    assert pairs.tolist() == [[0, 0], [1, 2]]


def test_each_timestamp_used_once_and_tolerance_inclusive():
    first = np.array([1.0, 1.01])
    second = np.array([1.005])
    assert associate(first, second, 0.005).tolist() == [[0, 0]]
    assert associate(np.array([1.0]), np.array([1.5]), 0.1).shape == (0, 2)


def test_matches_brute_force_on_random_streams():
    rng = np.random.default_rng(3)
    first = np.sort(rng.uniform(0, 10, 300))
    second = np.sort(rng.uniform(0, 10, 280))
    pairs = associate(first, second, 0.02)
    candidates = sorted(
        (abs(a - b), i, j) for i, a in enumerate(first) for j, b in enumerate(second)
        if abs(a - b) <= 0.02
    )
    used_i, used_j, expected = set(), set(), []
    for _, i, j in candidates:
        if i not in used_i and j not in used_j:
            used_i.add(i)
            used_j.add(j)
            expected.append((i, j))
    assert pairs.tolist() == [list(p) for p in sorted(expected)]
