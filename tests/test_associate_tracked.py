"""A carried frame looks for the frame before's persons where they were (rigsfm.associate.tracked)."""

from __future__ import annotations

import copy
import dataclasses
import itertools

import numpy as np
from test_associate_segments import H, W, _view

from rigsfm.associate import AssociateOptions
from rigsfm.associate.frame import _Frame
from rigsfm.associate.solve import associate_views
from rigsfm.associate.tracked import row_pairs, seen_before

OPTIONS = AssociateOptions(pixel_sigma=1.5, appearance=False, detection_probability=0.8)


def _crowd(points: np.ndarray, seed: int) -> tuple[list, list[np.ndarray]]:
    """Five cameras on a ring 18 m across aimed at the heads ``points``; each detects every head it sees with 1 px
    of noise, misses 10 %, and adds a few false heads. Returns the views and, per view, each detection's head (-1:
    false)."""
    rng = np.random.default_rng(seed)
    views, ids = [], []
    for k, angle in enumerate(np.radians([0, 72, 144, 180, 252])):
        centre = np.array([9 * np.cos(angle), 9 * np.sin(angle), 3.5])
        view = _view(f"rig0{k}/narrow/frame.png", centre, np.array([0.0, 0.0, 1.7]), points)
        inside = (view.xy[:, 0] >= 0) & (view.xy[:, 0] < W) & (view.xy[:, 1] >= 0) & (view.xy[:, 1] < H)
        inside &= rng.random(len(points)) > 0.1
        xy = view.xy[inside] + rng.normal(0, 1.0, (int(inside.sum()), 2))
        view.xy = np.r_[xy, rng.uniform([0, 0], [W, H], (5, 2))]
        views.append(view)
        ids.append(np.r_[np.flatnonzero(inside), np.full(5, -1)])
    return views, ids


