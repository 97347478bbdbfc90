"""Narrow observations from heads (``rigsfm run --narrow``, where the floor-guided SIFT finds no texture): a crowd
of 3D persons stands off the floor, so the floor warp that matches a painted crowd is wrong for every head, and
SIFT on flat-shaded, view-dependent silhouettes gives chance matches only. Heads themselves are the features:

1. **Head candidates** per narrow image, without a detector's input: heads are round blobs of a known size. In the
   floor frame a pixel's ray meets the head-centre plane (``HEAD_CENTRE_M``) at a distance that gives the radius a
   head of ``HEAD_RADIUS_M`` would have there, where that point lies inside the scene's footprint (the sparse points'
   outline: no head stands behind the farthest structure). OpenCV's Hough circles (on one thread: deterministic)
   search the image in horizontal bands whose expected radii lie within ``BAND_RATIO`` of each other, each band its
   own range of radii (one search over a whole narrow view's range of radii costs far more and gives more false
   circles); each circle is kept when its radius is within ``RADIUS_RATIO`` of the one expected at its centre,
   and its centre is refined to sub-pixel by a circle fitted to the strongest radial edge along 64 rays (trimmed:
   occluded arcs drop out), kept only where the fit moved it little.
2. **Association** of the candidates across the synchronised narrow views: :func:`rigsfm.associate.solve.
   associate_views` (``rigsfm associate``'s library call: candidates inside each pair's band between two heights,
   triangulation, multi-view growth, a global set packing, and the crowd's own correction of each view's pose
   error), on the first adjustment's poses and bands. Only confident persons are kept: ``MIN_GROUP_VIEWS`` views
   or more, a score above ``MIN_GROUP_SCORE`` (four views agreeing on one head are rarely chance: weighed at their
   own noise, these persons held the narrow rotation better than the fewer of three views scoring above 2).
3. **Observations**: each person is a track (its head centres), without the views seen in fewer than
   ``MIN_VIEW_PERSONS`` confident persons (the association corrects a view's pose from that many only: a view below
   it was searched at a pose whose error may exceed its band, and its few matches are chance as often as not; a
   person left in fewer than ``MIN_GROUP_VIEWS`` views is dropped); none is held out of the adjustment (a person adds
   one match to a pair, so a pair's held-out persons never reached the held-out check's minimum, and holding every
   fifth out only cost observations: the self-check's head verdicts, step 5, check the heads). Its pairs become
   :class:`rigsfm.run.narrow.observations.PairMatches`, so the tracks and the second adjustment are the floor
   matches' own.
4. **Decision** (``auto``): used when at least ``MIN_HEAD_GROUPS`` confident persons are found; a featureless view
   gives no circles at head size that three views agree on.
5. **Self-check**: a pair whose SIFT self-check found too few matches gets a verdict from its head matches against
   the delivered epipolar lines, when it holds ``MIN_HEAD_MATCHES``: ``ok`` when their 95th percentile is within
   the band plus ``HEAD_NOISE_PX`` (the two head centres' localisation noise). Its matches are every person the
   association finds in two or more views scoring above ``CHECK_MIN_SCORE`` (more likely one person than chance),
   not only the adjustment's confident ones: a wrong match costs the adjustment a biased track, but the check only
   one distance, which the association's band bounds (it admits a match only inside it); the confident persons
   alone leave many pairs of a crowd under ``MIN_HEAD_MATCHES``.
6. **Noise**: a head centre errs far more than a SIFT keypoint (a Hough circle and a silhouette's fitted edge, not a
   texture's corner), so its observations enter the second adjustment at their own noise
   (:class:`rigsfm.run.adjustment.problem.JointProblem`'s ``point_sigmas``), not at the images' pooled one: estimated
   from the confident persons themselves, their centres' residuals about the association's points with each view's
   pose correction removed (:func:`head_sigma`; ``HEAD_PIXEL_SIGMA`` where too few).
7. **Timing**: on a recording of three frames or more (without ``--frame-offsets FILE``), a rig whose heads meet
   the other views' persons best a frame away (:mod:`rigsfm.run.narrow.timing`) is named, and the heads are matched
   again without it: its heads stay out of the adjustment (``FRAMES NOT SYNCHRONISED``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from rigsfm.associate.options import AssociateOptions
from rigsfm.associate.solve import associate_views
from rigsfm.associate.views import View, view_pose_sigmas
from rigsfm.core.conventions import colmap_from_opencv_pixels
from rigsfm.core.geometry import pixel_line_distances
from rigsfm.core.ground import undistort_pixels
from rigsfm.core.image_files import read_image
from rigsfm.core.opencv_threads import one_opencv_thread
from rigsfm.core.polygons import point_in_polygon
from rigsfm.run.checks.guided import overlapping_pairs
from rigsfm.run.narrow.observations import PairMatches

logger = logging.getLogger(__name__)

HEAD_RADIUS_M = 0.1  # a head's radius (a head is about 0.2 m across)
HEAD_CENTRE_M = 1.6  # the plane where the expected radius is computed (heads' centres: ~1.4-1.8 m)
RADIUS_RATIO = (0.7, 1.45)  # a circle's radius against the one expected at its centre
HOUGH_PARAM1 = 50.0  # Canny's upper threshold of the Hough search
HOUGH_PARAM2 = 0.6  # the circles' "perfectness" (HOUGH_GRADIENT_ALT)
HEAD_PIXEL_SIGMA = 1.5  # a head centre's localisation noise per coordinate (px): the association's, and the fallback
MIN_SIGMA_DOF = 20  # residual degrees of freedom the heads' own noise estimate needs (step 6)
MIN_GROUP_VIEWS = 4  # a person enters the adjustment when seen in this many views
MIN_VIEW_PERSONS = AssociateOptions().self_calibration_min_members  # a view's heads enter from this many persons
# ... and scoring above this (log-likelihood ratio against clutter: one person the likelier)
MIN_GROUP_SCORE = 0.0
# The self-check's persons: two views or more, scoring above this (the association's log-likelihood ratio of one
# person against chance detections: above 0, one person is the likelier).
CHECK_MIN_SCORE = 0.0
MIN_HEAD_GROUPS = 12  # confident persons that make the heads usable (auto)
MIN_HEAD_MATCHES = 10  # head matches a pair needs for a self-check verdict
HEAD_NOISE_PX = 2.0 * 1.96 * HEAD_PIXEL_SIGMA / math.sqrt(2.0)  # allowed on top of the band (two centres' noise)
REFINE_RAYS = 64
REMAP_CIRCLES = 256  # circles per remap of the circle fit
MIN_SEARCH_RADIUS_PX = 6.0  # a band whose radii start below this is searched on the image enlarged twice
BAND_RATIO = 1.2  # a search band's largest expected head radius against its smallest
BAND_ROWS = 32  # the strips an image's expected radii are sampled in
FOOTPRINT_QUANTILE = 0.99  # the sparse points nearest the scene's centre that outline where heads can be
FOOTPRINT_MARGIN = 1.1  # that outline enlarged about its centre


@dataclass
class HeadMatches:
    """What the heads gave: per image its candidates, the confident persons, and their pairs."""

    candidates: dict[str, int] = field(default_factory=dict)  # image -> head candidates
    persons: int = 0  # confident persons (>= MIN_GROUP_VIEWS views, score > MIN_GROUP_SCORE)
    pairs: list[PairMatches] = field(default_factory=list)
    # The self-check's head matches per pair: every person in >= 2 views scoring above CHECK_MIN_SCORE (step 5).
    check_pairs: list[PairMatches] = field(default_factory=list)
    # The confident persons' head centres' residuals (px, undistorted) about their association's points, each view's
    # pose correction removed (step 6).
    residuals: list[np.ndarray] = field(default_factory=list)

    @property
    def sigma_px(self) -> float | None:
        """A head centre's noise per coordinate (px) from the confident persons' residuals (step 6); None where they
        leave too few degrees of freedom."""
        return head_sigma(np.concatenate(self.residuals) if self.residuals else np.zeros((0, 2)),
                          self.persons)


def scene_footprint(model: pycolmap.Reconstruction) -> np.ndarray | None:
    """Where on the floor a head can stand (module docstring, step 1): the convex hull (floor-frame x, y) of the
    camera centres and the sparse points but the farthest from their median (stray points), enlarged by
    ``FOOTPRINT_MARGIN`` about its centre; None with too few points. A head beyond every structure the images saw
    in its direction would stand behind it: the rows that look there (the far side of the scene, towards the horizon,
    where the expected radius is a few pixels) hold no head, only the search's most costly and false circles."""
    points = np.array([p.xyz for p in model.points3D.values()], dtype=np.float64).reshape(-1, 3)[:, :2]
    if len(points) < 3:
        return None
    distance = np.linalg.norm(points - np.median(points, axis=0), axis=1)
    points = points[distance <= np.quantile(distance, FOOTPRINT_QUANTILE)]
    centres = np.array([im.projection_center() for im in model.images.values() if im.has_pose],
                       dtype=np.float64).reshape(-1, 3)[:, :2]
    hull = cv2.convexHull(np.r_[points, centres].astype(np.float32), clockwise=False)
    if hull is None or len(hull) < 3:
        return None
    hull = hull.reshape(-1, 2).astype(np.float64)
    centre = hull.mean(axis=0)
    return centre + FOOTPRINT_MARGIN * (hull - centre)


