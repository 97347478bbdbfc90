"""associate's per-frame files built from whole arrays at once: the same text as person by person and cell by cell,
and the density grid's footprints and cells' views computed once per recording, not served for another extent."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from rigsfm.associate import output
from rigsfm.associate.detections import from_arrays
from rigsfm.associate.output import density_grid, grid_cells, persons_json, persons_rows
from rigsfm.associate.solve import FrameResult
from rigsfm.associate.trajectories import Links


def _frame(seed: int = 0) -> SimpleNamespace:
    """A frame of 40 persons over three views of random detections (some left unassigned)."""
    rng = np.random.default_rng(seed)
    names = ["rig00/narrow/f0.png", "rig01/narrow/f0.png", "rig02/narrow/f0.png"]
    detections = from_arrays({n: rng.uniform(0, 800, (50, 2)) for n in names})
    members = np.full((40, 3), -1, dtype=np.int64)
    for v in range(3):
        members[:, v] = rng.permutation(50)[:40]
    members[rng.random((40, 3)) < 0.3] = -1
    a = rng.normal(size=(40, 3, 3)) * 0.1
    result = FrameResult(names, rng.normal(size=(40, 3)) * 5, a @ np.transpose(a, (0, 2, 1)),
                         rng.normal(size=40) * 8, members, shift_px={n: rng.normal(size=2) for n in names},
                         band_sigma_px=dict.fromkeys(names, 1.5))
    views = [SimpleNamespace(name=n, sigma_pose_px=1.0, radius_px=None) for n in names]
    # a later frame of a recording: tracks numbered apart from the persons, some persons linked to the frame before's
    earlier = np.where(rng.random(40) < 0.7, rng.permutation(60)[:40], -1)
    links = Links(earlier=earlier, walk_m=0.1, confidence=np.where(earlier >= 0, rng.random(40), np.nan))
    return SimpleNamespace(frame="f0.png", result=result, detections=detections, views=views, poses_from=None,
                           lent_views=(), track=100 + rng.permutation(40), links=links)


def _rows_one_by_one(frame) -> list[list]:
    """persons_rows person by person, element by element (numpy scalars formatted as they come)."""
    result, views, det = frame.result, frame.views, frame.detections
    rows = []
    for p in range(len(result)):
        x, y, z = result.points[p]
        sx, sy, sz = np.sqrt(np.diag(result.covariances[p]))
        conf = result.confidence[p]
        members = [(v, int(i)) for v, i in enumerate(result.members[p]) if i >= 0]
        for v, i in members:
            d = det.images[views[v].name]
            rows.append([p, int(frame.track[p]), f"{x:.4f}", f"{y:.4f}", f"{z:.4f}", f"{sx:.4f}", f"{sy:.4f}", f"{sz:.4f}",
                         f"{conf:.4f}", len(members), d.image, d.text[i][0], d.text[i][1], int(d.rows[i])])
    return rows


def test_persons_rows_and_json_are_the_person_by_person_text():
    for seed in range(3):
        frame = _frame(seed)
        assert persons_rows(frame) == _rows_one_by_one(frame)
        data = persons_json(frame)
        result, det = frame.result, frame.detections
        assert len(data["persons"]) == len(result)
        for p, person in enumerate(data["persons"]):
            assert person["position_m"] == [round(float(c), 5) for c in result.points[p]]
            assert person["covariance_m2"] == np.round(result.covariances[p], 9).tolist()
            assert person["score"] == round(float(result.scores[p]), 4)
            assert person["confidence"] == round(float(result.confidence[p]), 5)  # this person's, not another's
            assert person["track"] == frame.track[p]
            linked = frame.links.earlier[p] >= 0
            assert person["after"] == (int(frame.links.earlier[p]) if linked else None)
            assert person["after_confidence"] == (round(float(frame.links.confidence[p]), 4) if linked else None)
            held = [(v, int(i)) for v, i in enumerate(result.members[p]) if i >= 0]
            assert [(d["image"], d["x"], d["row"]) for d in person["detections"]] == [
                (frame.views[v].name, float(det.images[frame.views[v].name].xy[i, 0]),
                 int(det.images[frame.views[v].name].rows[i])) for v, i in held]
        used = {(v, int(i)) for p in range(len(result)) for v, i in enumerate(result.members[p]) if i >= 0}
        assert data["unassigned"] == [{"image": view.name, "row": int(det.images[view.name].rows[i])}
                                      for v, view in enumerate(frame.views)
                                      for i in range(len(det.images[view.name])) if (v, i) not in used]


def test_density_rows_are_the_cell_by_cell_text():
    rng = np.random.default_rng(1)
    cell, bounds = 0.3, (-2.1, -0.9, 1.5, 2.1)  # cells whose edges round (0.3 is no binary fraction)
    nx, ny = 12, 10
    seen = rng.integers(0, 4, (ny, nx))
    points = np.c_[rng.uniform(-2.1, 1.5, 60), rng.uniform(-0.9, 2.1, 60), np.full(60, 1.6)]
    counts, rows = density_grid(points, bounds, cell, seen)
    x0, y0 = bounds[:2]
    assert rows == [[f"{x0 + i * cell:.3f}", f"{y0 + j * cell:.3f}", f"{x0 + (i + 1) * cell:.3f}",
                     f"{y0 + (j + 1) * cell:.3f}", int(counts[j, i]),
                     f"{counts[j, i] / cell ** 2:.3f}" if seen[j, i] >= 2 else "nan", int(seen[j, i])]
                    for j in range(ny) for i in range(nx)]
    assert counts.sum() == 60


def test_grid_cells_computes_once_per_extent(monkeypatch):
    """A recording's frames share the footprints and, where their persons stay inside them, the cells' views;
    a frame whose person widens the extent gets that extent's views."""
    calls = {"footprint": 0, "cells_seen": 0}

    def fake_footprint(image, height):
        calls["footprint"] += 1
        k = float(image.cam_from_world().matrix()[0, 3])
        return SimpleNamespace(polygon=np.array([[-4.0 + k, -3.0], [3.0 + k, -3.0], [3.0 + k, 4.0]]))

    def placed(name: str, k: float):  # an image of a camera at pose k (what its footprint depends on)
        pose = np.c_[np.eye(3), [k, 0.0, 0.0]]
        camera = SimpleNamespace(model="PINHOLE", params=np.array([800.0, 800.0, 400.0, 300.0]), width=800, height=600)
        return SimpleNamespace(name=name, camera=camera, cam_from_world=lambda: SimpleNamespace(matrix=lambda: pose))

    def fake_cells_seen(images, bounds, cell, height):
        calls["cells_seen"] += 1
        nx, ny = round((bounds[2] - bounds[0]) / cell), round((bounds[3] - bounds[1]) / cell)
        return np.full((ny, nx), 2 + int(bounds[0]) % 3, dtype=np.int64)

    monkeypatch.setattr(output, "footprint", fake_footprint)
    monkeypatch.setattr(output, "cells_seen", fake_cells_seen)
    images = [placed("a/frame0", 0.0), placed("b/frame0", 1.0)]
    later = [placed("a/frame1", 0.0), placed("b/frame1", 1.0)]  # the next frame of the same static cameras
    inside = np.array([[0.0, 0.0, 1.6]])
    fresh = grid_cells(images, inside, 1.0, 1.55)
    calls.update(footprint=0, cells_seen=0)
    known: dict = {}
    first = grid_cells(images, inside, 1.0, 1.55, known)
    again = grid_cells(later, inside + 0.5, 1.0, 1.55, known)
    assert calls == {"footprint": 2, "cells_seen": 1}  # once for both frames
    moved = grid_cells([placed("a/frame2", 0.0), placed("b/frame2", 1.5)], inside, 1.0, 1.55, known)
    assert calls["footprint"] == 3 and moved[0] != first[0]  # a camera that moved is placed again
    for got in (first, again):
        assert got[0] == fresh[0] and np.array_equal(got[1], fresh[1])
        assert all(np.array_equal(a, b) for a, b in zip(got[2], fresh[2]))
    wider = grid_cells(images, np.array([[-9.0, 0.0, 1.6]]), 1.0, 1.55, known)
    alone = grid_cells(images, np.array([[-9.0, 0.0, 1.6]]), 1.0, 1.55)
    assert wider[0] == alone[0] != fresh[0] and np.array_equal(wider[1], alone[1])


def test_floor_maps_of_a_recording_share_their_background_and_nothing_else():
    """The grid and footprints are drawn once per recording: each frame's map is still the map drawn alone (no
    earlier frame's persons in it, another frame's footprints not taken for its own)."""
    bounds = (-3.0, -2.0, 5.0, 4.0)
    prints = [np.array([[-2.0, -1.0], [4.0, -1.0], [4.0, 3.0], [-2.0, 3.0]])]
    other = [np.array([[-1.0, -1.5], [3.0, -1.0], [2.0, 3.5]])]
    frames = [_frame(seed) for seed in range(2)]
    for f in frames:  # inside the map
        f.result.points[:, :2] = np.clip(f.result.points[:, :2], -2.5, 3.5)
    known: dict = {}
    for f, feet in ((frames[0], prints), (frames[1], prints), (frames[0], other), (frames[1], prints)):
        drawn = output.floor_map(f, feet, bounds, 1.55, known=known)
        np.testing.assert_array_equal(drawn, output.floor_map(f, feet, bounds, 1.55))
    assert len(known) == 2  # one background per set of footprints
    assert not np.array_equal(output.floor_map(frames[0], prints, bounds, 1.55),
                              output.floor_map(frames[1], prints, bounds, 1.55))
