"""The views' self-calibration: per view a shift of its undistorted pixels (a small rotation) from the pairs'
candidates (``pairwise_view_shifts``) or from confident groups (``estimate_view_shifts``), and the views it leaves."""

from __future__ import annotations

import copy
import logging
import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from rigsfm.associate.frame import _Frame
from rigsfm.associate.options import AssociateOptions
from rigsfm.associate.rows import confident_rows
from rigsfm.associate.segments import near_segments
from rigsfm.associate.views import View

logger = logging.getLogger(__name__)


@dataclass
class ViewCorrection:
    """Per view: the shift (undistorted px) the crowd asks for, its posterior sigma, the residual scatter left."""

    shift_px: np.ndarray  # V x 2, total (relative to the run's pose)
    shift_sigma_px: np.ndarray  # V
    scatter_px: np.ndarray  # V, per coordinate, members' residual after the shift (robust)
    members: np.ndarray  # V, how many group members each view's estimate rests on


def estimate_view_shifts(frame: _Frame, groups: np.ndarray, options: AssociateOptions,
                         pooled: bool = False) -> ViewCorrection:
    """The per-view shift of the detections (a small rotation of a narrow camera) that best explains the groups'
    reprojection residuals: a bundle adjustment of points and shifts, each shift with the run's pose sigma as its
    prior (no view is fixed: the prior holds the gauge), residuals Huber-weighted so wrong groups weigh little.
    ``pooled``: the views' shifts come from earlier frames (other groups: independent evidence), so each one's
    prior is its current shift and posterior sigma instead of zero and the run's pose sigma."""
    views = frame.views
    nv = len(views)
    pixel = options.pixel_sigma
    assert pixel is not None  # associate_views resolves it
    base = np.array([v.shift_px for v in views], dtype=np.float64)
    prior = np.array([max(v.band_sigma_px if v.band_sigma_px is not None else v.sigma_pose_px, 1e-3)
                      for v in views])
    mean = np.zeros((nv, 2))
    if pooled:
        for v, view in enumerate(views):
            if view.shift_sigma_px is not None:
                prior[v], mean[v] = max(view.shift_sigma_px, 1e-3), view.shift_px
    raw = frame.uv + base[frame.view_of]  # the undistorted pixels as the run's pose sees them
    total = base.copy()
    count = np.zeros(nv)
    weight_sum = np.zeros(nv)
    scatter = np.full(nv, np.nan)
    saved = frame.uv, frame.rays, frame.noise
    frame.noise = np.full(nv, pixel)
    try:
        for _ in range(8):
            frame.uv = raw - total[frame.view_of]
            frame.rays = frame.rays_of(frame.uv)
            points, _ = frame.triangulate(groups)
            points, _ = frame.triangulate(groups, points)
            previous = total.copy()
            for v, view in enumerate(views):
                rows = np.flatnonzero(groups[:, v] >= 0)
                if not len(rows):
                    continue
                uv, z = view.project(points[rows])
                r = frame.uv[groups[rows, v]] - uv
                ok = (z > 0) & np.all(np.isfinite(r), axis=1)
                r = r[ok]
                norm = np.linalg.norm(r, axis=1)
                w = np.minimum(1.0, 2.0 * pixel / np.maximum(norm, 1e-9))
                # MAP of the total shift under its prior N(mean, prior^2): the residuals are against the shifted pixels
                total[v] = (w @ (r + total[v]) + (pixel / prior[v]) ** 2 * mean[v]) / (w.sum() + (pixel / prior[v]) ** 2)
                count[v], weight_sum[v] = len(r), w.sum()
                if len(r) >= 5:
                    size = np.sum(groups[rows[ok]] >= 0, axis=1)
                    dof = np.mean(2 * size / np.maximum(2 * size - 3, 1))  # the point took 3 of 2m coordinates
                    scatter[v] = math.sqrt(float(np.median(norm ** 2)) / (2 * math.log(2)) * dof)
            if np.max(np.abs(total - previous)) < 0.01:
                break
    finally:
        frame.uv, frame.rays, frame.noise = saved
    sigma = 1.0 / np.sqrt(weight_sum / pixel ** 2 + 1.0 / prior ** 2)
    return ViewCorrection(total, sigma, scatter, count.astype(int))


