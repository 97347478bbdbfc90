"""associate's floor.png and density.png: a map a reader can measure on (the world's metres along both axes, a
scale bar), not a picture without units."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from rigsfm.associate.output import COLOUR_BAR, density_image, floor_map
from rigsfm.core import charts

BOUNDS = (-3.0, -2.0, 5.0, 4.0)  # x0, y0, x1, y1 (m): the origin inside, negative and positive ticks


class _NoPersons:
    points, covariances = np.zeros((0, 3)), np.zeros((0, 3, 3))

    def __len__(self) -> int:
        return 0


def _ink(image: np.ndarray, rows: slice, cols: slice) -> int:
    return int((image[rows, cols].min(axis=2) < 160).sum())


def _check_axes(image: np.ndarray, frame: charts.MapFrame) -> None:
    assert image.shape[0] == frame.height and image.shape[1] >= frame.width  # (wider: a legend's room)
    xs, ys = frame.ticks("x"), frame.ticks("y")
    assert len(xs) >= 3 and len(ys) >= 3 and 0.0 in xs and 0.0 in ys  # the world's origin is labelled
    assert BOUNDS[0] <= xs[0] and xs[-1] <= BOUNDS[2] and BOUNDS[1] <= ys[0] and ys[-1] <= BOUNDS[3]
    plot_bottom, plot_left = frame.height - frame.bottom, frame.left
    for x in xs:  # a tick label under each x tick, where that many metres lie on the map
        u = int(round(frame.px([x, BOUNDS[1]])[0, 0]))
        assert abs(frame.px([x, 0.0])[0, 0] - (frame.left + (x - BOUNDS[0]) * frame.scale)) < 1e-9
        assert _ink(image, slice(plot_bottom + 4, plot_bottom + 22), slice(u - 10, u + 11)) > 5, x
    for y in ys:  # and left of each y tick
        v = int(round(frame.px([0.0, y])[0, 1]))
        assert _ink(image, slice(v - 7, v + 6), slice(2, plot_left - 4)) > 5, y
    # between two labelled ticks the margin stays blank: the labels are at the ticks, not a smear of text
    u0, u1 = (int(round(frame.px([x, 0.0])[0, 0])) for x in xs[:2])
    assert _ink(image, slice(plot_bottom + 4, plot_bottom + 22), slice(u0 + 20, u1 - 20)) == 0


def test_the_floor_map_has_metre_axes_and_a_scale():
    """floor.png was drawn with a 1 m grid but no number on it: where x = 0 or y = 3 m lies, and which way the
    world's axes run, could not be read off it."""
    frame = SimpleNamespace(frame="f0.png", result=_NoPersons())
    image = floor_map(frame, [np.array([[-2.0, -1.0], [4.0, -1.0], [4.0, 3.0], [-2.0, 3.0]])], BOUNDS, 1.55)
    _check_axes(image, charts.MapFrame.fit(BOUNDS, 900))


def test_the_density_image_has_metre_axes_and_a_scale():
    """density.png was the grid's cells as coloured squares, with no coordinates: which cell is where in the world
    (and how large a cell is) could not be read off it."""
    cell = 1.0
    counts = np.zeros((6, 8), dtype=np.int64)
    counts[1, 2] = 3
    seen = np.full((6, 8), 2)
    image = density_image(counts, cell, seen, BOUNDS)
    frame = charts.MapFrame(*BOUNDS, scale=24.0 / cell, top=charts.MapFrame.top + 44)
    _check_axes(image, frame)
    # the cell (row 1, column 2) lies at x 2-3 m from x0, y 1-2 m from y0: its colour is there on the map
    centre = frame.px([BOUNDS[0] + 2.5 * cell, BOUNDS[1] + 1.5 * cell])[0].round().astype(int)
    empty = frame.px([BOUNDS[0] + 0.5 * cell, BOUNDS[1] + 0.5 * cell])[0].round().astype(int)
    assert not np.array_equal(image[centre[1], centre[0]], image[empty[1], empty[0]])
    # the colours' scale: a bar from 0 (the empty cell's colour) to the largest density (the full cell's)
    x0, y0, x1, y1 = COLOUR_BAR
    full = frame.px([BOUNDS[0] + 2.5 * cell, BOUNDS[1] + 1.5 * cell])[0].round().astype(int)
    assert np.abs(image[(y0 + y1) // 2, x0].astype(int) - image[empty[1], empty[0]]).max() <= 3
    assert np.abs(image[(y0 + y1) // 2, x1 - 1].astype(int) - image[full[1], full[0]]).max() <= 3
