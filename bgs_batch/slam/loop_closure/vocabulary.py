"""A binary bag-of-words vocabulary learnt online from the ORB descriptors seen so far.

Words are k-majority clusters (k-means for bit strings: Hamming assignment, per-bit majority
vote). Training is deterministic: evenly spaced samples, a seeded choice of initial centres,
exact integer arithmetic. Keyframes become tf-idf weighted, L2-normalised word histograms;
the similarity of two keyframes is the dot product of theirs (1 for identical word statistics).
"""

from __future__ import annotations

import numpy as np

from bgs_batch.slam.loop_closure.features import bits, hamming

MAJORITY = 2  # a centre bit is set when more than half of its members have it set


def train(descriptors: np.ndarray, words: int, iterations: int, samples: int,
          rng: np.random.Generator) -> np.ndarray:  # fmt: skip
    """(k, 32) uint8 word centres, k = min(words, distinct descriptors)."""
    if len(descriptors) > samples:
        descriptors = descriptors[np.linspace(0, len(descriptors) - 1, samples).astype(int)]
    unique = np.unique(descriptors, axis=0)
    k = min(words, len(unique))
    if k == 0:
        return np.zeros((0, descriptors.shape[1]), np.uint8)
    data = bits(descriptors)
    centres = bits(unique[np.sort(rng.permutation(len(unique))[:k])])
    assignment = np.full(len(data), -1)
    for _ in range(iterations):
        new = np.argmin(hamming(data, centres), 1)
        if np.array_equal(new, assignment):
            break
        assignment = new
        order = np.argsort(assignment, kind="stable")
        members, starts = np.unique(assignment[order], return_index=True)
        counts = np.add.reduceat(data[order], starts, axis=0)
        sizes = np.diff(np.r_[starts, len(order)])
        centres[members] = (MAJORITY * counts > sizes[:, None]).astype(np.float32)
    return np.packbits(centres.astype(np.uint8), axis=1)


def assign(descriptors: np.ndarray, vocabulary: np.ndarray) -> np.ndarray:
    """The word of every descriptor (nearest centre, lowest index on ties)."""
    if len(descriptors) == 0 or len(vocabulary) == 0:
        return np.zeros(0, int)
    return np.argmin(hamming(bits(descriptors), bits(vocabulary)), 1)


def bow_vectors(word_lists: list[np.ndarray], words: int) -> np.ndarray:
    """(m, words) tf-idf, L2-normalised histograms of m keyframes' word lists.

    idf = log(m / n_w) with n_w the keyframes containing word w: words seen everywhere (floor,
    walls of one colour) count for nothing, rare ones for much.
    """
    hist = np.zeros((len(word_lists), words))
    for i, w in enumerate(word_lists):
        np.add.at(hist[i], w, 1.0)
    counts = np.maximum(hist.sum(1, keepdims=True), 1.0)
    present = (hist > 0).sum(0)
    idf = np.where(present > 0, np.log(len(word_lists) / np.maximum(present, 1)), 0.0)
    vectors = hist / counts * idf
    norms = np.linalg.norm(vectors, axis=1, keepdims=True)
    return np.where(norms > 0, vectors / np.where(norms > 0, norms, 1.0), 0.0)
