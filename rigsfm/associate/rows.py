"""Member rows (per view a detection or -1): a frame's row-wise arithmetic in blocks, distinct rows, row hashes
and the record of the groups a frame verified."""

from __future__ import annotations

import functools

import numpy as np

ROWS_PER_BLOCK = 4096  # hypotheses per block of the row-wise algebra: its temporaries stay in the CPU's cache


def _rowwise(method):
    """Run a method whose array arguments and results are per hypothesis (rows) on blocks of rows: each row's
    arithmetic is the same, while the temporaries of a hundred thousand hypotheses times the views would not fit
    any cache (and their allocation alone costs more than the arithmetic)."""

    @functools.wraps(method)
    def blocked(self, *arrays, **options):
        n = len(arrays[0])
        if n <= ROWS_PER_BLOCK:
            return method(self, *arrays, **options)

        def rows(a, k):
            return a[k:k + ROWS_PER_BLOCK] if isinstance(a, np.ndarray) and a.ndim and len(a) == n else a

        parts = [method(self, *(rows(a, k) for a in arrays), **{key: rows(a, k) for key, a in options.items()})
                 for k in range(0, n, ROWS_PER_BLOCK)]
        if isinstance(parts[0], tuple):
            return tuple(np.concatenate(column) for column in zip(*parts))
        return np.concatenate(parts)

    return blocked


def confident_rows(members: np.ndarray, scores: np.ndarray, min_score: float) -> np.ndarray:
    """Which groups a view's correction may rest on: three or more views, scoring above ``min_score`` (the
    self-calibration's threshold, ``AssociateOptions.self_calibration_min_score``)."""
    return (np.sum(members >= 0, axis=1) >= 3) & (scores > min_score)


def _sorted_rows(members: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The order that sorts member rows (-1 or a detection) as ``np.unique(axis=0)`` does, stable, and where in it a
    row repeats the one before: the columns packed into a few integer keys sort far faster than rows compared as
    records."""
    columns = np.ascontiguousarray(members.T) + 1  # >= 0; column by column, each contiguous
    bases = columns.max(axis=1) + 1
    keys, key, room = [], np.zeros(len(members), dtype=np.int64), 1
    for c in range(members.shape[1]):
        if room * int(bases[c]) >= 2 ** 62:
            keys.append(key)
            key, room = np.zeros(len(members), dtype=np.int64), 1
        key = key * bases[c] + columns[c]
        room *= int(bases[c])
    keys.append(key)
    order = _stable_order(keys)  # stable: the first of equal rows first; the first column decides first
    repeated = np.zeros(len(order), dtype=bool)
    repeated[1:] = True
    for key in keys:
        ranked = key[order]
        repeated[1:] &= ranked[1:] == ranked[:-1]
    return order, repeated


def _stable_order(keys: list[np.ndarray]) -> np.ndarray:
    """``np.lexsort(keys[::-1])`` of non-negative integer keys (the first decides first), as a radix sort: stable
    sorts of their 16-bit digits, least significant first (a stable sort of 16-bit integers is numpy's radix sort,
    far faster than its merge sorts of 64-bit keys)."""
    order = None
    for key in keys[::-1]:
        top, shift = int(key.max()) if len(key) else 0, 0
        while shift == 0 or top >> shift:
            digit = ((key if order is None else key[order]) >> shift).astype(np.uint16)  # the low 16 bits
            step = np.argsort(digit, kind="stable")
            order = step if order is None else order[step]
            shift += 16
    return order if order is not None else np.zeros(0, dtype=np.int64)


def _unique_rows(members: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(members, axis=0, return_index=True)`` (the same rows, order and first occurrences) for member
    rows."""
    if not members.size:
        return np.unique(members, axis=0, return_index=True)
    order, repeated = _sorted_rows(members)
    first = order[~repeated]
    return members[first], first


def _unique_inverse(members: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of ``members`` (as ``_unique_rows``) and, per row, which of them it is."""
    if not members.size:
        return members, np.zeros(len(members), dtype=np.int64)
    order, repeated = _sorted_rows(members)
    rank = np.empty(len(members), dtype=np.int64)
    rank[order] = np.cumsum(~repeated) - 1
    return members[order[~repeated]], rank


_HASH_FACTORS: dict[int, np.ndarray] = {}  # per number of columns, _row_hashes' odd constants


def _row_hashes(members: np.ndarray) -> np.ndarray:
    """A 64-bit hash of each member row (-1 or a detection per column): a sum of the columns times odd constants,
    wrapping; equal rows hash alike (a hash only says which rows to compare)."""
    factors = _HASH_FACTORS.get(members.shape[1])
    if factors is None:
        drawn = np.random.default_rng(members.shape[1]).integers(0, 2 ** 63, members.shape[1], dtype=np.uint64)
        factors = _HASH_FACTORS[members.shape[1]] = np.asarray(drawn) * np.uint64(2) + np.uint64(1)
    hashes = np.zeros(len(members), dtype=np.uint64)
    for c in range(members.shape[1]):
        hashes += (members[:, c] + 1).astype(np.uint64) * factors[c]
    return hashes


class _Verified:
    """The groups a frame verified (chunks of member rows and their ``_verify_steps``), with their hashes sorted for
    lookups (shared by the frame's re-scored copies, as the list was)."""

    def __init__(self) -> None:
        self.chunks: list[tuple[np.ndarray, tuple[np.ndarray, ...]]] = []
        self.starts = np.zeros(1, dtype=np.int64)  # each chunk's first row in the chunks stacked, and their total
        self.hashes = np.zeros(0, dtype=np.uint64)  # sorted, equal ones by their position
        self.positions = np.zeros(0, dtype=np.int64)  # each one's row in the chunks, stacked

    def add(self, rows: np.ndarray, out: tuple[np.ndarray, ...]) -> None:
        held = int(self.starts[-1])
        self.chunks.append((rows, out))
        self.starts = np.append(self.starts, held + len(rows))
        hashes = np.concatenate([self.hashes, _row_hashes(rows)])
        positions = np.concatenate([self.positions, held + np.arange(len(rows))])
        order = np.argsort(hashes, kind="stable")
        self.hashes, self.positions = hashes[order], positions[order]

    def find(self, members: np.ndarray) -> np.ndarray:
        """Per row of ``members``, its row in the stacked chunks (the last of equal rows there), -1 where none."""
        starts = self.starts
        hashes = _row_hashes(members)
        last = np.maximum(np.searchsorted(self.hashes, hashes, side="right") - 1, 0)
        hit = np.where(self.hashes[last] == hashes, self.positions[last], -1) if len(self.hashes) \
            else np.full(len(members), -1, dtype=np.int64)
        found = np.flatnonzero(hit >= 0)
        chunk = np.searchsorted(starts, hit[found], side="right") - 1
        for c in np.unique(chunk).tolist():
            at = found[chunk == c]
            if not np.array_equal(self.chunks[c][0][hit[at] - starts[c]], members[at]):
                return self._sorted_find(members)  # two rows share a hash: the rows themselves decide
        return hit

    def _sorted_find(self, members: np.ndarray) -> np.ndarray:
        table = np.concatenate([rows for rows, _ in self.chunks])
        _, rank = _unique_inverse(np.concatenate([table, members]))
        where = np.full(int(rank.max()) + 1, -1, dtype=np.int64)
        where[rank[:len(table)]] = np.arange(len(table))
        return where[rank[len(table):]]
