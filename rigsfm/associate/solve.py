"""Multi-view association of point detections (heads) in synchronised narrow images into 3D persons.

Per frame:

1. Each detection becomes a ray (undistorted through its camera, in the run's world frame). Each view gets a pose
   sigma in pixels from the run's calibrated 95 % bands (``band_ij / 1.96`` squared = ``s_i^2 + s_j^2``, solved for
   the ``s`` by non-negative least squares); a detection's reprojection noise is ``s_view^2 + pixel_sigma^2``.
2. Candidates for each pair (i, j): detections of j within ``gate_sigmas`` of the segment that i's ray between the
   two heights projects to in j (the band of the epipolar line, cut to the height range), triangulated.
3. Every candidate grows into a multi-view hypothesis: in every other view the detection nearest (Mahalanobis:
   the point's projected covariance plus that view's noise) to the point's projection joins when inside the gate;
   the point is re-triangulated (weighted: each ray by its distance and noise), members whose reprojection falls
   outside their band are dropped, twice over. Hypotheses outside the height range are dropped.
4. Each hypothesis scores its log-likelihood ratio against "these detections are clutter": per member
   ``log(p_d / clutter density) - log(2 pi s^2) - d^2 / 2``, per view that sees the point inside its image and has
   no member ``log(1 - p_d)``, and once the prior density of persons in the crowd's volume times the volume the
   point's covariance leaves (``log rho + 3/2 log 2 pi + 1/2 log det Sigma``: two views fix a point much less
   than four). A global set packing (each detection in at most one person; scipy's MILP) keeps the
   set of hypotheses with the largest summed score.
5. Self-calibration: a view's pose error moves all its detections alike, by more than the heads' spacing allows a
   band to absorb. Per view a shift of its undistorted pixels (a small rotation) is estimated, first from the pairs
   (pairwise_view_shifts), then from the confident groups (estimate_view_shifts), each under the run's pose sigma as
   its prior (the pairs' from their distances alone and with where the candidates' rays meet, the crowd's heights:
   whichever associates into more confident groups); the frame is associated again with the shifted views and the
   bands the shift leaves. A correction is kept only where it leaves more confident groups than before.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import logging
import math
from dataclasses import dataclass, field

import numpy as np
import pycolmap
import scipy.optimize
import scipy.sparse as sp
from scipy.spatial import cKDTree

from rigsfm.associate.appearance import AppearanceModel, describe, estimate, head_radius_px
from rigsfm.associate.occupancy import CountGrid
from rigsfm.associate.options import AssociateOptions
from rigsfm.associate.rates import truncated_binomial_p
from rigsfm.associate.segments import near_segments, pair_seeds
from rigsfm.associate.tracked import predicted_groups, row_pairs, seen_before
from rigsfm.core.ground import undistort_pixels

logger = logging.getLogger(__name__)

BAND_Z = 1.959964  # the bands are 95 % two-sided half-widths of a normal distance


@dataclass
class View:
    """One narrow image of a frame: its pinhole (undistorted) projection and its detections."""

    name: str
    k: np.ndarray  # 3x3
    r: np.ndarray  # 3x3 cam_from_world rotation
    t: np.ndarray  # 3
    centre: np.ndarray  # 3, world
    width: int
    height: int
    camera: pycolmap.Camera
    xy: np.ndarray  # N x 2 raw COLMAP pixels
    sigma_pose_px: float = 0.0
    centre_sigma_m: float = 0.0  # the camera centre's 1 sigma relative to the network (the run's uncertainty)
    centre_covariance_m2: np.ndarray | None = None  # its 3x3 covariance (world axes), where the run delivers it
    # The crowd's own correction of the run's pose error (a shift of the undistorted pixels, i.e. a small rotation
    # for a narrow camera) and the band sigma before it.
    shift_px: np.ndarray = field(default_factory=lambda: np.zeros(2))
    band_sigma_px: float | None = None
    shift_sigma_px: float | None = None  # the shift's own posterior sigma (None: not estimated)
    grey: np.ndarray | None = None  # the image's greys, where readable (the appearance cue)
    descriptor: np.ndarray | None = None  # N x D appearance of its detections (rigsfm.associate.appearance)
    head_px: float | None = None  # the apparent head radius its descriptors were sampled at (None: not described)
    radius_px: np.ndarray | None = None  # N: the detector's apparent head radius of each detection (px), if given

    @classmethod
    def of(cls, image: pycolmap.Image, xy: np.ndarray) -> View:
        pose = image.cam_from_world()
        camera = image.camera
        # a model's images have their cameras
        return cls(image.name, np.asarray(camera.calibration_matrix(), dtype=np.float64),  # type: ignore[union-attr]
                   pose.rotation.matrix(), np.asarray(pose.translation, dtype=np.float64),
                   # a model's images have their cameras
                   np.asarray(image.projection_center(), dtype=np.float64), camera.width, camera.height, camera,  # type: ignore[arg-type,union-attr]
                   np.asarray(xy, dtype=np.float64).reshape(-1, 2))

    def carry(self, before: View) -> None:
        """Take over what the crowd found about this camera in an earlier frame (a static camera's pose error and
        its persons' distances are the same in every frame): its shift, bands and head size."""
        self.shift_px = before.shift_px.copy()
        self.shift_sigma_px, self.sigma_pose_px = before.shift_sigma_px, before.sigma_pose_px
        self.band_sigma_px = before.band_sigma_px
        self.head_px = before.head_px

    @property
    def focal(self) -> float:
        return float(math.sqrt(abs(self.k[0, 0] * self.k[1, 1])))

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted pinhole pixels (N x 2) and depths of world points (N x 3)."""
        cam = points @ self.r.T + self.t
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            h = cam @ self.k.T
            uv = np.empty((len(h), 2))
            np.divide(h[:, 0], z, out=uv[:, 0])  # column by column: an N x 2 by N x 1 broadcast runs loops of two
            np.divide(h[:, 1], z, out=uv[:, 1])
        return uv, z

    def projected_covariance(self, points: np.ndarray, covariance: np.ndarray,
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The xx, xy and yy entries of world points' covariances (N x 3 x 3) carried into the pinhole pixels: each
        Jacobian row in closed form (a camera's row minus its depth row), no stacked matrix products."""
        cam = points @ self.r.T + self.t
        z = np.where(np.abs(cam[:, 2]) > 1e-9, cam[:, 2], 1e-9)
        a, b = np.empty((len(cam), 3)), np.empty((len(cam), 3))
        for jacobian, row, f in ((a, 0, self.k[0, 0]), (b, 1, self.k[1, 1])):
            scale, ratio = f / z, cam[:, row] / z
            for i in range(3):  # column by column: an N x 1 by 1 x 3 broadcast runs loops of three
                jacobian[:, i] = scale * (self.r[row, i] - ratio * self.r[2, i])
        ca = np.einsum("nij,nj->ni", covariance, a)
        cb = np.einsum("nij,nj->ni", covariance, b)
        return np.einsum("ni,ni->n", a, ca), np.einsum("ni,ni->n", b, ca), np.einsum("ni,ni->n", b, cb)

    def inside(self, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Where undistorted pixels fall inside the image (through the lens model) in front of the camera."""
        ok = z > 0
        if not ok.any():
            return ok
        normalised = (uv[ok] - self.k[:2, 2]) / np.array([self.k[0, 0], self.k[1, 1]])
        raw = np.asarray(self.camera.img_from_cam(np.c_[normalised, np.ones(len(normalised))]), dtype=np.float64)
        inside = np.all(np.isfinite(raw), axis=1) & (raw[:, 0] >= 0) & (raw[:, 0] <= self.width) \
            & (raw[:, 1] >= 0) & (raw[:, 1] <= self.height)
        ok[np.flatnonzero(ok)] = inside
        return ok


def view_pose_sigmas(names: list[str], bands: dict[tuple[str, str], float]) -> dict[str, float]:
    """Per view, the pose sigma (px, per coordinate) whose pairwise sums explain the pairs' 95 % bands."""
    index = {name: i for i, name in enumerate(names)}
    rows, target = [], []
    for (a, b), band in bands.items():
        if a in index and b in index and band is not None and math.isfinite(band):
            row = np.zeros(len(names))
            row[index[a]] = row[index[b]] = 1.0
            rows.append(row)
            target.append((band / BAND_Z) ** 2)
    if not rows:
        return dict.fromkeys(names, 0.0)
    matrix, target = np.asarray(rows), np.asarray(target)  # type: ignore[assignment]  # the list, as an array
    variance, _ = scipy.optimize.nnls(matrix, target)
    seen = matrix.sum(axis=0) > 0
    fallback = float(np.median(target) / 2.0)
    return {name: float(math.sqrt(variance[i] if seen[i] else fallback)) for name, i in index.items()}


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


ROWS_PER_BLOCK = 4096  # hypotheses per block of the row-wise algebra: its temporaries stay in the CPU's cache


def _rowwise(method):
    """Run a method whose array arguments and results are per hypothesis (rows) on blocks of rows: each row's
    arithmetic is the same, while the temporaries of a hundred thousand hypotheses times the views would not fit
    any cache (and their allocation alone costs more than the arithmetic)."""

    @functools.wraps(method)
    def blocked(self, *arrays, **options):
        n = len(arrays[0])
        if n <= ROWS_PER_BLOCK:
            return method(self, *arrays, **options)

        def rows(a, k):
            return a[k:k + ROWS_PER_BLOCK] if isinstance(a, np.ndarray) and a.ndim and len(a) == n else a

        parts = [method(self, *(rows(a, k) for a in arrays), **{key: rows(a, k) for key, a in options.items()})
                 for k in range(0, n, ROWS_PER_BLOCK)]
        if isinstance(parts[0], tuple):
            return tuple(np.concatenate(column) for column in zip(*parts))
        return np.concatenate(parts)

    return blocked


def _sorted_rows(members: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The order that sorts member rows (-1 or a detection) as ``np.unique(axis=0)`` does, stable, and where in it a
    row repeats the one before: the columns packed into a few integer keys sort far faster than rows compared as
    records."""
    columns = np.ascontiguousarray(members.T) + 1  # >= 0; column by column, each contiguous
    bases = columns.max(axis=1) + 1
    keys, key, room = [], np.zeros(len(members), dtype=np.int64), 1
    for c in range(members.shape[1]):
        if room * int(bases[c]) >= 2 ** 62:
            keys.append(key)
            key, room = np.zeros(len(members), dtype=np.int64), 1
        key = key * bases[c] + columns[c]
        room *= int(bases[c])
    keys.append(key)
    order = _stable_order(keys)  # stable: the first of equal rows first; the first column decides first
    repeated = np.zeros(len(order), dtype=bool)
    repeated[1:] = True
    for key in keys:
        ranked = key[order]
        repeated[1:] &= ranked[1:] == ranked[:-1]
    return order, repeated


def _stable_order(keys: list[np.ndarray]) -> np.ndarray:
    """``np.lexsort(keys[::-1])`` of non-negative integer keys (the first decides first), as a radix sort: stable
    sorts of their 16-bit digits, least significant first (a stable sort of 16-bit integers is numpy's radix sort,
    far faster than its merge sorts of 64-bit keys)."""
    order = None
    for key in keys[::-1]:
        top, shift = int(key.max()) if len(key) else 0, 0
        while shift == 0 or top >> shift:
            digit = ((key if order is None else key[order]) >> shift).astype(np.uint16)  # the low 16 bits
            step = np.argsort(digit, kind="stable")
            order = step if order is None else order[step]
            shift += 16
    return order if order is not None else np.zeros(0, dtype=np.int64)


def _unique_rows(members: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(members, axis=0, return_index=True)`` (the same rows, order and first occurrences) for member
    rows."""
    if not members.size:
        return np.unique(members, axis=0, return_index=True)
    order, repeated = _sorted_rows(members)
    first = order[~repeated]
    return members[first], first


def _unique_inverse(members: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of ``members`` (as ``_unique_rows``) and, per row, which of them it is."""
    if not members.size:
        return members, np.zeros(len(members), dtype=np.int64)
    order, repeated = _sorted_rows(members)
    rank = np.empty(len(members), dtype=np.int64)
    rank[order] = np.cumsum(~repeated) - 1
    return members[order[~repeated]], rank


_HASH_FACTORS: dict[int, np.ndarray] = {}  # per number of columns, _row_hashes' odd constants


def _row_hashes(members: np.ndarray) -> np.ndarray:
    """A 64-bit hash of each member row (-1 or a detection per column): a sum of the columns times odd constants,
    wrapping; equal rows hash alike (a hash only says which rows to compare)."""
    factors = _HASH_FACTORS.get(members.shape[1])
    if factors is None:
        drawn = np.random.default_rng(members.shape[1]).integers(0, 2 ** 63, members.shape[1], dtype=np.uint64)
        factors = _HASH_FACTORS[members.shape[1]] = np.asarray(drawn) * np.uint64(2) + np.uint64(1)
    hashes = np.zeros(len(members), dtype=np.uint64)
    for c in range(members.shape[1]):
        hashes += (members[:, c] + 1).astype(np.uint64) * factors[c]
    return hashes


class _Verified:
    """The groups a frame verified (chunks of member rows and their ``_verify_steps``), with their hashes sorted for
    lookups (shared by the frame's re-scored copies, as the list was)."""

    def __init__(self) -> None:
        self.chunks: list[tuple[np.ndarray, tuple[np.ndarray, ...]]] = []
        self.starts = np.zeros(1, dtype=np.int64)  # each chunk's first row in the chunks stacked, and their total
        self.hashes = np.zeros(0, dtype=np.uint64)  # sorted, equal ones by their position
        self.positions = np.zeros(0, dtype=np.int64)  # each one's row in the chunks, stacked

    def add(self, rows: np.ndarray, out: tuple[np.ndarray, ...]) -> None:
        held = int(self.starts[-1])
        self.chunks.append((rows, out))
        self.starts = np.append(self.starts, held + len(rows))
        hashes = np.concatenate([self.hashes, _row_hashes(rows)])
        positions = np.concatenate([self.positions, held + np.arange(len(rows))])
        order = np.argsort(hashes, kind="stable")
        self.hashes, self.positions = hashes[order], positions[order]

    def find(self, members: np.ndarray) -> np.ndarray:
        """Per row of ``members``, its row in the stacked chunks (the last of equal rows there), -1 where none."""
        starts = self.starts
        hashes = _row_hashes(members)
        last = np.maximum(np.searchsorted(self.hashes, hashes, side="right") - 1, 0)
        hit = np.where(self.hashes[last] == hashes, self.positions[last], -1) if len(self.hashes) \
            else np.full(len(members), -1, dtype=np.int64)
        found = np.flatnonzero(hit >= 0)
        chunk = np.searchsorted(starts, hit[found], side="right") - 1
        for c in np.unique(chunk).tolist():
            at = found[chunk == c]
            if not np.array_equal(self.chunks[c][0][hit[at] - starts[c]], members[at]):
                return self._sorted_find(members)  # two rows share a hash: the rows themselves decide
        return hit

    def _sorted_find(self, members: np.ndarray) -> np.ndarray:
        table = np.concatenate([rows for rows, _ in self.chunks])
        _, rank = _unique_inverse(np.concatenate([table, members]))
        where = np.full(int(rank.max()) + 1, -1, dtype=np.int64)
        where[rank[:len(table)]] = np.arange(len(table))
        return where[rank[len(table):]]


@dataclass
class FrameResult:
    """The persons of one frame: per person its point, covariance, score, confidence and member detections."""

    views: list[str]
    points: np.ndarray  # P x 3 world metres
    covariances: np.ndarray  # P x 3 x 3
    scores: np.ndarray  # P: log-likelihood ratio against clutter
    members: np.ndarray  # P x V: index of the detection in each view's list, or -1
    detection_probability: float | None = None  # the crowd's, as this frame's persons say it
    height_prior: tuple[float, float] | None = None  # mean and sigma (m) of the persons' heights, as they say it
    appearance: AppearanceModel | None = None  # the appearance cue's model, where the images gave one
    head_radius_m: float | None = None  # the crowd's mean head radius, where the detections gave radii
    # Per view, the shift (undistorted px) and band sigma the persons were found with; a carried frame's views go on
    # to hold the shifts refined from its persons, for the next frame.
    shift_px: dict[str, np.ndarray] = field(default_factory=dict)
    band_sigma_px: dict[str, float] = field(default_factory=dict)

    @property
    def confidence(self) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-np.clip(self.scores, -50, 50)))

    def __len__(self) -> int:
        return len(self.points)


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
        self.noise = np.array([math.sqrt(v.sigma_pose_px ** 2 + options.pixel_sigma ** 2) for v in views])
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
              floor: float | None = None) -> np.ndarray:
        """Each group's log-likelihood ratio against clutter. ``misses=False``: without the views that see its point
        and hold no member (each costs, so that is an upper bound of the full score). ``floor``: a group whose bound
        is at or below it scores -inf (its full score is at most the bound), its misses not counted."""
        p_d = self.options.detection_probability
        assert p_d is not None  # associate_views resolves it
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
        d2 = self.residuals(members, points)
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
        if misses and floor is not None:
            # the misses (the costly part: every view's lens) only where they can matter
            kept = (total if appearance is None else total + appearance) > floor
            rows = np.flatnonzero(kept)
            miss_total = total[rows]
            self._add_misses(miss_total, points[rows], present[rows])
            total[rows] = miss_total
        elif misses:
            self._add_misses(total, points, present)
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

    def _add_misses(self, total: np.ndarray, points: np.ndarray, present: np.ndarray) -> None:
        """Add, in place, the cost of every view that sees a point inside its image and holds no member."""
        p_d = self.options.detection_probability
        assert p_d is not None  # associate_views resolves it
        miss = math.log(max(1.0 - p_d, 1e-6))
        for v, view in enumerate(self.views):
            uv, z = view.project(points)
            seen = view.inside(uv, z) & ~present[:, v]
            total += np.where(seen, miss, 0.0)

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
        seed), scored and packed; the detections of those packed are theirs, and the pairs are searched among the
        others only (the pairs grow with the square of the detections they are searched among). Every group goes on
        to the frame's own packing: the earlier frame says where to look, this frame's evidence what is kept."""
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
        ok = (points[:, 2] >= lo) & (points[:, 2] <= hi) & np.all(
            np.nan_to_num(self.residuals(seeds, points), nan=0.0) <= self.options.member_gate ** 2, axis=1)
        members = seeds[ok]
        points, covariance = points[ok], covariance[ok]
        if floor is not None:
            strong = self.score(members, points, covariance, misses=False) > floor
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


def _pack(members: np.ndarray, scores: np.ndarray, total: int, time_limit: float) -> np.ndarray:
    """The subset of hypotheses with the largest summed score, each detection in at most one (MILP; greedy start)."""
    n = len(scores)
    if not n:
        return np.zeros(0, dtype=bool)
    rows = members[members >= 0]
    cols = np.repeat(np.arange(n), np.sum(members >= 0, axis=1))
    order = np.argsort(-scores)
    greedy = np.zeros(n, dtype=bool)
    used = bytearray(total)
    # row by row in Python's own lists: a numpy call per row costs more than the row's few members
    for g, row in zip(order.tolist(), members[order].tolist()):
        m = [d for d in row if d >= 0]
        if not any(used[d] for d in m):
            greedy[g] = True
            for d in m:
                used[d] = 1
    # Only detections claimed by two or more hypotheses constrain anything.
    a = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(total, n))
    shared = np.asarray(a.sum(axis=1)).ravel() > 1
    if not shared.any():
        return np.ones(n, dtype=bool)
    constraint = scipy.optimize.LinearConstraint(a[shared], -np.inf, 1.0)
    result = scipy.optimize.milp(-scores, constraints=[constraint], integrality=np.ones(n),
                                 bounds=scipy.optimize.Bounds(0, 1), options={"time_limit": time_limit})
    if result.x is None:
        logger.warning("set packing found no solution in %.1f s; kept the greedy one", time_limit)
        return greedy
    chosen = result.x > 0.5
    if scores[chosen].sum() < scores[greedy].sum():
        return greedy
    return chosen


def _solve(views: list[View], options: AssociateOptions, appearance: AppearanceModel | None = None,
           frame: _Frame | None = None, earlier: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
           ) -> tuple[_Frame, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """One association of a frame: hypotheses, their scores (with the appearance term where given) and the global
    packing. ``frame``: an earlier association's frame of the same ``views`` (their shifts and bands unchanged),
    whose grown groups are re-scored instead of grown again. ``earlier``: an earlier frame's persons (points,
    covariances), looked for first (``_Frame._tracked_hypotheses``)."""
    reused = frame.rescored(views, options, appearance) if frame is not None else None
    frame = _Frame(views, options, appearance, earlier) if reused is None else reused
    total = int(frame.offsets[-1])
    members, points, covariance, scores = frame.hypotheses()
    positive = scores > options.min_score
    members, points, covariance, scores = members[positive], points[positive], covariance[positive], scores[positive]
    chosen = _pack(members, scores - options.min_score, total, options.time_limit_s)
    if options.second_pass:
        # What the packing left: its hypotheses re-scored against the detections still free (a person seen in two
        # views competes with far fewer chance matches once the crowd's well-seen persons hold theirs), packed again.
        free = np.ones(total, dtype=bool)
        kept = members[chosen]
        free[kept[kept >= 0]] = False
        everyone = frame.clutter  # every detection's (the frame's own): put back after
        frame.clutter = frame.clutter_among(free)
        rest_m, rest_p, rest_c, rest_s = frame.hypotheses(free)
        more = rest_s > options.min_score
        if more.any():
            rest_m, rest_p, rest_c, rest_s = rest_m[more], rest_p[more], rest_c[more], rest_s[more]
            extra = _pack(rest_m, rest_s - options.min_score, total, options.time_limit_s)
            members = np.concatenate([members[chosen], rest_m[extra]])
            points = np.concatenate([points[chosen], rest_p[extra]])
            covariance = np.concatenate([covariance[chosen], rest_c[extra]])
            scores = np.concatenate([scores[chosen], rest_s[extra]])
            frame.clutter = everyone
            return frame, members, points, covariance, scores, int(positive.sum())
        frame.clutter = everyone
    return frame, members[chosen], points[chosen], covariance[chosen], scores[chosen], int(positive.sum())


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
    for v, view in enumerate(views):
        if view.band_sigma_px is None:
            view.band_sigma_px = view.sigma_pose_px
        band = view.band_sigma_px
        scatter = correction.scatter_px[v]
        if correction.members[v] < options.self_calibration_min_members or not math.isfinite(scatter):
            continue  # too few groups see this view to say anything: it keeps the run's pose and band
        excess = max(scatter ** 2 - options.pixel_sigma ** 2, 0.0)
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
    return members[(np.sum(members >= 0, axis=1) >= 3) & (scores > options.self_calibration_min_score)]


def _corrected(views: list[View], correction: ViewCorrection, options: AssociateOptions) -> list[View]:
    trial = [copy.copy(v) for v in views]
    for view in trial:
        if view.band_sigma_px is None:
            view.band_sigma_px = view.sigma_pose_px
    _apply_correction(trial, correction, options)
    return trial


def _centre_term(views: list[View], members: np.ndarray) -> np.ndarray:
    """Per group (G x 3 x 3), the covariance its views' own position errors add to its point.

    The cameras' position errors are shared by every person they see, so they do not shrink with more views: each
    person carries its views' mean centre covariance on top of the triangulation's; the views' errors move together
    (the network bends as a whole), so their mean is not divided by the number of views. The run's 3x3 says how the
    error leans (a ring of rigs moves more horizontally than vertically); where the run gives only the root of its
    trace, each axis holds a third of its square."""
    centre = np.array([v.centre_covariance_m2 if v.centre_covariance_m2 is not None
                       else v.centre_sigma_m ** 2 / 3.0 * np.eye(3) for v in views]).reshape(len(views), 3, 3)
    present = (members >= 0).astype(np.float64)
    return np.einsum("gv,vij->gij", present, centre) / np.maximum(present.sum(axis=1), 1)[:, None, None]


def associate_views(views: list[View], options: AssociateOptions, carried: bool = False,
                    earlier: FrameResult | None = None) -> FrameResult:
    """Persons seen by the detections of one frame's views (each view: pose, camera and raw detections).

    Every view's pose error is shared by all the persons it sees. With ``options.self_calibration_rounds`` > 0 the
    views are first shifted by the pairs' own evidence (pairwise_view_shifts: the distances alone and with the
    candidates' heights, the one whose association holds more confident groups), then, each round, by the confident
    groups of the last association (estimate_view_shifts), and the frame associated again with the shifted views
    and their tightened bands. A correction is kept only where it leaves more confident groups than before, and the
    pairs' one only where those are enough to re-estimate the shifts from (the crowd's own test of it: wrong shifts
    under tight bands break the groups up); the views are updated in place.

    ``carried``: the views already hold the shifts and head sizes of earlier frames of the same cameras (a static
    rig's pose error is the same in every frame): one association, with ``earlier``'s appearance model where it has
    one, whose confident groups refine the shifts in place for the next frame.
    ``earlier``: an earlier frame's result, whose detection probability, heights and (``carried``) appearance model
    this one takes (where ``options`` leaves them to the crowd).

    The appearance model is estimated once, from the first frame's association without it, and carried as the rates
    are: groups found under a model look alike by construction, so a model re-estimated from them would narrow frame
    by frame. A carried frame without an earlier model (or a view without a carried head size) estimates its own,
    as a first frame does, at the cost of a second association.

    ``options.seed_min_score`` holds for carried frames only: a first frame grows every pair seed (its first
    associations run at the run's wide bands, without the crowd's heights, where a seed's own score says less, and
    its self-calibration turns small changes of its groups into other shifts)."""
    names = [v.name for v in views]
    if not carried:
        options = dataclasses.replace(options, seed_min_score=None)
    given = options
    start = earlier.detection_probability if earlier is not None else None
    options = dataclasses.replace(options, detection_probability=options.detection_probability or start
                                  or START_DETECTION)
    if options.height_prior is None and earlier is not None:
        options = dataclasses.replace(options, height_prior=earlier.height_prior)
    if options.head_radius_m is None and earlier is not None and earlier.head_radius_m is not None:
        options = dataclasses.replace(options, head_radius_m=earlier.head_radius_m)
    model = _carried_appearance(views, options, earlier) if carried else None
    # a carried frame's persons are near the frame before's (the same cameras, a fraction of a second later)
    before = (earlier.points, earlier.covariances, seen_before(earlier.views, earlier.members, names)) \
        if carried and earlier is not None and options.walk_m is not None and len(earlier) else None
    state = _solve(views, options, model, earlier=before)
    count = len(_confident(state[1], state[4], options))
    pending: ViewCorrection | None = None
    if carried:
        # The views hold earlier frames' shifts: associate once with them, and pool this frame's groups into the
        # shifts for the next frame (the frame is not associated again: the next one gains, at no extra cost).
        confident = _confident(state[1], state[4], options)
        if options.self_calibration_rounds > 0 and len(confident) >= options.self_calibration_min_members:
            pending = estimate_view_shifts(state[0], confident, options, pooled=True)
    elif options.self_calibration_rounds > 0 and len(views) >= 3:
        # Two starts, each associated once and the one with more confident groups taken: the pairs' distances alone,
        # and with the candidates' heights (neither finds the shifts on every crowd)
        best: tuple | None = None
        offsets = _epipolar_offsets(state[0])  # the same candidates for both
        for heights in (False, True):
            correction, gain = pairwise_view_shifts(state[0], options, heights=heights, offsets=offsets)
            trial = _corrected(views, correction, options)
            tried = _solve(trial, options)
            tried_count = len(_confident(tried[1], tried[4], options))
            logger.info("pairwise shifts (%s, log-likelihood gain %.1f): %d confident groups against %d on the run's "
                        "poses", "with the heights" if heights else "distances", gain, tried_count, count)
            if best is None or tried_count > best[2]:
                best = (trial, tried, tried_count)
        assert best is not None  # the loop above runs twice
        trial, tried, tried_count = best
        # Kept only when the shifted views hold enough confident groups to re-estimate the shifts from: a handful
        # more than none is chance, not evidence.
        if tried_count > count and tried_count >= options.self_calibration_min_members:
            views[:] = trial
            state, count = tried, tried_count
    for _ in range(0 if carried else options.self_calibration_rounds):
        confident = _confident(state[1], state[4], options)
        if len(confident) < options.self_calibration_min_members:
            logger.info("%d confident groups: too few to correct the views", len(confident))
            break
        trial = _corrected(views, estimate_view_shifts(state[0], confident, options), options)
        tried = _solve(trial, options)
        tried_count = len(_confident(tried[1], tried[4], options))
        logger.info("shifts from %d groups: %d confident groups after", len(confident), tried_count)
        if tried_count < count:
            break
        views[:] = trial
        state, count, grew = tried, tried_count, tried_count > count
        if not grew:
            break  # converged: the crowd holds no more confident groups to learn from
    if not carried:
        _warn_beyond_band(views)
        # The crowd's own detection probability and heights, once, from the persons of the corrected views:
        # associated once more where they differ from what the association assumed.
        estimated = _crowd_rates(state, options, given)
        if estimated != options:
            options = estimated
            state = _solve(views, options, frame=state[0])
    if model is None and options.appearance and views and all(v.grey is not None for v in views):
        # The crowd's own appearance model, from this association's confident groups: associated once more with it.
        model = appearance_model(state, views, options)
        if model is not None:
            state = _solve(views, options, model, frame=state[0], earlier=before)
    frame, members, points, covariance, scores, positive = state
    total = int(frame.offsets[-1])
    covariance = covariance + _centre_term(views, members)
    local = np.where(members >= 0, members - frame.offsets[:-1][None], -1)
    order = np.lexsort((points[:, 1], points[:, 0]))
    logger.info("%d persons from %d detections in %d views (%d hypotheses)", len(order), total, len(views), positive)
    # The rates this frame used carry to the next frame as they are: the persons found under a height prior are
    # already shaped by it, so estimating it again from them would narrow it frame by frame.
    used = {v.name: v.shift_px.copy() for v in views}
    bands = {v.name: v.band_sigma_px if v.band_sigma_px is not None else v.sigma_pose_px for v in views}
    if pending is not None:  # after the frame's own record, which keeps the shifts its persons were found with
        _apply_correction(views, pending, options)
    return FrameResult(names, points[order], covariance[order], scores[order], local[order],
                       options.detection_probability, options.height_prior, model,
                       options.head_radius_m if state[0].log_radius is not None else None, used, bands)


START_DETECTION = 0.7  # the detection probability assumed until the frame's persons say otherwise
MIN_RATE_GROUPS = 20  # persons needed to estimate the detection probability or the heights from


def _crowd_rates(state: tuple, options: AssociateOptions, given: AssociateOptions) -> AssociateOptions:
    """``options`` with the detection probability and the height prior the association ``state`` found, each only
    where ``given`` leaves it to the crowd and enough persons say it (rounded: a change below that is noise)."""
    frame, members, points, covariance, scores, _ = state
    size = np.sum(members >= 0, axis=1)
    changes: dict = {}
    if given.detection_probability is None and len(members) >= MIN_RATE_GROUPS:
        p = truncated_binomial_p(size, np.maximum(frame.seen(points), size))
        if p is not None:
            changes["detection_probability"] = round(p, 2)
    confident = (size >= 3) & (scores > options.self_calibration_min_score)
    if given.height_prior is None and confident.sum() >= MIN_RATE_GROUPS:
        z = points[confident, 2]
        own = float(np.median(covariance[confident, 2, 2]))  # the score adds each point's own on top
        sigma = math.sqrt(max(float(np.var(z)) - own, 0.02 ** 2))
        changes["height_prior"] = (round(float(np.mean(z)), 2), round(sigma, 2))
    if given.head_radius_m is None and frame.log_radius is not None and confident.sum() >= MIN_RATE_GROUPS:
        # each member's radius times its distance over the focal: the person's R (the median: robust to a wrong one)
        rows, cols = np.nonzero(members[confident] >= 0)
        det = members[confident][rows, cols]
        dist = np.linalg.norm(points[confident][rows] - frame.centres[cols], axis=1)
        log_r = frame.log_radius[det] + np.log(dist) - np.log(frame.focals[cols])
        changes["head_radius_m"] = round(float(np.exp(np.median(log_r))), 3)
    if changes:
        logger.info("the crowd's rates: %s", changes)
    return dataclasses.replace(options, **changes)


def _carried_appearance(views: list[View], options: AssociateOptions,
                        earlier: FrameResult | None) -> AppearanceModel | None:
    """``earlier``'s appearance model, each view's detections described at its carried head size; None (and no view
    described) where the cue is off, an image unreadable, there is no earlier model or a view carries no head size."""
    model = earlier.appearance if earlier is not None else None
    if model is None or not options.appearance or not views \
            or any(v.grey is None or v.head_px is None for v in views):
        return None
    for view in views:
        view.descriptor = describe(view.grey, view.xy, view.head_px)  # type: ignore[arg-type]
    return model


def appearance_model(state: tuple, views: list[View], options: AssociateOptions) -> AppearanceModel | None:
    """Each view's detections described at the apparent head size of its persons (the median depth of the persons
    it sees in ``state``), and the same-against-different model from ``state``'s confident groups."""
    frame, members, points = state[0], state[1], state[2]
    for v, view in enumerate(views):
        seen = members[:, v] >= 0
        if not seen.any() or view.grey is None:
            view.descriptor = None
            continue
        _, z = view.project(points[seen])
        view.head_px = head_radius_px(view.focal, float(np.median(z)))
        view.descriptor = describe(view.grey, view.xy, view.head_px)
    if not all(v.descriptor is not None for v in views):
        logger.info("appearance: a view sees no person of the first association; left out")
        return None
    descriptors = np.concatenate([v.descriptor for v in views])  # type: ignore[misc]
    return estimate(descriptors, frame.view_of, _confident(members, state[4], options))
