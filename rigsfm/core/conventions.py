"""Convention conversions, each in one named function.

- Transforms are named ``a_from_b``: ``x_a = a_from_b * x_b``. ``cam_from_world`` maps world points into
  the camera frame (COLMAP's convention); a camera centre is ``cam_from_world.inverse().translation``.
- Quaternions: rig_config.json and COLMAP's images.txt write [w, x, y, z]; ``pycolmap.Rotation3d`` and
  ``Rotation3d.quat`` use [x, y, z, w].
- Pixels: COLMAP puts the centre of the first pixel at (0.5, 0.5), OpenCV at (0, 0).
- Camera axes: OpenCV/COLMAP look down +z with +y down; OpenGL (nerfstudio, Open3D's GL views) looks
  down -z with +y up.
- Euler angles (degrees) follow the intrinsic z-y'-x'' (yaw, pitch, roll) convention:
  ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
"""

from __future__ import annotations

import numpy as np
import pycolmap

OPENGL_FROM_OPENCV_AXES = np.diag([1.0, -1.0, -1.0])


def rotation_from_wxyz(q_wxyz) -> pycolmap.Rotation3d:
    """A rotation from a [w, x, y, z] quaternion (rig_config.json, images.txt order)."""
    w, x, y, z = (float(v) for v in q_wxyz)
    return pycolmap.Rotation3d(np.array([x, y, z, w]))


def wxyz_from_rotation(rotation: pycolmap.Rotation3d) -> list[float]:
    """The [w, x, y, z] quaternion of a rotation, with w >= 0."""
    x, y, z, w = (float(v) for v in rotation.quat)
    sign = -1.0 if w < 0 else 1.0
    return [sign * w, sign * x, sign * y, sign * z]


def colmap_from_opencv_pixels(xy_opencv: np.ndarray) -> np.ndarray:
    """Pixel coordinates (or a principal point) from OpenCV's convention to COLMAP's (+0.5)."""
    return np.asarray(xy_opencv, dtype=np.float64) + 0.5


def opencv_from_colmap_pixels(xy_colmap: np.ndarray) -> np.ndarray:
    """Pixel coordinates (or a principal point) from COLMAP's convention to OpenCV's (-0.5)."""
    return np.asarray(xy_colmap, dtype=np.float64) - 0.5


def opencv_from_resized_pixels(xy_resized: np.ndarray, factor: float) -> np.ndarray:
    """OpenCV pixels of an image from those of its copy resized by ``cv2.resize`` to 1/``factor`` of its size
    (either interpolation, area or linear): resized pixel k is centred on (k + 1/2) ``factor`` - 1/2."""
    return factor * np.asarray(xy_resized, dtype=np.float64) + (factor - 1) / 2


def opengl_c2w_from_cam_from_world(cam_from_world: pycolmap.Rigid3d) -> np.ndarray:
    """4x4 camera-to-world matrix with OpenGL camera axes (nerfstudio's transform_matrix)."""
    world_from_cam = cam_from_world.inverse().matrix()
    c2w = np.eye(4)
    c2w[:3, :3] = world_from_cam[:, :3] @ OPENGL_FROM_OPENCV_AXES
    c2w[:3, 3] = world_from_cam[:, 3]
    return c2w


def euler_zyx_degrees(rotation_matrix: np.ndarray) -> tuple[float, float, float]:
    """(yaw, pitch, roll) in degrees with ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    r = np.asarray(rotation_matrix, dtype=np.float64)
    pitch = np.arcsin(np.clip(-r[2, 0], -1.0, 1.0))
    if abs(r[2, 0]) < 1.0 - 1e-12:
        yaw = np.arctan2(r[1, 0], r[0, 0])
        roll = np.arctan2(r[2, 1], r[2, 2])
    else:  # Gimbal lock: only yaw - roll (or yaw + roll) is defined; put it all in yaw.
        yaw = np.arctan2(-r[0, 1], r[1, 1])
        roll = 0.0
    return float(np.degrees(yaw)), float(np.degrees(pitch)), float(np.degrees(roll))


def rotation_from_euler_zyx_degrees(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Inverse of :func:`euler_zyx_degrees`."""
    y, p, r = np.radians([yaw, pitch, roll])
    rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    return rz @ ry @ rx


def rotation_angle_deg(a_from_b: np.ndarray, c_from_b: np.ndarray) -> float:
    """Angle in degrees of the rotation between two 3x3 rotation matrices."""
    delta = np.asarray(a_from_b) @ np.asarray(c_from_b).T
    return float(np.degrees(np.arccos(np.clip((np.trace(delta) - 1.0) / 2.0, -1.0, 1.0))))


def rotation_vector(rotation: pycolmap.Rotation3d) -> np.ndarray:
    """Axis * angle (radians) of a rotation, the inverse of ``Rotation3d(axis_angle=...)`` (pycolmap has no
    logarithm; scipy's quaternions share pycolmap's [x, y, z, w] order)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(rotation.quat)).as_rotvec()
