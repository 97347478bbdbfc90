"""Typed options of ``rigsfm calibrate``; imports nothing heavy."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from pathlib import Path


class Distortion(enum.StrEnum):
    AUTO = "auto"  # k1 k2 p1 p2, plus k3 only where it lowers the error significantly
    OPENCV = "opencv"  # k1 k2 p1 p2 (COLMAP's OPENCV model)
    FULL_OPENCV = "full_opencv"  # k1 k2 p1 p2 k3 (COLMAP's FULL_OPENCV model)


@dataclass(frozen=True, kw_only=True)
class CalibrateOptions:
    board: Path  # board.yaml
    distortion: Distortion = Distortion.AUTO
    scene_dir: Path | None = None  # SCENE/<rig>/{wide,narrow}: E^sl rotation and direction from a textured scene
    baseline: float | None = None  # measured baseline length (m), replaces the board's
    merge: bool = False  # add/replace these rigs in an existing rigs.yaml
    overwrite: bool = False  # replace an existing rigs.yaml (with merge: same-named rigs in it)
    report_dir: Path | None = None  # default <out stem>.calibration/ beside the rigs.yaml
