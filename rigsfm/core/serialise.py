"""The one serialiser of cameras and poses to JSON/YAML-ready values (and back).

- A camera: ``{model, width, height, params}``, params in COLMAP's order and pixel convention.
- A pose ``a_from_b``: ``{rotation: 3x3, translation: 3}`` (x_a = R x_b + t), plus ``quaternion_wxyz`` where a
  reader wants it (rigs.yaml does not: its rotation is the matrix, as OpenCV's stereoCalibrate gives it).
"""

from __future__ import annotations

import numpy as np
import pycolmap

from rigsfm.core.conventions import wxyz_from_rotation


def camera_to_dict(camera: pycolmap.Camera) -> dict:
    return {
        "model": camera.model.name,
        "width": int(camera.width),
        "height": int(camera.height),
        "params": [float(p) for p in camera.params],
    }


def camera_from_dict(data: dict) -> pycolmap.Camera:
    """Inverse of :func:`camera_to_dict` (no validation: ``rigsfm.core.rig.parse_camera`` validates user files)."""
    return pycolmap.Camera(model=str(data["model"]), width=int(data["width"]), height=int(data["height"]),
                           params=[float(p) for p in data["params"]])


def pose_to_dict(transform: pycolmap.Rigid3d, *, quaternion: bool = True) -> dict:
    data: dict[str, list] = {"rotation": [[float(v) for v in row] for row in transform.rotation.matrix()]}
    if quaternion:
        data["quaternion_wxyz"] = wxyz_from_rotation(transform.rotation)
    data["translation"] = [float(v) for v in transform.translation]
    return data


def pose_from_dict(data: dict) -> pycolmap.Rigid3d:
    """Inverse of :func:`pose_to_dict` (from the rotation matrix; no validation)."""
    return pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(data["rotation"], dtype=np.float64)),
                            np.asarray(data["translation"], dtype=np.float64))
