"""What the association leaves out to save time: each cut must leave the persons it finds as they were."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
from test_associate_segments import _crowd_views

from rigsfm.associate import AssociateOptions
from rigsfm.associate.appearance import AppearanceModel
from rigsfm.associate.frame import _Frame
from rigsfm.associate.occupancy import CountGrid
from rigsfm.associate.solve import associate_views


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


def test_a_grid_pairs_every_point_within_the_radius_as_a_kd_tree_does():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(3)
    points = np.r_[rng.uniform(0, 400, (300, 2)), np.arange(0, 400, 8.0)[:, None].repeat(2, axis=1)]  # on cell edges
    grid = CountGrid(points)
    queries = np.r_[rng.uniform(-60, 460, (3000, 2)), points + 4.0]
    radius = np.r_[rng.uniform(0.5, 40, 3000), np.full(len(points), 4.0 * np.sqrt(2))]  # the last: exactly reached
    query, point, d2 = grid.pairs_within(queries, radius)
    assert np.all(np.diff(query) >= 0)  # query by query
    np.testing.assert_allclose(d2, np.sum((points[point] - queries[query]) ** 2, axis=1))
    balls = cKDTree(points).query_ball_point(queries, radius)
    assert sum(map(len, balls)) > 3000
    assert set(zip(query.tolist(), point.tolist())) == {(q, p) for q, ball in enumerate(balls) for p in ball}


def test_the_growth_s_member_is_the_gated_nearest_of_the_four_nearest_pixels():
    views, _ = _crowd_views(seed=4)
    frame = _Frame(views, AssociateOptions(pixel_sigma=1.5))
    rng = np.random.default_rng(4)
    v = 1
    mine = frame.uv[frame.tree_index[v]]
    uv = mine[rng.integers(0, len(mine), 4000)] + rng.normal(0, 6.0, (4000, 2))
    sxx, syy = rng.uniform(1, 40, 4000) ** 2, rng.uniform(1, 40, 4000) ** 2  # long ellipses: many within
    sxy = rng.uniform(-0.99, 0.99, 4000) * np.sqrt(sxx * syy)
    bound = 3.5 * np.sqrt(np.maximum(sxx, syy) + np.abs(sxy)) + 1.0
    best, best_d2 = frame._nearest_member(v, uv, bound, sxx, sxy, syy, 3.5 ** 2)
    # brute force: the four nearest in pixels within the bound, the nearest of them by the covariance in the gate
    distance = np.linalg.norm(uv[:, None] - mine[None], axis=2)
    nearest = np.argsort(distance, axis=1, kind="stable")[:, :4]
    dx, dy = np.moveaxis(mine[nearest] - uv[:, None], 2, 0)
    det = sxx * syy - sxy ** 2
    d2 = (dx * dx * syy[:, None] - 2 * dx * dy * sxy[:, None] + dy * dy * sxx[:, None]) / det[:, None]
    ok = (np.take_along_axis(distance, nearest, axis=1) <= bound[:, None]) & (d2 <= 3.5 ** 2)
    d2 = np.where(ok, d2, np.inf)
    pick = np.argmin(d2, axis=1)
    want = np.where(np.isfinite(d2.min(axis=1)), frame.tree_index[v][nearest[np.arange(4000), pick]], -1)
    assert (want >= 0).sum() > 1000
    np.testing.assert_array_equal(best, want)
    # the four nearest's cut matters: without it another detection wins in some rows
    assert np.sum(frame._nearest_member(v, uv, bound, sxx, sxy, syy, 3.5 ** 2, k=len(mine))[0] != want) > 5
    np.testing.assert_allclose(best_d2[want >= 0], d2.min(axis=1)[want >= 0], rtol=1e-9)


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
    monkeypatch.setattr(_Frame, "_verify_distinct", lambda self, members, count=6: self._verify_steps(members)[:count])
    anew = _Frame(views, options).hypotheses()
    np.testing.assert_array_equal(kept[0], anew[0])
    for a, b in zip(kept[1:], anew[1:]):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
    assert np.sum(kept[3] > options.min_score) > 50
    assert recorded < 0.8 * sum(rows), (recorded, sum(rows))


def test_the_growth_skips_only_points_without_a_detection_within_their_reach():
    views, _ = _crowd_views(seed=4)
    frame = _Frame(views, AssociateOptions(pixel_sigma=1.5))
    members, points, covariance = frame._gated(frame.pair_candidates(), None)
    skipped = []
    may_reach = frame._may_reach

    def counted(v, uv, z, spread):
        near = may_reach(v, uv, z, spread)
        skipped.append((len(uv), int(np.sum(~near))))
        return near

    frame._may_reach = counted  # type: ignore[method-assign]
    for single in (True, False):
        grown = frame.grow(members, points, covariance, single=single)
        frame._may_reach = lambda *args: None  # type: ignore[method-assign]  # every point searched by its reach
        np.testing.assert_array_equal(grown, frame.grow(members, points, covariance, single=single))
        frame._may_reach = counted  # type: ignore[method-assign]
    searched, left = np.sum(skipped, axis=0)
    assert len(members) > 1000 and left > 0.3 * searched  # most projections are far from every detection


def _inverse3(a):
    """Inverses of stacked 3x3 matrices by their adjugates (the stacked form ``_inverse3_symmetric`` writes out)."""
    c = np.empty_like(a)
    c[:, 0, 0] = a[:, 1, 1] * a[:, 2, 2] - a[:, 1, 2] * a[:, 2, 1]
    c[:, 0, 1] = a[:, 0, 2] * a[:, 2, 1] - a[:, 0, 1] * a[:, 2, 2]
    c[:, 0, 2] = a[:, 0, 1] * a[:, 1, 2] - a[:, 0, 2] * a[:, 1, 1]
    c[:, 1, 0] = a[:, 1, 2] * a[:, 2, 0] - a[:, 1, 0] * a[:, 2, 2]
    c[:, 1, 1] = a[:, 0, 0] * a[:, 2, 2] - a[:, 0, 2] * a[:, 2, 0]
    c[:, 1, 2] = a[:, 0, 2] * a[:, 1, 0] - a[:, 0, 0] * a[:, 1, 2]
    c[:, 2, 0] = a[:, 1, 0] * a[:, 2, 1] - a[:, 1, 1] * a[:, 2, 0]
    c[:, 2, 1] = a[:, 0, 1] * a[:, 2, 0] - a[:, 0, 0] * a[:, 2, 1]
    c[:, 2, 2] = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
    det = a[:, 0, 0] * c[:, 0, 0] + a[:, 0, 1] * c[:, 1, 0] + a[:, 0, 2] * c[:, 2, 0]
    return c / det[:, None, None]


def _stacked_triangulation(frame, members, points=None):
    """The triangulation as 3 x 3 stacks (the arithmetic ``_Frame.triangulate`` keeps, entry by entry)."""
    g, nv = members.shape
    present = members >= 0
    d = np.take(frame.rays_by_axis(), np.where(present, members, 0), axis=1)
    dc = np.einsum("igv,vi->gv", d, frame.centres)
    for _ in range(2 if points is None else 1):
        if points is None:
            depth = np.ones((g, nv))
        else:
            diff = points.T[:, :, None] - frame.centres.T[:, None, :]
            depth = np.maximum(np.sqrt(np.einsum("igv,igv->gv", diff, diff)), 0.1)
        w = np.where(present, (frame.focals[None] / (depth * frame.noise[None])) ** 2, 0.0)
        wd = w[None] * d
        a = np.empty((g, 3, 3))
        for r_, c_ in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)):
            a[:, r_, c_] = a[:, c_, r_] = -np.einsum("gv,gv->g", wd[r_], d[c_])
        a += w.sum(axis=1)[:, None, None] * np.eye(3)[None]
        b = w @ frame.centres - np.einsum("igv,gv->gi", wd, dc)
        a += np.eye(3)[None] * 1e-9 * np.trace(a, axis1=1, axis2=2)[:, None, None]
        covariance = _inverse3(a)
        points = np.einsum("gij,gj->gi", covariance, b)
    return points, covariance


def test_the_triangulation_entry_by_entry_is_the_stacked_one_to_the_bit():
    views, _ = _crowd_views(seed=2)
    frame = _Frame(views, AssociateOptions(pixel_sigma=1.5))
    seeds = frame.pair_candidates()
    grown = frame.grow(seeds, *frame.triangulate(seeds))
    assert len(seeds) > 1000 and np.sum(grown >= 0) > 2.5 * len(grown)
    for members in (seeds, grown):
        points, covariance = frame.triangulate(members)
        want = _stacked_triangulation(frame, members)
        assert points.tobytes() == want[0].tobytes() and covariance.tobytes() == want[1].tobytes()
        again = frame.triangulate(members, points + 0.01)
        want = _stacked_triangulation(frame, members, points + 0.01)
        assert again[0].tobytes() == want[0].tobytes() and again[1].tobytes() == want[1].tobytes()


def test_the_record_of_verified_groups_finds_the_last_equal_row_even_where_hashes_collide(monkeypatch):
    from rigsfm.associate import rows as member_rows

    rng = np.random.default_rng(6)
    rows = np.where(rng.random((3000, 6)) < 0.5, rng.integers(0, 40, (3000, 6)), -1)
    chunks = [rows[:1000], rows[1000:1800], rows[1800:]]  # repeated rows within and across chunks
    members = np.r_[rows[rng.integers(0, 3000, 500)], np.c_[np.full(500, 99), rows[:500, 1:]]]  # the last: none
    last = {r.tobytes(): i for i, r in enumerate(rows)}  # the last of equal rows
    want = np.array([last.get(m.tobytes(), -1) for m in members])
    assert (want >= 0).sum() == 500 and len(last) < 2900
    for hashes in (member_rows._row_hashes, lambda m: np.zeros(len(m), dtype=np.uint64)):  # the second: all collide
        monkeypatch.setattr(member_rows, "_row_hashes", hashes)
        record = member_rows._Verified()
        for chunk in chunks:
            record.add(chunk, (chunk[:, 0].astype(float),))
        np.testing.assert_array_equal(record.starts, np.cumsum([0] + [len(c) for c in chunks]))
        np.testing.assert_array_equal(record.find(members), want)


def test_distinct_member_rows_are_numpy_s_unique_rows_first_occurrences_and_inverse():
    from rigsfm.associate.rows import _unique_inverse, _unique_rows

    rng = np.random.default_rng(7)
    for top in (3, 200, 70_000, 2 ** 40):  # keys of one 16-bit digit to several 64-bit keys of four digits each
        rows = np.where(rng.random((4000, 9)) < 0.4, rng.integers(0, top, (4000, 9)), -1)
        rows = np.r_[rows, rows[rng.integers(0, 4000, 3000)]]  # repeated rows: their first occurrence
        want, first, inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
        got, at = _unique_rows(rows)
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(at, first)
        distinct, rank = _unique_inverse(rows)
        np.testing.assert_array_equal(distinct, want)
        np.testing.assert_array_equal(rank, inverse.ravel())


def test_a_disc_past_the_grid_s_edge_holds_none_of_the_edge_s_points():
    rng = np.random.default_rng(8)
    points = rng.uniform(0, 400, (300, 2))
    grid = CountGrid(points)
    # beyond each side by more than the radius: clipped, their boxes would be the edge cells, which hold points
    far = np.r_[np.c_[rng.uniform(420, 900, 200), rng.uniform(0, 400, 200)],
                np.c_[rng.uniform(0, 400, 200), rng.uniform(-500, -20, 200)]]
    radius = np.full(len(far), 15.0)
    assert not grid.any_within(far, radius).any()
    assert not len(grid.pairs_within(far, radius)[0])
    near = np.clip(far, -10.0, 410.0)  # just past the edge: within reach of its points
    assert grid.any_within(near, np.full(len(near), 40.0)).mean() > 0.5


def test_the_projected_covariance_column_by_column_is_the_broadcast_one_to_the_bit():
    views, _ = _crowd_views(seed=3)
    view = views[0]
    rng = np.random.default_rng(3)
    points = view.centre + rng.normal(0, 3.0, (2000, 3)) + 12.0 * view.r[2]
    root = rng.normal(0, 0.2, (2000, 3, 3))
    covariance = root @ np.transpose(root, (0, 2, 1))
    cam = points @ view.r.T + view.t
    z = np.where(np.abs(cam[:, 2]) > 1e-9, cam[:, 2], 1e-9)
    a = (view.k[0, 0] / z)[:, None] * (view.r[0][None] - (cam[:, 0] / z)[:, None] * view.r[2][None])
    b = (view.k[1, 1] / z)[:, None] * (view.r[1][None] - (cam[:, 1] / z)[:, None] * view.r[2][None])
    ca, cb = np.einsum("nij,nj->ni", covariance, a), np.einsum("nij,nj->ni", covariance, b)
    want = np.einsum("ni,ni->n", a, ca), np.einsum("ni,ni->n", b, ca), np.einsum("ni,ni->n", b, cb)
    got = view.projected_covariance(points, covariance)
    assert all(g.tobytes() == w.tobytes() for g, w in zip(got, want))


def test_a_shift_the_frame_rejects_raises_no_warning_and_one_it_keeps_does(caplog):
    """The pairs' starts and the rounds try corrections on copies of the views; only what the frame keeps says the
    run's pose is worse than its band (a rejected start warned: a false alarm on a view the truth had right)."""
    import logging

    from rigsfm.associate.shifts import ViewCorrection, _corrected, _warn_beyond_band

    views, _ = _crowd_views()
    for view in views:
        view.sigma_pose_px = 1.0
    far = ViewCorrection(np.array([[12.0, 0.0]] + [[0.0, 0.0]] * (len(views) - 1)), np.full(len(views), 0.1),
                         np.full(len(views), 1.0), np.full(len(views), 50))
    with caplog.at_level(logging.WARNING, logger="rigsfm.associate.shifts"):
        trial = _corrected(views, far, AssociateOptions(pixel_sigma=1.0))
        assert not caplog.records  # a trial: nothing said yet
        _warn_beyond_band(views)  # the views the frame kept: unshifted
        assert not caplog.records
        _warn_beyond_band(trial)  # had the frame kept the trial
    assert [r.getMessage().split(":")[0] for r in caplog.records] == [views[0].name]
    assert "moves its pixels by 12.0 px, beyond its pose sigma of 1.0 px" in caplog.records[0].getMessage()


