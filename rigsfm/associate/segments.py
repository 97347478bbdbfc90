"""Where a detection's ray between the two heights falls in another view, and how wide its band is there.

A narrow camera looks across the crowd at the rigs on the far side: a ray of it, cut to the heights where heads are,
runs through the crowd and can pass beside or behind a camera opposite. Only the part of the segment in front of that
camera has an image there; projecting the two ends as they are would drop the whole segment whenever one end lies
behind it, and with it every true pair of the two views at that place.

The band around that image is not the two views' pixel noises added as they are: a pixel of view i is an angle, and
the head it points at moves by that angle times its distance from i, which view j sees at its own distance. A head
twice as far from i as from j moves two pixels in j for a pixel of i, so the band of the pair is that much wider
there than where the two views see the head at equal distances.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

MIN_DEPTH_M = 0.1  # the nearest a point may be to a camera and still be imaged (as the rays' own start)


class _Projecting(Protocol):
    r: np.ndarray
    t: np.ndarray

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


class _Stacked(Protocol):
    """What ``pair_seeds`` reads of a frame (``frame._Frame``, whose pair search calls it): its views and their
    stacked detections."""

    centres: np.ndarray
    focals: np.ndarray
    noise: np.ndarray
    uv: np.ndarray
    rays: np.ndarray

    @property
    def views(self) -> Sequence[_Projecting]: ...

    @property
    def trees(self) -> Sequence[cKDTree | None]: ...

    @property
    def tree_index(self) -> Sequence[np.ndarray]: ...


def in_front(view: _Projecting, start: np.ndarray, end: np.ndarray,
             min_depth: float = MIN_DEPTH_M) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The segments ``start``-``end`` (N x 3 world points each) cut to their parts at least ``min_depth`` in front of
    ``view``'s camera (world points), and whether any part is."""
    start, end, ok, _ = cut_in_front(view, start, end, min_depth)
    return start, end, ok


def cut_in_front(view: _Projecting, start: np.ndarray, end: np.ndarray,
                 min_depth: float = MIN_DEPTH_M) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """:func:`in_front`, and whether any segment was cut (False: ``start`` and ``end`` are the segments given)."""
    depth_s = start @ view.r[2] + view.t[2]
    depth_e = end @ view.r[2] + view.t[2]
    ok = (depth_s >= min_depth) | (depth_e >= min_depth)
    if np.all(depth_s >= min_depth) and np.all(depth_e >= min_depth):
        return start, end, ok, False  # every segment wholly in front (mostly): nothing to cut
    with np.errstate(divide="ignore", invalid="ignore"):
        cut = np.clip((min_depth - depth_s) / (depth_e - depth_s), 0.0, 1.0)
    crossing = start + np.nan_to_num(cut)[:, None] * (end - start)
    start = np.where((depth_s < min_depth)[:, None], crossing, start)
    end = np.where((depth_e < min_depth)[:, None], crossing, end)
    return start, end, ok, True


def segment_in_view(view: _Projecting, start: np.ndarray, end: np.ndarray,
                    min_depth: float = MIN_DEPTH_M) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The undistorted pixels of the ends of the segments ``start``-``end`` (N x 3 world points each) in ``view``,
    each segment cut to its part at least ``min_depth`` in front of the camera, and whether any part is."""
    start, end, ok = in_front(view, start, end, min_depth)
    a, _ = view.project(start)
    b, _ = view.project(end)
    return a, b, ok


def band_sigma(points: np.ndarray, centre_i: np.ndarray, centre_j: np.ndarray, focal_i: float, focal_j: float,
               noise_i: float, noise_j: float) -> np.ndarray:
    """Per world point (N x 3), the 1 sigma (px of view j) of a detection in j of a head there about the image of
    view i's ray through it: j's own noise and i's carried to j at the two distances."""
    d_i = np.linalg.norm(points - centre_i, axis=1)
    d_j = np.maximum(np.linalg.norm(points - centre_j, axis=1), MIN_DEPTH_M)
    carried = noise_i * (focal_j * d_i) / (focal_i * d_j)
    return np.sqrt(noise_j ** 2 + carried ** 2)


