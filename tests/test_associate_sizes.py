"""The detections' apparent head radii as evidence of depth (frame.py's size term)."""

from __future__ import annotations

import copy

import numpy as np
from test_associate_segments import _crowd_views

from rigsfm.associate import AssociateOptions
from rigsfm.associate.frame import _Frame

HEAD_M = 0.11


def _with_radii(views, points, noise: float, seed: int = 0) -> list[np.ndarray]:
    """Each view's detections given f R / distance of the head they are (a false one: a random head's radius), with
    ``noise`` relative error; returns per view the true head of each detection (-1: false)."""
    rng = np.random.default_rng(seed)
    owners = []
    for view in views:
        uv, _ = view.project(points)
        dist = np.linalg.norm(points - view.centre[None], axis=1)
        gap = np.linalg.norm(view.xy[:, None] - uv[None], axis=2)
        owner = np.where(gap.min(axis=1) < 5.0, gap.argmin(axis=1), -1)
        radius = view.focal * HEAD_M / dist[np.where(owner >= 0, owner, rng.integers(0, len(points), len(owner)))]
        view.radius_px = radius * np.exp(noise * rng.normal(size=len(radius)))
        owners.append(owner)
    return owners


def test_the_size_term_sets_right_pairs_above_chance_pairs_at_other_depths():
    views, points = _crowd_views(seed=3, heads=150)
    owners = _with_radii(views, points, noise=0.03)
    options = AssociateOptions(pixel_sigma=1.5, detection_probability=0.8, height_prior=(1.75, 0.1),
                               head_radius_m=HEAD_M, size_noise=0.05, head_radius_spread=0.05)
    frame = _Frame(views, options)
    members, points3, covariance, _ = frame.hypotheses()
    owner = np.concatenate(owners)
    ids = np.where(members >= 0, owner[np.maximum(members, 0)], -2)
    pair = np.sum(members >= 0, axis=1) == 2
    first = np.array([row[row != -2][0] for row in ids])
    right = pair & (first >= 0) & np.all((ids == -2) | (ids == first[:, None]), axis=1)
    wrong = pair & ~right & np.all((ids == -2) | (ids >= 0), axis=1)  # two real heads of different persons
    assert right.sum() > 30 and wrong.sum() > 30
    size = frame.size_log_ratio(members, points3, covariance)
    assert np.median(size[right]) > np.median(size[wrong]) + 0.5
    # the wrong pairs whose point lies far from either head's depth are the ones the term sets apart
    with_sizes = frame.score(members, points3, covariance)
    plain = copy.copy(frame)
    plain.log_radius = None
    without = frame.score(members, points3, covariance) - size
    np.testing.assert_allclose(plain.score(members, points3, covariance), without)
    assert np.mean(with_sizes[right]) - np.mean(with_sizes[wrong]) > np.mean(without[right]) - np.mean(without[wrong])


def test_a_frame_without_a_radius_in_every_view_scores_as_before():
    views, points = _crowd_views(seed=4, heads=80)
    options = AssociateOptions(pixel_sigma=1.5, detection_probability=0.8, height_prior=(1.75, 0.1))
    before = _Frame(copy.deepcopy(views), options).hypotheses()
    _with_radii(views, points, noise=0.05)
    views[2].radius_px = None  # one view without radii: the cue is off for the frame
    after = _Frame(views, options).hypotheses()
    for a, b in zip(before, after):
        np.testing.assert_array_equal(a, b)


def test_the_csv_radius_column_reads_back_exactly_frame_by_frame(tmp_path):
    from rigsfm.associate import read_detections

    sizes = {f"rig0{r}/narrow/f{k}.png": (640, 480) for r in (1, 2) for k in (0, 1)}
    path = tmp_path / "heads.csv"
    # frame f0 gives radii (rig02's image analysed, empty); frame f1 leaves them empty: its size cue is off
    path.write_text("image,x,y,score,radius\nrig01/narrow/f0.png,10.5,20.25,0.9,12.125\nrig02/narrow/f0.png,,,,\n"
                    "rig01/narrow/f0.png,100,200,,0.1\nrig01/narrow/f1.png,1,2,,\nrig02/narrow/f1.png,3,4,,\n")
    detections = read_detections(path, sizes, set(sizes))
    np.testing.assert_array_equal(detections.images["rig01/narrow/f0.png"].radius, [12.125, 0.1])
    assert detections.images["rig01/narrow/f0.png"].rows.tolist() == [2, 4]
    empty = detections.images["rig02/narrow/f0.png"].radius
    assert empty is not None and empty.shape == (0,)
    assert detections.images["rig01/narrow/f1.png"].radius is None
    assert detections.images["rig02/narrow/f1.png"].radius is None
    path.write_text("image,x,y\nrig01/narrow/f0.png,10.5,20.25\n")  # no column: no radii
    assert read_detections(path, sizes, set(sizes)).images["rig01/narrow/f0.png"].radius is None
