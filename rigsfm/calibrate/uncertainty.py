"""Calibration uncertainties that ``rigsfm calibrate`` writes into rigs.yaml, and a reader for them.

Schema (every key optional; a reader that ignores them still gets the plain calibration)::

    sensors:
      wide:
        model: OPENCV
        params: [fx, fy, cx, cy, k1, k2, p1, p2]
        sigmas: [...]              # 1-sigma of each entry of params, same order and units (px, COLMAP
                                   # convention); 0 = held fixed (k4..k6 of FULL_OPENCV)
    narrow_from_wide:
      rotation: [[...], [...], [...]]
      translation: [tx, ty, tz]
      sigma_rotation_deg: [wx, wy, wz]     # R_true = Exp(w) R, w a small rotation vector in the narrow
                                           # camera's axes (applied on the left), degrees
      sigma_translation_m: [tx, ty, tz]    # t_true = t + dt, metres
      covariance: 6x6                      # of [w (rad), dt (m)], correlations included

They come from the joint refinement of both cameras and E^sl (``joint.py``): (J^T W J)^-1 scaled by the
weighted residual variance, board poses marginalised out, inflated where a delete-one-frame jackknife shows
the corner errors are not independent (real boards). The per-sensor and per-rig blocks are marginal
covariances: the correlations *between* them (a narrow principal-point error looks like an E^sl rotation of
dp / f_narrow rad) are in the report, not in rigs.yaml. Nothing is written for what the joint refinement did
not estimate: E^sl when the joint refinement was rejected, its rotation and translation when they come from a
scene (``--from-scene``), its translation when its length comes from ``--baseline``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rigsfm.core.errors import InputError
from rigsfm.core.io import load_yaml_or_json

if TYPE_CHECKING:
    from rigsfm.calibrate import RigResult

SENSORS = ("wide", "narrow")
SIGNIFICANT = 4  # digits written for sigmas ...
COVARIANCE_SIGNIFICANT = 8  # ... and for the covariance (its eigenvalues then move by < 1e-7 relative)


@dataclass
class RigSigmas:
    """1-sigma uncertainties of one rig's calibration (None: not estimated, nothing written)."""

    wide: np.ndarray | None = None  # per COLMAP param of the wide camera
    narrow: np.ndarray | None = None
    rotation_deg: np.ndarray | None = None  # per axis of w, R_true = Exp(w) R
    translation_m: np.ndarray | None = None
    covariance: np.ndarray | None = None  # 6x6 of [w (rad), t (m)]
    notes: list[str] = field(default_factory=list)  # why something is missing

    def sensor(self, name: str) -> np.ndarray | None:
        return self.wide if name == "wide" else self.narrow


def colmap_param_sigmas(covariance: np.ndarray, model: str) -> np.ndarray:
    """Sigmas of a camera's COLMAP params from the covariance of (fx, fy, cx, cy, k1, k2, p1, p2[, k3]).

    The principal point's +0.5 shift to COLMAP's convention does not change its sigma; FULL_OPENCV's
    k4..k6 are held at 0 and get sigma 0."""
    sigma = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    n_params = {"OPENCV": 8, "FULL_OPENCV": 12}[model]
    out = np.zeros(n_params)
    out[: min(len(sigma), n_params)] = sigma[:n_params]
    return out


def rig_sigmas(rig: RigResult) -> RigSigmas:
    """The uncertainties of what ``rig`` writes to rigs.yaml (see the module docstring for what is left out)."""
    detail = rig.stereo.joint_detail
    if not rig.stereo.use_joint or detail is None or detail.covariance is None:
        return RigSigmas(notes=[("no uncertainties: the joint refinement was not used, and OpenCV's fixed-intrinsics "
                                 "E^sl has no covariance that accounts for the intrinsics' errors")])
    wide, narrow = rig.cameras()
    out = RigSigmas(wide=colmap_param_sigmas(detail.block("wide"), wide.model.name),
                    narrow=colmap_param_sigmas(detail.block("narrow"), narrow.model.name))
    cov = detail.block("rig")
    if rig.scene is not None:
        out.notes.append("no E^sl uncertainty: its rotation and translation direction come from the scene")
        return out
    out.rotation_deg = np.degrees(np.sqrt(np.clip(np.diag(cov)[:3], 0.0, None)))
    if rig.measured_baseline is not None:
        out.notes.append("no E^sl translation uncertainty: its length comes from --baseline, whose error is unknown")
        return out
    out.translation_m = np.sqrt(np.clip(np.diag(cov)[3:], 0.0, None))
    out.covariance = 0.5 * (cov + cov.T)
    return out


