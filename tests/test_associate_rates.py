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


def test_persons_seen_by_as_many_views_as_needed_tell_nothing():
    """A person seen by two views and found holds both whatever the probability: a frame of two views gives no
    estimate (its flat likelihood once gave 0.02, and every later frame started from it and found no one), and such
    persons leave a mixed crowd's estimate as it is."""
    assert truncated_binomial_p(np.full(300, 2), np.full(300, 2)) is None
    rng = np.random.default_rng(1)
    seen = rng.integers(3, 9, size=2000)
    members = rng.binomial(seen, 0.6)
    found = members >= 2
    alone = truncated_binomial_p(members[found], seen[found])
    mixed = truncated_binomial_p(np.r_[members[found], np.full(500, 2)], np.r_[seen[found], np.full(500, 2)])
    assert alone is not None and abs(alone - 0.6) < 0.03 and mixed == alone, (alone, mixed)
