"""A floor the sparse points do not show (a crowd covering it): the floor matching starts below the lowest points."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

import rigsfm.run.world.floor as floor


def _covered(out) -> pycolmap.Reconstruction:
    """The run's model (floor frame: z up, 0 on the floor) without its points below 0.7 m, as where a crowd stands
    on the floor and hides it and the walls' feet: the lowest sparse points are then well above the floor."""
    model = pycolmap.Reconstruction(out / "sparse")
    for point_id in [i for i, p in model.points3D.items() if p.xyz[2] < 0.7]:
        model.delete_point3D(point_id)
    return model


@pytest.mark.slow
def test_a_covered_floor_is_found_by_lowering_the_guess(three_rig_run, monkeypatch):
    dataset, out, _ = three_rig_run
    model = _covered(out)
    normal, offset, how = floor.guess_floor(model)
    assert how == floor.LOWEST_POINTS and -offset > 0.7  # the guess is above the points taken away
    found = floor.estimate_floor(model, dataset.images)
    assert found.fit, found.fit
    # The floor the run found before, to a centimetre and a tenth of a degree.
    assert abs(found.fit.offset) < 0.01 and np.degrees(np.arccos(found.fit.normal[2])) < 0.1, found.fit
    # Matching through the guess alone finds no floor: the steps below it are what finds it.
    monkeypatch.setattr(floor, "LOWER_STEPS", ())
    assert not floor.estimate_floor(model, dataset.images).fit


@pytest.mark.slow
def test_the_covered_floor_search_fits_each_point_set_once(three_rig_run, monkeypatch):
    """A fit that finds no floor draws every RANSAC triple (seconds on a crowd): the search fits the sparse points,
    each matching round's points and each lowered step's points once."""
    dataset, out, _ = three_rig_run
    model = _covered(out)
    fitted = []
    fit_floor = floor.fit_floor

    def counted(reconstruction, markers=None, options=None, *, extra_points=None, **kwargs):
        points = np.zeros((0, 3)) if extra_points is None else np.asarray(extra_points)
        fitted.append(points.tobytes())
        return fit_floor(reconstruction, markers, options, extra_points=extra_points, **kwargs)

    monkeypatch.setattr(floor, "fit_floor", counted)
    found = floor.estimate_floor(model, dataset.images)
    assert found.fit and found.rounds > len(floor.LOWER_STEPS)  # the lowered steps ran
    assert len(fitted) == len(set(fitted)), f"{len(fitted) - len(set(fitted))} point sets fitted twice"
