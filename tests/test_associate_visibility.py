"""Each view's detection probability from the crowd's occlusion (rates.Occlusion, the score's visibility term)."""

from __future__ import annotations

import dataclasses

import numpy as np
from test_associate_segments import _crowd_views

from rigsfm.associate import AssociateOptions
from rigsfm.associate.frame import _Frame
from rigsfm.associate.rates import Occlusion, fit_occlusion, occluders

HEIGHTS = (1.75, 0.1)


def test_a_view_that_persons_in_front_hide_is_no_miss():
    views, points = _crowd_views(seed=0, heads=120)
    x = points[np.argmin(np.linalg.norm(points[:, :2], axis=1))]  # the head nearest the crowd's middle
    options = AssociateOptions(pixel_sigma=1.5, detection_probability=0.7, height_prior=HEIGHTS)
    frame = _Frame(views, options)
    # its detections in views 0 and 1 only: views 2-4 see it and hold no member
    row = np.full((1, len(views)), -1, dtype=np.int64)
    for v in (0, 1):
        uv, _ = views[v].project(x[None])
        own = frame.uv[frame.offsets[v]:frame.offsets[v + 1]]
        row[0, v] = frame.offsets[v] + int(np.argmin(np.linalg.norm(own - uv, axis=1)))
    point, covariance = frame.triangulate(row)
    seen = [v for v in range(2, len(views)) if views[v].inside(*views[v].project(point))[0]]
    assert len(seen) >= 2
    # the crowd's footprint a disc just in front of the point towards view 3 (persons there stand above its ray), or
    # a disc far from every ray: the same members, the same point
    towards = (frame.centres[3, :2] - x[:2]) / np.linalg.norm(frame.centres[3, :2] - x[:2])
    hidden = Occlusion(q=0.9, a=3.0, centre=tuple(x[:2] + towards), radius_m=0.9, heights=HEIGHTS)
    clear = dataclasses.replace(hidden, centre=(100.0, 100.0))
    depth = np.array([occluders(hidden, frame.centres[v][None], point)[0] for v in range(len(views))])
    assert depth[3] > 0.1 and depth[0] == depth[1] == 0.0  # view 3 hidden, the members' views clear
    scores = {}
    for name, model in (("hidden", hidden), ("clear", clear)):
        frame.options = dataclasses.replace(options, occlusion=model)
        scores[name] = float(frame.score(row, point, covariance)[0])
        # the floor's bound (q per member, no misses) holds the full score
        assert frame.score(row, point, covariance, misses=False)[0] >= scores[name]
    # view 3's miss costs log(1 - p_3) > log(1 - q): the group scores higher where the view is hidden
    assert scores["hidden"] > scores["clear"] + 1.0
    frame.options = dataclasses.replace(options, occlusion=hidden, visibility=False)
    plain = float(frame.score(row, point, covariance)[0])
    frame.options = dataclasses.replace(options, occlusion=clear, visibility=False)
    assert float(frame.score(row, point, covariance)[0]) == plain  # one probability for every view: no difference


def test_the_fit_recovers_the_occlusion_of_simulated_detections():
    views, points = _crowd_views(seed=1, heads=400)
    centres = np.array([v.centre for v in views])
    middle = np.median(points[:, :2], axis=0)
    radius = float(np.percentile(np.linalg.norm(points[:, :2] - middle, axis=1), 99))
    truth = Occlusion(q=0.85, a=2.0, centre=(float(middle[0]), float(middle[1])), radius_m=radius, heights=HEIGHTS)
    rng = np.random.default_rng(0)
    members = np.full((len(points), len(views)), -1, dtype=np.int64)
    for v, view in enumerate(views):
        uv, z = view.project(points)
        inside = np.flatnonzero(view.inside(uv, z))
        p = truth.probability(np.repeat(centres[v][None], len(inside), axis=0), points[inside])
        members[inside[rng.random(len(inside)) < p], v] = 0
    confident = np.ones(len(points), dtype=bool)
    fitted = fit_occlusion(views, centres, members, points, confident, HEIGHTS)
    assert fitted is not None
    assert fitted.centre == truth.centre and fitted.radius_m == truth.radius_m
    assert abs(fitted.q - 0.85) < 0.04 and abs(fitted.a - 2.0) < 0.6, fitted
    # without occlusion in the detections, none in the fit
    members[:] = -1
    for v, view in enumerate(views):
        uv, z = view.project(points)
        inside = np.flatnonzero(view.inside(uv, z))
        members[inside[rng.random(len(inside)) < 0.85], v] = 0
    flat = fit_occlusion(views, centres, members, points, confident, HEIGHTS)
    assert flat is not None and abs(flat.q - 0.85) < 0.04 and flat.a < 0.5, flat


def test_the_occlusion_is_fitted_on_a_self_calibrating_frame_and_not_carried():
    """A carried frame counts one probability for every view: with the frame before's occlusion its lens per
    (hypothesis, view) tripled a carried frame's CPU (0.27 -> 0.85 s on 8 views) for no gain in pair F1
    (benchmarks/README.md, twenty-second pass)."""
    from rigsfm.associate.solve import associate_views

    views, _ = _crowd_views(seed=2, heads=150)
    options = AssociateOptions(pixel_sigma=1.0)
    first = associate_views(views, options)
    assert first.occlusion is not None  # fitted with the crowd's rates
    later, _ = _crowd_views(seed=2, heads=150, noise_px=1.2)
    carried = associate_views(later, options, carried=True, earlier=first)
    assert carried.occlusion is None and carried.detection_probability == first.detection_probability
