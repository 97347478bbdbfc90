"""A detection's ray between the two heights, seen from a camera across the crowd (rigsfm.associate.segments)."""

from __future__ import annotations

import numpy as np
import pycolmap

from rigsfm.associate import AssociateOptions
from rigsfm.associate.frame import _Frame
from rigsfm.associate.segments import segment_in_view
from rigsfm.associate.views import View

F, W, H = 1800.0, 812, 617


def _view(name: str, centre: np.ndarray, target: np.ndarray, heads: np.ndarray) -> View:
    """A pinhole narrow camera at ``centre`` aimed at ``target``, detecting ``heads`` exactly."""
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    r = np.stack([right, np.cross(forward, right), forward])
    camera = pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[F, F, W / 2, H / 2])
    k = np.asarray(camera.calibration_matrix())
    view = View(name, k, r, -r @ centre, centre, W, H, camera, np.zeros((0, 2)))
    view.xy, _ = view.project(heads)
    return view


def _facing_pair(head: np.ndarray) -> tuple[View, View]:
    # two rigs 18 m apart across the crowd, cameras 3.5 m up, both aimed at one head 13 m from the first: that
    # camera's ray through the head reaches 1.0 m of height ~19 m away, behind the camera opposite
    a = _view("a", np.array([0.0, 0.0, 3.5]), head, head[None])
    b = _view("b", np.array([18.0, 0.0, 3.5]), head, head[None])
    return a, b


def test_a_segment_passing_behind_the_camera_opposite_keeps_its_front_part():
    head = np.array([13.0, 0.0, 1.8])
    a, b = _facing_pair(head)
    ray = head - a.centre
    low = a.centre + ray * (1.0 - a.centre[2]) / ray[2]
    high = a.centre + ray * (2.1 - a.centre[2]) / ray[2]
    assert b.project(low[None])[1][0] < 0 < b.project(high[None])[1][0]  # the far end lies behind b
    start, end, ok = segment_in_view(b, low[None], high[None])
    assert ok[0]
    # b's detection of the head lies on the segment's image, between its ends
    seen = b.xy[0]
    along = np.dot(seen - start[0], end[0] - start[0]) / np.sum((end[0] - start[0]) ** 2)
    normal = np.array([-(end[0] - start[0])[1], (end[0] - start[0])[0]]) / np.linalg.norm(end[0] - start[0])
    assert 0.0 < along < 1.0 and abs(np.dot(seen - start[0], normal)) < 1e-6
    # a segment wholly behind the camera has no image
    behind = np.array([[19.0, 0.0, 1.5]]), np.array([[25.0, 0.0, 1.5]])
    assert not segment_in_view(b, *behind)[2][0]


def test_the_head_between_two_facing_cameras_is_a_candidate_pair():
    head = np.array([13.0, 0.0, 1.8])
    a, b = _facing_pair(head)
    seeds = _Frame([a, b], AssociateOptions(pixel_sigma=1.5)).pair_candidates()
    assert [0, 1] in seeds.tolist()


def _crowd_views(seed: int = 0, heads: int = 120, noise_px: float = 1.0) -> tuple[list[View], np.ndarray]:
    """Five cameras on a ring 18 m across (two of them facing each other), all aimed at a crowd of ``heads`` heads
    at 1.6-1.9 m; each detects every head it sees with ``noise_px`` of noise, and a few false heads."""
    rng = np.random.default_rng(seed)
    points = np.c_[rng.uniform(-4, 4, (heads, 2)), rng.uniform(1.6, 1.9, heads)]
    views = []
    for k, angle in enumerate(np.radians([0, 72, 144, 180, 252])):
        centre = np.array([9 * np.cos(angle), 9 * np.sin(angle), 3.5])
        view = _view(f"v{k}", centre, np.array([0.0, 0.0, 1.7]), points)
        inside = (view.xy[:, 0] >= 0) & (view.xy[:, 0] < W) & (view.xy[:, 1] >= 0) & (view.xy[:, 1] < H)
        xy = view.xy[inside] + rng.normal(0, noise_px, (int(inside.sum()), 2))
        view.xy = np.r_[xy, rng.uniform([0, 0], [W, H], (5, 2))]
        views.append(view)
    return views, points


