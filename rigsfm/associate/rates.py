"""The crowd's own detection probability, from the persons one association found.

A person whose point projects inside ``n`` views is detected in each with probability ``p`` (occlusion included), so
its member count is binomial; but only persons detected in two views or more can be found at all, and those seen
in more views are found more readily. The maximum-likelihood ``p`` of the found persons' counts under the binomial
truncated to two or more members corrects the first of these; the kept persons' own counts (the detected ones) would
overstate ``p`` badly in a crowd where half the heads are hidden.
"""

from __future__ import annotations

import numpy as np
from scipy.special import gammaln

GRID = np.linspace(0.02, 0.98, 97)


def truncated_binomial_p(members: np.ndarray, seen: np.ndarray, at_least: int = 2) -> float | None:
    """Maximum-likelihood detection probability of groups with ``members`` detections among ``seen`` views that
    see them, each group known to hold at least ``at_least`` (a grid over 0.02-0.98). None without usable groups:
    a group seen by only ``at_least`` views holds all of them whatever the probability, so it tells nothing (two
    views' persons alone would otherwise give the grid's first value, and every person would score as unlikely)."""
    k, n = np.asarray(members, dtype=np.int64), np.asarray(seen, dtype=np.int64)
    ok = (n > at_least) & (k >= at_least) & (k <= n)
    k, n = k[ok], n[ok]
    if not len(k):
        return None
    p = GRID[:, None]
    log_p, log_q = np.log(p), np.log1p(-p)
    observed = k[None] * log_p + (n - k)[None] * log_q
    # P(K >= at_least) = 1 - sum_{j < at_least} C(n, j) p^j q^(n - j)
    below = np.zeros((len(GRID), len(n)))
    for j in range(at_least):
        log_choose = gammaln(n + 1) - gammaln(j + 1) - gammaln(n - j + 1)
        below += np.exp(log_choose[None] + j * log_p + (n - j)[None] * log_q)
    total = np.sum(observed - np.log(np.maximum(1.0 - below, 1e-300)), axis=1)
    return float(GRID[int(np.argmax(total))])
