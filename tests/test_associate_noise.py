"""The detector's noise from the crowd itself (``AssociateOptions.pixel_sigma`` None, the default)."""

from __future__ import annotations

import numpy as np
from test_associate_segments import _crowd_views

from rigsfm.associate import AssociateOptions
from rigsfm.associate.rates import detection_noise
from rigsfm.associate.solve import START_PIXEL_SIGMA, associate_views


def test_the_noise_of_least_squares_residuals_is_recovered():
    """Groups of 2-6 members, each point fitted to its members' 2m coordinates (3 of them taken by the point): the
    members' squared residuals give the noise back (fails without the degrees of freedom or the median's 2 ln 2)."""
    rng = np.random.default_rng(0)
    sigma, groups, views = 1.7, 3000, 6
    squared = np.full((groups, views), np.nan)
    for g in range(groups):
        m = int(rng.integers(2, views + 1))
        design = rng.normal(size=(2 * m, 3))  # how the point's three coordinates move the members' pixels
        q, _ = np.linalg.qr(design)
        e = rng.normal(0.0, sigma, 2 * m)
        r = e - q @ (q.T @ e)  # the least-squares residual
        squared[g, :m] = r[0::2] ** 2 + r[1::2] ** 2
    estimate = detection_noise(squared)
    assert estimate is not None and abs(estimate / sigma - 1.0) < 0.04, estimate
    assert detection_noise(squared[:5]) is None  # too few members to say


def test_a_first_frame_is_associated_again_with_the_noise_its_persons_show():
    """Detections with 2.5 px of noise: the first association assumes 1 px, its confident persons show more, and the
    frame is associated again from the start with it; more true heads are found than at the start's noise held (fails
    where the noise is not estimated)."""
    views, heads = _crowd_views(seed=3, heads=150, noise_px=2.5)
    options = AssociateOptions(heights=(1.4, 2.1))
    first = [*views]  # corrected in place
    estimated = associate_views(first, options)
    held = associate_views([*views], AssociateOptions(heights=(1.4, 2.1), pixel_sigma=START_PIXEL_SIGMA))

    def found(result) -> int:  # persons within 10 cm of a true head
        return int(np.sum(np.linalg.norm(result.points[:, None] - heads[None], axis=2).min(axis=1) < 0.1))

    assert 1.5 < estimated.pixel_sigma <= 2.6, estimated.pixel_sigma
    assert held.pixel_sigma == START_PIXEL_SIGMA
    assert found(estimated) >= found(held) + 10, (found(estimated), found(held))
    # a carried frame (the same cameras, its views carrying the first's) takes the first frame's noise as it is
    later, _ = _crowd_views(seed=4, heads=150, noise_px=2.5)
    for view, before in zip(later, first):
        view.carry(before)
    carried = associate_views(later, options, carried=True, earlier=estimated)
    assert carried.pixel_sigma == estimated.pixel_sigma
