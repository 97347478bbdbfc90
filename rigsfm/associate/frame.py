"""One frame's stacked detections (``_Frame``) and their arithmetic: rays, triangulation, growth, verification,
scores, and the hypotheses grown from the pair seeds and from an earlier frame's persons."""

from __future__ import annotations

import copy
import logging
import math

import numpy as np
from scipy.spatial import cKDTree

from rigsfm.associate.appearance import AppearanceModel
from rigsfm.associate.occupancy import CountGrid
from rigsfm.associate.options import AssociateOptions
from rigsfm.associate.packing import _pack
from rigsfm.associate.rows import _rowwise, _unique_inverse, _unique_rows, _Verified, confident_rows
from rigsfm.associate.segments import pair_seeds
from rigsfm.associate.tracked import predicted_groups, row_pairs
from rigsfm.associate.views import View
from rigsfm.core.ground import undistort_pixels

logger = logging.getLogger(__name__)


def _inverse3_symmetric(a00: np.ndarray, a01: np.ndarray, a02: np.ndarray, a11: np.ndarray, a12: np.ndarray,
                        a22: np.ndarray) -> np.ndarray:
    """Inverses (N x 3 x 3) of symmetric 3x3 matrices given by their six entries (N each), by their adjugates (many
    small matrices: faster than LAPACK; entry by entry, without the strided reads of an N x 3 x 3 stack)."""
    c00, c11, c22 = a11 * a22 - a12 * a12, a00 * a22 - a02 * a02, a00 * a11 - a01 * a01
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c12 = a02 * a01 - a00 * a12
    det = a00 * c00 + a01 * c01 + a02 * c02
    out = np.empty((len(a00), 3, 3))
    out[:, 0, 0], out[:, 1, 1], out[:, 2, 2] = c00 / det, c11 / det, c22 / det
    out[:, 0, 1] = out[:, 1, 0] = c01 / det
    out[:, 0, 2] = out[:, 2, 0] = c02 / det
    out[:, 1, 2] = out[:, 2, 1] = c12 / det
    return out


