"""The crowd's own detection probability, from the persons one association found.

A person whose point projects inside ``n`` views is detected in each with probability ``p`` (occlusion included), so
its member count is binomial; but only persons detected in two views or more can be found at all, and those seen
in more views are found more readily. The maximum-likelihood ``p`` of the found persons' counts under the binomial
truncated to two or more members corrects the first of these; the kept persons' own counts (the detected ones) would
overstate ``p`` badly in a crowd where half the heads are hidden.

Where a head is hidden depends on the view, though: persons standing in front of it above the ray hide it from one
camera and not from another (``Occlusion``, each view's own probability, fitted on the confident persons' detected
and missed views), so a view that hides a point is no miss.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy.special import gammaln, ndtr

GRID = np.linspace(0.02, 0.98, 97)


def truncated_binomial_p(members: np.ndarray, seen: np.ndarray, at_least: int = 2) -> float | None:
    """Maximum-likelihood detection probability of groups with ``members`` detections among ``seen`` views that
    see them, each group known to hold at least ``at_least`` (a grid over 0.02-0.98). None without usable groups:
    a group seen by only ``at_least`` views holds all of them whatever the probability, so it tells nothing (two
    views' persons alone would otherwise give the grid's first value, and every person would score as unlikely)."""
    k, n = np.asarray(members, dtype=np.int64), np.asarray(seen, dtype=np.int64)
    ok = (n > at_least) & (k >= at_least) & (k <= n)
    k, n = k[ok], n[ok]
    if not len(k):
        return None
    p = GRID[:, None]
    log_p, log_q = np.log(p), np.log1p(-p)
    observed = k[None] * log_p + (n - k)[None] * log_q
    # P(K >= at_least) = 1 - sum_{j < at_least} C(n, j) p^j q^(n - j)
    below = np.zeros((len(GRID), len(n)))
    for j in range(at_least):
        log_choose = gammaln(n + 1) - gammaln(j + 1) - gammaln(n - j + 1)
        below += np.exp(log_choose[None] + j * log_p + (n - j)[None] * log_q)
    total = np.sum(observed - np.log(np.maximum(1.0 - below, 1e-300)), axis=1)
    return float(GRID[int(np.argmax(total))])


def detection_noise(squared_px: np.ndarray) -> float | None:
    """The detector's noise per coordinate (px) from groups' members' squared reprojection residuals (G x V px^2,
    NaN where a view holds no member), robustly: a group of m members' summed squares is ``sigma^2`` times a
    chi-square of 2m - 3 degrees of freedom (its point took 3 of the 2m coordinates), so each group's sum over that
    chi-square's median (Wilson-Hilferty) has the median ``sigma^2``. None under ``MIN_NOISE_MEMBERS`` members. The
    groups an association keeps hold the detections that agree best, so on a crowd this runs below the detector's
    noise (benchmarks/README.md)."""
    present = np.isfinite(squared_px)
    size = present.sum(axis=1)
    ok = size >= 2
    if int(size[ok].sum()) < MIN_NOISE_MEMBERS:
        return None
    dof = 2.0 * size[ok] - 3.0
    median = dof * (1.0 - 2.0 / (9.0 * dof)) ** 3
    return float(np.sqrt(np.median(np.nansum(squared_px[ok], axis=1) / median)))


MIN_NOISE_MEMBERS = 30


# Metres back from a point towards the camera, along the floor, where the persons in front of it are counted.
STEPS = np.arange(0.3, 16.0, 0.1)
Q_GRID = np.linspace(0.5, 0.99, 50)
A_GRID = np.linspace(0.0, 4.0, 81)


@dataclass(frozen=True)
class Occlusion:
    """Each view's probability of detecting a point X: ``q exp(-a I_v(X))``, ``I_v(X)`` the persons (per unit
    density) whose heads or shoulders stand above the ray from camera v to X, inside the crowd's footprint (a disc
    round ``centre`` of ``radius_m``), their heights the crowd's prior (``heights``: mean, sigma). A view that
    hides X is no miss: one probability for every view counts it as one."""

    q: float
    a: float
    centre: tuple[float, float]
    radius_m: float
    heights: tuple[float, float]

    def probability(self, centres: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Per row, the detection probability of ``points`` seen from camera ``centres`` (N x 3 each)."""
        return self.q * np.exp(-self.a * occluders(self, centres, points))


def occluders(model: Occlusion, centres: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Per row, the expected persons (per unit density x 0.1 m steps) standing above the ray from ``centres`` to
    ``points`` inside the footprint."""
    out = np.empty(len(points))
    mean, sigma = model.heights
    middle = np.asarray(model.centre)
    for a in range(0, len(points), 4000):
        c, x = centres[a:a + 4000], points[a:a + 4000]
        back = c[:, :2] - x[:, :2]
        length = np.maximum(np.linalg.norm(back, axis=1), 1e-6)
        slope = (c[:, 2] - x[:, 2]) / length
        at = x[:, None, :2] + STEPS[None, :, None] * (back / length[:, None])[:, None, :]
        # not the point's own person: from 0.5 m before the camera
        inside = (np.linalg.norm(at - middle, axis=2) < model.radius_m) & (STEPS[None] < length[:, None] - 0.5)
        ray = x[:, 2:3] + STEPS[None] * slope[:, None]
        # a person's head top ~0.1 m above its point, its shoulders ~0.15 m below: the ray passes through either
        # (the normal's upper tail, where inside the footprint only: the rest adds zeros)
        above = np.zeros(ray.shape)
        above[inside] = ndtr(-((ray[inside] - 0.05 - mean) / sigma))
        out[a:a + 4000] = 0.1 * np.sum(above, axis=1)
    return out


def fit_occlusion(views: list, centres: np.ndarray, members: np.ndarray, points: np.ndarray, confident: np.ndarray,
                  heights: tuple[float, float]) -> Occlusion | None:
    """The occlusion model of a frame's persons (``points``, ``members`` P x V; ``views`` with ``project`` and
    ``inside``, their camera ``centres``): the footprint from every person (the confident ones alone stand nearer
    the centre, and rays from their cameras pass people outside it), ``q`` and ``a`` by maximum likelihood (a grid)
    of the ``confident`` ones' detected and missed views. None without persons."""
    if not confident.any():
        return None
    centre = np.median(points[:, :2], axis=0)
    radius = float(np.percentile(np.linalg.norm(points[:, :2] - centre, axis=1), 99))
    model = Occlusion(q=1.0, a=0.0, centre=(float(centre[0]), float(centre[1])), radius_m=radius,
                      heights=(float(heights[0]), float(heights[1])))
    x = points[confident]
    depth, detected = [], []
    for v, view in enumerate(views):
        uv, z = view.project(x)
        seen = view.inside(uv, z) | (members[confident, v] >= 0)
        depth.append(occluders(model, np.repeat(centres[v][None], int(seen.sum()), axis=0), x[seen]))
        detected.append(members[confident, v][seen] >= 0)
    d, hit = np.concatenate(depth), np.concatenate(detected)
    ll = np.zeros((len(Q_GRID), len(A_GRID)))
    for i, q in enumerate(Q_GRID):
        p = q * np.exp(-A_GRID[:, None] * d[None])
        ll[i] = np.sum(np.where(hit[None], np.log(np.maximum(p, 1e-9)), np.log(np.maximum(1 - p, 1e-9))), axis=1)
    best_q, best_a = np.unravel_index(int(np.argmax(ll)), ll.shape)
    return dataclasses.replace(model, q=float(Q_GRID[best_q]), a=float(A_GRID[best_a]))
