"""Descriptor matching against its definitions: guided matching (rigsfm.core.matching) on both of its paths, and
rigsfm track's all-against-all matching (rigsfm.track.register) block by block."""

import numpy as np
import pytest

from rigsfm.core import matching
from rigsfm.core.matching import candidate_matches


def reference_matches(di, dj, a, b, max_ratio):
    """The definition, one candidate at a time: ties go to the candidate listed first."""
    distance = [float(np.linalg.norm(di[i].astype(float) - dj[j].astype(float))) for i, j in zip(a, b)]
    of_i, of_j = {}, {}
    for n, (i, j) in enumerate(zip(a, b)):
        of_i.setdefault(i, []).append(n)
        of_j.setdefault(j, []).append(n)
    best_of_j = {j: a[min(ns, key=lambda n: distance[n])] for j, ns in of_j.items()}
    found = []
    for i, ns in sorted(of_i.items()):
        ranked = sorted(ns, key=lambda n: distance[n])  # stable: ties in listed order
        best = ranked[0]
        second = distance[ranked[1]] if len(ranked) > 1 else np.inf
        if distance[best] < max_ratio * second and best_of_j[b[best]] == i:
            found.append((i, b[best]))
    return np.array(found, dtype=int).reshape(-1, 2)


@pytest.mark.parametrize("dense", [True, False, "chunked"])
@pytest.mark.parametrize("seed", range(4))
def test_candidate_matches_equal_the_definition(seed, dense, monkeypatch):
    rng = np.random.default_rng(seed)
    # SIFT-like integer-valued float32 descriptors: features 0..49 of i have near copies 200..249 in j; features
    # 50..59 of i are near copies of 0..9 (two features of i prefer one of j: only one is mutual), 60..64 exact
    # copies of 10..14 (a tie: the candidate listed first is mutual); 245..249 of j repeat 240..244 exactly.
    di = rng.integers(0, 40, (300, 128)).astype(np.float32)
    di[50:60] = di[:10] + rng.integers(0, 3, (10, 128))
    di[60:65] = di[10:15]
    dj = np.concatenate([rng.integers(0, 40, (200, 128)), di[:50] + rng.integers(0, 3, (50, 128))]).astype(np.float32)
    dj[245:] = dj[240:245]
    k = np.arange(50)
    pairs = np.concatenate([np.c_[rng.integers(0, 300, 5000), rng.integers(0, 250, 5000)], np.c_[k, 200 + k],
                            np.c_[50 + k[:15], 200 + k[:15]], np.c_[40 + k[:5], 245 + k[:5]]])
    pairs = rng.permutation(np.unique(pairs, axis=0))  # each candidate once, in no particular order
    a, b = pairs[:, 0], pairs[:, 1]
    monkeypatch.setattr(matching, "DENSE_FACTOR", 10**9 if dense is True else 0)
    if dense == "chunked":  # the gathered path in chunks of 7 candidates, as millions are
        monkeypatch.setattr(matching, "GATHER_CHUNK", 7)
    found = candidate_matches(di, dj, a, b, 0.8)
    expected = reference_matches(di, dj, a, b, 0.8)
    assert len(expected) > 20
    np.testing.assert_array_equal(found, expected)


def test_track_matching_equals_the_definition_block_by_block(monkeypatch):
    """rigsfm track's all-against-all matching (rigsfm.track.register) against the full distance table in float64,
    with tables cut into 64-row blocks; duplicated descriptors on both sides give exact ties."""
    from rigsfm.track import register

    rng = np.random.default_rng(7)
    query = rng.integers(0, 60, (300, 128)).astype(np.uint8)
    train = rng.integers(0, 60, (250, 128)).astype(np.uint8)
    train[:120] = np.clip(query[:120].astype(int) + rng.integers(-3, 4, (120, 128)), 0, 255)
    train[200:210], query[150:155] = train[:10], query[20:25]  # ties in both directions
    monkeypatch.setattr(register, "MATCH_BLOCK_ROWS", 64)
    rows, cols, distances = register.match_mutual_ratio(query, train, 0.8)

    table = np.linalg.norm(query[:, None, :].astype(float) - train[None, :, :].astype(float), axis=2)
    nearest = np.argmin(table, axis=1)
    ranked = np.sort(table, axis=1)
    keep = (np.argmin(table, axis=0)[nearest] == np.arange(len(query))) & (ranked[:, 0] < 0.8 * ranked[:, 1])
    assert 80 < keep.sum() < 120  # the near copies, less the tied ones
    np.testing.assert_array_equal(rows, np.flatnonzero(keep))
    np.testing.assert_array_equal(cols, nearest[keep])
    np.testing.assert_allclose(distances, ranked[keep, 0], rtol=1e-6)
