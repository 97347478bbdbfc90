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


def test_the_floor_map_draws_each_track_s_trail_through_the_recording():
    """A recording's floor.png shows where each person who goes on stood in the frames before: a line through its
    track's last points, none for a track that starts in this frame."""
    from rigsfm.associate.output import TRAIL_FRAMES, next_trails
    from rigsfm.associate.solve import FrameResult

    def frame(points, tracks):
        points = np.c_[np.asarray(points, dtype=float), np.full(len(points), 1.7)]
        result = FrameResult(["a", "b"], points, np.tile(np.eye(3) * 1e-4, (len(points), 1, 1)),
                             np.zeros(len(points)), np.zeros((len(points), 2), dtype=np.int64))
        return SimpleNamespace(frame="f.png", result=result, track=np.array(tracks), links=object())

    trails: dict = {}
    for points, tracks in (([[-1.5, 0.0], [3.0, 1.0]], [0, 1]), ([[-0.75, 0.0], [3.0, 2.0]], [0, 2]),
                           ([[0.0, 0.0], [3.0, 2.5]], [0, 2])):
        trails = next_trails(trails, frame(points, tracks))
    np.testing.assert_array_equal(trails[0], [[-1.5, 0.0], [-0.75, 0.0], [0.0, 0.0]])  # three frames of track 0
    assert sorted(trails) == [0, 2] and len(trails[2]) == 2  # track 1 ended, track 2 started a frame ago
    last = frame([[0.0, 0.0], [3.0, 2.5]], [0, 2])
    view = charts.MapFrame.fit(BOUNDS, 900)
    with_trails = floor_map(last, [], BOUNDS, 1.55, trails=[trails[0], trails[2]])
    alone = floor_map(last, [], BOUNDS, 1.55)
    changed = np.argwhere(np.any(with_trails != alone, axis=2))
    changed = changed[changed[:, 0] > 30]  # below the title, which says so
    u0, v0 = view.px([-1.5, 0.0])[0]
    u1, _ = view.px([0.0, 0.0])[0]
    on_track0 = changed[np.abs(changed[:, 0] - v0) <= 2]
    assert on_track0[:, 1].min() <= u0 + 2 and on_track0[:, 1].max() >= u1 - 8  # from (-1.5, 0) to (0, 0)
    for _ in range(TRAIL_FRAMES + 5):  # a long track keeps its last frames only
        trails = next_trails(trails, frame([[0.0, 0.0]], [0]))
    assert len(trails[0]) == TRAIL_FRAMES
    assert next_trails(trails, SimpleNamespace(track=None)) == {}  # a frame without tracks
