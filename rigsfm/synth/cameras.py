"""Exact rig cameras and poses of the synthetic arena, and the realistic calibration error a user has.

Conventions: ``narrow_from_wide`` maps wide-camera coordinates to narrow-camera coordinates (metres);
``wide_from_world`` is the wide camera's ``cam_from_world`` (COLMAP camera axes: +z forward, +y
down), which is also the rig pose ``rig_from_world`` since the wide camera is the reference sensor.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pycolmap

from rigsfm.core.rig import RigCalibration
from rigsfm.synth.scene import SceneOptions

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class RigTruth:
    """One rig's exact cameras (at the dataset's image size), E^sl and world pose."""

    name: str
    wide: pycolmap.Camera
    narrow: pycolmap.Camera
    narrow_from_wide: pycolmap.Rigid3d
    wide_from_world: pycolmap.Rigid3d

    @property
    def narrow_from_world(self) -> pycolmap.Rigid3d:
        return self.narrow_from_wide * self.wide_from_world

    def centre(self, sensor: str = "wide") -> np.ndarray:
        pose = self.wide_from_world if sensor == "wide" else self.narrow_from_world
        return np.asarray(pose.inverse().translation, dtype=np.float64)

    def calibration(self) -> RigCalibration:
        return RigCalibration(self.name, self.wide, self.narrow, self.narrow_from_wide)


def rig_name(index: int) -> str:
    """``rig01``, ``rig02``, ... (``index`` counts from 0)."""
    return f"rig{index + 1:02d}"


def rig_angles(options: SceneOptions) -> np.ndarray:
    """Azimuths (radians) of the rigs on their circle: evenly round it, or spread over ``arc_deg``."""
    n = options.num_rigs
    if options.arc_deg >= 360.0:
        return np.arange(n) * 2 * np.pi / n
    return np.radians(np.linspace(-options.arc_deg / 2, options.arc_deg / 2, n))


def scaled_size(options: SceneOptions) -> tuple[int, int]:
    return (
        max(8, round(options.width * options.image_scale)),
        max(8, round(options.height * options.image_scale)),
    )


def opencv_camera(
    focal: float, aspect: float, principal: tuple[float, float], distortion: np.ndarray, options: SceneOptions
) -> pycolmap.Camera:
    """An OPENCV camera defined at full size, scaled to the dataset's image size (COLMAP pixels)."""
    width, height = scaled_size(options)
    sx, sy = width / options.width, height / options.height
    params = [focal * sx, focal * aspect * sy, principal[0] * sx, principal[1] * sy, *distortion]
    return pycolmap.Camera(model="OPENCV", width=width, height=height, params=params)


def axis_rotation(axis: int, angle: float) -> np.ndarray:
    """Right-handed rotation matrix by ``angle`` (radians) about coordinate axis 0, 1 or 2."""
    c, s = np.cos(angle), np.sin(angle)
    i, j = [k for k in range(3) if k != axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def look_at_centre(position: np.ndarray, yaw: float, pitch: float, roll: float) -> pycolmap.Rigid3d:
    """cam_from_world for a camera at ``position`` facing the arena centre (+yaw left), ``pitch`` down."""
    heading = np.arctan2(-position[1], -position[0]) + yaw
    flat = np.array([np.cos(heading), np.sin(heading), 0.0])
    forward = np.cos(pitch) * flat + np.sin(pitch) * np.array([0.0, 0.0, -1.0])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    world_from_cam = np.stack([right, down, forward], axis=1) @ axis_rotation(2, roll)
    cam_from_world = world_from_cam.T
    return pycolmap.Rigid3d(pycolmap.Rotation3d(cam_from_world), -cam_from_world @ position)


def make_rigs(options: SceneOptions) -> list[RigTruth]:
    """Exact intrinsics (each rig slightly different), E^sl and poses of every rig."""
    rng = np.random.default_rng([options.seed, 23])
    rigs = []
    w, h = options.width, options.height
    for index, phi in enumerate(rig_angles(options)):
        wide = opencv_camera(
            options.wide_focal * (1 + rng.uniform(-0.01, 0.01)),
            1 + rng.uniform(-5e-4, 5e-4),
            (w / 2 + rng.uniform(-6, 6), h / 2 + rng.uniform(-6, 6)),
            np.array([rng.uniform(-0.12, -0.08), rng.uniform(0.0, 0.02), *rng.uniform(-3e-4, 3e-4, 2)]),
            options,
        )
        narrow = opencv_camera(
            options.narrow_focal * (1 + rng.uniform(-0.01, 0.01)),
            1 + rng.uniform(-5e-4, 5e-4),
            (w / 2 + rng.uniform(-8, 8), h / 2 + rng.uniform(-8, 8)),
            np.array([rng.uniform(-0.04, 0.04), rng.uniform(-0.1, 0.1), *rng.uniform(-1e-4, 1e-4, 2)]),
            options,
        )
        # The narrow camera looks a few degrees further down (toward the centre), ~6 cm to the right.
        wide_from_narrow = (
            axis_rotation(0, -np.radians(options.narrow_extra_pitch_deg + rng.uniform(-0.5, 0.5)))
            @ axis_rotation(1, np.radians(rng.uniform(-0.5, 0.5)))
            @ axis_rotation(2, np.radians(rng.uniform(-0.3, 0.3)))
        )
        narrow_centre_in_wide = np.array([1.0, rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1)])
        narrow_centre_in_wide *= options.baseline / np.linalg.norm(narrow_centre_in_wide)
        narrow_from_wide_r = wide_from_narrow.T
        narrow_from_wide = pycolmap.Rigid3d(
            pycolmap.Rotation3d(narrow_from_wide_r), -narrow_from_wide_r @ narrow_centre_in_wide
        )
        position = np.array(
            [
                options.radius * np.cos(phi),
                options.radius * np.sin(phi),
                options.rig_height + rng.uniform(-0.25, 0.25),
            ]
        )
        pose = look_at_centre(
            position,
            np.radians(rng.uniform(-2.0, 2.0)),
            np.radians(options.wide_pitch_deg + rng.uniform(-1.0, 1.0)),
            np.radians(rng.uniform(-0.7, 0.7)),
        )
        rigs.append(RigTruth(rig_name(index), wide, narrow, narrow_from_wide, pose))
    return rigs


