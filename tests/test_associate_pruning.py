"""What the association leaves out to save time: each cut must leave the persons it finds as they were."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
from test_associate_segments import _crowd_views

from rigsfm.associate import AssociateOptions
from rigsfm.associate.appearance import AppearanceModel
from rigsfm.associate.occupancy import CountGrid
from rigsfm.associate.solve import _Frame, associate_views


def test_a_grid_box_never_misses_a_point_within_the_radius():
    rng = np.random.default_rng(0)
    points = np.r_[rng.uniform(0, 400, (300, 2)), np.arange(0, 400, 8.0)[:, None].repeat(2, axis=1)]  # on cell edges
    grid = CountGrid(points)
    queries = np.r_[rng.uniform(-30, 430, (3000, 2)), points + rng.choice([-1, 1], (len(points), 2)) * 4.0]
    radius = np.r_[rng.uniform(0.5, 20, 3000), np.full(len(points), 4.0 * np.sqrt(2))]  # the last: exactly reached
    near = np.min(np.linalg.norm(queries[:, None] - points[None], axis=2), axis=1)
    within = near <= radius
    found = grid.any_within(queries, radius)
    assert within.sum() > 500 and (~within).sum() > 500
    assert np.all(found[within])
    assert (~found[~within]).mean() > 0.3  # and it rules most empty discs out (its use)


def test_the_score_s_floor_leaves_every_hypothesis_above_it_as_it_was():
    views, _ = _crowd_views(seed=1)
    rng = np.random.default_rng(1)
    for view in views:  # greys that set the pairs' appearance terms apart (either sign)
        view.descriptor = rng.normal(0.0, 0.3, (len(view.xy), 2))
    model = AppearanceModel(np.array([0.1, 0.1]), np.array([0.4, 0.4]))
    options = AssociateOptions(pixel_sigma=1.5, detection_probability=0.8, height_prior=(1.75, 0.1))
    frame = _Frame(views, options, model)
    members, points, covariance, scores = frame.hypotheses()
    full = frame.score(members, points, covariance)
    above = full > options.min_score
    assert above.sum() > 50 and (~above).sum() > 50
    np.testing.assert_array_equal(scores[above], full[above])
    assert np.all(scores[~above] <= options.min_score)


def test_the_seeds_floor_leaves_the_persons_of_a_crowd():
    views, _ = _crowd_views(seed=2, noise_px=1.0)
    options = AssociateOptions(pixel_sigma=1.5, appearance=False, detection_probability=0.8)

    def carried(floor: float | None):  # a later frame's one association (the views' shifts as they are)
        return associate_views(copy.deepcopy(views), dataclasses.replace(options, seed_min_score=floor), carried=True)

    pruned, every = carried(options.seed_min_score), carried(None)
    assert len(every) > 50
    np.testing.assert_array_equal(pruned.members, every.members)
    np.testing.assert_array_equal(pruned.points, every.points)
    # a floor above what a right pair scores loses persons: the floor is what keeps them
    assert len(carried(2.0)) < len(every)
    # and a first frame grows every seed whatever the floor
    first = dataclasses.replace(options, self_calibration_rounds=0)
    np.testing.assert_array_equal(
        associate_views(copy.deepcopy(views), dataclasses.replace(first, seed_min_score=2.0)).members,
        associate_views(copy.deepcopy(views), dataclasses.replace(first, seed_min_score=None)).members)


def test_groups_grown_under_the_seeds_floor_are_not_rescored():
    views, _ = _crowd_views(seed=4)
    options = AssociateOptions(pixel_sigma=1.5, detection_probability=0.8)
    every = dataclasses.replace(options, seed_min_score=None)
    other = dataclasses.replace(every, detection_probability=0.6)
    assert _Frame(views, every).rescored(views, other) is not None  # the groups do not depend on the rates
    assert _Frame(views, options).rescored(views, dataclasses.replace(options, detection_probability=0.6)) is None


def test_groups_verified_once_per_frame_are_the_groups_verified_anew(monkeypatch):
    """A frame's record of the groups it verified serves its growth's later rounds and its final check (most groups
    are met again), and what it serves is what verifying them anew gives: the same groups, their points and scores
    to the rounding (a row's matrix product may round otherwise in another batch of rows), from far fewer rows
    verified."""
    views, _ = _crowd_views(seed=5, noise_px=1.0)
    options = AssociateOptions(pixel_sigma=1.5, appearance=False, detection_probability=0.8)
    rows: list[int] = []
    verify = _Frame._verify_steps

    def counted(self, members):
        rows.append(len(members))
        return verify(self, members)

    monkeypatch.setattr(_Frame, "_verify_steps", counted)
    kept = _Frame(views, options).hypotheses()
    recorded, rows[:] = sum(rows), []
    monkeypatch.setattr(_Frame, "_verify_distinct", lambda self, members: self._verify_steps(members))
    anew = _Frame(views, options).hypotheses()
    np.testing.assert_array_equal(kept[0], anew[0])
    for a, b in zip(kept[1:], anew[1:]):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
    assert np.sum(kept[3] > options.min_score) > 50
    assert recorded < 0.8 * sum(rows), (recorded, sum(rows))
