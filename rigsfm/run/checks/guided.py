"""Guided matching of one pair of synchronised narrow images, and the distances of its matches from the epipolar
lines (the self-check's measurement, ``rigsfm.run.checks.self_check``):

1. **Features**: OpenCV SIFT (:mod:`rigsfm.core.sift`) in image i (once per image, on it reduced by the integer
   factor that brings it nearest ``sift_size`` px: faster, with fewer matches whose distances follow the true ones
   as closely, see benchmarks/README.md); in the floor frame, image j is first warped into i's
   view through the plane z = ``warp_height_m`` (0: the floor) over the part of i that sees j, so the two long
   focal views, tens of degrees apart in azimuth, give comparable descriptors; SIFT runs on the warp and each
   keypoint is mapped back to j's own pixels (exact: the warp's own map). Keypoints are undistorted into
   pinhole COLMAP pixels (the frame of ``F_ji``). The warp gives several times the matches, where without it most
   are false.
2. **Guided candidates**: keypoint j is a candidate for keypoint i when it lies within the tolerance of i's
   epipolar line in j (keypoints of j sorted by their angle about the epipole, so each line looks at a narrow
   window of them), and in the floor frame between the images of i's ray at heights 0 and ``TOP_HEIGHT_M``
   (where a person can be: the segment cuts the ambiguity of repetitive crowd texture).
3. **Matches**: Lowe's ratio test (0.7) among each keypoint's candidates only (descriptor distances for the
   candidate pairs alone), then mutual best matches.
4. **Honest measurement**: distances of matches selected inside the band are truncated at the band and could
   never show a band that is too narrow. So the statistics come from a wider selection: ``WIDE_FACTOR`` x band
   + keypoint noise, doubled (up to ``MAX_TOLERANCE_PX``) until the matches' 95th percentile lies within half
   of it. Per pair: median, 95th percentile and number of the distances of the matches to their epipolar lines
   (pinhole pixels of j, as the band), the fraction within the band + keypoint noise, and the tolerance they were
   measured within. ``EPIPOLAR CHECK FAILED`` when the 95th percentile exceeds the band by more than
   ``KEYPOINT_NOISE_PX`` (SIFT's own localisation error across views). No verdict with fewer than
   ``MIN_MATCHES`` matches, or when even the widest search is filled by them ("inconclusive"). The matches
   inside the band (+ keypoint noise) are counted as ``band_matches``: those an analyst would use.

"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from rigsfm.core.conventions import colmap_from_opencv_pixels, opencv_from_colmap_pixels
from rigsfm.core.geometry import pixel_line_distances
from rigsfm.core.ground import (
    footprints,
    ground_from_image,
    image_from_plane,
    pairwise_overlaps,
    undistort_pixels,
)
from rigsfm.core.image_files import read_image
from rigsfm.core.matching import candidate_matches
from rigsfm.core.names import name_of
from rigsfm.core.sift import detect, opencv_sift, reduction_factor
from rigsfm.core.summary import SELF_CHECK_MIN_MATCHES
from rigsfm.run.world.floor_matching import grid_rays, plane_hits, plane_warp

logger = logging.getLogger(__name__)


TOP_HEIGHT_M = 2.2  # the highest point of a person (segment of the epipolar line searched, floor frame)
HEAD_HEIGHT_M = 1.7  # footprints overlap on the floor or at this height
MIN_OVERLAP_FRACTION = 0.05  # of the smaller footprint
WIDE_FACTOR = 5.0  # the measuring selection's lateral tolerance, x band
KEYPOINT_NOISE_PX = 1.0  # SIFT localisation error allowed on top of the band
MIN_MATCHES = SELF_CHECK_MIN_MATCHES
MAX_TOLERANCE_PX = 64.0
MAX_RATIO = 0.7  # Lowe's ratio among the candidates (looser lets false crowd matches through)
# Candidate pairs one search compares at most: beyond it (no floor frame, so whole epipolar lines, under bands of
# tens of px) every k-th keypoint of i is searched, which keeps the measurement's statistics and bounds its time and
# memory; a floor-frame search stays far below it.
MAX_CANDIDATES = 1_000_000


@dataclass
class PairCheck:
    frame: str
    i: str
    j: str
    band_px: float | None
    matches: int = 0  # measuring selection (wide tolerance)
    median_px: float | None = None
    p95_px: float | None = None
    within_band: float | None = None  # fraction of the measured matches within the band + keypoint noise
    band_matches: int = 0  # matches selected inside the band + keypoint noise
    measured_within_px: float | None = None  # lateral tolerance of the measuring selection
    verdict: str = "too few matches"  # ok, failed, too few matches, inconclusive, no band
    xy_i: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), repr=False)  # raw COLMAP pixels, measured
    xy_j: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), repr=False)
    distances_px: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)

    def to_dict(self) -> dict:
        return {"frame": self.frame, "i": self.i, "j": self.j, "band_px": self.band_px, "matches": self.matches,
                "median_px": self.median_px, "p95_px": self.p95_px, "within_band": self.within_band,
                "band_matches": self.band_matches, "measured_within_px": self.measured_within_px,
                "verdict": self.verdict}


@dataclass(frozen=True)
class NarrowFeatures:
    xy: np.ndarray  # raw COLMAP pixels
    undistorted: np.ndarray  # pinhole COLMAP pixels
    descriptors: np.ndarray

    def subset(self, keep: np.ndarray) -> NarrowFeatures:
        return NarrowFeatures(self.xy[keep], self.undistorted[keep], self.descriptors[keep])


@dataclass
class NarrowView:
    """One narrow image: its pixels, SIFT features and (floor frame) its rays' hits on the warp plane."""

    image: pycolmap.Image
    gray: np.ndarray
    features: NarrowFeatures | None
    sift_factor: int = 1  # SIFT ran on it (and runs on warps into it) reduced by this (SelfCheckOptions.sift_size)
    hits: tuple[np.ndarray, np.ndarray] | None = None
    grid_shape: tuple[int, int] | None = None


