"""Each narrow camera's uncertainty.

:func:`narrow_uncertainty`: per narrow camera the 1-sigma uncertainty of its centre (mm) and of its rotation
(deg), each the root of the trace of its 3x3 covariance (the RMS length of the 3D error), relative to the
network as a whole: the covariance is transformed to the datum in which the registered rigs' mean centre and
mean orientation are held (an S-transformation), so no rig is special."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from rigsfm.core.geometry import skew
from rigsfm.core.names import registered_narrow_images
from rigsfm.run.adjustment.covariance import frame_centre_jacobian
from rigsfm.run.adjustment.model import sensor_from_rig_view
from rigsfm.run.adjustment.result import JointCovariance


@dataclass(frozen=True)
class NarrowUncertainty:
    centre_sigma_mm: float  # sqrt(trace) of the centre's 3x3 covariance, relative to the network (mm)
    rotation_sigma_deg: float  # sqrt(trace) of the orientation's 3x3 covariance, relative to the network (deg)
    # The 3x3 covariances themselves (a network's errors are not isotropic: a ring of rigs moves more horizontally
    # than vertically, which a trace cannot say), in the camera's own axes (x right, y down, z forward), so they
    # hold unchanged when the world stage moves the model into the floor frame.
    centre_covariance_mm2: tuple[tuple[float, ...], ...] | None = None
    rotation_covariance_deg2: tuple[tuple[float, ...], ...] | None = None


def _rows(matrix: np.ndarray) -> tuple[tuple[float, ...], ...]:
    symmetric = (matrix + matrix.T) / 2
    return tuple(tuple(float(x) for x in row) for row in symmetric)


def _world_jacobian(pose: pycolmap.Rigid3d) -> np.ndarray:
    """``[delta theta (world-frame orientation), delta centre]`` (6) from a pose's ``[w, dt]`` (6)."""
    r, t = pose.rotation.matrix(), np.asarray(pose.translation)
    return np.block([[-r.T, np.zeros((3, 3))], [-r.T @ skew(t), -r.T]])


def narrow_tangent_jacobians(frame_pose: pycolmap.Rigid3d, sensor: pycolmap.Rigid3d) -> tuple[np.ndarray, np.ndarray]:
    """``[w, dt]`` of ``narrow_from_world = E * rig_from_world`` from ``[w, dt]`` of the frame and of E (6x6 each)."""
    r_e = sensor.rotation.matrix()
    d_frame = np.block([[r_e, np.zeros((3, 3))], [np.zeros((3, 3)), r_e]])
    d_sensor = np.eye(6)
    d_sensor[3:, :3] = -skew(r_e @ np.asarray(frame_pose.translation))
    return d_frame, d_sensor


def narrow_uncertainty(reconstruction: pycolmap.Reconstruction,
                       covariance: JointCovariance) -> dict[str, NarrowUncertainty]:
    """Per narrow image (module docstring): centre and rotation uncertainty relative to the network."""
    frames = sorted(f for f in reconstruction.reg_frame_ids() if ("frame", f) in covariance.offsets)
    if not frames:
        return {}
    size = covariance.covariance.shape[0]
    # registered frames have their poses
    centres = {f: frame_centre_jacobian(reconstruction.frame(f).rig_from_world)[0] for f in frames}  # type: ignore[arg-type]
    mean_centre = np.mean(list(centres.values()), axis=0)
    datum = np.zeros((6, size))  # mean [delta theta, delta centre] of the frames: the gauge motion to remove
    for f in frames:
        # registered frames have their poses
        datum[:, covariance.slice(("frame", f))] += _world_jacobian(reconstruction.frame(f).rig_from_world) / len(frames)  # type: ignore[arg-type]
    out = {}
    for image in registered_narrow_images(reconstruction):
        frame = reconstruction.frame(image.frame_id)
        sensor = sensor_from_rig_view(reconstruction, frame.rig_id, reconstruction.cameras[image.camera_id].sensor_id)
        pose = image.cam_from_world()
        # registered frames have their poses
        d_frame, d_sensor = narrow_tangent_jacobians(frame.rig_from_world, sensor)  # type: ignore[arg-type]
        world = _world_jacobian(pose)
        row = np.zeros((6, size))
        row[:, covariance.slice(("frame", image.frame_id))] = world @ d_frame
        key = ("sensor_from_rig", image.camera_id)
        if key in covariance.offsets:
            row[:, covariance.slice(key)] = world @ d_sensor
        correction = np.eye(6)
        correction[3:, :3] = -skew(pose.inverse().translation - mean_centre)  # the gauge rotation moves the centre
        row -= correction @ datum
        cov = row @ covariance.covariance @ row.T
        axes = pose.rotation.matrix()  # world -> camera axes
        out[image.name] = NarrowUncertainty(
            centre_sigma_mm=1000.0 * float(np.sqrt(max(np.trace(cov[3:, 3:]), 0.0))),
            rotation_sigma_deg=float(np.degrees(np.sqrt(max(np.trace(cov[:3, :3]), 0.0)))),
            centre_covariance_mm2=_rows(1e6 * axes @ cov[3:, 3:] @ axes.T),
            rotation_covariance_deg2=_rows(np.degrees(1.0) ** 2 * axes @ cov[:3, :3] @ axes.T))
    return out