def _ball_seeds(frame: _Frame) -> np.ndarray:
    """The pair seeds as every detection of j within a disc around each segment (a KD-tree's ball query), then in
    its band: what pair_candidates' line test must not change."""
    from rigsfm.associate.segments import MIN_DEPTH_M, band_sigma, in_front, nearest_on_rays

    lo, hi = frame.options.heights
    seeds = []
    for i in range(len(frame.views)):
        di = np.arange(frame.offsets[i], frame.offsets[i + 1])
        p_lo, p_hi = frame.ray_points(di, lo), frame.ray_points(di, hi)
        for j in range(i + 1, len(frame.views)):
            view_j, ci, cj = frame.views[j], frame.centres[i], frame.centres[j]
            start, end, ok = in_front(view_j, p_lo, p_hi)
            a, b = view_j.project(start)[0], view_j.project(end)[0]
            step = end - start
            t = np.clip(np.nan_to_num(np.sum((cj - start) * step, axis=1) / np.sum(step ** 2, axis=1)), 0.0, 1.0)
            near_j = np.maximum(np.linalg.norm(start + t[:, None] * step - cj, axis=1), MIN_DEPTH_M)
            far_i = np.maximum(np.linalg.norm(start - ci, axis=1), np.linalg.norm(end - ci, axis=1))
            carried = frame.noise[i] * frame.focals[j] * far_i / (frame.focals[i] * near_j)
            reach = frame.options.gate_sigmas * np.sqrt(frame.noise[j] ** 2 + carried ** 2)
            ball = frame.trees[j].query_ball_point((a + b) / 2, np.linalg.norm(b - a, axis=1) / 2 + reach)
            for r in np.flatnonzero(ok):
                for c in frame.tree_index[j][np.asarray(ball[r], dtype=np.int64)]:
                    p, s = frame.uv[c], b[r] - a[r]
                    along = np.clip(np.dot(p - a[r], s) / max(np.dot(s, s), 1e-12), 0.0, 1.0)
                    head = nearest_on_rays(ci, frame.rays[di[r]][None], cj, frame.rays[c][None],
                                           np.linalg.norm(p_lo[r] - ci)[None], np.linalg.norm(p_hi[r] - ci)[None])
                    sigma = band_sigma(head, ci, cj, frame.focals[i], frame.focals[j], frame.noise[i], frame.noise[j])
                    if np.linalg.norm(p - (a[r] + along * s)) <= frame.options.gate_sigmas * sigma[0]:
                        seeds.append((i, di[r], j, c))
    return np.array(sorted(seeds))


def test_pair_seeds_are_the_ball_searches_in_their_bands():
    views, _ = _crowd_views()
    frame = _Frame(views, AssociateOptions(pixel_sigma=1.5))
    seeds = frame.pair_candidates()
    found = np.array(sorted((int(np.flatnonzero(m >= 0)[0]), int(m[m >= 0][0]), int(np.flatnonzero(m >= 0)[1]),
                             int(m[m >= 0][1])) for m in seeds))
    reference = _ball_seeds(frame)
    assert len(reference) > 500  # the crowd fills the bands with chance pairs
    np.testing.assert_array_equal(found, reference)


def test_the_pairs_em_candidates_are_the_ball_searches_within_the_gate():
    from rigsfm.associate.shifts import _epipolar_offsets, _segment_in, _signed_distance

    views, _ = _crowd_views(seed=3)
    frame = _Frame(views, AssociateOptions(pixel_sigma=1.5))
    found = {(i, j): (d, gi) for i, j, d, gi, *_rest in _epipolar_offsets(frame)}
    total = 0
    for i in range(len(views)):
        di = np.arange(frame.offsets[i], frame.offsets[i + 1])
        for j in range(i + 1, len(views)):
            a, b, ok = _segment_in(frame, i, j, frame.uv[di])
            ok &= np.linalg.norm(b - a, axis=1) > 1e-6
            gate = frame.options.gate_sigmas * np.hypot(frame.noise[i], frame.noise[j])
            ball = frame.trees[j].query_ball_point((a + b) / 2, np.linalg.norm(b - a, axis=1) / 2 + gate)
            ra = np.array([r for r in np.flatnonzero(ok) for _ in ball[r]], dtype=np.int64)
            cb = frame.tree_index[j][np.array([c for r in np.flatnonzero(ok) for c in ball[r]], dtype=np.int64)]
            d, t, _ = _signed_distance(frame.uv[cb], a[ra], b[ra])
            keep = (t > 0) & (t < 1) & (np.abs(d) <= gate)
            total += int(keep.sum())
            np.testing.assert_array_equal(found.get((i, j), (np.zeros(0), None))[0], d[keep])
    assert total > 500