def _pair_precision_recall(members: np.ndarray, ids: list[np.ndarray]) -> tuple[float, float]:
    found, right = set(), 0
    for row in members:
        dets = [(v, int(i)) for v, i in enumerate(row) if i >= 0]
        for a, b in itertools.combinations(dets, 2):
            found.add((a, b))
            right += ids[a[0]][a[1]] >= 0 and ids[a[0]][a[1]] == ids[b[0]][b[1]]
    true = {}
    for v, per in enumerate(ids):
        for i, p in enumerate(per):
            if p >= 0:
                true.setdefault(int(p), []).append((v, i))
    pairs = sum(len(m) * (len(m) - 1) // 2 for m in true.values())
    return right / max(len(found), 1), right / max(pairs, 1)


def _walked(seed: int = 3, heads: int = 120) -> tuple[np.ndarray, np.ndarray]:
    """A crowd of heads at 1.6-1.9 m and the same heads a tenth of a second later (each walked ~10 cm)."""
    rng = np.random.default_rng(seed)
    before = np.c_[rng.uniform(-4, 4, (heads, 2)), rng.uniform(1.6, 1.9, heads)]
    heading = rng.uniform(0, 2 * np.pi, heads)
    after = before + np.c_[0.1 * np.cos(heading), 0.1 * np.sin(heading), np.zeros(heads)]
    return before, after


def test_a_carried_frame_finds_the_walked_crowd_from_the_frame_before_with_fewer_pair_seeds():
    before, after = _walked()
    first_views, _ = _crowd(before, seed=1)
    first = associate_views(first_views, OPTIONS, carried=True)
    views, ids = _crowd(after, seed=2)
    full_options = dataclasses.replace(OPTIONS, walk_m=None)
    tracked = associate_views(copy.deepcopy(views), OPTIONS, carried=True, earlier=first)
    full = associate_views(copy.deepcopy(views), full_options, carried=True, earlier=first)
    assert len(full) > 60
    # as right as the full search, against the truth
    tp, tr = _pair_precision_recall(tracked.members, ids)
    fp, fr = _pair_precision_recall(full.members, ids)
    assert tp >= fp - 0.02 and tr >= fr - 0.02, (tp, tr, fp, fr)
    # while searching the pairs among the detections the earlier persons leave only
    earlier = (first.points, first.covariances, seen_before(first.views, first.members, [v.name for v in views]))
    seeded = _Frame(copy.deepcopy(views), OPTIONS, earlier=earlier)
    everything = _Frame(copy.deepcopy(views), OPTIONS)
    seeded.hypotheses(), everything.hypotheses()
    assert seeded._seeds is not None and everything._seeds is not None
    assert len(seeded._seeds) < 0.5 * len(everything._seeds)


def test_persons_found_again_in_two_views_only_leave_their_detections_to_the_pair_search():
    """A person found again in two views only is the frame before's wrong person as often as not: it competes in the
    packing, but its detections stay in the pair search (held, they hid the right pairs from it)."""
    before, after = _walked()
    first = associate_views(_crowd(before, seed=1)[0], OPTIONS, carried=True)
    two = np.sum(first.members >= 0, axis=1) == 2
    assert two.sum() >= 5
    views, _ = _crowd(after, seed=2)
    earlier = (first.points[two], first.covariances[two],
               seen_before(first.views, first.members[two], [v.name for v in views]))
    seeded = _Frame(views, OPTIONS, earlier=earlier)
    members, _, _, scores = seeded.hypotheses()
    assert len(members) > 60 and seeded._among is not None
    assert seeded._scored is not None and np.isfinite(seeded._scored[0]).sum() >= 5  # found again, scored
    # what the pair search was not given: only detections of persons found again in three or more views
    confident = members[(np.sum(members >= 0, axis=1) >= 3) & (scores > OPTIONS.self_calibration_min_score)]
    held = np.flatnonzero(~seeded._among)
    assert np.isin(held, confident[confident >= 0]).all(), np.setdiff1d(held, confident)


def test_earlier_persons_nowhere_near_leave_the_full_search():
    _, after = _walked(seed=5)
    views, _ = _crowd(after, seed=6)
    first = associate_views(copy.deepcopy(views), OPTIONS, carried=True)
    away = dataclasses.replace(first, points=first.points + np.array([100.0, 0.0, 0.0]))
    tracked = associate_views(copy.deepcopy(views), OPTIONS, carried=True, earlier=away)
    full = associate_views(copy.deepcopy(views), dataclasses.replace(OPTIONS, walk_m=None), carried=True,
                           earlier=away)
    assert len(full) > 60
    np.testing.assert_array_equal(tracked.members, full.members)
    np.testing.assert_array_equal(tracked.points, full.points)


def test_an_earlier_person_is_looked_for_in_the_cameras_it_was_seen_by():
    earlier = ["rig01/narrow/frame0000.png", "rig02/narrow/frame0000.png", "rig03/narrow/frame0000.png"]
    members = np.array([[0, -1, 4], [-1, 2, 3]])
    # the next frame's images of the same cameras, one camera missing and in another order
    now = ["rig03/narrow/frame0001.png", "rig01/narrow/frame0001.png", "rig04/narrow/frame0001.png"]
    np.testing.assert_array_equal(seen_before(earlier, members, now), [[True, True, False], [True, False, False]])
    rows = np.array([[3, -1, 5, 7]])
    assert sorted(map(tuple, row_pairs(rows).tolist())) == [(-1, -1, 5, 7), (3, -1, -1, 7), (3, -1, 5, -1)]


def _tracked_frame(seed: int) -> _Frame:
    """A carried frame of a walking crowd, seeded by the frame before's persons."""
    before, after = _walked(seed=seed)
    first = associate_views(_crowd(before, seed=seed + 1)[0], OPTIONS, carried=True)
    views, _ = _crowd(after, seed=seed + 2)
    earlier = (first.points, first.covariances, seen_before(first.views, first.members, [v.name for v in views]))
    return _Frame(views, OPTIONS, earlier=earlier)


def test_the_second_pass_of_a_tracked_frame_checks_the_first_pass_groups_on_the_free_detections():
    frame = _tracked_frame(seed=7)
    grown = frame.hypotheses()[0]
    free = np.ones(int(frame.offsets[-1]), dtype=bool)
    free[grown[0][grown[0] >= 0]] = False  # one person's detections taken
    free[grown[-1][grown[-1] >= 0]] = False
    again = frame.hypotheses(free)[0]
    assert len(again) > 20
    assert np.all((again < 0) | free[np.maximum(again, 0)])
    # each within a first-pass group (its taken members, and any its check drops, left out): no pair grown again
    within = (again[:, None, :] < 0) | (again[:, None, :] == grown[None, :, :])
    assert np.all(np.any(np.all(within, axis=2), axis=1))


def test_a_tracked_frame_s_groups_keep_the_scores_they_took_before_the_pairs():
    frame = _tracked_frame(seed=7)
    members, points, covariance, scores = frame.hypotheses()
    assert frame._scored is not None and np.isfinite(frame._scored[0]).sum() > 50  # the tracked groups' own
    np.testing.assert_array_equal(scores, frame.score(members, points, covariance, floor=OPTIONS.min_score))


def test_the_seeds_gate_scores_each_seed_with_its_own_residuals():
    """The gate hands the score the residuals it computed for its own test: the seeds it keeps are those that a
    fresh score of each (its residuals computed anew) keeps, with the same points."""
    frame = _tracked_frame(seed=7)
    frame.hypotheses()  # the pair seeds, among what the tracked persons leave
    seeds = frame._seeds
    assert seeds is not None and len(seeds) > 100
    floor = -4.0
    members, points, covariance = frame._gated(seeds, floor)
    at, at_covariance = frame.triangulate(seeds)
    lo, hi = OPTIONS.heights
    ok = (at[:, 2] >= lo) & (at[:, 2] <= hi) & np.all(
        np.nan_to_num(frame.residuals(seeds, at), nan=0.0) <= OPTIONS.member_gate ** 2, axis=1)
    scores = frame.score(seeds[ok], at[ok], at_covariance[ok], misses=False, floor=floor)
    assert 0 < len(members) < ok.sum()  # the floor decides for some
    np.testing.assert_array_equal(members, seeds[ok][scores > floor])
    np.testing.assert_array_equal(points, at[ok][scores > floor])


def test_a_tracked_frame_grows_once_and_finds_the_persons_two_rounds_find(monkeypatch):
    before, after = _walked(seed=11)
    first = associate_views(_crowd(before, seed=12)[0], OPTIONS, carried=True)
    views, _ = _crowd(after, seed=13)
    grown = {}

    def associate(rounds: int | None):
        original, growth = _Frame._grown_from, _Frame.grow
        rows = []

        def grown_from(self, *args, **kwargs):
            if rounds is not None:
                kwargs["rounds"] = rounds
            return original(self, *args, **kwargs)

        def grow(self, members, *args, **kwargs):
            rows.append(len(members))
            return growth(self, members, *args, **kwargs)

        with monkeypatch.context() as patch:
            patch.setattr(_Frame, "_grown_from", grown_from)
            patch.setattr(_Frame, "grow", grow)
            result = associate_views(copy.deepcopy(views), OPTIONS, carried=True, earlier=first)
        grown[rounds] = sum(rows)
        return result

    once, twice = associate(None), associate(2)
    assert len(twice) > 60
    np.testing.assert_array_equal(once.members, twice.members)
    np.testing.assert_array_equal(once.points, twice.points)
    np.testing.assert_array_equal(once.scores, twice.scores)
    assert grown[None] < 0.8 * grown[2]  # the growth's second round is what it saves


class _Posed:
    """A narrow image as associate_frames reads one from a run: its name, camera and pose."""

    def __init__(self, view) -> None:
        import pycolmap

        self.name, self.has_pose, self.camera = view.name, True, view.camera
        self._pose = pycolmap.Rigid3d(pycolmap.Rotation3d(view.r), view.t)
        self._centre = view.centre

    def cam_from_world(self):
        return self._pose

    def projection_center(self):
        return self._centre


def _recording(frames: list[np.ndarray], shifts: np.ndarray, sigma_px: float):
    """A recording of static cameras (five on a ring) seeing the heads of each frame, every view's detections moved
    by its camera's ``shifts`` (a pose error the run's bands, ``sigma_px`` per view, allow): the run's model, the
    detections and per frame, per view, each detection's head (-1: false)."""
    from rigsfm.associate import from_arrays
    from rigsfm.associate.pipeline import RunModel
    from rigsfm.associate.views import BAND_Z

    images, points, ids = {}, {}, []
    for k, heads in enumerate(frames):
        views, frame_ids = _crowd(heads, seed=10 + k)
        for view, shift in zip(views, shifts):
            name = view.name.replace("frame.png", f"frame{k:04d}.png")
            images[name] = _Posed(dataclasses.replace(view, name=name))
            points[name] = view.xy + shift
        ids.append(frame_ids)
    bands = {(a, b): BAND_Z * np.sqrt(2) * sigma_px for a, b in itertools.permutations(images, 2)
             if a.split("/")[-1] == b.split("/")[-1]}
    return RunModel(images, bands, set(images), {"frame": "floor"}), from_arrays(points), ids


def test_a_frame_too_sparse_to_correct_its_views_is_associated_again_with_the_shifts_of_the_frames_after():
    """The recording starts with a few persons, too few for the crowd to correct the views, then fills: the later
    frames find each camera's shift, and the first frame is associated again with them (a static camera's pose
    error is the same in every frame), which the frame alone cannot do."""
    from rigsfm.associate import associate_frames

    rng = np.random.default_rng(5)
    full, _ = _walked(seed=4, heads=300)
    sparse = np.c_[rng.uniform(-4, 4, (12, 2)), rng.uniform(1.6, 1.9, 12)]
    walked = full + np.c_[rng.normal(0, 0.1, (300, 2)), np.zeros(300)]
    shifts = np.random.default_rng(12).normal(0.0, 4.0, (5, 2))
    model, detections, ids = _recording([sparse, full, walked], shifts, sigma_px=3.5)
    options = dataclasses.replace(OPTIONS, detection_probability=None)
    found = associate_frames(model, detections, options)
    alone = associate_frames(model, detections, dataclasses.replace(options, revisit=False))
    # the later frames found the cameras' shifts: the first frame's persons are found with them
    later = np.array([found[1].result.shift_px[v.name] for v in found[1].views])
    assert np.max(np.linalg.norm(later - shifts, axis=1)) < 1.0, later
    first = np.array([found[0].result.shift_px[v.name] for v in found[0].views])
    assert np.max(np.linalg.norm(first - shifts, axis=1)) < 1.0, first
    assert not any(np.any(shift) for shift in alone[0].result.shift_px.values())  # alone: the run's poses
    precision, recall = _pair_precision_recall(found[0].result.members, ids[0])
    before = _pair_precision_recall(alone[0].result.members, ids[0])
    # 1.0 / 1.0 against 0.97 / 0.88 on the run's poses
    assert precision >= before[0] and recall > before[1] + 0.05, (precision, recall, before)