def expected_radius(image: pycolmap.Image, xy: np.ndarray, footprint: np.ndarray | None = None) -> np.ndarray:
    """The radius (px) of a head centred at ``HEAD_CENTRE_M`` seen at raw COLMAP pixels ``xy`` (floor frame);
    NaN where the ray does not reach that plane in front of the camera, or meets it outside ``footprint``
    (:func:`scene_footprint`)."""
    camera = image.camera
    normalised = np.asarray(camera.cam_from_img(np.asarray(xy, dtype=np.float64).reshape(-1, 2)),  # type: ignore[union-attr]
                            dtype=np.float64)
    rays = np.c_[normalised, np.ones(len(normalised))] @ np.asarray(image.cam_from_world().rotation.matrix())
    centre = np.asarray(image.projection_center(), dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (HEAD_CENTRE_M - centre[2]) / rays[:, 2]
        distance = np.where(t > 0, t * np.linalg.norm(rays, axis=1), np.nan)
        if footprint is not None:
            where = centre[None, :2] + np.where(t > 0, t, 0.0)[:, None] * rays[:, :2]
            distance = np.where(point_in_polygon(where, footprint), distance, np.nan)
        return HEAD_RADIUS_M * float(camera.focal_length_x) / distance  # type: ignore[union-attr]


def _refine(gray: np.ndarray, circles: np.ndarray) -> np.ndarray:
    """Circles (OpenCV pixels x, y, r) refined to sub-pixel: per ray from the centre the strongest radial edge
    between 0.6 and 1.4 radii, a circle fitted to the strongest 60 % of them, trimmed twice; a circle keeps its
    Hough centre where too few edges agree or the fit moved it by more than 15 % of its radius. All circles at once
    (a Python loop per circle cost as much as the Hough search)."""
    out = np.asarray(circles, dtype=np.float64).copy()
    if len(out) == 0:
        return out
    smooth = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), 1.0)
    gx, gy = cv2.Sobel(smooth, cv2.CV_32F, 1, 0), cv2.Sobel(smooth, cv2.CV_32F, 0, 1)
    height, width = gray.shape
    angles = np.linspace(0.0, 2.0 * np.pi, REFINE_RAYS, endpoint=False)
    ca, sa = np.cos(angles)[None, :, None], np.sin(angles)[None, :, None]
    x, y, r = out[:, 0, None, None], out[:, 1, None, None], out[:, 2]
    radii = np.linspace(0.6 * r, 1.4 * r, 33, axis=1)[:, None, :]
    px, py = (x + radii * ca).astype(np.float32), (y + radii * sa).astype(np.float32)  # circle x ray x step
    inside = (px >= 0) & (px < width - 1) & (py >= 0) & (py < height - 1)
    radial = np.empty(px.shape, dtype=np.float32)
    for start in range(0, len(out), REMAP_CIRCLES):  # remap's maps hold fewer than 32767 rows
        part = slice(start, start + REMAP_CIRCLES)
        mx, my = px[part].reshape(-1, px.shape[2]), py[part].reshape(-1, px.shape[2])
        radial[part] = np.abs(cv2.remap(gx, mx, my, cv2.INTER_LINEAR).reshape(px[part].shape) * ca +
                              cv2.remap(gy, mx, my, cv2.INTER_LINEAR).reshape(px[part].shape) * sa)
    radial = radial * inside
    k = radial.argmax(axis=2)[:, :, None]
    strength = np.take_along_axis(radial, k, axis=2)[:, :, 0]
    # The edges relative to the Hough centre: the fit's normal equations stay well conditioned.
    ex = np.take_along_axis(px, k, axis=2)[:, :, 0].astype(np.float64) - out[:, 0, None]
    ey = np.take_along_axis(py, k, axis=2)[:, :, 0].astype(np.float64) - out[:, 1, None]
    keep = strength > np.percentile(strength, 40, axis=1, keepdims=True)
    alive = np.ones(len(out), bool)
    fitted = np.zeros((len(out), 3))
    for _ in range(3):
        alive &= keep.sum(axis=1) >= REFINE_RAYS * 3 // 8
        n = np.flatnonzero(alive)
        if len(n) == 0:
            break
        w = keep[n].astype(np.float64)
        a = np.stack([2.0 * ex[n], 2.0 * ey[n], np.ones_like(ex[n])], axis=2)  # circle x ray x 3
        b = ex[n] ** 2 + ey[n] ** 2
        sol = np.linalg.solve(np.einsum("nk,nki,nkj->nij", w, a, a), np.einsum("nk,nki,nk->ni", w, a, b)[:, :, None])
        sol = sol[:, :, 0]
        cr = np.sqrt(np.maximum(sol[:, 2] + sol[:, 0] ** 2 + sol[:, 1] ** 2, 0.0))
        fitted[n] = np.c_[sol[:, :2], cr]
        residual = np.abs(np.hypot(ex[n] - sol[:, :1], ey[n] - sol[:, 1:2]) - cr[:, None])
        median = np.nanmedian(np.where(keep[n], residual, np.nan), axis=1)
        keep[n] &= residual < np.maximum(1.0, 2.5 * median)[:, None]
    moved = np.hypot(fitted[:, 0], fitted[:, 1])
    accept = alive & (moved <= 0.15 * r) & (np.abs(fitted[:, 2] / r - 1) <= 0.15)
    out[accept] = np.c_[fitted[accept, :2] + out[accept, :2], fitted[accept, 2]]
    return out