def test_the_pairs_em_heights_are_where_the_rays_meet():
    """Each candidate's height in the pairs' EM is where its ray meets i's: a true pair's is its head's height (exact
    detections), and the finite-difference gradient predicts the height under a shift of either view."""
    from rigsfm.associate.shifts import _epipolar_offsets

    views, points = _crowd_views(seed=1, noise_px=0.0)
    options = AssociateOptions(pixel_sigma=1.5)
    pairs = _epipolar_offsets(_Frame(views, options))
    d = np.concatenate([p[2] for p in pairs])
    height = np.concatenate([p[6] for p in pairs])
    true = np.abs(d) < 1e-6  # exact detections: a true pair lies on its segment, a chance one almost never
    assert true.sum() > 300 and (~true).sum() > 300
    gap = np.min(np.abs(height[true][:, None] - points[None, :, 2]), axis=1)
    assert np.max(gap) < 1e-6, np.max(gap)
    # chance candidates' rays meet i's anywhere along the segment
    assert np.mean((height[~true] < 1.55) | (height[~true] > 1.95)) > 0.3
    # the heights under a shift of view 3 (i in its pairs with 4, j in the others'), against the linearised ones
    step = np.array([0.6, -0.4])
    views[3].shift_px = step
    shifted = {(p[0], p[1]): p for p in _epipolar_offsets(_Frame(views, options))}
    checked, close = 0, 0
    for i, j, d0, grad_i, grad_j, _gate, h0, grad_h, _per_px in pairs:
        if 3 not in (i, j) or (i, j) not in shifted:
            continue
        x = np.r_[step, 0.0, 0.0] if i == 3 else np.r_[0.0, 0.0, step]
        # the shift moves some candidates out of the band and others in: each predicted one against the nearest
        # after the shift (distance in px, height in cm)
        after = shifted[(i, j)]
        predicted = np.c_[d0 + np.c_[grad_i, grad_j] @ x, 100 * (h0 + grad_h @ x)]
        gap = np.min(np.linalg.norm(predicted[:, None] - np.c_[after[2], 100 * after[6]][None], axis=2), axis=1)
        checked += len(gap)
        close += int(np.sum(gap < 0.2))
    assert checked > 200 and close > 0.95 * checked, (close, checked)


def test_the_pairs_em_with_heights_finds_shifts_put_into_the_views():
    """Each view's detections moved by a few pixels: the pairs' EM with the candidates' heights, annealed from the
    run's poses and three draws, finds the shifts. The distances alone find them here too: where the heights' start
    wins (a crowd whose chance pairs leave the distances' EM in another optimum) is measured in benchmarks/README.md,
    not tested."""
    from rigsfm.associate.shifts import pairwise_view_shifts

    views, _ = _crowd_views(seed=2, heads=300)
    put = np.random.default_rng(12).normal(0.0, 4.0, (len(views), 2))
    for view, shift in zip(views, put):
        view.xy = view.xy + shift
        view.sigma_pose_px = 3.5
    options = AssociateOptions(pixel_sigma=1.5)
    correction, gain = pairwise_view_shifts(_Frame(views, options), options, heights=True)
    assert gain > 0
    assert np.max(np.linalg.norm(correction.shift_px - put, axis=1)) < 1.5, correction.shift_px


def test_no_segment_or_no_detection_gives_no_candidate():
    from rigsfm.associate.segments import near_segments

    points, none = np.array([[10.0, 10.0]]), np.zeros((0, 2))
    rows, near = near_segments(points, none, np.zeros(0), none, none, np.zeros(0))
    assert rows.shape == near.shape == (0,)
    rows, near = near_segments(none, points, np.ones(1), points, points, np.ones(1))
    assert rows.shape == near.shape == (0,)
