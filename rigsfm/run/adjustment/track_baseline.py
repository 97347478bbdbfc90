"""3D points without a baseline: every image that observes them was taken from (nearly) the same centre.

A track between frames of a static rig (the same camera centre at two times) cannot be triangulated. When its rays
are parallel (a static point) COLMAP's triangulation-angle filter drops it. When they are not (a person who moved
between the frames, matched to itself), the only point both rays pass through is the camera centre: the point sits
micrometres in front of the lens with no reprojection error, and the angle COLMAP measures there, between centres
as seen from the point, is large, so it survives. Its Jacobian then swamps the rig poses' information: Ceres' dense
Cholesky fails during the adjustment and the joint covariance's Schur complement loses every digit.
"""

from __future__ import annotations

import numpy as np
import pycolmap

MIN_BASELINE = 1e-3  # of the median observation depth; a rig's own wide-narrow baseline is several times more


def points_without_baseline(reconstruction: pycolmap.Reconstruction, min_baseline: float = MIN_BASELINE) -> list[int]:
    """Ids of the points whose observing camera centres all lie within ``min_baseline`` times the median
    observation depth of their mean (so that none is twice that from another)."""
    all_ids = np.array(sorted(reconstruction.point3D_ids()), dtype=np.int64)
    if not len(all_ids):
        return []
    all_xyz = np.array([reconstruction.points3D[i].xyz for i in all_ids])
    rows, centres, depths = [], [], []
    for image_id in reconstruction.reg_image_ids():
        image = reconstruction.image(image_id)
        row = np.searchsorted(all_ids, [p.point3D_id for p in image.get_observation_points2D()])
        if not len(row):
            continue
        cam_from_world = image.cam_from_world()
        depths.append(all_xyz[row] @ cam_from_world.rotation.matrix()[2] + cam_from_world.translation[2])
        rows.append(row)
        centres.append(np.broadcast_to(image.projection_center(), (len(row), 3)))
    if not rows:
        return []
    row, centre = np.concatenate(rows), np.concatenate(centres)
    counts = np.bincount(row, minlength=len(all_ids))
    sums = np.stack([np.bincount(row, centre[:, k], minlength=len(all_ids)) for k in range(3)], axis=1)
    mean = sums / np.maximum(counts, 1)[:, None]
    farthest = np.zeros(len(all_ids))
    np.maximum.at(farthest, row, np.linalg.norm(centre - mean[row], axis=1))
    limit = min_baseline * float(np.median(np.abs(np.concatenate(depths))))
    return all_ids[(counts > 0) & (farthest < limit)].tolist()


def delete_points_without_baseline(reconstruction: pycolmap.Reconstruction) -> int:
    """Delete :func:`points_without_baseline`; their number."""
    ids = points_without_baseline(reconstruction)
    for point_id in ids:
        reconstruction.delete_point3D(point_id)
    return len(ids)
