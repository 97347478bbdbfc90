"""The fraction of a frame by which rigs are off in time, where the crowd's motion allows (refines the integer
offsets of :mod:`rigsfm.run.checks.sync`).

For a pair of rigs (a, b) at its integer pairing ``d = o_a - o_b``, narrow a frame ``k`` is simultaneous with
narrow b at the fractional frame ``k + d + tau``, ``tau = f_a - f_b`` (the rigs' fractions). Each guided match
(a's keypoint, b's keypoint in frame ``k + d``, found as the self-check finds them but within band + keypoint noise
+ the crowd's motion over one frame, since a fraction shifts the matches off their lines by that much) is tracked
into b's frames ``k + d - 1`` and ``k + d + 1`` (pyramidal Lucas-Kanade, forward-backward checked): its position at
``k + d + tau`` is interpolated linearly, ``x(tau) = x + tau v`` (``v`` the central difference, or the one-sided
one at the recording's ends), so its signed distance from a's epipolar line is ``s + tau g`` with ``g`` the motion
across the line per frame. ``tau`` maximises the number of matches within band + keypoint noise (a grid over
-1..1; false matches of repetitive crowd texture are outvoted), then is refined by least squares on those
inliers, ``tau = -sum(s g) / sum(g^2)``. Its standard error joins the scatter's, ``rms / sqrt(sum(g^2))``, and
the lines' own error, ``band / 1.96 / rms(g)`` (common to the pair's matches, so it does not average down). Only
matches moving at least ``MIN_MOTION_PX`` across their line per frame count: a static feature, or a walker moving
along the line, cannot tell time. A pair with fewer than ``MIN_TRACKS`` such inliers tells no fraction ("too
little motion"; fewer tracked matches at all: "too few matches tracked").

Per rig: least squares over the pairs' ``O_a - O_b = d + tau`` (weights 1 / sigma^2) with the first rig at 0,
the standard errors from the normal equations, scaled up by the fit's reduced chi-square where the pairs disagree
by more than their errors. Then the gauge: the largest group of rigs on whole frames of each other (within
``WHOLE_FRAMES``; ties: the group at the integer search's offsets) is put on whole frames (the integer search's
gauge, most rigs at 0: the rigs off by a fraction are the others). A rig is named off when ``|offset| >=
NAMED_FRAMES`` and at least 3 standard errors.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from rigsfm.core.conventions import colmap_from_opencv_pixels, opencv_from_colmap_pixels
from rigsfm.core.ground import undistort_pixels
from rigsfm.run.checks.guided import (
    KEYPOINT_NOISE_PX,
    MAX_TOLERANCE_PX,
    band_candidates,
    epipolar_segments,
    guided_matches,
)

logger = logging.getLogger(__name__)

MIN_MOTION_PX = 1.0  # motion across the epipolar line per frame below which a match cannot tell time
MIN_TRACKS = 12  # inlier matches that move across their lines: fewer tells no fraction
MIN_SIGMA_FRAMES = 0.005  # floor on a pair's standard error
NAMED_FRAMES = 0.05  # a rig whose estimated offset is at least this (and 3 standard errors) is named off
WHOLE_FRAMES = 0.025  # rigs this close to whole frames of each other are taken as one group for the gauge
TAU_GRID = np.linspace(-1.0, 1.0, 401)
_LK = {"winSize": (21, 21), "maxLevel": 4,
       "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 40, 0.01)}
_LK_BACK_PX = 0.5  # forward-backward disagreement that drops a track


@dataclass(frozen=True)
class PairFraction:
    a: str
    b: str
    d: int  # the integer pairing: a frame k against b frame k + d
    tau: float | None  # b's frame k + d + tau is simultaneous with a's frame k
    sigma: float | None
    matches: int  # guided matches tracked in b
    inliers: int  # of them, within the band at tau and moving across their lines
    reason: str | None = None  # why no fraction

    def to_dict(self) -> dict:
        return {"a": self.a, "b": self.b, "d": self.d, "tau": None if self.tau is None else round(self.tau, 4),
                "sigma": None if self.sigma is None else round(self.sigma, 4), "matches": self.matches,
                "inliers": self.inliers, "reason": self.reason}


@dataclass
class SubframeEstimate:
    """Per-rig offsets in frames (integer + fraction) and their standard errors; None where no pair measured a
    fraction for the rig (``reason``)."""

    offsets: dict[str, float | None]
    sigmas: dict[str, float | None]
    pairs: list[PairFraction] = field(default_factory=list)
    reason: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def named(self) -> dict[str, float]:
        """Rigs clearly off in time (module docstring)."""
        return {r: o for r, o in self.offsets.items()
                if o is not None and abs(o) >= NAMED_FRAMES and abs(o) >= 3 * (self.sigmas.get(r) or 0.0)}

    def to_dict(self) -> dict:
        return {"offsets": {r: None if o is None else round(o, 3) for r, o in self.offsets.items()},
                "sigmas": {r: None if s is None else round(s, 3) for r, s in self.sigmas.items()},
                "named": {r: round(o, 3) for r, o in self.named.items()}, "reason": dict(self.reason),
                "named_frames": NAMED_FRAMES,
                "seconds": round(self.seconds, 3), "pairs": [p.to_dict() for p in self.pairs]}


def _track(gray_from: np.ndarray, gray_to: np.ndarray, xy_colmap: np.ndarray) -> np.ndarray:
    """Raw COLMAP pixels of ``xy_colmap`` tracked into ``gray_to`` (NaN where lost)."""
    if not len(xy_colmap):
        return np.zeros((0, 2))
    p0 = opencv_from_colmap_pixels(xy_colmap).astype(np.float32).reshape(-1, 1, 2)
    p1, found, _ = cv2.calcOpticalFlowPyrLK(gray_from, gray_to, p0, None, **_LK)  # type: ignore[call-overload]
    back, found_back, _ = cv2.calcOpticalFlowPyrLK(gray_to, gray_from, p1, None, **_LK)  # type: ignore[call-overload]
    ok = (found.ravel() == 1) & (found_back.ravel() == 1) & (np.linalg.norm((back - p0).reshape(-1, 2), axis=1)
                                                              <= _LK_BACK_PX)
    out = colmap_from_opencv_pixels(p1.reshape(-1, 2))
    out[~ok] = np.nan
    return out


def _velocities(frames: list, xy_colmap: np.ndarray) -> np.ndarray:
    """Undistorted motion per frame of b's keypoints (pinhole pixels; NaN where not tracked). ``frames``: b's
    loaded frames j - 1, j, j + 1 (None at the recording's ends)."""
    before, now, after = frames
    camera = now.image.camera
    here = undistort_pixels(camera, xy_colmap)
    moved = []
    for other, sign in ((before, -1.0), (after, 1.0)):
        if other is None:
            moved.append(np.full_like(here, np.nan))
            continue
        tracked = _track(now.gray, other.gray, xy_colmap)
        position = np.full_like(here, np.nan)
        ok = np.isfinite(tracked).all(axis=1)
        position[ok] = undistort_pixels(camera, tracked[ok])
        moved.append(sign * (position - here))
    backward, forward = moved
    central = 0.5 * (backward + forward)
    return np.where(np.isfinite(central), central, np.where(np.isfinite(forward), forward, backward))


def measure_pair(first, frames: list, features: Callable, f_ji: np.ndarray, band: float,
                 floor_frame: bool) -> tuple[np.ndarray, np.ndarray, int]:
    """One frame pairing's matches: signed distances ``s`` (px) from a's lines in b's frame j and motion ``g``
    across the lines per frame, for matches tracked in b; ``features(first, second)`` gives the pair's features
    (rigsfm.run.checks.guided.pair_features, cached by the caller)."""
    second = frames[1]
    fi, fj = features(first, second)
    if fi is None or fj is None or len(fi.xy) < 2 or len(fj.xy) < 2:
        return np.zeros(0), np.zeros(0), 0
    velocity = _velocities(frames, fj.xy)
    speed = np.linalg.norm(velocity, axis=1)
    motion = float(np.percentile(speed[np.isfinite(speed)], 95)) if np.isfinite(speed).any() else 0.0
    lines = np.c_[fi.undistorted, np.ones(len(fi.undistorted))] @ np.asarray(f_ji, dtype=np.float64).T
    lines /= np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    segments = epipolar_segments(first.image, second.image, fi.undistorted, floor_frame)
    tolerance = min(band + KEYPOINT_NOISE_PX + motion, MAX_TOLERANCE_PX)
    candidates = band_candidates(f_ji, lines, fj.undistorted, segments, tolerance)
    matches = guided_matches(fi, fj, candidates.a, candidates.b)
    if not len(matches):
        return np.zeros(0), np.zeros(0), 0
    line = lines[matches[:, 0]]
    v = velocity[matches[:, 1]]
    tracked = np.isfinite(v).all(axis=1)
    line, v, xy = line[tracked], v[tracked], fj.undistorted[matches[tracked, 1]]
    s = np.einsum("ij,ij->i", line, np.c_[xy, np.ones(len(xy))])
    g = np.einsum("ij,ij->i", line[:, :2], v)
    return s, g, int(tracked.sum())


def fit_tau(s: np.ndarray, g: np.ndarray, band: float) -> tuple[float | None, float | None, int, str | None]:
    """tau, its standard error, the inliers and why none (module docstring)."""
    threshold = band + KEYPOINT_NOISE_PX
    if len(s) < MIN_TRACKS:
        return None, None, 0, f"too few matches tracked between the rig's frames ({len(s)})"
    moving = np.abs(g) >= MIN_MOTION_PX
    s, g = s[moving], g[moving]
    if len(s) < MIN_TRACKS:
        return None, None, 0, f"too little motion across the epipolar lines ({len(s)} moving tracks)"
    counts = (np.abs(s[:, None] + TAU_GRID[None] * g[:, None]) <= threshold).sum(axis=0)
    best = counts.max()
    tau = float(np.median(TAU_GRID[counts == best]))
    inliers = np.zeros(len(s), bool)
    for _ in range(3):  # least squares on the inliers, their set updated with tau
        inliers = np.abs(s + tau * g) <= threshold
        if inliers.sum() < MIN_TRACKS:
            return None, None, int(inliers.sum()), f"too few tracks on the epipolar lines ({int(inliers.sum())})"
        tau = float(-np.sum(s[inliers] * g[inliers]) / np.sum(g[inliers] ** 2))
    inliers = np.abs(s + tau * g) <= threshold
    n = int(inliers.sum())
    if n < MIN_TRACKS:
        return None, None, n, f"too few tracks on the epipolar lines ({n})"
    residual = s[inliers] + tau * g[inliers]
    rms = math.sqrt(float(np.sum(residual ** 2)) / max(n - 1, 1))
    scatter = rms / math.sqrt(float(np.sum(g[inliers] ** 2)))
    # the band bounds the epipolar lines' own error, common to the pair's matches: it does not average down
    lines = band / 1.96 / math.sqrt(float(np.mean(g[inliers] ** 2)))
    return tau, max(math.hypot(scatter, lines), MIN_SIGMA_FRAMES), n, None


def _gauge(total: dict[str, float], integer: dict[str, int]) -> float:
    """The shift that puts the largest group of rigs on whole frames (ties: the group at the integer offsets,
    then the smallest shift); the group's mean (module docstring)."""
    def group(c: float) -> list[str]:
        return [r for r in total if abs(total[r] - c - round(total[r] - c)) <= WHOLE_FRAMES]

    def key(c: float) -> tuple[int, int, float]:
        members = group(c)
        return len(members), sum(abs(total[r] - c - integer.get(r, 0)) <= WHOLE_FRAMES for r in members), -abs(c)

    best = max(total.values(), key=key)
    members = group(best)
    shift = best + float(np.mean([total[r] - best - round(total[r] - best) for r in members]))
    # the whole frames of the shift: the group at the integer search's offsets
    return shift + round(float(np.median([total[r] - shift - integer.get(r, 0) for r in members])))


def combine(rigs: list[str], integer: dict[str, int], pairs: list[PairFraction]) -> SubframeEstimate:
    """Per-rig offsets from the pairs' fractions (module docstring)."""
    measured = [p for p in pairs if p.tau is not None]
    # rigs joined to the first by measured pairs
    joined, changed = {rigs[0]}, True
    while changed:
        changed = False
        for p in measured:
            if (p.a in joined) != (p.b in joined):
                joined |= {p.a, p.b}
                changed = True
    if len(joined) < 2:
        reason = {r: next((p.reason for p in pairs if r in (p.a, p.b) and p.reason), "no pair measured")
                  for r in rigs}
        return SubframeEstimate({r: None for r in rigs}, {r: None for r in rigs}, pairs, reason)
    unknowns = [r for r in rigs if r in joined and r != rigs[0]]
    column = {r: n for n, r in enumerate(unknowns)}
    rows, values, weights = [], [], []
    for p in measured:
        if p.a not in joined:
            continue
        row = np.zeros(len(unknowns))
        if p.a in column:
            row[column[p.a]] += 1.0
        if p.b in column:
            row[column[p.b]] -= 1.0
        rows.append(row)
        values.append(p.d + p.tau)  # type: ignore[operator]  # measured
        weights.append(1.0 / p.sigma ** 2)  # type: ignore[operator]
    a, y, w = np.array(rows), np.array(values), np.array(weights)
    normal = a.T @ (w[:, None] * a)
    solution = np.linalg.solve(normal, a.T @ (w * y))
    covariance = np.linalg.inv(normal)
    dof = len(y) - len(unknowns)
    if dof > 0:
        chi2 = float(np.sum(w * (y - a @ solution) ** 2)) / dof
        covariance *= max(chi2, 1.0)
    total = {rigs[0]: 0.0, **{r: float(solution[column[r]]) for r in unknowns}}
    sigma = {rigs[0]: 0.0, **{r: float(math.sqrt(covariance[column[r], column[r]])) for r in unknowns}}
    shift = _gauge(total, integer)
    offsets: dict[str, float | None] = {r: None for r in rigs}
    sigmas: dict[str, float | None] = {r: None for r in rigs}
    for r in total:
        offsets[r] = total[r] - shift
        # the gauge moved off the first rig: its error is about a typical rig's
        sigmas[r] = sigma[r] if r != rigs[0] else float(np.median([sigma[u] for u in unknowns]))
    reason = {r: "no pair with a fraction joins it to the others" for r in rigs if r not in joined}
    return SubframeEstimate(offsets, sigmas, pairs, reason)
