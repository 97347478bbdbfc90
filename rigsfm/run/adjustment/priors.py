"""The calibration's uncertainty as priors of the metric bundle adjustment: one :class:`RigPrior` per rig.

Read from rigs.yaml's optional uncertainty keys (per sensor ``sigmas``, one per entry of ``params``; per rig
``narrow_from_wide: {sigma_rotation_deg, sigma_translation_m, covariance}``, see the README's input contract
and ``rigsfm.calibrate.uncertainty``). Whatever a rig lacks gets the defaults of a good board calibration
(:data:`GOOD_BOARD`), and the run warns ``CALIBRATION UNCERTAINTY ASSUMED`` naming those rigs.

Conventions. Intrinsic sigmas are absolute, in COLMAP's order and units. E^sl's 6x6 covariance is of
``[w (rad), dt (m)]`` with ``R_true = Exp(w) R`` (w in the narrow camera's axes, applied on the left) and
``t_true = t + dt``: exactly the tangent in which COLMAP's bundle adjuster moves a ``sensor_from_rig`` block
(Ceres' quaternion manifold ``q' = Quaternion(delta) * q``, a rotation by ``w = 2 delta``; ``t' = t + dt``),
so it enters the joint covariance unchanged (:func:`rigsfm.run.adjustment.uncertainty`). COLMAP's pose-prior cost
(``pycolmap.cost_functions.AbsolutePosePriorCost``) measures a different residual, ``[w, t - Exp(w) t_prior]``
= ``[w, dt + [t_prior]x w]`` to first order: :func:`pose_prior_residual_covariance` converts.

Validation: a sigma that is negative, NaN, zero where a board calibration always estimates it (focal length,
principal point, E^sl rotation and translation), a rotation sigma over 5 deg or a focal sigma over 10 % of
the focal length is refused with one line naming the rig and the key. A distortion sigma of 0 holds that
coefficient (``rigsfm calibrate`` writes 0 for FULL_OPENCV's k4..k6, which it holds at 0).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.errors import InputError
from rigsfm.core.geometry import skew
from rigsfm.core.rig import MAX_SIGMA_ROTATION_DEG, RigCalibration, check_camera_sigmas

logger = logging.getLogger(__name__)

MAX_ROTATION_SIGMA_DEG = MAX_SIGMA_ROTATION_DEG
FOCAL_NAMES = ("f", "fx", "fy")
PRINCIPAL_NAMES = ("cx", "cy")
_RADIAL = re.compile(r"^k(\d?)$")
_TANGENTIAL = re.compile(r"^p(\d)$")


@dataclass(frozen=True)
class BoardDefaults:
    """1-sigma uncertainties assumed for a rig whose rigs.yaml gives none: a good board calibration.

    Set so as not to be over-confident for the errors rigsfm's rendered arena gives its calibration files
    (``rigsfm.synth.cameras.perturb_rig_from``: focal +-0.05..0.15 %, RMS 0.10 %; principal point
    +-0.2..0.8 px, RMS 0.53 px; k1 / k2 +-2..6e-4 / +-1..3e-4 on the wide camera, half on the narrow; p1, p2
    within 1e-5; E^sl rotated 0.05..0.1 deg about a random axis, RMS 0.044 deg per axis; translation +-1 mm
    uniform, RMS 0.58 mm per axis) nor for the "realistic" ones (focal +-0.2 %, principal point +-1 px).
    """

    focal_relative: float = 0.0012  # 0.12 % of the focal length
    principal_point_px: float = 0.6
    radial: tuple[float, ...] = (5e-4, 3e-4, 1e-4)  # k1, k2, then every further radial coefficient
    tangential: float = 1e-5
    rotation_deg: float = 0.045  # per axis of w
    translation_m: float = 6e-4  # per axis

    def camera_sigmas(self, camera: pycolmap.Camera) -> tuple[np.ndarray, list[str]]:
        """Sigma of each of ``camera.params`` and the names of the parameters with no default (held: 0)."""
        sigmas, held = [], []
        for name, value in zip(param_names(camera), np.asarray(camera.params, dtype=np.float64), strict=True):
            if name in FOCAL_NAMES:
                sigmas.append(self.focal_relative * abs(float(value)))
            elif name in PRINCIPAL_NAMES:
                sigmas.append(self.principal_point_px)
            elif (m := _RADIAL.match(name)) is not None:
                order = max(int(m.group(1) or 1), 1) - 1  # k and k0 are the first radial coefficient
                sigmas.append(self.radial[min(order, len(self.radial) - 1)])
            elif _TANGENTIAL.match(name) is not None:
                sigmas.append(self.tangential)
            else:  # omega (FOV), thin-prism, EUCM: no default; held as today
                sigmas.append(0.0)
                held.append(name)
        return np.asarray(sigmas, dtype=np.float64), held

    def narrow_from_wide_covariance(self) -> np.ndarray:
        return np.diag(np.r_[np.full(3, np.radians(self.rotation_deg)), np.full(3, self.translation_m)] ** 2)


GOOD_BOARD = BoardDefaults()


@dataclass(frozen=True)
class RigPrior:
    """One rig's calibration uncertainty. ``wide`` / ``narrow``: sigma of each camera param (COLMAP order; 0 =
    held exactly); ``narrow_from_wide``: 6x6 covariance of E^sl in the bundle adjustment's tangent ``[w (rad),
    dt (m)]`` (module docstring). ``assumed``: which of them came from :data:`GOOD_BOARD`."""

    wide: np.ndarray
    narrow: np.ndarray
    narrow_from_wide: np.ndarray
    assumed: tuple[str, ...] = ()

    def sensor(self, sensor: str) -> np.ndarray:
        return self.wide if sensor == "wide" else self.narrow


@dataclass(frozen=True)
class CalibrationPriors:
    rigs: Mapping[str, RigPrior]
    held_params: Mapping[str, tuple[str, ...]] = field(default_factory=dict)  # "<rig>/<sensor>" -> no default

    def __getitem__(self, rig: str) -> RigPrior:
        return self.rigs[rig]

    @property
    def assumed(self) -> dict[str, tuple[str, ...]]:
        """Rig name -> what was assumed (``wide``, ``narrow``, ``narrow_from_wide rotation`` ...)."""
        return {name: prior.assumed for name, prior in sorted(self.rigs.items()) if prior.assumed}

    def warning(self) -> str | None:
        """The ``CALIBRATION UNCERTAINTY ASSUMED`` warning, or None when rigs.yaml gave every uncertainty."""
        assumed = self.assumed
        if not assumed:
            return None
        if len(set(assumed.values())) == 1:
            listed = f"{', '.join(assumed)} ({', '.join(next(iter(assumed.values())))})"
        else:
            listed = "; ".join(f"{rig} ({', '.join(parts)})" for rig, parts in assumed.items())
        return (f"CALIBRATION UNCERTAINTY ASSUMED: rigs.yaml gives no sigmas for {listed}; a good board calibration's "
                f"were used (focal {100 * GOOD_BOARD.focal_relative:g} %, principal point "
                f"{GOOD_BOARD.principal_point_px:g} px, E^sl {GOOD_BOARD.rotation_deg:g} deg and "
                f"{1000 * GOOD_BOARD.translation_m:g} mm per axis). Calibrate with `rigsfm calibrate`, which writes "
                "them, or add them by hand, so that the refined calibration and the epipolar bands rest on your "
                "calibration's real uncertainty")


def param_names(camera: pycolmap.Camera) -> list[str]:
    return [n.strip() for n in camera.params_info.split(",")]


def pose_prior_residual_covariance(covariance: np.ndarray, prior: pycolmap.Rigid3d) -> np.ndarray:
    """The covariance of ``AbsolutePosePriorCost``'s residual ``[w, t - Exp(w) t_prior]`` for a pose whose error
    ``[w, dt]`` (``R = Exp(w) R_prior``, ``t = t_prior + dt``) has ``covariance``: to first order the residual
    is ``[w, dt + [t_prior]x w]``."""
    jacobian = np.eye(6)
    jacobian[3:, :3] = skew(np.asarray(prior.translation, dtype=np.float64))
    return jacobian @ np.asarray(covariance, dtype=np.float64) @ jacobian.T


def tangent_covariance_from_residual(covariance: np.ndarray, prior: pycolmap.Rigid3d) -> np.ndarray:
    """The inverse of :func:`pose_prior_residual_covariance`."""
    jacobian = np.eye(6)
    jacobian[3:, :3] = -skew(np.asarray(prior.translation, dtype=np.float64))
    return jacobian @ np.asarray(covariance, dtype=np.float64) @ jacobian.T


# ------------------------------------------------------------------------------------------------------------
# Reading and checking


def _check_pose_covariance(covariance: np.ndarray, where: str, source: str) -> None:
    sigmas = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    for axis, kind in enumerate(("x", "y", "z")):
        if np.degrees(sigmas[axis]) > MAX_ROTATION_SIGMA_DEG:
            raise InputError(f"{where} {source}: rotation sigma {np.degrees(sigmas[axis]):.3g} deg about {kind} is "
                             f"over {MAX_ROTATION_SIGMA_DEG:g} deg; recalibrate (or check the units: degrees, 1 sigma)")
    scale = np.sqrt(np.clip(np.diag(covariance), 1e-300, None))
    if np.min(np.diag(covariance)) <= 0 or np.linalg.eigvalsh(covariance / np.outer(scale, scale)).min() <= 1e-12:
        raise InputError(f"{where} {source}: must be positive definite (no E^sl is known exactly in any direction); "
                         "give its real uncertainty")


def _check_axis_sigmas(values: np.ndarray, where: str, key: str, unit: str) -> None:
    if not np.all(np.isfinite(values)) or np.any(values <= 0):
        raise InputError(f"{where} {key}: every entry must be a finite number > 0 ({unit}, 1 sigma), got "
                         f"{values.tolist()}")


def rig_prior(rig: RigCalibration, sigmas=None, where: str | None = None,
              defaults: BoardDefaults = GOOD_BOARD) -> tuple[RigPrior, dict[str, tuple[str, ...]]]:
    """One rig's prior from ``sigmas`` (a ``rigsfm.calibrate.uncertainty.RigSigmas``; None: every value assumed),
    checked; returns it and the parameters held for lack of a default (``{"<rig>/<sensor>": names}``)."""
    where = where or f"rigs.yaml: rig '{rig.name}'"
    assumed, held, cameras = [], {}, {}
    for sensor in ("wide", "narrow"):
        camera = rig.camera(sensor)
        given = None if sigmas is None else sigmas.sensor(sensor)
        if given is None:
            values, no_default = defaults.camera_sigmas(camera)
            assumed.append(sensor)
            if no_default:
                held[f"{rig.name}/{sensor}"] = tuple(no_default)
        else:
            values = np.asarray(given, dtype=np.float64)
            if values.shape != (len(camera.params),):
                raise InputError(f"{where} sensor {sensor} sigmas: expected {len(camera.params)} numbers (one per "
                                 f"entry of params), got {values.size}")
            check_camera_sigmas(values, camera, f"{where} sensor {sensor} sigmas")  # core.rig's, as rigs.yaml's
        cameras[sensor] = values
    default = defaults.narrow_from_wide_covariance()
    covariance = None if sigmas is None else sigmas.covariance
    pose_where = f"{where} narrow_from_wide"
    if covariance is not None:
        covariance = 0.5 * (np.asarray(covariance, dtype=np.float64) + np.asarray(covariance, dtype=np.float64).T)
        _check_pose_covariance(covariance, pose_where, "covariance")
    else:
        rotation = None if sigmas is None else sigmas.rotation_deg
        translation = None if sigmas is None else sigmas.translation_m
        covariance = default.copy()
        if rotation is None:
            assumed.append("E^sl rotation")
        else:
            rotation = np.asarray(rotation, dtype=np.float64)
            _check_axis_sigmas(rotation, pose_where, "sigma_rotation_deg", "degrees")
            covariance[:3, :3] = np.diag(np.radians(rotation) ** 2)
        if translation is None:
            assumed.append("E^sl translation")
        else:
            translation = np.asarray(translation, dtype=np.float64)
            _check_axis_sigmas(translation, pose_where, "sigma_translation_m", "metres")
            covariance[3:, 3:] = np.diag(translation**2)
        _check_pose_covariance(covariance, pose_where, "sigma_rotation_deg")
    return RigPrior(cameras["wide"], cameras["narrow"], covariance, tuple(assumed)), held


def calibration_priors(rigs: Sequence[RigCalibration], rigs_path: Path | None = None,
                       defaults: BoardDefaults = GOOD_BOARD) -> CalibrationPriors:
    """Every rig's :class:`RigPrior`: from rigs.yaml's uncertainty keys at ``rigs_path`` (checked: one line naming
    rig and key for a bad one), :data:`GOOD_BOARD` for what a rig lacks (or for everything without a path).

    The sigmas are the ones ``rigsfm.core.rig.load_rigs`` read and checked (``RigCalibration.sigmas``)."""
    written = {rig.name: rig.sigmas for rig in rigs if rig.sigmas is not None}
    priors, held = {}, {}
    for rig in rigs:
        where = f"{rigs_path}: rig '{rig.name}'" if rigs_path is not None else f"rig '{rig.name}'"
        priors[rig.name], rig_held = rig_prior(rig, written.get(rig.name), where, defaults)
        held.update(rig_held)
    result = CalibrationPriors(priors, held)
    if result.assumed:
        logger.warning("%s", result.warning())
    for camera, names in held.items():
        logger.warning("No default uncertainty for %s's %s: held at rigs.yaml's values", camera, ", ".join(names))
    return result


def draw_calibration(rigs: Sequence[RigCalibration], priors: CalibrationPriors,
                     rng: np.random.Generator) -> list[RigCalibration]:
    """rigs.yaml as it might have been: every intrinsic and E^sl moved by one draw of its prior (E^sl as
    R = Exp(w) R, t + dt, the tangent of ``RigPrior.narrow_from_wide``)."""
    out = []
    for rig in rigs:
        prior = priors[rig.name]
        cameras = {}
        for sensor in ("wide", "narrow"):
            camera = rig.camera(sensor)
            params = np.asarray(camera.params) + rng.standard_normal(len(camera.params)) * prior.sensor(sensor)
            cameras[sensor] = pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height,
                                              params=params)
        d = rng.multivariate_normal(np.zeros(6), prior.narrow_from_wide)
        pose = rig.narrow_from_wide
        out.append(RigCalibration(rig.name, cameras["wide"], cameras["narrow"], pycolmap.Rigid3d(
            pycolmap.Rotation3d(d[:3]) * pose.rotation, np.asarray(pose.translation) + d[3:])))
    return out