def _round(values, digits: int = SIGNIFICANT) -> list[float]:
    return [float(f"{v:.{digits}g}") for v in np.ravel(values)]


def add_sigmas(entry: dict, sigmas: RigSigmas) -> dict:
    """Add the uncertainty keys to one rig's rigs.yaml entry (a dict as ``rigs.rigs_to_yaml`` builds it)."""
    for sensor in SENSORS:
        if sigmas.sensor(sensor) is not None:
            entry["sensors"][sensor]["sigmas"] = _round(sigmas.sensor(sensor))
    pose = entry["narrow_from_wide"]
    if sigmas.rotation_deg is not None:
        pose["sigma_rotation_deg"] = _round(sigmas.rotation_deg)
    if sigmas.translation_m is not None:
        pose["sigma_translation_m"] = _round(sigmas.translation_m)
    if sigmas.covariance is not None:
        pose["covariance"] = [_round(row, COVARIANCE_SIGNIFICANT) for row in sigmas.covariance]
    return entry


def _vector(value, n: int, where: str) -> np.ndarray:
    try:
        out = np.array(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as e:
        raise InputError(f"{where}: expected {n} numbers, got {value!r}") from e
    if out.shape != (n,) or not np.all(np.isfinite(out)) or np.any(out < 0):
        raise InputError(f"{where}: expected {n} finite numbers >= 0, got {value!r}")
    return out


def sigmas_from_entry(entry: dict, where: str) -> RigSigmas:
    """Read and check the uncertainty keys of one rig entry of rigs.yaml (absent keys stay None)."""
    out = RigSigmas()
    for sensor in SENSORS:
        spec = entry["sensors"][sensor]
        if "sigmas" in spec:
            setattr(out, sensor, _vector(spec["sigmas"], len(spec["params"]), f"{where} sensor {sensor} sigmas "
                                         f"(one per entry of params)"))
    pose = entry["narrow_from_wide"]
    if "sigma_rotation_deg" in pose:
        out.rotation_deg = _vector(pose["sigma_rotation_deg"], 3, f"{where} narrow_from_wide sigma_rotation_deg")
    if "sigma_translation_m" in pose:
        out.translation_m = _vector(pose["sigma_translation_m"], 3, f"{where} narrow_from_wide sigma_translation_m")
    if "covariance" in pose:
        try:
            cov = np.array(pose["covariance"], dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise InputError(f"{where} narrow_from_wide covariance: expected a 6x6 matrix of numbers") from e
        if cov.shape != (6, 6) or not np.all(np.isfinite(cov)):
            raise InputError(f"{where} narrow_from_wide covariance: expected a finite 6x6 matrix, got shape {cov.shape}")
        scale = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
        if not np.allclose(cov, cov.T, rtol=1e-6, atol=0) or np.linalg.eigvalsh(cov / np.outer(scale, scale)).min() < -1e-6:
            raise InputError(f"{where} narrow_from_wide covariance: must be symmetric positive semi-definite "
                             "([w (rad), t (m)])")
        out.covariance = cov
    return out


def load_sigmas(path: Path) -> dict[str, RigSigmas]:
    """The uncertainties in rigs.yaml, by rig name (rigs.load_rigs reads and checks the rest of the file)."""
    data = load_yaml_or_json(Path(path), "rig calibration")
    return {e["name"]: sigmas_from_entry(e, f"{path}: rig {e['name']}") for e in data.get("rigs", [])}