def search_bands(image: pycolmap.Image, height: int, width: int, footprint: np.ndarray | None = None
                 ) -> list[tuple[int, int, float, float]]:
    """The image's horizontal bands of similar expected head radius (module docstring, step 1): (first row, row after
    the last, smallest, largest expected radius) in OpenCV pixel rows. The image is cut in ``BAND_ROWS`` strips, the
    radius sampled along each strip's middle row, and neighbouring strips joined while their radii stay within
    ``BAND_RATIO`` of each other; strips whose rays do not reach the heads' plane inside ``footprint`` are left out."""
    edges = np.linspace(0.0, float(height), BAND_ROWS + 1)
    middles = 0.5 * (edges[:-1] + edges[1:])
    grid = np.array([[x, y] for y in middles for x in np.linspace(0.0, float(width), 9)], dtype=np.float64)
    expected = expected_radius(image, grid, footprint).reshape(BAND_ROWS, -1)
    expected = np.where(np.isfinite(expected) & (expected > 0), expected, np.nan)
    known = np.isfinite(expected).any(axis=1)
    low, high = np.full(BAND_ROWS, np.nan), np.full(BAND_ROWS, np.nan)
    low[known], high[known] = np.nanmin(expected[known], axis=1), np.nanmax(expected[known], axis=1)
    bands = []
    start = 0
    while start < BAND_ROWS:
        if not known[start]:
            start += 1
            continue
        lo, hi, end = low[start], high[start], start + 1  # strips start..end-1
        while end < BAND_ROWS and known[end] and max(hi, high[end]) <= BAND_RATIO * min(lo, low[end]):
            lo, hi, end = min(lo, low[end]), max(hi, high[end]), end + 1
        bands.append((int(round(edges[start])), int(round(edges[end])), float(lo), float(hi)))
        start = end
    return bands


