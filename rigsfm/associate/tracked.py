"""A carried frame's persons where the frame before's were.

The frames of a recording are a fraction of a second apart, and a person walks a few tens of centimetres in that
time: each of the earlier frame's persons is looked for again around its point, its head's detections in every view
taken as one hypothesis, before any pair is searched. The hypothesis is then verified, grown and scored as a pair
seed's group is, so it competes on this frame's evidence alone; the earlier frame only says where to look.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from rigsfm.core.names import ImageName


class _Growing(Protocol):
    """What ``predicted_groups`` asks of a frame (``frame._Frame``, whose tracked hypotheses call it): its growth."""

    def grow(self, members: np.ndarray, points: np.ndarray, covariance: np.ndarray) -> np.ndarray: ...


VERTICAL_SHARE = 0.25  # a walking head rises and falls far less than it moves across the floor


def walk_covariance(walk_m: float) -> np.ndarray:
    """The 3x3 covariance (m^2) of a head's move between two frames: ``walk_m`` per floor axis."""
    return np.diag([walk_m ** 2, walk_m ** 2, (VERTICAL_SHARE * walk_m) ** 2])


def _camera(name: str) -> str:
    try:
        return ImageName.parse(name).camera
    except ValueError:
        return name  # not a run's image name: the view is its own camera


def seen_before(earlier_views: list[str], earlier_members: np.ndarray, views: list[str]) -> np.ndarray:
    """Per earlier person (its members over ``earlier_views``), whether it had a member in the camera of each of
    ``views`` (P x V): where it was hidden or missed, the head nearest where it would be is someone else's."""
    column = {_camera(name): c for c, name in enumerate(earlier_views)}
    out = np.zeros((len(earlier_members), len(views)), dtype=bool)
    for v, name in enumerate(views):
        c = column.get(_camera(name))
        if c is not None:
            out[:, v] = earlier_members[:, c] >= 0
    return out


def predicted_groups(frame: _Growing, points: np.ndarray, covariance: np.ndarray, seen: np.ndarray,
                     walk_m: float) -> np.ndarray:
    """Per earlier person (its point and covariance, P x 3 and P x 3 x 3, and the views it was ``seen`` in, P x V),
    the detection of each of those views nearest where it would be (Mahalanobis: its covariance, a walk's and the
    view's noise, within the member gate): member rows (G x V) of those with two or more."""
    loose = covariance + walk_covariance(walk_m)[None]
    # searched only in the views it was seen in: the growth fills each view without a member on its own
    members = frame.grow(np.where(seen, -1, 0).astype(np.int64), points, loose)
    members = np.where(seen, members, -1)
    return members[np.sum(members >= 0, axis=1) >= 2]


def row_pairs(rows: np.ndarray) -> np.ndarray:
    """Every two members of each row, as pair seeds (S x V): a row nearest where an earlier person was may hold
    another head in a view or two, and a pair of its right members grows into the person without them."""
    seeds = []
    nv = rows.shape[1]
    for i in range(nv):
        for j in range(i + 1, nv):
            both = (rows[:, i] >= 0) & (rows[:, j] >= 0)
            m = np.full((int(both.sum()), nv), -1, dtype=np.int64)
            m[:, i], m[:, j] = rows[both, i], rows[both, j]
            seeds.append(m)
    return np.concatenate(seeds) if seeds else np.zeros((0, nv), dtype=np.int64)
