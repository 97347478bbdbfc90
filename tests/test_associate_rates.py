"""The crowd's detection probability from the persons an association finds (rigsfm.associate.rates)."""

from __future__ import annotations

import numpy as np

from rigsfm.associate.rates import truncated_binomial_p


def test_found_persons_give_the_detection_probability_not_their_own_share():
    """Only persons detected in two views or more can be found: their own share of detections overstates the
    probability (more so where it is low, as in a dense crowd); the truncated binomial gives it back."""
    rng = np.random.default_rng(0)
    for p in (0.3, 0.46, 0.7):
        seen = rng.integers(2, 9, size=3000)
        members = rng.binomial(seen, p)
        found = members >= 2
        naive = members[found].sum() / seen[found].sum()
        estimate = truncated_binomial_p(members[found], seen[found])
        assert estimate is not None and abs(estimate - p) < 0.03, (p, estimate)
        if p < 0.5:
            assert naive - p > 0.05, (p, naive)  # what the kept groups alone would say


def test_no_usable_persons_give_no_estimate():
    assert truncated_binomial_p(np.array([1, 0]), np.array([1, 3])) is None
