"""Descriptor matching restricted to candidate pairs (guided matching): Lowe's ratio test among each feature's
candidates, then mutual best matches; an n_i x n_j distance table only where the candidates are a good part of it."""

from __future__ import annotations

import numpy as np


def candidate_matches(descriptors_i: np.ndarray, descriptors_j: np.ndarray, a: np.ndarray, b: np.ndarray,
                      max_ratio: float) -> np.ndarray:
    """(k, 2) index pairs among the candidate pairs (a[n], b[n]) (feature a of i, feature b of j): the nearest
    candidate of each feature of i (L2 descriptor distance, as OpenCV's) that passes the ratio test against its
    second-nearest candidate (a single candidate passes) and is in turn the nearest candidate of its feature of j."""
    a, b = np.asarray(a, dtype=np.int64), np.asarray(b, dtype=np.int64)
    if not len(a):
        return np.zeros((0, 2), int)
    di, dj = np.asarray(descriptors_i, np.float32), np.asarray(descriptors_j, np.float32)
    norms_i, norms_j = np.einsum("ij,ij->i", di, di), np.einsum("ij,ij->i", dj, dj)
    if len(di) * len(dj) <= min(DENSE_FACTOR * len(a), DENSE_MAX):  # one product beats two gathered rows a pair
        dots = (di @ dj.T)[a, b]
    else:  # in chunks: the gathered rows of millions of candidates would take gigabytes (each row's sum is the same)
        dots = np.empty(len(a), dtype=np.float32)
        for start in range(0, len(a), GATHER_CHUNK):
            rows = slice(start, start + GATHER_CHUNK)
            dots[rows] = np.einsum("ij,ij->i", di[a[rows]], dj[b[rows]])
    distance = np.sqrt(np.maximum(norms_i[a] + norms_j[b] - 2.0 * dots, 0.0))
    by_distance = np.argsort(distance, kind="stable")  # shared by both groupings below
    order = _grouped(a, by_distance)
    a_s, b_s, d_s = a[order], b[order], distance[order]
    first = np.flatnonzero(np.r_[True, a_s[1:] != a_s[:-1]])
    has_second = np.r_[first[1:], len(a_s)] - first > 1
    second = np.where(has_second, d_s[np.minimum(first + 1, len(d_s) - 1)], np.inf)
    passed = first[d_s[first] < max_ratio * second]
    order_b = _grouped(b, by_distance)
    first_b = order_b[np.r_[True, b[order_b][1:] != b[order_b][:-1]]]
    best_a_of_b = np.full(int(b.max()) + 1, -1, dtype=np.int64)
    best_a_of_b[b[first_b]] = a[first_b]
    mutual = best_a_of_b[b_s[passed]] == a_s[passed]
    return np.c_[a_s[passed][mutual], b_s[passed][mutual]].astype(int)


# The whole table of descriptor products (one BLAS product) when the candidates are at least 1/16 of it and it
# holds at most 16 M entries (64 MB): faster than gathering two descriptors per candidate when the candidates are
# that dense (floor matching and the self-check's guided matching).
DENSE_FACTOR = 16
DENSE_MAX = 1 << 24
GATHER_CHUNK = 1 << 16  # candidates whose descriptor rows are gathered at once (2 x 32 MB)


def _grouped(feature: np.ndarray, by_distance: np.ndarray) -> np.ndarray:
    """``np.lexsort((distance, feature))`` from the stable distance order: one more stable sort, by feature
    (a radix sort when the indices fit 16 bits), faster than lexsort's two."""
    keys = feature[by_distance]
    if keys.max() < 1 << 16:
        keys = keys.astype(np.uint16)
    return by_distance[np.argsort(keys, kind="stable")]
