"""What ``rigsfm calibrate`` found: each rig's cameras and E^sl (``RigResult``) and all rigs (``CalibrationResult``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pycolmap

from rigsfm.calibrate.board import BoardSpec
from rigsfm.calibrate.intrinsics import CameraCalibration, colmap_camera
from rigsfm.calibrate.scene import SceneEstimate
from rigsfm.calibrate.stereo import StereoCalibration
from rigsfm.calibrate.uncertainty import RigSigmas, rig_sigmas
from rigsfm.core.rig import RigCalibration


@dataclass
class RigResult:
    name: str
    wide: CameraCalibration
    narrow: CameraCalibration
    stereo: StereoCalibration
    R: np.ndarray  # final narrow_from_wide
    T: np.ndarray
    scene: SceneEstimate | None = None
    measured_baseline: float | None = None  # --baseline (m), replacing the board's length of T
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    def cameras(self) -> tuple[pycolmap.Camera, pycolmap.Camera]:
        """Final (wide, narrow) cameras, COLMAP convention: joint-refined intrinsics if they were accepted."""
        fit = self.stereo.final
        return (colmap_camera(fit.K_wide, fit.dist_wide, self.wide.image_size, self.wide.model),
                colmap_camera(fit.K_narrow, fit.dist_narrow, self.narrow.image_size, self.narrow.model))

    def sigmas(self) -> RigSigmas:
        """The uncertainties written with this rig (``uncertainty.py``)."""
        return rig_sigmas(self)

    def rig_calibration(self) -> RigCalibration:
        wide, narrow = self.cameras()
        return RigCalibration(name=self.name, wide=wide, narrow=narrow,
                              narrow_from_wide=pycolmap.Rigid3d(pycolmap.Rotation3d(self.R), self.T.astype(np.float64)))


@dataclass
class CalibrationResult:
    board: BoardSpec
    rigs: list[RigResult]

    def rig_calibrations(self) -> list[RigCalibration]:
        return [r.rig_calibration() for r in self.rigs]

    @property
    def warnings(self) -> list[str]:
        return [w for r in self.rigs for w in r.warnings]
