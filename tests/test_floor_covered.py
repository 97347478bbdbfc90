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