def nearest_on_rays(centre_i: np.ndarray, rays_i: np.ndarray, centre_j: np.ndarray, rays_j: np.ndarray,
                    lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Per row, the point of ray i (unit directions, N x 3) nearest ray j's, its distance along ray i held between
    ``lo`` and ``hi`` (N each: the part of ray i where heads may be)."""
    w = centre_i - centre_j
    b = np.sum(rays_i * rays_j, axis=1)
    d, e = rays_i @ w, rays_j @ w
    with np.errstate(divide="ignore", invalid="ignore"):
        along = (b * e - d) / (1.0 - b ** 2)
    along = np.clip(np.nan_to_num(along, nan=0.5 * (lo + hi)), np.minimum(lo, hi), np.maximum(lo, hi))
    return centre_i + along[:, None] * rays_i


def pair_seeds(frame: _Stacked, i: int, j: int, di: np.ndarray, p_lo: np.ndarray, p_hi: np.ndarray, gate: float,
               among: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """View j's detections inside the band of the rays of view i's detections ``di`` between the heights (their
    points ``p_lo``, ``p_hi``), the band ``gate`` sigmas wide where each candidate would put the head: the rows of
    ``di`` and the stacked detections of j of every candidate near a segment, and which are inside (None: none near).
    ``frame``: the frame's stacked detections; ``among``: only these of j's (stacked indices, a subset of its
    tree's), None: all."""
    view_j = frame.views[j]
    tree = frame.trees[j]
    candidates = frame.tree_index[j] if among is None else among
    start, end, ok, cut = cut_in_front(view_j, p_lo, p_hi)
    if tree is None or not ok.any():
        return None
    a, _ = view_j.project(start)
    b, _ = view_j.project(end)
    args = (frame.centres[i], frame.centres[j], frame.focals[i], frame.focals[j], frame.noise[i], frame.noise[j])
    centre_i, centre_j = frame.centres[i], frame.centres[j]
    lo_i, hi_i = np.linalg.norm(p_lo - centre_i, axis=1), np.linalg.norm(p_hi - centre_i, axis=1)

    def carried(start: np.ndarray, end: np.ndarray, far_i: np.ndarray) -> np.ndarray:
        """i's noise carried to j at the segments' widest: i's farthest end (``far_i``), j's nearest point."""
        step = end - start
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.clip(np.nan_to_num(np.sum((centre_j - start) * step, axis=1) / np.sum(step ** 2, axis=1)), 0.0, 1.0)
        near_j = np.maximum(np.linalg.norm(start + t[:, None] * step - centre_j, axis=1), MIN_DEPTH_M)
        return frame.noise[i] * (frame.focals[j] * far_i) / (frame.focals[i] * near_j)

    # The band anywhere on the whole segment (the part behind j included, where the candidates' heads may fall):
    # no candidate farther from its segment than this can be inside its band.
    whole = carried(p_lo, p_hi, np.maximum(lo_i, hi_i))
    # the band's widest on the part in front of j (the whole segment where all of it is)
    front = whole if not cut else carried(
        start, end, np.maximum(np.linalg.norm(start - centre_i, axis=1), np.linalg.norm(end - centre_i, axis=1)))
    reach = gate * np.sqrt(frame.noise[j] ** 2 + front ** 2)
    seg = b - a
    length = np.linalg.norm(seg, axis=1)
    rows = np.flatnonzero(ok)
    widest = gate * np.sqrt(frame.noise[j] ** 2 + whole ** 2)
    widest = widest * (1 + 1e-9) + 1e-9  # the band below is computed otherwise: room for its rounding
    ra, cb = near_segments(frame.uv[candidates], ((a + b) / 2)[rows], (length / 2 + reach)[rows],
                            a[rows], seg[rows], widest[rows])
    if not len(ra):
        return None
    ra, cb = rows[ra], candidates[cb]
    p = frame.uv[cb]
    s = seg[ra]
    l2 = np.maximum(np.sum(s ** 2, axis=1), 1e-12)
    tt = np.clip(np.sum((p - a[ra]) * s, axis=1) / l2, 0.0, 1.0)
    dist = np.linalg.norm(p - (a[ra] + tt[:, None] * s), axis=1)
    head = nearest_on_rays(centre_i, frame.rays[di[ra]], frame.centres[j], frame.rays[cb], lo_i[ra], hi_i[ra])
    return ra, cb, dist <= gate * band_sigma(head, *args)


CELLS_PER_BLOCK = 1 << 20  # segment-detection pairs tested at once


def near_segments(points: np.ndarray, centre: np.ndarray, radius: np.ndarray, start: np.ndarray, step: np.ndarray,
                   widest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per segment (``start`` + [0, 1] ``step``), the ``points`` within ``radius`` of ``centre`` (the disc around the
    segment, as a KD-tree's ball query finds them) and within ``widest`` of the segment: the segments' rows and the
    points' indices, by segment, then point. Every segment against every point, in blocks: a view holds a few hundred
    detections, and the discs around long segments hold ten times more of them than the bands do."""
    out_rows, out_points = [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)]
    l2 = np.maximum(step[:, 0] ** 2 + step[:, 1] ** 2, 1e-12)
    # first the line through each segment (one product per pair; never nearer than the segment), with room for
    # rounding, then the exact tests on the few pairs left
    line = (widest * (1 + 1e-6)) ** 2 * l2
    block = max(1, CELLS_PER_BLOCK // max(len(points), 1))
    for k in range(0, len(centre), block):
        s, a = step[k:k + block], start[k:k + block]
        cross = (points[None, :, 0] - a[:, 0, None]) * s[:, 1, None] - (points[None, :, 1] - a[:, 1, None]) * s[:, 0, None]
        # row-major, as np.nonzero gives them (its 2D path is ten times slower than the flat one)
        r, q = np.divmod(np.flatnonzero(cross ** 2 <= line[k:k + block, None]), len(points))
        out_rows.append(r + k)
        out_points.append(q)
    rows, near = np.concatenate(out_rows), np.concatenate(out_points)
    p = points[near]
    d = p - centre[rows]
    inside = d[:, 0] ** 2 + d[:, 1] ** 2 <= radius[rows] ** 2
    e, s = p - start[rows], step[rows]
    t = np.clip((e[:, 0] * s[:, 0] + e[:, 1] * s[:, 1]) / l2[rows], 0.0, 1.0)
    gap = np.hypot(e[:, 0] - t * s[:, 0], e[:, 1] - t * s[:, 1])
    keep = inside & (gap <= widest[rows])
    return rows[keep], near[keep]
