"""A narrow pair's matches as correlated observations (rigsfm.run.adjustment.correlated)."""

from __future__ import annotations

import numpy as np
import pytest

from rigsfm.run.adjustment.correlated import MIN_PAIR_POINTS, PairNoise, pair_noise


def _matches(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform([0, 0], [800, 600], (n, 2))


def test_a_pairs_smooth_error_is_its_correlation_and_white_noise_is_none():
    rng = np.random.default_rng(1)
    xy = _matches(120, 0)
    white = rng.normal(0.0, 0.2, 120)
    u = (xy - 400.0) / 400.0
    smooth = 0.2 * (u[:, 0] ** 2 - u[:, 1] + 0.5 * u[:, 0] * u[:, 1])  # a quadratic in the position
    smooth *= 0.2 / np.sqrt(np.mean(smooth**2))  # as large as the noise: half the variance shared
    noise = pair_noise(white, xy)
    assert noise is not None and noise.rho < 0.1 and noise.sigma_px == pytest.approx(0.2 / np.sqrt(2), rel=0.2)
    correlated = pair_noise(white + smooth, xy)
    assert correlated is not None and correlated.rho == pytest.approx(0.5, abs=0.1), correlated
    assert correlated.white_px == pytest.approx(0.2 / np.sqrt(2), rel=0.2)
    assert pair_noise(white[:MIN_PAIR_POINTS - 1], xy[:MIN_PAIR_POINTS - 1]) is None  # too few to fit
    assert pair_noise(np.zeros(120), xy) is None  # exact matches: nothing to weigh


def test_a_pairs_weight_counts_its_noise_and_its_correlation():
    quiet = PairNoise((1, 2), 100, 0.1, 0.0, 0.1)
    noisy = PairNoise((1, 3), 100, 0.4, 0.0, 0.4)
    shared = PairNoise((1, 4), 100, 0.1, 0.5, 0.1 / np.sqrt(2))
    # pooled noise 0.2 px, inflated 3x: each pair's own noise is inflated alike
    assert quiet.weight(0.6, 3.0) == pytest.approx(2.0)
    assert noisy.weight(0.6, 3.0) == pytest.approx(0.5)
    assert shared.weight(0.6, 3.0) == pytest.approx(2.0 / np.sqrt(1 + 99 * 0.5))  # the information of ~2 matches
    # a held calibration's error makes the smooth part: the white part alone weighs the pair
    assert shared.weight(0.6, 3.0, held=True) == pytest.approx(2.0 * np.sqrt(2))
