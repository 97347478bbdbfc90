"""The global set packing: the hypotheses with the largest summed score, each detection in at most one."""

from __future__ import annotations

import logging

import numpy as np
import scipy.optimize
import scipy.sparse as sp

logger = logging.getLogger(__name__)


def _pack(members: np.ndarray, scores: np.ndarray, total: int, time_limit: float) -> np.ndarray:
    """The subset of hypotheses with the largest summed score, each detection in at most one (MILP; greedy start)."""
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
