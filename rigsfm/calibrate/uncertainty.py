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

from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from rigsfm.core.rig import RigSigmas, add_sigmas, load_rigs, sigmas_from_entry

if TYPE_CHECKING:
    import pycolmap

    from rigsfm.calibrate.scene import SceneEstimate
    from rigsfm.calibrate.stereo import StereoCalibration

__all__ = ["RigSigmas", "add_sigmas", "colmap_param_sigmas", "load_sigmas", "rig_sigmas", "sigmas_from_entry"]

SENSORS = ("wide", "narrow")


class _Calibrated(Protocol):
    """What ``rig_sigmas`` reads of a rig's result (``results.RigResult``, whose ``sigmas`` calls it)."""

    stereo: StereoCalibration
    scene: SceneEstimate | None
    measured_baseline: float | None

    def cameras(self) -> tuple[pycolmap.Camera, pycolmap.Camera]: ...


def colmap_param_sigmas(covariance: np.ndarray, model: str) -> np.ndarray:
    """Sigmas of a camera's COLMAP params from the covariance of (fx, fy, cx, cy, k1, k2, p1, p2[, k3]).

    The principal point's +0.5 shift to COLMAP's convention does not change its sigma; FULL_OPENCV's
    k4..k6 are held at 0 and get sigma 0."""
    sigma = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    n_params = {"OPENCV": 8, "FULL_OPENCV": 12}[model]
    out = np.zeros(n_params)
    out[: min(len(sigma), n_params)] = sigma[:n_params]
    return out


def rig_sigmas(rig: _Calibrated) -> RigSigmas:
    """The uncertainties of what ``rig`` writes to rigs.yaml (see the module docstring for what is left out)."""
    detail = rig.stereo.joint_detail
    if not rig.stereo.use_joint or detail is None or detail.covariance is None:
        return RigSigmas(notes=[("no uncertainties: the joint refinement was not used, and OpenCV's fixed-intrinsics "
                                 "E^sl has no covariance that accounts for the intrinsics' errors")])
    wide, narrow = rig.cameras()
    # a solved rig has its blocks
    out = RigSigmas(wide=colmap_param_sigmas(detail.block("wide"), wide.model.name),  # type: ignore[arg-type]
                    narrow=colmap_param_sigmas(detail.block("narrow"), narrow.model.name))  # type: ignore[arg-type]
    cov = detail.block("rig")
    if rig.scene is not None:
        out.notes.append("no E^sl uncertainty: its rotation and translation direction come from the scene")
        return out
    # a solved rig has its blocks
    out.rotation_deg = np.degrees(np.sqrt(np.clip(np.diag(cov)[:3], 0.0, None)))  # type: ignore[arg-type]
    if rig.measured_baseline is not None:
        out.notes.append("no E^sl translation uncertainty: its length comes from --baseline, whose error is unknown")
        return out
    # a solved rig has its blocks
    out.translation_m = np.sqrt(np.clip(np.diag(cov)[3:], 0.0, None))  # type: ignore[arg-type]
    out.covariance = 0.5 * (cov + cov.T)  # type: ignore[union-attr]
    return out


def load_sigmas(path: Path) -> dict[str, RigSigmas]:
    """The uncertainties in rigs.yaml, by rig name (empty ``RigSigmas`` for a rig without them); the whole file
    is checked by ``rigsfm.core.rig.load_rigs``, which also puts them on ``RigCalibration.sigmas``."""
    return {rig.name: rig.sigmas if rig.sigmas is not None else RigSigmas() for rig in load_rigs(Path(path))}
