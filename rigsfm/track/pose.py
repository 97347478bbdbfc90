"""The rig pose from 2D-3D correspondences with E^sl held fixed (pycolmap's LO-RANSAC + refinement)."""

from __future__ import annotations

import numpy as np
import pycolmap

from rigsfm.track.options import RegistrationOptions


def refinement_options() -> pycolmap.AbsolutePoseRefinementOptions:
    """COLMAP's default gradient tolerance (1.0) stops while the weak rotation/translation coupling of a wide
    camera is still off by millimetres; converge fully instead."""
    refinement = pycolmap.AbsolutePoseRefinementOptions()
    refinement.gradient_tolerance = 1e-10
    refinement.max_num_iterations = 200
    return refinement


def estimate_rig_pose(
    correspondences: dict[str, tuple[np.ndarray, np.ndarray]],
    cameras: dict[str, pycolmap.Camera],
    sensor_from_rig: dict[str, pycolmap.Rigid3d],
    options: RegistrationOptions,
) -> tuple[pycolmap.Rigid3d, np.ndarray, list[str]] | None:
    """``rig_from_world``, the inlier mask (concatenated in the order of the sensors used) and the sensors
    used, from per-sensor 2D-3D correspondences ``(xy (COLMAP pixels), xyz)``; None if no pose is found.

    Several sensors with matches: generalized absolute pose with the fixed ``sensor_from_rig`` (E^sl);
    one sensor: that camera's absolute pose, moved to the rig frame through its fixed ``sensor_from_rig``.
    """
    sensors = [s for s in correspondences if len(correspondences[s][0]) >= options.min_matches]
    if not sensors:
        return None
    xy = np.concatenate([correspondences[s][0] for s in sensors])
    xyz = np.concatenate([correspondences[s][1] for s in sensors])
    if len(sensors) > 1:
        ransac = pycolmap.RANSACOptions()
        ransac.max_error = options.max_error_px
        ransac.random_seed = options.seed
        idxs = [i for i, s in enumerate(sensors) for _ in range(len(correspondences[s][0]))]
        result = pycolmap.estimate_and_refine_generalized_absolute_pose(
            xy, xyz, idxs, [sensor_from_rig[s] for s in sensors], [cameras[s] for s in sensors], ransac,
            refinement_options())
        if result is None:
            return None
        rig_from_world = result["rig_from_world"]
    else:
        estimation = pycolmap.AbsolutePoseEstimationOptions()
        estimation.ransac.max_error = options.max_error_px
        estimation.ransac.random_seed = options.seed
        result = pycolmap.estimate_and_refine_absolute_pose(xy, xyz, cameras[sensors[0]], estimation,
                                                           refinement_options())
        if result is None:
            return None
        rig_from_world = sensor_from_rig[sensors[0]].inverse() * result["cam_from_world"]
    return rig_from_world, np.asarray(result["inlier_mask"], dtype=bool).reshape(-1), sensors


def reprojection_errors(cam_from_world: pycolmap.Rigid3d, camera: pycolmap.Camera, xy: np.ndarray,
                        xyz: np.ndarray) -> np.ndarray:
    """Pixel distances between observed ``xy`` and the projections of ``xyz``."""
    m = cam_from_world.matrix()
    in_cam = np.asarray(xyz, dtype=np.float64).reshape(-1, 3) @ m[:, :3].T + m[:, 3]
    projected = np.asarray(camera.img_from_cam(in_cam, check_cheirality=False), dtype=np.float64).reshape(-1, 2)
    return np.linalg.norm(projected - xy, axis=1)


def pose_covariance(rig_from_world: pycolmap.Rigid3d, observations: list[tuple], frame_from_world: np.ndarray,
                    step: float = 1e-6) -> np.ndarray:
    """6x6 covariance of a rig pose in the coordinates a change is reported in: the rotation vector
    (radians) of ``exp(w) * R`` and the centre shift (metres) expressed in the frame ``frame_from_world``
    (a 3x3 rotation: the reference camera's). Linearised (numeric Jacobian of the inlier reprojection
    errors), scaled by their residual variance. ``observations``: (camera, sensor_from_rig, xy, xyz).

    A wide camera that sees its map points at similar depths has one weak direction (a sideways shift
    with a compensating rotation); this covariance carries it, so tests of a change can account for it.
    """
    rotation = rig_from_world.rotation.matrix()
    centre = -rotation.T @ np.asarray(rig_from_world.translation)

    def residuals(delta: np.ndarray) -> np.ndarray:
        r = pycolmap.Rotation3d(axis_angle=delta[:3]).matrix() @ rotation
        c = centre + frame_from_world.T @ delta[3:]
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(r), -r @ c)
        return np.concatenate([
            (np.asarray(camera.img_from_cam(
                xyz @ (s * pose).matrix()[:, :3].T + (s * pose).matrix()[:, 3], check_cheirality=False)) - xy).ravel()
            for camera, s, xy, xyz in observations])

    r0 = residuals(np.zeros(6))
    jacobian = np.stack([(residuals(step * e) - residuals(-step * e)) / (2 * step) for e in np.eye(6)], axis=1)
    variance = float(r0 @ r0) / max(len(r0) - 6, 1)
    return variance * np.linalg.pinv(jacobian.T @ jacobian)
