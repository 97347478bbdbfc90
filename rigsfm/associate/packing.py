"""The global set packing: the hypotheses with the largest summed score, each detection in at most one."""

from __future__ import annotations

import logging

import numpy as np
import scipy.optimize
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

logger = logging.getLogger(__name__)


EXACT_GROUP = 20  # hypotheses of a group of conflicts branched on exactly; a larger one goes to the MILP
EXACT_STEPS = 5000  # branchings allowed one group before it goes to the MILP all the same


def _pack(members: np.ndarray, scores: np.ndarray, total: int, time_limit: float) -> np.ndarray:
    """The subset of hypotheses with the largest summed score, each detection in at most one (a mask).

    Hypotheses conflict where they share a detection, and the conflicts fall apart into small groups (a few
    hypotheses of one place of the crowd, where the bands are narrow): each group's best subset is found exactly by
    branching (its largest weight independent set), and the groups too large for that (a first frame's wide bands
    join hundreds) go to one MILP; a hypothesis without conflicts is kept where its score is positive."""
    n = len(scores)
    if not n:
        return np.zeros(0, dtype=bool)
    present = members >= 0
    columns = np.repeat(np.arange(n), present.sum(axis=1))
    a = sp.csr_matrix((np.ones(len(columns)), (members[present], columns)), shape=(total, n))
    shared = a[np.asarray(a.sum(axis=1)).ravel() > 1]
    conflicts = (shared.T @ shared).tocoo()
    other = conflicts.row != conflicts.col
    first, second = conflicts.row[other], conflicts.col[other]
    count, group = connected_components(sp.coo_matrix((np.ones(len(first)), (first, second)), shape=(n, n)),
                                        directed=False)
    size = np.bincount(group, minlength=count)
    chosen = (size[group] == 1) & (scores > 0)
    order = np.argsort(group, kind="stable")  # the hypotheses group by group
    starts = np.concatenate([[0], np.cumsum(size)])
    local = np.empty(n, dtype=np.int64)
    local[order] = np.arange(n) - starts[group[order]]
    neighbours = [0] * n  # each hypothesis' conflicts within its group, as bits of their places in it
    for p, q in zip(first.tolist(), local[second].tolist()):
        neighbours[p] |= 1 << q
    weights = scores.tolist()
    large = []
    for g in np.flatnonzero(size > 1).tolist():
        nodes = order[starts[g]:starts[g + 1]].tolist()
        best = None if len(nodes) > EXACT_GROUP else _best_independent([neighbours[v] for v in nodes],
                                                                        [weights[v] for v in nodes])
        if best is None:
            large.append(g)
            continue
        chosen[[v for k, v in enumerate(nodes) if best >> k & 1]] = True
    if large:
        rows = np.flatnonzero(np.isin(group, large))
        chosen[rows] = _pack_milp(members[rows], scores[rows], total, time_limit)
    return chosen


def _best_independent(neighbours: list[int], weights: list[float]) -> int | None:
    """The nodes (bits) of the largest summed weight of which no two are neighbours (``neighbours``: each node's, as
    bits); None where that takes more than ``EXACT_STEPS`` branchings. Branches on the node of most neighbours
    left: without it, or with it and without its neighbours; a node without neighbours left is taken where its
    weight is positive."""
    known: dict[int, tuple[float, int]] = {}

    def best(nodes: int) -> tuple[float, int]:
        if not nodes:
            return 0.0, 0
        if nodes in known:
            return known[nodes]
        if len(known) > EXACT_STEPS:
            raise _TooLarge
        free_value, free, pivot, most = 0.0, 0, -1, 0
        rest = nodes
        while rest:
            bit = rest & -rest
            rest ^= bit
            v = bit.bit_length() - 1
            degree = (neighbours[v] & nodes).bit_count()
            if not degree:
                if weights[v] > 0:
                    free_value, free = free_value + weights[v], free | bit
            elif degree > most:
                pivot, most = v, degree
        if pivot < 0:
            known[nodes] = free_value, free
            return known[nodes]
        left = nodes & ~free & ~(1 << pivot)
        without, without_set = best(left)
        with_, with_set = best(left & ~neighbours[pivot])
        with_ += weights[pivot]
        known[nodes] = (free_value + without, free | without_set) if without >= with_ \
            else (free_value + with_, free | with_set | 1 << pivot)
        return known[nodes]

    try:
        return best((1 << len(weights)) - 1)[1]
    except _TooLarge:
        return None


class _TooLarge(Exception):
    """A group of hypotheses whose exact packing takes more branchings than ``EXACT_STEPS``."""


def _pack_milp(members: np.ndarray, scores: np.ndarray, total: int, time_limit: float) -> np.ndarray:
    """``_pack``'s subset by a MILP (HiGHS; greedy start), for groups of conflicts too large to branch on."""
    n = len(scores)
    if not n:
        return np.zeros(0, dtype=bool)
    rows = members[members >= 0]
    cols = np.repeat(np.arange(n), np.sum(members >= 0, axis=1))
    order = np.argsort(-scores)
    greedy = np.zeros(n, dtype=bool)
    used = bytearray(total)
    # row by row in Python's own lists: a numpy call per row costs more than the row's few members
    for g, row in zip(order.tolist(), members[order].tolist()):
        m = [d for d in row if d >= 0]
        if not any(used[d] for d in m):
            greedy[g] = True
            for d in m:
                used[d] = 1
    # Only detections claimed by two or more hypotheses constrain anything.
    a = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(total, n))
    shared = np.asarray(a.sum(axis=1)).ravel() > 1
    if not shared.any():
        return np.ones(n, dtype=bool)
    constraint = scipy.optimize.LinearConstraint(a[shared], -np.inf, 1.0)
    result = scipy.optimize.milp(-scores, constraints=[constraint], integrality=np.ones(n),
                                 bounds=scipy.optimize.Bounds(0, 1), options={"time_limit": time_limit})
    if result.x is None:
        logger.warning("set packing found no solution in %.1f s; kept the greedy one", time_limit)
        return greedy
    chosen = result.x > 0.5
    if scores[chosen].sum() < scores[greedy].sum():
        return greedy
    return chosen
