"""Reprojection residuals of a reconstruction, per image."""

from __future__ import annotations

from collections.abc import Collection

import numpy as np
import pycolmap


def reprojection_errors(reconstruction: pycolmap.Reconstruction, without: Collection[int] = ()
                        ) -> dict[str, np.ndarray]:
    """For every registered image name, the pixel distance between each observation and its projection; the
    observations of the points ``without`` (point3D ids) left out."""
    skip = set(without)
    errors = {}
    # Every point's position read once (a lookup per observation through Reconstruction.point3D costs more).
    xyz_of = {point3D_id: point.xyz for point3D_id, point in reconstruction.points3D.items()}
    for image in reconstruction.images.values():
        if not image.has_pose:
            continue
        observed = image.get_observation_points2D()  # in index order, like image.points2D
        if skip:
            observed = [p for p in observed if p.point3D_id not in skip]
        if len(observed) == 0:
            errors[image.name] = np.zeros(0)
            continue
        xyz = np.array([xyz_of[p.point3D_id] for p in observed])
        xy = np.array([p.xy for p in observed])
        camera = reconstruction.cameras[image.camera_id]
        projected = np.asarray(camera.img_from_cam(image.cam_from_world() * xyz))
        errors[image.name] = np.linalg.norm(projected - xy, axis=1)
    return errors