def detect_heads(image: pycolmap.Image, gray: np.ndarray, footprint: np.ndarray | None = None) -> np.ndarray:
    """Head candidates of one narrow image (module docstring, step 1): N x 3, raw COLMAP pixels x, y and the radius
    (px). ``image``: its pose in the floor frame (metres, z up); ``gray``: its pixels; ``footprint``: where heads
    can stand (:func:`scene_footprint`; None: anywhere)."""
    height, width = gray.shape
    found = [np.zeros((0, 3))]
    for top, bottom, lo, hi in search_bands(image, height, width, footprint):
        low, high = RADIUS_RATIO[0] * lo, RADIUS_RATIO[1] * hi
        if high < 4.0 or low > 0.5 * min(width, height):
            continue
        # The band's rows and a head's radius around them: its circles whose centres lie in the band are whole.
        pad = int(math.ceil(high)) + 2
        first, last = max(0, top - pad), min(height, bottom + pad)
        circles = _hough(gray[first:last], low, high)
        circles[:, 1] += first
        found.append(circles[(circles[:, 1] >= top - 0.5) & (circles[:, 1] < bottom - 0.5)])
    circles = np.concatenate(found)
    xy = colmap_from_opencv_pixels(circles[:, :2])
    with np.errstate(invalid="ignore"):
        ratio = circles[:, 2] / expected_radius(image, xy, footprint)
    keep = (ratio >= RADIUS_RATIO[0]) & (ratio <= RADIUS_RATIO[1])
    return np.c_[xy[keep], circles[keep, 2]]


