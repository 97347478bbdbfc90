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


# narrow_poses.json's "conventions" block (also the exports' poses.json)
CONVENTIONS = {
    "cam_from_world": "x_cam = R @ x_world + t (metres); centre = -R.T @ t",
    "quaternion": "[w, x, y, z]",
    "pixels": "COLMAP: centre of the first pixel at (0.5, 0.5)",
    "narrow_j_from_narrow_i": "x_j = R @ x_i + t",
    "euler_zyx_deg": "(yaw, pitch, roll), R = Rz(yaw) @ Ry(pitch) @ Rx(roll), intrinsic z-y'-x''",
    "centre_direction_in_i": "unit vector from centre i to centre j, in camera i's frame",
    "F_ji": "x_j^T F_ji x_i = 0, homogeneous COLMAP pixels of undistorted images (pinhole K of each camera)",
    "E_ji": "[t]_x R of narrow_j_from_narrow_i",
    "epipolar_band_95_px": "half-width (pinhole px of j) of the band around the epipolar line of a point of i "
                           "that holds its true correspondence with 95 % probability, pooled over the analysis "
                           "points (epipolar_band_points: 'floor' = the floor seen by both cameras on a 15x15 "
                           "grid of image i; 'depths' = that grid at every depth at which it appears in j; "
                           "their depths in camera i: epipolar_band_depth_range_m) and over the joint "
                           "uncertainty of rig poses, intrinsics and E^sl (rigs.yaml's sigmas included). "
                           "Calibrated, not a bound: the calibration's error is one draw per pair, so one pair "
                           "may hold fewer of its points; epipolar_band_p_below_85 is the model's probability "
                           "that under 85 % of this pair's points lie inside. null if it could not be estimated "
                           "or the images share no view",
    "world": "the frame of every pose and point: see world.frame, world.origin, world.x_axis, world.z_axis",
    "ground_from_image": "3x3 H: (x, y, w) = H @ (u, v, 1) for an undistorted COLMAP pixel (u, v) of the camera's "
                         "pinhole K (as F_ji); the point on the plane z = plane_height_m is (x / w, y / w) in "
                         "world metres; w > 0 only for pixels whose ray meets the plane in front of the camera "
                         "(below the horizon). Raw pixels: undistort with the camera model first",
    "footprint_m": "the part of the plane the image sees: counter-clockwise polygon (x, y) in world metres, the "
                   "image border (pixel edges) through the full camera model; clipped = cut at the horizon or "
                   "at 20 camera heights' depth",
    "footprint_centre_m": "where the ray of the image centre (W/2, H/2) meets the plane",
    "gsd_mm_per_px": "ground sampling distance at footprint_centre_m: sqrt |det J| of the pixel -> plane "
                     "Jacobian (mm per pixel); gsd_mm_per_px_xy: along image x and y",
    "ground_overlap_m2": "per plane of world.plane_heights_m, the area (m^2) seen by both narrow cameras of the "
                         "pair; null for two images of the same camera",
    "seen_by_two_or_more_m2": "per plane of world.plane_heights_m, the area seen by two or more narrow cameras "
                              "(where stereo analysis is possible), counted on a 5 cm raster",
}