def _signed(rng: np.random.Generator, low: float, high: float) -> float:
    return float(rng.choice([-1.0, 1.0]) * rng.uniform(low, high))


def perturb_camera(camera: pycolmap.Camera, rng: np.random.Generator, wide: bool) -> pycolmap.Camera:
    """A good board calibration's errors: focal +-0.05..0.15 %, principal point +-0.2..0.8 px,
    distortion off by well under a pixel at the image corners."""
    fx, fy, cx, cy, k1, k2, p1, p2 = (float(p) for p in camera.params)
    k_scale = 1.0 if wide else 0.5
    params = [
        fx * (1 + _signed(rng, 0.0005, 0.0015)),
        fy * (1 + _signed(rng, 0.0005, 0.0015)),
        cx + _signed(rng, 0.2, 0.8),
        cy + _signed(rng, 0.2, 0.8),
        k1 + k_scale * _signed(rng, 0.0002, 0.0006),
        k2 + k_scale * _signed(rng, 0.0001, 0.0003),
        p1 + _signed(rng, 0.0, 1e-5),
        p2 + _signed(rng, 0.0, 1e-5),
    ]
    return pycolmap.Camera(model="OPENCV", width=camera.width, height=camera.height, params=params)


def perturb_rig_from(exact: RigCalibration, rng: np.random.Generator) -> RigCalibration:
    """A user's calibration of one rig: intrinsics as above, E^sl rotated 0.05..0.1 deg, t +-1 mm."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.uniform(0.05, 0.1))
    delta = pycolmap.Rotation3d(axis_angle=axis * angle)
    rotation = delta.matrix() @ exact.narrow_from_wide.rotation.matrix()
    translation = np.asarray(exact.narrow_from_wide.translation) + rng.uniform(-0.001, 0.001, 3)
    return RigCalibration(
        exact.name,
        perturb_camera(exact.wide, rng, wide=True),
        perturb_camera(exact.narrow, rng, wide=False),
        pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), translation),
    )


def _rms_uniform(low: float, high: float) -> float:
    """RMS of a value uniform in [low, high] (with a random sign)."""
    return float(np.sqrt((low * low + low * high + high * high) / 3.0))


def calibration_error_sigmas(calibration: RigCalibration) -> dict:
    """The 1-sigma uncertainties an honest calibration would write for the errors ``perturb_rig_from`` makes: the RMS
    of each (focal 0.104 %, principal point 0.53 px, k1 / k2 4.2e-4 / 2.1e-4 wide and half that narrow, p1 / p2
    5.8e-6; E^sl rotation 0.044 deg per axis, translation 0.58 mm per axis). As rigs.yaml's keys: ``wide``,
    ``narrow`` (one per param), ``rotation_deg``, ``translation_m`` (per axis)."""
    out = {}
    for sensor, k_scale in (("wide", 1.0), ("narrow", 0.5)):
        fx, fy = (float(p) for p in calibration.camera(sensor).params[:2])
        out[sensor] = np.array([fx * _rms_uniform(0.0005, 0.0015), fy * _rms_uniform(0.0005, 0.0015),
                                _rms_uniform(0.2, 0.8), _rms_uniform(0.2, 0.8),
                                k_scale * _rms_uniform(0.0002, 0.0006), k_scale * _rms_uniform(0.0001, 0.0003),
                                _rms_uniform(0.0, 1e-5), _rms_uniform(0.0, 1e-5)])
    out["rotation_deg"] = np.full(3, _rms_uniform(0.05, 0.1) / np.sqrt(3.0))  # a random axis: a third per axis
    out["translation_m"] = np.full(3, _rms_uniform(0.0, 0.001))
    return out


def user_calibration(rigs: list[RigTruth], options: SceneOptions) -> list[RigCalibration]:
    """What rigs.yaml holds: the exact calibration, perturbed if ``options.calibration_noise``."""
    exact = [rig.calibration() for rig in rigs]
    if not options.calibration_noise:
        return exact
    rng = np.random.default_rng([options.seed, 31])
    return [perturb_rig_from(rig, rng) for rig in exact]