def _hough(gray: np.ndarray, low: float, high: float) -> np.ndarray:
    """Circles of radius ``low``-``high`` px in ``gray``, refined (:func:`_refine`): N x 3, its OpenCV pixels x, y
    and the radius."""
    # Small heads are searched on the image enlarged twice: the Hough gradient misses most circles below ~6 px (a
    # band of larger ones enlarged costs 4x the CPU for more false circles).
    factor = 2 if low < MIN_SEARCH_RADIUS_PX else 1
    search = gray if factor == 1 else cv2.resize(gray, None, fx=factor, fy=factor, interpolation=cv2.INTER_LINEAR)
    low, high = max(low * factor, 3.0), high * factor
    with one_opencv_thread():  # HOUGH_GRADIENT_ALT merges its stripes' circles in the order the threads finish
        found = cv2.HoughCircles(cv2.GaussianBlur(search, (5, 5), 1.0), cv2.HOUGH_GRADIENT_ALT, 1.5, 0.8 * low,
                                 param1=HOUGH_PARAM1, param2=HOUGH_PARAM2, minRadius=int(low), maxRadius=int(high) + 1)
    if found is None:
        return np.zeros((0, 3))
    circles = _refine(search, np.asarray(found[0], dtype=np.float64).reshape(-1, 3))
    circles[:, :2] = (circles[:, :2] + 0.5) / factor - 0.5  # the image's OpenCV pixels
    circles[:, 2] /= factor
    return circles