def _best_packing(members: np.ndarray, scores: np.ndarray) -> float:
    """The largest summed score of hypotheses sharing no detection, by every subset (a few hypotheses only)."""
    best = 0.0
    for subset in range(1 << len(scores)):
        rows = [k for k in range(len(scores)) if subset >> k & 1]
        used = members[rows][members[rows] >= 0]
        if len(np.unique(used)) == len(used):
            best = max(best, float(scores[rows].sum()))
    return best


def test_the_packing_by_groups_of_conflicts_is_the_best_packing(monkeypatch):
    """The packing's exact branching (each group of conflicting hypotheses) and its MILP (a group too large to
    branch on) both find the largest summed score: random crowded instances, three views of six detections."""
    import rigsfm.associate.packing as packing

    rng = np.random.default_rng(5)
    for trial in range(40):
        n = 14
        members = np.where(rng.random((n, 3)) < 0.7, rng.integers(0, 6, (n, 3)) + 6 * np.arange(3), -1)
        members = members[np.sum(members >= 0, axis=1) >= 2]
        scores = rng.uniform(0.1, 5.0, len(members))
        best = _best_packing(members, scores)
        for steps in (packing.EXACT_STEPS, 0):  # 0: every group goes to the MILP
            monkeypatch.setattr(packing, "EXACT_STEPS", steps)
            chosen = packing._pack(members, scores, 18, 10.0)
            used = members[chosen][members[chosen] >= 0]
            assert len(np.unique(used)) == len(used), trial
            assert abs(scores[chosen].sum() - best) < 1e-9, (trial, steps)