def _segment_in(frame: _Frame, i: int, j: int, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the rays of view i's undistorted pixels ``uv`` between the two heights project in view j: the ends
    (N x 2 each) and whether both lie in front of j. The pairs' EM keeps only whole segments: its mixture takes a
    candidate's distance at the two views' noise as they are, which holds where j sees the ray at about i's distance,
    not for a ray that passes behind j (pair_seeds widens those pairs' bands)."""
    lo, hi = frame.options.heights
    centre = frame.centres[i][None]
    d = frame.rays_of_view(uv, i)
    ends, front = [], np.ones(len(uv), dtype=bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for height in (lo, hi):
            t = (height - centre[:, 2]) / d[:, 2]
            t = np.where(np.isfinite(t) & (t > 0.1), t, 0.1)
            end, z = frame.views[j].project(centre + t[:, None] * d)
            ends.append(end)
            front &= z > 0
    return ends[0], ends[1], front


def _signed_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signed distance of points p from the lines a-b, where along a-b they fall (0..1 inside) and the normals."""
    s = b - a
    length = np.linalg.norm(s, axis=1)
    normal = np.c_[-s[:, 1], s[:, 0]] / length[:, None]
    return np.sum((p - a) * normal, axis=1), np.sum((p - a) * s, axis=1) / length ** 2, normal


def _ray_height(ci: np.ndarray, di: np.ndarray, cj: np.ndarray, dj: np.ndarray) -> np.ndarray:
    """The height (z) of the point of ray i (centre, unit direction; rows) nearest to ray j: where i's ray meets j's."""
    w = ci - cj
    b = np.sum(di * dj, axis=1)
    t = (b * np.sum(dj * w, axis=1) - np.sum(di * w, axis=1)) / np.maximum(1.0 - b * b, 1e-12)
    return ci[:, 2] + t * di[:, 2]


def _epipolar_offsets(frame: _Frame) -> list[tuple]:
    """Per pair (i, j): every candidate's signed distance (px) from i's ray segment in j, and how it moves with
    a shift of i's pixels (finite differences) and of j's (the segment's normal); then the height (m) where the
    candidate's ray meets i's, how it moves with the four shift coordinates (n x 4, finite differences) and with a
    pixel along the segment (m per px, its size): (i, j, d, dd/ds_i, dd/ds_j, gate, h, dh/ds, dh/dpx)."""
    out: list[tuple] = []
    for i in range(len(frame.views)):
        di = np.arange(frame.offsets[i], frame.offsets[i + 1])
        di = di[frame.valid[di]]
        if not len(di):
            continue
        for j in range(i + 1, len(frame.views)):
            tree = frame.trees[j]
            if tree is None:
                continue
            a, b, ok = _segment_in(frame, i, j, frame.uv[di])
            length = np.linalg.norm(b - a, axis=1)
            ok &= length > 1e-6
            gate = frame.options.gate_sigmas * math.hypot(frame.noise[i], frame.noise[j])
            # the detections in the disc around each segment (as a ball search finds them) that may lie in its band
            # (room for the rounding of the distance below); the others are never kept
            rows = np.flatnonzero(ok)
            found, near = near_segments(frame.uv[frame.tree_index[j]], ((a + b) / 2)[rows], length[rows] / 2 + gate,
                                        a[rows], (b - a)[rows], np.full(len(rows), gate * (1 + 1e-9) + 1e-9))
            if not len(found):
                continue
            ra = rows[found]
            p = frame.uv[frame.tree_index[j][near]]
            d, t, normal = _signed_distance(p, a[ra], b[ra])
            keep = (t > 0) & (t < 1) & (np.abs(d) <= gate)
            grad_i = np.zeros((len(d), 2))
            for axis in range(2):
                step = np.zeros(2)
                step[axis] = 1.0
                a1, b1, _ = _segment_in(frame, i, j, frame.uv[di] - step)  # as a shift of +1 moves the pixels
                grad_i[:, axis] = _signed_distance(p, a1[ra], b1[ra])[0] - d
            # A shift s_j moves j's pixels by -s_j: the distance by -normal . s_j.
            ra, p = ra[keep], p[keep]
            ci, cj = np.broadcast_to(frame.centres[i], (len(p), 3)), np.broadcast_to(frame.centres[j], (len(p), 3))
            ui = frame.uv[di[ra]]
            ray_i, ray_j = frame.rays_of_view(ui, i), frame.rays_of_view(p, j)
            h = _ray_height(ci, ray_i, cj, ray_j)
            grad_h = np.zeros((len(p), 4))
            for axis in range(2):
                step = np.zeros(2)
                step[axis] = 1.0
                grad_h[:, axis] = _ray_height(ci, frame.rays_of_view(ui - step, i), cj, ray_j) - h
                grad_h[:, 2 + axis] = _ray_height(ci, ray_i, cj, frame.rays_of_view(p - step, j)) - h
            along = (b - a)[ra] / length[ra, None]
            per_px = np.abs(np.sum(grad_h[:, 2:] * along, axis=1))
            out.append((i, j, d[keep], grad_i[keep], -normal[keep], gate, h, grad_h, per_px))
    return out


ANNEAL = (4.0, 2.0, 1.0)  # the pairs' EM with heights: its distances' variance, as a multiple of the pixels', by stage
HEIGHT_BIN_M = 0.05  # the chance candidates' heights: their histogram's bin


def pairwise_view_shifts(frame: _Frame, options: AssociateOptions, starts: int | None = None, seed: int = 0,
                         heights: bool = True, offsets: list[tuple] | None = None) -> tuple[ViewCorrection, float]:
    """Per-view shifts from the pairs alone, before any association: every pair's candidates are a mixture of
    true correspondences and chance ones. A true one's distance from the epipolar segment is the two views' pixel
    noise once the views are shifted right, and its height (where its ray meets i's) is the crowd's, a normal whose
    mean and spread the EM estimates (from ``options.height_prior`` where given, else the height range's middle); a
    chance one is uniform across the band, its height as all candidates' heights are spread (their histogram: the
    chance ones are nearly all of them). EM over that mixture, each view's shift with the run's pose sigma as its
    prior, from the run's poses and from draws of that prior, each annealed (the distances' variance widened at
    first, so that a start far from the shifts does not stop in the nearest of the many optima the crowd's chance
    pairs leave); the best penalised likelihood wins. Returns the correction and its log-likelihood gain over no
    shift. ``heights`` False: the distances alone, not annealed (``starts``: 20 then, else 4). ``offsets``: the
    frame's ``_epipolar_offsets``, where the caller has them already."""
    views = frame.views
    nv = len(views)
    prior = np.array([max(v.band_sigma_px if v.band_sigma_px is not None else v.sigma_pose_px, 1e-3)
                      for v in views])
    starts = starts if starts is not None else 4 if heights else 20
    pairs = offsets if offsets is not None else _epipolar_offsets(frame)
    if not pairs:
        return ViewCorrection(np.zeros((nv, 2)), prior, np.full(nv, np.nan), np.zeros(nv, dtype=int)), 0.0
    d = np.concatenate([p[2] for p in pairs])
    height = np.concatenate([p[6] for p in pairs])
    per_px = np.concatenate([p[8] for p in pairs])
    # Each candidate's distance and height move with four of the 2V shift coordinates (i's and j's): kept compact,
    # the normal equations are per-pair 4x4 blocks summed from precomputed outer products.
    grad = np.concatenate([np.c_[p[3], p[4]] for p in pairs])  # n x 4
    grad_h = np.concatenate([p[7] for p in pairs])  # n x 4
    cols = np.array([[2 * i, 2 * i + 1, 2 * j, 2 * j + 1] for i, j, *_rest in pairs])  # pairs x 4
    sizes = np.array([len(p[2]) for p in pairs])
    pair_of = np.repeat(np.arange(len(pairs)), sizes)
    indptr, indices = np.concatenate([[0], np.cumsum(sizes)]), np.arange(len(d))
    # the outer products' ten distinct entries (symmetric) and grad * value (and the heights' grad alone, for their
    # mean), summed per pair in one sparse product
    upper = [(r_, c_) for r_ in range(4) for c_ in range(r_, 4)]
    full = np.array([upper.index((min(r_, c_), max(r_, c_))) for r_ in range(4) for c_ in range(4)])
    sums_of = np.c_[np.stack([grad[:, r_] * grad[:, c_] for r_, c_ in upper], axis=1), grad * d[:, None]]
    sums_h_of = np.c_[np.stack([grad_h[:, r_] * grad_h[:, c_] for r_, c_ in upper], axis=1),
                      grad_h * height[:, None], grad_h]
    block_rows = np.repeat(cols, 4, axis=1).ravel()
    block_cols = np.tile(cols, (1, 4)).ravel()
    uniform = np.repeat([1.0 / (2 * p[5]) for p in pairs], sizes)
    lo, hi = options.heights
    edges = np.arange(lo - HEIGHT_BIN_M, hi + 2 * HEIGHT_BIN_M, HEIGHT_BIN_M)
    histogram, _ = np.histogram(np.clip(height, edges[0], edges[-1]), bins=edges, density=True)
    chance = uniform * np.maximum(histogram[np.clip(np.searchsorted(edges, height) - 1, 0, len(histogram) - 1)],
                                  1e-3 / (hi - lo))
    assert options.pixel_sigma is not None  # associate_views resolves it
    pixel_var = 2.0 * options.pixel_sigma ** 2
    precision = np.repeat(1.0 / prior ** 2, 2)
    least_spread = HEIGHT_BIN_M
    start_height = options.height_prior or ((lo + hi) / 2, (hi - lo) / 4)

    # Each candidate's row of the Jacobian holds its pair's four shift coordinates in order: a sparse product sums
    # grad . x in the order the terms are written, one pass over the candidates.
    jac_indices = cols[pair_of].ravel()
    jac_indptr = np.arange(0, 4 * len(d) + 1, 4)
    jac = sp.csr_matrix((grad.ravel(), jac_indices, jac_indptr), shape=(len(d), 2 * nv))
    jac_h = sp.csr_matrix((grad_h.ravel(), jac_indices, jac_indptr), shape=(len(d), 2 * nv))
    pair_sums = sp.csr_matrix((np.ones(len(d)), indices, indptr), shape=(len(pairs), len(d)))

    def moved(base, jacobian, x):
        return base + jacobian @ x

    def residual(x):
        return moved(d, jac, x)

    def blocks(w, sums_from, lhs):
        pair_sums.data = w  # the weights summed per pair: the same sparsity every step
        sums = pair_sums @ sums_from
        np.add.at(lhs, (block_rows, block_cols), sums[:, full].ravel())
        return sums[:, 10:]

    def normal_equations(w, var, wh=None, mean=0.0):
        lhs = np.zeros((2 * nv, 2 * nv))
        rhs = np.zeros(2 * nv)
        np.add.at(rhs, cols.ravel(), blocks(w / var, sums_of, lhs).ravel())
        if wh is not None:
            sums = blocks(wh, sums_h_of, lhs)
            np.add.at(rhs, cols.ravel(), (sums[:, :4] - mean * sums[:, 4:]).ravel())
        return lhs + np.diag(precision), rhs

    per_px2 = per_px ** 2

    def loglik(x, share, mean, spread, var=pixel_var, value=True, h=None):
        # h: the heights at x where the step before computed them
        r = residual(x)
        shares = np.repeat(share, sizes)  # share[pair_of]
        if heights:
            height_var = spread ** 2 + per_px2 * var
            rh = (moved(height, jac_h, x) if h is None else h) - mean
            inlier = shares * np.exp(-0.5 * (r ** 2 / var + rh ** 2 / height_var)) / (2 * math.pi
                                                                                      * np.sqrt(var * height_var))
            mix = inlier + (1 - shares) * chance
        else:
            inlier = shares * np.exp(-0.5 * r ** 2 / var) / math.sqrt(2 * math.pi * var)
            mix = inlier + (1 - shares) * uniform
        if not value:  # the EM's steps need the weights only
            return None, inlier / mix
        return float(np.sum(np.log(mix)) - 0.5 * np.sum(precision * x ** 2)), inlier / mix

    counts = np.maximum(np.bincount(pair_of, minlength=len(pairs)), 1)
    rng = np.random.default_rng(seed)
    best = None
    for start in range(starts):
        x = np.zeros(2 * nv) if start == 0 else rng.normal(0.0, np.repeat(prior, 2))
        share = np.full(len(pairs), 0.1)
        mean, spread = start_height
        h = None
        for factor in ANNEAL if heights else (1.0,):
            var = factor * pixel_var
            for _ in range(50):
                _, w = loglik(x, share, mean, spread, var, value=False, h=h)
                share = np.clip(np.bincount(pair_of, w, len(pairs)) / counts, 1e-3, 0.999)
                # r = d + J x, rh = h + J_h x - mean: the weighted least squares with the prior, then the heights'
                # mean and spread (their excess over what the pixels' noise gives) under the new shifts
                wh = w / (spread ** 2 + per_px2 * var) if heights else None
                lhs, rhs = normal_equations(w, var, wh, mean)
                new = np.linalg.solve(lhs, -rhs)
                if wh is not None:  # the distances alone (no heights) leave their mean and spread unused
                    h = moved(height, jac_h, new)
                    mean = float(np.sum(wh * h) / max(np.sum(wh), 1e-12))
                    excess = float(np.sum(w * ((h - mean) ** 2 - per_px2 * var)) / max(np.sum(w), 1e-12))
                    spread = min(max(math.sqrt(max(excess, 0.0)), least_spread), (hi - lo) / 2)
                done = np.max(np.abs(new - x)) < 0.01
                x = new
                if done:
                    break
        value, w = loglik(x, share, mean, spread)
        if best is None or value > best[0]:
            best = (value, x, w, share, mean, spread)
    assert best is not None  # the loop above runs at least once
    value, x, w, share, mean, spread = best
    zero = loglik(np.zeros(2 * nv), share, mean, spread)[0]
    lhs, _ = normal_equations(w, pixel_var, w / (spread ** 2 + per_px ** 2 * pixel_var) if heights else None, mean)
    cov = np.linalg.inv(lhs)
    sigma = np.sqrt(np.maximum(cov[0::2, 0::2].diagonal(), cov[1::2, 1::2].diagonal()))
    r = residual(x)
    count = np.zeros(nv)
    per_pair = np.bincount(pair_of, w, len(pairs))
    for k, (i, j, *_rest) in enumerate(pairs):
        count[i] += per_pair[k]
        count[j] += per_pair[k]
    if heights:
        logger.debug("pairs' EM: the crowd's heights %.2f +- %.2f m", mean, spread)
    # A pair's distance carries both views' noise: per view and coordinate, half its variance.
    scatter = np.full(nv, math.sqrt(float(np.sum(w * r ** 2) / max(w.sum(), 1e-9)) / 2.0))
    return ViewCorrection(x.reshape(nv, 2), sigma, scatter, count.astype(int)), value - zero


def _apply_correction(views: list[View], correction: ViewCorrection, options: AssociateOptions) -> None:
    """Shift each view's detections and tighten its band to what the shift leaves: the shift's own uncertainty plus
    whatever scatter the groups show beyond the detector's noise, never wider than the run's band."""
    pixel = options.pixel_sigma
    assert pixel is not None  # associate_views resolves it
    for v, view in enumerate(views):
        if view.band_sigma_px is None:
            view.band_sigma_px = view.sigma_pose_px
        band = view.band_sigma_px
        scatter = correction.scatter_px[v]
        if correction.members[v] < options.self_calibration_min_members or not math.isfinite(scatter):
            continue  # too few groups see this view to say anything: it keeps the run's pose and band
        excess = max(scatter ** 2 - pixel ** 2, 0.0)
        view.shift_px = correction.shift_px[v].copy()
        view.shift_sigma_px = float(correction.shift_sigma_px[v])
        view.sigma_pose_px = float(min(band, math.sqrt(correction.shift_sigma_px[v] ** 2 + excess)))
        logger.info("%s: shift (%.2f, %.2f) px +- %.2f from %d members, scatter %.2f px, sigma %.2f -> %.2f px",
                    view.name, *view.shift_px, correction.shift_sigma_px[v], correction.members[v], scatter, band,
                    view.sigma_pose_px)


def _warn_beyond_band(views: list[View]) -> None:
    """Say where the shifts a frame keeps move a view beyond its run's band (a start or round the frame rejects
    says nothing about the run's pose)."""
    for view in views:
        band, moved = view.band_sigma_px, float(np.linalg.norm(view.shift_px))
        if band is not None and band > 0 and moved > 3.03 * band:  # outside the 99 % circle of the band's 2D normal
            logger.warning("%s: the crowd moves its pixels by %.1f px, beyond its pose sigma of %.1f px; the run's "
                           "pose of this image is worse than its band says", view.name, moved, band)


def _confident(members: np.ndarray, scores: np.ndarray, options: AssociateOptions) -> np.ndarray:
    """The groups a correction may rest on: three or more views, scoring above the self-calibration's threshold."""
    return members[confident_rows(members, scores, options.self_calibration_min_score)]


def _corrected(views: list[View], correction: ViewCorrection, options: AssociateOptions) -> list[View]:
    trial = [copy.copy(v) for v in views]
    for view in trial:
        if view.band_sigma_px is None:
            view.band_sigma_px = view.sigma_pose_px
    _apply_correction(trial, correction, options)
    return trial