class _Frame:
    """The stacked detections of one frame's views."""

    def __init__(self, views: list[View], options: AssociateOptions, appearance: AppearanceModel | None = None,
                 earlier: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None):
        self.views = views
        # an earlier frame's persons (points, covariances, views seen in) of the same cameras: this frame's are near
        self.earlier = earlier if earlier is not None and len(earlier[0]) else None
        self._among: np.ndarray | None = None  # the detections the pair seeds are searched among (None: all)
        self.options = options
        self.appearance = appearance if views and all(v.descriptor is not None for v in views) else None
        self.descriptors = np.concatenate([v.descriptor for v in views]) if self.appearance is not None else None  # type: ignore[misc]
        pixel = options.pixel_sigma
        assert pixel is not None  # associate_views resolves it
        self.noise = np.array([math.sqrt(v.sigma_pose_px ** 2 + pixel ** 2) for v in views])
        counts = [len(v.xy) for v in views]
        self.offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.view_of = np.repeat(np.arange(len(views)), counts)
        undist, rays = [], []
        for v in views:
            if len(v.xy):
                uv = undistort_pixels(v.camera, v.xy) - v.shift_px[None]
                d = np.c_[(uv - v.k[:2, 2]) / np.array([v.k[0, 0], v.k[1, 1]]), np.ones(len(uv))] @ v.r
                d /= np.linalg.norm(d, axis=1, keepdims=True)
            else:
                uv, d = np.zeros((0, 2)), np.zeros((0, 3))
            undist.append(uv)
            rays.append(d)
        self.uv = np.concatenate(undist) if undist else np.zeros((0, 2))
        self.rays = np.concatenate(rays) if rays else np.zeros((0, 3))
        self._by_axis: tuple[np.ndarray, np.ndarray] | None = None  # rays_by_axis, and of which rays
        self._rows: tuple[np.ndarray, ...] | None = None  # _per_row's arrays, and of which noises
        self.k_of = np.array([v.k for v in views]) if views else np.zeros((0, 3, 3))
        self.r_of = np.array([v.r for v in views]) if views else np.zeros((0, 3, 3))
        self._gram = self.r_of @ np.transpose(self.r_of, (0, 2, 1))  # each rotation's rows' dot products
        self.valid = np.all(np.isfinite(self.uv), axis=1)
        self.centres = np.array([v.centre for v in views])
        self.focals = np.array([v.focal for v in views])
        self.trees = [cKDTree(u[np.all(np.isfinite(u), axis=1)]) if len(u) else None for u in undist]
        self.grids = [CountGrid(u[np.all(np.isfinite(u), axis=1)]) if len(u) else None for u in undist]
        self.tree_index = [np.flatnonzero(np.all(np.isfinite(u), axis=1)) + self.offsets[i]
                           for i, u in enumerate(undist)]
        # Clutter density (detections per px^2) around each detection: crowds fill a band of the image (the heads'
        # heights), where a chance match is far likelier than the image's mean density says.
        self.clutter = self.clutter_among(np.ones(len(self.uv), dtype=bool))
        self.log_radius, self.radius_chance = _radius_model(views)
        # what the groups depend on in each view, to tell a frame whose views were corrected since
        self._posed = [(v.shift_px.copy(), v.sigma_pose_px, v.xy) for v in views]
        self._seeds: np.ndarray | None = None  # pair_candidates, once
        self._grown: dict[bytes | None, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        # every group verified so far and its ``_verify_steps`` (a function of the group's members alone): the
        # growth's rounds and the final check meet most groups again
        self._verified = _Verified()
        # the scores a carried frame's tracked groups took (NaN: not one), and the options, appearance and clutter
        # they were scored under
        self._scored: tuple[np.ndarray, AssociateOptions, AppearanceModel | None, np.ndarray] | None = None

    def rescored(self, views: list[View], options: AssociateOptions, appearance: AppearanceModel | None = None,
                 ) -> _Frame | None:
        """This frame under other score options or an appearance model (the views' descriptors as they are now),
        keeping the groups it grew; None where ``views`` are not its views as they were, or ``options`` change what
        the groups depend on (with the seeds' floor, the score itself: its seeds were chosen by it)."""
        geometry = ("heights", "pixel_sigma", "gate_sigmas", "member_gate", "clutter_radius_px")
        if len(views) != len(self.views) or any(a is not b for a, b in zip(views, self.views)):
            return None
        moved = any(not np.array_equal(shift, v.shift_px) or sigma != v.sigma_pose_px or xy is not v.xy
                    for (shift, sigma, xy), v in zip(self._posed, views))
        if moved or any(getattr(options, name) != getattr(self.options, name) for name in geometry):
            return None
        if self.options.seed_min_score is not None or options.seed_min_score is not None:
            return None
        frame = copy.copy(self)
        frame.options = options
        views = self.views
        frame.appearance = appearance if views and all(v.descriptor is not None for v in views) else None
        frame.descriptors = np.concatenate([v.descriptor for v in views]) if frame.appearance is not None else None  # type: ignore[misc]
        frame.clutter = self.clutter_among(np.ones(len(self.uv), dtype=bool))
        return frame

    def clutter_among(self, free: np.ndarray) -> np.ndarray:
        """Per detection, the density (per px^2) of the ``free`` detections of its view within the clutter radius:
        the chance matches it competes with."""
        radius = self.options.clutter_radius_px
        out = np.zeros(len(self.uv))
        for i, view in enumerate(self.views):
            rows = self.tree_index[i]
            mine = rows[free[rows]]
            if not len(rows):
                continue
            near = cKDTree(self.uv[mine]).query_ball_point(self.uv[rows], radius, return_length=True) \
                if len(mine) else np.zeros(len(rows))
            out[rows] = np.maximum(np.maximum(near, 1) / (math.pi * radius ** 2), 1.0 / (view.width * view.height))
        return out

    def rays_by_axis(self) -> np.ndarray:
        """The rays coordinate-major (3 x N, contiguous: the triangulation gathers them so), of ``self.rays`` as it
        is now (the shifts' estimate sets other rays for a while)."""
        if self._by_axis is None or self._by_axis[0] is not self.rays:
            self._by_axis = (self.rays, np.ascontiguousarray(self.rays.T))
        return self._by_axis[1]

    def _per_row(self, g: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The views' centres (g V x 3), focals and noises (g x V each) repeated for g rows, of ``self.noise`` as
        it is now: arrays of the rows' shape (a row of V broadcast runs inner loops of V elements)."""
        held = self._rows
        if held is None or held[0] is not self.noise or len(held[2]) < g:
            n = max(g, len(held[2]) if held is not None else 0)
            nv = len(self.views)
            held = self._rows = (self.noise, np.tile(self.centres, (n, 1)),
                                 np.ascontiguousarray(np.broadcast_to(self.focals[None], (n, nv))),
                                 np.ascontiguousarray(np.broadcast_to(self.noise[None], (n, nv))))
        return held[1][:g * len(self.views)], held[2][:g], held[3][:g]

    def rays_of(self, uv: np.ndarray) -> np.ndarray:
        """Unit world directions of undistorted pixels (one per detection, in the stacked order)."""
        k, r = self.k_of[self.view_of], self.r_of[self.view_of]
        normalised = (uv - k[:, :2, 2]) / np.stack([k[:, 0, 0], k[:, 1, 1]], axis=1)
        d = np.einsum("ni,nij->nj", np.c_[normalised, np.ones(len(uv))], r)
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def rays_of_view(self, uv: np.ndarray, v: int) -> np.ndarray:
        """Unit world directions of undistorted pixels of view v."""
        k, r = self.k_of[v], self.r_of[v]
        d = np.c_[(uv - k[:2, 2]) / np.array([k[0, 0], k[1, 1]]), np.ones(len(uv))] @ r
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    # --- geometry --------------------------------------------------------------------------------------------

    def ray_points(self, det: np.ndarray, height: float) -> np.ndarray:
        """Where each detection's ray meets z = height (in front: t >= a small positive distance)."""
        c = self.centres[self.view_of[det]]
        d = self.rays[det]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (height - c[:, 2]) / d[:, 2]
        t = np.where(np.isfinite(t) & (t > 0.1), t, 0.1)
        return c + t[:, None] * d

    @_rowwise
    def triangulate(self, members: np.ndarray, points: np.ndarray | None = None,
                    ) -> tuple[np.ndarray, np.ndarray]:
        """Weighted ray intersection of each row's members (G x V, -1: none); returns points and covariances."""
        g, nv = members.shape
        present = members >= 0
        # coordinate-major (3 x G x V): the sums over the views run on contiguous rows
        d = np.take(self.rays_by_axis(), np.where(present, members, 0), axis=1)
        dc = np.einsum("igv,vi->gv", d, self.centres)
        centres, focals, noise = self._per_row(g)
        for _ in range(2 if points is None else 1):
            if points is None:
                depth = np.ones((g, nv))
            else:
                # 3 x G x V, laid out as the broadcast of points.T and centres.T leaves it (the sum below adds in
                # the order its layout sets), from one flat subtraction
                diff = (np.repeat(points, nv, axis=0) - centres).reshape(g, nv, 3).transpose(2, 0, 1)
                depth = np.maximum(np.sqrt(np.einsum("igv,igv->gv", diff, diff)), 0.1)
            # A ray's lateral sigma (m) at the point: its angular noise times the distance.
            w = np.where(present, (focals / (depth * noise)) ** 2, 0.0)
            wd = w[None] * d
            # the normal matrix entry by entry (symmetric: six sums over the views): the weights' sum on the
            # diagonal, and a ridge of 1e-9 of the trace there
            s = w.sum(axis=1)
            y = {(r_, c_): np.einsum("gv,gv->g", wd[r_], d[c_])
                 for r_, c_ in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))}
            a00, a11, a22 = -y[0, 0] + s, -y[1, 1] + s, -y[2, 2] + s
            ridge = 1e-9 * (a00 + a11 + a22)
            a00, a11, a22 = a00 + ridge, a11 + ridge, a22 + ridge
            a01, a02, a12 = -y[0, 1], -y[0, 2], -y[1, 2]
            b = w @ self.centres - np.einsum("igv,gv->gi", wd, dc)
            covariance = _inverse3_symmetric(a00, a01, a02, a11, a12, a22)
            points = np.einsum("gij,gj->gi", covariance, b)
        return points, covariance  # type: ignore[return-value]  # the loop sets points

    @_rowwise
    def residuals(self, members: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Squared reprojection distance of each member over its noise (G x V; NaN where no member)."""
        out = np.full(members.shape, np.nan)
        for v, view in enumerate(self.views):
            rows = np.flatnonzero(members[:, v] >= 0)
            if not len(rows):
                continue
            uv, z = view.project(points[rows])
            seen = self.uv[members[rows, v]]
            dx, dy = uv[:, 0] - seen[:, 0], uv[:, 1] - seen[:, 1]  # the sum over an axis of two, column by column
            out[rows, v] = np.where(z > 0, (dx * dx + dy * dy) / self.noise[v] ** 2, np.inf)
        return out

    # --- hypotheses ------------------------------------------------------------------------------------------

    def pair_candidates(self, among: np.ndarray | None = None) -> np.ndarray:
        """Seeds (S x V members): every pair (i, j) whose detection in j lies in the band of i's ray segment;
        ``among``: only pairs of these detections (a mask over the stacked ones), None: all."""
        lo, hi = self.options.heights
        gate = self.options.gate_sigmas
        seeds = []
        for i, _vi in enumerate(self.views):
            di = np.arange(self.offsets[i], self.offsets[i + 1])
            di = di[self.valid[di] if among is None else self.valid[di] & among[di]]
            if not len(di):
                continue
            p_lo, p_hi = self.ray_points(di, lo), self.ray_points(di, hi)
            for j in range(i + 1, len(self.views)):
                dj = None if among is None else self.tree_index[j][among[self.tree_index[j]]]
                found = pair_seeds(self, i, j, di, p_lo, p_hi, gate, dj)
                if found is None:
                    continue
                ra, cb, keep = found
                m = np.full((int(keep.sum()), len(self.views)), -1, dtype=np.int64)
                m[:, i] = di[ra[keep]]
                m[:, j] = cb[keep]
                seeds.append(m)
        if not seeds:
            return np.zeros((0, len(self.views)), dtype=np.int64)
        return np.concatenate(seeds)

    @_rowwise
    def grow(self, members: np.ndarray, points: np.ndarray, covariance: np.ndarray, single: bool = False,
             ) -> np.ndarray:
        """Add, in every view without a member, the detection nearest the point's projection within the gate.
        ``single``: only the nearest of all views' (a pair's point is loose along its rays, so its projection in a
        third view is long and a crowd puts wrong heads in it; the third member pins the point for the others)."""
        members = members.copy()
        gate2 = self.options.member_gate ** 2
        one_view = np.full(len(members), -1, dtype=np.int64)
        one_det = np.full(len(members), -1, dtype=np.int64)
        one_d2 = np.full(len(members), np.inf)
        spread = None  # each row's covariance's Frobenius norm (>= its largest eigenvalue), once all views need it
        for v, view in enumerate(self.views):
            rows = np.flatnonzero(members[:, v] < 0)
            if not len(rows) or self.grids[v] is None:  # the search below is the grid's
                continue
            at = points[rows]
            uv, z = view.project(at)
            front = (z > 0) & np.isfinite(uv[:, 0]) & np.isfinite(uv[:, 1])
            if not front.all():
                front = np.flatnonzero(front)  # indices: a mask's gathers of 2D rows are slower
                rows, uv, z, at = rows[front], uv[front], z[front], at[front]
            if not len(rows):
                continue
            if spread is None:
                spread = np.sqrt(np.einsum("nij,nij->n", covariance, covariance))
            # most points have no detection within any reach their covariance allows: their covariance's projection
            # is not needed (a box of a larger radius holds every cell of a smaller one's)
            near = self._may_reach(v, uv, z, spread[rows])
            if near is not None:
                near = np.flatnonzero(near)
                rows, uv, at = rows[near], uv[near], at[near]
                if not len(rows):
                    continue
            sxx, sxy, syy = view.projected_covariance(at, covariance[rows])
            sxx, syy = sxx + self.noise[v] ** 2, syy + self.noise[v] ** 2
            # 2x2 symmetric: the largest eigenvalue and the inverse in closed form
            largest = (sxx + syy) / 2 + np.sqrt(((sxx - syy) / 2) ** 2 + sxy ** 2)
            reach = np.sqrt(largest) * self.options.member_gate
            best, best_d2 = self._nearest_member(v, uv, reach + 1.0, sxx, sxy, syy, gate2)
            if not single:
                members[rows, v] = best
                continue
            better = best_d2 < one_d2[rows]
            one_view[rows[better]], one_det[rows[better]], one_d2[rows[better]] = v, best[better], best_d2[better]
        if single:
            rows = np.flatnonzero(one_view >= 0)
            members[rows, one_view[rows]] = one_det[rows]
        return members

    def _may_reach(self, v: int, uv: np.ndarray, z: np.ndarray, spread: np.ndarray) -> np.ndarray | None:
        """Which points ``uv`` of view v (depths ``z`` > 0; ``spread``: a bound of their covariance's largest
        eigenvalue) may have a detection within the growth's reach: an upper bound of the reach (the Jacobian's
        closed form, times the spread, with room for rounding) whose box holds one; None: every point (a view whose
        calibration matrix the bound does not know)."""
        k, gram = self.k_of[v], self._gram[v]
        if k[1, 0] != 0 or k[2, 0] != 0 or k[2, 1] != 0 or k[2, 2] != 1:
            return None
        fx, fy = k[0, 0], k[1, 1]
        y = (uv[:, 1] - k[1, 2]) / fy
        x = (uv[:, 0] - k[0, 2] - k[0, 1] * y) / fx
        inv = 1.0 / np.maximum(z, 1e-9)
        # J J^T of the projection's Jacobian rows fx / z (r0 - x r2) and fy / z (r1 - y r2)
        jxx = (fx * inv) ** 2 * (gram[0, 0] - 2 * x * gram[0, 2] + x * x * gram[2, 2])
        jyy = (fy * inv) ** 2 * (gram[1, 1] - 2 * y * gram[1, 2] + y * y * gram[2, 2])
        jxy = fx * fy * inv * inv * (gram[0, 1] - y * gram[0, 2] - x * gram[1, 2] + x * y * gram[2, 2])
        jacobian = (jxx + jyy) / 2 + np.sqrt(((jxx - jyy) / 2) ** 2 + jxy ** 2)
        largest = (np.abs(jacobian) * spread + self.noise[v] ** 2) * (1 + 1e-6) + 1e-12
        reach = np.sqrt(largest) * self.options.member_gate * (1 + 1e-6) + (1.0 + 1e-6)
        near = ~np.isfinite(reach)  # searched exactly (the exact reach decides)
        finite = np.flatnonzero(~near)
        near[finite] = self.grids[v].any_within(uv[finite], reach[finite])  # type: ignore[union-attr]
        return near

    def _nearest_member(self, v: int, uv: np.ndarray, bound: np.ndarray, sxx: np.ndarray, sxy: np.ndarray,
                        syy: np.ndarray, gate2: float, k: int = 4) -> tuple[np.ndarray, np.ndarray]:
        """Per point ``uv`` of view v (its projected covariance ``sxx``, ``sxy``, ``syy``), the detection nearest it
        by the covariance (-1 where none) and its squared distance (inf), among the ``k`` nearest in pixels within
        ``bound`` (those farther than the reach the gate rejects anyway), inside the gate: one pass over the grid's
        cells of every searched point's box instead of a KD-tree's search per point."""
        grid = self.grids[v]
        assert grid is not None  # views with detections have grids
        best = np.full(len(uv), -1, dtype=np.int64)
        best_d2 = np.full(len(uv), np.inf)
        searched = np.flatnonzero(np.isfinite(bound))
        query, point, euclid, dx, dy = grid.offsets_within(uv[searched], bound[searched])
        query = searched[query]
        if not len(query):
            return best, best_d2
        counts = np.bincount(query, minlength=len(uv))
        crowded = np.flatnonzero(counts[query] > k)
        if len(crowded):
            # more than k near: the k nearest only, as the tree's query returns them
            ranked = crowded[np.lexsort((euclid[crowded], query[crowded]))]
            order = np.arange(len(ranked)) - np.searchsorted(query[ranked], query[ranked])
            keep = np.ones(len(query), dtype=bool)
            keep[ranked[order >= k]] = False
            query, point, dx, dy = query[keep], point[keep], dx[keep], dy[keep]
        det = sxx * syy - sxy ** 2
        inv_xx, inv_xy, inv_yy = syy / det, -sxy / det, sxx / det  # the inverse 2x2, entry by entry
        cand = self.tree_index[v][point]
        xy = inv_xy[query]
        d2 = dx * inv_xx[query] * dx + dx * xy * dy + dy * xy * dx + dy * inv_yy[query] * dy  # x^T S^-1 x
        inside = np.flatnonzero(d2 <= gate2)
        query, cand, d2 = query[inside], cand[inside], d2[inside]
        np.minimum.at(best_d2, query, d2)
        won = d2 == best_d2[query]
        best[query[won]] = cand[won]
        return best, best_d2

    def verify(self, members: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Re-triangulate, drop members outside their band, re-triangulate: members, points, covariances."""
        return self._verify_steps(members)[:3]

    def _verify_distinct(self, members: np.ndarray, count: int = 6) -> tuple[np.ndarray, ...]:
        """``_verify_steps`` of member rows, each group computed once per frame: the rows this frame verified
        before are taken from then (row by row the same arithmetic; a row's matrix product may round otherwise in
        another batch of rows, as ``_rowwise``'s blocks and the final check's reuse already allow; rows repeated
        within ``members`` are each computed, as callers mostly pass distinct ones); the first ``count`` of them
        (those the caller reads)."""
        record = self._verified
        if not record.chunks or not len(members):
            out = self._verify_steps(members)
            if len(members):
                record.add(members, out)
            return out[:count]
        known, starts = record.chunks, record.starts
        hit = record.find(members)
        new, old = np.flatnonzero(hit < 0), np.flatnonzero(hit >= 0)
        fresh = self._verify_steps(members[new])
        out = tuple(np.empty((len(members), *f.shape[1:]), dtype=f.dtype) for f in fresh[:count])
        for o, f in zip(out, fresh):
            o[new] = f
        chunk = np.searchsorted(starts, hit[old], side="right") - 1
        for c in np.unique(chunk).tolist():
            at = old[chunk == c]
            for o, f in zip(out, known[c][1]):
                o[at] = f[hit[at] - starts[c]]
        if len(new):
            record.add(members[new], fresh)
        return out

    @_rowwise
    def _verify_steps(self, members: np.ndarray) -> tuple[np.ndarray, ...]:
        """``verify``'s members, points and covariances, and the point, covariance and squared residuals of its
        second check (where it dropped nothing, a fresh triangulation refined once and its residuals: the same)."""
        gate2 = self.options.member_gate ** 2
        points, covariance = self.triangulate(members)
        for _ in range(2):
            d2 = self.residuals(members, points)
            worst = np.nanargmax(np.where(np.isnan(d2), -1.0, d2), axis=1)
            rows = np.arange(len(members))
            bad = d2[rows, worst] > gate2
            members = members.copy()
            members[rows[bad], worst[bad]] = -1
            checked = points, covariance, d2
            points, covariance = self.triangulate(members, points)
        return members, points, covariance, *checked

    @_rowwise
    def score(self, members: np.ndarray, points: np.ndarray, covariance: np.ndarray, misses: bool = True,
              floor: float | None = None, d2: np.ndarray | None = None) -> np.ndarray:
        """Each group's log-likelihood ratio against clutter. ``misses=False``: without the views that see its point
        and hold no member (each costs, so that is an upper bound of the full score). ``floor``: a group whose bound
        is at or below it scores -inf (its full score is at most the bound), its misses not counted. With the
        options' occlusion, each view's detection probability is its own (at most ``q``: the bound's, per member).
        ``d2``: the groups' ``residuals`` at ``points``, where the caller has them."""
        p_d = self.options.detection_probability
        assert p_d is not None  # associate_views resolves it
        occlusion = self.options.view_occlusion
        if occlusion is not None:
            p_d = occlusion.q
        lo, hi = self.options.heights
        # A person's point is a priori anywhere on the crowd's floor, at a height the crowd's persons have: the
        # likelihood integrated over it (Laplace) pays for the three coordinates the detections themselves fix.
        if self.options.height_prior is None:
            height = np.full(len(points), -math.log(hi - lo))
        else:
            mean, sigma = self.options.height_prior
            var = sigma ** 2 + np.maximum(covariance[:, 2, 2], 0.0)
            height = -0.5 * np.log(2 * math.pi * var) - 0.5 * (points[:, 2] - mean) ** 2 / var
        prior = math.log(self.options.persons_per_m2) + height + 1.5 * math.log(2 * math.pi)
        sign, logdet = np.linalg.slogdet(covariance)
        prior = prior + 0.5 * np.where(sign > 0, logdet, -np.inf)
        d2 = self.residuals(members, points) if d2 is None else d2
        present = members >= 0
        clutter = np.where(present, self.clutter[np.where(present, members, 0)], 1.0)
        per_member = math.log(p_d) - np.log(clutter) - np.log(2 * math.pi * self.noise ** 2)[None] \
            - 0.5 * np.nan_to_num(d2, nan=0.0, posinf=1e6)
        total = prior + np.sum(np.where(present, per_member, 0.0), axis=1)
        if self.log_radius is not None:
            total += self.size_log_ratio(members, points, covariance)
        appearance = self.appearance.group_log_ratio(self.descriptors, members) \
            if self.appearance is not None and self.descriptors is not None else None
        kept = None
        if floor is not None and (misses or occlusion is not None):
            # the misses and each view's occlusion (the costly part: every view's lens) only where they can matter
            kept = (total if appearance is None else total + appearance) > floor
            rows = np.flatnonzero(kept)
            miss_total = total[rows]
            self._add_misses(miss_total, points[rows], present[rows], misses)
            total[rows] = miss_total
        elif misses or occlusion is not None:
            self._add_misses(total, points, present, misses)
        if appearance is not None:
            total += appearance
        if kept is not None:
            total[~kept] = -np.inf
        return total

    @_rowwise
    def size_log_ratio(self, members: np.ndarray, points: np.ndarray, covariance: np.ndarray) -> np.ndarray:
        """Each group's log-likelihood ratio of its members' apparent head radii: one head of radius R at the point
        (log r = log f R - log distance, R shared by the members, the crowd's mean R and spread as its prior, each
        radius with the detector's noise and its distance's own) against each radius drawn from its view's."""
        assert self.log_radius is not None and self.radius_chance is not None
        opts = self.options
        mean = math.log(opts.head_radius_m if opts.head_radius_m is not None else START_HEAD_RADIUS_M)
        shared = opts.head_radius_spread ** 2 + (0.0 if opts.head_radius_m is not None else START_HEAD_RADIUS_LOG_SIGMA ** 2)
        present = members >= 0
        idx = np.where(present, members, 0)
        e = np.zeros(members.shape)
        d = np.ones(members.shape)
        for v in range(len(self.views)):
            rows = np.flatnonzero(present[:, v])
            if not len(rows):
                continue
            diff = points[rows] - self.centres[v][None]
            dist = np.maximum(np.linalg.norm(diff, axis=1), 0.1)
            u = diff / dist[:, None]
            var_log_dist = np.einsum("ni,nij,nj->n", u, covariance[rows], u) / dist ** 2
            e[rows, v] = self.log_radius[idx[rows, v]] + np.log(dist) - math.log(self.focals[v]) - mean
            d[rows, v] = opts.size_noise ** 2 + np.maximum(var_log_dist, 0.0)
        e, inv = np.where(present, e, 0.0), np.where(present, 1.0 / d, 0.0)
        a, b = inv.sum(axis=1), (e * inv).sum(axis=1)
        n = present.sum(axis=1)
        # the members' residuals share the person's R: covariance diag(d) + shared * 1 1^T (Sherman-Morrison)
        quad = (e * e * inv).sum(axis=1) - shared * b * b / (1.0 + shared * a)
        logdet = np.where(present, np.log(d), 0.0).sum(axis=1) + np.log1p(shared * a)
        person = -0.5 * (n * math.log(2 * math.pi) + logdet + quad)
        m, var = self.radius_chance[:, 0][idx], self.radius_chance[:, 1][idx]
        chance = -0.5 * (np.log(2 * math.pi * var) + (self.log_radius[idx] - m) ** 2 / var)
        return person - np.where(present, chance, 0.0).sum(axis=1)

    def _add_misses(self, total: np.ndarray, points: np.ndarray, present: np.ndarray, misses: bool = True) -> None:
        """Add, in place, the cost of every view that sees a point inside its image and holds no member (``misses``)
        and, with the options' occlusion, each member's view's own detection probability against the ``q`` the
        score counted it at."""
        occlusion = self.options.view_occlusion
        if occlusion is None:
            p_d = self.options.detection_probability
            assert p_d is not None  # associate_views resolves it
            miss = math.log(max(1.0 - p_d, 1e-6))
            for v, view in enumerate(self.views):
                uv, z = view.project(points)
                seen = view.inside(uv, z) & ~present[:, v]
                total += np.where(seen, miss, 0.0)
            return
        log_q = math.log(occlusion.q)
        for v, view in enumerate(self.views):
            uv, z = view.project(points)
            at = np.flatnonzero((view.inside(uv, z) & misses) | present[:, v])
            if not len(at):
                continue
            p = occlusion.probability(np.repeat(self.centres[v][None], len(at), axis=0), points[at])
            member = present[at, v]
            total[at[member]] += np.log(np.maximum(p[member], 1e-6)) - log_q
            if misses:
                total[at[~member]] += np.log(np.maximum(1 - p[~member], 1e-6))

    @_rowwise
    def seen(self, points: np.ndarray) -> np.ndarray:
        """How many views see each point inside their image (G)."""
        count = np.zeros(len(points), dtype=np.int64)
        for view in self.views:
            uv, z = view.project(points)
            count += view.inside(uv, z)
        return count

    def hypotheses(self, free: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Candidate persons (members, points, covariances, scores: -inf at or below the options' minimum score);
        ``free``: only among these detections."""
        # The groups depend on the views' geometry and ``free`` only, not on what the score weighs (the detection
        # probability, the heights' prior, the appearance, the clutter): a frame associated again with other rates
        # or an appearance model re-scores the groups it already grew (not under the seeds' floor, which the score
        # sets).
        key = None if free is None else free.tobytes()
        grown = self._grown.get(key)
        if grown is None:
            grown = self._grown_hypotheses(free)
            self._grown = {k: g for k, g in self._grown.items() if k is None}  # the first pass's, and this one
            self._grown[key] = grown
        members, points, covariance = grown
        # those at or below the minimum score are left out by every caller: -inf, their misses not counted
        known = self._scored[0] if key is None and self._scored is not None and all(
            a is b for a, b in zip(self._scored[1:], (self.options, self.appearance, self.clutter))) else None
        if known is None:
            return members, points, covariance, self.score(members, points, covariance, floor=self.options.min_score)
        # the tracked groups were scored so already (a row's score is a function of the row alone)
        scores = known.copy()
        rows = np.flatnonzero(np.isnan(known))
        scores[rows] = self.score(members[rows], points[rows], covariance[rows], floor=self.options.min_score)
        return members, points, covariance, scores

    def _grown_hypotheses(self, free: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The groups of ``hypotheses`` before their scores."""
        if self.earlier is not None and self.options.walk_m is not None:
            if free is None:
                return self._tracked_hypotheses()
            if self._among is not None and None in self._grown:
                # the second pass: the first pass's groups on the free detections, checked again (grown once: the
                # tracked groups and the pairs among the rest already hold what the free pairs would grow into)
                members = self._grown[None][0]
                members = np.where((members >= 0) & ~free[np.maximum(members, 0)], -1, members)
                return self._checked(_unique_rows(members)[0])
        return self._grown_from_pairs(free)

    def _tracked_hypotheses(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The groups of a frame with an earlier frame's persons: grown from the detections nearest where each
        earlier person was (``tracked.predicted_groups``, the row verified and every two of its members as a pair
        seed), scored and packed; the detections of the confident ones packed (three or more views, as the
        self-calibration's) are theirs, and the pairs are searched among the others only (the pairs grow with the
        square of the detections they are searched among). Every group goes on to the frame's own packing: the
        earlier frame says where to look, this frame's evidence what is kept."""
        earlier, covariance, seen = self.earlier  # type: ignore[misc]  # the caller's test
        rows = predicted_groups(self, earlier, covariance, seen, self.options.walk_m)  # type: ignore[arg-type]
        total = int(self.offsets[-1])
        if not len(rows):
            return self._grown_from_pairs(None)
        members, points, covariance = self._verify_distinct(rows, 3)
        keep = np.sum(members >= 0, axis=1) >= 2
        pairs = self._gated(row_pairs(rows), None)
        members = np.concatenate([members[keep], pairs[0]])
        points, covariance = np.concatenate([points[keep], pairs[1]]), np.concatenate([covariance[keep], pairs[2]])
        members, first = _unique_rows(members)
        # one round of growth: the rows are whole persons already, and their pairs grow back into them
        tracked = self._grown_from(members, points[first], covariance[first], None, rounds=1)
        scores = self.score(*tracked, floor=self.options.min_score)
        above = np.flatnonzero(scores > self.options.min_score)
        chosen = above[_pack(tracked[0][above], scores[above] - self.options.min_score, total,
                             self.options.time_limit_s)]
        held = tracked[0][chosen]
        # only the confident ones hold their detections (three or more views, as the self-calibration trusts): a
        # weak group found again is the frame before's wrong person as often as not, and held, its detections would
        # hide the right pairs from the search
        held = held[confident_rows(held, scores[chosen], self.options.self_calibration_min_score)]
        self._among = np.ones(total, dtype=bool)
        self._among[held[held >= 0]] = False
        rest = self._grown_from_pairs(self._among)
        logger.info("%d of %d earlier persons found again, holding %d of %d detections; %d pair seeds among the rest",
                    len(chosen), len(earlier), int(total - self._among.sum()), total,
                    len(self._seeds) if self._seeds is not None else 0)
        members = np.concatenate([tracked[0], rest[0]])
        members, first = _unique_rows(members)
        known = np.full(len(members), np.nan)
        mine = first < len(tracked[0])
        known[mine] = scores[first[mine]]
        self._scored = (known, self.options, self.appearance, self.clutter)
        return members, np.concatenate([tracked[1], rest[1]])[first], np.concatenate([tracked[2], rest[2]])[first]

    def _grown_from_pairs(self, free: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The groups grown from the pair seeds among ``free`` (None: all detections)."""
        if self._seeds is None:
            self._seeds = self.pair_candidates(self._among)
        seeds = self._seeds
        if free is not None:
            seeds = seeds[np.all((seeds < 0) | free[np.maximum(seeds, 0)], axis=1)]
        if not len(seeds):
            empty = np.zeros((0, len(self.views)), dtype=np.int64)
            return empty, np.zeros((0, 3)), np.zeros((0, 3, 3))
        # among what the tracked persons leave, one round: a second round's groups are alternatives to the first's
        # that the packing does not keep there (benchmarks/README.md, fourteenth pass)
        return self._grown_from(*self._gated(seeds, self.options.seed_min_score), free,
                                rounds=1 if self._among is not None else 2)

    def _gated(self, seeds: np.ndarray, floor: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The seeds whose point lies between the heights with every member inside its gate (and, with a ``floor``,
        whose own score, its misses left out, exceeds it): members, points, covariances."""
        points, covariance = self.triangulate(seeds)
        lo, hi = self.options.heights
        d2 = self.residuals(seeds, points)
        ok = (points[:, 2] >= lo) & (points[:, 2] <= hi) & np.all(
            np.nan_to_num(d2, nan=0.0) <= self.options.member_gate ** 2, axis=1)
        members = seeds[ok]
        points, covariance = points[ok], covariance[ok]
        if floor is not None:
            strong = self.score(members, points, covariance, misses=False, floor=floor, d2=d2[ok]) > floor
            members, points, covariance = members[strong], points[strong], covariance[strong]
        return members, points, covariance

    def _grown_from(self, members: np.ndarray, points: np.ndarray, covariance: np.ndarray,
                    free: np.ndarray | None, rounds: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Groups grown from ``members`` (their points and covariances) into the other views' ``free`` detections
        (None: all), ``rounds`` times, each verified; every distinct group met on the way, verified again."""

        def only_free(m: np.ndarray) -> np.ndarray:
            return m if free is None else np.where((m >= 0) & ~free[np.maximum(m, 0)], -1, m)

        lo, hi = self.options.heights
        groups = [members]
        for _ in range(rounds):
            members = only_free(self.grow(members, points, covariance, single=True))
            points, covariance = self.triangulate(members, points)
            members = only_free(self.grow(members, points, covariance))
            # a group's verification depends on its members alone: each distinct group verified once
            distinct, which = _unique_inverse(members)
            members, points, covariance = (a[which] for a in self._verify_distinct(distinct, 3))
            groups.append(members)
            # seeds of one person grow into the same group: grow each group once
            members, first = _unique_rows(members)
            points, covariance = points[first], covariance[first]
        return self._checked(_unique_rows(np.concatenate(groups))[0])

    def _checked(self, members: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The distinct groups of two or more members (``members``: distinct rows) verified, between the heights,
        every member inside its gate: members, points, covariances."""
        lo, hi = self.options.heights
        members = members[np.sum(members >= 0, axis=1) >= 2]
        if not len(members):
            return members, np.zeros((0, 3)), np.zeros((0, 3, 3))
        verified, _, _, once, once_covariance, once_d2 = self._verify_distinct(members)
        unchanged = np.all(verified == members, axis=1)
        keep = np.sum(verified >= 0, axis=1) >= 2
        members, first = _unique_rows(verified[keep])
        # A fresh triangulation, refined once, and its residuals: what the verification computed already for the
        # groups it left as they were (the same function of the members); the others anew.
        fresh = ~unchanged[keep][first]
        rows = np.flatnonzero(keep)[first]
        points, covariance, d2 = once[rows], once_covariance[rows], once_d2[rows]
        if fresh.any():
            again, again_covariance = self.triangulate(members[fresh])
            again, again_covariance = self.triangulate(members[fresh], again)
            points[fresh], covariance[fresh] = again, again_covariance
            d2[fresh] = self.residuals(members[fresh], again)
        inside = np.all(np.nan_to_num(d2, nan=0.0) <= self.options.member_gate ** 2, axis=1)
        ok = (points[:, 2] >= lo) & (points[:, 2] <= hi) & inside
        return members[ok], points[ok], covariance[ok]


START_HEAD_RADIUS_M = 0.1  # the crowd's mean head radius assumed until its persons say otherwise
START_HEAD_RADIUS_LOG_SIGMA = 0.3  # its uncertainty (relative) until then


def _radius_model(views: list[View]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The stacked detections' log radii and, per detection, the mean and variance of a chance match's log radius
    there: a line in the image row fitted to its view's (the crowd's heads stand at similar heights, so a head's row
    already says much of its distance; a chance match's radius is another head's at that row); None where a view has
    no radii (the cue is off)."""
    if not views or any(v.radius_px is None for v in views):
        return None, None
    logs, chance = [], []
    for v in views:
        lr = np.log(np.asarray(v.radius_px, dtype=np.float64))
        row = v.xy[:, 1] / max(v.height, 1)
        if len(lr) >= 4:
            a = np.c_[np.ones(len(lr)), row]
            coef = np.linalg.lstsq(a, lr, rcond=None)[0]
            mean = a @ coef
            var = max(float(np.sum((lr - mean) ** 2)) / (len(lr) - 2), 0.03 ** 2)
        else:
            mean, var = np.full(len(lr), float(np.mean(lr)) if len(lr) else 0.0), 0.5 ** 2
        logs.append(lr)
        chance.append(np.c_[mean, np.full(len(lr), var)])
    return np.concatenate(logs), np.concatenate(chance).reshape(-1, 2)