def _sift():
    return opencv_sift(8000, contrast_threshold=0.02)


def _to_features(camera: pycolmap.Camera, xy_colmap: np.ndarray, descriptors: np.ndarray | None) -> NarrowFeatures | None:
    if descriptors is None or len(xy_colmap) < 2:
        return None
    undistorted = undistort_pixels(camera, xy_colmap)
    finite = np.isfinite(undistorted).all(axis=1)
    return NarrowFeatures(xy_colmap[finite], undistorted[finite], descriptors[finite])


def load_narrow(image: pycolmap.Image, image_dir: Path, warp_height: float | None, sift_size: int) -> NarrowView | None:
    gray = read_image(image_dir / image.name, cv2.IMREAD_GRAYSCALE)
    # a model's images have their cameras
    if gray is None or gray.shape != (image.camera.height, image.camera.width):  # type: ignore[union-attr]
        logger.warning("self-check: cannot read %s as a %dx%d image", image_dir / image.name, image.camera.width,  # type: ignore[union-attr]
                       image.camera.height)  # type: ignore[union-attr]
        return None
    factor = reduction_factor(gray.shape, sift_size)
    xy, descriptors = detect(_sift(), gray, None, factor)
    # a model's images have their cameras
    narrow = NarrowView(image, gray, _to_features(image.camera, colmap_from_opencv_pixels(xy), descriptors), factor)  # type: ignore[arg-type]
    if warp_height is not None:
        # a model's images have their cameras
        normalised, narrow.grid_shape = grid_rays(image.camera)  # type: ignore[arg-type]
        narrow.hits = plane_hits(image, np.array([0.0, 0.0, 1.0]), -warp_height, np.inf, normalised)
    return narrow