def head_candidates(image: pycolmap.Image, image_dir: Path, footprint: np.ndarray | None,
                    searched: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """:func:`detect_heads` of the image file (none where it cannot be read); ``searched``: image name -> its
    candidates, those searched before (taken from it; this one's added)."""
    if searched is not None and image.name in searched:
        return searched[image.name]
    gray = read_image(Path(image_dir) / image.name, cv2.IMREAD_GRAYSCALE)
    found = np.zeros((0, 3)) if gray is None else detect_heads(image, gray, footprint)
    if searched is not None:
        searched[image.name] = found
    return found


def head_sigma(residuals: np.ndarray, persons: int) -> float | None:
    """A head centre's noise per coordinate (module docstring, step 6) from ``residuals`` (N x 2 px) of ``persons``
    triangulated points: the median absolute coordinate as a normal's (a wrong member of a person does not pull
    it), times ``sqrt(2 N / (2 N - 3 P))`` for what each person's triangulation absorbed; None below
    ``MIN_SIGMA_DOF`` degrees of freedom."""
    residuals = np.asarray(residuals, dtype=np.float64).reshape(-1, 2)
    residuals = residuals[np.isfinite(residuals).all(axis=1)]
    dof = 2 * len(residuals) - 3 * persons
    if dof < MIN_SIGMA_DOF:
        return None
    return float(1.4826 * np.median(np.abs(residuals)) * math.sqrt(2 * len(residuals) / dof))


def _residuals(views: list[View], result, groups: np.ndarray) -> np.ndarray:
    """The head centres of ``groups`` (rows of ``result``) against their points' projections, per view its pose
    correction (``result.shift_px``) removed as the association removed it: undistorted px, N x 2."""
    out = [np.zeros((0, 2))]
    for v, view in enumerate(views):
        rows = groups[result.members[groups, v] >= 0]
        if not len(rows):
            continue
        projected, depth = view.project(result.points[rows])
        observed = undistort_pixels(view.camera, view.xy[result.members[rows, v]]) - result.shift_px.get(
            view.name, np.zeros(2))[None]
        out.append((observed - projected)[depth > 0])
    return np.concatenate(out)


def _association_options() -> AssociateOptions:
    # one detection probability for every view: the occlusion model was measured on detectors' heads, not on these
    # Hough candidates (benchmarks/README.md, twenty-second pass), and the run's numbers stand on it as it was
    return AssociateOptions(pixel_sigma=HEAD_PIXEL_SIGMA, visibility=False)


def match_heads(floor_model: pycolmap.Reconstruction, image_dir: Path, frames: dict[str, list[pycolmap.Image]],
                bands: dict[tuple[str, str], float], max_frames: int = 1, threads: int = 1,
                progress: Callable[[int, int], None] | None = None,
                searched: dict[str, np.ndarray] | None = None) -> HeadMatches:
    """Heads matched across the synchronised narrow views of the first ``max_frames`` frames (module docstring,
    steps 1-3). ``floor_model``: the first adjustment in the floor frame; ``frames``: frame -> its narrow images
    (of ``floor_model``); ``bands``: (i, j) -> the pair's 95 % band (px) from the first adjustment's uncertainty;
    ``threads``: images searched at once; ``progress(done, total)``: per frame, its images searched and then its
    association; ``searched``: image -> its candidates, those searched before (and this call's, added)."""
    out = HeadMatches()
    searched = {} if searched is None else searched
    footprint = scene_footprint(floor_model)
    for frame in list(frames)[:max(1, max_frames)]:
        images = frames[frame]
        overlapping = overlapping_pairs(floor_model, images, True)
        names = sorted({n for p in overlapping for n in p})
        if len(names) < 2:
            continue
        images_of = [floor_model.find_image_with_name(name) for name in names]

        def candidates(image: pycolmap.Image) -> np.ndarray:
            return head_candidates(image, image_dir, footprint, searched)

        views = []
        # The images side by side (OpenCV's Hough frees the GIL), each search on one thread: the same circles.
        with one_opencv_thread(), ThreadPoolExecutor(max(1, min(threads, len(names)))) as pool:
            for image, heads in zip(images_of, pool.map(candidates, images_of)):
                out.candidates[image.name] = len(heads)
                views.append(View.of(image, heads[:, :2]))
                if progress:
                    progress(len(views), len(names) + 1)
        if sum(len(v.xy) for v in views) == 0:
            if progress:  # nothing to associate: the frame is done
                progress(len(names) + 1, len(names) + 1)
            continue
        pair_bands = {key: float(b) for key, b in bands.items() if key[0] in names and key[1] in names
                      and b is not None and math.isfinite(float(b))}
        sigmas = view_pose_sigmas(names, pair_bands)
        for view in views:
            view.sigma_pose_px = sigmas[view.name]
        result = associate_views(views, _association_options())
        if progress:
            progress(len(names) + 1, len(names) + 1)
        members = confident_members(result.members, result.scores)
        confident = np.flatnonzero((members >= 0).sum(axis=1) >= MIN_GROUP_VIEWS)
        per_pair = _per_pair(views, members, confident, overlapping)  # none held out (step 3)
        out.persons += len(confident)
        out.residuals.append(_residuals(views, dataclasses.replace(result, members=members), confident))
        out.pairs.extend(_pair_matches(frame, per_pair))
        checked = np.flatnonzero(((result.members >= 0).sum(axis=1) >= 2) & (result.scores > CHECK_MIN_SCORE))
        out.check_pairs.extend(_pair_matches(frame, _per_pair(views, result.members, checked, overlapping)))
        logger.info("narrow observations from heads, %s: %s candidates per image, %d confident persons of %d",
                    frame, [len(v.xy) for v in views], len(confident), len(result))
    return out


def confident_members(members: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """``members`` (persons x views, -1 where unseen) of the confident persons (``MIN_GROUP_VIEWS`` views or more,
    score above ``MIN_GROUP_SCORE``), -1 elsewhere, and without the views in fewer than ``MIN_VIEW_PERSONS`` of
    them (module docstring, step 3): the association corrects a view's pose only from that many persons, so a
    view below it was searched at its first pose, whose error may exceed the band, and its few matches are chance
    as often as not; a person left in fewer than ``MIN_GROUP_VIEWS`` views is dropped."""
    out = np.where(((members >= 0).sum(axis=1, keepdims=True) >= MIN_GROUP_VIEWS)
                   & (scores[:, None] > MIN_GROUP_SCORE), members, -1)
    for _ in range(members.shape[1]):  # dropping a view's persons can take another view below the minimum
        few = (out >= 0).sum(axis=0) < MIN_VIEW_PERSONS
        out[:, few] = -1
        out[(out >= 0).sum(axis=1) < MIN_GROUP_VIEWS] = -1
        if not ((out >= 0).sum(axis=0)[~few] < MIN_VIEW_PERSONS).any():
            break
    return out


def _per_pair(views: list[View], members: np.ndarray, groups: np.ndarray, overlapping: list,
              held: np.ndarray | None = None) -> dict[tuple[str, str], tuple[list, list, list]]:
    """(i, j) -> the head centres in i and in j of ``groups`` (rows of ``members``) seen in both, and whether each
    is held out (``held``: per group; None: none)."""
    per_pair: dict[tuple[str, str], tuple[list, list, list]] = {p: ([], [], []) for p in overlapping}
    for n, g in enumerate(groups):
        seen = np.flatnonzero(members[g] >= 0)
        for a in seen:
            for b in seen:
                key = (views[a].name, views[b].name)
                if key in per_pair:
                    per_pair[key][0].append(views[a].xy[members[g, a]])
                    per_pair[key][1].append(views[b].xy[members[g, b]])
                    per_pair[key][2].append(bool(held is not None and held[n]))
    return per_pair


def _pair_matches(frame: str, per_pair: dict[tuple[str, str], tuple[list, list, list]]) -> list[PairMatches]:
    return [PairMatches(frame, i, j, np.asarray(xy_i, dtype=np.float64).reshape(-1, 2),
                        np.asarray(xy_j, dtype=np.float64).reshape(-1, 2), np.asarray(held_out, bool),
                        found=len(held_out))
            for (i, j), (xy_i, xy_j, held_out) in per_pair.items()]


def decide_heads(heads: HeadMatches) -> tuple[bool, str]:
    """Whether the heads' matches enter the adjustment (``auto``), and why."""
    enough = heads.persons >= MIN_HEAD_GROUPS
    counts = (f"{heads.persons} persons matched in >= {MIN_GROUP_VIEWS} views from "
              f"{sum(heads.candidates.values())} head candidates in {len(heads.candidates)} narrow images "
              f"(>= {MIN_HEAD_GROUPS} needed)")
    return enough, ("heads usable: " if enough else "no usable heads: ") + counts


def head_self_check(checks: list, head_pairs: list[PairMatches], reconstruction: pycolmap.Reconstruction,
                    narrow_poses: dict) -> int:
    """Verdicts from heads (module docstring, step 5) for the self-check's pairs (rigsfm.run.checks.guided.PairCheck,
    changed in place) that have none; ``head_pairs``: HeadMatches.check_pairs; ``reconstruction`` and ``narrow_poses``
    as delivered. Returns how many got one."""
    by_pair = {(p["i"], p["j"]): p for p in narrow_poses.get("pairs", [])}
    heads = {(p.frame, p.i, p.j): p for p in head_pairs}
    given = 0
    for check in checks:
        pair = heads.get((check.frame, check.i, check.j))
        entry = by_pair.get((check.i, check.j))
        if check.verdict != "too few matches" or pair is None or entry is None or pair.matches < MIN_HEAD_MATCHES:
            continue
        camera_i = reconstruction.cameras[reconstruction.find_image_with_name(check.i).camera_id]
        camera_j = reconstruction.cameras[reconstruction.find_image_with_name(check.j).camera_id]
        ui, uj = undistort_pixels(camera_i, pair.xy_i), undistort_pixels(camera_j, pair.xy_j)
        f_ji = np.asarray(entry["F_ji"], dtype=np.float64)
        distances = pixel_line_distances(np.c_[ui, np.ones(len(ui))] @ f_ji.T, uj)
        distances = distances[np.isfinite(distances)]
        if len(distances) < MIN_HEAD_MATCHES:
            continue
        band = entry.get("epipolar_band_95_px")
        check.matches, check.xy_i, check.xy_j, check.distances_px = len(distances), pair.xy_i, pair.xy_j, distances
        check.median_px, check.p95_px = float(np.median(distances)), float(np.percentile(distances, 95))
        check.measured_within_px = None
        if band is None:
            check.verdict = "no band"
        else:
            check.within_band = float(np.mean(distances <= band + HEAD_NOISE_PX))  # as the verdict: noisy centres
            check.verdict = "failed" if check.p95_px > band + HEAD_NOISE_PX else "ok"
        given += 1
    return given
