"""Which boxes of an image hold any of a view's detections: a summed-area table of their counts on a coarse grid.

The growth asks, for each of ~10^5 projected points per view, for the detections nearest it within a few pixels,
and most points have none there. A box's count on a grid of cells is four lookups, against a KD-tree's descent per
point; a box that covers every cell its disc touches and counts nothing holds no detection of the disc.
"""

from __future__ import annotations

import numpy as np

CELL_PX = 8.0  # about a detection's reach in the growth: a box spans a few cells


class CountGrid:
    """Counts of 2D points on a grid of ``cell`` px over their bounding box, summed for box queries."""

    def __init__(self, points: np.ndarray, cell: float = CELL_PX):
        self.cell = cell
        self.origin = points.min(axis=0) if len(points) else np.zeros(2)
        span = (points.max(axis=0) - self.origin) if len(points) else np.zeros(2)
        self.shape = (int(span[1] // cell) + 1, int(span[0] // cell) + 1)  # rows (y), columns (x)
        ix, iy = self._cells(points)
        counts = np.zeros(self.shape, dtype=np.int64)
        np.add.at(counts, (iy, ix), 1)
        self.table = np.zeros((self.shape[0] + 1, self.shape[1] + 1), dtype=np.int64)
        self.table[1:, 1:] = counts.cumsum(axis=0).cumsum(axis=1)
        # the points cell by cell, rows of cells first: a row of a box's cells is one run of them
        self.points = np.asarray(points, dtype=np.float64)
        self.order = np.argsort(iy * self.shape[1] + ix, kind="stable")
        self.starts = np.concatenate([[0], np.cumsum(counts.ravel())])

    def _cells(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The (clipped) cell column and row of each point (monotone in its coordinates)."""
        cell = np.floor((xy - self.origin) / self.cell)
        ix = np.clip(cell[:, 0], 0, self.shape[1] - 1).astype(np.int64)
        iy = np.clip(cell[:, 1], 0, self.shape[0] - 1).astype(np.int64)
        return ix, iy

    def _boxes(self, xy: np.ndarray, radius: np.ndarray) -> tuple[np.ndarray, ...]:
        """The first and last cell column and row of the box around each disc, and how many points its cells hold."""
        # a hair wider than the disc: the points' own cells come from the same monotone arithmetic, so rounding
        # cannot move a point inside the disc out of the box
        r = radius * (1 + 1e-9) + 1e-6
        # column by column (1D arrays: an N x 2 array's broadcasts run inner loops of two elements)
        ends = []
        beyond = np.zeros(len(xy), dtype=bool)  # a disc past the grid's last cell (clipped, its box would be the edge's)
        for c, size in ((0, self.shape[1]), (1, self.shape[0])):
            p = xy[:, c]
            for first, edge in ((True, p - r), (False, p + r)):  # _cells' arithmetic, in place
                edge -= self.origin[c]
                edge /= self.cell
                np.floor(edge, out=edge)
                beyond |= edge > size - 1 if first else edge < 0
                np.clip(edge, 0, size - 1, out=edge)
                ends.append(edge.astype(np.int64))
        x0, x1, y0, y1 = ends
        width = self.shape[1] + 1
        t = self.table.ravel()
        top, bottom = y0 * width, (y1 + 1) * width
        count = t[bottom + x1 + 1] - t[top + x1 + 1] - t[bottom + x0] + t[top + x0]
        count[beyond] = 0
        return x0, y0, x1, y1, count

    def any_within(self, xy: np.ndarray, radius: np.ndarray) -> np.ndarray:
        """Whether any point may lie within ``radius`` of each of ``xy`` (N x 2, finite): False only where the cells
        of the box around the disc hold none."""
        return self._boxes(xy, radius)[4] > 0

    def pairs_within(self, xy: np.ndarray, radius: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every point within ``radius`` of each of ``xy`` (N x 2, finite; N radii): the queries' rows, the points'
        indices and their squared distances, query by query (a query's points in no particular order)."""
        query, point, d2, _, _ = self.offsets_within(xy, radius)
        return query, point, d2

    def offsets_within(self, xy: np.ndarray, radius: np.ndarray,
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``pairs_within``'s pairs, and each point's offset from its query (x, then y)."""
        x0, y0, x1, y1, count = self._boxes(xy, radius)
        searched = np.flatnonzero(count > 0)  # most boxes hold none
        x0, y0, x1, y1 = x0[searched], y0[searched], x1[searched], y1[searched]
        # one run of points per query and row of cells of its box: the cell a run starts at, and how many cells
        spans = y1 - y0 + 1
        width = self.shape[1]
        skipped = np.cumsum(spans) - spans
        query = np.repeat(np.arange(len(searched)), spans)
        cell = np.repeat((y0 - skipped) * width + x0, spans) + np.arange(len(query)) * width
        first = self.starts[cell]
        length = self.starts[cell + np.repeat(x1 - x0 + 1, spans)] - first
        query = np.repeat(query, length)
        at = np.repeat(first - (np.cumsum(length) - length), length) + np.arange(len(query))
        point = self.order[at]
        query = searched[query]
        dx = self.points[:, 0][point] - xy[:, 0][query]
        dy = self.points[:, 1][point] - xy[:, 1][query]
        d2 = dx * dx + dy * dy
        inside = np.flatnonzero(d2 <= radius[query] ** 2)
        return query[inside], point[inside], d2[inside], dx[inside], dy[inside]