def _dehomogenise(h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    with np.errstate(divide="ignore", invalid="ignore"):
        return h[:, :2] / h[:, 2:], h[:, 2] > 0


def epipolar_segments(image_i: pycolmap.Image, image_j: pycolmap.Image, undistorted_i: np.ndarray,
              floor_frame: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """For keypoints of i: the end points (pinhole pixels of j) of the part of the epipolar line where the
    point is between heights 0 and TOP_HEIGHT_M, and which keypoints have one (None: no height limit)."""
    if not floor_frame:
        return None
    homogeneous = np.c_[undistorted_i, np.ones(len(undistorted_i))]
    ends, valid = [], np.ones(len(undistorted_i), bool)
    for height in (0.0, TOP_HEIGHT_M):
        on_plane = homogeneous @ ground_from_image(image_i, height).T  # w > 0: the ray meets the plane in front
        in_j = on_plane @ image_from_plane(image_j, height).T  # third coordinate: depth in j x w
        xy, front = _dehomogenise(in_j)
        valid &= (on_plane[:, 2] > 0) & front & np.isfinite(xy).all(axis=1)
        ends.append(xy)
    return ends[0], ends[1], valid


@dataclass(frozen=True)
class BandCandidates:
    """Keypoint pairs (a in i, b in j) near i's epipolar line: lateral distance (px) and, when a height segment
    limits the search, the position along the segment (0 at the floor, 1 at TOP_HEIGHT_M) and its length (px)."""

    a: np.ndarray
    b: np.ndarray
    lateral: np.ndarray
    along: np.ndarray | None
    length: np.ndarray | None

    def within(self, tolerance: float) -> np.ndarray:
        keep = self.lateral <= tolerance
        if self.along is not None:
            margin = tolerance / np.maximum(self.length, 1e-9)  # type: ignore[arg-type]  # set with along
            keep &= (self.along >= -margin) & (self.along <= 1 + margin)
        return keep

    def subset(self, keep: np.ndarray) -> BandCandidates:
        return BandCandidates(self.a[keep], self.b[keep], self.lateral[keep],
                              None if self.along is None else self.along[keep],
                              None if self.length is None else self.length[keep])

    def thinned(self, budget: int) -> BandCandidates:
        """The candidates of every k-th keypoint of i, k the smallest that brings them within ``budget`` (all of
        a keypoint's candidates kept: its ratio test is unchanged)."""
        if len(self.a) <= budget:
            return self
        step = -(-len(self.a) // budget)
        while np.count_nonzero(self.a % step == 0) > budget:  # keypoints' candidates differ in number
            step += 1
        return self.subset(self.a % step == 0)


def _pencil(f_ji: np.ndarray, points_j: np.ndarray, lines: np.ndarray):
    """Epipolar lines in j all pass through the epipole e_j (e_j^T F_ji = 0). Returns each point's angle about
    e_j and distance from it, and each line's angle (radians, modulo pi): a point lies r |sin(angle difference)|
    from a line. An epipole at infinity is moved to 1e12 px along its direction (the same formula holds)."""
    u, _, _ = np.linalg.svd(np.asarray(f_ji, dtype=np.float64))
    e = u[:, 2]
    scale = max(abs(e[2]), 1e-12 * np.linalg.norm(e[:2]))
    epipole = e[:2] / np.copysign(scale, e[2] if e[2] != 0 else 1.0)
    offset = points_j - epipole
    point_angle = np.mod(np.arctan2(offset[:, 1], offset[:, 0]), np.pi)
    line_angle = np.mod(np.arctan2(lines[:, 0], -lines[:, 1]), np.pi)  # direction (-b, a) of a x + b y + c = 0
    return point_angle, np.linalg.norm(offset, axis=1), line_angle


def _pencil_windows(point_angle: np.ndarray, radius: np.ndarray, line_angle: np.ndarray, tolerance: float,
                    shells: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Keypoint pairs (a: line of i, b: keypoint of j) whose angles about the epipole are close enough for b to lie
    within ``tolerance`` of a's line, ordered by line and then by angle from the start of its window. One window,
    set by the keypoint nearest the epipole, holds them all; where a keypoint lies pixels from the epipole (opposite
    rigs: it is in view) that window is the whole pencil and every pair of the table is looked at. So, where that
    costs more than twice as much (``shells`` None), keypoints are windowed by radius instead, in shells that double
    from ``tolerance`` (each keypoint a window its shell's nearest allows), and their pairs put back in the one
    window's order: the same pairs, in the same order, at a fraction of the pairs looked at."""
    n = len(point_angle)
    order = np.argsort(point_angle)
    angles = np.concatenate([point_angle[order] - np.pi, point_angle[order], point_angle[order] + np.pi])
    index = np.tile(order, 3)

    def windowed(positions: np.ndarray, window: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For the keypoints at ``positions`` (ascending) of ``order``: each line's start (in their tripled
        positions), count, and those positions."""
        tripled = np.concatenate([positions, positions + n, positions + 2 * n])
        starts = np.searchsorted(angles[tripled], line_angle - window, side="left")
        ends = np.searchsorted(angles[tripled], line_angle + window, side="right")
        return starts, np.maximum(ends - starts, 0), tripled

    def expanded(starts: np.ndarray, counts: np.ndarray, tripled: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a = np.repeat(np.arange(len(line_angle)), counts)
        within = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        return a, tripled[np.repeat(starts, counts) + within]

    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    window = float(np.arcsin(min(1.0, tolerance / max(float(radius.min()), 1e-9))))
    whole = windowed(np.arange(n), window)
    if shells is False:
        a, tripled = expanded(*whole)
        return a, index[tripled]
    ranked = radius[order]
    shell = np.where(ranked < tolerance, 0, np.floor(np.log2(np.maximum(ranked, tolerance) / tolerance)) + 1)
    parts = []
    for s in np.unique(shell):
        positions = np.flatnonzero(shell == s)
        # its own nearest keypoint's window (a hair wider: the lateral test after it decides), within the one window
        nearest = max(float(ranked[positions].min()), 1e-9)
        parts.append(windowed(positions, min(window, float(np.arcsin(min(1.0, tolerance * (1 + 1e-6) / nearest))))))
    if shells is None and 2 * sum(int(p[1].sum()) for p in parts) >= whole[1].sum():
        a, tripled = expanded(*whole)
        return a, index[tripled]
    pairs = [expanded(*part) for part in parts]
    a = np.concatenate([p[0] for p in pairs])
    tripled = np.concatenate([p[1] for p in pairs])
    sort = np.argsort(a * (3 * n) + tripled)  # the one window's order: by line, then by tripled position
    return a[sort], index[tripled[sort]]


def band_candidates(f_ji: np.ndarray, lines: np.ndarray, undistorted_j: np.ndarray, segments, tolerance: float,
                ) -> BandCandidates:
    """Every keypoint pair within ``tolerance`` px of i's line (and of its height segment, module docstring).
    Keypoints of j are sorted by their angle about the epipole, so each line only looks at a narrow window of
    them (no n_i x n_j table)."""
    point_angle, radius, line_angle = _pencil(f_ji, undistorted_j, lines)
    a, b = _pencil_windows(point_angle, radius, line_angle, tolerance)
    hj = np.c_[undistorted_j[b], np.ones(len(b))]
    lateral = np.abs(np.einsum("ij,ij->i", lines[a], hj)) / np.linalg.norm(lines[a, :2], axis=1)
    keep = lateral <= tolerance
    a, b, lateral = a[keep], b[keep], lateral[keep]
    along = length = None
    if segments is not None:
        start_j, end_j, valid = segments
        direction = end_j[a] - start_j[a]
        length = np.linalg.norm(direction, axis=1)
        along = np.einsum("ij,ij->i", undistorted_j[b] - start_j[a], direction) / np.maximum(length, 1e-9) ** 2
        keep = valid[a] & np.isfinite(along)
        a, b, lateral, along, length = a[keep], b[keep], lateral[keep], along[keep], length[keep]
    candidates = BandCandidates(a, b, lateral, along, length)
    return candidates.subset(candidates.within(tolerance))


def guided_matches(fi: NarrowFeatures, fj: NarrowFeatures, a: np.ndarray, b: np.ndarray,
                    max_ratio: float = MAX_RATIO) -> np.ndarray:
    """(k, 2) index pairs among the candidate pairs (a, b): ratio test among candidates, mutual best."""
    return candidate_matches(fi.descriptors, fj.descriptors, a, b, max_ratio)


def overlapping_pairs(reconstruction: pycolmap.Reconstruction, images: Sequence[pycolmap.Image],
                       floor_frame: bool) -> list[tuple[str, str]]:
    """Pairs of images of different rigs whose footprints (floor or head height) overlap by more than
    MIN_OVERLAP_FRACTION of the smaller one; every pair when the world is not the floor frame."""
    pairs = [(a.name, b.name) for a, b in itertools.combinations(images, 2) if name_of(a).rig != name_of(b).rig]
    if not floor_frame:
        return pairs
    keep = set()
    names = {im.name for im in images}
    for height in (0.0, HEAD_HEIGHT_M):
        prints = {n: fp for n, fp in footprints(reconstruction, "narrow", height).items() if n in names}
        for overlap in pairwise_overlaps(prints, pieces=False):
            if overlap.area > MIN_OVERLAP_FRACTION * min(prints[overlap.a].area, prints[overlap.b].area):
                keep.add((overlap.a, overlap.b))
    return [p for p in pairs if p in keep]


def match_line_distances(lines: np.ndarray, fj: NarrowFeatures, matches: np.ndarray) -> np.ndarray:
    return pixel_line_distances(lines[matches[:, 0]], fj.undistorted[matches[:, 1]])


def pair_features(first: NarrowView, second: NarrowView) -> tuple[NarrowFeatures | None, NarrowFeatures | None]:
    """Features of i and j to compare (module docstring, step 1): in the floor frame j's are found on j warped
    into i's view, and i's are those the warp covers."""
    fi, fj = first.features, second.features
    if first.hits is not None and fi is not None:  # j warped into i's view through the plane: comparable features
        warp = plane_warp(first.hits, first.grid_shape,  # type: ignore[arg-type]  # set with hits
                          first.gray.shape, second.image, second.gray, 1000)
        if warp is None:
            return None, None
        fi = fi.subset(warp.covers(opencv_from_colmap_pixels(fi.xy)))
        xy, descriptors = detect(_sift(), warp.warped, warp.mask, first.sift_factor)
        # a model's images have their cameras
        fj = _to_features(second.image.camera, warp.source_pixels(xy), descriptors)  # type: ignore[arg-type]
    return fi, fj


def check_pair(first: NarrowView, second: NarrowView, f_ji: np.ndarray, band: float | None, floor_frame: bool,
               cached: tuple[NarrowFeatures, NarrowFeatures] | None = None) -> PairCheck:
    """One pair (module docstring, steps 2-4); ``cached``: its features from an earlier pass on the same images
    (rigsfm.run.narrow; raw pixels and descriptors kept, undistorted again with this model's cameras)."""
    image_i, image_j = first.image, second.image
    check = PairCheck(name_of(image_i).frame, image_i.name, image_j.name, band)
    if band is None or not np.isfinite(band):
        check.verdict = "no band"
        return check
    if cached is None:
        fi, fj = pair_features(first, second)
    else:  # a model's images have their cameras
        fi = _to_features(image_i.camera, cached[0].xy, cached[0].descriptors)  # type: ignore[arg-type]
        fj = _to_features(image_j.camera, cached[1].xy, cached[1].descriptors)  # type: ignore[arg-type]
    if fi is None or fj is None or len(fi.xy) < 2:
        return check
    f_ji = np.asarray(f_ji, dtype=np.float64)
    lines = np.c_[fi.undistorted, np.ones(len(fi.undistorted))] @ f_ji.T
    segments = epipolar_segments(image_i, image_j, fi.undistorted, floor_frame)
    tolerance = WIDE_FACTOR * band + KEYPOINT_NOISE_PX
    while True:  # widen until the distances are well inside the tolerance (never truncated by it)
        candidates = band_candidates(f_ji, lines, fj.undistorted, segments, tolerance).thinned(MAX_CANDIDATES)
        matches = guided_matches(fi, fj, candidates.a, candidates.b)
        distances = match_line_distances(lines, fj, matches) if len(matches) else np.zeros(0)
        if check.measured_within_px is None:
            in_band = candidates.within(band + KEYPOINT_NOISE_PX)
            check.band_matches = len(guided_matches(fi, fj, candidates.a[in_band], candidates.b[in_band]))
        check.measured_within_px = tolerance
        settled = len(matches) >= MIN_MATCHES and np.percentile(distances, 95) <= 0.5 * tolerance
        if settled or tolerance >= MAX_TOLERANCE_PX:
            break
        tolerance = min(2.0 * tolerance, MAX_TOLERANCE_PX)
    check.matches = len(matches)
    if len(matches):
        check.xy_i, check.xy_j, check.distances_px = fi.xy[matches[:, 0]], fj.xy[matches[:, 1]], distances
    if check.matches < MIN_MATCHES:
        return check
    check.median_px, check.p95_px = float(np.median(distances)), float(np.percentile(distances, 95))
    # keypoints err on their own: against the bare band (which may be under a pixel) even exact poses would miss
    check.within_band = float(np.mean(distances <= band + KEYPOINT_NOISE_PX))
    if check.p95_px > 0.5 * tolerance:  # the matches fill the whole search band: no measurement
        check.verdict = "inconclusive"
    else:
        check.verdict = "failed" if check.p95_px > band + KEYPOINT_NOISE_PX else "ok"
    return check
